"""Renders of the posed head in the plate's crop boxes, read by the landmark network, and
the anchors that tie the network's points to the head's surface.

The render of camera c in frame f is not made at the plate's size and then cropped: the
crop box (x0, y0, x1, y1) of the plate (side s pixels) is rendered directly at S x S pixels
with the camera's intrinsics mapped into the crop (`crop_intrinsics`: `f' = f S / s`,
`c' = (c - x0) S / s - 1/2`), which is what `crop_and_resize` of a full-size render would
give, at a cost that does not grow with the plate's size. Render pixel j's centre is at
image coordinate `x0 + (j + 1/2) s / S` (`crop_to_image`).

This module imports torch at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import project_points_torch
from ..landmarks.correspondence import MEDIAPIPE_TO_68
from ..landmarks.network import MESH_SIZE, srgb_encode
from ..render.renderer import render_mesh, triangle_adjacency

__all__ = ["FitModel", "FitViews", "Anchors", "crop_intrinsics", "crop_to_image", "image_to_crop",
           "render_crops", "network_points", "landmark_anchors", "anchors_from_render"]


@dataclass
class FitModel:
    """The face model and its appearance as tensors for fitting.

    Attributes:
        neutral: (V, 3) neutral with the identity applied, cm, model frame (y up, z out of the face).
        deltas: (K, V, 3) expression shapes, cm per unit weight.
        names: K expression names.
        faces: (T, 3) int64 triangles drawn (hidden parts removed).
        adjacency: (T, 3) `triangle_adjacency(faces)`.
        landmarks: (68,) vertex of each Multi-PIE point.
        albedo: (1, V, 3) linear; sh: (1, 9, 3); background: (3,) linear.
    """

    neutral: Tensor
    deltas: Tensor
    names: list[str]
    faces: np.ndarray
    adjacency: np.ndarray
    landmarks: np.ndarray
    albedo: Tensor
    sh: Tensor
    background: Tensor

    @classmethod
    def build(cls, neutral: np.ndarray, deltas: np.ndarray, names: list[str], faces: np.ndarray,
              landmarks: np.ndarray, albedo: np.ndarray, sh: np.ndarray, background: np.ndarray,
              device: str = "cpu") -> "FitModel":
        faces = np.asarray(faces, np.int64)
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
        return cls(t(neutral), t(deltas), list(names), faces, triangle_adjacency(faces),
                   np.asarray(landmarks, np.int64), t(albedo)[None], t(sh)[None], t(background))

    def vertices(self, weights: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
        """(B, K) weights, (B, 3, 3), (B, 3) cm -> (B, V, 3) world vertices, cm."""
        k, v = self.deltas.shape[:2]
        local = self.neutral.reshape(-1) + weights @ self.deltas.reshape(k, -1)
        return local.reshape(-1, v, 3) @ rot.transpose(1, 2) + trans[:, None]


@dataclass
class FitViews:
    """The plate's landmarks in every frame and camera, and the cameras.

    Attributes:
        target: (B, C, 68, 2) the network's 68 points on the plate, image pixels (0 where unseen).
        boxes: (B, C, 4) crop boxes x0 y0 x1 y1, pixels (a dummy box where unseen).
        seen: (B, C) bool, the face was found in that view.
        world_to_camera: (C, 4, 4); intrinsics: (C, 4) fx fy cx cy; distortion: (C, 2) or None.
        image_size: (C, 2) width, height of each camera's plate, pixels.
    """

    target: Tensor
    boxes: Tensor
    seen: Tensor
    world_to_camera: Tensor
    intrinsics: Tensor
    distortion: Tensor | None
    image_size: Tensor

    @property
    def scale(self) -> Tensor:
        """(B, C) 256 / crop side, 0 where unseen (the energy's unit, `nodes.fit.energy`)."""
        side = (self.boxes[..., 2] - self.boxes[..., 0]).clamp_min(1e-6)
        return torch.where(self.seen, 256.0 / side, torch.zeros_like(side))


class Anchors(NamedTuple):
    """Where each render landmark sits on the head.

    Attributes:
        vertices: (B, C, L, 3) int64 triangle corners.
        bary: (B, C, L, 3) barycentric weights (sum 1).
        offset: (B, C, L, 2) network point minus the anchor's projection at anchoring time, pixels.
    """

    vertices: Tensor
    bary: Tensor
    offset: Tensor


def crop_intrinsics(intrinsics: Tensor, boxes: Tensor, size: int) -> Tensor:
    """Intrinsics of the S x S render of a crop box (see the module docstring).

    Args:
        intrinsics: (C, 4) fx fy cx cy of the plate, pixels.
        boxes: (B, C, 4) x0 y0 x1 y1, pixels.
        size: S.
    Returns:
        (B, C, 4) fx fy cx cy of the render, render pixels.
    """
    k = size / (boxes[..., 2] - boxes[..., 0]).clamp_min(1e-6)
    fx, fy, cx, cy = intrinsics[None].expand(*boxes.shape[:2], 4).unbind(-1)
    return torch.stack([fx * k, fy * k, (cx - boxes[..., 0]) * k - 0.5, (cy - boxes[..., 1]) * k - 0.5], -1)


def crop_to_image(points: Tensor, boxes: Tensor, size: int) -> Tensor:
    """(B, C, L, 2) render pixel coordinates -> image pixels, given (B, C, 4) boxes."""
    k = ((boxes[..., 2] - boxes[..., 0]) / size)[..., None, None]
    return boxes[..., None, :2] + (points + 0.5) * k


def image_to_crop(points: Tensor, boxes: Tensor, size: int) -> Tensor:
    """Inverse of `crop_to_image`."""
    k = ((boxes[..., 2] - boxes[..., 0]) / size)[..., None, None]
    return (points - boxes[..., None, :2]) / k - 0.5


def render_crops(model: FitModel, views: FitViews, vertices: Tensor, *, size: int = MESH_SIZE,
                 supersample: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """Render every frame's head in every camera's crop box.

    Args:
        model: the model and appearance; views: cameras and boxes.
        vertices: (B, V, 3) world vertices, cm.
        size: S, the render's side (the face mesh's input, 192).
        supersample: render at s x and average (the landmark network reads lips better).
    Returns:
        image (B * C, S, S, 3) linear (differentiable in vertices and appearance),
        triangle (B * C, S, S) int64 visible triangle (-1 none),
        pix (B * C, V, 2) the projected vertices in render pixels.
    """
    b, c = views.boxes.shape[:2]
    k = crop_intrinsics(views.intrinsics, views.boxes, size).reshape(b * c, 4)
    e = views.world_to_camera[None].expand(b, c, 4, 4).reshape(b * c, 4, 4)
    dist = None if views.distortion is None else views.distortion[None].expand(b, c, 2).reshape(b * c, 2)
    verts = vertices[:, None].expand(b, c, *vertices.shape[1:]).reshape(b * c, *vertices.shape[1:])
    out = render_mesh(verts, model.faces, e, k, size, size, albedo=model.albedo, sh=model.sh,
                      background=model.background, distortion=dist, supersample=supersample,
                      adjacency=model.adjacency)
    pix = project_points_torch(verts, e, k, dist)
    return out.image * _inside_image(views, size).reshape(b * c, size, size, 1), out.triangle, pix


def _inside_image(views: FitViews, size: int) -> Tensor:
    """(B, C, S, S) 1 where a render pixel's centre falls inside the plate, else 0.

    `crop_and_resize` fills the part of a crop box outside the plate with black; the render
    does the same, so that the network sees the same framing on both.
    """
    j = torch.arange(size, dtype=views.boxes.dtype, device=views.boxes.device)
    k = (views.boxes[..., 2] - views.boxes[..., 0]) / size  # (B, C)
    u = views.boxes[..., 0, None] + (j + 0.5) * k[..., None]  # (B, C, S)
    v = views.boxes[..., 1, None] + (j + 0.5) * k[..., None]
    w, h = views.image_size[:, 0], views.image_size[:, 1]  # (C,)
    inside_u = (u >= -0.5) & (u <= w[None, :, None] - 0.5)
    inside_v = (v >= -0.5) & (v <= h[None, :, None] - 0.5)
    return (inside_v[..., :, None] & inside_u[..., None, :]).to(views.boxes.dtype)


def network_points(images: Tensor, network: torch.nn.Module) -> tuple[Tensor, Tensor]:
    """The face mesh's 68 Multi-PIE points on S x S renders (the whole render is the crop).

    Args:
        images: (N, S, S, 3) linear colour (sRGB-encoded here), S = the network's input size.
        network: `MediaPipeFaceMesh` (468 points, crop pixels from the corner).
    Returns:
        points (N, 68, 2) render pixel coordinates (centres at integers), presence (N,).
    """
    points, presence = network(srgb_encode(images.clamp(0.0, 1.0)))
    return points[:, MEDIAPIPE_TO_68] - 0.5, presence


def landmark_anchors(model: FitModel, b: int, c: int) -> Anchors:
    """Anchors on the model's 68 landmark vertices (before any render): offset 0."""
    dev = model.neutral.device
    ids = torch.as_tensor(model.landmarks, device=dev)[:, None].expand(68, 3)
    bary = torch.tensor([1.0, 0.0, 0.0], device=dev).expand(68, 3)
    return Anchors(ids.expand(b, c, 68, 3).clone(), bary.expand(b, c, 68, 3).clone(),
                   torch.zeros(b, c, 68, 2, device=dev))


def _barycentrics(corners: Tensor, points: Tensor) -> Tensor:
    """(..., 3, 2), (..., 2) -> (..., 3) barycentrics clamped into the triangle (sum 1)."""
    p0, p1, p2 = corners.unbind(-2)
    v0, v1, v2 = p1 - p0, p2 - p0, points - p0
    den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
    den = torch.where(den.abs() < 1e-9, torch.full_like(den, 1e-9), den)
    l1 = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
    l2 = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
    lam = torch.stack([1.0 - l1 - l2, l1, l2], -1).clamp_min(0.0)
    return lam / lam.sum(-1, keepdim=True).clamp_min(1e-9)


def anchors_from_render(model: FitModel, views: FitViews, triangle: Tensor, pix: Tensor, points: Tensor,
                        presence: Tensor, fallback: Anchors, *, min_presence: float = 0.5) -> Anchors:
    """Tie the network's points on the render to the surface under them.

    For render point i of a view: the triangle under the nearest covered pixel (the point
    itself when covered), the barycentrics of the point in that triangle's projection
    (clamped into it), and the offset between the point and the anchor's projection.

    Args:
        model, views: as in `render_crops`.
        triangle: (B * C, S, S) visible triangle; pix: (B * C, V, 2) projected vertices.
        points: (B * C, 68, 2) the network's points on the render, render pixels.
        presence: (B * C,) the network's face presence on the render.
        fallback: anchors kept for views whose render the network did not read as a face
            (presence < `min_presence`) or that did not see the face.
    Returns:
        Anchors (B, C, 68, ...); offsets converted to image pixels.
    """
    from scipy.ndimage import distance_transform_edt

    b, c = views.boxes.shape[:2]
    n, s = triangle.shape[:2]
    tri_np = triangle.cpu().numpy()
    pts = points.detach()
    ij = pts.round().long().clamp(0, s - 1).cpu().numpy()  # (N, 68, 2) x, y
    tri_ids = np.empty((n, 68), np.int64)
    for m in range(n):
        grid = tri_np[m]
        if (grid >= 0).any():
            near = distance_transform_edt(grid < 0, return_distances=False, return_indices=True)
            yy, xx = near[0][ij[m, :, 1], ij[m, :, 0]], near[1][ij[m, :, 1], ij[m, :, 0]]
            tri_ids[m] = grid[yy, xx]
        else:
            tri_ids[m] = -1
    ok_tri = tri_ids >= 0
    faces = torch.as_tensor(model.faces, device=pix.device)
    corner_ids = faces[torch.as_tensor(np.where(ok_tri, tri_ids, 0), device=pix.device)]  # (N, 68, 3)
    rows = torch.arange(n, device=pix.device)[:, None, None]
    corners = pix.detach()[rows, corner_ids]  # (N, 68, 3, 2)
    bary = _barycentrics(corners, pts)
    anchor_pix = (bary[..., None] * corners).sum(-2)
    k = ((views.boxes[..., 2] - views.boxes[..., 0]) / s).reshape(n, 1, 1)
    offset = (pts - anchor_pix) * k  # render pixels -> image pixels
    good = (torch.as_tensor(ok_tri, device=pix.device).all(-1) & (presence.detach() >= min_presence)
            & views.seen.reshape(n)).reshape(b, c)
    g = good[..., None, None]
    return Anchors(torch.where(g, corner_ids.reshape(b, c, 68, 3), fallback.vertices),
                   torch.where(g, bary.reshape(b, c, 68, 3), fallback.bary),
                   torch.where(g, offset.reshape(b, c, 68, 2), fallback.offset))
