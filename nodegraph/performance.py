"""`Performance`: a fitted facial performance, the value that fit, temporal, export and the
readers of animation files exchange.

Per frame it holds the head's rigid pose (model-to-world rotation and translation, cm) and the
named expression weights, with a failure flag; for the whole shot the identity weights and the
frame rate. It also owns the column layout of a fitted `ParamSequence` (`POSE_COLUMNS` then
the weights by name), the one table `nodes.fit` writes and `nodes.temporal` reads.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .ports import PortType, check_array, check_finite, fail
from .sequences import ParamSequence

__all__ = ["Performance", "MATRIX_COLUMNS", "TRANSLATION_COLUMNS", "POSE_COLUMNS"]

MATRIX_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))
"""Column names of the model-to-world rotation, row-major (`r01` is row 0, column 1)."""

TRANSLATION_COLUMNS = ("tx", "ty", "tz")
"""Column names of the model-to-world translation, cm."""

POSE_COLUMNS = MATRIX_COLUMNS + TRANSLATION_COLUMNS
"""The first 12 columns of a fitted `ParamSequence`; the expression weights follow by name."""

_ROTATION_TOL = 1e-3  # max |R R^T - I| of a stored rotation (float32 storage and round trips)


@dataclass(eq=False)
class Performance(PortType):
    """A facial performance over frames: the head's pose and named expression weights.

    Posed vertices are `R_f (neutral + identity @ identity_deltas + w_f @ expression_deltas) + t_f`.

    Attributes:
        rotation: (F, 3, 3) float32, model-to-world (`x_world = R x_model + t`), det +1.
        translation: (F, 3) float32, cm, world frame.
        weights: (F, K) float32, unitless (ARKit-style shapes are in [0, 1]).
        expression_names: K shape names (the face model's; ARKit names for the ICT head).
        failed: (F,) bool, True where the frame has no trustworthy solution (its pose and
            weights are still finite: the fit's or a neighbour's values).
        identity: (I,) float32 identity weights of the face model (empty: the model as given).
        fps: frames per second (> 0).
    """

    rotation: np.ndarray
    translation: np.ndarray
    weights: np.ndarray
    expression_names: list[str]
    failed: np.ndarray
    identity: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))
    fps: float = 30.0

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("rotation", "translation", "weights", "failed")

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "rotation", self.rotation, 3, (3, 3))
        check_array(where, "translation", self.translation, 2, (3,))
        check_array(where, "weights", self.weights, 2)
        check_array(where, "failed", self.failed, 1, kinds="b")
        check_array(where, "identity", self.identity, 1)
        for name in ("rotation", "translation", "weights", "identity"):
            check_finite(where, name, getattr(self, name))
        if len(self.expression_names) != self.weights.shape[1]:
            fail(where, f"{len(self.expression_names)} expression names for {self.weights.shape[1]} weight columns")
        if len(set(self.expression_names)) != len(self.expression_names):
            fail(where, "expression names must be distinct")
        if not (isinstance(self.fps, (int, float)) and np.isfinite(self.fps) and 0 < self.fps <= 1e4):
            fail(where, f"'fps' must be a number in (0, 10000], found {self.fps!r}")
        if len(self.rotation):
            rot = self.rotation.astype(np.float64)
            err = np.abs(rot @ rot.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
            det = np.linalg.det(rot)
            bad = np.flatnonzero((err > _ROTATION_TOL) | (det < 0))
            if bad.size:
                fail(where, f"'rotation' of frame {int(bad[0])} is not a rotation (|R R^T - I| = "
                            f"{err[bad[0]]:.3g}, det {det[bad[0]]:.3g})")
        super().validate(where)

    # -- the fitted ParamSequence layout --------------------------------------------------
    @classmethod
    def from_params(cls, fitted: ParamSequence, *, failed: np.ndarray | None = None,
                    identity: np.ndarray | None = None, fps: float = 30.0,
                    where: str = "fitted") -> "Performance":
        """Read a fitted `ParamSequence` (`POSE_COLUMNS`, then the weights).

        Non-finite values (a frame the fit could not solve) become the identity rotation, zero
        translation and zero weights, and the frame is flagged failed.

        Args:
            fitted: (F, 12 + K) values; columns `r00..r22, tx, ty, tz`, then K shape names.
            failed: (F,) bool, or None (no frame failed but the non-finite ones).
            identity: (I,) identity weights, or None.
            fps: frames per second.
            where: prefix of error messages (the port).
        Raises:
            ValueError: naming the missing pose columns.
        """
        names = list(fitted.names)
        if tuple(names[:12]) != POSE_COLUMNS:
            missing = [n for n in POSE_COLUMNS if n not in names]
            fail(where, f"expected the columns {list(POSE_COLUMNS)} first (a fitted sequence of nodes.fit), "
                        f"found {names[:12]}" + (f" (missing {missing})" if missing else ""))
        values = np.asarray(fitted.values, np.float32)
        f = len(values)
        good = np.isfinite(values).all(axis=1)
        flags = ~good if failed is None else (np.asarray(failed, bool).reshape(f) | ~good)
        rotation = np.where(good[:, None, None], np.nan_to_num(values[:, :9]).reshape(f, 3, 3), np.eye(3, dtype=np.float32))
        translation = np.where(good[:, None], np.nan_to_num(values[:, 9:12]), 0.0)
        weights = np.where(good[:, None], np.nan_to_num(values[:, 12:]), 0.0)
        ident = np.zeros(0, np.float32) if identity is None else np.asarray(identity, np.float32).reshape(-1)
        return cls(rotation.astype(np.float32), translation.astype(np.float32), weights.astype(np.float32),
                   names[12:], flags, ident, float(fps))

    def to_params(self) -> ParamSequence:
        """The fitted `ParamSequence` form: (F, 12 + K) float32, `POSE_COLUMNS` then the weights."""
        f = len(self.rotation)
        values = np.concatenate([self.rotation.reshape(f, 9), self.translation, self.weights], axis=1)
        return ParamSequence(values.astype(np.float32), list(POSE_COLUMNS) + list(self.expression_names))

    def weights_in(self, names: list[str]) -> np.ndarray:
        """(F, K) float32 weights in the order of K shape names (a face model's); absent shapes are 0.

        Raises:
            ValueError: when the performance has a shape `names` lacks (naming a few).
        """
        index = {n: i for i, n in enumerate(names)}
        missing = [n for n in self.expression_names if n not in index]
        if missing:
            raise ValueError(f"expected shapes of the face model ({len(names)} shapes, e.g. {list(names[:3])}), "
                             f"found {len(missing)} it lacks, e.g. {missing[:3]}")
        out = np.zeros((len(self.weights), len(names)), np.float32)
        out[:, [index[n] for n in self.expression_names]] = self.weights
        return out

    def rigid(self) -> np.ndarray:
        """(F, 4, 4) float64 model-to-world transforms."""
        out = np.tile(np.eye(4), (len(self.rotation), 1, 1))
        out[:, :3, :3] = self.rotation
        out[:, :3, 3] = self.translation
        return out
