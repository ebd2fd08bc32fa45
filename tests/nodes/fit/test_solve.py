"""Stage solver internals (nodes.fit.solve): the hand-chained Jacobian of a stage's residuals
against forward-mode autodiff of the residuals themselves."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from nodes.fit.energy import axis_angle_to_rotmat  # noqa: E402
from nodes.fit.solve import PoseState, _stage_jacobian, _stage_residuals  # noqa: E402
from nodes.fit.views import Anchors, FitViews  # noqa: E402


def _problem(distortion: torch.Tensor | None):
    g = torch.Generator().manual_seed(0)
    b, c, l, k, x_dim = 3, 2, 80, 7, 4
    cams = torch.eye(4).repeat(c, 1, 1)
    cams[1, :3, :3] = axis_angle_to_rotmat(torch.tensor([0.0, 0.4, 0.0]))
    cams[1, :3, 3] = torch.tensor([-20.0, 0.0, 5.0])
    views = FitViews(target=torch.rand(b, c, l, 2, generator=g) * 200 + 20,
                     boxes=torch.tensor([40.0, 30.0, 168.0, 158.0]).expand(b, c, 4).clone(),
                     seen=torch.tensor([[True, True], [True, False], [True, True]]), world_to_camera=cams,
                     intrinsics=torch.tensor([[300.0, 310.0, 100.0, 90.0], [280.0, 280.0, 110.0, 95.0]]),
                     distortion=distortion, image_size=torch.tensor([[200.0, 200.0], [220.0, 200.0]]))
    neutral = torch.randn(b, c, l, 3, generator=g) * 5.0
    deltas = torch.randn(b, c, l, k, 3, generator=g) * 0.5
    extra = torch.randn(b, c, l, x_dim, 3, generator=g) * 0.3
    anchors = Anchors(torch.zeros(b, c, l, 3, dtype=torch.long), torch.ones(b, c, l, 3) / 3,
                      torch.randn(b, c, l, 2, generator=g), torch.ones(b, c, dtype=torch.bool))
    rot0 = axis_angle_to_rotmat(torch.randn(b, 3, generator=g) * 0.3)
    weights = torch.rand(b, k, generator=g)
    shapes = torch.tensor([1, 3, 4, 6])
    weights[0, 1], weights[1, 3], weights[2, 4] = 0.0, 1.0, -0.05  # at and past the bounds
    w_lm = torch.rand(b, c, l, generator=g)
    w_lm[0, 0, :5] = 0.0
    x = torch.cat([torch.zeros(b, 3), torch.tensor([[1.0, -2.0, 60.0]]).expand(b, 3) + torch.randn(b, 3, generator=g),
                   weights[:, shapes]], 1)
    prior_pose = PoseState(axis_angle_to_rotmat(torch.randn(b, 3, generator=g) * 0.1) @ rot0, x[:, 3:6] + 0.5, weights)
    return views, neutral, deltas, extra, anchors, rot0, weights, shapes, w_lm, x, prior_pose


@pytest.mark.parametrize("distortion", [None, torch.tensor([[-0.2, 0.1], [0.05, 0.0]])])
@pytest.mark.parametrize("rigid_prior", [False, True])
def test_stage_jacobian_matches_forward_autodiff(distortion, rigid_prior):
    views, neutral, deltas, extra, anchors, rot0, weights, shapes, w_lm, x, prior_pose = _problem(distortion)
    kw = dict(prior=100.0, edge_weight=1.0, rigid_prior=prior_pose if rigid_prior else None,
              rigid_prior_weight=50.0 if rigid_prior else 0.0)
    jac = _stage_jacobian(neutral, deltas, views, rot0, weights, shapes, w_lm, x, extra=extra, **kw)

    def fn(d: torch.Tensor) -> torch.Tensor:
        shape = torch.einsum("x,bclxd->bcld", d[x.shape[1]:], extra)
        return _stage_residuals(neutral + shape, deltas, views, anchors, rot0, weights, shapes, w_lm, **kw)(
            x + d[None, :x.shape[1]])

    ref = torch.func.jacfwd(fn)(torch.zeros(x.shape[1] + extra.shape[3]))  # (B, M, P)
    assert jac.shape == ref.shape
    assert float(ref.abs().max()) > 10.0
    torch.testing.assert_close(jac, ref, atol=1e-3, rtol=1e-4)
