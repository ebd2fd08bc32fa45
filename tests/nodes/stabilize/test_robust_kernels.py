"""The numba kernels of the robust alignment agree with the torch ops they replace on the CPU.

`robust_align`, `still_vertices` and the candidate gather of the still refinement run as numba
kernels on CPU tensors (`nodes/stabilize/robust_kernels.py`, float64 sums) and as torch ops
elsewhere (`kernels=False`). Tolerances: the torch path computes distances and sums in
float32. Distances of order 1e-2 (unit-RMS coordinates) carry a relative error of about
6e-8 / 1e-2 = 6e-6 there, so IRLS weights (slope at most 4 in the distance / width) may
differ by a few 1e-4 and the fitted rotations by about 1e-7; 1e-5 for transforms and 2e-3 for
weights leave a margin of 10x or more. Every frame is computed by one thread, so the kernel
results do not depend on the thread count.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from nodes.stabilize.robust import locally_still, robust_align, still_vertices


def _rotations(count: int, max_angle: float, generator: torch.Generator) -> torch.Tensor:
    axis = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=1, keepdim=True)
    angle = (torch.rand(count, generator=generator, dtype=torch.float64) * max_angle)[:, None, None]
    k = torch.zeros(count, 3, 3, dtype=torch.float64)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    k = k - k.transpose(1, 2)
    return torch.eye(3, dtype=torch.float64) + angle.sin() * k + (1 - angle.cos()) * (k @ k)


def _scene(frames: int = 60, vertices: int = 900, seed: int = 0, moving: float = 0.3):
    """Rest shape (3, V), frames x = rot^T (rest + motion + noise - trans), truth rot, trans."""
    g = torch.Generator().manual_seed(seed)
    rest = torch.randn(3, vertices, generator=g, dtype=torch.float64)
    rot = _rotations(frames, math.radians(20.0), g)
    trans = 0.3 * torch.randn(frames, 3, generator=g, dtype=torch.float64)
    offset = torch.zeros(frames, 3, vertices, dtype=torch.float64)
    mover = torch.rand(vertices, generator=g) < moving                     # an expression region
    offset[:, :, mover] = 0.2 * torch.randn(frames, 3, int(mover.sum()), generator=g, dtype=torch.float64)
    noise = 0.003 * torch.randn(frames, 3, vertices, generator=g, dtype=torch.float64)
    target = rest + offset + noise
    # S = rot x + trans = target  ->  x = rot^T (target - trans)
    x = rot.transpose(1, 2) @ (target - trans[:, :, None])
    return x.float().contiguous(), rest.float(), rot, trans


@pytest.mark.parametrize("start", ["identity", "near"])
def test_robust_align_kernel_matches_torch(start):
    x, rest, rot_true, trans_true = _scene()
    f = x.shape[0]
    if start == "identity":  # far from the rest: the quartile widens every frame's width
        rot0, trans0 = torch.eye(3, dtype=torch.float64).expand(f, 3, 3), torch.zeros(f, 3, dtype=torch.float64)
    else:
        rot0, trans0 = rot_true, trans_true + 0.01
    prior = torch.ones(x.shape[2])
    prior[:100] = 2.0
    prior[100:110] = 0.0
    fused = robust_align(x, rest, rot0, trans0, 0.05, iterations=4, vertex_weights=prior, kernels=True)
    ops = robust_align(x, rest, rot0, trans0, 0.05, iterations=4, vertex_weights=prior, kernels=False)
    assert float((fused.rot - ops.rot).abs().max()) < 1e-5
    assert float((fused.trans - ops.trans).abs().max()) < 1e-5
    assert float((fused.weights - ops.weights).abs().max()) < 2e-3
    assert float(fused.weights[:, 100:110].abs().max()) == 0.0
    # and it found the truth: the still vertices' noise is 0.003, the motion 0.2
    assert float((fused.rot - rot_true).abs().max()) < 2e-3


def test_robust_align_kernel_uniform_fallback_and_shapes():
    x, rest, _, _ = _scene(frames=8, vertices=200)
    f = x.shape[0]
    rot0, trans0 = torch.eye(3, dtype=torch.float64).expand(f, 3, 3), torch.zeros(f, 3, dtype=torch.float64)
    zero = torch.zeros(x.shape[2])  # every weight 0: least squares, as weighted_kabsch does
    fused = robust_align(x, rest, rot0, trans0, 0.05, iterations=1, vertex_weights=zero, kernels=True)
    ops = robust_align(x, rest, rot0, trans0, 0.05, iterations=1, vertex_weights=zero, kernels=False)
    assert float((fused.rot - ops.rot).abs().max()) < 1e-5
    with pytest.raises(ValueError, match="rest: expected shape"):
        robust_align(x, rest[:, :10], rot0, trans0, 0.05)
    with pytest.raises(ValueError, match="vertex_weights: expected shape"):
        robust_align(x, rest, rot0, trans0, 0.05, vertex_weights=zero[:5])


def test_robust_align_kernel_same_on_one_and_two_threads():
    x, rest, rot_true, trans_true = _scene(seed=3)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = robust_align(x, rest, rot_true, trans_true, 0.05, iterations=3)
        torch.set_num_threads(2)
        two = robust_align(x, rest, rot_true, trans_true, 0.05, iterations=3)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one.rot, two.rot) and torch.equal(one.trans, two.trans)


def test_still_vertices_kernel_matches_cumulative_sum():
    g = torch.Generator().manual_seed(5)
    frames, vertices, sigma = 300, 700, 0.01
    residual = sigma * torch.randn(frames, 3, vertices, generator=g)
    t = torch.linspace(0, 6 * math.pi, frames)[:, None]
    residual[:, 0, :200] += 0.02 * torch.sin(t)                 # slow expression motion: not still
    centre = torch.randn(3, vertices, generator=g)
    for window in (1, 7, 15, frames):
        fused = still_vertices(residual + centre, sigma, window=window, centre=centre, kernels=True)
        ops = still_vertices(residual + centre, sigma, window=window, centre=centre, kernels=False)
        assert torch.equal(fused, ops), window
    still = still_vertices(residual, sigma, window=15)
    assert not bool(still[:200].any()) and bool(still[200:].float().mean() > 0.99)


def test_still_refinement_gather_matches_torch():
    from nodes.stabilize.robust_kernels import gather_normalized

    rng = np.random.default_rng(2)
    verts = (10 * rng.standard_normal((9, 50, 3))).astype(np.float32)
    ids = np.array([3, 0, 49, 17, 17], np.int64)
    centre = np.array([1.5, -2.0, 0.25])
    out = np.empty((9, 3, ids.size), np.float32)
    gather_normalized(verts, ids, centre, 4.0, out)
    expected = ((verts[:, ids].astype(np.float64) - centre) / 4.0).astype(np.float32).transpose(0, 2, 1)
    np.testing.assert_array_equal(out, expected)


def test_robust_align_per_frame_weights_kernel_matches_torch():
    """(F, V) weights: a vertex region that moves only in some frames, weighted 0 there."""
    x, rest, rot_true, trans_true = _scene(seed=4, moving=0.0)
    f, _, v = x.shape
    # vertices 0..299 move by 0.2 in frames 20..39 only (in the skull frame, then to the world)
    offset = torch.zeros(f, 3, v, dtype=torch.float64)
    offset[20:40, 1, :300] = 0.2
    x = (x.double() + rot_true.transpose(1, 2) @ offset).float().contiguous()
    weights = torch.ones(f, v)
    weights[20:40, :300] = 0.0
    rot0, trans0 = torch.eye(3, dtype=torch.float64).expand(f, 3, 3), torch.zeros(f, 3, dtype=torch.float64)
    fused = robust_align(x, rest, rot0, trans0, 1.0, iterations=4, vertex_weights=weights, kernels=True)
    ops = robust_align(x, rest, rot0, trans0, 1.0, iterations=4, vertex_weights=weights, kernels=False)
    assert float((fused.rot - ops.rot).abs().max()) < 1e-5
    assert float((fused.trans - ops.trans).abs().max()) < 1e-5
    assert float(fused.weights[20:40, :300].abs().max()) == 0.0
    # the noise is 0.003 on 600 vertices: the rotation within a few 1e-4; with the moving
    # vertices kept (width 1.0 > 0.2, uniform weights) a third of the points sit 0.2 off
    assert float((fused.rot - rot_true).abs().max()) < 2e-3
    kept = robust_align(x, rest, rot0, trans0, 1.0, iterations=4, kernels=True)
    assert float((kept.trans[20:40] - trans_true[20:40]).abs().max()) > 0.03
    assert float((fused.trans[20:40] - trans_true[20:40]).abs().max()) < 0.01


def test_locally_still_kernel_matches_cumulative_sum_and_finds_a_held_offset():
    g = torch.Generator().manual_seed(6)
    frames, vertices, sigma = 200, 500, 0.01
    residual = sigma * torch.randn(frames, 3, vertices, generator=g)
    residual[80:120, 2, :100] += 0.01               # one noise std, held over 40 frames
    for half_window in (0, 3, 15, frames):
        fused = locally_still(residual, sigma, half_window=half_window, kernels=True)
        ops = locally_still(residual, sigma, half_window=half_window, kernels=False)
        # the same float64 sums in another order: a tie at the threshold is the only difference
        assert float((fused != ops).float().mean()) < 1e-4, half_window
    still = locally_still(residual, sigma, half_window=15)
    # 31 frames of the held offset: n |m|^2 / sigma^2 ~ 31 + chi^2_3 (noncentral), far above 11.34
    assert float(still[95:105, :100].mean()) < 0.01
    # noise alone: chi^2_3 under its 99 % quantile in 99 % of the entries; overlapping windows
    # are correlated, so 200 frames x 400 vertices are about 6 x 400 independent draws (binomial
    # std 0.002) and 50 x 100 about 2 x 100 (std 0.007): bounds at 4-5 std
    assert 0.98 < float(still[:, 100:].mean()) < 0.999
    assert 0.95 < float(still[:50, :100].mean())
