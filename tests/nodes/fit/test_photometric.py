"""Photometric term of the fit (nodes.fit.photometric): bilinear sampling against torch's
grid_sample, the hand-chained Jacobian against forward-mode autodiff, the blur."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodes.fit.energy import axis_angle_to_rotmat  # noqa: E402
from nodes.fit.photometric import PhotoSamples, PhotoTerm  # noqa: E402
from nodes.geometry.image import gaussian_blur, sample_bilinear  # noqa: E402
from nodes.fit.views import FitViews  # noqa: E402


def test_sample_bilinear_matches_grid_sample():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 9, 13, 3, generator=g)
    xy = torch.rand(2, 50, 2, generator=g) * torch.tensor([12.0, 8.0])
    ours = sample_bilinear(images, xy)
    grid = torch.stack([xy[..., 0] / 12.0 * 2 - 1, xy[..., 1] / 8.0 * 2 - 1], -1)[:, :, None]  # centres at integers
    ref = torch.nn.functional.grid_sample(images.permute(0, 3, 1, 2), grid, align_corners=True)[..., 0]
    torch.testing.assert_close(ours, ref.permute(0, 2, 1), atol=1e-6, rtol=0)


def test_sample_bilinear_gradient_matches_forward_autodiff_and_is_zero_where_clamped():
    g = torch.Generator().manual_seed(3)
    images = torch.rand(2, 9, 13, 3, generator=g)
    xy = torch.rand(2, 40, 2, generator=g) * torch.tensor([12.0, 8.0])
    xy[:, :5, 0] = torch.tensor([-2.0, 13.5, 20.0, -0.5, 12.5])  # outside in x: clamped
    value, grad = sample_bilinear(images, xy, gradient=True)
    torch.testing.assert_close(value, sample_bilinear(images, xy))
    for k in range(2):
        tangent = torch.zeros_like(xy)
        tangent[..., k] = 1.0
        _, ref = torch.func.jvp(lambda p: sample_bilinear(images, p), (xy,), (tangent,))
        torch.testing.assert_close(grad[..., k], ref, atol=1e-5, rtol=0)
    assert float(grad[:, :5, :, 0].abs().max()) == 0.0 and float(grad[:, 5:, :, 0].abs().max()) > 0.1


def test_gaussian_blur_keeps_a_constant_and_smooths_noise():
    g = torch.Generator().manual_seed(1)
    flat = torch.full((1, 20, 20, 3), 0.3)
    torch.testing.assert_close(gaussian_blur(flat, 1.5), flat)
    noise = torch.randn(1, 64, 64, 3, generator=g)
    assert gaussian_blur(noise, 1.0).std() < 0.5 * noise.std()


def _term(b: int = 2, n: int = 30, s: int = 5, distortion: torch.Tensor | None = None) -> tuple[PhotoTerm, torch.Tensor]:
    g = torch.Generator().manual_seed(2)
    size = 64
    views = FitViews(target=torch.zeros(b, 1, 68, 2), boxes=torch.tensor([[[40.0, 30.0, 168.0, 158.0]]]).repeat(b, 1, 1),
                     seen=torch.ones(b, 1, dtype=torch.bool), world_to_camera=torch.eye(4)[None],
                     intrinsics=torch.tensor([[300.0, 300.0, 100.0, 90.0]]), distortion=distortion,
                     image_size=torch.tensor([[200.0, 200.0]]))
    plates = gaussian_blur(torch.rand(b, size, size, 3, generator=g), 2.0)
    samples = PhotoSamples(vertices=torch.zeros(b, 1, n, 3, dtype=torch.long), bary=torch.ones(b, 1, n, 3) / 3,
                           colour=torch.rand(b, 1, n, 3, generator=g), weight=torch.rand(b, 1, n, generator=g) / n,
                           plates=plates, size=size, neutral=torch.zeros(b, 1, n, 3), deltas=torch.zeros(b, 1, n, 1, 3))
    local0 = torch.randn(b, 1, n, 3, generator=g) * 3.0
    basis = torch.randn(b, 1, n, 3, s, generator=g) * 0.5
    rot0 = axis_angle_to_rotmat(torch.tensor([[0.1, -0.2, 0.05], [0.0, 0.3, -0.1]]))[:b]
    return PhotoTerm(samples, views, 500.0, local0, basis), rot0


@pytest.mark.parametrize("distortion", [None, torch.tensor([[-0.3, 0.2]])])
def test_photo_term_jacobian_matches_forward_autodiff(distortion):
    term, rot0 = _term(distortion=distortion)
    b, s = rot0.shape[0], term.basis.shape[-1]
    trans = torch.tensor([[0.5, -0.3, 60.0], [-1.0, 0.2, 65.0]])
    active = torch.full((b, s), 0.2)
    r, jac = term.jacobian(rot0, trans, active)

    def fn(x: torch.Tensor) -> torch.Tensor:
        return term.residuals(x[:, :3], rot0, x[:, 3:6], x[:, 6:])

    x0 = torch.cat([torch.zeros(b, 3), trans, active], 1)
    ref = torch.func.jacfwd(lambda d: fn(x0 + d[None]))(torch.zeros(6 + s))
    torch.testing.assert_close(r, fn(x0))
    assert float(ref.abs().max()) > 1.0  # the samples do move on the plate
    torch.testing.assert_close(jac, ref, atol=1e-3, rtol=1e-3)


def _broadcast_jacobian(term: PhotoTerm, rot: torch.Tensor, trans: torch.Tensor, active: torch.Tensor,
                        pose: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """PhotoTerm.jacobian as it was written before `_chain_basis` (whole-batch broadcasts, concatenated)."""
    from nodes.fit.photometric import photometric_point_jacobian

    local = term.local0 + torch.einsum("bcnds,bs->bcnd", term.basis, active) if active.shape[1] else term.local0
    q = local @ rot[:, None].transpose(-1, -2)
    r, jp = photometric_point_jacobian(term.samples, q + trans[:, None, None, :], term.views, term.weight)
    cols = [torch.linalg.cross(q[..., None, :].expand_as(jp), jp, dim=-1), jp] if pose else []
    if term.basis.shape[-1]:
        jr = torch.einsum("bcnij,bjk->bcnik", jp, rot)
        basis = term.basis
        cols.append(jr[..., 0, None] * basis[..., None, 0, :] + jr[..., 1, None] * basis[..., None, 1, :]
                    + jr[..., 2, None] * basis[..., None, 2, :])
    jac = torch.cat(cols, -1) if len(cols) > 1 else cols[0] if cols else jp[..., :0]
    return r.reshape(r.shape[0], -1), jac.reshape(r.shape[0], -1, jac.shape[-1])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_photo_term_jacobian_has_the_bits_of_the_broadcast_products(dtype):
    """`_chain_basis` (chunks of CHAIN_CHUNK samples, written in place) makes the same products and
    sums in the same order as whole-batch broadcasts: equal to the bit, over chunk boundaries, with
    and without the pose columns, and the kept `_local` answers as a fresh one."""
    from nodes.fit.photometric import CHAIN_CHUNK
    from nodes.fit.solve import in_dtype

    for n, s in ((2 * CHAIN_CHUNK + 3, 5), (7, 5), (CHAIN_CHUNK, 0)):
        term, rot0 = _term(n=n, s=s)
        term = PhotoTerm(*in_dtype((term.samples, term.views), dtype), term.weight, term.local0.to(dtype),
                         term.basis.to(dtype))
        rot0 = rot0.to(dtype)
        trans = torch.tensor([[0.5, -0.3, 60.0], [-1.0, 0.2, 65.0]], dtype=dtype)
        for active in (torch.full((2, s), 0.2, dtype=dtype), torch.full((2, s), -0.1, dtype=dtype),
                       torch.full((2, s), 0.2, dtype=dtype)):
            for pose in (True, False):
                r, jac = term.jacobian(rot0, trans, active, pose=pose)
                if not pose and not s:  # no columns (the broadcast version failed to reshape them)
                    assert jac.shape == (2, r.shape[1], 0)
                    continue
                r_ref, jac_ref = _broadcast_jacobian(term, rot0, trans, active, pose=pose)
                assert jac.dtype == jac_ref.dtype and jac.shape == jac_ref.shape
                assert torch.equal(r, r_ref) and torch.equal(jac, jac_ref)
            fresh = PhotoTerm(term.samples, term.views, term.weight, term.local0, term.basis)
            assert torch.equal(term.residuals(torch.zeros(2, 3, dtype=dtype), rot0, trans, active),
                               fresh.residuals(torch.zeros(2, 3, dtype=dtype), rot0, trans, active))
            active += 0.05  # changed in place: the kept points are not reused
            assert torch.equal(term.jacobian(rot0, trans, active)[1], _broadcast_jacobian(term, rot0, trans, active)[1])
