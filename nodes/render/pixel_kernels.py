"""Compiled (numba) forward and backward of the renderer's differentiable parts on the CPU.

Two computations of `nodes.render.renderer` cost most of a CPU render when written as torch
ops (dozens of small element-wise ops and their autograd nodes, each over every covered
pixel or every triangle):

- `normals_forward` / `normals_backward`: area-weighted unit vertex normals (the sum of the
  adjacent faces' cross products, normalized with the norm clamped to `eps`) and the
  gradient of a loss with respect to the vertices given its gradient w.r.t. the normals.
- `shade_forward` / `shade_backward`: for each covered pixel, the screen barycentrics of
  its centre in its triangle, made perspective-correct (`mu_k = (l_k / z_k) / S`,
  `S = sum_j l_j / z_j`, depth `1 / S`), the interpolated albedo and normal, the normal
  normalized (norm clamped to 1e-12), the 9 SH basis values and `colour = albedo * E(n)`;
  backward: the gradients w.r.t. the projected vertices, their camera depths, the vertex
  normals, the albedo and the SH coefficients, scattered over the pixels' corners.
- `antialias_forward` / `antialias_backward`: the silhouette blends of the analytic
  antialiasing over the pixel pairs `raster.silhouette_pairs` found, and their gradients
  w.r.t. the image and (through where the edge crosses each pair) the projected vertices.

Each backward recomputes its forward's intermediates from the inputs (a few multiplies per
pixel) rather than storing them. The math is the torch path's, term by term (the torch path
stays for CUDA and is the reference in `tests/nodes/render/test_pixel_kernels.py`); the
kernels run serially over pixels or triangles (their outputs are scatter-adds), in the
inputs' float type for arrays and float64 for scalar temporaries.

Conventions as `renderer`: pixel centres at integers, pixel `p` of a (B, H, W) image is
flat index `(b * H + y) * W + x`; SH order of `renderer.sh_basis`.

This module imports numba at the top (kernels cached on disk, `cache=True`): import it from
torch modules only, never from a package `__init__`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from .halves import run_halves

__all__ = ["normals_forward", "normals_backward", "shade_forward", "shade_backward", "shade_image",
           "shade_image_backward", "antialias_forward", "antialias_backward", "project_forward", "project_backward"]

_Y0, _Y1, _Y2A, _Y2B, _Y2C = 0.282094791773878, 0.488602511902920, 1.092548430592079, \
    0.315391565252520, 0.546274215296040
_NORMAL_EPS = 1e-12  # the shading normal's norm clamp (as the torch path)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normal_sums_kernel(vertices, faces, sums):  # pragma: no cover - compiled
    for b in range(vertices.shape[0]):
        for t in range(faces.shape[0]):
            i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
            ax = vertices[b, i1, 0] - vertices[b, i0, 0]
            ay = vertices[b, i1, 1] - vertices[b, i0, 1]
            az = vertices[b, i1, 2] - vertices[b, i0, 2]
            bx = vertices[b, i2, 0] - vertices[b, i0, 0]
            by = vertices[b, i2, 1] - vertices[b, i0, 1]
            bz = vertices[b, i2, 2] - vertices[b, i0, 2]
            nx = ay * bz - az * by
            ny = az * bx - ax * bz
            nz = ax * by - ay * bx
            for i in (i0, i1, i2):
                sums[b, i, 0] += nx
                sums[b, i, 1] += ny
                sums[b, i, 2] += nz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normalize_kernel(sums, eps, out):  # pragma: no cover - compiled
    for b in range(sums.shape[0]):
        for v in range(sums.shape[1]):
            x, y, z = sums[b, v, 0], sums[b, v, 1], sums[b, v, 2]
            r = max(math.sqrt(x * x + y * y + z * z), eps)
            out[b, v, 0] = x / r
            out[b, v, 1] = y / r
            out[b, v, 2] = z / r


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _normals_backward_kernel(vertices, faces, sums, normals, grad, eps, grad_v):  # pragma: no cover
    nb, nv = sums.shape[0], sums.shape[1]
    g_sum = np.empty((nv, 3), sums.dtype)
    for b in range(nb):
        for v in range(nv):  # through n = s / max(|s|, eps)
            x, y, z = sums[b, v, 0], sums[b, v, 1], sums[b, v, 2]
            r = math.sqrt(x * x + y * y + z * z)
            gx, gy, gz = grad[b, v, 0], grad[b, v, 1], grad[b, v, 2]
            if r > eps:
                nx, ny, nz = normals[b, v, 0], normals[b, v, 1], normals[b, v, 2]
                d = nx * gx + ny * gy + nz * gz
                g_sum[v, 0] = (gx - nx * d) / r
                g_sum[v, 1] = (gy - ny * d) / r
                g_sum[v, 2] = (gz - nz * d) / r
            else:
                g_sum[v, 0] = gx / eps
                g_sum[v, 1] = gy / eps
                g_sum[v, 2] = gz / eps
        for t in range(faces.shape[0]):  # through the face normal e1 x e2 (e1 = p1 - p0, e2 = p2 - p0)
            i0, i1, i2 = faces[t, 0], faces[t, 1], faces[t, 2]
            fx = g_sum[i0, 0] + g_sum[i1, 0] + g_sum[i2, 0]
            fy = g_sum[i0, 1] + g_sum[i1, 1] + g_sum[i2, 1]
            fz = g_sum[i0, 2] + g_sum[i1, 2] + g_sum[i2, 2]
            ax = vertices[b, i1, 0] - vertices[b, i0, 0]
            ay = vertices[b, i1, 1] - vertices[b, i0, 1]
            az = vertices[b, i1, 2] - vertices[b, i0, 2]
            bx = vertices[b, i2, 0] - vertices[b, i0, 0]
            by = vertices[b, i2, 1] - vertices[b, i0, 1]
            bz = vertices[b, i2, 2] - vertices[b, i0, 2]
            g1x = by * fz - bz * fy  # e2 x g
            g1y = bz * fx - bx * fz
            g1z = bx * fy - by * fx
            g2x = fy * az - fz * ay  # g x e1
            g2y = fz * ax - fx * az
            g2z = fx * ay - fy * ax
            grad_v[b, i1, 0] += g1x
            grad_v[b, i1, 1] += g1y
            grad_v[b, i1, 2] += g1z
            grad_v[b, i2, 0] += g2x
            grad_v[b, i2, 1] += g2y
            grad_v[b, i2, 2] += g2z
            grad_v[b, i0, 0] -= g1x + g2x
            grad_v[b, i0, 1] -= g1y + g2y
            grad_v[b, i0, 2] -= g1z + g2z


def normals_forward(vertices: np.ndarray, faces: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit area-weighted vertex normals.

    Args:
        vertices: (B, V, 3) float32 or float64, cm (C-contiguous).
        faces: (T, 3) int64.
        eps: the norm clamp (a vertex with no area around it gets a zero normal).
    Returns:
        normals (B, V, 3) unit (or zero), and the unnormalized sums (B, V, 3) cm^2 that
        `normals_backward` takes.
    """
    sums = np.zeros(vertices.shape, vertices.dtype)
    _normal_sums_kernel(vertices, faces, sums)
    normals = np.empty_like(sums)
    _normalize_kernel(sums, eps, normals)
    return normals, sums


def normals_backward(vertices: np.ndarray, faces: np.ndarray, sums: np.ndarray, normals: np.ndarray,
                     grad: np.ndarray, eps: float) -> np.ndarray:
    """Gradient w.r.t. the vertices (B, V, 3) given `grad`, that w.r.t. the normals (B, V, 3)."""
    grad_v = np.zeros(vertices.shape, vertices.dtype)
    _normals_backward_kernel(vertices, faces, sums, normals, grad, eps, grad_v)
    return grad_v


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _advance_row(p, height, width, b, y, row_start):  # pragma: no cover - compiled
    """(image, row, flat index of the row's first pixel) of pixel p, stepping on from those of an
    earlier pixel (b, y, row_start) row by row: the covered pixels are ascending, so a kernel walks
    the rows once instead of two 64-bit integer divisions per pixel."""
    while p >= row_start + width:
        row_start += width
        y += 1
        if y == height:
            y = 0
            b += 1
    return b, y, row_start


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _irradiance(sh, bs, ch, y1, y2, y3, y4, y5, y6, y7, y8):  # pragma: no cover - compiled
    return (_Y0 * sh[bs, 0, ch] + y1 * sh[bs, 1, ch] + y2 * sh[bs, 2, ch] + y3 * sh[bs, 3, ch]
            + y4 * sh[bs, 4, ch] + y5 * sh[bs, 5, ch] + y6 * sh[bs, 6, ch] + y7 * sh[bs, 7, ch]
            + y8 * sh[bs, 8, ch])


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _basis(x, y, z):  # pragma: no cover - compiled
    """SH basis values 1..8 of a unit normal (value 0 is the constant _Y0)."""
    return (_Y1 * y, _Y1 * z, _Y1 * x, _Y2A * x * y, _Y2A * y * z, _Y2B * (3.0 * z * z - 1.0), _Y2A * x * z,
            _Y2C * (x * x - y * y))


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _edge_functions(pix2, r0, r1, r2, px, py):  # pragma: no cover - compiled
    """(twice the signed area, cross products opposite corners 0 and 1) of point (px, py) in the
    triangle of rows r0, r1, r2 of pix2: barycentrics l0 = cr0 / area, l1 = cr1 / area."""
    x0, y0 = pix2[r0, 0], pix2[r0, 1]
    x1, y1 = pix2[r1, 0], pix2[r1, 1]
    x2, y2 = pix2[r2, 0], pix2[r2, 1]
    area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
    cr0 = (x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)
    cr1 = (x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)
    return area, cr0, cr1


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _shade_one(pix2, dep, nrm, albedo, sh, one_albedo, one_sh, nv, b, r0, r1, r2, px, py):  # pragma: no cover
    """Colour, perspective-correct barycentrics and depth of one covered pixel (module docstring)."""
    area, cr0, cr1 = _edge_functions(pix2, r0, r1, r2, px, py)
    inv_area = 1.0 / area  # reciprocals (float64): 6 divisions a pixel instead of 12, as the backward
    l0 = cr0 * inv_area
    l1 = cr1 * inv_area
    l2 = 1.0 - l0 - l1
    m0, m1, m2 = l0 / dep[r0], l1 / dep[r1], l2 / dep[r2]
    inv_s = 1.0 / (m0 + m1 + m2)
    mu0, mu1, mu2 = m0 * inv_s, m1 * inv_s, m2 * inv_s
    ba = 0 if one_albedo else b
    bs = 0 if one_sh else b
    vx = mu0 * nrm[r0, 0] + mu1 * nrm[r1, 0] + mu2 * nrm[r2, 0]
    vy = mu0 * nrm[r0, 1] + mu1 * nrm[r1, 1] + mu2 * nrm[r2, 1]
    vz = mu0 * nrm[r0, 2] + mu1 * nrm[r1, 2] + mu2 * nrm[r2, 2]
    inv_r = 1.0 / max(math.sqrt(vx * vx + vy * vy + vz * vz), _NORMAL_EPS)
    q1, q2, q3, q4, q5, q6, q7, q8 = _basis(vx * inv_r, vy * inv_r, vz * inv_r)
    c0, c1, c2 = r0 - b * nv, r1 - b * nv, r2 - b * nv
    a = mu0 * albedo[ba, c0, 0] + mu1 * albedo[ba, c1, 0] + mu2 * albedo[ba, c2, 0]
    red = a * _irradiance(sh, bs, 0, q1, q2, q3, q4, q5, q6, q7, q8)
    a = mu0 * albedo[ba, c0, 1] + mu1 * albedo[ba, c1, 1] + mu2 * albedo[ba, c2, 1]
    green = a * _irradiance(sh, bs, 1, q1, q2, q3, q4, q5, q6, q7, q8)
    a = mu0 * albedo[ba, c0, 2] + mu1 * albedo[ba, c1, 2] + mu2 * albedo[ba, c2, 2]
    blue = a * _irradiance(sh, bs, 2, q1, q2, q3, q4, q5, q6, q7, q8)
    return red, green, blue, mu0, mu1, mu2, inv_s


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shade_forward_kernel(pix, depth, normals, albedo, sh, pixels, corners, height, width,
                          colour, mu_out, depth_out):  # pragma: no cover - compiled
    nv = depth.shape[1]
    pix2 = pix.reshape(-1, 2)
    dep = depth.reshape(-1)
    nrm = normals.reshape(-1, 3)
    one_albedo = albedo.shape[0] == 1
    one_sh = sh.shape[0] == 1
    b = y = row_start = 0
    for n in range(pixels.shape[0]):
        b, y, row_start = _advance_row(pixels[n], height, width, b, y, row_start)
        r0, r1, r2 = b * nv + corners[n, 0], b * nv + corners[n, 1], b * nv + corners[n, 2]
        px, py = float(pixels[n] - row_start), float(y)
        (colour[n, 0], colour[n, 1], colour[n, 2], mu_out[n, 0], mu_out[n, 1], mu_out[n, 2],
         depth_out[n]) = _shade_one(pix2, dep, nrm, albedo, sh, one_albedo, one_sh, nv, b, r0, r1, r2, px, py)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shade_image_kernel(pix, depth, normals, albedo, sh, pixels, corners, height, width, background,
                        image, geometry, p_lo, p_hi, n_lo, n_hi):  # pragma: no cover - compiled
    """Image pixels p_lo..p_hi - 1, of which covered pixels n_lo..n_hi - 1 (of `pixels`)."""
    nv = depth.shape[1]
    pix2 = pix.reshape(-1, 2)
    dep = depth.reshape(-1)
    nrm = normals.reshape(-1, 3)
    one_albedo = albedo.shape[0] == 1
    one_sh = sh.shape[0] == 1
    size = height * width
    one_bg_image = background.shape[0] == 1
    one_bg_pixel = background.shape[1] == 1
    for p in range(p_lo, p_hi):  # the background, coverage 0, geometry 0
        bb = 0 if one_bg_image else p // size
        q = 0 if one_bg_pixel else p - (p // size) * size
        image[p, 0] = background[bb, q, 0]
        image[p, 1] = background[bb, q, 1]
        image[p, 2] = background[bb, q, 2]
        image[p, 3] = 0.0
        geometry[p, 0] = geometry[p, 1] = geometry[p, 2] = geometry[p, 3] = 0.0
    b = y = row_start = 0
    for n in range(n_lo, n_hi):
        p = pixels[n]
        b, y, row_start = _advance_row(p, height, width, b, y, row_start)
        r0, r1, r2 = b * nv + corners[n, 0], b * nv + corners[n, 1], b * nv + corners[n, 2]
        px, py = float(p - row_start), float(y)
        (image[p, 0], image[p, 1], image[p, 2], geometry[p, 1], geometry[p, 2], geometry[p, 3],
         geometry[p, 0]) = _shade_one(pix2, dep, nrm, albedo, sh, one_albedo, one_sh, nv, b, r0, r1, r2, px, py)
        image[p, 3] = 1.0


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _flush_sh_grad(grad_sh, bs, acc):  # pragma: no cover - compiled
    """grad_sh[bs] += the sums in acc (27,: sh[j, c] at 9 c + j), and acc = 0."""
    for c in range(3):
        for j in range(9):
            grad_sh[bs, j, c] += acc[9 * c + j]
            acc[9 * c + j] = 0.0


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _shade_backward_kernel(pix, inv_depth, normals, albedo, sh, pixels, corners, height, width,
                           g_colour, g_geometry, image_rows, grad_pix, grad_depth, grad_normals, grad_albedo,
                           grad_sh, n_lo, n_hi):  # pragma: no cover - compiled
    """Covered pixels n_lo..n_hi - 1; grad_sh (B or 1, 9, 3) float64; inv_depth (B, V) float64,
    1 / the vertices' depth (once per vertex, not three divisions per pixel). The gradients
    w.r.t. the colour (first 3 columns of g_colour) and the depth and barycentrics (g_geometry's
    4 columns) of covered pixel n are in row n, or with `image_rows` row pixels[n] (the image
    layout of `shade_image`); an empty array (0 rows) is zero."""
    nv = inv_depth.shape[1]
    pix2 = pix.reshape(-1, 2)
    inv_dep = inv_depth.reshape(-1)
    nrm = normals.reshape(-1, 3)
    gp2 = grad_pix.reshape(-1, 2)
    gd1 = grad_depth.reshape(-1)
    gn2 = grad_normals.reshape(-1, 3)
    one_albedo = albedo.shape[0] == 1
    one_sh = sh.shape[0] == 1
    has_colour = g_colour.shape[0] > 0
    has_geometry = g_geometry.shape[0] > 0
    acc = np.zeros(27)  # float64 sums of the SH gradient of image sh_image (sh[j, c] at 9 c + j)
    sh_image = 0
    b = y = row_start = 0
    for n in range(n_lo, n_hi):
        b, y, row_start = _advance_row(pixels[n], height, width, b, y, row_start)
        r0, r1, r2 = b * nv + corners[n, 0], b * nv + corners[n, 1], b * nv + corners[n, 2]
        px, py = float(pixels[n] - row_start), float(y)
        row = pixels[n] if image_rows else n
        if has_colour:
            gc0, gc1, gc2 = g_colour[row, 0], g_colour[row, 1], g_colour[row, 2]
        else:
            gc0 = gc1 = gc2 = 0.0
        if has_geometry:
            g_z, g_mu0, g_mu1, g_mu2 = g_geometry[row, 0], g_geometry[row, 1], g_geometry[row, 2], g_geometry[row, 3]
        else:
            g_z = g_mu0 = g_mu1 = g_mu2 = 0.0
        x0, y0 = pix2[r0, 0], pix2[r0, 1]
        x1, y1 = pix2[r1, 0], pix2[r1, 1]
        x2, y2 = pix2[r2, 0], pix2[r2, 1]
        area, cr0, cr1 = _edge_functions(pix2, r0, r1, r2, px, py)
        inv_area = 1.0 / area
        l0 = cr0 * inv_area
        l1 = cr1 * inv_area
        l2 = 1.0 - l0 - l1
        iz0, iz1, iz2 = inv_dep[r0], inv_dep[r1], inv_dep[r2]
        m0, m1, m2 = l0 * iz0, l1 * iz1, l2 * iz2
        s = m0 + m1 + m2
        inv_s = 1.0 / s
        mu0, mu1, mu2 = m0 * inv_s, m1 * inv_s, m2 * inv_s
        ba = 0 if one_albedo else b
        bs = 0 if one_sh else b
        c0, c1, c2 = r0 - b * nv, r1 - b * nv, r2 - b * nv
        n0x, n0y, n0z = nrm[r0, 0], nrm[r0, 1], nrm[r0, 2]
        n1x, n1y, n1z = nrm[r1, 0], nrm[r1, 1], nrm[r1, 2]
        n2x, n2y, n2z = nrm[r2, 0], nrm[r2, 1], nrm[r2, 2]
        vx = mu0 * n0x + mu1 * n1x + mu2 * n2x
        vy = mu0 * n0y + mu1 * n1y + mu2 * n2y
        vz = mu0 * n0z + mu1 * n1z + mu2 * n2z
        norm = math.sqrt(vx * vx + vy * vy + vz * vz)
        inv_r = 1.0 / max(norm, _NORMAL_EPS)
        x, yy, z = vx * inv_r, vy * inv_r, vz * inv_r
        q1, q2, q3, q4, q5, q6, q7, q8 = _basis(x, yy, z)
        a00, a01, a02 = albedo[ba, c0, 0], albedo[ba, c0, 1], albedo[ba, c0, 2]
        a10, a11, a12 = albedo[ba, c1, 0], albedo[ba, c1, 1], albedo[ba, c1, 2]
        a20, a21, a22 = albedo[ba, c2, 0], albedo[ba, c2, 1], albedo[ba, c2, 2]
        # colour_c = a_c E_c, a_c = sum_k mu_k albedo_kc, E_c = sum_j Y_j sh[j, c]
        ge0 = gc0 * (mu0 * a00 + mu1 * a10 + mu2 * a20)
        ge1 = gc1 * (mu0 * a01 + mu1 * a11 + mu2 * a21)
        ge2 = gc2 * (mu0 * a02 + mu1 * a12 + mu2 * a22)
        ga0 = gc0 * _irradiance(sh, bs, 0, q1, q2, q3, q4, q5, q6, q7, q8)
        ga1 = gc1 * _irradiance(sh, bs, 1, q1, q2, q3, q4, q5, q6, q7, q8)
        ga2 = gc2 * _irradiance(sh, bs, 2, q1, q2, q3, q4, q5, q6, q7, q8)
        if bs != sh_image:  # d colour_c / d sh[j, c] = Y_j a_c, summed in registers per SH image
            _flush_sh_grad(grad_sh, sh_image, acc)
            sh_image = bs
        acc[0] += _Y0 * ge0
        acc[1] += q1 * ge0
        acc[2] += q2 * ge0
        acc[3] += q3 * ge0
        acc[4] += q4 * ge0
        acc[5] += q5 * ge0
        acc[6] += q6 * ge0
        acc[7] += q7 * ge0
        acc[8] += q8 * ge0
        acc[9] += _Y0 * ge1
        acc[10] += q1 * ge1
        acc[11] += q2 * ge1
        acc[12] += q3 * ge1
        acc[13] += q4 * ge1
        acc[14] += q5 * ge1
        acc[15] += q6 * ge1
        acc[16] += q7 * ge1
        acc[17] += q8 * ge1
        acc[18] += _Y0 * ge2
        acc[19] += q1 * ge2
        acc[20] += q2 * ge2
        acc[21] += q3 * ge2
        acc[22] += q4 * ge2
        acc[23] += q5 * ge2
        acc[24] += q6 * ge2
        acc[25] += q7 * ge2
        acc[26] += q8 * ge2
        gq1 = sh[bs, 1, 0] * ge0 + sh[bs, 1, 1] * ge1 + sh[bs, 1, 2] * ge2
        gq2 = sh[bs, 2, 0] * ge0 + sh[bs, 2, 1] * ge1 + sh[bs, 2, 2] * ge2
        gq3 = sh[bs, 3, 0] * ge0 + sh[bs, 3, 1] * ge1 + sh[bs, 3, 2] * ge2
        gq4 = sh[bs, 4, 0] * ge0 + sh[bs, 4, 1] * ge1 + sh[bs, 4, 2] * ge2
        gq5 = sh[bs, 5, 0] * ge0 + sh[bs, 5, 1] * ge1 + sh[bs, 5, 2] * ge2
        gq6 = sh[bs, 6, 0] * ge0 + sh[bs, 6, 1] * ge1 + sh[bs, 6, 2] * ge2
        gq7 = sh[bs, 7, 0] * ge0 + sh[bs, 7, 1] * ge1 + sh[bs, 7, 2] * ge2
        gq8 = sh[bs, 8, 0] * ge0 + sh[bs, 8, 1] * ge1 + sh[bs, 8, 2] * ge2
        # the SH basis of the unit normal (x, yy, z)
        gnx = _Y1 * gq3 + _Y2A * yy * gq4 + _Y2A * z * gq7 + 2.0 * _Y2C * x * gq8
        gny = _Y1 * gq1 + _Y2A * x * gq4 + _Y2A * z * gq5 - 2.0 * _Y2C * yy * gq8
        gnz = _Y1 * gq2 + _Y2A * yy * gq5 + 6.0 * _Y2B * z * gq6 + _Y2A * x * gq7
        if norm > _NORMAL_EPS:  # n = v / max(|v|, eps)
            d = x * gnx + yy * gny + z * gnz
            gvx, gvy, gvz = (gnx - x * d) * inv_r, (gny - yy * d) * inv_r, (gnz - z * d) * inv_r
        else:
            gvx, gvy, gvz = gnx * inv_r, gny * inv_r, gnz * inv_r
        # the interpolation value = sum_k mu_k attr_k, to the albedo and normals of the corners
        grad_albedo[ba, c0, 0] += mu0 * ga0
        grad_albedo[ba, c0, 1] += mu0 * ga1
        grad_albedo[ba, c0, 2] += mu0 * ga2
        grad_albedo[ba, c1, 0] += mu1 * ga0
        grad_albedo[ba, c1, 1] += mu1 * ga1
        grad_albedo[ba, c1, 2] += mu1 * ga2
        grad_albedo[ba, c2, 0] += mu2 * ga0
        grad_albedo[ba, c2, 1] += mu2 * ga1
        grad_albedo[ba, c2, 2] += mu2 * ga2
        gn2[r0, 0] += mu0 * gvx
        gn2[r0, 1] += mu0 * gvy
        gn2[r0, 2] += mu0 * gvz
        gn2[r1, 0] += mu1 * gvx
        gn2[r1, 1] += mu1 * gvy
        gn2[r1, 2] += mu1 * gvz
        gn2[r2, 0] += mu2 * gvx
        gn2[r2, 1] += mu2 * gvy
        gn2[r2, 2] += mu2 * gvz
        gmu0 = g_mu0 + a00 * ga0 + a01 * ga1 + a02 * ga2 + n0x * gvx + n0y * gvy + n0z * gvz
        gmu1 = g_mu1 + a10 * ga0 + a11 * ga1 + a12 * ga2 + n1x * gvx + n1y * gvy + n1z * gvz
        gmu2 = g_mu2 + a20 * ga0 + a21 * ga1 + a22 * ga2 + n2x * gvx + n2y * gvy + n2z * gvz
        # mu_k = m_k / S, depth = 1 / S, m_k = l_k / z_k
        g_s = -g_z * inv_s * inv_s
        dot = gmu0 * mu0 + gmu1 * mu1 + gmu2 * mu2
        gm0 = (gmu0 - dot) * inv_s + g_s
        gm1 = (gmu1 - dot) * inv_s + g_s
        gm2 = (gmu2 - dot) * inv_s + g_s
        gd1[r0] -= gm0 * l0 * iz0 * iz0
        gd1[r1] -= gm1 * l1 * iz1 * iz1
        gd1[r2] -= gm2 * l2 * iz2 * iz2
        gl0 = gm0 * iz0 - gm2 * iz2  # l2 = 1 - l0 - l1
        gl1 = gm1 * iz1 - gm2 * iz2
        # l0 = cr0 / area, l1 = cr1 / area
        g_c0, g_c1 = gl0 * inv_area, gl1 * inv_area
        g_area = -(gl0 * l0 + gl1 * l1) * inv_area
        # cr0 = (x1 - px)(y2 - py) - (x2 - px)(y1 - py); cr1 = (x2 - px)(y0 - py) - (x0 - px)(y2 - py);
        # area = (x1 - x0)(y2 - y0) - (x2 - x0)(y1 - y0)
        gp2[r0, 0] += -g_c1 * (y2 - py) + g_area * (y1 - y2)
        gp2[r0, 1] += g_c1 * (x2 - px) + g_area * (x2 - x1)
        gp2[r1, 0] += g_c0 * (y2 - py) + g_area * (y2 - y0)
        gp2[r1, 1] += -g_c0 * (x2 - px) - g_area * (x2 - x0)
        gp2[r2, 0] += -g_c0 * (y1 - py) + g_c1 * (y0 - py) - g_area * (y1 - y0)
        gp2[r2, 1] += g_c0 * (x1 - px) - g_c1 * (x0 - px) + g_area * (x1 - x0)
    _flush_sh_grad(grad_sh, sh_image, acc)


def shade_forward(pix: np.ndarray, depth: np.ndarray, normals: np.ndarray, albedo: np.ndarray, sh: np.ndarray,
                  pixels: np.ndarray, corners: np.ndarray, height: int, width: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Shade the covered pixels (module docstring).

    Args:
        pix: (B, V, 2) projected vertices, pixels; depth: (B, V) their camera z, cm;
        normals: (B, V, 3) unit vertex normals, world frame; albedo: (B or 1, V, 3);
        sh: (B or 1, 9, 3) SH irradiance coefficients. One float dtype, C-contiguous.
        pixels: (N,) int64 flat indices into (B, H, W) of the covered pixels, ascending.
        corners: (N, 3) int64 vertex indices of each pixel's triangle.
        height, width: the image size, pixels.
    Returns:
        colour (N, 3) linear, mu (N, 3) perspective-correct barycentrics, depth (N,) cm.
    """
    dt = pix.dtype
    colour = np.empty((len(pixels), 3), dt)
    mu = np.empty((len(pixels), 3), dt)
    dep = np.empty(len(pixels), dt)
    _shade_forward_kernel(pix, depth, normals, albedo, sh, pixels, corners, height, width, colour, mu, dep)
    return colour, mu, dep


def shade_backward(pix: np.ndarray, depth: np.ndarray, normals: np.ndarray, albedo: np.ndarray, sh: np.ndarray,
                   pixels: np.ndarray, corners: np.ndarray, height: int, width: int, g_colour: np.ndarray,
                   g_mu: np.ndarray, g_depth: np.ndarray) -> tuple[np.ndarray, ...]:
    """Gradients of `shade_forward` (same inputs, and the gradients w.r.t. its three outputs).

    Returns:
        gradients w.r.t. pix (B, V, 2), depth (B, V), normals (B, V, 3), albedo (B or 1, V, 3)
        and sh (B or 1, 9, 3).
    """
    g_geometry = np.concatenate([g_depth.reshape(-1, 1), g_mu], 1).astype(pix.dtype)
    return _shade_backward_halves(pix, depth, normals, albedo, sh, pixels, corners, height, width,
                                  np.ascontiguousarray(g_colour, pix.dtype), g_geometry, False)


def _shade_backward_halves(pix: np.ndarray, depth: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                           sh: np.ndarray, pixels: np.ndarray, corners: np.ndarray, height: int, width: int,
                           g_colour: np.ndarray, g_geometry: np.ndarray, image_rows: bool) -> tuple[np.ndarray, ...]:
    """`_shade_backward_kernel` over two fixed halves of the pixels (arguments as there)."""
    dt = pix.dtype
    n = len(pixels)
    with np.errstate(divide="ignore", invalid="ignore"):  # as the kernel's float64 1.0 / z (inf at 0)
        inv_depth = 1.0 / depth.astype(np.float64)

    def half(n_lo: int, n_hi: int) -> list[np.ndarray]:
        grads = [np.zeros(pix.shape, dt), np.zeros(depth.shape, dt), np.zeros(normals.shape, dt),
                 np.zeros(albedo.shape, dt), np.zeros(sh.shape, np.float64)]
        _shade_backward_kernel(pix, inv_depth, normals, albedo, sh, pixels, corners, height, width,
                               g_colour, g_geometry, image_rows, *grads, n_lo, n_hi)
        return grads

    # two fixed halves of the pixels, each scattering into its own buffers, added in one order
    # (`halves`: the same bits on one thread or two)
    first, second = run_halves(lambda: half(0, n // 2), lambda: half(n // 2, n), n)
    for a, b in zip(first, second):
        a += b
    return tuple(first[:4]) + (first[4].astype(dt),)


def shade_image(pix: np.ndarray, depth: np.ndarray, normals: np.ndarray, albedo: np.ndarray, sh: np.ndarray,
                pixels: np.ndarray, corners: np.ndarray, height: int, width: int, background: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """`shade_forward` written straight into B images over their background (one pass each,
    no per-pixel temporaries or scatter afterwards).

    Args:
        pix, depth, normals, albedo, sh, pixels, corners, height, width: as `shade_forward`.
        background: (B or 1, H * W or 1, 3) linear colour per image and pixel (or one for all),
            the inputs' dtype, C-contiguous.
    Returns:
        image (B * H * W, 4): colour of the covered pixels, the background elsewhere, and
        coverage (1 covered, 0 not); geometry (B * H * W, 4): depth (cm) and the 3
        perspective-correct barycentrics of the covered pixels, 0 elsewhere.
    """
    dt = pix.dtype
    npix = depth.shape[0] * height * width
    image = np.empty((npix, 4), dt)
    geometry = np.empty((npix, 4), dt)
    p_mid = npix // 2  # two halves of the image (disjoint writes; `halves`)
    n_mid = int(np.searchsorted(pixels, p_mid))
    run_halves(lambda: _shade_image_kernel(pix, depth, normals, albedo, sh, pixels, corners, height, width, background,
                                           image, geometry, 0, p_mid, 0, n_mid),
               lambda: _shade_image_kernel(pix, depth, normals, albedo, sh, pixels, corners, height, width, background,
                                           image, geometry, p_mid, npix, n_mid, len(pixels)), len(pixels))
    return image, geometry


def shade_image_backward(pix: np.ndarray, depth: np.ndarray, normals: np.ndarray, albedo: np.ndarray,
                         sh: np.ndarray, pixels: np.ndarray, corners: np.ndarray, height: int, width: int,
                         g_image: np.ndarray | None, g_geometry: np.ndarray | None) -> tuple[np.ndarray, ...]:
    """Gradients of `shade_image` w.r.t. pix, depth, normals, albedo and sh (as `shade_backward`)
    given those w.r.t. its image and geometry ((B * H * W, 4) each, or None: zero). The coverage
    channel is constant (no gradient); the background's gradient is the image's at the pixels
    not covered (the caller's)."""
    empty = np.zeros((0, 4), pix.dtype)
    return _shade_backward_halves(pix, depth, normals, albedo, sh, pixels, corners, height, width,
                                  empty if g_image is None else g_image, empty if g_geometry is None else g_geometry,
                                  True)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _edge_barycentric(pix2, r0, r1, r2, k, px, py):  # pragma: no cover - compiled
    """Barycentric k of point (px, py) in triangle (rows r0, r1, r2 of pix2), as
    `renderer.screen_barycentrics` (l2 = 1 - l0 - l1)."""
    area, cr0, cr1 = _edge_functions(pix2, r0, r1, r2, px, py)
    l0 = cr0 / area
    l1 = cr1 / area
    if k == 0:
        return l0
    if k == 1:
        return l1
    return 1.0 - l0 - l1


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _add_edge_barycentric_grad(pix2, gp2, r0, r1, r2, k, px, py, g):  # pragma: no cover - compiled
    """gp2 += g * d l_k / d corners (l_k of `_edge_barycentric`; l2 = 1 - l0 - l1)."""
    x0, y0 = pix2[r0, 0], pix2[r0, 1]
    x1, y1 = pix2[r1, 0], pix2[r1, 1]
    x2, y2 = pix2[r2, 0], pix2[r2, 1]
    area, cr0, cr1 = _edge_functions(pix2, r0, r1, r2, px, py)
    g0 = g if k == 0 else (-g if k == 2 else 0.0)  # d loss / d l0, d l1
    g1 = g if k == 1 else (-g if k == 2 else 0.0)
    g_c0, g_c1 = g0 / area, g1 / area
    g_area = -(g0 * cr0 + g1 * cr1) / (area * area)
    gp2[r0, 0] += -g_c1 * (y2 - py) + g_area * (y1 - y2)
    gp2[r0, 1] += g_c1 * (x2 - px) + g_area * (x2 - x1)
    gp2[r1, 0] += g_c0 * (y2 - py) + g_area * (y2 - y0)
    gp2[r1, 1] += -g_c0 * (x2 - px) - g_area * (x2 - x0)
    gp2[r2, 0] += -g_c0 * (y1 - py) + g_c1 * (y0 - py) - g_area * (y1 - y0)
    gp2[r2, 1] += g_c0 * (x1 - px) - g_c1 * (x0 - px) + g_area * (x1 - x0)


@numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _pair_alpha(pix2, faces, nv, height, width, occ, far, tri, edge, m):  # pragma: no cover - compiled
    """Where the silhouette edge of pair m crosses its segment (0 at the occluder's centre)."""
    size = height * width
    b = occ[m] // size
    t = tri[m]
    r0, r1, r2 = b * nv + faces[t, 0], b * nv + faces[t, 1], b * nv + faces[t, 2]
    ro = occ[m] - b * size
    rf = far[m] - b * size
    oy, fy = ro // width, rf // width
    ox, fx = float(ro - oy * width), float(rf - fy * width)
    l_occ = _edge_barycentric(pix2, r0, r1, r2, edge[m], ox, float(oy))
    l_far = _edge_barycentric(pix2, r0, r1, r2, edge[m], fx, float(fy))
    return l_occ, l_far, l_occ / (l_occ - l_far), r0, r1, r2, ox, float(oy), fx, float(fy)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _antialias_forward_kernel(colour, pix, faces, height, width, occ, far, tri, edge, out):  # pragma: no cover
    nv = pix.shape[1]
    pix2 = pix.reshape(-1, 2)
    for m in range(occ.shape[0]):
        alpha = _pair_alpha(pix2, faces, nv, height, width, occ, far, tri, edge, m)[2]
        o, f = occ[m], far[m]
        if alpha >= 0.5:  # the edge lies past the midpoint: the far pixel takes some occluder colour
            w = alpha - 0.5
            for c in range(colour.shape[1]):
                out[f, c] += w * (colour[o, c] - colour[f, c])
        else:
            w = 0.5 - alpha
            for c in range(colour.shape[1]):
                out[o, c] += w * (colour[f, c] - colour[o, c])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _antialias_backward_kernel(colour, pix, faces, height, width, occ, far, tri, edge, grad,
                               g_colour, g_pix):  # pragma: no cover - compiled
    nv = pix.shape[1]
    pix2 = pix.reshape(-1, 2)
    gp2 = g_pix.reshape(-1, 2)
    for m in range(occ.shape[0]):
        l_occ, l_far, alpha, r0, r1, r2, ox, oy, fx, fy = _pair_alpha(pix2, faces, nv, height, width, occ, far,
                                                                      tri, edge, m)
        o, f = occ[m], far[m]
        spill = alpha >= 0.5
        target = f if spill else o
        sign = 1.0 if spill else -1.0  # delta = sign (alpha - 1/2) sign (c_occ - c_far)
        w = sign * (alpha - 0.5)
        g_w = 0.0
        for c in range(colour.shape[1]):
            gd = grad[target, c]
            g_w += gd * sign * (colour[o, c] - colour[f, c])
            g_colour[o, c] += sign * w * gd
            g_colour[f, c] -= sign * w * gd
        g_alpha = sign * g_w
        d = l_occ - l_far  # alpha = l_occ / (l_occ - l_far)
        g_lo = -l_far / (d * d) * g_alpha
        g_lf = l_occ / (d * d) * g_alpha
        k = edge[m]
        _add_edge_barycentric_grad(pix2, gp2, r0, r1, r2, k, ox, oy, g_lo)
        _add_edge_barycentric_grad(pix2, gp2, r0, r1, r2, k, fx, fy, g_lf)


def antialias_forward(colour: np.ndarray, pix: np.ndarray, faces: np.ndarray, height: int, width: int,
                      occ: np.ndarray, far: np.ndarray, tri: np.ndarray, edge: np.ndarray) -> np.ndarray:
    """The silhouette blends of `renderer._antialias` (module docstring there, step 5).

    Args:
        colour: (B * H * W, C) image, C-contiguous; pix: (B, V, 2) projected vertices;
        faces: (T, 3) int64; occ, far, tri, edge: (M,) int64 pairs of `raster.silhouette_pairs`.
    Returns:
        (B * H * W, C) the image with the blends added (the blends read `colour`, not each other).
    """
    out = colour.copy()
    _antialias_forward_kernel(colour, pix, faces, height, width, occ, far, tri, edge, out)
    return out


def antialias_backward(colour: np.ndarray, pix: np.ndarray, faces: np.ndarray, height: int, width: int,
                       occ: np.ndarray, far: np.ndarray, tri: np.ndarray, edge: np.ndarray,
                       grad: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of `antialias_forward` w.r.t. colour (B * H * W, C) and pix (B, V, 2)."""
    g_colour = grad.copy()
    g_pix = np.zeros(pix.shape, pix.dtype)
    _antialias_backward_kernel(colour, pix, faces, height, width, occ, far, tri, edge, grad, g_colour, g_pix)
    return g_colour, g_pix


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _project_kernel(vertices, world_to_camera, intrinsics, distortion, pix, depth):  # pragma: no cover
    has_distortion = distortion.shape[0] > 0
    for b in range(vertices.shape[0]):
        e = world_to_camera[b]
        fx, fy, cx, cy = intrinsics[b, 0], intrinsics[b, 1], intrinsics[b, 2], intrinsics[b, 3]
        k1 = distortion[b, 0] if has_distortion else 0.0
        k2 = distortion[b, 1] if has_distortion else 0.0
        for v in range(vertices.shape[1]):
            px, py, pz = vertices[b, v, 0], vertices[b, v, 1], vertices[b, v, 2]
            qx = px * e[0, 0] + py * e[0, 1] + pz * e[0, 2] + e[0, 3]
            qy = px * e[1, 0] + py * e[1, 1] + pz * e[1, 2] + e[1, 3]
            qz = px * e[2, 0] + py * e[2, 1] + pz * e[2, 2] + e[2, 3]
            x, y = qx / qz, qy / qz
            if has_distortion:
                r2 = x * x + y * y
                f = 1.0 + r2 * (k1 + k2 * r2)
                x, y = x * f, y * f
            pix[b, v, 0] = fx * x + cx
            pix[b, v, 1] = fy * y + cy
            depth[b, v] = qz


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _project_backward_kernel(vertices, world_to_camera, intrinsics, distortion, g_pix, g_depth, grad_v, grad_e,
                             grad_k, grad_d):  # pragma: no cover - compiled
    has_distortion = distortion.shape[0] > 0
    has_pix = g_pix.shape[0] > 0
    has_depth = g_depth.shape[0] > 0
    for b in range(vertices.shape[0]):
        e = world_to_camera[b]
        fx, fy = intrinsics[b, 0], intrinsics[b, 1]
        k1 = distortion[b, 0] if has_distortion else 0.0
        k2 = distortion[b, 1] if has_distortion else 0.0
        ge = np.zeros((3, 4))  # float64 sums over the vertices
        gfx = gfy = gcx = gcy = gk1 = gk2 = 0.0
        for v in range(vertices.shape[1]):
            px, py, pz = vertices[b, v, 0], vertices[b, v, 1], vertices[b, v, 2]
            qx = px * e[0, 0] + py * e[0, 1] + pz * e[0, 2] + e[0, 3]
            qy = px * e[1, 0] + py * e[1, 1] + pz * e[1, 2] + e[1, 3]
            qz = px * e[2, 0] + py * e[2, 1] + pz * e[2, 2] + e[2, 3]
            x, y = qx / qz, qy / qz
            gu = g_pix[b, v, 0] if has_pix else 0.0
            gv = g_pix[b, v, 1] if has_pix else 0.0
            gz = g_depth[b, v] if has_depth else 0.0
            gx, gy = gu * fx, gv * fy  # u = fx xd + cx, v = fy yd + cy
            if has_distortion:  # xd = x f, yd = y f, f = 1 + r2 (k1 + k2 r2)
                r2 = x * x + y * y
                f = 1.0 + r2 * (k1 + k2 * r2)
                gfx += gu * x * f
                gfy += gv * y * f
                g_f = gx * x + gy * y
                gk1 += g_f * r2
                gk2 += g_f * r2 * r2
                g_r2 = g_f * (k1 + 2.0 * k2 * r2)
                gx, gy = gx * f + 2.0 * x * g_r2, gy * f + 2.0 * y * g_r2
            else:
                gfx += gu * x
                gfy += gv * y
            gcx += gu
            gcy += gv
            # x = qx / qz, y = qy / qz, depth = qz
            gqx, gqy = gx / qz, gy / qz
            gqz = gz - (gx * x + gy * y) / qz
            grad_v[b, v, 0] = e[0, 0] * gqx + e[1, 0] * gqy + e[2, 0] * gqz
            grad_v[b, v, 1] = e[0, 1] * gqx + e[1, 1] * gqy + e[2, 1] * gqz
            grad_v[b, v, 2] = e[0, 2] * gqx + e[1, 2] * gqy + e[2, 2] * gqz
            ge[0, 0] += gqx * px
            ge[0, 1] += gqx * py
            ge[0, 2] += gqx * pz
            ge[0, 3] += gqx
            ge[1, 0] += gqy * px
            ge[1, 1] += gqy * py
            ge[1, 2] += gqy * pz
            ge[1, 3] += gqy
            ge[2, 0] += gqz * px
            ge[2, 1] += gqz * py
            ge[2, 2] += gqz * pz
            ge[2, 3] += gqz
        for i in range(3):
            for j in range(4):
                grad_e[b, i, j] = ge[i, j]
        grad_k[b, 0], grad_k[b, 1], grad_k[b, 2], grad_k[b, 3] = gfx, gfy, gcx, gcy
        if has_distortion:
            grad_d[b, 0], grad_d[b, 1] = gk1, gk2


def project_forward(vertices: np.ndarray, world_to_camera: np.ndarray, intrinsics: np.ndarray,
                    distortion: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection with radial distortion, as `geometry.camera.project_points_torch`.

    Args:
        vertices: (B, V, 3) world points, cm; world_to_camera: (B, 4, 4); intrinsics: (B, 4)
            (fx, fy, cx, cy); distortion: (B, 2) (k1, k2) or None. One float dtype, C-contiguous.
    Returns:
        pix (B, V, 2) pixels and depth (B, V) camera-frame z, cm.
    """
    dt = vertices.dtype
    pix = np.empty(vertices.shape[:2] + (2,), dt)
    depth = np.empty(vertices.shape[:2], dt)
    _project_kernel(vertices, world_to_camera, intrinsics, np.zeros((0, 2), dt) if distortion is None else distortion,
                    pix, depth)
    return pix, depth


def project_backward(vertices: np.ndarray, world_to_camera: np.ndarray, intrinsics: np.ndarray,
                     distortion: np.ndarray | None, g_pix: np.ndarray | None, g_depth: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Gradients of `project_forward` w.r.t. vertices (B, V, 3), world_to_camera (B, 4, 4; the
    last row 0), intrinsics (B, 4) and distortion (B, 2) (None without), given those w.r.t.
    pix and depth (None: zero)."""
    dt = vertices.dtype
    empty = np.zeros((0, 2), dt)
    grad_v = np.empty(vertices.shape, dt)
    grad_e = np.zeros(world_to_camera.shape, dt)
    grad_k = np.empty(intrinsics.shape, dt)
    grad_d = None if distortion is None else np.zeros(distortion.shape, dt)
    _project_backward_kernel(vertices, world_to_camera, intrinsics, empty if distortion is None else distortion,
                             empty.reshape(0, 0, 2) if g_pix is None else g_pix,
                             empty.reshape(0, 0) if g_depth is None else g_depth, grad_v, grad_e, grad_k,
                             empty if grad_d is None else grad_d)
    return grad_v, grad_e, grad_k, grad_d
