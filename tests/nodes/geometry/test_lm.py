"""geometry.lm against scipy.optimize.least_squares (MINPACK's Levenberg-Marquardt) on small problems."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.optimize import least_squares

from nodes.geometry.lm import LMSchedule, damped_step, from_jacobian, levenberg_marquardt
from nodes.geometry.rotation import axis_angle_to_rotmat_torch as axis_angle_to_rotmat

f64 = torch.float64


def _rosenbrock(x: torch.Tensor) -> torch.Tensor:
    return torch.stack([10.0 * (x[:, 1] - x[:, 0] ** 2), 1.0 - x[:, 0]], 1)


def _rosenbrock_jac(x: torch.Tensor) -> torch.Tensor:
    b = x.shape[0]
    jac = torch.zeros(b, 2, 2, dtype=x.dtype)
    jac[:, 0, 0], jac[:, 0, 1], jac[:, 1, 0] = -20.0 * x[:, 0], 10.0, -1.0
    return jac


def test_rosenbrock_batch_matches_scipy_and_the_known_minimum():
    starts = torch.tensor([[-1.2, 1.0], [2.0, -1.0], [0.5, 3.0], [-3.0, -3.0]], dtype=f64)
    out = levenberg_marquardt(_rosenbrock, from_jacobian(_rosenbrock_jac), starts, iterations=200,
                              schedule=LMSchedule(rel_tol=0.0, floor=0.0))
    for b in range(len(starts)):
        ref = least_squares(lambda v: _rosenbrock(torch.as_tensor(v)[None])[0].numpy(), starts[b].numpy(),
                            method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
        # zero-residual problem with a regular minimum at (1, 1): both converge quadratically
        # there, to float64 rounding of the 2x2 solve (|J| ~ 20, x ~ 1): well under 1e-8.
        np.testing.assert_allclose(out.x[b].numpy(), ref, atol=1e-8)
        np.testing.assert_allclose(out.x[b].numpy(), [1.0, 1.0], atol=1e-8)
    assert float(out.cost.max()) < 1e-16


def test_exponential_fit_matches_scipy_with_noise():
    gen = np.random.default_rng(3)
    t = torch.linspace(0.0, 2.0, 40, dtype=f64)
    truth = torch.tensor([[2.0, -1.3], [0.5, 0.7], [4.0, -0.2]], dtype=f64)
    y = truth[:, :1] * torch.exp(truth[:, 1:] * t) + torch.as_tensor(gen.normal(0, 0.02, (3, 40)))

    def res(x: torch.Tensor) -> torch.Tensor:
        return x[:, :1] * torch.exp(x[:, 1:] * t) - y

    def jac(x: torch.Tensor) -> torch.Tensor:
        e = torch.exp(x[:, 1:] * t)
        return torch.stack([e, x[:, :1] * t * e], 2)

    x0 = torch.tensor([[1.0, 0.0]] * 3, dtype=f64)
    out = levenberg_marquardt(res, from_jacobian(jac), x0, iterations=100, schedule=LMSchedule(rel_tol=1e-14))
    for b in range(3):
        ref = least_squares(lambda v, b=b: res(torch.as_tensor(v).expand(3, 2))[b].numpy(), x0[b].numpy(),
                            method="lm", xtol=1e-14, ftol=1e-14).x
        # same minimum of a well-conditioned problem (cond(J) < 1e3); the stopping rule leaves
        # a relative cost change below 1e-14, i.e. |dx| ~ sqrt(1e-14 cost / |J^T J|) < 1e-6
        np.testing.assert_allclose(out.x[b].numpy(), ref, atol=1e-6)
        # and near the truth within the noise's effect (0.02 noise over 40 samples)
        np.testing.assert_allclose(out.x[b].numpy(), truth[b].numpy(), atol=0.05)


def test_batched_rigid_alignment_with_relinearized_rotation():
    gen = np.random.default_rng(7)
    b, n = 5, 30
    pts = torch.as_tensor(gen.normal(0, 5.0, (n, 3)))
    omega = torch.as_tensor(gen.normal(0, 0.8, (b, 3)))
    trans = torch.as_tensor(gen.normal(0, 3.0, (b, 3)))
    noise = torch.as_tensor(gen.normal(0, 0.01, (b, n, 3)))
    target = pts @ axis_angle_to_rotmat(omega).transpose(1, 2) + trans[:, None] + noise
    base = {"rot": torch.eye(3, dtype=f64).expand(b, 3, 3).clone()}

    def res(x: torch.Tensor) -> torch.Tensor:  # x = [omega increment about base rot, t]
        rot = axis_angle_to_rotmat(x[:, :3]) @ base["rot"]
        return (pts @ rot.transpose(1, 2) + x[:, None, 3:] - target).reshape(len(x), -1)

    def jac(x: torch.Tensor) -> torch.Tensor:  # at omega = 0 (relinearized every accepted step)
        q = pts @ base["rot"].transpose(1, 2)  # (B, N, 3)
        j = torch.zeros(len(x), n, 3, 6, dtype=f64)
        # d(exp([w]) q)/dw at w = 0 = -[q]_x
        j[..., 0, 1], j[..., 0, 2] = q[..., 2], -q[..., 1]
        j[..., 1, 0], j[..., 1, 2] = -q[..., 2], q[..., 0]
        j[..., 2, 0], j[..., 2, 1] = q[..., 1], -q[..., 0]
        j[..., :, 3:] = torch.eye(3, dtype=f64)
        return j.reshape(len(x), n * 3, 6)

    def relin(x: torch.Tensor, accepted: torch.Tensor) -> torch.Tensor:
        new = axis_angle_to_rotmat(x[:, :3]) @ base["rot"]
        base["rot"] = torch.where(accepted[:, None, None], new, base["rot"])
        return torch.cat([torch.where(accepted[:, None], torch.zeros_like(x[:, :3]), x[:, :3]), x[:, 3:]], 1)

    out = levenberg_marquardt(res, from_jacobian(jac), torch.zeros(b, 6, dtype=f64), iterations=50,
                              schedule=LMSchedule(rel_tol=1e-12), relinearize=relin)
    rot_lm = axis_angle_to_rotmat(out.x[:, :3]) @ base["rot"]
    for k in range(b):
        def res_np(v: np.ndarray, k: int = k) -> np.ndarray:
            r = axis_angle_to_rotmat(torch.as_tensor(v[None, :3]))[0]
            return (pts @ r.T + torch.as_tensor(v[3:]) - target[k]).reshape(-1).numpy()

        ref = least_squares(res_np, np.concatenate([omega[k].numpy() * 0.9, np.zeros(3)]), method="lm",
                            xtol=1e-14, ftol=1e-14).x
        rot_ref = axis_angle_to_rotmat(torch.as_tensor(ref[None, :3]))[0]
        # the same least-squares minimum (noise 0.01 cm, 30 points 5 cm apart: the minimum is
        # regular, curvature ~ n |p|^2); stopping at 1e-12 relative cost: < 1e-6 apart
        np.testing.assert_allclose(rot_lm[k].numpy(), rot_ref.numpy(), atol=1e-6)
        np.testing.assert_allclose(out.x[k, 3:].numpy(), ref[3:], atol=1e-5)
    assert torch.allclose(rot_lm, axis_angle_to_rotmat(omega), atol=5e-3)


def test_damped_step_solves_the_damped_system_and_a_rejected_step_keeps_x():
    gen = np.random.default_rng(1)
    jac = torch.as_tensor(gen.normal(size=(3, 8, 4)))
    r = torch.as_tensor(gen.normal(size=(3, 8)))
    jtj, jtr = jac.transpose(1, 2) @ jac, (jac.transpose(1, 2) @ r[..., None])[..., 0]
    lam = torch.tensor([0.0, 1.0, 100.0], dtype=f64)
    dx = damped_step(jtj, jtr, lam, floor=0.0)
    a = jtj + torch.diag_embed(lam[:, None] * torch.diagonal(jtj, dim1=1, dim2=2))
    torch.testing.assert_close((a @ dx[..., None])[..., 0], -jtr, rtol=1e-10, atol=1e-10)
    # a cost that no step lowers (x already at its minimum): x unchanged, lam grown, solve stops
    x0 = torch.zeros(2, 2, dtype=f64)
    out = levenberg_marquardt(lambda x: x + 0.0, from_jacobian(lambda x: torch.eye(2, dtype=f64).expand(2, 2, 2)),
                              x0, iterations=5)
    assert torch.equal(out.x, x0) and out.iterations == 1 and bool((out.lam > 1e-3).all())


@pytest.mark.parametrize("threads", [1, 4])
def test_lm_is_deterministic_across_threads(threads: int):
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        starts = torch.tensor([[-1.2, 1.0], [2.0, -1.0]], dtype=f64)
        out = levenberg_marquardt(_rosenbrock, from_jacobian(_rosenbrock_jac), starts, iterations=100)
    finally:
        torch.set_num_threads(before)
    np.testing.assert_allclose(out.x.numpy(), 1.0, atol=1e-6)


def test_residual_count_that_follows_x_and_residuals_returned_by_the_linearization():
    """A residual vector whose length depends on x (as a coverage does: `temporal.flowfit`), two
    elements of different lengths in one batch, and `normal` returning the residuals at x (the
    3-value form): r(x) = (x - c) repeated 1 + floor(|x|) times, cost (1 + floor|x|)(x - c)^2,
    minimum 0 at x = c. Gauss-Newton on (x - c) is exact in one step, so the answer is c to
    float64 rounding of a scalar division (1e-15 relative)."""
    c = torch.tensor([[0.25], [-0.6]], dtype=f64)

    def res(x: torch.Tensor) -> torch.Tensor:
        k = int(1 + torch.floor(x.abs()).max())  # the longest element's count; shorter ones padded by 0
        reps = (1 + torch.floor(x.abs())).to(torch.long)  # (B, 1)
        cols = torch.arange(k)[None]
        return torch.where(cols < reps, x - c, torch.zeros((), dtype=f64))

    seen = []

    def normal(x: torch.Tensor, _r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        r = res(x)
        seen.append(r.shape[1])
        n = (r != 0).sum(1).clamp_min(1).to(f64)
        return n[:, None, None], (r.sum(1))[:, None], r

    out = levenberg_marquardt(res, normal, torch.tensor([[5.3], [-2.7]], dtype=f64), iterations=30,
                              schedule=LMSchedule(rel_tol=0.0))
    np.testing.assert_allclose(out.x.numpy(), c.numpy(), rtol=0, atol=1e-12)
    assert seen[0] == 6 and seen[-1] == 1  # the count changed along the way (6 at x = 5.3, 1 at |x| < 1)
    assert float(out.cost.max()) < 1e-24
