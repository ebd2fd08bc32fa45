"""The parameter layout of fitted sequences, and posing the face model from it.

A fitted sequence is a `ParamSequence` whose columns are, by name (the layout of
`nodes.fit`'s output):

- the head's rotation, model-to-world (`x_world = R x_model + t`): either `r00 .. r22`
  (row-major matrix, `nodes.fit`'s layout) or `rot_x, rot_y, rot_z` (axis-angle, radians);
- translation, cm, world frame: `tx, ty, tz` (`nodes.fit`) or `trans_x, trans_y, trans_z`;
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
from nodegraph.performance import MATRIX_COLUMNS, TRANSLATION_COLUMNS

from ..geometry.rotation import axis_angle_to_rotmat, axis_angle_to_rotmat_torch, rotmat_to_axis_angle

__all__ = ["ROTATION_NAMES", "TRANSLATION_NAMES", "RIGID_NAMES", "MATRIX_NAMES", "FIT_TRANSLATION_NAMES", "Layout",
           "params_layout", "make_params", "to_unknowns", "from_unknowns",
           "posed_vertices"]

ROTATION_NAMES = ("rot_x", "rot_y", "rot_z")
TRANSLATION_NAMES = ("trans_x", "trans_y", "trans_z")
RIGID_NAMES = ROTATION_NAMES + TRANSLATION_NAMES
MATRIX_NAMES = MATRIX_COLUMNS  # the fit's layout (`nodegraph.performance`)
FIT_TRANSLATION_NAMES = TRANSLATION_COLUMNS


@dataclass(frozen=True)
class Layout:
    """Where the pose and the model's weights are in a `ParamSequence`'s columns.

    Attributes:
        rotation: (3,) column indices of rot_x..rot_z, or (9,) of r00..r22 (`matrix`).
        translation: (3,) column indices of the translation.
        weights: (K,) column index of each model shape, -1 where the sequence lacks it.
        matrix: the rotation is stored as a row-major matrix.
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray
    matrix: bool = False

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
    weights = np.array([index.get(n, -1) for n in shape_names], np.int64)
    if all(n in index for n in MATRIX_NAMES + FIT_TRANSLATION_NAMES):
        return Layout(np.array([index[n] for n in MATRIX_NAMES]), np.array([index[n] for n in FIT_TRANSLATION_NAMES]),
                      weights, True)
    missing = [n for n in RIGID_NAMES if n not in index]
    if missing:
        raise ValueError(f"{where}: expected columns r00..r22, tx, ty, tz (nodes.fit) or {list(RIGID_NAMES)} "
                         f"(axis-angle radians, cm), missing {missing} among {names[:12]}")
    return Layout(np.array([index[n] for n in ROTATION_NAMES]), np.array([index[n] for n in TRANSLATION_NAMES]),
                  weights)


def to_unknowns(values: np.ndarray, layout: Layout) -> np.ndarray:
    """(F, D) sequence values -> (F, 6 + K) float64 [axis-angle rad, cm, weights] (NaN and missing -> 0)."""
    v = np.nan_to_num(np.asarray(values, np.float64))
    f, k = len(v), len(layout.weights)
    x = np.zeros((f, 6 + k))
    if layout.matrix:
        rot = v[:, layout.rotation].reshape(f, 3, 3)
        ok = np.abs(np.linalg.det(rot) - 1.0) < 0.1 if f else np.zeros(0, bool)
        rot[~ok] = np.eye(3)
        x[:, :3] = rotmat_to_axis_angle(rot)
    else:
        x[:, :3] = v[:, layout.rotation]
    x[:, 3:6] = v[:, layout.translation]
    have = layout.weights >= 0
    x[:, 6:][:, have] = v[:, layout.weights[have]]
    return x


def from_unknowns(x: np.ndarray, values: np.ndarray, layout: Layout) -> np.ndarray:
    """Write (F, 6 + K) unknowns back into a copy of the (F, D) sequence values (float32)."""
    out = np.array(values, np.float64)
    f = len(out)
    if layout.matrix:
        out[:, layout.rotation] = axis_angle_to_rotmat(x[:, :3]).reshape(f, 9)
    else:
        out[:, layout.rotation] = x[:, :3]
    out[:, layout.translation] = x[:, 3:6]
    have = layout.weights >= 0
    out[:, layout.weights[have]] = x[:, 6:][:, have]
    return out.astype(np.float32)


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
    k, v = model_deltas.shape[:2]
    local = model_neutral.reshape(-1) + weights @ model_deltas.reshape(k, -1)
    rot = axis_angle_to_rotmat_torch(rotation)
    return local.reshape(-1, v, 3) @ rot.transpose(1, 2) + translation[:, None]
