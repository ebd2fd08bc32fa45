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

import threading
from dataclasses import dataclass
from functools import lru_cache
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import project_points_torch
from ..geometry.image import crop_intrinsics, crop_to_image, image_to_crop, sample_bilinear, sample_separable
from ..landmarks.correspondence import MEDIAPIPE_TO_68
from ..landmarks.network import MESH_SIZE, srgb_encode
from ..geometry.mesh import triangle_adjacency
from ..render.renderer import render_mesh

__all__ = ["FitModel", "FitViews", "Anchors", "at_anchors", "crop_intrinsics", "crop_to_image", "image_to_crop",
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
        noise: the plate's noise, standard deviation per plate pixel, linear units
            (`nodes.fit.appearance.estimate_noise`): renders get as much (`render_crops`).
        iris: (2, 3) the iris centres at weight 0 (the eyeballs' front vertices), iris_centres
            (2, 3) the eyeballs' centres, cm, model frame, and iris_turns (K, 2, 2) each shape's yaw
            and pitch of each eye per unit weight, radians (`nodes.fit.energy.iris_model_points`);
            None when the fit does not read the iris.
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
    noise: float = 0.0
    iris: Tensor | None = None
    iris_centres: Tensor | None = None
    iris_turns: Tensor | None = None

    @classmethod
    def build(cls, neutral: np.ndarray, deltas: np.ndarray, names: list[str], faces: np.ndarray,
              landmarks: np.ndarray, albedo: np.ndarray, sh: np.ndarray, background: np.ndarray,
              device: str = "cpu", noise: float = 0.0) -> "FitModel":
        faces = np.asarray(faces, np.int64)
        t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
        return cls(t(neutral), t(deltas), list(names), faces, triangle_adjacency(faces),
                   np.asarray(landmarks, np.int64), t(albedo)[None], t(sh)[None], t(background), float(noise))

    def vertices(self, weights: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
        """(B, K) weights, (B, 3, 3), (B, 3) cm -> (B, V, 3) world vertices, cm.

        Frame by frame: a (B, K) x (K, 3V) product blocks its sums by B, so a frame's vertices
        (and from them its render and fit) depended on the frames solved beside it."""
        k, v = self.deltas.shape[:2]
        basis = self.deltas.reshape(k, -1)
        flat = self.neutral.reshape(-1)
        return torch.stack([(flat + w @ basis).reshape(v, 3) @ r.T + t for w, r, t in zip(weights, rot, trans)])


@dataclass
class FitViews:
    """The plate's landmarks in every frame and camera, and the cameras.

    Attributes:
        target: (B, C, 68, 2) the network's 68 points on the plate, image pixels (0 where unseen).
        boxes: (B, C, 4) crop boxes x0 y0 x1 y1, pixels (a dummy box where unseen).
        seen: (B, C) bool, the face was found in that view.
        world_to_camera: (C, 4, 4); intrinsics: (C, 4) fx fy cx cy; distortion: (C, 2) or None.
        image_size: (C, 2) width, height of each camera's plate, pixels.
        plates: (B, C, S, S, 3) the plate's crops at the boxes (`crop_and_resize`, linear), for
            the photometric term (`nodes.fit.photometric`); None without it.
        iris: (B, C, 2, 2) the plate's iris centres (eye 0 the subject's right), image pixels,
            NaN where not read; None without them.
    """

    target: Tensor
    boxes: Tensor
    seen: Tensor
    world_to_camera: Tensor
    intrinsics: Tensor
    distortion: Tensor | None
    image_size: Tensor
    plates: Tensor | None = None
    iris: Tensor | None = None

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
        rendered: (B, C) bool, anchored on a render (False: the fallback, `landmark_anchors`,
            whose points past the 68 are placeholders).
    """

    vertices: Tensor
    bary: Tensor
    offset: Tensor
    rendered: Tensor


_VERTEX_ROWS: list[tuple[Tensor, int, Tensor]] = []  # (values, its _version, (V, K * 3) rows), newest last
_VERTEX_ROWS_LOCK = threading.Lock()


def _vertex_rows(values: Tensor) -> Tensor:
    """(K, V, 3) -> (V, K * 3) contiguous: each vertex's K vectors in one row, so that gathering a
    corner copies one row. Cached for the last 4 tensors (the model's shapes and identity
    components are gathered again at every stage and round); a cached entry holds its tensor,
    so its storage is not reused while cached, and an in-place change (`_version`) is seen."""
    with _VERTEX_ROWS_LOCK:
        for src, version, rows in _VERTEX_ROWS:
            if src is values and version == values._version:
                return rows
    rows = values.detach().permute(1, 0, 2).reshape(values.shape[1], -1).contiguous()
    with _VERTEX_ROWS_LOCK:
        _VERTEX_ROWS.append((values, values._version, rows))
        del _VERTEX_ROWS[:-4]
    return rows


def at_anchors(values: Tensor, vertices: Tensor, bary: Tensor) -> Tensor:
    """Per-vertex vectors interpolated at anchors (triangle corners + barycentrics).

    `sum_j bary_j values[corner_j]`, summed over the corners in order (j = 0, 1, 2). (K, V, 3)
    values are gathered from their vertex-major rows (`_vertex_rows`, cached): one (K * 3) row
    per corner instead of K scattered 3-vectors, 6-17x faster for K = 53 (68-3000 anchors, one
    thread), the same bits.

    Args:
        values: (V, 3) one vector per vertex, or (K, V, 3) K of them (shapes, components).
        vertices: (B, C, L, 3) int64 corners; bary: (B, C, L, 3) barycentrics.
    Returns:
        (B, C, L, 3), or (B, C, L, K, 3) for (K, V, 3) values.
    """
    if values.ndim == 2:
        corners = values[vertices]  # (B, C, L, 3, 3)
    else:
        corners = _vertex_rows(values)[vertices]  # (B, C, L, 3, K * 3)
    w = bary[..., None]
    out = corners[..., 0, :] * w[..., 0, :] + corners[..., 1, :] * w[..., 1, :] + corners[..., 2, :] * w[..., 2, :]
    if values.ndim == 2:
        return out
    if values.requires_grad and torch.is_grad_enabled():  # the cached rows are detached: gather afresh
        corners = values[:, vertices]
        out = (corners[..., 0, :] * w[None, ..., 0, :] + corners[..., 1, :] * w[None, ..., 1, :]
               + corners[..., 2, :] * w[None, ..., 2, :])
        return out.permute(1, 2, 3, 0, 4)
    return out.unflatten(-1, (values.shape[0], 3))


@lru_cache(maxsize=4)
def _noise_pattern(side: int, device: str) -> Tensor:
    """(side, side, 3) standard normal noise, the same for every call (seed 0, tiled from 256^2)."""
    g = torch.Generator().manual_seed(0)
    tile = torch.randn(256, 256, 3, generator=g)
    reps = -(-side // 256)
    return tile.repeat(reps, reps, 1)[:side, :side].to(device)


def _plate_grids(views: FitViews, size: int) -> tuple[Tensor, Tensor, Tensor, int]:
    """Where `crop_and_resize` samples each view's plate, on a grid a render can be made on.

    `crop_and_resize` box-filters a plate by `k = int(s / S)` (s the box side; k >= 2 only)
    and samples the filtered pixels bilinearly. The render grid of a view is those filtered
    pixels around its box: render pixel j is filtered pixel `origin + j`, centred at plate
    coordinate `k (origin + j) + (k - 1) / 2`.

    Returns:
        k (N,) float, origin (N, 2) filtered-pixel index of render pixel 0 (x, y), coords
        (N, S, 2) the render-pixel coordinates that output pixel i samples along x and along y
        (x from the box's x range, y from its y range), and R, the renders' side.
    """
    n = views.boxes.shape[0] * views.boxes.shape[1]
    boxes = views.boxes.reshape(n, 4)
    side = (boxes[:, 2] - boxes[:, 0]).clamp_min(1e-6)
    k = torch.floor(torch.minimum(side, boxes[:, 3] - boxes[:, 1]) / size).clamp_min(1.0)
    off = (k - 1) / 2
    origin = torch.floor((boxes[:, :2] - off[:, None]) / k[:, None]) - 1
    t = (torch.arange(size, dtype=boxes.dtype, device=boxes.device) + 0.5) / size
    xs = (boxes[:, 0, None] + t * (boxes[:, 2] - boxes[:, 0])[:, None] - off[:, None]) / k[:, None] - origin[:, :1]
    ys = (boxes[:, 1, None] + t * (boxes[:, 3] - boxes[:, 1])[:, None] - off[:, None]) / k[:, None] - origin[:, 1:]
    r = int(torch.ceil(torch.maximum(xs.max(), ys.max())).item()) + 2
    return k, origin, torch.stack([xs, ys], -1), max(r, 2)


_LAST_RENDER = threading.local()  # per thread: the last render's inputs and output (`_render_mesh_reusing_last`)


def _render_mesh_reusing_last(verts: Tensor, faces: np.ndarray, e: Tensor, k: Tensor, side: int, *,
                              albedo: Tensor, sh: Tensor, background: Tensor, distortion: Tensor | None,
                              supersample: int, adjacency: np.ndarray):
    """`render_mesh` of the crops, returning the previous call's output (this thread's) when every
    input is equal to it and no gradient is recorded: a fit round renders the same estimate
    twice (with the plate's noise for the network, without it for the photometric samples),
    and the noise is added after the render (`render_crops`)."""
    if torch.is_grad_enabled() and any(t.requires_grad for t in (verts, e, k, albedo, sh, background)):
        return render_mesh(verts, faces, e, k, side, side, albedo=albedo, sh=sh, background=background,
                           distortion=distortion, supersample=supersample, adjacency=adjacency)
    tensors = (verts, e, k, albedo, sh, background, distortion)
    values = (side, supersample)
    last = getattr(_LAST_RENDER, "entry", None)
    if last is not None and last[1] == values and last[3] is faces and last[4] is adjacency and all(
            (a is None and b is None) or (a is not None and b is not None and a.shape == b.shape
                                          and a.dtype == b.dtype and a.device == b.device and torch.equal(a, b))
            for a, b in zip(last[0], tensors)):
        return last[2]
    with torch.no_grad():
        out = render_mesh(verts, faces, e, k, side, side, albedo=albedo, sh=sh, background=background,
                          distortion=distortion, supersample=supersample, adjacency=adjacency)
    _LAST_RENDER.entry = (tuple(None if t is None else t.detach().clone() for t in tensors), values, out, faces,
                          adjacency)
    return out


def render_crops(model: FitModel, views: FitViews, vertices: Tensor, *, size: int = MESH_SIZE,
                 supersample: int = 2) -> tuple[Tensor, Tensor, Tensor]:
    """Render every frame's head in every camera's crop box, as the network sees the plate.

    The head is rendered at the plate's own resolution around the box (box-filtered as
    `crop_and_resize` filters the plate, `_plate_grids`) and then resampled into the S x S
    crop the same way the plate is: the render and the plate go through the network at the
    same sharpness. (Rendered straight at S x S, a face smaller than S px on the plate was
    sharper in the render than in the plate's upsampled crop, and the network read the two
    differently.) The plate's noise is added too (`FitModel.noise`, per plate pixel; divided by
    k where the plate is box-filtered): the network reads a noisy face differently from a
    clean one, and not only at random. Synthetic 256^2 plates with noise 0.005, the true
    identity and appearance: the deep energy at the true parameters was 3.8x the fitted one
    with renders made straight at S x S, 2.9x at the plate's resolution, 0.75x with its noise
    as well (noise-free plates: 0.07x).

    Args:
        model: the model and appearance; views: cameras and boxes.
        vertices: (B, V, 3) world vertices, cm.
        size: S, the crop's side (the face mesh's input, 192).
        supersample: render at s x and average (the landmark network reads lips better).
    Returns:
        image (B * C, S, S, 3) linear (differentiable in vertices and appearance; 0 where the
        box leaves the plate), triangle (B * C, S, S) int64 visible triangle under each crop
        pixel (-1 none), pix (B * C, V, 2) the projected vertices in crop pixels.
    """
    b, c = views.boxes.shape[:2]
    n = b * c
    e = views.world_to_camera[None].expand(b, c, 4, 4).reshape(n, 4, 4)
    dist = None if views.distortion is None else views.distortion[None].expand(b, c, 2).reshape(n, 2)
    verts = vertices[:, None].expand(b, c, *vertices.shape[1:]).reshape(n, *vertices.shape[1:])
    k, origin, coords, r = _plate_grids(views, size)
    intr = views.intrinsics[None].expand(b, c, 4).reshape(n, 4)
    off = (k - 1) / 2
    grid_k = torch.stack([intr[:, 0] / k, intr[:, 1] / k, (intr[:, 2] - off) / k - origin[:, 0],
                          (intr[:, 3] - off) / k - origin[:, 1]], -1)
    out = _render_mesh_reusing_last(verts, model.faces, e, grid_k, r, albedo=model.albedo, sh=model.sh,
                                    background=model.background, distortion=dist, supersample=supersample,
                                    adjacency=model.adjacency)
    # filtered plate pixels that exist: 0 <= origin + j < ceil(W / k)
    j = torch.arange(r, dtype=k.dtype, device=k.device)
    cam = torch.arange(c, device=k.device).repeat(b)
    limit = torch.ceil(views.image_size[cam].to(k.dtype) / k[:, None])  # (N, 2) width, height
    in_x = (origin[:, :1] + j >= 0) & (origin[:, :1] + j < limit[:, :1])
    in_y = (origin[:, 1:] + j >= 0) & (origin[:, 1:] + j < limit[:, 1:])
    image = out.image
    if model.noise > 0:  # the plate's noise (one fixed pattern: a view's noise never depends on its batch)
        pattern = _noise_pattern(r, str(image.device)).to(image.dtype)
        image = (image + (model.noise / k)[:, None, None, None] * pattern).clamp(0.0, 1.0)
    image = image * (in_y[:, :, None] & in_x[:, None, :]).to(image.dtype)[..., None]
    xs, ys = coords[..., 0], coords[..., 1]  # (N, S) render-pixel coordinates of the crop's samples
    crop = sample_separable(image, xs, ys)  # the same values for any R (the batch's largest box)
    ix = xs.round().long().clamp(0, r - 1)
    iy = ys.round().long().clamp(0, r - 1)
    rows = torch.arange(n, device=k.device)[:, None, None]
    triangle = out.triangle[rows, iy[:, :, None], ix[:, None, :]]
    pix = project_points_torch(verts, e, crop_intrinsics(views.intrinsics, views.boxes, size).reshape(n, 4), dist)
    return crop, triangle, pix


def network_points(images: Tensor, network: torch.nn.Module,
                   indices: np.ndarray = MEDIAPIPE_TO_68) -> tuple[Tensor, Tensor]:
    """Face-mesh points on S x S renders (the whole render is the crop).

    Args:
        images: (N, S, S, 3) linear colour (sRGB-encoded here), S = the network's input size.
        network: `MediaPipeFaceMesh` (468 points, crop pixels from the corner).
        indices: (L,) the face-mesh points wanted (default: the 68 Multi-PIE points).
    Returns:
        points (N, L, 2) render pixel coordinates (centres at integers), presence (N,).
    """
    points, presence = network(srgb_encode(images.clamp(0.0, 1.0)))
    return points[:, torch.as_tensor(indices, device=points.device)] - 0.5, presence


def landmark_anchors(model: FitModel, b: int, c: int, points: int = 68) -> Anchors:
    """Anchors on the model's 68 landmark vertices (before any render): offset 0; points past
    the 68 (`points` > 68) are placeholders on landmark 0 (`rendered` False)."""
    dev = model.neutral.device
    ids = torch.as_tensor(model.landmarks, device=dev)
    ids = torch.cat([ids, ids[:1].expand(points - 68)])[:, None].expand(points, 3)
    bary = torch.tensor([1.0, 0.0, 0.0], device=dev).expand(points, 3)
    return Anchors(ids.expand(b, c, points, 3).clone(), bary.expand(b, c, points, 3).clone(),
                   torch.zeros(b, c, points, 2, device=dev), torch.zeros(b, c, dtype=torch.bool, device=dev))


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
        points: (B * C, L, 2) the network's points on the render, render pixels.
        presence: (B * C,) the network's face presence on the render.
        fallback: anchors kept for views whose render the network did not read as a face
            (presence < `min_presence`) or that did not see the face.
    Returns:
        Anchors (B, C, L, ...); offsets converted to image pixels.
    """
    from scipy.ndimage import distance_transform_edt

    b, c = views.boxes.shape[:2]
    n, s = triangle.shape[:2]
    tri_np = triangle.cpu().numpy()
    pts = points.detach()
    npts = pts.shape[1]
    ij = pts.round().long().clamp(0, s - 1).cpu().numpy()  # (N, L, 2) x, y
    tri_ids = np.empty((n, npts), np.int64)
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
    corner_ids = faces[torch.as_tensor(np.where(ok_tri, tri_ids, 0), device=pix.device)]  # (N, L, 3)
    rows = torch.arange(n, device=pix.device)[:, None, None]
    corners = pix.detach()[rows, corner_ids]  # (N, L, 3, 2)
    bary = _barycentrics(corners, pts)
    anchor_pix = (bary[..., None] * corners).sum(-2)
    k = ((views.boxes[..., 2] - views.boxes[..., 0]) / s).reshape(n, 1, 1)
    offset = (pts - anchor_pix) * k  # render pixels -> image pixels
    good = (torch.as_tensor(ok_tri, device=pix.device).all(-1) & (presence.detach() >= min_presence)
            & views.seen.reshape(n)).reshape(b, c)
    g = good[..., None, None]
    return Anchors(torch.where(g, corner_ids.reshape(b, c, npts, 3), fallback.vertices),
                   torch.where(g, bary.reshape(b, c, npts, 3), fallback.bary),
                   torch.where(g, offset.reshape(b, c, npts, 2), fallback.offset), good)
