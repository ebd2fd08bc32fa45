"""The stage solves run only the frames still converging (issue 31): `levenberg_marquardt(compact=True)`
gives each element the result it gets in the full batch, and `solve_stage`, whose per-frame data is
cut to the running frames, gives what evaluating every frame at every iteration gives, with the
photometric term."""

from __future__ import annotations

import dataclasses
import types

import pytest

torch = pytest.importorskip("torch")

from nodes.fit.energy import axis_angle_to_rotmat, posed_anchor_points, project_views  # noqa: E402
from nodes.fit.photometric import PhotoSamples  # noqa: E402
from nodes.fit import solve  # noqa: E402
from nodes.fit.solve import PoseState, Stage, solve_stage  # noqa: E402
from nodes.fit.views import Anchors, FitViews  # noqa: E402
from nodes.geometry.lm import LMSchedule, from_jacobian, levenberg_marquardt  # noqa: E402

f64 = torch.float64


def _rosenbrock(x: torch.Tensor) -> torch.Tensor:
    return torch.stack([10.0 * (x[:, 1] - x[:, 0] ** 2), 1.0 - x[:, 0]], 1)


def _rosenbrock_jac(x: torch.Tensor) -> torch.Tensor:
    jac = torch.zeros(x.shape[0], 2, 2, dtype=x.dtype)
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0] = -20.0 * x[:, 0], 10.0, -1.0
    return jac


def test_compact_iterations_give_each_element_its_full_batch_result_and_run_fewer_rows():
    # starts near and far from the minimum (1, 1): the near ones stop after a few iterations
    starts = torch.tensor([[0.999, 1.001], [-1.2, 1.0], [2.0, -1.0], [1.05, 1.1], [-3.0, -3.0]], dtype=f64)
    schedule = LMSchedule(rel_tol=1e-6)
    full = levenberg_marquardt(_rosenbrock, from_jacobian(_rosenbrock_jac), starts, iterations=60, schedule=schedule)
    seen: list[int] = []

    def residuals(x: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        assert x.shape[0] == len(rows)
        seen.append(len(rows))
        return _rosenbrock(x)

    def normal(x: torch.Tensor, r: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        jac = _rosenbrock_jac(x)
        return jac.transpose(1, 2) @ jac, (jac.transpose(1, 2) @ r[..., None])[..., 0]

    compact = levenberg_marquardt(residuals, normal, starts, iterations=60, schedule=schedule, compact=True)
    # the same arithmetic on each element's own row: the same bits
    assert torch.equal(compact.x, full.x) and torch.equal(compact.cost, full.cost)
    assert torch.equal(compact.lam, full.lam) and compact.iterations == full.iterations
    assert float(full.cost.max()) < 1e-10  # every start reached the minimum
    assert seen[0] == len(starts) and min(seen) < len(starts)  # the stopped elements were not evaluated
    assert sum(seen) < len(seen) * len(starts)


def _batch(b: int = 4, c: int = 1, l: int = 68, k: int = 6, n: int = 300, s: int = 64):
    """A stage's inputs for b frames: anchored points, plate targets, and photometric samples on
    smooth random plates (each frame its own pose, so that they converge at different iterations)."""
    g = torch.Generator().manual_seed(3)
    cams = torch.eye(4, dtype=f64)[None].repeat(c, 1, 1)
    views = FitViews(target=torch.rand(b, c, l, 2, generator=g, dtype=f64) * 120 + 70,
                     boxes=torch.tensor([60.0, 60.0, 196.0, 196.0], dtype=f64).expand(b, c, 4).clone(),
                     seen=torch.ones(b, c, dtype=torch.bool), world_to_camera=cams,
                     intrinsics=torch.tensor([[480.0, 480.0, 128.0, 128.0]], dtype=f64), distortion=None,
                     image_size=torch.tensor([[256.0, 256.0]], dtype=f64))
    neutral = torch.randn(b, c, l, 3, generator=g, dtype=f64) * 4.0
    deltas = torch.randn(b, c, l, k, 3, generator=g, dtype=f64) * 0.5
    anchors = Anchors(torch.zeros(b, c, l, 3, dtype=torch.long), torch.full((b, c, l, 3), 1 / 3, dtype=f64),
                      torch.zeros(b, c, l, 2, dtype=f64), torch.ones(b, c, dtype=torch.bool))
    smooth = torch.nn.functional.avg_pool2d(torch.rand(b * c, 3, s + 8, s + 8, generator=g, dtype=f64), 9, 1)
    samples = PhotoSamples(torch.zeros(b, c, n, 3, dtype=torch.long), torch.full((b, c, n, 3), 1 / 3, dtype=f64),
                           torch.rand(b, c, n, 3, generator=g, dtype=f64), torch.full((b, c, n), 1.0 / n, dtype=f64),
                           smooth.permute(0, 2, 3, 1).contiguous(), s,
                           torch.randn(b, c, n, 3, generator=g, dtype=f64) * 4.0,
                           torch.randn(b, c, n, k, 3, generator=g, dtype=f64) * 0.3)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=f64))
    rot = axis_angle_to_rotmat(torch.randn(b, 3, generator=g, dtype=f64) * 0.2) @ flip
    trans = torch.tensor([0.0, 0.0, 60.0], dtype=f64) + torch.randn(b, 3, generator=g, dtype=f64)
    weights = torch.rand(b, k, generator=g, dtype=f64) * 0.3
    # the targets: the anchored points at that pose, 0.5 px noise; the starts off by 0 to 26 deg, 0 to 17 cm
    pts = posed_anchor_points(neutral, deltas, weights, rot, trans)
    target = project_views(pts, views.world_to_camera, views.intrinsics, None)
    views = dataclasses.replace(views, target=target + 0.5 * torch.randn(target.shape, generator=g, dtype=f64))
    off = torch.arange(b, dtype=f64)[:, None]
    start = PoseState(axis_angle_to_rotmat(0.15 * off * torch.tensor([1.0, -0.5, 0.3], dtype=f64)) @ rot,
                      trans + off * torch.tensor([2.0, -1.5, 5.0], dtype=f64), (weights + 0.1 * off).clamp(0, 1))
    return views, anchors, (neutral, deltas), samples, start


@pytest.mark.parametrize("stage, frames_stop_apart", [(Stage("rigid_all", True, True, (), "all"), True),
                                                      (Stage("jaw_mouth", True, True, (0, 2, 3), "all"), True),
                                                      # shapes only (nearly linear): all stop together
                                                      (Stage("jaw", False, False, (1, 4), "all"), False)])
def test_the_stage_solve_on_the_running_frames_equals_the_solve_on_all(stage: Stage, frames_stop_apart: bool,
                                                                       monkeypatch):
    """solve_stage cut to the running frames against the same solve evaluating every frame at every
    iteration (the Levenberg-Marquardt iterations without compaction, through solve_stage's own
    callbacks with all the rows): the same result, the photometric term included."""
    views, anchors, anchored, samples, state = _batch()
    model = types.SimpleNamespace(iris=None)  # the anchored points are given; no iris
    kw = dict(prior=1.0, edge_weight=1.0, eyelid_weight=0.2, iterations=30, photo_weight=5.0, photo=samples,
              anchored=anchored)
    rows_seen: list[int] = []
    compact_lm = solve.levenberg_marquardt

    def counting(residuals, normal, x0, **options):
        def count(x, rows):
            rows_seen.append(len(rows))
            return residuals(x, rows)
        return compact_lm(count, normal, x0, **options)

    monkeypatch.setattr(solve, "levenberg_marquardt", counting)
    cut, e_cut = solve_stage(stage, model, views, anchors, state, **kw)

    def every_row(residuals, normal, x0, *, relinearize, compact, **options):
        assert compact
        rows = torch.arange(x0.shape[0])
        return compact_lm(lambda x: residuals(x, rows), lambda x, r: normal(x, r, rows), x0,
                          relinearize=lambda x, accepted: relinearize(x, accepted, rows), **options)

    monkeypatch.setattr(solve, "levenberg_marquardt", every_row)
    every, e_every = solve_stage(stage, model, views, anchors, state, **kw)
    assert (min(rows_seen) < len(state.rot)) == frames_stop_apart, rows_seen  # some frames stopped before others
    moved = (every.trans - state.trans).norm(dim=1) + (every.weights - state.weights).abs().sum(1)
    assert float(moved.min()) > 1e-3  # every frame moved: the comparison is not of starts
    for a, b in zip(cut, every):  # each frame computed from its own rows only: the same bits
        assert torch.equal(a, b)
    assert torch.equal(e_cut, e_every)
