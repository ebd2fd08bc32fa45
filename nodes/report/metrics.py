"""Stabilization error against ground truth: per-vertex, rotation and translation errors.

A stabilization estimate is a sequence of skull-to-world transforms `M_f`. Its skull frame
may differ from the true one by a global rigid offset (any reference frame is as good as
another), so the offset is solved first and the errors are measured after removing it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from nodegraph import (SEQUENCE, In, InputError, MeshSequence, Node, NodeParams, Out, Param,
                       RigidSequence, Table)

from ..geometry.rigid import apply_rigid, fit_rigid, invert_rigid, rotation_angle

__all__ = ["StabilizationErrors", "stabilization_errors", "StabilizationError"]


class StabilizationErrors(NamedTuple):
    """Errors of a stabilization against ground truth (see `stabilization_errors`).

    Attributes:
        per_vertex: (F, V) float64, cm: `|G^-1 E_fv - S_fv|`.
        rotation_deg: (F,) float64, degrees: angle of `truth_f^-1 estimate_f G`.
        translation_cm: (F,) float64, cm: how far `estimate_f G` moves the centroid `c` of the
            true stabilized mesh from where `truth_f` puts it.
        offset: (4, 4) float64, the global skull-frame offset `G` (true skull -> estimated
            skull frame).
    """

    per_vertex: np.ndarray
    rotation_deg: np.ndarray
    translation_cm: np.ndarray
    offset: np.ndarray

    def summary(self) -> dict[str, float]:
        """Return median, mean, p95 of the per-vertex error (cm) and median/max of the
        per-frame rotation (deg) and translation (cm) errors, as plain floats."""
        pv = self.per_vertex.reshape(-1)
        return {
            "median_cm": float(np.median(pv)),
            "mean_cm": float(np.mean(pv)),
            "p95_cm": float(np.percentile(pv, 95)),
            "rot_median_deg": float(np.median(self.rotation_deg)),
            "rot_max_deg": float(np.max(self.rotation_deg)),
            "trans_median_cm": float(np.median(self.translation_cm)),
            "trans_max_cm": float(np.max(self.translation_cm)),
        }


def _check_rigid(name: str, value: np.ndarray) -> np.ndarray:
    value = np.asarray(value, np.float64)
    if value.ndim != 3 or value.shape[1:] != (4, 4):
        raise ValueError(f"{name}: expected shape (F, 4, 4), found {value.shape}")
    return value


def stabilization_errors(estimate: np.ndarray, truth_rigid: np.ndarray,
                         truth_stabilized: np.ndarray) -> StabilizationErrors:
    """Measure a stabilization against ground truth, up to one global skull-frame offset.

    With the noise-free world mesh `W_f = truth_f S_f`, the estimated stabilization of it is
    `E_f = estimate_f^-1 W_f`. The estimated skull frame may differ from the true one by a
    rigid offset `G` (true skull -> estimated skull), `E_f ~ G S_f`; `G` is the Kabsch fit
    over all frames and vertices at once. Then:

    - per-vertex error: `|G^-1 E_fv - S_fv|` (cm), what is left of the head motion in the
      stabilized mesh;
    - rotation error of frame f: the angle of `D_f = truth_f^-1 estimate_f G` (deg), which is
      the identity for a perfect estimate (`estimate_f = truth_f G^-1`);
    - translation error of frame f: `|D_f c - c|` (cm) with `c` the centroid of `S` over all
      frames and vertices, i.e. the displacement of the head centre. (The translation part of
      `D_f` alone would depend on where the skull origin lies.)

    Args:
        estimate: (F, 4, 4) estimated skull-to-world transforms.
        truth_rigid: (F, 4, 4) true skull-to-world transforms.
        truth_stabilized: (F, V, 3) noise-free true skull-frame mesh, cm.
    Returns:
        StabilizationErrors.
    Raises:
        ValueError: on shapes that disagree, naming the argument.
    """
    estimate = _check_rigid("estimate", estimate)
    truth_rigid = _check_rigid("truth_rigid", truth_rigid)
    stab = np.asarray(truth_stabilized, np.float64)
    if stab.ndim != 3 or stab.shape[2] != 3 or stab.shape[1] == 0:
        raise ValueError(f"truth_stabilized: expected shape (F, V, 3) with V > 0, found "
                         f"{stab.shape}")
    num_frames = estimate.shape[0]
    for name, value in (("truth_rigid", truth_rigid), ("truth_stabilized", stab)):
        if value.shape[0] != num_frames:
            raise ValueError(f"{name}: expected {num_frames} frames (as estimate), found "
                             f"{value.shape[0]}")
    if num_frames == 0:
        raise ValueError("estimate: expected at least one frame, found 0")
    relative = invert_rigid(estimate) @ truth_rigid          # E_f = relative_f S_f
    estimated = apply_rigid(relative, stab)                  # (F, V, 3)
    offset = fit_rigid(stab.reshape(-1, 3), estimated.reshape(-1, 3)).matrix()
    per_vertex = np.linalg.norm(apply_rigid(invert_rigid(offset), estimated) - stab, axis=-1)
    delta = invert_rigid(truth_rigid) @ estimate @ offset    # D_f, identity when perfect
    centre = stab.reshape(-1, 3).mean(0)
    translation = np.linalg.norm(apply_rigid(delta, centre[None])[:, 0] - centre, axis=-1)
    return StabilizationErrors(per_vertex, np.rad2deg(rotation_angle(delta[:, :3, :3])),
                               translation, offset)


_COLUMNS = ("label", "median_cm", "mean_cm", "p95_cm", "rot_median_deg", "trans_median_cm")


class StabilizationError(Node):
    """Tabulate a stabilization's errors against ground truth (one row, see
    `stabilization_errors`)."""

    type_name = "report.StabilizationError"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        label: str = Param("", description="Row label (e.g. the method's name).")
        group: str = Param("", description="Vertex group of 'truth' measured (and used to solve "
                                           "the global offset); \"\" = all vertices.")

    estimate = In(RigidSequence, doc="Estimated skull-to-world transforms.")
    truth_rigid = In(RigidSequence, doc="True skull-to-world transforms.")
    truth = In(MeshSequence, doc="True (noise-free) stabilized mesh, skull frame, cm.")
    table = Out(Table, doc="One row: label, median_cm, mean_cm, p95_cm, rot_median_deg, "
                           "trans_median_cm.")

    def run(self, estimate: RigidSequence, truth_rigid: RigidSequence,
            truth: MeshSequence) -> dict:
        group = self.params.group
        vertices = truth.vertices
        if group:
            if group not in truth.groups:
                raise InputError("group", f"expected a vertex group '{group}' in 'truth', found "
                                          f"groups {sorted(truth.groups)}")
            vertices = vertices[:, truth.groups[group]]
            if vertices.shape[1] == 0:
                raise InputError("group", f"expected a non-empty vertex group '{group}', found 0 "
                                          f"vertices")
        if len(self.frames) == 0:
            raise InputError("estimate", "expected at least one frame, found 0")
        summary = stabilization_errors(estimate.matrices, truth_rigid.matrices, vertices).summary()
        row = [self.params.label] + [summary[name] for name in _COLUMNS[1:]]
        return {"table": Table(columns=list(_COLUMNS), rows=[row])}
