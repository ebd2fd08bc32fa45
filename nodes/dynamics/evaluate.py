"""Errors of dynamics removal and synthesis against a known truth."""

from __future__ import annotations

import numpy as np

from nodegraph import SEQUENCE, In, InputError, MeshSequence, Node, NodeParams, Out, Param, Table

from .removal import region_vertices

__all__ = ["rms_distance", "Evaluate"]


def rms_distance(a: np.ndarray, b: np.ndarray) -> float:
    """RMS over frames and vertices of the Euclidean distance between (F, V, 3) positions (cm)."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    return float(np.sqrt((d * d).sum(-1).mean()))


class Evaluate(Node):
    """RMS distance to the truth of a result and of the unprocessed input ("doing nothing")."""

    type_name = "dynamics.Evaluate"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        region: str = Param("", description="vertex group evaluated ('' = all vertices)")
        label: str = Param("result", description="name of the result row")

    result = In(MeshSequence, doc="e.g. the removal's quasistatic output (cm)")
    baseline = In(MeshSequence, doc="the input of the step (e.g. the dynamic capture)")
    truth = In(MeshSequence, doc="what the result should be (cm)")
    table = Out(Table, doc="rows: baseline and result RMS (mm), reduction (%)")

    def run(self, result: MeshSequence, baseline: MeshSequence, truth: MeshSequence) -> dict:
        for name, mesh in (("result", result), ("baseline", baseline)):
            if mesh.vertices.shape != truth.vertices.shape:
                raise InputError(name, f"expected shape {truth.vertices.shape} (as truth), found "
                                       f"{mesh.vertices.shape}")
        ids = region_vertices(truth, self.params.region)
        base = rms_distance(baseline.vertices[:, ids], truth.vertices[:, ids])
        res = rms_distance(result.vertices[:, ids], truth.vertices[:, ids])
        reduction = 100.0 * (1.0 - res / base) if base > 0 else 0.0
        table = Table(["row", "rms_mm", "reduction_pct"],
                      [["baseline", round(10 * base, 4), 0.0],
                       [self.params.label, round(10 * res, 4), round(reduction, 2)]])
        return {"table": table}
