"""Differentiable mesh renderer in torch: albedo, 9-coefficient SH lighting, analytic antialiasing.

Pipeline of `render_mesh` (batched over B = frames x cameras):

1. Project vertices with a `Camera`-style pinhole (`nodes.geometry.camera`, OpenCV
   convention: x right, y down, z forward; pixel origin top-left, centres at integers).
2. Rasterize (`nodes.render.raster`, numba, no gradients): the nearest triangle covering
   each pixel centre (z-buffer, either winding, triangles crossing the near plane skipped).
3. In torch, for the covered pixels: screen-space barycentrics of the pixel centre from the
   projected corners (differentiable in the vertices), made perspective-correct
   (`mu_i = (l_i / z_i) / sum_j l_j / z_j`), interpolating per-vertex albedo and normals.
4. Shade: `colour = albedo * E(n)` with `E(n) = sum_k sh[k] Y_k(n)`, the 9 real spherical
   harmonics `Y_k` of the unit world-frame normal (Lambertian irradiance; see `sh_basis`).
   Pixels no triangle covers take the background.
5. Antialias the silhouettes analytically, in the manner of nvdiffrast (Laine et al. 2020,
   "Modular primitives for high-performance differentiable rendering", sec. 3.3): for every
   horizontally or vertically adjacent pixel pair showing different triangles, the nearer
   one's triangle is the occluder; if the edge where the segment between the two pixel
   centres leaves it is a silhouette edge (no neighbour across it, or a neighbour facing
   the other way in screen space) and is more perpendicular than parallel to the pair's
   direction, the edge crosses the segment at `alpha` (0 at the occluder's centre, 1 at the
   other's) and the colours are blended: the far pixel gets `(alpha - 1/2) (c_occ - c_far)`
   when `alpha > 1/2`, else the occluder pixel gets `(1/2 - alpha) (c_far - c_occ)`.
   `alpha` is a rational function of the projected edge endpoints, so the image has
   gradients with respect to vertex positions at silhouettes (interior pixels have them
   through the barycentrics).

Why analytic antialiasing rather than SoftRas-style soft coverage: it needs the hard
rasterization only (one triangle per pixel, which numba z-buffers in milliseconds for the
52k-triangle ICT head), touches only the pixel pairs along silhouettes, leaves interior
pixels exact (no blur of the face that the landmark network reads) and costs O(pixels) in
torch; SoftRas blends every triangle within a few pixels of every pixel (O(pixels x nearby
triangles) memory in forward and backward), far over a 50 ms budget on two cores.

On the CPU, every differentiable step runs as numba kernels with hand-written backwards
(`nodes.render.pixel_kernels`): the projection (`_CompiledProjection`), the vertex normals
(`vertex_normals`), and shading, compositing over the background and the silhouette blends
as one autograd node (`_CompiledImage`: the covered pixels are shaded straight into the
image and its depth / barycentric buffer, no image-sized torch temporaries); one pass over
the vertices or the covered pixels each way instead of dozens of torch ops and their
autograd nodes. The kernels split their work into two fixed halves that run on two threads
when torch may use two (`nodes.render.halves`; the same bits on one thread or two).
Elsewhere (CUDA) the steps are torch ops. The two paths agree to rounding
(`tests/nodes/render/test_pixel_kernels.py`).

Units: positions in cm; colours linear light (albedo in [0, 1]). This module imports torch
at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import project_points_torch
from ..geometry.image import box_downsample
from ..geometry.mesh import triangle_adjacency
from .pixel_kernels import (antialias_backward, antialias_forward, normals_backward, normals_forward,
                            project_backward, project_forward, shade_backward, shade_forward, shade_image,
                            shade_image_backward)
from .raster import covered_pixels, rasterize_triangles, silhouette_pairs

__all__ = ["RenderOutput", "sh_basis", "sh_from_lights", "vertex_normals",
           "screen_barycentrics", "shade_pixels", "render_mesh", "SH_BAND_FACTORS"]

SH_BAND_FACTORS = (math.pi, 2.0 * math.pi / 3.0, math.pi / 4.0)
"""Clamped-cosine convolution factors A_l of SH bands 0, 1, 2 (Ramamoorthi and Hanrahan 2001)."""

_Y0, _Y1, _Y2A, _Y2B, _Y2C = 0.282094791773878, 0.488602511902920, 1.092548430592079, \
    0.315391565252520, 0.546274215296040


class RenderOutput(NamedTuple):
    """What `render_mesh` returns (B images of H x W pixels).

    Attributes:
        image: (B, H, W, 3) linear colour, antialiased, background composited.
        alpha: (B, H, W) coverage in [0, 1] (1 inside, fractional along silhouettes).
        depth: (B, H, W) camera-frame z of the visible surface, cm, 0 where none (not
            antialiased).
        triangle: (B, H, W) int64 index of the visible triangle into `faces`, -1 where none.
        barycentrics: (B, H, W, 3) perspective-correct barycentrics of the visible point in
            its triangle (corner order of `faces`), 0 where none.
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    triangle: Tensor
    barycentrics: Tensor


def sh_basis(normals: Tensor) -> Tensor:
    """Evaluate the 9 real, orthonormal spherical harmonics of bands 0-2.

    Order: Y00, Y1-1 (y), Y10 (z), Y11 (x), Y2-2 (xy), Y2-1 (yz), Y20 (3z^2 - 1), Y21 (xz),
    Y22 (x^2 - y^2), with the usual constants (0.282095, 0.488603, 1.092548, 0.315392,
    0.546274).

    Args:
        normals: (..., 3) unit vectors (x, y, z), world frame.
    Returns:
        (..., 9) basis values.

    Example:
        >>> [round(v, 4) for v in sh_basis(torch.tensor([0.0, 0.0, 1.0])).tolist()]
        [0.2821, 0.0, 0.4886, 0.0, 0.0, 0.0, 0.6308, 0.0, 0.0]
    """
    x, y, z = normals.unbind(-1)
    one = torch.ones_like(x)
    return torch.stack([_Y0 * one, _Y1 * y, _Y1 * z, _Y1 * x, _Y2A * x * y, _Y2A * y * z,
                        _Y2B * (3.0 * z * z - 1.0), _Y2A * x * z, _Y2C * (x * x - y * y)], -1)


def sh_from_lights(ambient: Sequence[float] | float, direction: Sequence[float] = (0.0, 0.0, 1.0),
                   intensity: Sequence[float] | float = 0.0) -> np.ndarray:
    """SH irradiance coefficients of an ambient term plus one distant light.

    `E(n) = ambient + intensity * max(n . d, 0)`, the directional part projected on bands
    0-2 (`E_lm = A_l * intensity * Y_lm(d)`, `SH_BAND_FACTORS`), so the directional part is
    the smooth approximation `1/4 + c/2 + 5/32 (3 c^2 - 1)` (times intensity, c = n . d) of
    the clamped cosine: 1.0625 facing the light, 0.09 at grazing, -0.04 at its minimum
    (c = -8/15) and 0.0625 facing away.

    Args:
        ambient: uniform irradiance, per channel (3,) or one value.
        direction: (3,) direction towards the light, world frame (normalized here).
        intensity: irradiance of the light on a surface facing it, per channel or one value.
    Returns:
        (9, 3) float32 coefficients for `render_mesh(sh=...)`.

    Example:
        >>> [round(float(v), 4) for v in sh_from_lights(0.5)[:2, 0]]
        [1.7725, 0.0]
    """
    amb = np.broadcast_to(np.asarray(ambient, np.float64), (3,))
    inten = np.broadcast_to(np.asarray(intensity, np.float64), (3,))
    d = np.asarray(direction, np.float64)
    norm = np.linalg.norm(d)
    if d.shape != (3,) or not norm > 0:
        raise ValueError(f"direction: expected a non-zero (3,) vector, found {d.tolist()}")
    y = sh_basis(torch.as_tensor(d / norm)).numpy()
    bands = np.array([SH_BAND_FACTORS[0]] + [SH_BAND_FACTORS[1]] * 3 + [SH_BAND_FACTORS[2]] * 5)
    coeffs = (bands * y)[:, None] * inten[None, :]
    coeffs[0] += amb / _Y0
    return coeffs.astype(np.float32)


class _Incidence(NamedTuple):
    """Sparse CSR matrices of one triangle list (built once per faces, see `_incidence`)."""

    faces: Tensor  # (T, 3) int64, to check a cache hit
    corner: tuple[Tensor, Tensor, Tensor]  # (T, V): row t picks corner k of triangle t
    corner_t: tuple[Tensor, Tensor, Tensor]  # (V, T): their transposes (scatter to vertices)
    to_vertices: Tensor  # (V, T): sum of each vertex's adjacent triangles
    to_faces: Tensor  # (T, V): its transpose


_INCIDENCE_CACHE: dict[tuple, _Incidence] = {}


def _incidence(faces: Tensor, num_vertices: int, dtype: torch.dtype) -> _Incidence:
    """Sparse incidence matrices of `faces`, cached by (V, T, device, dtype) and checked
    against the cached faces (a cheap exact comparison), so a changed topology rebuilds."""
    key = (num_vertices, len(faces), faces.device, dtype)
    hit = _INCIDENCE_CACHE.get(key)
    if hit is not None and torch.equal(hit.faces, faces):
        return hit
    t = len(faces)
    rows = torch.arange(t, device=faces.device)
    ones = torch.ones(t, device=faces.device, dtype=dtype)

    def csr(r: Tensor, c: Tensor, v: Tensor, shape: tuple[int, int]) -> Tensor:
        return torch.sparse_coo_tensor(torch.stack([r, c]), v, shape).coalesce().to_sparse_csr()

    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        corner = tuple(csr(rows, faces[:, k], ones, (t, num_vertices)) for k in range(3))
        corner_t = tuple(csr(faces[:, k], rows, ones, (num_vertices, t)) for k in range(3))
        all_rows, all_faces = faces.T.reshape(-1), rows.repeat(3)
        to_vertices = csr(all_rows, all_faces, ones.repeat(3), (num_vertices, t))
        to_faces = csr(all_faces, all_rows, ones.repeat(3), (t, num_vertices))
    inc = _Incidence(faces.clone(), corner, corner_t, to_vertices, to_faces)  # type: ignore[arg-type]
    if len(_INCIDENCE_CACHE) >= 4:
        _INCIDENCE_CACHE.pop(next(iter(_INCIDENCE_CACHE)))
    _INCIDENCE_CACHE[key] = inc
    return inc


class _NormalSums(torch.autograd.Function):
    """Unnormalized vertex normals (sum of adjacent face cross products) with a hand-written
    backward; both directions are sparse matrix products (several times faster than
    gather / index_add autograd on CPU)."""

    @staticmethod
    def forward(ctx, vertices: Tensor, inc: _Incidence) -> Tensor:  # type: ignore[override]
        bsz, nv, _ = vertices.shape
        t = len(inc.faces)
        x = vertices.permute(1, 0, 2).reshape(nv, bsz * 3)
        p0, p1, p2 = ((m @ x).reshape(t, bsz, 3) for m in inc.corner)
        e1, e2 = p1 - p0, p2 - p0
        face_n = torch.linalg.cross(e1, e2, dim=-1)  # (T, B, 3), twice the area
        ctx.save_for_backward(e1, e2)
        ctx.inc = inc
        return (inc.to_vertices @ face_n.reshape(t, bsz * 3)).reshape(nv, bsz, 3).permute(1, 0, 2)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        e1, e2 = ctx.saved_tensors
        inc: _Incidence = ctx.inc
        bsz, nv, _ = grad.shape
        t = len(inc.faces)
        g_face = (inc.to_faces @ grad.permute(1, 0, 2).reshape(nv, bsz * 3)).reshape(t, bsz, 3)
        g1 = torch.linalg.cross(e2, g_face, dim=-1)  # d<g, e1 x e2>/d e1
        g2 = torch.linalg.cross(g_face, e1, dim=-1)  # d<g, e1 x e2>/d e2
        c0, c1, c2 = inc.corner_t
        gx = c1 @ g1.reshape(t, -1) + c2 @ g2.reshape(t, -1) - c0 @ (g1 + g2).reshape(t, -1)
        return gx.reshape(nv, bsz, 3).permute(1, 0, 2), None


class _CompiledNormals(torch.autograd.Function):
    """Unit vertex normals on the CPU by the numba kernels of `pixel_kernels` (forward and
    backward), the same math as `_NormalSums` + normalization in torch."""

    @staticmethod
    def forward(ctx, vertices: Tensor, faces: np.ndarray, eps: float) -> Tensor:  # type: ignore[override]
        v = vertices.detach().contiguous().numpy()
        normals, sums = normals_forward(v, faces, eps)
        ctx.arrays = (v, faces, sums, normals)
        ctx.eps, ctx.dtype = eps, vertices.dtype
        return torch.from_numpy(normals)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        v, faces, sums, normals = ctx.arrays
        g = grad.detach().to(ctx.dtype).contiguous().numpy()
        return torch.from_numpy(normals_backward(v, faces, sums, normals, g, ctx.eps)), None, None


def _compiled(device: torch.device, dtype: torch.dtype, compiled: bool | None) -> bool:
    """Whether to use the numba kernels: by default on the CPU in float32 / float64."""
    if compiled is None:
        return device.type == "cpu" and dtype in (torch.float32, torch.float64)
    if compiled and device.type != "cpu":
        raise ValueError(f"compiled: the numba kernels run on the CPU only, found tensors on {device}")
    return compiled


def vertex_normals(vertices: Tensor, faces: Tensor, eps: float = 1e-12, *,
                   compiled: bool | None = None) -> Tensor:
    """Area-weighted vertex normals (sum of adjacent face cross products, normalized).

    On the CPU by default by numba kernels (`pixel_kernels.normals_forward` / `_backward`);
    elsewhere (CUDA) with sparse incidence matrices (cached per triangle list) and a
    hand-written backward. `tests/nodes/render/test_renderer.py` checks values and gradients
    against a plain gather / index_add autograd reference, `test_pixel_kernels.py` the two
    paths against each other.

    Args:
        vertices: (B, V, 3) positions, cm.
        faces: (T, 3) int64 vertex indices; the normal points to the side from which the
            corners run counter-clockwise (right-hand rule).
        eps: vertices with no area around them get a zero normal (norm clamped to eps).
        compiled: True = the numba kernels (CPU tensors only), False = torch ops, None = the
            kernels on the CPU in float32 / float64, torch ops otherwise.
    Returns:
        (B, V, 3) unit normals, same dtype and device.
    """
    faces = torch.as_tensor(faces, device=vertices.device).long()
    if _compiled(vertices.device, vertices.dtype, compiled):
        return _CompiledNormals.apply(vertices, np.ascontiguousarray(faces.numpy()), float(eps))
    normals = _NormalSums.apply(vertices, _incidence(faces, vertices.shape[1], vertices.dtype))
    return normals / normals.norm(dim=-1, keepdim=True).clamp_min(eps)


def screen_barycentrics(corners: Tensor, points: Tensor) -> Tensor:
    """Barycentric coordinates of 2D points in 2D triangles (extrapolated outside).

    Args:
        corners: (..., 3, 2) triangle corners, pixels.
        points: (..., 2) points, pixels.
    Returns:
        (..., 3) `l` with `sum(l) = 1` and `points = sum_i l_i corners_i`; inf/nan for a
        degenerate triangle.
    """
    p0, p1, p2 = corners.unbind(-2)
    px, py = points.unbind(-1)

    def cross(a: Tensor, b: Tensor) -> Tensor:
        return (a[..., 0] - px) * (b[..., 1] - py) - (b[..., 0] - px) * (a[..., 1] - py)

    area = (p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1]) - \
        (p2[..., 0] - p0[..., 0]) * (p1[..., 1] - p0[..., 1])
    l0 = cross(p1, p2) / area
    l1 = cross(p2, p0) / area
    return torch.stack([l0, l1, 1.0 - l0 - l1], -1)


def _signed_area(corners: Tensor) -> Tensor:
    p0, p1, p2 = corners.unbind(-2)
    return (p1[..., 0] - p0[..., 0]) * (p2[..., 1] - p0[..., 1]) - \
        (p2[..., 0] - p0[..., 0]) * (p1[..., 1] - p0[..., 1])


class _CompiledAntialias(torch.autograd.Function):
    """The blends of `_antialias` on the CPU by the numba kernels of `pixel_kernels`."""

    @staticmethod
    def forward(ctx, colour: Tensor, pix: Tensor, faces: np.ndarray, height: int, width: int,  # type: ignore[override]
                *pairs: np.ndarray) -> Tensor:
        c, p = colour.detach().contiguous().numpy(), pix.detach().contiguous().numpy()
        ctx.arrays, ctx.dtype = (c, p, faces, height, width) + pairs, colour.dtype
        return torch.from_numpy(antialias_forward(c, p, faces, height, width, *pairs))

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        g_colour, g_pix = antialias_backward(*ctx.arrays, grad.detach().to(ctx.dtype).contiguous().numpy())
        return (torch.from_numpy(g_colour), torch.from_numpy(g_pix)) + (None,) * 7


def _antialias(colour: Tensor, tri: Tensor, zbuf: Tensor, pix: Tensor, faces: Tensor,
               adjacency: np.ndarray, compiled: bool = False) -> Tensor:
    """Analytic silhouette antialiasing (see the module docstring, step 5).

    The pairs and their silhouette edges are found by `raster.silhouette_pairs` (discrete);
    the crossing `alpha` and the blend are computed here, differentiably.

    Args:
        colour: (B, H, W, C) shaded, composited image (C channels, e.g. RGB + coverage).
        tri: (B, H, W) int64 visible triangle, -1 none.
        zbuf: (B, H, W) camera z of the visible surface, +inf none.
        pix: (B, V, 2) projected vertices, pixels.
        faces: (T, 3) int64; adjacency: (T, 3) int64 (`triangle_adjacency`).
        compiled: blend by the numba kernels (CPU tensors) rather than torch ops.
    Returns:
        (B, H, W, C) the image with the silhouette blends added.
    """
    bsz, height, width, channels = colour.shape
    faces_np = np.ascontiguousarray(faces.cpu().numpy(), np.int64)
    pairs = silhouette_pairs(tri.cpu().numpy(), zbuf.cpu().numpy(), pix.detach().cpu().numpy(), faces_np, adjacency)
    if len(pairs[0]) == 0:
        return colour
    if compiled:
        return _CompiledAntialias.apply(colour.reshape(-1, channels), pix, faces_np, height, width,
                                        *pairs).reshape(colour.shape)
    occ, far, t, edge = (torch.from_numpy(a).to(colour.device) for a in pairs)
    flat = colour.reshape(-1, channels)
    batch = occ // (height * width)
    corners = pix[batch[:, None], faces[t]]  # (M, 3, 2)

    def centre(index: Tensor) -> Tensor:
        rem = index % (height * width)
        return torch.stack([rem % width, rem // width], -1).to(pix.dtype)

    rows = torch.arange(len(t), device=t.device)
    l_occ = screen_barycentrics(corners, centre(occ))[rows, edge]
    l_far = screen_barycentrics(corners, centre(far))[rows, edge]
    alpha = l_occ / (l_occ - l_far)  # where the edge crosses the segment, 0 at occ, 1 at far
    c_occ, c_far = flat[occ], flat[far]
    spill = alpha >= 0.5
    weight = torch.where(spill, alpha - 0.5, 0.5 - alpha)[:, None]
    delta = weight * torch.where(spill[:, None], c_occ - c_far, c_far - c_occ)
    return flat.index_add(0, torch.where(spill, far, occ), delta).reshape(colour.shape)


class _CompiledShade(torch.autograd.Function):
    """`shade_pixels` on the CPU by the numba kernels of `pixel_kernels` (forward and
    backward; the backward touches only the covered pixels and their corners)."""

    @staticmethod
    def forward(ctx, pix: Tensor, depth: Tensor, normals: Tensor, albedo: Tensor, sh: Tensor,  # type: ignore[override]
                pixels: np.ndarray, corners: np.ndarray, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
        arrays = tuple(t.detach().contiguous().numpy() for t in (pix, depth, normals, albedo, sh))
        colour, mu, dep = shade_forward(*arrays, pixels, corners, height, width)
        ctx.arrays, ctx.dtype = arrays + (pixels, corners, height, width), pix.dtype
        return torch.from_numpy(colour), torch.from_numpy(mu), torch.from_numpy(dep)

    @staticmethod
    def backward(ctx, g_colour: Tensor, g_mu: Tensor, g_depth: Tensor):  # type: ignore[override]
        arrays = ctx.arrays
        dt, n = arrays[0].dtype, len(arrays[5])

        def grad(g: Tensor | None, shape: tuple[int, ...]) -> np.ndarray:
            return np.zeros(shape, dt) if g is None else g.detach().to(ctx.dtype).contiguous().numpy()

        grads = shade_backward(*arrays, grad(g_colour, (n, 3)), grad(g_mu, (n, 3)), grad(g_depth, (n,)))
        return tuple(torch.from_numpy(g) for g in grads) + (None, None, None, None)


class _CompiledProjection(torch.autograd.Function):
    """Step 1 on the CPU: pixels and camera z of the vertices by `pixel_kernels.project_forward`
    (one pass, the arithmetic of `project_points_torch`), with a hand-written backward to the
    vertices, the camera, the intrinsics and the distortion."""

    @staticmethod
    def forward(ctx, vertices: Tensor, world_to_camera: Tensor, intrinsics: Tensor,  # type: ignore[override]
                distortion: Tensor | None) -> tuple[Tensor, Tensor]:
        ctx.set_materialize_grads(False)
        arrays = tuple(None if t is None else t.detach().contiguous().numpy()
                       for t in (vertices, world_to_camera, intrinsics, distortion))
        ctx.arrays, ctx.dtype = arrays, vertices.dtype
        pix, depth = project_forward(*arrays)
        return torch.from_numpy(pix), torch.from_numpy(depth)

    @staticmethod
    def backward(ctx, g_pix: Tensor | None, g_depth: Tensor | None):  # type: ignore[override]
        if g_pix is None and g_depth is None:
            return None, None, None, None
        grads = project_backward(*ctx.arrays, *(None if g is None else g.detach().to(ctx.dtype).contiguous().numpy()
                                                for g in (g_pix, g_depth)))
        return tuple(None if g is None else torch.from_numpy(g) for g in grads)


class _CompiledImage(torch.autograd.Function):
    """Steps 3-5 of the module docstring on the CPU as one autograd node: the covered pixels
    shaded straight into the image over its background (`pixel_kernels.shade_image`), the
    geometry buffer (depth, barycentrics) filled in the same pass, then the silhouette blends
    (`antialias_forward`). The backward reads the image and geometry gradients at the covered
    pixels and the blended pairs only (plus the background's at the uncovered pixels, when
    the background needs one). Same arithmetic as `shade_pixels` + compositing + `_antialias`."""

    @staticmethod
    def forward(ctx, pix: Tensor, depth: Tensor, normals: Tensor, albedo: Tensor, sh: Tensor,  # type: ignore[override]
                background: Tensor, pixels: np.ndarray, corners: np.ndarray, faces: np.ndarray, height: int,
                width: int, pairs: tuple[np.ndarray, ...] | None) -> tuple[Tensor, Tensor]:
        ctx.set_materialize_grads(False)
        arrays = tuple(t.detach().contiguous().numpy() for t in (pix, depth, normals, albedo, sh))
        bg = background.detach().to(pix.dtype).contiguous().numpy()
        image, geometry = shade_image(*arrays, pixels, corners, height, width, bg)
        blended = antialias_forward(image, arrays[0], faces, height, width, *pairs) if pairs else image
        ctx.arrays = arrays + (pixels, corners, height, width)
        ctx.image, ctx.faces, ctx.pairs, ctx.bg_shape = image, faces, pairs, tuple(background.shape)
        ctx.dtype = pix.dtype
        shape = (depth.shape[0], height, width, 4)
        return torch.from_numpy(blended).reshape(shape), torch.from_numpy(geometry).reshape(shape)

    @staticmethod
    def backward(ctx, g_image: Tensor | None, g_geometry: Tensor | None):  # type: ignore[override]
        if g_image is None and g_geometry is None:
            return (None,) * 12
        arrays = ctx.arrays
        pix = arrays[0]
        g_colour = g_pix = None
        if g_image is not None:
            g_colour = g_image.detach().to(ctx.dtype).contiguous().numpy().reshape(-1, 4)
            if ctx.pairs:
                g_colour, g_pix = antialias_backward(ctx.image, pix, ctx.faces, arrays[7], arrays[8], *ctx.pairs,
                                                     g_colour)
        g_geo = None if g_geometry is None else g_geometry.detach().to(ctx.dtype).contiguous().numpy().reshape(-1, 4)
        grads = list(shade_image_backward(*arrays, g_colour, g_geo))
        if g_pix is not None:
            grads[0] += g_pix
        g_background = None
        if ctx.needs_input_grad[5] and g_colour is not None:  # the image's gradient at the uncovered pixels
            g = torch.from_numpy(g_colour[:, :3].copy())
            g[torch.from_numpy(arrays[5])] = 0.0
            g = g.reshape(arrays[1].shape[0], -1, 3)
            g_background = g.sum(0, keepdim=True) if ctx.bg_shape[0] == 1 else g
            if ctx.bg_shape[1] == 1:
                g_background = g_background.sum(1, keepdim=True)
        return tuple(torch.from_numpy(g) for g in grads) + (g_background,) + (None,) * 6


def _shade_torch(pix: Tensor, depth: Tensor, normals: Tensor, albedo: Tensor, sh: Tensor, pixels: Tensor,
                 corners: Tensor, height: int, width: int) -> tuple[Tensor, Tensor, Tensor]:
    """`shade_pixels` in torch ops (any device; autograd)."""
    bsz, nv = depth.shape
    dt = pix.dtype
    batch = pixels // (height * width)
    rem = pixels % (height * width)
    centres = torch.stack([rem % width, rem // width], -1).to(dt)
    flat_corner = (batch[:, None] * nv + corners).reshape(-1)  # rows of (B * V, ...) tensors
    tri_pix = pix.reshape(-1, 2).index_select(0, flat_corner).reshape(-1, 3, 2)
    lam = screen_barycentrics(tri_pix, centres)
    mu = lam / depth.reshape(-1).index_select(0, flat_corner).reshape(-1, 3)
    inv_z = mu.sum(-1)
    mu = mu / inv_z[:, None]
    attrs = torch.cat([albedo.expand(bsz, nv, 3), normals], -1).reshape(bsz * nv, 6)
    values = (mu[:, :, None] * attrs.index_select(0, flat_corner).reshape(-1, 3, 6)).sum(1)  # (N, 6)
    n = values[:, 3:6]
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(n)  # (N, 9)
    if sh.shape[0] == 1:
        irradiance = basis @ sh[0]
    else:
        irradiance = torch.bmm(basis[:, None, :], sh.index_select(0, batch))[:, 0]
    return values[:, :3] * irradiance, mu, 1.0 / inv_z


def shade_pixels(pix: Tensor, depth: Tensor, normals: Tensor, albedo: Tensor, sh: Tensor, pixels: Tensor,
                 corners: Tensor, height: int, width: int, *, compiled: bool | None = None
                 ) -> tuple[Tensor, Tensor, Tensor]:
    """Shade the covered pixels of B images (steps 3 and 4 of the module docstring).

    For pixel p of triangle (i0, i1, i2): the screen barycentrics `l` of its centre, made
    perspective-correct (`mu_k = (l_k / z_k) / S`, `S = sum_j l_j / z_j`), the interpolated
    albedo and normal (normalized) and `colour = albedo * sum_k sh[k] Y_k(n)`.

    Args:
        pix: (B, V, 2) projected vertices, pixels.
        depth: (B, V) their camera-frame z, cm.
        normals: (B, V, 3) unit vertex normals, world frame.
        albedo: (B or 1, V, 3) linear; sh: (B or 1, 9, 3) (`sh_basis` order).
        pixels: (N,) int64 flat indices into (B, H, W) of the covered pixels.
        corners: (N, 3) int64 vertex indices of the triangle covering each.
        height, width: image size, pixels.
        compiled: True = numba kernels (CPU only), False = torch ops, None = the kernels on
            the CPU in float32 / float64 (the two agree to rounding; differentiable either way).
    Returns:
        colour (N, 3), mu (N, 3) perspective-correct barycentrics (corner order of `corners`),
        depth (N,) camera z of the visible point, cm.
    """
    if _compiled(pix.device, pix.dtype, compiled):
        return _CompiledShade.apply(pix, depth, normals, albedo, sh,
                                    np.ascontiguousarray(pixels.numpy(), np.int64),
                                    np.ascontiguousarray(corners.numpy(), np.int64), height, width)
    return _shade_torch(pix, depth, normals, albedo, sh, pixels, corners, height, width)


def render_mesh(vertices: Tensor, faces: Tensor | np.ndarray, world_to_camera: Tensor,
                intrinsics: Tensor, height: int, width: int, *, albedo: Tensor, sh: Tensor,
                background: Tensor | Sequence[float] = (0.0, 0.0, 0.0),
                distortion: Tensor | None = None, antialias: bool = True, supersample: int = 1,
                near: float = 1e-3, adjacency: np.ndarray | Tensor | None = None,
                compiled: bool | None = None) -> RenderOutput:
    """Render B views of a mesh with per-vertex albedo and SH lighting (differentiable).

    Args:
        vertices: (B, V, 3) world positions, cm.
        faces: (T, 3) int vertex indices (the triangles to draw).
        world_to_camera: (B, 4, 4) rigid `T_camera_world` (OpenCV camera: x right, y down,
            z forward).
        intrinsics: (B, 4) (fx, fy, cx, cy), pixels of the H x W output.
        height, width: output size, pixels.
        albedo: (B or 1, V, 3) linear albedo per vertex.
        sh: (B or 1, 9, 3) SH irradiance coefficients per colour channel, world frame
            (`sh_basis` order; `sh_from_lights` builds them).
        background: (B or 1, H, W, 3) image, or (3,) colour, linear.
        distortion: (B, 2) (k1, k2) or None. Vertices are distorted; edges stay straight
            in the image (fine for the mild distortion of face cameras).
        antialias: analytic silhouette antialiasing (gradients at silhouettes need it).
        supersample: render at s times the size and average s x s blocks (s = 2 helps the
            landmark network read thin features such as lips and brows).
        near: triangles with a corner closer than this (cm, camera z) are not drawn.
        adjacency: (T, 3) `triangle_adjacency(faces)`, computed when None (pass it when
            rendering the same topology often).
        compiled: the shading, normals and antialiasing by the numba kernels of
            `pixel_kernels` (True, CPU tensors only) or torch ops (False); None: the kernels on
            the CPU in float32 / float64, torch ops otherwise (the two agree to rounding).
    Returns:
        RenderOutput; with `supersample > 1`, image and alpha are block averages and
        depth / triangle / barycentrics are those of sample (s // 2, s // 2) of each block.
    Raises:
        ValueError: shapes that do not match (named, with the shapes found).
    """
    if vertices.ndim != 3 or vertices.shape[-1] != 3:
        raise ValueError(f"vertices: expected shape (B, V, 3), found {tuple(vertices.shape)}")
    bsz, nv = vertices.shape[:2]
    dev, dt = vertices.device, vertices.dtype
    faces_t = torch.as_tensor(np.asarray(faces) if not isinstance(faces, Tensor) else faces,
                              device=dev).long()
    if faces_t.ndim != 2 or faces_t.shape[1] != 3:
        raise ValueError(f"faces: expected shape (T, 3), found {tuple(faces_t.shape)}")
    world_to_camera = torch.as_tensor(world_to_camera, device=dev, dtype=dt)
    intrinsics = torch.as_tensor(intrinsics, device=dev, dtype=dt)
    if tuple(world_to_camera.shape) != (bsz, 4, 4):
        raise ValueError(f"world_to_camera: expected shape ({bsz}, 4, 4), found "
                         f"{tuple(world_to_camera.shape)}")
    if tuple(intrinsics.shape) != (bsz, 4):
        raise ValueError(f"intrinsics: expected shape ({bsz}, 4), found {tuple(intrinsics.shape)}")
    albedo = torch.as_tensor(albedo, device=dev, dtype=dt)
    sh = torch.as_tensor(sh, device=dev, dtype=dt)
    if albedo.ndim != 3 or albedo.shape[0] not in (1, bsz) or tuple(albedo.shape[1:]) != (nv, 3):
        raise ValueError(f"albedo: expected shape ({bsz} or 1, {nv}, 3), found {tuple(albedo.shape)}")
    if sh.ndim != 3 or sh.shape[0] not in (1, bsz) or tuple(sh.shape[1:]) != (9, 3):
        raise ValueError(f"sh: expected shape ({bsz} or 1, 9, 3), found {tuple(sh.shape)}")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample: expected an integer >= 1, found {supersample}")
    hs, ws = height * s, width * s
    background = torch.as_tensor(background, device=dev, dtype=dt)
    if background.ndim == 1:
        if background.shape != (3,):
            raise ValueError(f"background: expected (3,) or (B, H, W, 3), found {tuple(background.shape)}")
        background_rows = background.reshape(1, 1, 3)  # (B or 1, H * W or 1, 3)
    else:
        if background.ndim != 4 or background.shape[0] not in (1, bsz) or \
                tuple(background.shape[1:]) != (height, width, 3):
            raise ValueError(f"background: expected shape ({bsz} or 1, {height}, {width}, 3), found "
                             f"{tuple(background.shape)}")
        if s > 1:
            background = background.repeat_interleave(s, 1).repeat_interleave(s, 2)
        background_rows = background.reshape(background.shape[0], hs * ws, 3)
    if s > 1:  # pixel centre convention: x_s = s (x + 1/2) - 1/2
        intrinsics = torch.cat([intrinsics[:, :2] * s, (intrinsics[:, 2:] + 0.5) * s - 0.5], -1)

    use_kernels = _compiled(dev, dt, compiled)
    if distortion is not None:
        distortion = torch.as_tensor(distortion, device=dev, dtype=dt)
    if use_kernels and (distortion is None or tuple(distortion.shape) == (bsz, 2)):
        pix, depth_v = _CompiledProjection.apply(vertices, world_to_camera, intrinsics, distortion)
    else:
        # camera z of the vertices (B, V): the third row of T_camera_world
        depth_v = (vertices @ world_to_camera[:, 2:3, :3].transpose(1, 2))[..., 0] + world_to_camera[:, 2:3, 3]
        pix = project_points_torch(vertices, world_to_camera, intrinsics, distortion)  # (B, V, 2)
    faces_np = np.ascontiguousarray(faces_t.cpu().numpy(), np.int64)
    tri_np, z_np = rasterize_triangles(pix.detach().cpu().numpy(), depth_v.detach().cpu().numpy(),
                                       faces_np, hs, ws, near, triangle_dtype=np.int64)
    tri = torch.from_numpy(tri_np).to(dev)
    zbuf = torch.from_numpy(z_np).to(dev)

    idx_np, corners_np = covered_pixels(tri_np, faces_np)  # the covered pixels (ascending), their corners
    idx = torch.from_numpy(idx_np).to(dev)
    corners = torch.from_numpy(corners_np).to(dev)
    normals = vertex_normals(vertices, faces_t, compiled=use_kernels)
    adj = None
    if antialias:
        adj = triangle_adjacency(faces_np) if adjacency is None else \
            np.asarray(adjacency.cpu() if isinstance(adjacency, Tensor) else adjacency, np.int64)
    if use_kernels:  # shading, compositing and blends in one pass each way (`_CompiledImage`)
        faces_c = np.ascontiguousarray(faces_np, np.int64)
        pairs = None
        if antialias:
            pairs = silhouette_pairs(tri_np, z_np, pix.detach().numpy(), faces_c, adj)
            pairs = pairs if len(pairs[0]) else None
        image, geometry = _CompiledImage.apply(pix, depth_v, normals, albedo, sh, background_rows, idx_np,
                                               corners.numpy(), faces_c, hs, ws, pairs)
        depth = geometry[..., 0]
        bary = geometry[..., 1:4]
    else:
        shaded, mu, depth_p = shade_pixels(pix, depth_v, normals, albedo, sh, idx, corners, hs, ws,
                                           compiled=False)
        npix = bsz * hs * ws
        # separate buffers: a loss on the image alone then never back-propagates through depth
        # and barycentrics (slices of one shared buffer would each cost a full-size zero fill)
        ones = torch.ones(len(idx), 1, device=dev, dtype=dt)
        canvas = torch.cat([background_rows.expand(bsz, hs * ws, 3).reshape(npix, 3),
                            torch.zeros(npix, 1, device=dev, dtype=dt)], -1)
        image = canvas.index_put((idx,), torch.cat([shaded, ones], -1)).reshape(bsz, hs, ws, 4)
        geometry = torch.zeros(npix, 4, device=dev, dtype=dt).index_put(
            (idx,), torch.cat([depth_p[:, None], mu], -1))
        if antialias:
            image = _antialias(image, tri, zbuf, pix, faces_t, adj, False)
        depth = geometry[:, 0].reshape(bsz, hs, ws)
        bary = geometry[:, 1:4].reshape(bsz, hs, ws, 3)
    if s > 1:
        image = box_downsample(image, s)
        c = s // 2
        depth, tri, bary = depth[:, c::s, c::s], tri[:, c::s, c::s], bary[:, c::s, c::s]
    return RenderOutput(image[..., :3], image[..., 3], depth, tri, bary)
