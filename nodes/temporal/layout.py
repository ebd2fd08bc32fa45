"""The parameter layout of fitted sequences, and posing the face model from it.

A fitted sequence is a `ParamSequence` whose columns are, by name (the layout of
`nodes.fit`'s output):

- `rot_x, rot_y, rot_z`: the head's rotation, axis-angle (axis times angle), radians,
  model-to-world (`x_world = R(omega) x_model + t`);
- `trans_x, trans_y, trans_z`: translation, cm, world frame;
- the expression weights by the model's shape names (ARKit names for the ICT head), unitless,
  in [0, 1]. Columns of the model's shapes that are absent are taken as 0; other columns pass
  through untouched.

Torch is imported inside the functions that need it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nodegraph import FaceModel, ParamSequence

__all__ = ["ROTATION_NAMES", "TRANSLATION_NAMES", "RIGID_NAMES", "Layout", "params_layout", "make_params",
           "posed_vertices", "quat_from_axis_angle", "axis_angle_from_quat"]

ROTATION_NAMES = ("rot_x", "rot_y", "rot_z")
TRANSLATION_NAMES = ("trans_x", "trans_y", "trans_z")
RIGID_NAMES = ROTATION_NAMES + TRANSLATION_NAMES


@dataclass(frozen=True)
class Layout:
    """Where the pose and the model's weights are in a `ParamSequence`'s columns.

    Attributes:
        rotation: (3,) column indices of rot_x..rot_z.
        translation: (3,) column indices of trans_x..trans_z.
        weights: (K,) column index of each model shape, -1 where the sequence lacks it.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray

    @property
    def expression_columns(self) -> np.ndarray:
        """Column indices of the model's shapes that the sequence has."""
        return self.weights[self.weights >= 0]


def params_layout(names: list[str], shape_names: list[str], where: str = "params") -> Layout:
    """Find the pose and weight columns by name.

    Args:
        names: the ParamSequence's column names.
        shape_names: the face model's K expression names.
        where: prefix of error messages (the port).
    Returns:
        Layout.
    Raises:
        ValueError: naming the missing rigid columns.
    """
    index = {n: i for i, n in enumerate(names)}
    missing = [n for n in RIGID_NAMES if n not in index]
    if missing:
        raise ValueError(f"{where}: expected columns {list(RIGID_NAMES)} (axis-angle radians, cm), "
                         f"missing {missing} among {names[:10]}")
    return Layout(np.array([index[n] for n in ROTATION_NAMES]), np.array([index[n] for n in TRANSLATION_NAMES]),
                  np.array([index.get(n, -1) for n in shape_names]))


def make_params(rotation: np.ndarray, translation: np.ndarray, weights: np.ndarray, shape_names: list[str],
                fps: float | None = None) -> ParamSequence:
    """(F, 3) axis-angle rad, (F, 3) cm, (F, K) weights -> ParamSequence in the standard layout."""
    values = np.concatenate([rotation, translation, weights], 1).astype(np.float32)
    return ParamSequence(values, list(RIGID_NAMES) + list(shape_names))


def posed_vertices(model_neutral: Any, model_deltas: Any, rotation: Any, translation: Any, weights: Any) -> Any:
    """World vertices of the posed head (torch).

    Args:
        model_neutral: (V, 3) cm; model_deltas: (K, V, 3) cm per unit weight.
        rotation: (B, 3) axis-angle rad; translation: (B, 3) cm; weights: (B, K).
    Returns:
        (B, V, 3) world vertices, cm: `R(omega) (neutral + sum_k w_k d_k) + t`.
    """
    from ..fit.energy import axis_angle_to_rotmat

    k, v = model_deltas.shape[:2]
    local = model_neutral.reshape(-1) + weights @ model_deltas.reshape(k, -1)
    rot = axis_angle_to_rotmat(rotation)
    return local.reshape(-1, v, 3) @ rot.transpose(1, 2) + translation[:, None]


def quat_from_axis_angle(omega: np.ndarray) -> np.ndarray:
    """(..., 3) axis-angle rad -> (..., 4) unit quaternions (w, x, y, z), w >= 0."""
    omega = np.asarray(omega, np.float64)
    angle = np.linalg.norm(omega, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-12), 0.5 - angle ** 2 / 48.0)
    return np.concatenate([np.cos(half), omega * scale], -1)


def axis_angle_from_quat(quat: np.ndarray) -> np.ndarray:
    """(..., 4) quaternions (w, x, y, z), any norm or sign -> (..., 3) axis-angle rad, angle <= pi."""
    q = np.asarray(quat, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    factor = np.where(s > 1e-12, angle / np.maximum(s, 1e-12), 2.0)
    return q[..., 1:] * factor
