"""MediaPipe's face detector (BlazeFace short range) and face mesh (468 points) in torch.

Both networks ship in `nodes/data/mediapipe` (Apache-2.0) and are replayed op by op from
their `.tflite` files (`nodes.landmarks.tflite_torch`), so gradients flow from the
landmarks to the input pixels.

Conventions: images are (B, H, W, 3) float RGB in [0, 1], sRGB-encoded (the networks were
trained on photos); pixel centres at integer coordinates, origin top-left, x right, y down.
A box is `(x0, y0, x1, y1)` in those coordinates, the crop covering `[x0, x1] x [y0, y1]`
(the whole image is `(-0.5, -0.5, W - 0.5, H - 0.5)`); crop pixel j's centre is at
`x0 + (j + 1/2) (x1 - x0) / S`.

- `crop_and_resize`: bilinear, differentiable in the pixels with the box held constant (the
  paper's dD/dF = 0); for a shrink by k >= 2 the image is first averaged over k x k blocks
  (no aliasing of fine detail).
- `detect_faces`: the image letterboxed to a square (black bars) and resized to 128 x 128,
  BlazeFace's 896 SSD anchors decoded to boxes and 6 keypoints, weighted non-maximum
  suppression (IoU 0.3), the best face's box scaled 1.5 about its centre to a square: the
  crop box of the face mesh (as MediaPipe's face-landmark front end, without its roll
  rotation: faces should be upright within about 20 degrees).
- `MediaPipeFaceMesh`: crops (B, 192, 192, 3) -> 468 points (x, y in crop pixels, 0 at the
  crop corner; z dropped) and face presence (sigmoid of the presence logit).
- `face_landmarks`: crop, run a landmark network, map the points back to image pixels.

This module imports torch at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

import importlib.resources
from functools import lru_cache
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .heatmap import LandmarkNetwork
from .tflite_torch import TfliteModule, read_tflite

__all__ = ["FACE_LANDMARK_MODEL", "FACE_DETECTOR_MODEL", "mediapipe_path", "srgb_encode",
           "crop_and_resize", "letterbox_box", "square_box", "ssd_anchors", "decode_detections",
           "weighted_nms", "FaceDetections", "BlazeFace", "MediaPipeFaceMesh", "detect_faces",
           "face_landmarks", "load_face_detector", "load_face_mesh"]

FACE_LANDMARK_MODEL = "face_landmark.tflite"
FACE_DETECTOR_MODEL = "face_detection_short_range.tflite"
DETECTOR_SIZE = 128
MESH_SIZE = 192
BOX_SCALE = 1.5
"""Side of the face-mesh crop over the longer side of the detector's face box (MediaPipe's)."""


def mediapipe_path(name: str) -> Path:
    """Path of a bundled MediaPipe model file (`nodes/data/mediapipe/NAME`)."""
    return Path(str(importlib.resources.files("nodes") / "data" / "mediapipe" / name))


def srgb_encode(linear: Tensor) -> Tensor:
    """Encode linear light as sRGB (IEC 61966-2-1), differentiably (torch twin of
    `nodegraph.types.linear_to_srgb`; the power branch's input is clamped away from 0 so its
    gradient stays finite)."""
    power = 1.055 * linear.clamp_min(0.0031308) ** (1.0 / 2.4) - 0.055
    return torch.where(linear <= 0.0031308, linear * 12.92, power)


# -- boxes and crops -----------------------------------------------------------------------
def letterbox_box(height: int, width: int) -> np.ndarray:
    """The square box centred on an H x W image that holds all of it: (4,) x0 y0 x1 y1."""
    side = float(max(height, width))
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    return np.array([cx - side / 2, cy - side / 2, cx + side / 2, cy + side / 2])


def square_box(boxes: np.ndarray, scale: float = BOX_SCALE) -> np.ndarray:
    """Square boxes of side `scale * max(w, h)` about the centres of `boxes` ((..., 4) -> (..., 4))."""
    boxes = np.asarray(boxes, np.float64)
    centre = (boxes[..., :2] + boxes[..., 2:]) / 2
    side = scale * np.maximum(boxes[..., 2] - boxes[..., 0], boxes[..., 3] - boxes[..., 1])
    return np.concatenate([centre - side[..., None] / 2, centre + side[..., None] / 2], -1)


def crop_and_resize(images: Tensor, boxes: Tensor | np.ndarray, size: int) -> Tensor:
    """Crop each image to its box and resize to size x size, bilinearly (differentiable in pixels).

    Args:
        images: (B, H, W, C) float.
        boxes: (B, 4) x0 y0 x1 y1, pixels (see the module docstring); held constant.
        size: output side S, pixels.
    Returns:
        (B, S, S, C); samples outside the image are 0 (black).
    """
    if images.ndim != 4:
        raise ValueError(f"images: expected shape (B, H, W, C), found {tuple(images.shape)}")
    boxes = torch.as_tensor(np.asarray(boxes, np.float64) if not isinstance(boxes, Tensor) else boxes,
                            dtype=images.dtype, device=images.device).reshape(-1, 4)
    if len(boxes) != len(images):
        raise ValueError(f"boxes: expected shape ({len(images)}, 4), found {tuple(boxes.shape)}")
    out = []
    x = images.permute(0, 3, 1, 2)
    t = (torch.arange(size, device=images.device, dtype=images.dtype) + 0.5) / size
    for b in range(len(images)):  # per image: each has its own box and shrink factor
        x0, y0, x1, y1 = boxes[b].tolist()
        img = x[b:b + 1]
        k = int(min(x1 - x0, y1 - y0) / size)
        offset, step = 0.0, 1.0
        if k >= 2:  # box filter before the bilinear shrink; pooled pixel i covers k i .. k i + k - 1
            img = F.avg_pool2d(F.pad(img, (0, (-img.shape[3]) % k, 0, (-img.shape[2]) % k)), k)
            offset, step = (k - 1) / 2.0, float(k)
        h, w = img.shape[2], img.shape[3]
        xs = (x0 + t * (x1 - x0) - offset) / step  # in pooled pixel-centre coordinates
        ys = (y0 + t * (y1 - y0) - offset) / step
        gx = (xs + 0.5) / w * 2 - 1
        gy = (ys + 0.5) / h * 2 - 1
        grid = torch.stack(torch.broadcast_tensors(gx[None, :], gy[:, None]), -1)[None]
        out.append(F.grid_sample(img, grid, mode="bilinear", padding_mode="zeros", align_corners=False))
    return torch.cat(out).permute(0, 2, 3, 1)


# -- BlazeFace ---------------------------------------------------------------------------
@lru_cache(maxsize=1)
def ssd_anchors() -> np.ndarray:
    """The 896 anchor centres of BlazeFace short range, (896, 2) x, y in [0, 1].

    MediaPipe's SsdAnchorsCalculator with 4 layers, strides 8, 16, 16, 16, fixed anchor size
    and an interpolated anchor per layer: 2 anchors per cell of the 16 x 16 grid, then 6 per
    cell of the 8 x 8 grid (the three stride-16 layers merged), cells in row-major order.
    """
    out = []
    for grid, per_cell in ((16, 2), (8, 6)):
        c = (np.arange(grid) + 0.5) / grid
        yy, xx = np.meshgrid(c, c, indexing="ij")
        centres = np.stack([xx.ravel(), yy.ravel()], -1)
        out.append(np.repeat(centres, per_cell, axis=0))
    return np.concatenate(out)


def decode_detections(regressors: Tensor, logits: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Decode BlazeFace outputs against the anchors.

    Args:
        regressors: (B, 896, 16) raw box (x, y, w, h) and 6 keypoints (x, y), in 128-pixel units.
        logits: (B, 896, 1) raw scores.
    Returns:
        boxes (B, 896, 4) x0 y0 x1 y1, keypoints (B, 896, 6, 2) x y, both normalized to
        [0, 1] over the detector input; scores (B, 896) = sigmoid(clip(logit, -100, 100)).
        Keypoints: right eye, left eye, nose tip, mouth, right ear tragion, left ear tragion.
    """
    anchors = torch.as_tensor(ssd_anchors(), dtype=regressors.dtype, device=regressors.device)
    r = regressors / DETECTOR_SIZE
    centre = r[..., 0:2] + anchors
    half = r[..., 2:4] / 2
    boxes = torch.cat([centre - half, centre + half], -1)
    keypoints = r[..., 4:16].reshape(*r.shape[:-1], 6, 2) + anchors[:, None, :]
    scores = torch.sigmoid(logits[..., 0].clamp(-100.0, 100.0))
    return boxes, keypoints, scores


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), -1)
    area = np.prod(box[2:] - box[:2])
    areas = np.prod(boxes[:, 2:] - boxes[:, :2], -1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def weighted_nms(boxes: np.ndarray, keypoints: np.ndarray, scores: np.ndarray, *, min_score: float = 0.5,
                 iou: float = 0.3) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Weighted non-maximum suppression (MediaPipe's WEIGHTED algorithm, BlazeFace paper).

    Candidates above `min_score`, by decreasing score: the best one and all others with
    IoU > `iou` form a cluster whose box and keypoints are the score-weighted means; its
    score is the best one's. The cluster is removed and the next best starts a new one.

    Args:
        boxes: (N, 4); keypoints: (N, K, 2); scores: (N,).
    Returns:
        [(box (4,), keypoints (K, 2), score)], by decreasing score.
    """
    order = np.argsort(-scores, kind="stable")
    order = order[scores[order] >= min_score]
    out = []
    while len(order):
        overlap = _iou(boxes[order[0]], boxes[order])
        members = order[overlap > iou]
        members = members if len(members) else order[:1]
        w = scores[members][:, None]
        box = (boxes[members] * w).sum(0) / w.sum()
        kps = (keypoints[members] * w[:, :, None]).sum(0) / w.sum()
        out.append((box, kps, float(scores[order[0]])))
        order = order[overlap <= iou]
        order = order[~np.isin(order, members)]
    return out


class BlazeFace(nn.Module):
    """BlazeFace short range: (B, 128, 128, 3) RGB in [0, 1] -> (regressors, logits)."""

    def __init__(self, path: str | Path | None = None):
        super().__init__()
        self.net = TfliteModule(read_tflite(path or mediapipe_path(FACE_DETECTOR_MODEL)),
                                ["regressors", "classificators"])

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        return self.net(images * 2.0 - 1.0)


class MediaPipeFaceMesh(nn.Module):
    """MediaPipe face mesh as a `LandmarkNetwork`: (B, 192, 192, 3) RGB in [0, 1] -> (points
    (B, 468, 2) crop pixels, 0 at the crop corner; presence (B,) in [0, 1])."""

    input_size = MESH_SIZE
    num_points = 468

    def __init__(self, path: str | Path | None = None):
        super().__init__()
        self.net = TfliteModule(read_tflite(path or mediapipe_path(FACE_LANDMARK_MODEL)),
                                ["conv2d_21", "conv2d_31"])

    def forward(self, crops: Tensor) -> tuple[Tensor, Tensor]:
        if crops.ndim != 4 or tuple(crops.shape[1:]) != (MESH_SIZE, MESH_SIZE, 3):
            raise ValueError(f"crops: expected shape (B, {MESH_SIZE}, {MESH_SIZE}, 3), found "
                             f"{tuple(crops.shape)}")
        coords, logit = self.net(crops)
        points = coords.reshape(len(crops), 468, 3)[..., :2]
        return points, torch.sigmoid(logit.reshape(len(crops)))


@lru_cache(maxsize=2)
def _cached(kind: str) -> nn.Module:
    module = BlazeFace() if kind == "detector" else MediaPipeFaceMesh()
    return module.eval()


def load_face_detector(device: str = "cpu", dtype: torch.dtype = torch.float32) -> BlazeFace:
    """The bundled BlazeFace (weights read once per process), on `device`."""
    return _cached("detector").to(device=device, dtype=dtype)


def load_face_mesh(device: str = "cpu", dtype: torch.dtype = torch.float32) -> MediaPipeFaceMesh:
    """The bundled face mesh network (weights read once per process), on `device`."""
    return _cached("mesh").to(device=device, dtype=dtype)


class FaceDetections(NamedTuple):
    """Per image, the best face: `boxes` (B, 4) square crop boxes for the face mesh (x0 y0 x1
    y1 pixels; NaN where none), `face_boxes` (B, 4) the detector's own box, `keypoints`
    (B, 6, 2) pixels, `scores` (B,) in [0, 1] (0 where none), `found` (B,) bool."""

    boxes: np.ndarray
    face_boxes: np.ndarray
    keypoints: np.ndarray
    scores: np.ndarray
    found: np.ndarray


def detect_faces(images: Tensor, detector: nn.Module | None = None, *, min_score: float = 0.5,
                 iou: float = 0.3, scale: float = BOX_SCALE) -> FaceDetections:
    """Detect the best face in each image and return its square crop box (no gradients).

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        detector: a `BlazeFace` (default: the bundled one, on the images' device).
        min_score: detections below this score are dropped (MediaPipe: 0.5).
        iou: weighted-NMS overlap threshold (MediaPipe: 0.3).
        scale: crop side over the longer side of the face box.
    Returns:
        FaceDetections in image pixels.
    """
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected shape (B, H, W, 3), found {tuple(images.shape)}")
    bsz, height, width = images.shape[:3]
    detector = detector or load_face_detector(str(images.device), images.dtype)
    letter = letterbox_box(height, width)
    with torch.no_grad():
        inputs = crop_and_resize(images, np.repeat(letter[None], bsz, 0), DETECTOR_SIZE)
        boxes_n, kps_n, scores = decode_detections(*detector(inputs))
    side = letter[2] - letter[0]
    boxes_n, kps_n, scores = (t.double().cpu().numpy() for t in (boxes_n, kps_n, scores))
    out = FaceDetections(np.full((bsz, 4), np.nan), np.full((bsz, 4), np.nan),
                         np.full((bsz, 6, 2), np.nan), np.zeros(bsz), np.zeros(bsz, bool))
    for b in range(bsz):
        faces = weighted_nms(boxes_n[b], kps_n[b], scores[b], min_score=min_score, iou=iou)
        if not faces:
            continue
        box, kps, score = faces[0]
        box_px = letter[[0, 1, 0, 1]] + box * side
        out.face_boxes[b] = box_px
        out.keypoints[b] = letter[:2] + kps * side
        out.boxes[b] = square_box(box_px, scale)
        out.scores[b] = score
        out.found[b] = True
    return out


def face_landmarks(images: Tensor, boxes: Tensor | np.ndarray, network: LandmarkNetwork) -> tuple[Tensor, Tensor]:
    """Run a landmark network on the boxes' crops and map the points to image pixels.

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded (gradients flow to them).
        boxes: (B, 4) x0 y0 x1 y1 crop boxes, pixels (held constant).
        network: a `LandmarkNetwork` (e.g. `MediaPipeFaceMesh`, `HeatmapLandmarks`).
    Returns:
        points (B, L, 2) image pixels (centres at integers), presence (B,).
    """
    size = int(network.input_size)
    crops = crop_and_resize(images, boxes, size)
    points, presence = network(crops)
    box = torch.as_tensor(np.asarray(boxes, np.float64) if not isinstance(boxes, Tensor) else boxes,
                          dtype=points.dtype, device=points.device).reshape(-1, 1, 4)
    scale = (box[..., 2:] - box[..., :2]) / size
    return box[..., :2] + points * scale, presence
