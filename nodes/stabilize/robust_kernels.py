"""CPU kernels (numba) of the robust per-frame alignment and the stillness test of `robust.py`.

The torch versions in `robust.py` make one pass over the (F, 3, V) points per elementwise
operation (transform, subtract, square, sum, sqrt, quartile, weights, normalised weights,
weighted points, cross-covariance: about ten full-size temporaries per IRLS step). Here one
step is one pass per frame: each frame's distances, lower quartile, IRLS weights and the
weighted moments that Kabsch needs are computed together, with float64 accumulators. The
3x3 SVDs stay in torch (`robust.kabsch_from_moments`).

Frames are independent and each is computed by one thread from start to end, so the result
is the same bit for bit on any thread count. Against the torch path (float32 sums in another
order) rotations agree to about 1e-7 rad.

This module imports numba at the top (kernels cached on disk, `cache=True`); `robust.py`
imports it only when a CPU tensor needs it.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["MOMENTS", "irls_moments", "window_mean_square", "local_window_still", "gather_normalized"]

MOMENTS = 16
"""Per-frame moments: [sum w, sum w x (3), sum w r (3), sum w x r^T (9, row-major)]."""


@numba.njit(cache=True, nogil=True)
def irls_moments(x: np.ndarray, rest: np.ndarray, rot: np.ndarray, trans: np.ndarray, width: float,
                 prior: np.ndarray, rank: int, moments: np.ndarray, weights: np.ndarray) -> None:
    """One IRLS step's weights and Kabsch moments, frame by frame (see `robust.robust_align`).

    Per frame f: distances `d_v = |rot_f x_fv + trans_f - rest_v|`, the frame's width
    `max(width, 3 q_f)` with `q_f` the rank-th smallest distance (1-based), weights
    `c_v psi'(d_v) / d_v` (1 below half the width, `(w - d) / d` up to it, 0 beyond) and their
    moments. A frame whose weights sum to 0 gets the moments of uniform weights (its fit is
    then least squares), as `robust.weighted_kabsch` does.

    Args:
        x: (F, 3, V) float32 points. rest: (3, V) float32 target points.
        rot: (F, 3, 3) float64, trans: (F, 3) float64 current transforms.
        width: w > 0, units of x. prior: (1, V) float32 vertex weights c_v shared by every
            frame, or (F, V) per frame (`c_fv`, e.g. 0 where a vertex moves in that frame).
        rank: 1-based rank of the quartile (V // 4, at least 1).
        moments: (F, 16) float64 output, see `MOMENTS`.
        weights: (F, V) float32 output of the weights (before the uniform fallback), or a
            (0, V) array to skip writing them.
    """
    num_frames = x.shape[0]
    num_vertices = x.shape[2]
    write = weights.shape[0] == num_frames
    for f in range(num_frames):
        r00, r01, r02 = rot[f, 0, 0], rot[f, 0, 1], rot[f, 0, 2]
        r10, r11, r12 = rot[f, 1, 0], rot[f, 1, 1], rot[f, 1, 2]
        r20, r21, r22 = rot[f, 2, 0], rot[f, 2, 1], rot[f, 2, 2]
        t0, t1, t2 = trans[f, 0], trans[f, 1], trans[f, 2]
        xa, xb, xc = x[f, 0], x[f, 1], x[f, 2]
        ra, rb, rc = rest[0], rest[1], rest[2]
        cv = prior[f] if prior.shape[0] == num_frames else prior[0]
        dist = np.empty(num_vertices, np.float64)
        near = 0
        for v in range(num_vertices):
            a, b, c = np.float64(xa[v]), np.float64(xb[v]), np.float64(xc[v])
            e0 = r00 * a + r01 * b + r02 * c + t0 - ra[v]
            e1 = r10 * a + r11 * b + r12 * c + t1 - rb[v]
            e2 = r20 * a + r21 * b + r22 * c + t2 - rc[v]
            d = np.sqrt(e0 * e0 + e1 * e1 + e2 * e2)
            dist[v] = d
            near += 3.0 * d <= width
        frame_width = width
        if near < rank:  # the quartile q has 3 q > width: find it (a selection, O(V))
            frame_width = 3.0 * np.partition(dist, rank - 1)[rank - 1]
        inv_width = 1.0 / frame_width
        uniform = False
        for attempt in range(2):
            sw = sa = sb = sc = sp = sq = ss = 0.0
            m00 = m01 = m02 = m10 = m11 = m12 = m20 = m21 = m22 = 0.0
            for v in range(num_vertices):
                if uniform:
                    w = 1.0
                else:
                    u = dist[v] * inv_width
                    w = (1.0 if u < 0.5 else max(1.0 - u, 0.0) / u) * cv[v]
                    if write:
                        weights[f, v] = w
                    if w == 0.0:
                        continue
                a, b, c = np.float64(xa[v]), np.float64(xb[v]), np.float64(xc[v])
                p, q, s = np.float64(ra[v]), np.float64(rb[v]), np.float64(rc[v])
                wa, wb, wc = w * a, w * b, w * c
                sw += w
                sa += wa
                sb += wb
                sc += wc
                sp += w * p
                sq += w * q
                ss += w * s
                m00 += wa * p
                m01 += wa * q
                m02 += wa * s
                m10 += wb * p
                m11 += wb * q
                m12 += wb * s
                m20 += wc * p
                m21 += wc * q
                m22 += wc * s
            if sw > 0.0:
                break
            uniform = True
        out = moments[f]
        out[0], out[1], out[2], out[3] = sw, sa, sb, sc
        out[4], out[5], out[6] = sp, sq, ss
        out[7], out[8], out[9] = m00, m01, m02
        out[10], out[11], out[12] = m10, m11, m12
        out[13], out[14], out[15] = m20, m21, m22


@numba.njit(cache=True, nogil=True)
def window_mean_square(stab: np.ndarray, centre: np.ndarray, window: int, out: np.ndarray) -> None:
    """Mean over windows of the squared window-mean residual (see `robust.still_vertices`).

    For each vertex v: `out_v = mean_f sum_c (1/k sum_{j<k} (stab_{f+j,c,v} - centre_{c,v}))^2`
    over the F - k + 1 windows of k = `window` consecutive frames; running sums in float64.

    Args:
        stab: (F, 3, V) float32 stabilized points. centre: (3, V) float32 per-vertex centre.
        window: k, 1 <= k <= F. out: (V,) float64 output.
    """
    num_frames = stab.shape[0]
    num_vertices = stab.shape[2]
    block = 256
    count = num_frames - window + 1
    for start in range((num_vertices + block - 1) // block):
        lo = start * block
        hi = min(num_vertices, lo + block)
        n = hi - lo
        run = np.zeros((3, n), np.float64)
        total = np.zeros(n, np.float64)
        for f in range(num_frames):
            for c in range(3):
                for i in range(n):
                    run[c, i] += stab[f, c, lo + i] - centre[c, lo + i]
                    if f >= window:
                        run[c, i] -= stab[f - window, c, lo + i] - centre[c, lo + i]
            if f >= window - 1:
                for i in range(n):
                    total[i] += (run[0, i] * run[0, i] + run[1, i] * run[1, i] + run[2, i] * run[2, i])
        for i in range(n):
            out[lo + i] = total[i] / (window * window) / count


@numba.njit(cache=True, nogil=True)
def local_window_still(residual: np.ndarray, half_window: int, threshold: float, out: np.ndarray) -> None:
    """Which vertices are at their rest around each frame (see `robust.locally_still`).

    For each frame f and vertex v: the mean `m_fv` of the residual over the frames
    `max(0, f - h) .. min(F - 1, f + h)` (n_f of them, h = `half_window`), and
    `out_fv = 1` when `n_f |m_fv|^2 < threshold`, else 0; running sums in float64.

    Args:
        residual: (F, 3, V) float32 stabilized points minus their rest.
        half_window: h >= 0 (frames). threshold: in squared units of the residual.
        out: (F, V) float32 output.
    """
    num_frames = residual.shape[0]
    num_vertices = residual.shape[2]
    block = 256
    for start in range((num_vertices + block - 1) // block):
        lo = start * block
        hi = min(num_vertices, lo + block)
        n = hi - lo
        run = np.zeros((3, n), np.float64)
        for f in range(min(half_window, num_frames)):      # frames 0 .. h - 1 enter first
            for c in range(3):
                for i in range(n):
                    run[c, i] += residual[f, c, lo + i]
        for f in range(num_frames):
            enter, leave = f + half_window, f - half_window - 1
            if enter < num_frames:
                for c in range(3):
                    for i in range(n):
                        run[c, i] += residual[enter, c, lo + i]
            if leave >= 0:
                for c in range(3):
                    for i in range(n):
                        run[c, i] -= residual[leave, c, lo + i]
            count = min(num_frames - 1, f + half_window) - max(0, f - half_window) + 1
            for i in range(n):
                square = run[0, i] * run[0, i] + run[1, i] * run[1, i] + run[2, i] * run[2, i]
                out[f, lo + i] = 1.0 if square < threshold * count else 0.0


@numba.njit(cache=True, nogil=True)
def gather_normalized(vertices: np.ndarray, ids: np.ndarray, centre: np.ndarray, scale: float,
                      out: np.ndarray) -> None:
    """out[f, c, n] = (vertices[f, ids[n], c] - centre[c]) / scale, coordinates first.

    Args:
        vertices: (F, V, 3) float32 or float64. ids: (N,) int64 vertex indices.
        centre: (3,) float64. scale: > 0. out: (F, 3, N) float32 output.
    """
    for f in range(vertices.shape[0]):
        for n in range(ids.shape[0]):
            i = ids[n]
            out[f, 0, n] = (vertices[f, i, 0] - centre[0]) / scale
            out[f, 1, n] = (vertices[f, i, 1] - centre[1]) / scale
            out[f, 2, n] = (vertices[f, i, 2] - centre[2]) / scale
