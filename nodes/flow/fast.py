"""The forward pass of `nodes.flow.dense.dense_flow`, compiled: the same model, counts and
arithmetic (float32, summed in another order: results agree to about 1e-4 px on average,
1e-2 px at worst near silhouettes), as numba kernels (row-parallel
over numba's threads) per warp instead of thousands of small torch operations per pair (256^2,
2 cores: 12 ms against 125 ms). For plate flow, where no gradient is needed (`flow.OpticalFlow` on the CPU); the
torch version stays the differentiable one. Agreement: tests/nodes/flow/test_fast_flow.py.

This module imports numba at the top (kernels cached on disk): import it from node `run()`
methods only.
"""

from __future__ import annotations

import numba
import numpy as np

from .dense import FlowSettings

__all__ = ["dense_flow_numpy"]



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


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _warp(img: np.ndarray, u: np.ndarray, v: np.ndarray, out: np.ndarray, inside: np.ndarray) -> None:
    # bilinear sample at p + flow, positions clamped to the image (grid_sample border, align_corners)
    h, w = img.shape
    for y in numba.prange(h):
        for x in range(w):
            px = x + u[y, x]
            py = y + v[y, x]
            inside[y, x] = np.float32(1.0) if (0.0 <= px <= w - 1 and 0.0 <= py <= h - 1) else np.float32(0.0)
            px = min(max(px, np.float32(0.0)), np.float32(w - 1))
            py = min(max(py, np.float32(0.0)), np.float32(h - 1))
            x0 = min(int(px), w - 1)  # px, py >= 0 here: truncation is the floor
            y0 = min(int(py), h - 1)
            x1 = min(x0 + 1, w - 1)
            y1 = min(y0 + 1, h - 1)
            fx = px - x0
            fy = py - y0
            top = img[y0, x0] * (np.float32(1.0) - fx) + img[y0, x1] * fx
            bottom = img[y1, x0] * (np.float32(1.0) - fx) + img[y1, x1] * fx
            out[y, x] = top * (np.float32(1.0) - fy) + bottom * fy


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _warp_solve(a1: np.ndarray, a2: np.ndarray, gx1: np.ndarray, gy1: np.ndarray, u: np.ndarray, v: np.ndarray,
                alpha: float, eps: float, iterations: int) -> None:
    """One warp: linearize about (u, v), then `iterations` Jacobi sweeps (in place)."""
    h, w = a1.shape
    warped = np.empty_like(a1)
    inside = np.empty_like(a1)
    gx2 = np.empty_like(a1)
    gy2 = np.empty_like(a1)
    _warp(a2, u, v, warped, inside)
    _gradients(warped, gx2, gy2)
    ix = np.empty_like(a1)
    iy = np.empty_like(a1)
    su = np.empty_like(a1)
    sv = np.empty_like(a1)
    const = np.empty_like(a1)
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
    _jacobi(u, v, ix, iy, su, sv, const, iterations)


@numba.njit(cache=True, nogil=True)
def _pad_edges(p: np.ndarray) -> None:
    # replicate the interior's border into the one-pixel frame of a padded (H + 2, W + 2) array
    h, w = p.shape[0] - 2, p.shape[1] - 2
    for y in range(1, h + 1):
        p[y, 0] = p[y, 1]
        p[y, w + 1] = p[y, w]
    for x in range(w + 2):
        p[0, x] = p[1, x]
        p[h + 1, x] = p[h, x]


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _jacobi(u: np.ndarray, v: np.ndarray, ix: np.ndarray, iy: np.ndarray, su: np.ndarray, sv: np.ndarray,
            const: np.ndarray, iterations: int) -> None:
    """`iterations` Jacobi sweeps of the linearized Euler-Lagrange equations (in place).

    The flow lives in padded arrays whose frame is refreshed from the border every sweep
    (replicate borders, as `_neighbour_average`), so the stencil loop has no branches.
    """
    h, w = u.shape
    pu = np.empty((h + 2, w + 2), np.float32)
    pv = np.empty((h + 2, w + 2), np.float32)
    qu = np.empty((h + 2, w + 2), np.float32)
    qv = np.empty((h + 2, w + 2), np.float32)
    pu[1:h + 1, 1:w + 1] = u
    pv[1:h + 1, 1:w + 1] = v
    k = np.float32(1.0 / 12.0)
    two, four = np.float32(2.0), np.float32(4.0)
    for _ in range(iterations):
        _pad_edges(pu)
        _pad_edges(pv)
        for y in numba.prange(h):
            for x in range(w):
                # 8-neighbour average: ([1 2 1]^T [1 2 1] - 4 delta) / 12
                au = ((pu[y, x] + two * pu[y, x + 1] + pu[y, x + 2])
                      + two * (pu[y + 1, x] + two * pu[y + 1, x + 1] + pu[y + 1, x + 2])
                      + (pu[y + 2, x] + two * pu[y + 2, x + 1] + pu[y + 2, x + 2]) - four * pu[y + 1, x + 1]) * k
                av = ((pv[y, x] + two * pv[y, x + 1] + pv[y, x + 2])
                      + two * (pv[y + 1, x] + two * pv[y + 1, x + 1] + pv[y + 1, x + 2])
                      + (pv[y + 2, x] + two * pv[y + 2, x + 1] + pv[y + 2, x + 2]) - four * pv[y + 1, x + 1]) * k
                r = ix[y, x] * au + iy[y, x] * av + const[y, x]
                qu[y + 1, x + 1] = au - su[y, x] * r
                qv[y + 1, x + 1] = av - sv[y, x] * r
        pu, qu = qu, pu
        pv, qv = qv, pv
    u[:, :] = pu[1:h + 1, 1:w + 1]
    v[:, :] = pv[1:h + 1, 1:w + 1]




@numba.njit(cache=True, nogil=True)
def _median3(f: np.ndarray) -> None:
    # separable 3x3 median: median of 3 along x, then along y, replicate borders (in place)
    h, w = f.shape
    t = np.empty_like(f)
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


def dense_flow_numpy(image1, image2, settings: FlowSettings = FlowSettings()) -> np.ndarray:
    """`dense_flow` (same arguments, torch tensors (1, C, H, W) on the CPU) without gradients.

    Returns:
        (2, H, W) float32 flow, pixels (x right, y down).
    """
    import torch

    from .dense import _iterations_at, luminance, upsample_flow

    if image1.ndim != 4 or image1.shape != image2.shape or image1.shape[0] != 1:
        raise ValueError(f"image1, image2: expected two (1, C, H, W) tensors of one shape, found "
                         f"{tuple(image1.shape)} and {tuple(image2.shape)}")
    s = settings
    with torch.no_grad():
        i1 = luminance(image1.float())[0, 0].numpy().astype(np.float32)
        i2 = luminance(image2.float())[0, 0].numpy().astype(np.float32)
        mean = np.float32(0.5) * (i1.mean(dtype=np.float32) + i2.mean(dtype=np.float32))
        scale = max(np.float32(0.5) * (np.abs(i1 - mean).mean(dtype=np.float32)
                                       + np.abs(i2 - mean).mean(dtype=np.float32)), np.float32(1e-6))
        i1 = ((i1 - mean) / scale * np.float32(0.25)).astype(np.float32)
        i2 = ((i2 - mean) / scale * np.float32(0.25)).astype(np.float32)
        pyr1, pyr2 = [i1], [i2]
        while len(pyr1) < s.levels and min(pyr1[-1].shape) // 2 >= s.min_size:
            pyr1.append(_blur_down(pyr1[-1]))
            pyr2.append(_blur_down(pyr2[-1]))
        levels = len(pyr1)
        flow = None
        last = min(max(s.skip_levels, 0), levels - 1)
        for level in range(levels - 1, last - 1, -1):
            a1, a2 = pyr1[level], pyr2[level]
            h, w = a1.shape
            if flow is None:
                flow = torch.zeros(1, 2, h, w)
            else:
                flow = upsample_flow(flow, (h, w))
            u = np.ascontiguousarray(flow[0, 0].numpy())
            v = np.ascontiguousarray(flow[0, 1].numpy())
            gx1, gy1 = np.empty_like(a1), np.empty_like(a1)
            _gradients(a1, gx1, gy1)
            iters = _iterations_at(level, levels, s)
            for _ in range(s.warps):
                _warp_solve(a1, a2, gx1, gy1, u, v, s.alpha, s.eps, iters)
                if s.median and s.median_every_warp:
                    _median3(u)
                    _median3(v)
            if s.median and not s.median_every_warp:
                _median3(u)
                _median3(v)
            flow = torch.as_tensor(np.stack([u, v]))[None]
        flow = upsample_flow(flow, image1.shape[-2:])
    return flow[0].numpy()
