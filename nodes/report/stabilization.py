"""A report comparing stabilizations: error table against ground truth, head-motion curves,
position histograms in world and skull frames."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nodegraph import SEQUENCE, Files, In, Index, InputError, MeshSequence, Node, NodeParams, Out, Param
from nodegraph import RigidSequence, Table
from nodegraph.files import files_value, write_text_atomic

from ..geometry.rigid import stabilize_vertices
from .metrics import StabilizationErrors, stabilization_errors
from .plots import default_vertices, plot_head_motion, plot_position_histograms

__all__ = ["error_table", "StabilizationReport"]

COLUMNS = ["method", "median_cm", "mean_cm", "p95_cm", "rot_median_deg", "rot_max_deg", "trans_median_cm"]


def error_table(errors: dict[str, StabilizationErrors]) -> Table:
    """One row of `StabilizationErrors.summary()` per method (errors in cm and degrees)."""
    rows = []
    for label, err in errors.items():
        summary = err.summary()
        rows.append([label] + [round(summary[c], 6) for c in COLUMNS[1:]])
    return Table(list(COLUMNS), rows)


def markdown_table(table: Table, digits: int = 4) -> str:
    """The table as markdown (floats with `digits` decimals)."""
    head = "| " + " | ".join(table.columns) + " |\n|" + "---|" * len(table.columns) + "\n"
    body = "".join("| " + " | ".join(f"{c:.{digits}f}" if isinstance(c, float) else str(c) for c in row) + " |\n"
                   for row in table.rows)
    return head + body


def write_table(folder: Path, stem: str, table: Table, digits: int = 4) -> list[Path]:
    """Write `stem.md` (`markdown_table`) and `stem.json` ({"columns", "rows"}) atomically; return both paths."""
    md, js = folder / f"{stem}.md", folder / f"{stem}.json"
    write_text_atomic(md, markdown_table(table, digits))
    write_text_atomic(js, json.dumps({"columns": table.columns, "rows": table.rows}, indent=1) + "\n")
    return [md, js]


class StabilizationReport(Node):
    """Write a folder comparing any number of stabilizations of a capture (with ground truth when given).

    Files: `head_motion.png` (truth and each estimate), `histograms.png` (vertex positions over
    time in world vs each estimate's skull frame), and with ground truth `errors.md` /
    `errors.json` (median / mean / p95 vertex error in cm after removing one global rigid
    offset, rotation error in degrees, head-centre translation error in cm).
    """

    type_name = "report.StabilizationReport"
    version = 3
    # v1 had four optional ports estimate_1..estimate_4; v2 has one list port, in edge order;
    # v3 draws each estimate's histogram in its own colour (v2: all black).
    port_renames = {1: {f"estimate_{i}": "estimates" for i in range(1, 5)}}
    kind = SEQUENCE
    writes_files = True
    preload = ("matplotlib.figure", "matplotlib.backends.backend_agg")

    class Params(NodeParams):
        folder: str = Param("out/report", output_file=True, description="Output folder (created).")
        labels: list[str] = Param([], description="Names of the estimates, in the order of their "
                                  "connections; missing names are estimate_1, estimate_2, ...")
        histogram_vertices: list[Index] = Param([], description="Vertices shown in histograms.png; empty = 4 "
                                              "evenly spaced vertices of the mesh.")

    capture = In(MeshSequence, doc="Captured mesh sequence, world, cm.")
    truth_rigid = In(RigidSequence, optional=True, doc="True skull-to-world transforms.")
    truth = In(MeshSequence, optional=True, doc="True noise-free skull-frame mesh, cm.")
    estimates = In(RigidSequence, many=True, optional=True,
                   doc="Stabilizations to compare (skull-to-world), in connection order.")
    files = Out(Files, doc="The files written.")
    table = Out(Table, doc="Error table (empty without ground truth).")

    def run(self, capture: MeshSequence, truth_rigid: RigidSequence | None, truth: MeshSequence | None,
            estimates: list[RigidSequence]) -> dict:
        labels = list(self.params.labels) + [f"estimate_{i + 1}" for i in range(len(self.params.labels),
                                                                                  len(estimates))]
        if len(set(labels[:len(estimates)])) < len(estimates):
            raise InputError("labels", f"expected distinct names for the {len(estimates)} estimates, "
                                       f"found {labels[:len(estimates)]}")
        given = {labels[i]: estimate.matrices for i, estimate in enumerate(estimates)}
        if not given and truth_rigid is None:
            raise InputError("estimates", "connect at least one estimate or truth_rigid, found none")
        if (truth is None) != (truth_rigid is None):
            raise InputError("truth" if truth is None else "truth_rigid",
                             "ground truth needs both truth_rigid and truth, found only one")
        if truth is not None and truth.vertices.shape != capture.vertices.shape:
            raise InputError("truth", f"expected vertices {capture.vertices.shape} like capture, "
                             f"found {truth.vertices.shape}")
        ids = self.params.histogram_vertices or None
        if ids is not None and max(ids) >= capture.num_vertices:
            raise InputError("histogram_vertices", f"vertex {max(ids)} outside 0..{capture.num_vertices - 1}")
        folder = Path(self.params.folder)
        written = []
        table = Table(list(COLUMNS), [])
        curves = dict(given)
        if truth is not None:
            errors = {label: stabilization_errors(m, truth_rigid.matrices, truth.vertices)
                      for label, m in given.items()}
            # Each estimate's skull frame differs from the truth's by one rigid offset G:
            # plot estimate @ G so that the curves are comparable.
            curves = {"truth": truth_rigid.matrices} | {
                f"{label} (aligned)": given[label] @ err.offset for label, err in errors.items()}
            if errors:
                table = error_table(errors)
                written += write_table(folder, "errors", table)
        self.progress(0.2, "errors measured")
        written.append(plot_head_motion(curves, folder / "head_motion.png", fps=capture.fps))
        self.progress(0.5, "head motion plotted")
        # Only the shown vertices are stabilized and histogrammed (not all F x V).
        shown = default_vertices(capture.num_vertices) if ids is None else np.asarray(ids, np.int64)
        world = capture.vertices[:, shown]
        skulls = {label: stabilize_vertices(world, m) for label, m in curves.items()}
        written.append(plot_position_histograms(world, skulls, folder / "histograms.png",
                                                vertex_labels=shown))
        paths = [str(p) for p in written]
        return {"files": files_value(paths), "table": table}
