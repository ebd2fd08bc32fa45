"""temporal.MotionReport and its helpers on sequences with known Euler angles and roughness."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodegraph import ParamSequence, RigidSequence, run_node
from nodes.temporal.layout import MATRIX_NAMES, RIGID_NAMES
from nodes.temporal.report import MotionReport, rigid_curves, roughness


def _sequences(frames: int = 12):
    t = np.arange(frames, dtype=np.float64)
    euler = np.stack([178.0 + 0.5 * t, 2.0 * np.sin(t / 3.0), 0.1 * t ** 2], 1)  # x crosses 180 deg
    rot = Rotation.from_euler("xyz", euler, degrees=True)
    trans = np.stack([t, 0.5 * t, np.full(frames, 60.0)], 1)
    matrix = ParamSequence(np.concatenate([rot.as_matrix().reshape(frames, 9), trans], 1).astype(np.float32),
                           list(MATRIX_NAMES) + ["tx", "ty", "tz"])
    axis_angle = ParamSequence(np.concatenate([rot.as_rotvec(), trans], 1).astype(np.float32), list(RIGID_NAMES))
    return euler, trans, matrix, axis_angle


def test_rigid_curves_unwrap_and_agree_across_layouts():
    euler, trans, matrix, axis_angle = _sequences()
    for seq in (matrix, axis_angle):
        angles, t = rigid_curves(seq)
        unwrapped = angles - 360.0 * np.round((angles - euler) / 360.0)[:1]  # one global 360 deg offset at most
        np.testing.assert_allclose(unwrapped, euler, atol=1e-3)
        np.testing.assert_allclose(t, trans, atol=1e-4)
    values = matrix.values.copy()
    values[3] = np.nan
    angles, t = rigid_curves(ParamSequence(values, list(matrix.names)))
    assert np.isnan(angles[3]).all() and np.isnan(t[3]).all() and np.isfinite(angles[[2, 4]]).all()
    with pytest.raises(Exception, match="expected columns"):
        rigid_curves(ParamSequence(np.zeros((3, 2), np.float32), ["a", "b"]))


def test_roughness_of_a_ramp_and_a_parabola():
    t = np.arange(10, dtype=np.float64)
    np.testing.assert_allclose(roughness(np.stack([2 * t + 1, 0.5 * t ** 2], 1)), [0.0, 1.0], atol=1e-12)
    assert np.isnan(roughness(np.zeros((2, 3)))).all()


def test_motion_report_tables_errors_against_the_truth(tmp_path):
    euler, trans, matrix, _ = _sequences()
    noisy = matrix.values.copy()
    noisy[:, 9] += np.where(np.arange(len(noisy)) % 2, 0.2, -0.2)  # 0.2 cm zigzag in x
    failed = ParamSequence(np.eye(len(noisy), dtype=np.float32)[5:6].T, ["failed"])
    out = run_node(MotionReport, {"folder": str(tmp_path), "labels": ["exact", "zigzag"]},
                   series=[matrix, ParamSequence(noisy, list(matrix.names))], truth=matrix, failed=failed)
    rows = {row[0]: row for row in out["table"].rows}
    assert rows["exact"][3] == pytest.approx(0.0, abs=1e-3) and rows["exact"][4] == pytest.approx(0.0, abs=1e-4)
    assert rows["zigzag"][4] == pytest.approx(0.2, abs=1e-4)
    assert rows["zigzag"][2] == pytest.approx(rows["exact"][2] + 0.8 ** 2, rel=1e-3)  # second difference +-0.8 cm
    saved = json.loads((tmp_path / "motion.json").read_text())
    assert [r[0] for r in saved["rows"]] == ["exact", "zigzag"]
    assert (tmp_path / "motion.png").stat().st_size > 10_000
    with pytest.raises(Exception, match="labels"):
        run_node(MotionReport, {"folder": str(tmp_path), "labels": ["a", "a"]}, series=[matrix, matrix])
    with pytest.raises(Exception, match="truth"):
        run_node(MotionReport, {"folder": str(tmp_path), "labels": ["truth"]}, series=[matrix], truth=matrix)


def test_motion_report_truth_as_rigid_transforms(tmp_path):
    euler, trans, matrix, _ = _sequences()
    mats = np.tile(np.eye(4), (len(euler), 1, 1))
    mats[:, :3, :3] = Rotation.from_euler("xyz", euler, degrees=True).as_matrix()
    mats[:, :3, 3] = trans
    noisy = matrix.values.copy()
    noisy[:, 10] += 0.3  # 0.3 cm off in y
    series = [ParamSequence(noisy, list(matrix.names))]
    by_rigid = run_node(MotionReport, {"folder": str(tmp_path / "a")}, series=series, truth_rigid=RigidSequence(mats))
    by_params = run_node(MotionReport, {"folder": str(tmp_path / "b")}, series=series, truth=matrix)
    np.testing.assert_equal(by_rigid["table"].rows, by_params["table"].rows)  # NaN columns included
    assert by_rigid["table"].rows[0][4] == pytest.approx(0.3, abs=1e-4)
    with pytest.raises(Exception, match="one port"):
        run_node(MotionReport, {"folder": str(tmp_path)}, series=series, truth=matrix, truth_rigid=RigidSequence(mats))
    with pytest.raises(Exception, match="truth_rigid.*frames|frames"):
        run_node(MotionReport, {"folder": str(tmp_path)}, series=series, truth_rigid=RigidSequence(mats[:4]))


def test_motion_report_states_weights_and_projected_points(tmp_path):
    """Weights' roughness and deviation, the 68 points' roughness (px^2) and deviation (px), weights.png."""
    from nodegraph import Camera
    from nodes.io.face_model import load_face_model

    model = load_face_model(region="face", max_vertices=500)
    frames = 12
    t = np.arange(frames)
    rot = Rotation.from_euler("YXZ", np.stack([0.1 + 0 * t, 0 * t, 0 * t], 1)).as_matrix()
    rot = np.diag([1.0, -1.0, -1.0]) @ rot  # facing the camera
    trans = np.tile([0.0, 0.0, 60.0], (frames, 1))
    weights = np.zeros((frames, len(model.expression_names)))
    jaw = model.expression_names.index("jawOpen")
    weights[:, jaw] = 0.3 + 0.2 * np.sin(t / 2)
    names = list(MATRIX_NAMES) + ["tx", "ty", "tz"] + list(model.expression_names)
    smooth = ParamSequence(np.concatenate([rot.reshape(frames, 9), trans, weights], 1).astype(np.float32), names)
    zig = smooth.values.copy()
    zig[:, 12 + jaw] += 0.05 * (-1.0) ** t  # a jittering jaw
    rough = ParamSequence(zig, names)
    cam = Camera.from_fov(256, 256, 40.0)
    out = run_node(MotionReport, {"folder": str(tmp_path), "labels": ["raw", "smooth"]}, series=[rough, smooth],
                   model=model, camera=cam)
    rows = {r[0]: dict(zip(out["table"].columns, r)) for r in out["table"].rows}
    assert rows["smooth"]["weights_dev"] == pytest.approx(0.05 / len(model.expression_names), rel=1e-3)
    assert rows["raw"]["weights_dev"] == 0.0
    expected = np.mean(np.diff(np.sin(t / 2), 2) ** 2)  # the smooth jaw's roughness per unit amplitude^2
    assert rows["raw"]["rough_weights"] > 10 * rows["smooth"]["rough_weights"]
    assert rows["smooth"]["rough_weights"] == pytest.approx(0.04 * expected / len(model.expression_names), rel=1e-2)
    assert rows["raw"]["rough_lm_px2"] > 2 * rows["smooth"]["rough_lm_px2"] and rows["smooth"]["lm_dev_px"] > 0.01
    assert (tmp_path / "weights.png").stat().st_size > 10_000
    with pytest.raises(Exception, match="both 'model' and 'camera'"):
        run_node(MotionReport, {"folder": str(tmp_path)}, series=[smooth], model=model)
