"""Fixed correspondences between landmark schemes: MediaPipe's 468-point face mesh, the
Multi-PIE / iBUG 300-W 68 points, and the bundled ICT head's 68 landmark vertices.

`MEDIAPIPE_TO_68[i]` is the face-mesh point used for Multi-PIE point i (0-based: 0-16 jaw
from the subject's right ear to the left, 17-21 right brow, 22-26 left brow, 27-30 nose
bridge to tip, 31-35 nostrils, 36-41 right eye, 42-47 left eye, 48-59 outer lip, 60-67 inner
lip; "right" is the subject's right, on the image's left in a frontal view). The table starts
from the widely used hand-made one (as published with face-alignment tooling built on
MediaPipe: jaw 127 234 93 132 58 136 150 176 152 400 379 365 288 361 323 454 356, eyes
33 ... 263, lips 61 39 37 0 267 269 291 405 314 17 84 181 / 78 82 13 312 308 317 14 87) and
replaces, in left-right mirror pairs, the entries whose face-mesh point lay more than 1% of
the inter-ocular distance farther from the bundled ICT head's landmark vertex than another
point did, on renders of the head at ten poses (yaw up to 25 deg, pitch 8 deg, jaw open up
to 0.5): jaw 4-7 and 9-12 (lower on the jaw line, as the head's landmarks are), nose 29,
eye corners 36, 39, 42, 45, outer lip 49, 53, 55, 59 and the inner lip 60, 61, 63-65, 67.
The jaw candidates were restricted to the face-oval ring, so the jaw stays a contour.
With it, the network's 68 points on renders of the head lie within about 3% of the
inter-ocular distance of the projected landmark vertices on average (the standard table:
about 5%; numbers in the landmarks tests and the README).

Caveats:

- Jaw (0-16): Multi-PIE jaw points lie on the visible cheek/chin contour, which slides over
  the surface as the head turns; the face-mesh points are fixed surface points. They agree
  in frontal views and drift apart with yaw; fitting should down-weight them (the paper's
  per-landmark weights).
- Nose tip (30): face-mesh point 4 vs the ICT model's landmark vertex 30 differ by a small
  offset, measured in `tests/nodes/landmarks/test_render_landmarks.py` and documented in the
  README.
- For fitting (paper 2), both the plate and the render go through the same table, so the
  energy does not depend on it; the table matters where network points are compared with
  model vertices (initialization, evaluation).

The 68 points map to the bundled model by index: `FaceModel.landmarks[i]` is the vertex of
Multi-PIE point i, so `MEDIAPIPE_TO_68` composed with `FaceModel.landmarks` relates the
face mesh to the model's vertices (`mediapipe_to_model_vertices`).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MEDIAPIPE_TO_68", "MESH_EXTRA_POINTS", "MULTIPIE_68_GROUPS", "mediapipe_to_68", "mediapipe_to_model_vertices",
           "outer_eye_corners_68", "inter_ocular_distance"]

MEDIAPIPE_TO_68 = np.array([
    127, 234, 93, 132, 172, 150, 149, 148, 152, 377, 378, 379, 397, 361, 323, 454, 356,  # jaw 0-16
    70, 63, 105, 66, 107,  # right brow 17-21
    336, 296, 334, 293, 300,  # left brow 22-26
    168, 197, 195, 4,  # nose bridge 27-30
    75, 97, 2, 326, 305,  # nostrils 31-35
    7, 160, 158, 112, 153, 144,  # right eye 36-41
    341, 385, 387, 249, 373, 380,  # left eye 42-47
    61, 40, 37, 0, 267, 270, 291, 321, 314, 17, 84, 91,  # outer lip 48-59
    76, 81, 13, 311, 306, 402, 14, 178,  # inner lip 60-67
], dtype=np.int64)
"""(68,) face-mesh index of each Multi-PIE point (see the module docstring)."""

MESH_EXTRA_POINTS = np.setdiff1d(np.arange(468), MEDIAPIPE_TO_68)
"""(400,) the face-mesh points that are not among the 68 (surface points over the cheeks,
forehead and nose; `fit.EstimateIdentity` reads them after the 68)."""

MULTIPIE_68_GROUPS = {
    "jaw": np.arange(0, 17), "brows": np.arange(17, 27), "nose": np.arange(27, 36),
    "eyes": np.arange(36, 48), "outer_lip": np.arange(48, 60), "inner_lip": np.arange(60, 68),
}
"""Named groups of the 68 Multi-PIE points (0-based indices)."""


def mediapipe_to_68(points: np.ndarray) -> np.ndarray:
    """Select the 68 Multi-PIE points from 468 face-mesh points (works on numpy or torch).

    Args:
        points: (..., 468, D) face-mesh points.
    Returns:
        (..., 68, D) the Multi-PIE points, same library and dtype.

    Example:
        >>> mediapipe_to_68(np.arange(468.0)[:, None])[30, 0]
        4.0
    """
    if points.shape[-2] != 468:
        raise ValueError(f"points: expected shape (..., 468, D), found {tuple(points.shape)}")
    return points[..., MEDIAPIPE_TO_68, :]


def mediapipe_to_model_vertices(model_landmarks: np.ndarray) -> dict[int, int]:
    """Face-mesh index -> model vertex, through the 68 points.

    Args:
        model_landmarks: (68,) int, `FaceModel.landmarks` (vertex of each Multi-PIE point).
    Returns:
        {face-mesh index: vertex index} for the 68 points.
    """
    model_landmarks = np.asarray(model_landmarks)
    if model_landmarks.shape != (68,):
        raise ValueError(f"model_landmarks: expected shape (68,), found {model_landmarks.shape}")
    return {int(m): int(v) for m, v in zip(MEDIAPIPE_TO_68, model_landmarks)}


def outer_eye_corners_68() -> tuple[int, int]:
    """Indices of the outer eye corners among the 68 points (36: right, 45: left)."""
    return 36, 45


def inter_ocular_distance(points68: np.ndarray) -> np.ndarray:
    """Distance between the outer eye corners (points 36 and 45), the usual error unit.

    Args:
        points68: (..., 68, 2) pixels.
    Returns:
        (...) pixels.
    """
    points68 = np.asarray(points68, np.float64)
    return np.linalg.norm(points68[..., 36, :] - points68[..., 45, :], axis=-1)
