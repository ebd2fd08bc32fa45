"""Which frames the appearance and identity estimates use, and how far apart their views are.

- near-neutral frames: the least open mouths (inner-lip gap over the eye distance), where the
  expression blendshapes matter least for a rigid alignment and an albedo painting;
- `painting_frame_count`: how many frames fit.EstimateAppearance paints for a plate's noise;
- `view_spread_deg`: how far apart the directions the head was seen from are (frames turning or
  several cameras), which decides whether the lighting is fitted first and which identity prior
  applies.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nodegraph import Landmarks2D

__all__ = ["painting_frame_count", "view_spread_deg"]


def _mouth_gaps(landmarks: Landmarks2D, found: np.ndarray) -> np.ndarray:
    """(F,) inner-lip gap over the eye distance; inf where no face was found."""
    from ..landmarks.correspondence import inter_ocular_distance

    pts = landmarks.points.astype(np.float64)
    gap = np.linalg.norm(pts[:, 66] - pts[:, 62], axis=-1) / np.maximum(inter_ocular_distance(pts), 1e-6)
    return np.where(found & np.isfinite(gap), gap, np.inf)


def _near_neutral_frame(landmarks: Landmarks2D, found: np.ndarray) -> int:
    """The detected frame with the least open mouth (inner-lip gap over the eye distance)."""
    return int(np.argmin(_mouth_gaps(landmarks, found)))


def _painting_frames(landmarks: Landmarks2D, found: np.ndarray, count: int, exclude: int) -> np.ndarray:
    """Up to `count` detected frames other than `exclude`, the least open mouths first."""
    gap = _mouth_gaps(landmarks, found)
    gap[exclude] = np.inf
    order = np.argsort(gap, kind="stable")[:max(count, 0)]
    return order[np.isfinite(gap[order])]


def _render_noise(asked: float, plate_noise: float, above: float = 0.02) -> float:
    """fit.EstimateAppearance's render noise: `asked` >= 0 as given, -1 the plate's, -2 the plate's above `above`."""
    if asked >= 0:
        return float(asked)
    if asked == -1 or plate_noise > above:
        return float(plate_noise)
    return 0.0


def view_spread_deg(rot: Any, world_to_camera: Any, seen: Any) -> float:
    """Largest angle (degrees) between the head's orientation in any seen view and in the first.

    Args:
        rot: (B, 3, 3) torch, the frames' head rotations (model to world).
        world_to_camera: (C, 4, 4) torch, the cameras.
        seen: (B, C) bool torch, the views that saw the face.
    Returns:
        0 for a single view; the spread of the directions the head was seen from otherwise (the
        frames' turns and the cameras' placement both count).
    """
    import torch

    from ..geometry.rigid import rotation_angle

    in_cam = world_to_camera[None, :, :3, :3] @ rot[:, None]  # (B, C, 3, 3) model to each camera
    views = in_cam[seen.to(torch.bool)]
    if len(views) < 2:
        return 0.0
    rel = (views[:1].transpose(-1, -2) @ views).detach().cpu().numpy()
    return float(np.degrees(rotation_angle(rel).max()))



def painting_frame_count(noise: float, target: float = 0.01, most: int = 8) -> int:
    """Frames `fit.EstimateAppearance` paints by default, for a plate of `noise` (linear).

    The painting frames' poses come from the landmarks alone, and every later fit aligns the
    plate to the painting (the photometric term), so a painting frame's pose error becomes
    every frame's. On a noisy plate that error is mostly random (bench/fit.py, noise 0.03, 16
    frames: the frames' errors spread 3.6 deg about their median), and n frames divide it by
    about sqrt(n): n = (noise / target)^2, at least 1, at most `most`. On a clean plate the
    error is a bias shared by the frames and one frame (the least open mouth) paints sharper
    (seed 1, noise 0.005: 2.4 deg with 1 frame, 3.2 with 8).
    """
    if not np.isfinite(noise) or noise <= target:
        return 1
    return int(min(max(round((noise / target) ** 2), 1), most))
