"""MediaPipe's face detectors (BlazeFace short and full range) and face mesh (468 points) in torch.

The networks ship in `nodes/data/mediapipe` (Apache-2.0) and are replayed op by op from
their `.tflite` files (`nodes.landmarks.tflite_torch`), so gradients flow from the
landmarks to the input pixels.

Conventions: images are (B, H, W, 3) float RGB in [0, 1], sRGB-encoded (the networks were
trained on photos); pixel centres at integer coordinates, origin top-left, x right, y down.
A box is `(x0, y0, x1, y1)` in those coordinates, the crop covering `[x0, x1] x [y0, y1]`
(the whole image is `(-0.5, -0.5, W - 0.5, H - 0.5)`); crop pixel j's centre is at
`x0 + (j + 1/2) (x1 - x0) / S`.

- `crop_and_resize` (`nodes.geometry.image`): bilinear, differentiable in the pixels with the
  box held constant (the paper's dD/dF = 0); for a shrink by k >= 2 the image is first
  averaged over k x k blocks (no aliasing of fine detail).
- `detect_all_faces`: every face: the image letterboxed to a square (black bars) and resized
  to 128 x 128, BlazeFace's 896 SSD anchors decoded to boxes and 6 keypoints; for faces
  smaller than that pass sees (`min_face_px`), an image pyramid of finer levels run fully
  convolutionally (`grid_anchors`, `pyramid_scales`); one weighted non-maximum suppression
  (IoU 0.3) over all levels. `detect_faces`: the face `face` chooses
  (`nodes.landmarks.tracking`), its box scaled 1.5 about its centre to a square (the crop box
  of the face mesh, as MediaPipe's face-landmark front end) and its roll (`eye_roll`).
- `FullRangeBlazeFace` / `detect_full_range`: BlazeFace full range (192 x 192 input, 2304
  anchors of one stride-4 grid, sparse weights) on the whole frame letterboxed, decoded and
  merged as short range's. On a 1080p frame it finds faces down to a box of about 100 px (an
  eye distance of 45-60 px), where the short-range whole frame stops at about 300 px; one call
  costs about 4.7 short-range calls (190 against 40 ms on one thread at load 9), so it is a
  second look of `landmarks.TrackFaces`, not a level of the pyramid.
- `MediaPipeFaceMesh`: crops (B, 192, 192, 3) -> 468 points (x, y in crop pixels, 0 at the
  crop corner; z dropped) and face presence (sigmoid of the presence logit).
- `face_landmarks`: crop (turned by a roll angle when given), run a landmark network, map the
  points back to image pixels; `upright_face_landmarks` re-turns the crop by the points' own
  eye line (`points_roll`) a few times, so a face rolled 90 degrees is read upright.

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

from ..geometry.image import crop_and_resize, resize_bilinear
from .correspondence import MEDIAPIPE_TO_68
from .heatmap import LandmarkNetwork
from .tflite_torch import TfliteModule, read_tflite
from .tracking import FaceChoice, choose_face

__all__ = ["FACE_LANDMARK_MODEL", "FACE_DETECTOR_MODEL", "mediapipe_path", "srgb_encode",
           "letterbox_box", "square_box", "ssd_anchors", "decode_detections",
           "weighted_nms", "Faces", "FaceDetections", "BlazeFace", "MediaPipeFaceMesh", "grid_anchors",
           "pyramid_scales", "detect_all_faces", "eye_roll", "detect_faces", "select_faces", "face_landmarks",
           "load_face_detector", "load_face_mesh", "DETECT_MIN_PX", "DEFAULT_MIN_FACE_PX", "points_roll",
           "upright_face_landmarks", "FULL_RANGE_DETECTOR_MODEL", "FULL_RANGE_SIZE", "FullRangeBlazeFace",
           "full_range_anchors", "load_full_range_detector", "detect_full_range", "FULL_RANGE_MIN_SCORE"]

FACE_LANDMARK_MODEL = "face_landmark.tflite"
FACE_DETECTOR_MODEL = "face_detection_short_range.tflite"
FULL_RANGE_DETECTOR_MODEL = "face_detection_full_range_sparse.tflite"
DETECTOR_SIZE = 128
FULL_RANGE_SIZE = 192
"""Input side of BlazeFace full range (`FullRangeBlazeFace`), pixels."""
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


@lru_cache(maxsize=1)
def full_range_anchors() -> np.ndarray:
    """The 2304 anchor centres of BlazeFace full range, (2304, 2) x, y in [0, 1].

    MediaPipe's full-range options (face_detection_full_range.pbtxt): one layer of stride 4 on
    the 192 x 192 input, one anchor per cell of the 48 x 48 grid (no interpolated anchor), fixed
    anchor size, cells in row-major order.
    """
    c = (np.arange(FULL_RANGE_SIZE // 4) + 0.5) / (FULL_RANGE_SIZE // 4)
    yy, xx = np.meshgrid(c, c, indexing="ij")
    return np.stack([xx.ravel(), yy.ravel()], -1)


def decode_detections(regressors: Tensor, logits: Tensor, anchors: np.ndarray | None = None,
                      input_size: int = DETECTOR_SIZE) -> tuple[Tensor, Tensor, Tensor]:
    """Decode BlazeFace outputs against the anchors.

    Args:
        regressors: (B, N, 16) raw box (x, y, w, h) and 6 keypoints (x, y), in input pixels.
        logits: (B, N, 1) raw scores.
        anchors: (N, 2) anchor centres in [0, 1] (default `ssd_anchors()`, short range's 896).
        input_size: the detector's input side (128 short range, 192 full range).
    Returns:
        boxes (B, N, 4) x0 y0 x1 y1, keypoints (B, N, 6, 2) x y, both normalized to
        [0, 1] over the detector input; scores (B, N) = sigmoid(clip(logit, -100, 100)).
        Keypoints: right eye, left eye, nose tip, mouth, right ear tragion, left ear tragion.
    """
    anchors = torch.as_tensor(ssd_anchors() if anchors is None else anchors, dtype=regressors.dtype,
                              device=regressors.device)
    r = regressors / input_size
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


class FullRangeBlazeFace(nn.Module):
    """BlazeFace full range (sparse weights): (B, 192, 192, 3) RGB in [0, 1] -> (regressors
    (B, 2304, 16), logits (B, 2304, 1)), against `full_range_anchors` in 192-pixel units. Input
    in [-1, 1] as MediaPipe's face_detection_full_range graph feeds it. Not fully convolutional
    (its upsampling sizes and output reshape are fixed): the input is always 192 x 192."""

    input_size = FULL_RANGE_SIZE

    def __init__(self, path: str | Path | None = None):
        super().__init__()
        self.net = TfliteModule(read_tflite(path or mediapipe_path(FULL_RANGE_DETECTOR_MODEL)),
                                ["Identity", "Identity_1"])

    def forward(self, images: Tensor) -> tuple[Tensor, Tensor]:
        if images.ndim != 4 or tuple(images.shape[1:]) != (FULL_RANGE_SIZE, FULL_RANGE_SIZE, 3):
            raise ValueError(f"images: expected shape (B, {FULL_RANGE_SIZE}, {FULL_RANGE_SIZE}, 3), found "
                             f"{tuple(images.shape)}")
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


@lru_cache(maxsize=3)
def _cached(kind: str) -> nn.Module:
    module = {"detector": BlazeFace, "full_range": FullRangeBlazeFace, "mesh": MediaPipeFaceMesh}[kind]()
    return module.eval()


def load_full_range_detector(device: str = "cpu", dtype: torch.dtype = torch.float32) -> FullRangeBlazeFace:
    """The bundled BlazeFace full range (weights read once per process), on `device`."""
    return _cached("full_range").to(device=device, dtype=dtype)


def load_face_detector(device: str = "cpu", dtype: torch.dtype = torch.float32) -> BlazeFace:
    """The bundled BlazeFace (weights read once per process), on `device`."""
    return _cached("detector").to(device=device, dtype=dtype)


def load_face_mesh(device: str = "cpu", dtype: torch.dtype = torch.float32) -> MediaPipeFaceMesh:
    """The bundled face mesh network (weights read once per process), on `device`."""
    return _cached("mesh").to(device=device, dtype=dtype)


class Faces(NamedTuple):
    """All faces found in one image, by decreasing score: `boxes` (N, 4) the detector's face
    boxes x0 y0 x1 y1, `keypoints` (N, 6, 2) x y (see `decode_detections`), both in image
    pixels; `scores` (N,) in [0, 1]."""

    boxes: np.ndarray
    keypoints: np.ndarray
    scores: np.ndarray


class FaceDetections(NamedTuple):
    """Per image, the chosen face: `boxes` (B, 4) square crop boxes for the face mesh (x0 y0
    x1 y1 pixels; NaN where none), `face_boxes` (B, 4) the detector's own box, `keypoints`
    (B, 6, 2) pixels, `scores` (B,) in [0, 1] (0 where none), `found` (B,) bool, `rolls` (B,)
    the eye line's angle, radians (`eye_roll`; NaN where none)."""

    boxes: np.ndarray
    face_boxes: np.ndarray
    keypoints: np.ndarray
    scores: np.ndarray
    found: np.ndarray
    rolls: np.ndarray


def grid_anchors(height: int, width: int) -> np.ndarray:
    """Anchor centres of BlazeFace short range run on an H x W input (multiples of 16), pixels.

    The network is fully convolutional up to its outputs, so on a larger input it gives one
    prediction per anchor of the larger grids, in the order of `ssd_anchors` (2 anchors per
    cell of the stride-8 grid, then 6 per cell of the stride-16 grid, row-major); on 128 x 128
    this is `ssd_anchors() * 128`. Returns (N, 2) x, y.
    """
    out = []
    for stride, per_cell in ((8, 2), (16, 6)):
        yy, xx = np.meshgrid((np.arange(height // stride) + 0.5) * stride,
                             (np.arange(width // stride) + 0.5) * stride, indexing="ij")
        out.append(np.repeat(np.stack([xx.ravel(), yy.ravel()], -1), per_cell, axis=0))
    return np.concatenate(out)


DETECT_MIN_PX = 20.0
"""Smallest face box side, in detector-input pixels, that BlazeFace short range finds reliably
(the astronaut's face shrunk: score 0.89-0.92 at 20 px, 0.66-0.79 at 16, 0.22-0.49 at 12)."""
LEVEL_MAX_PX = 96.0
"""Largest face box side, in detector-input pixels, kept from a finer pyramid level (larger
faces are found by the coarser levels; larger boxes there are parts of a face)."""
DEFAULT_MIN_FACE_PX = 40.0
"""Default smallest face looked for: a face box of 40 px, an eye distance of about 19 px (the
box side is about 2.1 eye distances)."""
PYRAMID_MIN_SCORE = 0.7
"""Least score of a detection from a finer pyramid level: the finer levels see many more
windows of background, and their false detections (the astronaut's suit, a star field) scored
0.50-0.66 where faces of 20-30 detector pixels scored 0.83-0.97."""
_LEVEL_PIXELS = 4_000_000
"""Detector-input pixels per network call on the finer levels (bounds the memory of a call)."""


def pyramid_scales(height: int, width: int, min_face_px: float) -> list[float]:
    """Scales (detector pixels per image pixel) of the finer pyramid levels after the whole frame.

    The whole frame (letterboxed to 128) finds faces of side >= `DETECT_MIN_PX` / (128 / long
    side); each finer level doubles the scale until a face of `min_face_px` is `DETECT_MIN_PX`
    detector pixels wide (the last step smaller), so no level is added when the frame is at most
    `128 * min_face_px / DETECT_MIN_PX` pixels on its long side (256 for the default 40 px).

    Example:
        >>> [round(s, 3) for s in pyramid_scales(1080, 1920, 40.0)]
        [0.133, 0.267, 0.5]
    """
    if min_face_px <= 0:
        return []
    scale = DETECTOR_SIZE / float(max(height, width))
    target = min(DETECT_MIN_PX / min_face_px, 2.0)
    out = []
    while scale < target * (1 - 1e-9):
        scale = min(2 * scale, target)
        out.append(scale)
    return out


def _suppress_contained(faces: list[tuple[np.ndarray, np.ndarray, float]],
                        fraction: float = 0.5) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """Drop faces whose box lies more than `fraction` inside the box of a face that is larger
    and scores higher (parts of a face found on a fine level); a small confident face inside
    a large doubtful box is kept and the large box dropped."""
    def inside(i: int, j: int) -> float:  # fraction of box i inside box j
        a, b = faces[i][0], faces[j][0]
        inter = np.prod(np.clip(np.minimum(a[2:], b[2:]) - np.maximum(a[:2], b[:2]), 0, None))
        return float(inter / max(np.prod(a[2:] - a[:2]), 1e-12))

    area = [float(np.prod(f[0][2:] - f[0][:2])) for f in faces]
    drop = set()
    for i in range(len(faces)):
        for j in range(len(faces)):
            if i != j and area[j] > area[i] and inside(i, j) > fraction:
                drop.add(i if faces[j][2] >= faces[i][2] else j)
    return [f for i, f in enumerate(faces) if i not in drop]


def detect_all_faces(images: Tensor, detector: nn.Module | None = None, *, min_score: float = 0.5,
                     iou: float = 0.3, min_face_px: float = 0.0,
                     pyramid_min_score: float = PYRAMID_MIN_SCORE) -> list[Faces]:
    """Find every face in each image: the whole frame, then an image pyramid (no gradients).

    Level 0 is the whole frame letterboxed to 128 x 128 (MediaPipe's front end). When faces
    smaller than level 0 can see are wanted (`min_face_px`), finer levels follow
    (`pyramid_scales`): the frame resized (area-averaged) to each scale and run fully
    convolutionally, which is the detector over overlapping 128 x 128 tiles at a stride of
    16 pixels without recomputing their overlaps (a face is never cut by a tile edge). The
    candidates of all levels, in image pixels, go through one weighted NMS; then a face lying
    mostly inside a larger one is dropped.

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        detector: a `BlazeFace` (default: the bundled one, on the images' device).
        min_score: detections below this score are dropped (MediaPipe: 0.5).
        iou: weighted-NMS overlap threshold (MediaPipe: 0.3).
        min_face_px: smallest face box side to look for, image pixels; 0 = level 0 only.
        pyramid_min_score: least score on the finer levels (at least `min_score`).
    Returns:
        one `Faces` per image.
    """
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected shape (B, H, W, 3), found {tuple(images.shape)}")
    bsz, height, width = images.shape[:3]
    detector = detector or load_face_detector(str(images.device), images.dtype)
    letter = letterbox_box(height, width)
    side = letter[2] - letter[0]
    cand: list[list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = [[] for _ in range(bsz)]
    with torch.no_grad():
        inputs = crop_and_resize(images, np.repeat(letter[None], bsz, 0), DETECTOR_SIZE)
        boxes_n, kps_n, scores = (t.double().cpu().numpy() for t in decode_detections(*detector(inputs)))
        for b in range(bsz):
            keep = scores[b] >= min_score
            cand[b].append((letter[[0, 1, 0, 1]] + boxes_n[b, keep] * side, letter[:2] + kps_n[b, keep] * side,
                            scores[b, keep]))
        for scale in pyramid_scales(height, width, min_face_px):
            h, w = max(int(round(height * scale)), 1), max(int(round(width * scale)), 1)
            sy, sx = h / height, w / width
            hp, wp = -(-h // 16) * 16, -(-w // 16) * 16
            anchors = torch.as_tensor(grid_anchors(hp, wp), dtype=images.dtype, device=images.device)
            step = max(1, _LEVEL_PIXELS // (hp * wp))
            for start in range(0, bsz, step):
                level = resize_bilinear(images[start:start + step], (h, w), antialias=scale < 1)
                level = F.pad(level, (0, 0, 0, wp - w, 0, hp - h))
                regressors, logits = detector(level)
                score = torch.sigmoid(logits[..., 0].clamp(-100.0, 100.0))
                for i in range(len(level)):
                    keep = ((score[i] >= max(min_score, pyramid_min_score)) &
                            (regressors[i, :, 2:4].amax(-1) <= LEVEL_MAX_PX))
                    r = regressors[i, keep].double().cpu().numpy()
                    a = anchors[keep].double().cpu().numpy()
                    centre, half = r[:, 0:2] + a, r[:, 2:4] / 2
                    box = np.concatenate([centre - half, centre + half], -1)
                    kps = r[:, 4:16].reshape(-1, 6, 2) + a[:, None, :]
                    to_image = np.array([sx, sy])
                    cand[start + i].append((((box.reshape(-1, 2, 2) + 0.5) / to_image - 0.5).reshape(-1, 4),
                                            (kps + 0.5) / to_image - 0.5, score[i, keep].double().cpu().numpy()))
    out = []
    for parts in cand:
        boxes_px = np.concatenate([p[0] for p in parts]).reshape(-1, 4)
        kps_px = np.concatenate([p[1] for p in parts]).reshape(-1, 6, 2)
        found = _suppress_contained(weighted_nms(boxes_px, kps_px, np.concatenate([p[2] for p in parts]),
                                                 min_score=min_score, iou=iou))
        out.append(Faces(np.array([f[0] for f in found]).reshape(-1, 4),
                         np.array([f[1] for f in found]).reshape(-1, 6, 2), np.array([f[2] for f in found])))
    return out


FULL_RANGE_MIN_SCORE = 0.5
"""Least score of a BlazeFace full-range detection (`detect_full_range`; MediaPipe's full-range
graph uses 0.5 too)."""


def detect_full_range(images: Tensor, detector: nn.Module | None = None, *,
                      min_score: float = FULL_RANGE_MIN_SCORE, iou: float = 0.3) -> list[Faces]:
    """Every face BlazeFace full range finds in each whole image (no gradients).

    The image letterboxed to a square and resized to 192 x 192 (`FullRangeBlazeFace`), its
    2304 anchors decoded (`full_range_anchors`) and merged by weighted NMS, as MediaPipe's
    face_detection_full_range graph. On a 1920 x 1080 frame (a tenth of the frame per detector
    pixel) it found the astronaut down to a 45 px eye distance (score 0.63; 0.89 at 60 px).

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        detector: a `FullRangeBlazeFace` (default: the bundled one, on the images' device).
        min_score: detections below this score are dropped.
        iou: weighted-NMS overlap threshold.
    Returns:
        one `Faces` per image, in image pixels, by decreasing score.
    """
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images: expected shape (B, H, W, 3), found {tuple(images.shape)}")
    bsz, height, width = images.shape[:3]
    detector = detector or load_full_range_detector(str(images.device), images.dtype)
    letter = letterbox_box(height, width)
    side = letter[2] - letter[0]
    with torch.no_grad():
        inputs = crop_and_resize(images, np.repeat(letter[None], bsz, 0), FULL_RANGE_SIZE)
        boxes_n, kps_n, scores = (t.double().cpu().numpy() for t in
                                  decode_detections(*detector(inputs), full_range_anchors(), FULL_RANGE_SIZE))
    out = []
    for b in range(bsz):
        keep = scores[b] >= min_score
        found = weighted_nms(letter[[0, 1, 0, 1]] + boxes_n[b, keep] * side, letter[:2] + kps_n[b, keep] * side,
                             scores[b, keep], min_score=min_score, iou=iou)
        out.append(Faces(np.array([f[0] for f in found]).reshape(-1, 4),
                         np.array([f[1] for f in found]).reshape(-1, 6, 2), np.array([f[2] for f in found])))
    return out


def eye_roll(keypoints: np.ndarray) -> np.ndarray:
    """The eye line's angle from the detector's keypoints (MediaPipe's crop rotation).

    Args:
        keypoints: (..., 6, 2) pixels; 0 the subject's right eye (image left when upright), 1 the left.
    Returns:
        (...) radians, atan2 of the right-to-left eye vector in image axes (y down): 0 for an
        upright face, positive when the face is turned clockwise on screen.
    """
    kps = np.asarray(keypoints, np.float64)
    d = kps[..., 1, :] - kps[..., 0, :]
    return np.arctan2(d[..., 1], d[..., 0])


def detect_faces(images: Tensor, detector: nn.Module | None = None, *, min_score: float = 0.5,
                 iou: float = 0.3, scale: float = BOX_SCALE, min_face_px: float = 0.0,
                 face: FaceChoice = "largest") -> FaceDetections:
    """Detect the chosen face in each image and return its square crop box (no gradients).

    Each image is treated alone (`nodes.landmarks.tracking.follow_faces` follows a face in a
    video).

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        detector: a `BlazeFace` (default: the bundled one, on the images' device).
        min_score: detections below this score are dropped (MediaPipe: 0.5).
        iou: weighted-NMS overlap threshold (MediaPipe: 0.3).
        scale: crop side over the longer side of the face box.
        min_face_px: smallest face to look for (`detect_all_faces`); 0 = the whole frame only.
        face: which face (`nodes.landmarks.tracking.choose_face`).
    Returns:
        FaceDetections in image pixels.
    """
    found = detect_all_faces(images, detector, min_score=min_score, iou=iou, min_face_px=min_face_px)
    height, width = images.shape[1:3]
    chosen = [choose_face(f.boxes, f.scores, face, (height, width)) for f in found]
    return select_faces(found, np.array(chosen, np.int64), scale)


def select_faces(faces: list[Faces], chosen: np.ndarray, scale: float = BOX_SCALE) -> FaceDetections:
    """FaceDetections of `faces[b]`'s detection `chosen[b]` (-1: none), crop boxes scaled by `scale`."""
    bsz = len(faces)
    out = FaceDetections(np.full((bsz, 4), np.nan), np.full((bsz, 4), np.nan), np.full((bsz, 6, 2), np.nan),
                         np.zeros(bsz), np.zeros(bsz, bool), np.full(bsz, np.nan))
    for b, (f, i) in enumerate(zip(faces, chosen)):
        if i < 0:
            continue
        out.face_boxes[b] = f.boxes[i]
        out.keypoints[b] = f.keypoints[i]
        out.boxes[b] = square_box(f.boxes[i], scale)
        out.scores[b] = f.scores[i]
        out.found[b] = True
        out.rolls[b] = eye_roll(f.keypoints[i])
    return out


def face_landmarks(images: Tensor, boxes: Tensor | np.ndarray, network: LandmarkNetwork,
                   angles: Tensor | np.ndarray | None = None) -> tuple[Tensor, Tensor]:
    """Run a landmark network on the boxes' crops and map the points to image pixels.

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded (gradients flow to them).
        boxes: (B, 4) x0 y0 x1 y1 crop boxes, pixels (held constant).
        network: a `LandmarkNetwork` (e.g. `MediaPipeFaceMesh`, `HeatmapLandmarks`).
        angles: (B,) radians or None: each crop turned by its angle about the box centre
            (`crop_and_resize`; e.g. `eye_roll` of the detector's keypoints), so that the
            network sees the face upright; the points are turned back.
    Returns:
        points (B, L, 2) image pixels (centres at integers), presence (B,).
    """
    size = int(network.input_size)
    crops = crop_and_resize(images, boxes, size, angles)
    points, presence = network(crops)
    box = torch.as_tensor(np.asarray(boxes, np.float64) if not isinstance(boxes, Tensor) else boxes,
                          dtype=points.dtype, device=points.device).reshape(-1, 1, 4)
    scale = (box[..., 2:] - box[..., :2]) / size
    if angles is None:
        return box[..., :2] + points * scale, presence
    theta = torch.as_tensor(np.asarray(angles.detach().cpu() if isinstance(angles, Tensor) else angles, np.float64),
                            dtype=points.dtype, device=points.device).reshape(-1, 1)
    c, s = torch.cos(theta), torch.sin(theta)
    d = (points - size / 2) * scale  # offsets from the crop centre, image pixels, crop axes
    centre = (box[..., :2] + box[..., 2:]) / 2
    turned = torch.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], -1)
    return centre + turned, presence


def points_roll(points: np.ndarray) -> np.ndarray:
    """The eye line's angle from landmarks (as `eye_roll`): the right eye's centre to the left's.

    Args:
        points: (..., 468, 2) face-mesh or (..., 68, 2) Multi-PIE points, pixels.
    Returns:
        (...) radians (NaN where the points are NaN).
    """
    p = np.asarray(points, np.float64)
    if p.shape[-2] == 468:
        p = p[..., MEDIAPIPE_TO_68, :]
    if p.shape[-2] != 68:
        raise ValueError(f"points: expected shape (..., 468, 2) or (..., 68, 2), found {p.shape}")
    d = p[..., 42:48, :].mean(-2) - p[..., 36:42, :].mean(-2)
    return np.arctan2(d[..., 1], d[..., 0])


ROLL_DEADZONE_RAD = np.deg2rad(10.0)
"""Rolls up to this are read from the upright crop: the face mesh reads them as well as a turned
one, and the fit's landmarks (and the accuracy it was tuned to) stay those of the upright crop."""


def upright_face_landmarks(images: Tensor, boxes: np.ndarray, network: LandmarkNetwork,
                           angles: np.ndarray | None = None, passes: int = 2) -> tuple[Tensor, Tensor, np.ndarray]:
    """`face_landmarks` with the crop turned upright, then re-turned by the points' own eye line.

    The detector's eye keypoints give the roll only roughly (a face rolled 90 degrees reads as
    about 40), so after the first pass the crop is turned by the eye line of the points found
    (`points_roll`) and read again, `passes` times: each pass leaves a smaller roll in the crop,
    which the network reads better.

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        boxes: (B, 4) crop boxes, pixels (the crop turns about their centres; side kept).
        network: a `LandmarkNetwork` of 468 or 68 points.
        angles: (B,) first roll, radians (e.g. `eye_roll`); None or NaN = 0 (upright).
        passes: extra passes after the first (0: the first crop only).
    Returns:
        points (B, L, 2) image pixels, presence (B,), the roll of the last crop (B,) radians.
    """
    def turn(roll: np.ndarray) -> np.ndarray:  # within ROLL_DEADZONE_RAD of upright: the upright crop
        return np.where(np.abs(roll) > ROLL_DEADZONE_RAD, roll, 0.0)

    theta = turn(np.zeros(len(images)) if angles is None else np.nan_to_num(np.asarray(angles, np.float64).reshape(-1)))
    points, presence = face_landmarks(images, boxes, network, theta)
    for _ in range(passes):
        roll = points_roll(points.detach().double().cpu().numpy())
        new = turn(np.where(np.isfinite(roll), roll, theta))
        if np.array_equal(new, theta):  # nothing to turn (an upright face): the same crop again
            break
        theta = new
        points, presence = face_landmarks(images, boxes, network, theta)
    return points, presence, theta
