"""Robust per-frame alignment to a rest shape, mode-seeking rest estimates and a noise estimate.

The pieces mode pursuit uses around its spline stages (see `mode_pursuit.py`):

- `weighted_kabsch`: per-frame weighted least-squares rigid fit of (F, 3, V) points onto one
  (3, V) rest shape (Kabsch 1976 / Umeyama 1991), batched over frames. Closed form, so it
  has no basin: any head rotation is recovered in one step once the weights are right.
- `robust_align`: iteratively reweighted Kabsch (IRLS) with the weights of the bounded
  penalty `psi_w` applied to each vertex's distance `r = |S_fv - R_v|` (cm):
  `k(r) = psi_w'(r) / r ∝ 1` for `r < w/2`, `(w - r) / r` for `w/2 <= r < w`, 0 beyond.
  Each step decreases `sum_fv psi_w(r_fv)` (a redescending M-estimator), so vertices
  moving with an expression, outliers and sliding skin drop out of a frame's fit.
- `rest_mode`: the per-vertex mode of the stabilized positions over frames: start at the
  candidate frame (of up to 64 evenly spaced ones) with the most samples within `radius`,
  then mean-shift with a flat kernel. Unlike the median it finds the rest also when a vertex
  is away from it (an expression) in most frames, as long as the rest is the densest place.
- `noise_level`: the tracking noise std (cm) from second differences over frames of the
  stabilized positions, `sigma = 1.4826 median|S_{f+1} - 2 S_f + S_{f-1}| / sqrt(6)`:
  i.i.d. noise passes with variance 6 sigma^2, while head motion (removed), held expressions
  and slow expressions give near-zero second differences, and the median ignores the
  minority of fast-moving coordinates.

Layout: coordinates first, `x` (F, 3, V) float32 as in the mode-pursuit optimizer;
`S_f = rot_f x_f + trans_f`.
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

__all__ = ["lower_median", "still_vertices", "locally_still", "RobustAlignment", "weighted_kabsch", "psi_weights", "robust_align",
           "rest_mode",
           "noise_level", "residual_scale", "apply_transforms", "kabsch_from_moments", "frame_blocks"]


class RobustAlignment(NamedTuple):
    """Result of `robust_align`.

    Attributes:
        rot: (F, 3, 3) float64 rotations (world -> skull).
        trans: (F, 3) float64 translations, units of `x`: `S_f = rot_f x_f + trans_f`.
        weights: (F, V) float32 final IRLS weights in [0, 1] (0 = ignored in that frame).
    """

    rot: Tensor
    trans: Tensor
    weights: Tensor


def lower_median(values: Tensor, dim: int | None = None) -> Tensor:
    """`torch.median`'s value (of all entries, or along `dim`): the lower middle of an even count.

    On the CPU it selects with numpy's partition (introselect) instead of torch's median, which
    sorts: the same values bit for bit, 5-10x faster (651 x 3 x 26,719 float32 along frames:
    0.65 s against 3.6 s at one thread on a loaded 2-core machine). Other devices and tensors
    that need a gradient use `torch.median`. Entries must be finite (a NaN is not propagated
    on the CPU path).

    Args:
        values: float tensor, any shape (non-empty along `dim`).
        dim: the axis reduced; None = all entries.
    Returns:
        A 0-d tensor (dim None) or `values` without `dim`, values' dtype and device.
    """
    if values.device.type != "cpu" or values.requires_grad or values.numel() == 0 \
            or values.dtype not in (torch.float32, torch.float64):
        return values.median() if dim is None else values.median(dim=dim).values
    array = values.numpy().reshape(-1) if dim is None else values.numpy()
    axis = 0 if dim is None else dim % array.ndim
    k = (array.shape[axis] - 1) // 2
    return torch.from_numpy(np.asarray(np.partition(array, k, axis=axis).take(k, axis=axis)))  # 0-d for dim None


def apply_transforms(x: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """Return `S_f = rot_f x_f + trans_f` as (F, 3, V) in x's dtype (x is (F, 3, V))."""
    return torch.baddbmm(trans.to(x.dtype)[:, :, None], rot.to(x.dtype), x)


def weighted_kabsch(x: Tensor, rest: Tensor, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Per-frame rigid fit minimising `sum_v w_fv |rot_f x_fv + trans_f - rest_v|^2`.

    Args:
        x: (F, 3, V) points per frame (any unit).
        rest: (3, V) target points, same unit.
        weights: (F, V) >= 0, or None for uniform; a frame whose weights sum to 0 gets
            uniform weights (its fit is then plain least squares).
    Returns:
        rot (F, 3, 3) float64 (det +1), trans (F, 3) float64.
    """
    if x.ndim != 3 or x.shape[1] != 3:
        raise ValueError(f"x: expected shape (F, 3, V), found {tuple(x.shape)}")
    if rest.shape != x.shape[1:]:
        raise ValueError(f"rest: expected shape {tuple(x.shape[1:])} (from x), found {tuple(rest.shape)}")
    f, _, v = x.shape
    if weights is None:
        weights = x.new_ones(f, v)
    w = weights.to(x.dtype)
    total = w.sum(1, keepdim=True)
    w = torch.where(total > 0, w / total.clamp(min=1e-30), torch.full_like(w, 1.0 / v))
    wx = x * w[:, None, :]
    cx = wx.sum(2).double()                                              # (F, 3)
    cr = (w @ rest.T).double()                                           # (F, 3)
    cov = torch.bmm(wx, rest.T.expand(f, v, 3)).double() - cx[:, :, None] * cr[:, None, :]
    return _kabsch(cx, cr, cov)


def kabsch_from_moments(moments: Tensor) -> tuple[Tensor, Tensor]:
    """Per-frame rigid fit from weighted moments (`robust_kernels.irls_moments`).

    Args:
        moments: (F, 16) float64: [sum w, sum w x (3), sum w r (3), sum w x r^T (9, row-major)]
            with sum w > 0.
    Returns:
        rot (F, 3, 3) float64 (det +1), trans (F, 3) float64, as `weighted_kabsch`.
    """
    total = moments[:, :1]
    cx = moments[:, 1:4] / total
    cr = moments[:, 4:7] / total
    cov = moments[:, 7:].reshape(-1, 3, 3) / total[:, :, None] - cx[:, :, None] * cr[:, None, :]
    return _kabsch(cx, cr, cov)


def _kabsch(cx: Tensor, cr: Tensor, cov: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation and translation taking centroid cx to cr given the (F, 3, 3) cross-covariance
    `sum w (x - cx)(r - cr)^T` (float64)."""
    f = cov.shape[0]
    u, _, vh = torch.linalg.svd(cov)                                     # cov = U S V^T
    d = torch.sign(torch.linalg.det(vh.transpose(1, 2) @ u.transpose(1, 2)))
    d = torch.where(d == 0, torch.ones_like(d), d)
    fix = torch.ones(f, 3, dtype=torch.float64, device=cov.device)
    fix[:, 2] = d
    rot = vh.transpose(1, 2) @ (fix[:, :, None] * u.transpose(1, 2))    # V diag(1,1,d) U^T
    trans = cr - (rot @ cx[:, :, None])[:, :, 0]
    return rot, trans


def psi_weights(distance: Tensor, width: float | Tensor) -> Tensor:
    """IRLS weights `psi_w'(r) / r`, scaled to 1 at 0, of distances r = |S - R| (same unit as width).

    `width` is a float or a tensor broadcasting against `distance`.

    Returns:
        (...) in [0, 1]: 1 for r < w/2, (w - r) / r for w/2 <= r < w, 0 beyond.
    """
    u = distance / width
    return torch.where(u < 0.5, torch.ones_like(u), (1.0 - u).clamp(min=0.0) / u.clamp(min=0.5))


def _distances(x: Tensor, rot: Tensor, trans: Tensor, rest: Tensor) -> Tensor:
    """(F, V) distances |rot_f x_fv + trans_f - rest_v|."""
    return apply_transforms(x, rot, trans).sub_(rest).square_().sum(1).sqrt_()


def residual_scale(distance: Tensor) -> float:
    """Robust scale of distances: median over all entries (same unit)."""
    flat = distance.reshape(-1)
    if flat.numel() > 1 << 20:  # a strided subset is as good a median and much faster
        flat = flat[:: flat.numel() // (1 << 20) + 1]
    return float(lower_median(flat))


def robust_align(x: Tensor, rest: Tensor, rot: Tensor, trans: Tensor, width: float, *,
                 iterations: int = 4, vertex_weights: Tensor | None = None,
                 kernels: bool = True) -> RobustAlignment:
    """Iteratively reweighted Kabsch of every frame onto the rest, bounded penalty of width w.

    Minimises `sum_{f, v} c_v psi_w(|rot_f x_fv + trans_f - rest_v|)` per frame by IRLS
    (weights `c_v psi_w'(r) / r`, see the module docstring), starting from (rot, trans).
    Each step uses the width `max(w, 3 q_f)` for frame f, `q_f` the lower quartile of its
    distances, so a frame that starts
    far from the rest is first fitted nearly by least squares (annealing, as in robust ICP);
    once aligned, every frame uses w.

    Args:
        x: (F, 3, V) float32 points.
        rest: (3, V) rest shape.
        rot, trans: (F, 3, 3), (F, 3) starting transforms.
        width: w > 0 (units of x).
        iterations: IRLS steps (each one Kabsch per frame).
        vertex_weights: (V,) prior weights c_v >= 0 (e.g. higher on a rigid region), or (F, V)
            per frame (e.g. 0 where a vertex moves in that frame), or None.
        kernels: on the CPU, run each step as one fused pass per frame
            (`robust_kernels.irls_moments`, float64 sums; 5-10x faster); False: torch ops.
    Returns:
        RobustAlignment. A frame with no vertex within w keeps least-squares weights.
    """
    if not width > 0:
        raise ValueError(f"width: expected > 0, found {width}")
    if x.ndim != 3 or x.shape[1] != 3:
        raise ValueError(f"x: expected shape (F, 3, V), found {tuple(x.shape)}")
    f, _, v = x.shape
    for name, value, shape in (("rest", rest, (3, v)), ("rot", rot, (f, 3, 3)), ("trans", trans, (f, 3))):
        if value is not None and tuple(value.shape) != shape:
            raise ValueError(f"{name}: expected shape {shape} (from x), found {tuple(value.shape)}")
    if vertex_weights is not None and tuple(vertex_weights.shape) not in ((v,), (f, v)):
        raise ValueError(f"vertex_weights: expected shape ({v},) or ({f}, {v}) (from x), found "
                         f"{tuple(vertex_weights.shape)}")
    rot, trans = rot.double(), trans.double()
    if kernels and x.device.type == "cpu" and iterations > 0:
        return _robust_align_cpu(x, rest, rot, trans, width, iterations, vertex_weights)
    weights = x.new_ones(x.shape[0], x.shape[2])
    for _ in range(iterations):
        dist = _distances(x, rot, trans, rest)
        # A frame far from the rest (a poor start) gets a wider width for this step, so that
        # its fit does not rest on the few vertices that happen to be within `width`.
        # (The lower quartile: expressions move a minority of the vertices, a misalignment all.)
        quartile = dist.kthvalue(max(1, dist.shape[1] // 4), dim=1).values
        frame_width = (3.0 * quartile).clamp(min=width)
        weights = psi_weights(dist, frame_width[:, None])
        if vertex_weights is not None:
            weights = weights * vertex_weights.to(weights.dtype)
        rot, trans = weighted_kabsch(x, rest, weights)
    return RobustAlignment(rot, trans, weights)


def _robust_align_cpu(x: Tensor, rest: Tensor, rot: Tensor, trans: Tensor, width: float, iterations: int,
                      vertex_weights: Tensor | None) -> RobustAlignment:
    """`robust_align` by the numba kernel: the same steps, one pass over the points per step."""
    from .robust_kernels import MOMENTS, irls_moments

    f, _, v = x.shape
    xs = x.detach().to(torch.float32).contiguous().numpy()
    rs = rest.detach().to(torch.float32).contiguous().numpy()
    prior = (np.ones((1, v), np.float32) if vertex_weights is None
             else vertex_weights.detach().to(torch.float32).reshape(-1, v).contiguous().numpy())
    per_frame = prior.shape[0] == f
    moments = np.empty((f, MOMENTS), np.float64)
    weights = np.empty((f, v), np.float32)
    for step in range(iterations):
        r, t = rot.contiguous().numpy(), trans.contiguous().numpy()
        out = weights if step == iterations - 1 else None

        def block(lo: int, hi: int) -> None:
            irls_moments(xs[lo:hi], rs, r[lo:hi], t[lo:hi], float(width), prior[lo:hi] if per_frame else prior,
                         max(1, v // 4),
                         moments[lo:hi], np.empty((0, v), np.float32) if out is None else out[lo:hi])

        frame_blocks(block, f)
        rot, trans = kabsch_from_moments(torch.from_numpy(moments))
    return RobustAlignment(rot, trans, torch.from_numpy(weights))


def frame_blocks(run: Callable[[int, int], None], num_frames: int, *, min_frames: int = 32) -> None:
    """Call `run(lo, hi)` on contiguous blocks of frames, one per torch thread, in parallel.

    For numba kernels that release the GIL and compute each frame on its own: the result does
    not depend on the number of threads. At most one block per `min_frames` frames.
    """
    threads = max(1, min(torch.get_num_threads(), num_frames // min_frames))
    if threads == 1:
        run(0, num_frames)
        return
    bounds = np.linspace(0, num_frames, threads + 1).round().astype(int)
    with ThreadPoolExecutor(threads) as pool:
        list(pool.map(run, bounds[:-1].tolist(), bounds[1:].tolist()))


def rest_mode(stab: Tensor, radius: float, *, start: Tensor | None = None, steps: int = 3,
              candidates: int = 32, sample_frames: int = 256, block_frames: int = 64) -> Tensor:
    """Return each vertex's mode over frames of its stabilized positions (see the module docstring).

    Args:
        stab: (F, 3, V) stabilized positions.
        radius: kernel radius (units of stab), > 0.
        start: (3, V) starting modes: skip the candidate search and only mean-shift from
            there (cheap: one pass over the frames per step).
        steps: mean-shift steps after the candidate search (flat kernel of `radius`).
        candidates: at most this many evenly spaced candidate frames.
        sample_frames: densities are counted over at most this many evenly spaced frames.
        block_frames: frames per block (bounds memory).
    Returns:
        (3, V) mode estimates; a vertex with no sample within `radius` of any candidate keeps
        its per-vertex median.
    """
    f, _, v = stab.shape
    r2 = radius * radius
    if start is not None:
        return _mean_shift(stab, start, r2, steps, block_frames)
    median = lower_median(stab, dim=0)
    if f <= 2:
        return median
    picks = torch.unique(torch.linspace(0, f - 1, min(candidates, f), device=stab.device).round().long())
    # Densities are counted over at most `sample_frames` evenly spaced frames (as good a count).
    samples = stab[torch.unique(torch.linspace(0, f - 1, min(sample_frames, f), device=stab.device).round().long())]
    counts = torch.zeros(picks.numel() + 1, v, dtype=stab.dtype, device=stab.device)
    centres = torch.cat([stab[picks], median[None]], 0)                  # (C + 1, 3, V)
    for a in range(0, samples.shape[0], block_frames):
        s = samples[a:a + block_frames]                                  # (B, 3, V)
        for c in range(centres.shape[0]):
            d2 = (s - centres[c]).square_().sum(1)                       # (B, V)
            counts[c] += (d2 < r2).sum(0).to(stab.dtype)
    best = counts.argmax(0)                                              # (V,)
    mode = centres.gather(0, best[None, None, :].expand(1, 3, v))[0]     # (3, V)
    return _mean_shift(stab, mode, r2, steps, block_frames)


def _mean_shift(stab: Tensor, mode: Tensor, r2: float, steps: int, block_frames: int) -> Tensor:
    """Flat-kernel mean shift of (3, V) modes over (F, 3, V) samples (squared radius r2)."""
    f, _, v = stab.shape
    for _ in range(steps):
        num = torch.zeros_like(mode)
        den = torch.zeros(v, dtype=stab.dtype, device=stab.device)
        for a in range(0, f, block_frames):
            d = stab[a:a + block_frames] - mode
            inside = (d.square().sum(1) < r2).to(stab.dtype)             # (B, V)
            num += (d * inside[:, None, :]).sum(0)
            den += inside.sum(0)
        mode = mode + num / den.clamp(min=1.0)
    return mode


def noise_level(stab: Tensor) -> float:
    """Tracking-noise std from second differences over frames (see the module docstring).

    Args:
        stab: (F, 3, V) stabilized positions, F >= 3.
    Returns:
        sigma (units of stab); 0.0 when F < 3.
    """
    if stab.shape[0] < 3:
        return 0.0
    d2 = (stab[2:] - 2.0 * stab[1:-1] + stab[:-2]).abs().reshape(-1)
    if d2.numel() > 1 << 21:
        d2 = d2[:: d2.numel() // (1 << 21) + 1]
    return float(lower_median(d2)) * 1.4826 / math.sqrt(6.0)



def still_vertices(residual: Tensor, sigma: float, *, window: int = 15, ratio: float = 2.0,
                   centre: Tensor | None = None, kernels: bool = True) -> Tensor:
    """Which vertices stay at their rest up to the tracking noise, over the whole shot.

    Noise is white over frames; expressions are smooth. The residual `S_fv - R_v` of a vertex
    that moves only with the skull, averaged over `k` consecutive frames, has mean square
    `3 sigma^2 / k` (noise alone, per coordinate std `sigma`); a vertex that moves with
    expressions keeps its displacement through the average. A vertex is still when the mean
    over frames of its averaged squared residual is under `ratio` times that. At 0.1 cm noise,
    expression motion of a few millimetres hides inside the bounded penalty's width frame by
    frame, but not in this test over the shot.

    Args:
        residual: (F, 3, V) stabilized vertices minus their rest (units of sigma).
        sigma: per-coordinate noise std, > 0.
        window: k, frames averaged (at most F).
        ratio: threshold over the noise-only mean square (2: with F / k = 20 windows the
            noise-only statistic has a relative std of about 0.18, so a still vertex fails
            the test with a probability under 1e-6).
        centre: (3, V) subtracted from `residual` first (e.g. stabilized positions and their
            per-vertex median), or None.
        kernels: on the CPU, running window sums in one pass (`robust_kernels`; the same
            float64 sums, 3-4x faster than the cumulative sum over frames); False: torch ops.
    Returns:
        (V,) bool.
    """
    if not sigma > 0:
        raise ValueError(f"sigma: expected > 0, found {sigma}")
    if residual.ndim != 3 or residual.shape[1] != 3:
        raise ValueError(f"residual: expected shape (F, 3, V), found {tuple(residual.shape)}")
    if centre is not None and tuple(centre.shape) != tuple(residual.shape[1:]):
        raise ValueError(f"centre: expected shape {tuple(residual.shape[1:])}, found {tuple(centre.shape)}")
    k = max(1, min(int(window), residual.shape[0]))
    if kernels and residual.device.type == "cpu":
        from .robust_kernels import window_mean_square

        out = np.empty(residual.shape[2], np.float64)
        zero = np.zeros((3, residual.shape[2]), np.float32)
        window_mean_square(residual.detach().to(torch.float32).contiguous().numpy(),
                           zero if centre is None else centre.detach().to(torch.float32).contiguous().numpy(),
                           k, out)
        mean_square = torch.from_numpy(out)
    else:
        if centre is not None:
            residual = residual - centre
        c = torch.cumsum(torch.cat([torch.zeros_like(residual[:1]), residual.double()]), 0)
        mean_square = ((c[k:] - c[:-k]) / k).square().sum(1).mean(0)
    return mean_square.to(residual.device) < ratio * 3.0 * sigma * sigma / k


def locally_still(residual: Tensor, sigma: float, *, half_window: int, threshold: float = 11.34,
                  kernels: bool = True) -> Tensor:
    """Per frame, which vertices are at their rest around that frame, up to the tracking noise.

    `still_vertices` judges a vertex over the whole shot, so an expression held in a sixth of
    the frames can pass it while it moves the vertex by a millimetre in those frames. Here each
    frame gets its own answer: the residual `S_fv - R_v` averaged over the n_f frames within
    `half_window` of f has, for noise alone, `n_f |m_fv|^2 / sigma^2 ~ chi^2_3`; the vertex is
    still at f when that is under `threshold` (11.34: the 99 % quantile, so 1 % of the still
    vertices are dropped in any frame; n = 31 frames at 0.1 cm noise find a displacement of
    0.06 cm).

    Args:
        residual: (F, 3, V) stabilized vertices minus their rest (units of sigma).
        sigma: per-coordinate noise std, > 0.
        half_window: h >= 0, frames each side of f averaged.
        threshold: on `n_f |m_fv|^2 / sigma^2` (unitless).
        kernels: on the CPU, running sums in one pass (`robust_kernels.local_window_still`);
            False: torch ops (cumulative sums, float64).
    Returns:
        (F, V) float32: 1 where still, 0 where not.
    """
    if not sigma > 0:
        raise ValueError(f"sigma: expected > 0, found {sigma}")
    if residual.ndim != 3 or residual.shape[1] != 3:
        raise ValueError(f"residual: expected shape (F, 3, V), found {tuple(residual.shape)}")
    if half_window < 0:
        raise ValueError(f"half_window: expected >= 0, found {half_window}")
    f, _, v = residual.shape
    limit = float(threshold) * sigma * sigma
    if kernels and residual.device.type == "cpu":
        from .robust_kernels import local_window_still

        out = np.empty((f, v), np.float32)
        local_window_still(residual.detach().to(torch.float32).contiguous().numpy(), int(half_window), limit, out)
        return torch.from_numpy(out)
    c = torch.cat([torch.zeros_like(residual[:1], dtype=torch.float64), residual.double().cumsum(0)])
    frames = torch.arange(f, device=residual.device)
    lo, hi = (frames - half_window).clamp(min=0), (frames + half_window + 1).clamp(max=f)
    count = (hi - lo).double()
    square = (c[hi] - c[lo]).square().sum(1)                              # n^2 |m|^2, (F, V)
    return (square < limit * count[:, None]).to(torch.float32)
