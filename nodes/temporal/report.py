"""Rigid parameters over time, several versions of one shot side by side (the paper's Figs. 15-17).

`rigid_curves` turns a fitted `ParamSequence` (either layout of `nodes.temporal.layout`) into
Euler angles (deg) and translations (cm) per frame; `roughness` is the mean squared second
difference of a curve (what temporal smoothing lowers); `temporal.MotionReport` plots the
curves of every connected sequence (raw fit, averaged, hybrid, ...), with the truth when it is
known, shades failed frames, and returns a table of roughness and error to the truth.

matplotlib is imported inside the functions that need it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import (SEQUENCE, Camera, FaceModel, Files, In, InputError, Node, NodeParams, Out, Param, ParamSequence,
                       RigidSequence, Table)
from nodegraph.files import files_value
from nodegraph.flags import flags_to_mask

from ..geometry.rotation import axis_angle_to_rotmat
from ..report.plots import plot_rigid_curves, rigid_to_euler_translation
from ..report.stabilization import write_table
from .layout import FIT_TRANSLATION_NAMES, MATRIX_NAMES, ROTATION_NAMES, TRANSLATION_NAMES

__all__ = ["rigid_curves", "matrix_curves", "roughness", "weight_columns", "projected_landmarks", "plot_weight_curves",
           "MotionReport"]

_AXES = ("x", "y", "z")


def rigid_curves(params: ParamSequence, where: str = "series") -> tuple[np.ndarray, np.ndarray]:
    """Head rotation and translation per frame.

    Args:
        params: (F, P) with r00..r22 + tx ty tz (`nodes.fit`) or rot_x..z (rad) + trans_x..z (cm).
        where: the port named in errors.
    Returns:
        angles (F, 3) degrees, extrinsic XYZ (`R = Rz Ry Rx`, scipy "xyz"), unwrapped over time;
        translation (F, 3) cm. Frames with non-finite values are NaN.
    Raises:
        InputError: the rigid columns are missing.
    """
    names = list(params.names)
    values = np.asarray(params.values, np.float64)
    if all(n in names for n in MATRIX_NAMES) and all(n in names for n in FIT_TRANSLATION_NAMES):
        rot = values[:, [names.index(n) for n in MATRIX_NAMES]].reshape(-1, 3, 3)
        trans = values[:, [names.index(n) for n in FIT_TRANSLATION_NAMES]]
    elif all(n in names for n in ROTATION_NAMES + TRANSLATION_NAMES):
        rot = values[:, [names.index(n) for n in ROTATION_NAMES]]
        trans = values[:, [names.index(n) for n in TRANSLATION_NAMES]]
    else:
        raise InputError(where, f"expected columns r00..r22 + tx ty tz or rot_x..z + trans_x..z, found "
                                f"{names[:12]}{' ...' if len(names) > 12 else ''}")
    good = np.isfinite(rot.reshape(len(rot), -1)).all(1) & np.isfinite(trans).all(1)
    matrices = np.full((len(values), 4, 4), np.nan)
    matrices[good] = np.eye(4)
    matrices[good, :3, :3] = rot[good] if rot.ndim == 3 else axis_angle_to_rotmat(rot[good])
    matrices[good, :3, 3] = trans[good]
    return matrix_curves(matrices)


def matrix_curves(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`rigid_curves` of (F, 4, 4) rigid transforms (frames with non-finite entries are NaN)."""
    matrices = np.asarray(matrices, np.float64)
    good = np.isfinite(matrices.reshape(len(matrices), -1)).all(1)
    angles = np.full((len(matrices), 3), np.nan)
    trans = np.full((len(matrices), 3), np.nan)
    if good.any():
        euler, trans[good] = rigid_to_euler_translation(matrices[good])
        angles[good] = np.degrees(np.unwrap(np.radians(euler), axis=0))
    return angles, trans


def roughness(curve: np.ndarray) -> np.ndarray:
    """Mean squared second difference per column over frames where three in a row are finite.

    Args:
        curve: (F, C) values per frame.
    Returns:
        (C,) mean of `(x[f+1] - 2 x[f] + x[f-1])^2`, in the curve's units squared; NaN when
        no three consecutive frames are finite.
    """
    curve = np.asarray(curve, np.float64)
    if len(curve) < 3:
        return np.full(curve.shape[1], np.nan)
    second = curve[2:] - 2.0 * curve[1:-1] + curve[:-2]
    ok = np.isfinite(second).all(1)
    return (second[ok] ** 2).mean(0) if ok.any() else np.full(curve.shape[1], np.nan)


COLUMNS = ("series", "rough_rot_deg2", "rough_trans_cm2", "rot_err_deg", "trans_err_cm", "rough_weights",
           "weights_dev", "rough_lm_px2", "lm_dev_px")
"""The table's columns: per series, roughness (mean squared second difference) of the Euler angles
(deg^2), the translation (cm^2) and the weights (mean over shapes); the median error to the truth
(deg, cm); the mean absolute deviation of the weights from the first series'; and, with a model
and a camera, the projected 68 points' roughness (px^2, mean over points of |second difference|^2)
and mean distance from the first series' points (px)."""

_POSE_NAMES = set(MATRIX_NAMES + FIT_TRANSLATION_NAMES + ROTATION_NAMES + TRANSLATION_NAMES)


def weight_columns(params: ParamSequence) -> list[int]:
    """Indices of the columns that are not the pose (the expression weights)."""
    return [i for i, n in enumerate(params.names) if n not in _POSE_NAMES]


def projected_landmarks(params: ParamSequence, model: FaceModel, camera: Camera) -> np.ndarray:
    """(F, 68, 2) pixels of the model's 68 landmark vertices posed by the fitted parameters (NaN where unsolved)."""
    from ..geometry.camera import project_points

    names = list(params.names)
    values = np.asarray(params.values, np.float64)
    index = {n: i for i, n in enumerate(model.expression_names)}
    weights = np.zeros((len(values), len(index)))
    for j in weight_columns(params):
        if names[j] in index:
            weights[:, index[names[j]]] = values[:, j]
    angles_ok = np.isfinite(values).all(1)
    if all(n in names for n in MATRIX_NAMES):
        rot = values[:, [names.index(n) for n in MATRIX_NAMES]].reshape(-1, 3, 3)
        trans = values[:, [names.index(n) for n in FIT_TRANSLATION_NAMES]]
    else:
        rot = np.tile(np.eye(3), (len(values), 1, 1))
        rot[angles_ok] = axis_angle_to_rotmat(values[angles_ok][:, [names.index(n) for n in ROTATION_NAMES]])
        trans = values[:, [names.index(n) for n in TRANSLATION_NAMES]]
    local = model.evaluate(np.nan_to_num(weights).astype(np.float32))[:, model.landmarks].astype(np.float64)
    world = np.einsum("fij,flj->fli", np.nan_to_num(rot), local) + np.nan_to_num(trans)[:, None]
    points = project_points(world, camera.world_to_camera, [camera.fx, camera.fy, camera.cx, camera.cy],
                            [camera.k1, camera.k2] if (camera.k1 or camera.k2) else None)
    points[~angles_ok] = np.nan
    return points


def plot_weight_curves(series: dict[str, np.ndarray], names: list[str], path: str | Path, *, count: int = 6,
                       first_frame: int = 0, shaded: np.ndarray | None = None) -> Path:
    """The `count` expression weights that move most in the first series, every series over time.

    Args:
        series: label -> (F, K) weights (the same K names in every series).
        names: the K shape names.
        path: PNG written.
    Returns:
        The written path.
    """
    from matplotlib.figure import Figure

    from ..report.plots import SERIES_COLOURS, save_figure

    first = next(iter(series.values()))
    spread = np.nan_to_num(np.nanstd(first, axis=0)) if len(first) else np.zeros(len(names))
    shown = np.argsort(-spread)[:count]
    fig = Figure(figsize=(12, 2.2 * max(len(shown), 1)))
    frames = np.arange(first_frame, first_frame + len(first))
    for row, k in enumerate(shown):
        ax = fig.add_subplot(max(len(shown), 1), 1, row + 1)
        if shaded is not None and shaded.any():
            for f in frames[shaded]:
                ax.axvspan(f - 0.5, f + 0.5, color="0.9", lw=0)
        for i, (label, weights) in enumerate(series.items()):
            ax.plot(frames, weights[:, k], color=SERIES_COLOURS[i % len(SERIES_COLOURS)], lw=1.2, label=label)
        ax.set_ylabel(names[k], fontsize=8)
        if row == 0:
            ax.legend(loc="upper right", fontsize=8)
    fig.axes[-1].set_xlabel("frame") if fig.axes else None
    fig.tight_layout()
    return save_figure(fig, path)


class MotionReport(Node):
    """Plot the head's motion and the most moving expression weights over time for several versions of a fit."""

    type_name = "temporal.MotionReport"
    version = 2
    kind = SEQUENCE
    writes_files = True
    preload = ("matplotlib.figure", "matplotlib.backends.backend_agg")

    class Params(NodeParams):
        folder: str = Param("motion_report", output_file=True, description="Output folder (created if missing): "
                            "motion.png (pose), weights.png (the six weights that move most), motion.md, "
                            "motion.json.")
        labels: list[str] = Param([], description="Names of the connected series, in connection order; "
                                  "missing ones are series_1, series_2, ...")

    series = In(ParamSequence, many=True, doc="Fitted parameter sequences to compare (e.g. raw, averaged, hybrid).")
    truth = In(ParamSequence, optional=True, doc="True parameters, when known (synthetic plates).")
    truth_rigid = In(RigidSequence, optional=True, doc="Or the truth as model-to-world transforms (e.g. the skull of "
                                                       "a synthetic performance, rendered by a camera in its world).")
    failed = In(ParamSequence, optional=True, doc="(F, 1+) flags: 1 in the 'failed' column (else the first) "
                "where the fit failed (shaded; see nodegraph.flags).")
    model = In(FaceModel, optional=True, doc="The fitted model: with `camera`, the projected 68 points' roughness "
               "and deviation.")
    camera = In(Camera, optional=True, doc="The plate's camera (with `model`).")
    files = Out(Files, doc="The files written.")
    table = Out(Table, doc="Per series (columns `COLUMNS`): roughness (mean squared second difference) of the "
                           "Euler angles (deg^2), translation (cm^2) and weights; median error to the truth "
                           "(deg, cm); the weights' deviation from the first series; with model and camera, "
                           "the projected 68 points' roughness (px^2) and deviation (px).")

    def run(self, series: list[ParamSequence], truth: ParamSequence | None,
            failed: ParamSequence | None, truth_rigid: RigidSequence | None = None,
            model: FaceModel | None = None, camera: Camera | None = None) -> dict:
        if not series:
            raise InputError("series", "connect at least one parameter sequence, found none")
        labels = list(self.params.labels) + [f"series_{i + 1}" for i in range(len(self.params.labels), len(series))]
        labels = labels[:len(series)]
        if len(set(labels)) < len(labels):
            raise InputError("labels", f"expected distinct names for the {len(series)} series, found {labels}")
        frames = series[0].num_frames
        for name, seq in zip(labels, series):
            if seq.num_frames != frames:
                raise InputError("series", f"expected {frames} frames in every series (as '{labels[0]}'), "
                                           f"'{name}' has {seq.num_frames}")
        if truth is not None and truth_rigid is not None:
            raise InputError("truth_rigid", "expected the truth on one port, found both 'truth' and 'truth_rigid' "
                                            "connected")
        if truth_rigid is not None and truth_rigid.num_frames != frames:
            raise InputError("truth_rigid", f"expected {frames} frames (as the series), found {truth_rigid.num_frames}")
        if (truth is not None or truth_rigid is not None) and "truth" in labels:
            raise InputError("labels", f"'truth' names the connected truth; expected other names, found {labels}")
        if truth is not None and truth.num_frames != frames:
            raise InputError("truth", f"expected {frames} frames (as the series), found {truth.num_frames}")
        mask = flags_to_mask(failed, frames)  # failed frames are shaded; NaN flags count as failed
        curves = {name: rigid_curves(seq, "series") for name, seq in zip(labels, series)}
        true_curves = rigid_curves(truth, "truth") if truth is not None else None
        if truth_rigid is not None:
            true_curves = matrix_curves(truth_rigid.matrices)
        weights = {}
        for name, seq in zip(labels, series):
            by_name = {seq.names[j]: seq.values[:, j].astype(np.float64) for j in weight_columns(seq)}
            weights[name] = by_name
        shape_names = [n for n in weights[labels[0]] if all(n in w for w in weights.values())]
        stacked = {name: np.stack([w[n] for n in shape_names], 1) if shape_names else np.zeros((frames, 0))
                   for name, w in weights.items()}
        if (model is None) != (camera is None):
            raise InputError("camera" if camera is None else "model", "expected both 'model' and 'camera' "
                             "connected (for the projected points), found one")
        points = {name: projected_landmarks(seq, model, camera) for name, seq in zip(labels, series)} \
            if model is not None else {}
        rows = []
        for name, (angles, trans) in curves.items():
            row = [name, float(np.nansum(roughness(angles))), float(np.nansum(roughness(trans)))]
            if true_curves is not None:
                rot_err = np.linalg.norm(angles - true_curves[0], axis=1)
                trans_err = np.linalg.norm(trans - true_curves[1], axis=1)
                row += [float(np.nanmedian(rot_err)), float(np.nanmedian(trans_err))]
            else:
                row += [float("nan"), float("nan")]
            w = stacked[name]
            row += [float(np.nanmean(roughness(w))) if w.shape[1] else float("nan"),
                    float(np.nanmean(np.abs(w - stacked[labels[0]]))) if w.shape[1] else float("nan")]
            if points:
                p = points[name]
                row += [float(np.nanmean(roughness(p.reshape(frames, -1)).reshape(-1, 2).sum(1))),
                        float(np.nanmean(np.linalg.norm(p - points[labels[0]], axis=2)))]
            else:
                row += [float("nan"), float("nan")]
            rows.append([row[0]] + [round(v, 6) for v in row[1:]])
        table = Table(list(COLUMNS), rows)
        folder = Path(self.params.folder)
        shown = ({"truth": true_curves} if true_curves is not None else {}) | curves
        png = plot_rigid_curves(shown, folder / "motion.png", first_frame=self.frames.start, shaded=mask,
                                dashed="truth" if true_curves is not None else None)
        self.progress(0.6, "motion plotted")
        paths = [str(png)]
        if shape_names:
            paths.append(str(plot_weight_curves(stacked, shape_names, folder / "weights.png",
                                                first_frame=self.frames.start, shaded=mask)))
            self.progress(0.8, "weights plotted")
        paths += [str(f) for f in write_table(folder, "motion", table, digits=6)]
        return {"files": files_value(paths), "table": table}
