"""The discrete half of the rasterizer: which triangle covers which pixel (numba, no gradients).

`rasterize_triangles` z-buffers triangles given in screen space and returns, per pixel, the
index of the nearest covering triangle and its camera depth. Everything differentiable
(barycentrics, attributes, shading, antialiasing) is computed afterwards in torch from these
indices (`nodes.render.renderer`).

Conventions: pixel origin top-left, x to the right, y down, pixel centres at integer
coordinates (OpenCV, as `nodegraph.types.Camera`). A pixel is covered by a triangle when its
centre lies inside or on the triangle (either winding: no back-face culling). Depth is the
camera-frame z (cm), interpolated perspective-correctly (1 / z is affine in screen space).
Triangles with a corner at z <= `near` are skipped whole (no clipping).

This module imports numba at the top (compiled kernels cached on disk, `cache=True`): import it
from node `run()` methods or torch modules only, never from a package `__init__`.
"""

from __future__ import annotations

import math
import threading

import numba
import numpy as np

from .halves import halves_in_parallel, run_halves

__all__ = ["rasterize_triangles", "covered_pixels", "silhouette_pairs", "WALK_STEPS"]

WALK_STEPS = 8
"""Most triangles `silhouette_pairs` walks across from a pixel centre to a silhouette edge."""

PRUNE_NONE, PRUNE_DISTANCE, PRUNE_MASK = 0, 1, 2
"""How `silhouette_pairs` skips pixel pairs before walking (`_find_pairs`)."""

EDGE_MARGIN = 1e-3
"""Pixels by which `_edge_mask` widens each silhouette edge. Where the walk of `_pairs_kernel` keeps a
pair, the segment between the two centres leaves its triangle through that edge at s = l_o / (l_o -
l_f), l the barycentric opposite the edge at the two centres (float64 cross products of
coordinate differences over twice the area; the third one 1 - l0 - l1). With D the largest
coordinate difference between the triangle's corners and a centre within 2 px of the edge and
L the edge's larger extent (|dx| or |dy|), each l is off by a few 1.1e-16 D^2 / |A| while
l_o - l_f is at least 0.7 L / |A| (the kept edge is more perpendicular than parallel to the pair),
so the crossing is off by under ~10 * 1.1e-16 D^2 / (0.7 L) px. `_edge_mask` requires
L >= EDGE_ROUNDING * D^2, which bounds that by 1.6e-4 px: within the margin."""

EDGE_ROUNDING = 1e-11
"""`_edge_mask` marks a silhouette edge only where L >= EDGE_ROUNDING * D^2 (see EDGE_MARGIN; for
D = 1000 px, L >= 1e-5 px); an image with an edge below that (or a non-finite one) is walked
without the masks."""



@numba.njit(cache=True, nogil=True)
def _raster_kernel(pix, depth, faces, near, tri_out, z_out, row_lo, row_hi):  # pragma: no cover - compiled
    """Rows row_lo..row_hi - 1 of every image (a band: two bands write disjoint rows)."""
    batch, height, width = tri_out.shape
    for b in range(batch):
        for t in range(faces.shape[0]):
            i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
            x0, y0 = pix[b, i0, 0], pix[b, i0, 1]
            x1, y1 = pix[b, i1, 0], pix[b, i1, 1]
            x2, y2 = pix[b, i2, 0], pix[b, i2, 1]
            xa = min(x0, min(x1, x2))
            xb = max(x0, max(x1, x2))
            ya = min(y0, min(y1, y2))
            yb = max(y0, max(y1, y2))
            # no pixel centre in the box (most triangles of a dense mesh at this size; NaN too)
            if not (math.ceil(xa) <= math.floor(xb) and math.ceil(ya) <= math.floor(yb)):
                continue
            z0, z1, z2 = depth[b, i0], depth[b, i1], depth[b, i2]
            if not (z0 > near and z1 > near and z2 > near):
                continue
            area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
            if not (area != 0.0 and np.isfinite(area)):
                continue
            if xb < 0.0 or yb < row_lo or xa > width - 1 or ya > row_hi - 1:
                continue
            xmin = max(int(np.ceil(xa)), 0)
            xmax = min(int(np.floor(xb)), width - 1)
            ymin = max(int(np.ceil(ya)), row_lo)
            ymax = min(int(np.floor(yb)), row_hi - 1)
            inv = 1.0 / area
            iz0, iz1, iz2 = 1.0 / z0, 1.0 / z1, 1.0 / z2
            # no point of the triangle is nearer than its nearest corner (1 / z is a convex
            # combination of the corners' 1 / z), less 1e-12 for the rounding of z below
            # (a few float64 ulps): a pixel already showing something at least that near is
            # skipped before its barycentrics (35-45% of the raster's time on the ICT head)
            z_low = min(z0, min(z1, z2)) * (1.0 - 1e-12)
            for py in range(ymin, ymax + 1):
                for px in range(xmin, xmax + 1):
                    if not z_low < z_out[b, py, px]:
                        continue
                    w0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv
                    w1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv
                    w2 = 1.0 - w0 - w1
                    if w0 < 0.0 or w1 < 0.0 or w2 < 0.0:
                        continue
                    z = 1.0 / (w0 * iz0 + w1 * iz1 + w2 * iz2)
                    if z < z_out[b, py, px]:
                        z_out[b, py, px] = z
                        tri_out[b, py, px] = t


def rasterize_triangles(pix: np.ndarray, depth: np.ndarray, faces: np.ndarray, height: int, width: int,
                        near: float = 1e-3, *, triangle_dtype: type = np.int32) -> tuple[np.ndarray, np.ndarray]:
    """Z-buffer triangles in screen space: nearest covering triangle per pixel centre.

    Args:
        pix: (B, V, 2) float, pixel coordinates of the vertices (x right, y down, origin
            top-left, pixel centres at integers).
        depth: (B, V) float, camera-frame z of the vertices, cm (> `near` in front).
        faces: (T, 3) int vertex indices.
        height, width: image size, pixels.
        near: triangles with any corner at z <= near (cm) are skipped.
        triangle_dtype: integer type of the returned triangle indices (np.int64 for the
            renderer, which indexes with them; no conversion afterwards).
    Returns:
        triangle: (B, H, W) `triangle_dtype` (int32 by default), index into `faces` of the
            visible triangle, -1 where none.
        zbuffer: (B, H, W) float64 camera z of the visible surface, cm, +inf where none.
    Raises:
        ValueError: shapes that do not match (named, with the shapes found).

    Example:
        >>> tri, z = rasterize_triangles(np.array([[[0., 0], [3, 0], [0, 3]]]),
        ...                              np.full((1, 3), 5.0), np.array([[0, 1, 2]]), 3, 3)
        >>> tri[0].tolist()
        [[0, 0, 0], [0, 0, 0], [0, 0, -1]]
    """
    pix = np.ascontiguousarray(pix, dtype=np.float64)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    if pix.ndim != 3 or pix.shape[2] != 2:
        raise ValueError(f"pix: expected shape (B, V, 2), found {pix.shape}")
    if depth.shape != pix.shape[:2]:
        raise ValueError(f"depth: expected shape {pix.shape[:2]} (from pix), found {depth.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (T, 3), found {faces.shape}")
    if faces.size and (faces.min() < 0 or faces.max() >= pix.shape[1]):
        raise ValueError(f"faces: expected vertex indices in 0..{pix.shape[1] - 1}, found "
                         f"{int(faces.min())}..{int(faces.max())}")
    tri = np.full((pix.shape[0], height, width), -1, triangle_dtype)
    zbuf = np.full((pix.shape[0], height, width), np.inf, np.float64)
    work = pix.shape[0] * max(height * width, len(faces))
    if faces.size and halves_in_parallel(work):  # two bands of rows, side by side (`halves`)
        half = height // 2
        run_halves(lambda: _raster_kernel(pix, depth, faces, float(near), tri, zbuf, 0, half),
                   lambda: _raster_kernel(pix, depth, faces, float(near), tri, zbuf, half, height), work)
    elif faces.size:  # one pass: each pixel sees the triangles in the same order, so the same bits as
        # the two bands, without setting up every triangle twice (~30% of the raster at 256^2)
        _raster_kernel(pix, depth, faces, float(near), tri, zbuf, 0, height)
    return tri, zbuf


@numba.njit(cache=True, nogil=True)
def _covered_kernel(tri, faces):  # pragma: no cover - compiled
    flat = tri.reshape(-1)
    count = 0
    for p in range(flat.shape[0]):
        if flat[p] >= 0:
            count += 1
    pixels = np.empty(count, np.int64)
    corners = np.empty((count, 3), np.int64)
    n = 0
    for p in range(flat.shape[0]):
        t = flat[p]
        if t >= 0:
            pixels[n] = p
            corners[n, 0], corners[n, 1], corners[n, 2] = faces[t, 0], faces[t, 1], faces[t, 2]
            n += 1
    return pixels, corners


def covered_pixels(triangle: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The covered pixels of a rasterization and their triangles' corners, in one pass.

    Args:
        triangle: (B, H, W) int visible triangle per pixel, -1 none (`rasterize_triangles`).
        faces: (T, 3) int64 vertex indices.
    Returns:
        pixels (N,) int64 flat indices into (B, H, W) of the pixels showing a triangle, ascending
        (`np.flatnonzero(triangle >= 0)`), and corners (N, 3) int64, `faces[triangle.flat[pixels]]`.

    Example:
        >>> pixels, corners = covered_pixels(np.array([[[-1, 1], [0, -1]]]), np.array([[0, 1, 2], [3, 4, 5]]))
        >>> pixels.tolist(), corners.tolist()
        ([1, 2], [[3, 4, 5], [0, 1, 2]])
    """
    return _covered_kernel(np.ascontiguousarray(triangle), np.ascontiguousarray(faces, np.int64))


@numba.njit(cache=True, nogil=True)
def _bary(pix, b, i0, i1, i2, qx, qy, out):  # pragma: no cover - compiled
    x0, y0 = pix[b, i0, 0], pix[b, i0, 1]
    x1, y1 = pix[b, i1, 0], pix[b, i1, 1]
    x2, y2 = pix[b, i2, 0], pix[b, i2, 1]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    if area == 0.0:  # a triangle seen edge-on: no point is inside it
        out[0] = out[1] = out[2] = -1.0
        return area
    out[0] = ((x1 - qx) * (y2 - qy) - (x2 - qx) * (y1 - qy)) / area
    out[1] = ((x2 - qx) * (y0 - qy) - (x0 - qx) * (y2 - qy)) / area
    out[2] = 1.0 - out[0] - out[1]
    return area


@numba.njit(cache=True, nogil=True)
def _reverse_adjacency(adjacency):  # pragma: no cover - compiled
    """CSR lists of the triangles whose `adjacency` names each triangle (start (T + 1,), items)."""
    ntri = adjacency.shape[0]
    start = np.zeros(ntri + 1, np.int64)
    for t in range(ntri):
        for e in range(3):
            if adjacency[t, e] >= 0:
                start[adjacency[t, e] + 1] += 1
    for t in range(ntri):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    items = np.empty(start[ntri], np.int64)
    for t in range(ntri):
        for e in range(3):
            nb = adjacency[t, e]
            if nb >= 0:
                items[fill[nb]] = t
                fill[nb] += 1
    return start, items


@numba.njit(cache=True, nogil=True)
def _facing(pix, b, faces, facing):  # pragma: no cover - compiled
    for t in range(faces.shape[0]):
        i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
        x0, y0 = pix[b, i0, 0], pix[b, i0, 1]
        x1, y1 = pix[b, i1, 0], pix[b, i1, 1]
        x2, y2 = pix[b, i2, 0], pix[b, i2, 1]
        facing[t] = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0) > 0.0


@numba.njit(cache=True, nogil=True)
def _walk_distance(pix, b, faces, adjacency, start, items, steps, facing, dist, queue):  # pragma: no cover
    """Per triangle: which way it faces on screen (signed area > 0, as `_bary`'s area) and
    how many steps across `adjacency` it lies from the nearest triangle with a silhouette
    edge (no neighbour, or a neighbour facing the other way), by a breadth-first search
    backwards along `adjacency` (`start`, `items`: `_reverse_adjacency`); `steps` = farther
    than steps - 1, where the walk of `_pairs_kernel` cannot reach one."""
    ntri = faces.shape[0]
    _facing(pix, b, faces, facing)
    tail = 0
    for t in range(ntri):
        dist[t] = steps
        for e in range(3):
            nb = adjacency[t, e]
            if nb < 0 or facing[nb] != facing[t]:
                dist[t] = 0
                queue[tail] = t
                tail += 1
                break
    head = 0
    while head < tail:  # the walk goes t -> adjacency[t, e]: t is one step farther than its neighbour
        t = queue[head]
        head += 1
        d = dist[t] + 1
        if d >= steps:
            continue
        for j in range(start[t], start[t + 1]):
            p = items[j]
            if dist[p] > d:
                dist[p] = d
                queue[tail] = p
                tail += 1


@numba.njit(cache=True, nogil=True)
def _mark_span(mask, line, lo, hi, first, last):  # pragma: no cover - compiled
    """mask[line, first..last] = True, clipped to the mask (a helper of `_edge_mask`)."""
    n = mask.shape[1]
    if line < 0 or line >= mask.shape[0]:
        return
    for i in range(max(first, 0), min(last, n - 1) + 1):
        mask[line, i] = True


@numba.njit(cache=True, nogil=True)
def _edge_mask(pix, b, faces, adjacency, facing, mask_h, mask_v):  # pragma: no cover - compiled
    """Mark the pixel pairs whose segment passes within EDGE_MARGIN px of a silhouette edge that
    could end the walk of `_pairs_kernel` there: mask_h[y, x] for the pair (x, y)-(x + 1, y) and
    edges steeper than 45 degrees (dy > dx), mask_v[y, x] for (x, y)-(x, y + 1) and the others
    (the walk keeps a pair only for such an edge, crossed between the two centres). `facing`
    must hold image b's (`_facing`). Returns False, with the masks incomplete, when an edge is
    too short or not finite for that margin to bound the walk's rounding (then the caller walks
    without the masks)."""
    m = EDGE_MARGIN
    height, width = mask_h.shape
    for t in range(faces.shape[0]):
        for e in range(3):
            nb = adjacency[t, e]
            if nb >= 0 and facing[nb] == facing[t]:
                continue
            k1 = faces[t, (e + 1) % 3]
            k2 = faces[t, (e + 2) % 3]
            ax, ay = pix[b, k1, 0], pix[b, k1, 1]
            bx, by = pix[b, k2, 0], pix[b, k2, 1]
            dx = abs(pix[b, k2, 0] - pix[b, k1, 0])  # as `_pairs_kernel` computes them
            dy = abs(pix[b, k2, 1] - pix[b, k1, 1])
            if dx != dx or dy != dy:
                continue  # NaN: the walk's orientation test fails for both axes, never kept
            k0 = faces[t, e]
            cx, cy = pix[b, k0, 0], pix[b, k0, 1]
            reach = max(dx, dy) + max(abs(cx - ax), abs(cy - ay)) + 2.0  # bounds D of EDGE_MARGIN
            if not (np.isfinite(reach) and np.isfinite(cx) and np.isfinite(cy)) \
                    or not max(dx, dy) >= EDGE_ROUNDING * reach * reach:
                return False
            if dy > dx:  # horizontal pairs on the rows the edge spans (+- m); per row the edge's x
                # range within y +- m (+- m), and the pairs whose segment [x, x + 1] meets it
                if ay > by:
                    ax, ay, bx, by = bx, by, ax, ay
                slope = (bx - ax) / (by - ay)
                for y in range(int(math.ceil(ay - m)), int(math.floor(by + m)) + 1):
                    if y < 0 or y >= height:
                        continue
                    xa = ax + (max(y - m, ay) - ay) * slope
                    xb = ax + (min(y + m, by) - ay) * slope
                    _mark_span(mask_h, y, 0, 0, int(math.ceil(min(xa, xb) - m)) - 1, int(math.floor(max(xa, xb) + m)))
            else:  # vertical pairs, x and y swapped
                if ax > bx:
                    ax, ay, bx, by = bx, by, ax, ay
                slope = (by - ay) / (bx - ax)
                for x in range(int(math.ceil(ax - m)), int(math.floor(bx + m)) + 1):
                    if x < 0 or x >= width:
                        continue
                    ya = ay + (max(x - m, ax) - ax) * slope
                    yb = ay + (min(x + m, bx) - ax) * slope
                    lo = int(math.ceil(min(ya, yb) - m)) - 1
                    hi = int(math.floor(max(ya, yb) + m))
                    for y in range(max(lo, 0), min(hi, height - 1) + 1):
                        mask_v[y, x] = True
    return True


@numba.njit(cache=True, nogil=True)
def _walk_kernel(pix, b, faces, adjacency, steps, prune, start, items, facing, dist, mask_h,
                 mask_v):  # pragma: no cover - compiled
    """`facing` of image b's triangles and, by `prune`: 2 the pair masks of `_edge_mask` (returns 2,
    or 0 where they cannot be trusted: no pruning), 1 the walk distance `dist` (returns 1), 0
    neither (returns 0). The returned mode is the pruning `_pairs_kernel` applies."""
    if prune == 2:
        _facing(pix, b, faces, facing)
        mask_h[:] = False
        mask_v[:] = False
        return 2 if _edge_mask(pix, b, faces, adjacency, facing, mask_h, mask_v) else 0
    if prune == 1:  # O(triangles): worth it when there are more pixels than triangles
        _walk_distance(pix, b, faces, adjacency, start, items, steps, facing, dist, np.empty(faces.shape[0], np.int64))
        return 1
    _facing(pix, b, faces, facing)
    return 0


@numba.njit(cache=True, nogil=True)
def _pairs_kernel(tri, zbuf, pix, faces, adjacency, steps, prune, start, items, b_lo, b_hi, axis_lo, axis_hi,
                  facing, dist, mask_h, mask_v, walked, occ_out, far_out, tri_out, edge_out):  # pragma: no cover
    """Pairs of images b_lo..b_hi - 1 along axes axis_lo..axis_hi - 1 (0: horizontal pairs, 1:
    vertical), in that order; `walked` >= 0: `facing` and `dist` or the masks already hold image
    b_lo's (`_walk_kernel`, which returned `walked`), else they are computed here per image."""
    batch, height, width = tri.shape
    count = 0
    lo = np.zeros(3)
    lf = np.zeros(3)
    for b in range(b_lo, b_hi):
        mode = walked
        if walked < 0:
            mode = _walk_kernel(pix, b, faces, adjacency, steps, prune, start, items, facing, dist, mask_h, mask_v)
        for axis in range(axis_lo, axis_hi):
            mask = mask_h if axis == 0 else mask_v
            for y in range(height - axis):
                for x in range(width - 1 + axis):
                    y2, x2 = y + axis, x + 1 - axis
                    ta, tb = tri[b, y, x], tri[b, y2, x2]
                    if ta == tb:
                        continue
                    if mode == 2 and not mask[y, x]:
                        continue  # no silhouette edge the walk could end at near this pair
                    if zbuf[b, y, x] < zbuf[b, y2, x2]:
                        oy, ox, fy, fx, t = y, x, y2, x2, ta
                    else:
                        oy, ox, fy, fx, t = y2, x2, y, x, tb
                    if mode == 1 and dist[t] >= steps:
                        continue  # no silhouette edge within the walk's reach: nothing to find
                    own = facing[t]
                    cur = t
                    for _ in range(steps):
                        c0, c1, c2 = faces[cur, 0], faces[cur, 1], faces[cur, 2]
                        _bary(pix, b, c0, c1, c2, ox, oy, lo)
                        _bary(pix, b, c0, c1, c2, fx, fy, lf)
                        best = np.inf
                        edge = -1
                        for i in range(3):
                            if lf[i] < lo[i]:
                                s = lo[i] / (lo[i] - lf[i])
                                if s < best:
                                    best = s
                                    edge = i
                        if edge < 0 or not best < 1.0:
                            break  # the far centre lies in this triangle: no silhouette
                        nb = adjacency[cur, edge]
                        boundary = nb < 0 or facing[nb] != own
                        if boundary:
                            k1 = faces[cur, (edge + 1) % 3]
                            k2 = faces[cur, (edge + 2) % 3]
                            dx = abs(pix[b, k2, 0] - pix[b, k1, 0])
                            dy = abs(pix[b, k2, 1] - pix[b, k1, 1])
                            if (axis == 0 and dy > dx) or (axis == 1 and dx >= dy):
                                if best >= 0.0:
                                    occ_out[count] = (b * height + oy) * width + ox
                                    far_out[count] = (b * height + fy) * width + fx
                                    tri_out[count] = cur
                                    edge_out[count] = edge
                                    count += 1
                            break
                        cur = nb
    return count


def silhouette_pairs(triangle: np.ndarray, zbuffer: np.ndarray, pix: np.ndarray, faces: np.ndarray,
                     adjacency: np.ndarray, steps: int = WALK_STEPS
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Find the silhouette edges between adjacent pixel centres (the discrete half of the
    analytic antialiasing of `nodes.render.renderer`).

    For each horizontally or vertically adjacent pixel pair showing different triangles, the
    pixel with the nearer surface is the occluder. From its triangle, the segment towards the
    other pixel's centre is followed across edges whose neighbour faces the same way in
    screen space (at most `steps` triangles) to the first silhouette edge (no neighbour, or a
    neighbour facing the other way). The pair is kept when that edge is crossed before the
    far centre and is more perpendicular than parallel to the pair (steeper than 45 degrees
    for horizontal pairs, flatter for vertical ones, so every edge is counted once). Before
    walking, each silhouette edge marks the pairs whose segment passes within EDGE_MARGIN px of
    it, steep edges the horizontal pairs, the others the vertical ones (`_edge_mask`: a few
    pairs per row or column it spans), and unmarked pairs are skipped: a kept pair's segment
    crosses its edge, so the same pairs are found (2-4% of the pairs marked on the ICT head at
    256^2, against 8% of them walked with the breadth-first prune used before: 2.9 -> 1.9 ms).
    Where an edge is too short for the margin to bound the walk's rounding (EDGE_ROUNDING), one
    image falls back to that prune (when it has at least as many pixels as triangles: the
    triangles farther than `steps - 1` steps from a silhouette edge are skipped), a batch to none.

    Args:
        triangle: (B, H, W) int visible triangle per pixel, -1 none (`rasterize_triangles`).
        zbuffer: (B, H, W) float camera z, +inf none.
        pix: (B, V, 2) float projected vertices, pixels.
        faces: (T, 3) int; adjacency: (T, 3) int (`geometry.mesh.triangle_adjacency`).
        steps: most triangles walked.
    Returns:
        occluder, far: (M,) int64 flat pixel indices into (B, H, W);
        triangle: (M,) int64 the triangle whose edge is the silhouette;
        edge: (M,) int64 the corner (0..2) opposite that edge.
    """
    tri = np.ascontiguousarray(triangle, np.int64)
    return _find_pairs(tri, np.ascontiguousarray(zbuffer, np.float64), np.ascontiguousarray(pix, np.float64),
                       np.ascontiguousarray(faces, np.int64), np.ascontiguousarray(adjacency, np.int64), int(steps),
                       PRUNE_MASK)


def _find_pairs(tri: np.ndarray, zbuf: np.ndarray, pix: np.ndarray, faces: np.ndarray, adjacency: np.ndarray,
                steps: int, prune: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`silhouette_pairs` in two halves (`halves.run_halves`): one image's horizontal and vertical
    pairs after its walk distances or pair masks, or the first and second half of a batch's
    images; the halves' pairs are concatenated in the order one pass would find them. `prune`:
    PRUNE_NONE, PRUNE_DISTANCE (skip occluders farther than steps - 1 triangles from a silhouette
    edge) or PRUNE_MASK (skip pairs no silhouette edge passes near; where an image's edges are
    too short for the masks' margin, one image falls back to PRUNE_DISTANCE, a batch to none).
    The three find the same pairs."""
    batch = tri.shape[0]
    no_lists = (np.zeros(1, np.int64), np.zeros(0, np.int64))
    start, items = reverse_adjacency(adjacency) if prune == PRUNE_DISTANCE else no_lists
    ntri = len(faces)
    height, width = tri.shape[1], tri.shape[2]

    def buffers() -> tuple[np.ndarray, ...]:
        masks = (height, width) if prune == PRUNE_MASK else (0, 0)
        return (np.zeros(ntri, np.bool_), np.zeros(ntri if prune != PRUNE_MASK else 0, np.int64),
                np.empty(masks, np.bool_), np.empty(masks, np.bool_))

    def half(b_lo: int, b_hi: int, axis_lo: int, axis_hi: int, walked: int, bufs: tuple[np.ndarray, ...]):
        size = (b_hi - b_lo) * (axis_hi - axis_lo) * height * width + 1
        outs = [np.empty(size, np.int64) for _ in range(4)]
        n = _pairs_kernel(tri, zbuf, pix, faces, adjacency, steps, prune, start, items, b_lo, b_hi, axis_lo, axis_hi,
                          *bufs, walked, *outs)
        return [a[:n] for a in outs]

    work = tri.size
    if batch == 1:
        bufs = buffers()
        walked = _walk_kernel(pix, 0, faces, adjacency, steps, prune, start, items, *bufs)
        if prune == PRUNE_MASK and walked == PRUNE_NONE and height * width >= ntri:
            start, items = reverse_adjacency(adjacency)
            bufs = (bufs[0], np.zeros(ntri, np.int64)) + bufs[2:]
            walked = _walk_kernel(pix, 0, faces, adjacency, steps, PRUNE_DISTANCE, start, items, *bufs)
        first, second = run_halves(lambda: half(0, 1, 0, 1, walked, bufs), lambda: half(0, 1, 1, 2, walked, bufs),
                                   work)
    else:
        mid = batch // 2
        first, second = run_halves(lambda: half(0, mid, 0, 2, -1, buffers()),
                                   lambda: half(mid, batch, 0, 2, -1, buffers()), work)
    occ, far, t_out, e_out = (np.concatenate([a, b]) for a, b in zip(first, second))
    return occ, far, t_out, e_out


_REVERSE_CACHE: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
_REVERSE_LOCK = threading.Lock()


def reverse_adjacency(adjacency: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """CSR lists (start (T + 1,), items) of the triangles whose `adjacency` row names each
    triangle, for the pruned silhouette walk. The last four triangle lists' lists are kept
    (a render of the same mesh reuses them after an exact comparison of the adjacency, ~50 us
    for the ICT head against ~0.5 ms to rebuild)."""
    adjacency = np.ascontiguousarray(adjacency, np.int64)
    with _REVERSE_LOCK:
        for adj, start, items in _REVERSE_CACHE:
            if adj.shape == adjacency.shape and np.array_equal(adj, adjacency):
                return start, items
    start, items = _reverse_adjacency(adjacency)
    with _REVERSE_LOCK:
        _REVERSE_CACHE.insert(0, (adjacency.copy(), start, items))
        del _REVERSE_CACHE[4:]
    return start, items
