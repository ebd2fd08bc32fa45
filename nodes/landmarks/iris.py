"""MediaPipe's iris model in torch: 5 iris points per eye, in eye crops from the face mesh's points.

The network (`iris_landmark.tflite`, Apache-2.0, shipped in `nodes/data/mediapipe`) reads a
64 x 64 crop of one eye, RGB in [0, 1], and gives 71 eye-contour and brow points and 5 iris
points (x, y in crop pixels; z dropped). It was trained on the eye on the image's left (the
subject's right eye in a frontal view); the other eye is mirrored before and after, as
MediaPipe's `IrisLandmarkLeftAndRight` graph does. Each crop is MediaPipe's: a square about
the midpoint of the eye's two corners (face-mesh points 33 and 133 for the image-left eye, 362
and 263 for the image-right one), of side 2.3 corner distances, turned by the corner line's
angle so the eye lies level.

Conventions as in `nodes.landmarks.network`: images (B, H, W, 3) float RGB in [0, 1],
sRGB-encoded; pixel centres at integers, origin top-left, x right, y down. Eye 0 is the
subject's right eye (the image's left in a frontal view, Multi-PIE points 36-41), eye 1 the
left (42-47). Iris point 0 is the iris centre, points 1-4 lie on its rim. A per-eye gaze
measure from them: `nodes.landmarks.tracking.eye_gaze`.

This module imports torch at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from ..geometry.image import crop_and_resize
from .network import mediapipe_path
from .tflite_torch import TfliteModule, read_tflite
from .tracking import EYE_CORNERS

__all__ = ["IRIS_MODEL", "IRIS_SIZE", "EYE_CORNERS", "EYE_BOX_SCALE", "IrisNetwork", "load_iris_network",
           "eye_crops", "iris_landmarks"]

IRIS_MODEL = "iris_landmark.tflite"
IRIS_SIZE = 64
"""Side of the iris network's input crop, pixels."""
EYE_BOX_SCALE = 2.3
"""Side of an eye crop over its corner distance (MediaPipe's `IrisLandmarkLandmarksToRoi`)."""


class IrisNetwork(nn.Module):
    """MediaPipe's iris model: (B, 64, 64, 3) RGB in [0, 1] -> (eye contour and brows (B, 71, 2),
    iris (B, 5, 2)), crop pixels, 0 at the crop corner; for the image-left eye (mirror the other)."""

    input_size = IRIS_SIZE

    def __init__(self, path: str | Path | None = None):
        super().__init__()
        self.net = TfliteModule(read_tflite(path or mediapipe_path(IRIS_MODEL)),
                                ["output_eyes_contours_and_brows", "output_iris"])

    def forward(self, crops: Tensor) -> tuple[Tensor, Tensor]:
        if crops.ndim != 4 or tuple(crops.shape[1:]) != (IRIS_SIZE, IRIS_SIZE, 3):
            raise ValueError(f"crops: expected shape (B, {IRIS_SIZE}, {IRIS_SIZE}, 3), found {tuple(crops.shape)}")
        contour, iris = self.net(crops)
        return contour.reshape(len(crops), 71, 3)[..., :2], iris.reshape(len(crops), 5, 3)[..., :2]


@lru_cache(maxsize=1)
def _cached() -> IrisNetwork:
    return IrisNetwork().eval()


def load_iris_network(device: str = "cpu", dtype: torch.dtype = torch.float32) -> IrisNetwork:
    """The bundled iris network (weights read once per process), on `device`."""
    return _cached().to(device=device, dtype=dtype)


def eye_crops(points468: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MediaPipe's eye crops from face-mesh points (see the module docstring).

    Args:
        points468: (B, 468, 2) pixels.
    Returns:
        boxes (B, 2, 4) x0 y0 x1 y1 pixels (the crop before its turn), angles (B, 2) radians
        (the corner line's angle, clockwise on screen; `crop_and_resize`'s convention).
    """
    p = np.asarray(points468, np.float64)
    if p.ndim != 3 or p.shape[1:] != (468, 2):
        raise ValueError(f"points468: expected shape (B, 468, 2), found {p.shape}")
    a, b = p[:, EYE_CORNERS[:, 0]], p[:, EYE_CORNERS[:, 1]]  # (B, 2, 2)
    centre, d = (a + b) / 2, b - a
    half = EYE_BOX_SCALE * np.linalg.norm(d, axis=-1, keepdims=True) / 2
    return np.concatenate([centre - half, centre + half], -1), np.arctan2(d[..., 1], d[..., 0])


def iris_landmarks(images: Tensor, points468: np.ndarray, network: nn.Module) -> np.ndarray:
    """The 5 iris points of each eye in image pixels (no gradients).

    Args:
        images: (B, H, W, 3) RGB in [0, 1], sRGB-encoded.
        points468: (B, 468, 2) face-mesh points, pixels (NaN rows: no face).
        network: an `IrisNetwork`.
    Returns:
        (B, 2, 5, 2) float64 pixels: eye 0 the subject's right, eye 1 the left; point 0 the iris
        centre, 1-4 on its rim; NaN where the points are NaN.
    """
    p = np.asarray(points468, np.float64)
    out = np.full((len(p), 2, 5, 2), np.nan)
    rows = np.flatnonzero(np.isfinite(p).all((1, 2)))
    if not len(rows):
        return out
    boxes, angles = eye_crops(p[rows])
    sel = images if len(rows) == len(images) else images[torch.as_tensor(rows, device=images.device)]
    with torch.no_grad():
        crops = torch.stack([crop_and_resize(sel, boxes[:, e], IRIS_SIZE, angles[:, e]) for e in (0, 1)], 1)
        crops[:, 1] = crops[:, 1].flip(2)  # the image-right eye mirrored
        # both eyes in one call: the second crop adds a third of one crop's cost (per-operator
        # overhead dominates at 64 x 64); two calls side by side on two Python threads cost 1.5x
        # the CPU time and gained no wall time on the shared 2-core machine
        _, iris = network(crops.reshape(-1, IRIS_SIZE, IRIS_SIZE, 3))
    iris = iris.double().cpu().numpy().reshape(len(rows), 2, 5, 2)
    iris[:, 1, :, 0] = IRIS_SIZE - iris[:, 1, :, 0]  # mirrored back (x' = S - x on pixel edges)
    side = (boxes[..., 2] - boxes[..., 0])[..., None]  # (R, 2, 1)
    d = (iris - IRIS_SIZE / 2) * side[..., None] / IRIS_SIZE  # offsets from the crop centre, crop axes
    c, s = np.cos(angles)[..., None], np.sin(angles)[..., None]
    centre = (boxes[..., :2] + boxes[..., 2:]) / 2
    out[rows] = centre[:, :, None] + np.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], -1)
    return out
