"""The forward pass of `nodes.flow.dense.dense_flow`, compiled: the same model, counts and
arithmetic (float32, summed in another order: results agree to about 1e-4 px on average,
1e-2 px at worst near silhouettes), as numba kernels per warp instead of thousands of small
torch operations per pair (256^2, 2 cores, the defaults: 6.4-7.3 ms against 75-87 ms at load 2-5). For plate
flow, where no gradient is needed (`flow.OpticalFlow` on the CPU); the torch version stays the
differentiable one. Agreement: tests/nodes/flow/test_fast_flow.py.

Threads: the Jacobi sweeps run over row strips, one per numba thread, several sweeps per
parallel launch (each strip recomputes a halo of rows, so the result is the same bit for bit
on any thread count); pyramid levels under `PARALLEL_PIXELS` run on one thread, where
starting the threads would cost more than the sweep. Scratch buffers are allocated once per
level (fresh 256^2 arrays every warp cost more in page faults than the arithmetic).

This module imports numba at the top (kernels cached on disk): import it from node `run()`
methods only."""

from __future__ import annotations

import numba
import numpy as np

from .dense import FlowSettings

__all__ = ["dense_flow_numpy"]

PARALLEL_PIXELS = 48 * 48  # smaller pyramid levels run on one thread



@numba.njit(cache=True, nogil=True, inline="always")
def _clamp(i: int, n: int) -> int:
    return 0 if i < 0 else (n - 1 if i > n - 1 else i)


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _gradients(img: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> None:
    # 5-point central differences (1, -8, 0, 8, -1) / 12, replicate borders
    h, w = img.shape
    c = np.float32(1.0 / 12.0)
    for y in numba.prange(h):
        for x in range(w):
            gx[y, x] = (img[y, _clamp(x - 2, w)] - np.float32(8.0) * img[y, _clamp(x - 1, w)]
                        + np.float32(8.0) * img[y, _clamp(x + 1, w)] - img[y, _clamp(x + 2, w)]) * c
            gy[y, x] = (img[_clamp(y - 2, h), x] - np.float32(8.0) * img[_clamp(y - 1, h), x]
                        + np.float32(8.0) * img[_clamp(y + 1, h), x] - img[_clamp(y + 2, h), x]) * c


@numba.njit(cache=True, nogil=True, inline="always", fastmath=True)
def _bilinear(img: np.ndarray, px: float, py: float) -> float:
    # img sampled bilinearly at (px, py), px, py >= 0 (truncation is the floor); indices clamped
    h, w = img.shape
    x0 = min(int(px), w - 1)
    y0 = min(int(py), h - 1)
    x1 = min(x0 + 1, w - 1)
    y1 = min(y0 + 1, h - 1)
    fx = px - x0
    fy = py - y0
    top = img[y0, x0] * (np.float32(1.0) - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (np.float32(1.0) - fx) + img[y1, x1] * fx
    return top * (np.float32(1.0) - fy) + bottom * fy


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _warp(img: np.ndarray, u: np.ndarray, v: np.ndarray, out: np.ndarray, inside: np.ndarray) -> None:
    # bilinear sample at p + flow, positions clamped to the image (grid_sample border, align_corners)
    h, w = img.shape
    for y in numba.prange(h):
        for x in range(w):
            px = x + u[y, x]
            py = y + v[y, x]
            inside[y, x] = np.float32(1.0) if (0.0 <= px <= w - 1 and 0.0 <= py <= h - 1) else np.float32(0.0)
            out[y, x] = _bilinear(img, min(max(px, np.float32(0.0)), np.float32(w - 1)),
                                  min(max(py, np.float32(0.0)), np.float32(h - 1)))


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _linearize(a1: np.ndarray, a2: np.ndarray, gx1: np.ndarray, gy1: np.ndarray, u: np.ndarray, v: np.ndarray,
               alpha: float, eps: float, work: np.ndarray) -> None:
    """A warp's linearization about (u, v): the Jacobi coefficients ix, iy, su, sv, const into
    `work[4:9]` (`work` (9, H, W) float32 scratch)."""
    h, w = a1.shape
    warped, inside, gx2, gy2, ix, iy, su, sv, const = (work[0], work[1], work[2], work[3], work[4], work[5],
                                                       work[6], work[7], work[8])
    _warp(a2, u, v, warped, inside)
    _gradients(warped, gx2, gy2)
    e = np.float32(eps)
    a2_ = np.float32(alpha) * np.float32(alpha)
    for y in numba.prange(h):
        for x in range(w):
            gxx = np.float32(0.5) * (gx1[y, x] + gx2[y, x])
            gyy = np.float32(0.5) * (gy1[y, x] + gy2[y, x])
            it = warped[y, x] - a1[y, x]
            weight = inside[y, x] * e / np.sqrt(it * it + e * e)
            s = weight / (a2_ + weight * (gxx * gxx + gyy * gyy))
            ix[y, x] = gxx
            iy[y, x] = gyy
            su[y, x] = gxx * s
            sv[y, x] = gyy * s
            const[y, x] = it - (gxx * u[y, x] + gyy * v[y, x])


@numba.njit(cache=True, nogil=True, inline="always", fastmath=True)
def _sweep_row(pu: np.ndarray, pv: np.ndarray, qu: np.ndarray, qv: np.ndarray, j: int, y: int, ix: np.ndarray,
               iy: np.ndarray, su: np.ndarray, sv: np.ndarray, const: np.ndarray, omega: float,
               gamma: float) -> None:
    # one Chebyshev-accelerated Jacobi update of image row y, held in row j of the column-padded
    # buffers p (current iterate) and q (the previous one on entry, the new one on exit):
    # q <- omega (gamma J(p) + (1 - gamma) p - q) + q, J the plain Jacobi update
    w = ix.shape[1]
    k = np.float32(1.0 / 12.0)
    two, four = np.float32(2.0), np.float32(4.0)
    om, ga, keep = np.float32(omega), np.float32(gamma), np.float32(1.0 - gamma)
    for x in range(w):
        # 8-neighbour average: ([1 2 1]^T [1 2 1] - 4 delta) / 12
        au = ((pu[j - 1, x] + two * pu[j - 1, x + 1] + pu[j - 1, x + 2])
              + two * (pu[j, x] + two * pu[j, x + 1] + pu[j, x + 2])
              + (pu[j + 1, x] + two * pu[j + 1, x + 1] + pu[j + 1, x + 2]) - four * pu[j, x + 1]) * k
        av = ((pv[j - 1, x] + two * pv[j - 1, x + 1] + pv[j - 1, x + 2])
              + two * (pv[j, x] + two * pv[j, x + 1] + pv[j, x + 2])
              + (pv[j + 1, x] + two * pv[j + 1, x + 1] + pv[j + 1, x + 2]) - four * pv[j, x + 1]) * k
        r = ix[y, x] * au + iy[y, x] * av + const[y, x]
        ju = ga * (au - su[y, x] * r) + keep * pu[j, x + 1]
        jv = ga * (av - sv[y, x] * r) + keep * pv[j, x + 1]
        qu[j, x + 1] = om * (ju - qu[j, x + 1]) + qu[j, x + 1]
        qv[j, x + 1] = om * (jv - qv[j, x + 1]) + qv[j, x + 1]
    qu[j, 0], qu[j, w + 1] = qu[j, 1], qu[j, w]
    qv[j, 0], qv[j, w + 1] = qv[j, 1], qv[j, w]


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _jacobi_block(u: np.ndarray, v: np.ndarray, prev_u: np.ndarray, prev_v: np.ndarray, out_u: np.ndarray,
                  out_v: np.ndarray, out_prev_u: np.ndarray, out_prev_v: np.ndarray, ix: np.ndarray,
                  iy: np.ndarray, su: np.ndarray, sv: np.ndarray, const: np.ndarray, omegas: np.ndarray,
                  gamma: float, strips: int, first: bool, last: bool) -> None:
    """`len(omegas)` accelerated Jacobi sweeps from the iterates (u, v) (current) and (prev_u,
    prev_v) (previous; not read when `first`: the first sweep's previous iterate is the start)
    into (out_u, out_v) and (out_prev_u, out_prev_v) (not written when `last`), in `strips` row
    strips at once (`_sweep_row`; `omegas[s]` the extrapolation of sweep s).

    Each strip copies its rows and `sweeps - 1` rows either side (replicate borders at the
    image's edges), sweeps them locally and keeps its own rows: the halo rows go stale one row
    a sweep, so the kept rows are exactly the global sweeps' (the same arithmetic, any strip
    count), for one parallel launch per `sweeps` sweeps instead of one per sweep.
    """
    h, w = u.shape
    sweeps = omegas.shape[0]
    for strip in numba.prange(strips):
        r0, r1 = strip * h // strips, (strip + 1) * h // strips
        lo, hi = max(r0 - (sweeps - 1), 0), min(r1 + (sweeps - 1), h)
        n = hi - lo
        pu = np.empty((n + 2, w + 2), np.float32)
        pv = np.empty((n + 2, w + 2), np.float32)
        qu = np.empty((n + 2, w + 2), np.float32)
        qv = np.empty((n + 2, w + 2), np.float32)
        for j in range(n + 2):
            y = min(max(lo - 1 + j, 0), h - 1)
            for x in range(w):
                pu[j, x + 1] = u[y, x]
                pv[j, x + 1] = v[y, x]
            if first:
                for x in range(w):
                    qu[j, x + 1] = u[y, x]
                    qv[j, x + 1] = v[y, x]
            else:
                for x in range(w):
                    qu[j, x + 1] = prev_u[y, x]
                    qv[j, x + 1] = prev_v[y, x]
            pu[j, 0], pu[j, w + 1] = u[y, 0], u[y, w - 1]
            pv[j, 0], pv[j, w + 1] = v[y, 0], v[y, w - 1]
        for s in range(sweeps):
            for j in range(1, n + 1):
                _sweep_row(pu, pv, qu, qv, j, lo - 1 + j, ix, iy, su, sv, const, omegas[s], gamma)
            if lo == 0:  # replicate the image's top and bottom rows
                qu[0], qv[0] = qu[1], qv[1]
            if hi == h:
                qu[n + 1], qv[n + 1] = qu[n], qv[n]
            pu, qu = qu, pu
            pv, qv = qv, pv
        for y in range(r0, r1):
            for x in range(w):
                out_u[y, x] = pu[y - lo + 1, x + 1]
                out_v[y, x] = pv[y - lo + 1, x + 1]
            if not last:
                for x in range(w):
                    out_prev_u[y, x] = qu[y - lo + 1, x + 1]
                    out_prev_v[y, x] = qv[y - lo + 1, x + 1]


def _jacobi(u: np.ndarray, v: np.ndarray, ix: np.ndarray, iy: np.ndarray, su: np.ndarray, sv: np.ndarray,
            const: np.ndarray, iterations: int, acceleration: float, scratch: np.ndarray) -> None:
    """`iterations` Chebyshev-accelerated Jacobi sweeps of the linearized Euler-Lagrange
    equations (in place; `dense.chebyshev_weights`).

    Blocks of sweeps per parallel launch (`_jacobi_block`), over as many row strips as numba
    has threads; blocks short enough that the strips' halos stay a small part of their rows.
    `scratch` (6, H, W) float32.
    """
    from .dense import chebyshev_weights

    h = u.shape[0]
    omegas, gamma = chebyshev_weights(iterations, acceleration, *(() if acceleration else (0.0,)))
    omegas = np.asarray(omegas, np.float32)
    strips = numba.get_num_threads()
    block = iterations if strips == 1 else max(1, min(iterations, h // (8 * strips)))
    cur_u, cur_v, prev_u, prev_v = u, v, scratch[0], scratch[1]
    free = [scratch[2], scratch[3], scratch[4], scratch[5]]
    done = 0
    while done < iterations:
        k = min(block, iterations - done)
        nu, nv, npu, npv = free
        _jacobi_block(cur_u, cur_v, prev_u, prev_v, nu, nv, npu, npv, ix, iy, su, sv, const,
                      omegas[done:done + k], gamma, strips, done == 0, done + k == iterations)
        free = [cur_u, cur_v, prev_u, prev_v]
        cur_u, cur_v, prev_u, prev_v = nu, nv, npu, npv
        done += k
    if cur_u is not u:
        u[:] = cur_u
        v[:] = cur_v


@numba.njit(cache=True, nogil=True)
def _median3(f: np.ndarray, t: np.ndarray) -> None:
    # separable 3x3 median: median of 3 along x, then along y, replicate borders (in place; t scratch)
    h, w = f.shape
    for y in range(h):
        for x in range(w):
            a, b, c = f[y, _clamp(x - 1, w)], f[y, x], f[y, _clamp(x + 1, w)]
            t[y, x] = max(min(a, b), min(max(a, b), c))
    for y in range(h):
        for x in range(w):
            a, b, c = t[_clamp(y - 1, h), x], t[y, x], t[_clamp(y + 1, h), x]
            f[y, x] = max(min(a, b), min(max(a, b), c))


@numba.njit(cache=True, nogil=True, fastmath=True)
def _blur_down(img: np.ndarray) -> np.ndarray:
    # 5-tap binomial (1 4 6 4 1) / 16 along x and y, replicate borders, every second pixel
    h, w = img.shape
    t = np.empty((h, (w + 1) // 2), np.float32)
    for y in range(h):
        for j in range(t.shape[1]):
            x = 2 * j
            t[y, j] = (img[y, _clamp(x - 2, w)] + np.float32(4.0) * img[y, _clamp(x - 1, w)]
                       + np.float32(6.0) * img[y, x] + np.float32(4.0) * img[y, _clamp(x + 1, w)]
                       + img[y, _clamp(x + 2, w)]) * np.float32(1.0 / 16.0)
    out = np.empty(((h + 1) // 2, t.shape[1]), np.float32)
    for i in range(out.shape[0]):
        y = 2 * i
        for j in range(t.shape[1]):
            out[i, j] = (t[_clamp(y - 2, h), j] + np.float32(4.0) * t[_clamp(y - 1, h), j]
                         + np.float32(6.0) * t[y, j] + np.float32(4.0) * t[_clamp(y + 1, h), j]
                         + t[_clamp(y + 2, h), j]) * np.float32(1.0 / 16.0)
    return out


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _upsample(f: np.ndarray, out: np.ndarray, factor: float) -> None:
    # bilinear resize of f into out (torch's interpolate, align_corners=False), times `factor`
    h, w = f.shape
    oh, ow = out.shape
    sy, sx = np.float32(h / oh), np.float32(w / ow)
    c = np.float32(factor)
    for i in numba.prange(oh):
        py = max((i + np.float32(0.5)) * sy - np.float32(0.5), np.float32(0.0))
        for j in range(ow):
            px = max((j + np.float32(0.5)) * sx - np.float32(0.5), np.float32(0.0))
            out[i, j] = _bilinear(f, px, py) * c


@numba.njit(cache=True, nogil=True, fastmath=True)
def _luminance(img: np.ndarray) -> np.ndarray:
    # (C, H, W) -> (H, W): Rec. 709 luma for C = 3, the channel mean otherwise (`dense.luminance`)
    c, h, w = img.shape
    out = np.zeros((h, w), np.float32)
    for k in range(c):
        wk = np.float32(1.0 / c)
        if c == 3:
            wk = np.float32((0.2126, 0.7152, 0.0722)[k])
        for y in range(h):
            for x in range(w):
                out[y, x] += wk * img[k, y, x]
    return out


@numba.njit(cache=True, nogil=True, fastmath=True)
def _normalize_pair(i1: np.ndarray, i2: np.ndarray) -> None:
    # the pair's common contrast normalization of `dense_flow`: (I - mean) / (mean abs deviation) / 4
    n = i1.size
    a, b = i1.ravel(), i2.ravel()
    total = 0.0  # float64 sums
    for k in range(n):
        total += a[k] + b[k]
    mean = np.float32(total / (2 * n))
    dev = 0.0
    for k in range(n):
        dev += abs(a[k] - mean) + abs(b[k] - mean)
    scale = np.float32(4.0) * max(np.float32(dev / (2 * n)), np.float32(1e-6))
    for k in range(n):
        a[k] = (a[k] - mean) / scale
        b[k] = (b[k] - mean) / scale


def _resize_flow(u: np.ndarray, v: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    # `dense.upsample_flow` on the two components
    if u.shape == (h, w):
        return u, v
    uu, vv = np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    _upsample(u, uu, w / u.shape[1])
    _upsample(v, vv, h / u.shape[0])
    return uu, vv


def dense_flow_numpy(image1, image2, settings: FlowSettings = FlowSettings()) -> np.ndarray:
    """`dense_flow` (same arguments, torch tensors (1, C, H, W) on the CPU) without gradients.

    Returns:
        (2, H, W) float32 flow, pixels (x right, y down).
    """
    from .dense import _iterations_at, _warps_at

    if image1.ndim != 4 or image1.shape != image2.shape or image1.shape[0] != 1:
        raise ValueError(f"image1, image2: expected two (1, C, H, W) tensors of one shape, found "
                         f"{tuple(image1.shape)} and {tuple(image2.shape)}")
    s = settings
    i1 = _luminance(np.ascontiguousarray(image1[0].detach().float().numpy()))
    i2 = _luminance(np.ascontiguousarray(image2[0].detach().float().numpy()))
    _normalize_pair(i1, i2)
    pyr1, pyr2 = [i1], [i2]
    while len(pyr1) < s.levels and min(pyr1[-1].shape) // 2 >= s.min_size:
        pyr1.append(_blur_down(pyr1[-1]))
        pyr2.append(_blur_down(pyr2[-1]))
    levels = len(pyr1)
    work_buffer = np.empty(9 * i1.size, np.float32)
    scratch_buffer = np.empty(6 * i1.size, np.float32)
    u = v = None
    last = min(max(s.skip_levels, 0), levels - 1)
    threads = numba.get_num_threads()
    try:
        for level in range(levels - 1, last - 1, -1):
            a1, a2 = pyr1[level], pyr2[level]
            h, w = a1.shape
            # numba's threads only where a sweep outweighs their start (~20 us per parallel loop)
            numba.set_num_threads(threads if h * w >= PARALLEL_PIXELS else 1)
            if u is None:
                u, v = np.zeros((h, w), np.float32), np.zeros((h, w), np.float32)
            else:
                u, v = _resize_flow(u, v, h, w)
            gx1, gy1 = np.empty_like(a1), np.empty_like(a1)
            work = work_buffer[:9 * h * w].reshape(9, h, w)  # one buffer for every level: no fresh pages
            scratch = scratch_buffer[:6 * h * w].reshape(6, h, w)
            iters = _iterations_at(level, levels, s)
            _gradients(a1, gx1, gy1)
            for _ in range(_warps_at(level, h * w, s)):
                _linearize(a1, a2, gx1, gy1, u, v, s.alpha, s.eps, work)
                _jacobi(u, v, work[4], work[5], work[6], work[7], work[8], iters, s.acceleration, scratch)
                if s.median and s.median_every_warp:
                    _median3(u, work[0])
                    _median3(v, work[0])
            if s.median and not s.median_every_warp:
                _median3(u, work[0])
                _median3(v, work[0])
        numba.set_num_threads(threads)
        u, v = _resize_flow(u, v, *i1.shape)
    finally:
        numba.set_num_threads(threads)
    return np.stack([u, v])
