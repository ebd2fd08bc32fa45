"""Geometric render flow: the exact screen-space motion of a rendered surface between two poses.

For each pixel centre `x` of frame 1 covered by the mesh, the visible surface point is found
by rasterizing frame 1 (`nodes.render.renderer.render_mesh`: triangle + perspective-correct
barycentrics). The same surface point (same triangle, same barycentrics) is then placed with
frame 2's vertices and projected: `flow(x) = pi(sum_j mu_j V2[t_j]) - x`.

Differentiability: the barycentrics are recomputed in torch from frame 1's projected corners
(`screen_barycentrics` of the pixel centre, made perspective-correct with frame 1's depths),
so the flow is differentiable in both vertex sets: in `vertices2` through the projection of
the moved point, and in `vertices1` through which point of the triangle lies under the pixel
(exact inside a triangle; the triangle ids themselves are discrete). Occlusion in frame 2 is
not tested (a point hidden in frame 2 still gets its geometric motion), as for optical flow
ground truth.

Units: vertices cm (world frame), flow pixels (x right, y down). Torch at module level:
import from node `run()` methods only.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import project_points_torch
from ..render.raster import rasterize_triangles
from ..render.renderer import screen_barycentrics

__all__ = ["Coverage", "coverage", "surface_flow", "render_flow", "flow_image"]


class Coverage(NamedTuple):
    """The covered pixels of frame 1, flattened and padded to the same count per batch element.

    Attributes:
        pixel: (B, N) int64 flat pixel index y * W + x (0 for padding).
        triangle: (B, N) int64 triangle index into `faces` (0 for padding).
        valid: (B, N) bool, False for padding.
        height, width: image size, pixels.
    """

    pixel: Tensor
    triangle: Tensor
    valid: Tensor
    height: int
    width: int


def coverage(vertices: Tensor, faces: Tensor, world_to_camera: Tensor, intrinsics: Tensor, height: int,
             width: int, *, near: float = 0.1, stride: int = 1) -> Coverage:
    """Rasterize (no gradients) and list the covered pixels of each view.

    Args:
        vertices: (B, V, 3) world positions, cm.
        faces: (T, 3) int64.
        world_to_camera: (B, 4, 4); intrinsics: (B, 4) fx fy cx cy, pixels.
        height, width: image size, pixels.
        near: triangles closer than this (camera z, cm) are not drawn.
        stride: keep every stride-th pixel in x and y (fewer residuals for solvers).
    Returns:
        Coverage.
    """
    with torch.no_grad():
        rot, trans = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
        depth = (vertices @ rot.transpose(1, 2) + trans[:, None])[..., 2]
        pix = project_points_torch(vertices, world_to_camera, intrinsics)
        tri, _ = rasterize_triangles(pix.cpu().numpy(), depth.cpu().numpy(), faces.cpu().numpy(), height,
                                     width, near)
    if stride > 1:
        keep = np.zeros((height, width), bool)
        keep[::stride, ::stride] = True
        tri = np.where(keep[None], tri, -1)
    flat = tri.reshape(len(tri), -1)
    counts = (flat >= 0).sum(1)
    n = max(int(counts.max(initial=0)), 1)
    pixel = np.zeros((len(tri), n), np.int64)
    triangle = np.zeros((len(tri), n), np.int64)
    valid = np.zeros((len(tri), n), bool)
    for b in range(len(tri)):  # loop over views only; pixels are gathered vectorized
        idx = np.flatnonzero(flat[b] >= 0)
        pixel[b, :len(idx)] = idx
        triangle[b, :len(idx)] = flat[b, idx]
        valid[b, :len(idx)] = True
    dev = vertices.device
    return Coverage(torch.from_numpy(pixel).to(dev), torch.from_numpy(triangle).to(dev),
                    torch.from_numpy(valid).to(dev), height, width)


def surface_flow(vertices1: Tensor, vertices2: Tensor, faces: Tensor, cover: Coverage, world_to_camera: Tensor,
                 intrinsics: Tensor) -> Tensor:
    """Flow of the covered pixels of frame 1 to frame 2 (module docstring).

    Args:
        vertices1, vertices2: (B, V, 3) world positions at frames 1 and 2, cm (or the corner
            positions only: (B, N, 3, 3) per covered pixel, see `Coverage`; then `faces` is
            ignored).
        faces: (T, 3) int64.
        cover: the covered pixels of frame 1 (`coverage` of `vertices1`).
        world_to_camera: (B, 4, 4); intrinsics: (B, 4).
    Returns:
        (B, N, 2) flow, pixels; 0 at padding entries.
    """
    if vertices1.ndim == 4:
        c1, c2 = vertices1, vertices2
    else:
        b = vertices1.shape[0]
        corner = faces[cover.triangle]  # (B, N, 3)
        bidx = torch.arange(b, device=vertices1.device)[:, None, None]
        c1, c2 = vertices1[bidx, corner], vertices2[bidx, corner]  # (B, N, 3, 3)
    bsz, n = c1.shape[:2]
    p1 = project_points_torch(c1.reshape(bsz, -1, 3), world_to_camera, intrinsics).reshape(bsz, n, 3, 2)
    rot, trans = world_to_camera[:, :3, :3], world_to_camera[:, :3, 3]
    z1 = (c1.reshape(bsz, -1, 3) @ rot.transpose(1, 2) + trans[:, None])[..., 2].reshape(bsz, n, 3)
    x = (cover.pixel % cover.width).to(c1.dtype)
    y = torch.div(cover.pixel, cover.width, rounding_mode="floor").to(c1.dtype)
    centre = torch.stack([x, y], -1)
    lam = screen_barycentrics(p1, centre)
    lam = torch.where(cover.valid[..., None], lam, torch.full_like(lam, 1.0 / 3.0))
    mu = lam / z1
    mu = mu / mu.sum(-1, keepdim=True)
    point2 = (mu[..., None] * c2).sum(-2)  # (B, N, 3)
    q = project_points_torch(point2, world_to_camera, intrinsics)
    return torch.where(cover.valid[..., None], q - centre, torch.zeros_like(q))


def flow_image(values: Tensor, cover: Coverage) -> tuple[Tensor, Tensor]:
    """Scatter per-pixel values (B, N, 2) into images (B, 2, H, W) and a (B, H, W) bool mask."""
    bsz = values.shape[0]
    hw = cover.height * cover.width
    out = values.new_zeros(bsz, hw, 2)
    out = out.scatter(1, cover.pixel[..., None].expand(-1, -1, 2), torch.where(cover.valid[..., None], values, 0))
    mask = torch.zeros(bsz, hw, dtype=torch.bool, device=values.device)
    mask = mask.scatter(1, cover.pixel, cover.valid)
    return out.permute(0, 2, 1).reshape(bsz, 2, cover.height, cover.width), mask.reshape(bsz, cover.height,
                                                                                          cover.width)


def render_flow(vertices1: Tensor, vertices2: Tensor, faces: Tensor, world_to_camera: Tensor, intrinsics: Tensor,
                height: int, width: int, *, near: float = 0.1) -> tuple[Tensor, Tensor]:
    """Dense geometric flow image from frame 1 to frame 2 of a rendered mesh.

    Args:
        vertices1, vertices2: (B, V, 3) world positions, cm.
        faces: (T, 3) int64 (the triangles drawn).
        world_to_camera: (B, 4, 4); intrinsics: (B, 4) fx fy cx cy, pixels.
        height, width: image size, pixels.
        near: near plane, cm.
    Returns:
        flow (B, 2, H, W) pixels (0 where not covered) and covered (B, H, W) bool.

    Example:
        >>> import torch
        >>> v = torch.tensor([[[-1.0, -1, 10], [1, -1, 10], [0, 1, 10]]])
        >>> e, k = torch.eye(4)[None], torch.tensor([[50.0, 50, 15.5, 15.5]])
        >>> f, m = render_flow(v, v + torch.tensor([0.2, 0, 0]), torch.tensor([[0, 1, 2]]), e, k, 32, 32)
        >>> round(f[0, 0][m[0]].mean().item(), 3)
        1.0
    """
    faces = torch.as_tensor(faces, device=vertices1.device).long()
    cover = coverage(vertices1, faces, world_to_camera, intrinsics, height, width, near=near)
    values = surface_flow(vertices1, vertices2, faces, cover, world_to_camera, intrinsics)
    return flow_image(values, cover)
