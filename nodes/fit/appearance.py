"""Per-vertex albedo and 9-coefficient SH lighting from one plate and a fitted pose (the
paper's appearance step: estimated once, on a near-neutral frame, and used for every later
render).

With the head posed on the plate and rendered at the plate's size, every covered pixel p
(away from silhouettes) sees a surface point with normal n_p and barycentric weights
beta_pv on its triangle's corners. Lambertian shading `I_p = a_p (Y(n_p) . sh)`:

1. lighting: linear least squares for `sh` (9 x 3) with the albedo fixed to the default
   appearance's, `min sum_p |I_p - a0_p (Y(n_p) sh)|^2` (over the face's pixels);
2. albedo: the image divided by the shading, projected on the vertices and pulled toward the
   default where the plate says little: `a_v = (sum_p beta_pv I_p / s_p + mu a0_v) /
   (sum_p beta_pv + mu)`; vertices not seen keep `a0_v`.

The background colour is the median of the plate's uncovered pixels. Torch is imported at
the top: import this module from node `run()` methods only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from ..render.renderer import render_mesh, sh_basis, vertex_normals

__all__ = ["Appearance", "albedo_smoothing_steps", "estimate_appearance", "estimate_noise"]


class Appearance(NamedTuple):
    """albedo (V, 3) linear in [0, 1], sh (9, 3), background (3,) linear, seen (V,) bool (a pixel of
    the plate fell on the vertex's triangles)."""

    albedo: np.ndarray
    sh: np.ndarray
    background: np.ndarray
    seen: np.ndarray


def estimate_noise(image: np.ndarray) -> float:
    """Standard deviation of a plate's pixel noise, robustly (Immerkaer 1996, with a median).

    The 3 x 3 kernel [[1, -2, 1], [-2, 4, -2], [1, -2, 1]] cancels smooth image content
    (it is the product of two second differences); on white noise of deviation sigma its
    response has deviation 6 sigma. The median of its absolute response over every pixel and
    channel, / (0.6745 * 6), is sigma where most pixels are smooth (edges and texture are a
    minority the median ignores).

    Args:
        image: (H, W, C) linear plate.
    Returns:
        sigma in the image's units (0 for images under 3 x 3).
    """
    img = np.asarray(image, np.float64)
    if img.ndim == 2:
        img = img[..., None]
    if img.shape[0] < 3 or img.shape[1] < 3:
        return 0.0
    d = img[:, :-2] - 2 * img[:, 1:-1] + img[:, 2:]  # second difference along x
    r = d[:-2] - 2 * d[1:-1] + d[2:]  # and along y
    return float(np.median(np.abs(r)) / (0.6745 * 6.0))


def albedo_smoothing_steps(noise: float, target: float = 0.01) -> int:
    """Steps of evidence pooling (`estimate_appearance`'s `smooth_steps`) for a plate of `noise`.

    A vertex's albedo estimate carries about one plate pixel's noise (a face of about 100 px has
    about a pixel per vertex); pooling n pixels divides it by sqrt(n), and k walk steps pool
    about 1 + k / 2 of them. The steps bring the albedo's noise to `target` (linear units):
    none for a clean plate (noise <= target), 16 for noise 0.03.
    """
    if not np.isfinite(noise) or noise <= target:
        return 0
    return int(min(np.ceil(2.0 * ((noise / target) ** 2 - 1.0)), 64))


def _lazy_walk(faces: np.ndarray, count: int):
    """(V, V) scipy.sparse `(I + Deg^-1 A) / 2` of the triangles' edges (the walk of `smooth_steps`)."""
    from scipy import sparse

    from ..geometry.mesh import uniform_laplacian

    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), 1), axis=0)
    return (sparse.identity(count, format="csr") - 0.5 * uniform_laplacian(edges, count)).tocsr()


def _pool(acc: torch.Tensor, wsum: torch.Tensor, faces: np.ndarray, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    """`steps` steps of `_lazy_walk` on per-vertex evidence: sums (V, 3) and weights (V,)."""
    walk = _lazy_walk(np.asarray(faces, np.int64), acc.shape[0])
    evidence = np.concatenate([acc.numpy(), wsum.numpy()[:, None]], 1).astype(np.float64)
    for _ in range(int(steps)):
        evidence = walk @ evidence
    return torch.as_tensor(evidence[:, :3], dtype=acc.dtype), torch.as_tensor(evidence[:, 3], dtype=acc.dtype)


def estimate_appearance(image: np.ndarray, vertices: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray,
                        intrinsics: np.ndarray, default_albedo: np.ndarray, *, distortion: np.ndarray | None = None,
                        prior_weight: float = 1.0, region: np.ndarray | None = None,
                        smooth_steps: int = 0, relative_steps: int = 0, sh: np.ndarray | None = None) -> Appearance:
    """Estimate albedo and SH lighting from one or several linear plates (see the module docstring).

    With several frames (the head seen in several poses, the light fixed in the world) the
    lighting is one least-squares fit over every frame's pixels and each vertex's albedo is the
    mean of its frames' estimates, each pixel weighted by `cos^2` of its surface's angle to the
    view (grazing pixels are blurred and mostly shadow). One frame's painting carries that
    frame's pose error into every later render; several frames average it.

    Args:
        image: (H, W, 3) linear RGB plate, or (N, H, W, 3) N of them.
        vertices: (V, 3) the fitted head, world frame, cm, or (N, V, 3) one per plate.
        faces: (T, 3) triangles drawn.
        world_to_camera: (4, 4); intrinsics: (4,) fx fy cx cy, pixels; distortion: (2,) or None.
        default_albedo: (V, 3) the prior albedo a0.
        prior_weight: mu, in pixels' worth of evidence.
        region: (V,) bool vertices whose pixels fit the lighting (default: all).
        smooth_steps: k, steps of a lazy random walk on the mesh's edges (`(I + Deg^-1 A) / 2`)
            that pool each vertex's evidence with its neighbours' before the division: the
            albedo of a noisy plate is the mean over a neighbourhood that grows with k (about
            1 + k rings' worth of pixels), not one pixel's noise (`albedo_smoothing_steps`).
        relative_steps: 0 = the albedo is painted (the plate divided by the shading). k > 0 = the
            albedo is the default's times the plate's ratio to it, that ratio's evidence pooled by
            k more walk steps: the skin's colour comes from the plate, the features (brows, lips,
            eyes) stay where the model puts them. A painting made at a wrong pose reproduces the
            plate at that pose, so a later fit against it keeps that pose's error; a pooled ratio
            carries little of the features' positions.
        sh: (9, 3) lighting to paint under instead of fitting it (e.g. fitted to more frames).
    Returns:
        Appearance.
    """
    images = np.asarray(image)[None] if np.ndim(image) == 3 else np.asarray(image)
    verts_np = np.asarray(vertices)[None] if np.ndim(vertices) == 2 else np.asarray(vertices)
    if len(images) != len(verts_np):
        raise ValueError(f"vertices: expected one head per plate ({len(images)}), found {len(verts_np)}")
    n_f, h, w = images.shape[:3]
    dt = torch.float32
    verts = torch.as_tensor(verts_np, dtype=dt)
    faces_t = torch.as_tensor(np.asarray(faces, np.int64))
    a0 = torch.as_tensor(default_albedo, dtype=dt)
    w2c = torch.as_tensor(world_to_camera, dtype=dt)
    with torch.no_grad():
        out = render_mesh(verts, faces_t, w2c[None].expand(n_f, 4, 4),
                          torch.as_tensor(intrinsics, dtype=dt)[None].expand(n_f, 4), h, w, albedo=a0[None],
                          sh=torch.zeros(1, 9, 3), distortion=None if distortion is None else
                          torch.as_tensor(distortion, dtype=dt)[None].expand(n_f, 2), antialias=False)
        tri = out.triangle
        covered = tri >= 0  # (N, H, W)
        interior = covered.clone()  # drop silhouette pixels (their colour mixes the background)
        interior[:, 1:] &= covered[:, :-1]
        interior[:, :-1] &= covered[:, 1:]
        interior[:, :, 1:] &= covered[:, :, :-1]
        interior[:, :, :-1] &= covered[:, :, 1:]
        img = torch.as_tensor(images[..., :3], dtype=dt)
        bg = img[~covered].median(0).values if (~covered).any() else torch.full((3,), 0.2)
        fs, ys, xs = torch.nonzero(interior, as_tuple=True)
        corner = faces_t[tri[fs, ys, xs]]  # (N, 3)
        bary = out.barycentrics[fs, ys, xs]  # (N, 3)
        normals = vertex_normals(verts, faces_t)  # (F, V, 3)
        n = (bary[..., None] * normals[fs[:, None], corner]).sum(1)
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        point = (bary[..., None] * verts[fs[:, None], corner]).sum(1)  # world, cm
        centre = -w2c[:3, :3].T @ w2c[:3, 3]
        view = centre - point
        cos = (n * view).sum(-1) / view.norm(dim=-1).clamp_min(1e-9)
        weight = cos.clamp_min(0.0) ** 2 if n_f > 1 else torch.ones_like(cos)
        basis = sh_basis(n)  # (N, 9)
        colour = img[fs, ys, xs]  # (N, 3)
        a_p = (bary[..., None] * a0[corner]).sum(1)
        use = torch.ones(len(ys), dtype=torch.bool)
        if region is not None:
            use = torch.as_tensor(region)[corner].all(1)
        if sh is not None:
            sh = torch.as_tensor(np.asarray(sh), dtype=dt).reshape(9, 3)
        else:
            sh = torch.zeros(9, 3)
            for ch in range(3):
                a = basis[use] * a_p[use, ch:ch + 1]
                sol = torch.linalg.lstsq(a.double(), colour[use, ch:ch + 1].double()).solution
                sh[:, ch] = sol[:, 0].float()
        shading = (basis @ sh).clamp_min(0.05)  # (N, 3)
        ratio = colour / shading
        if relative_steps > 0:  # evidence of the albedo's ratio to the default
            ratio = ratio / a_p.clamp_min(0.02)
        v = a0.shape[0]
        bw = bary * weight[:, None]  # (N, 3)
        acc = torch.zeros(v, 3).index_add(0, corner.reshape(-1), (bw[..., None] * ratio[:, None]).reshape(-1, 3))
        wsum = torch.zeros(v).index_add(0, corner.reshape(-1), bw.reshape(-1))
        seen = wsum > 0  # evidence of the vertex's own pixels (pooling spreads it)
        if smooth_steps + relative_steps > 0:
            acc, wsum = _pool(acc, wsum, faces, smooth_steps + relative_steps)
        if relative_steps > 0:
            albedo = (a0 * (acc + prior_weight) / (wsum[:, None] + prior_weight)).clamp(0.0, 1.0)
        else:
            albedo = ((acc + prior_weight * a0) / (wsum[:, None] + prior_weight)).clamp(0.0, 1.0)
    return Appearance(albedo.numpy(), sh.numpy(), bg.numpy(), seen.numpy())
