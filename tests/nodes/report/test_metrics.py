"""Tests of nodes.report.metrics: stabilization errors and the report.StabilizationError node."""

import numpy as np
import pytest
from scipy.linalg import orthogonal_procrustes
from scipy.spatial.transform import Rotation

from nodegraph import MeshSequence, NodeError, RigidSequence, Table, run_node
from nodes.report.metrics import StabilizationError, stabilization_errors


def _rigid(rotvec, trans):
    out = np.tile(np.eye(4), (len(rotvec), 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    out[:, :3, 3] = trans
    return out


def _truth(num_frames=8, num_vertices=50, seed=0):
    rng = np.random.default_rng(seed)
    truth = _rigid(rng.normal(0, 0.3, (num_frames, 3)), rng.normal(0, 5, (num_frames, 3)))
    shape = rng.normal(0, 6, (1, num_vertices, 3))
    stab = shape + rng.normal(0, 0.3, (num_frames, num_vertices, 3))  # expressions, cm
    return truth, stab


def _reference(estimate, truth, stab):
    """Float64 loop re-implementation of the documented definitions."""
    num_frames, num_vertices = stab.shape[:2]
    est_stab = np.empty_like(stab)
    for f in range(num_frames):
        for v in range(num_vertices):
            world = truth[f] @ np.append(stab[f, v], 1.0)
            est_stab[f, v] = np.linalg.solve(estimate[f], world)[:3]
    src, dst = stab.reshape(-1, 3), est_stab.reshape(-1, 3)
    r_t, _ = orthogonal_procrustes(src - src.mean(0), dst - dst.mean(0))
    offset = np.eye(4)
    offset[:3, :3], offset[:3, 3] = r_t.T, dst.mean(0) - r_t.T @ src.mean(0)
    per_vertex = np.linalg.norm(
        np.einsum("ij,fvj->fvi", r_t, est_stab - offset[:3, 3]) - stab, axis=-1)
    centre = src.mean(0)
    rot_deg, trans_cm = [], []
    for f in range(num_frames):
        delta = np.linalg.inv(truth[f]) @ estimate[f] @ offset
        rot_deg.append(Rotation.from_matrix(delta[:3, :3]).magnitude() * 180 / np.pi)
        trans_cm.append(np.linalg.norm(delta[:3, :3] @ centre + delta[:3, 3] - centre))
    return per_vertex, np.array(rot_deg), np.array(trans_cm), offset


def test_stabilization_errors_match_float64_loop():
    rng = np.random.default_rng(1)
    truth, stab = _truth()
    estimate = truth @ _rigid(rng.normal(0, 0.02, (8, 3)), rng.normal(0, 0.2, (8, 3)))
    result = stabilization_errors(estimate, truth, stab)
    per_vertex, rot_deg, trans_cm, offset = _reference(estimate, truth, stab)
    assert result.per_vertex.shape == (8, 50)
    np.testing.assert_allclose(result.per_vertex, per_vertex, atol=1e-9)
    np.testing.assert_allclose(result.rotation_deg, rot_deg, atol=1e-7)
    np.testing.assert_allclose(result.translation_cm, trans_cm, atol=1e-9)
    np.testing.assert_allclose(result.offset, offset, atol=1e-9)


def test_stabilization_errors_ignore_a_global_skull_offset():
    truth, stab = _truth(seed=2)
    offset = _rigid(np.array([[0.3, -0.2, 0.5]]), np.array([[2.0, -3.0, 10.0]]))[0]
    estimate = truth @ np.linalg.inv(offset)  # another, equally valid skull frame
    result = stabilization_errors(estimate, truth, stab)
    np.testing.assert_allclose(result.offset, offset, atol=1e-9)
    assert result.per_vertex.max() < 1e-9
    assert result.rotation_deg.max() < 1e-6 and result.translation_cm.max() < 1e-9


def test_stabilization_errors_of_symmetric_rotations_about_the_centre():
    # frames alternate +/- theta about an axis through the centroid: the best offset is the
    # identity, every frame is off by theta, the centre does not move
    truth, stab = _truth(num_frames=2, seed=3)
    # points mirrored in z about the centre: z is a principal axis of the cloud, so the
    # offset that averages the two frames is exactly the identity
    centre = np.array([1.0, -2.0, 3.0])
    half = stab[0, :25] - stab[0, :25].mean(0)
    stab[:] = centre + np.concatenate([half, half * [1, 1, -1]])
    theta = np.deg2rad(2.0)
    axis = np.array([0.0, 0.0, 1.0])
    pert = []
    for sign in (1, -1):
        rot = Rotation.from_rotvec(sign * theta * axis).as_matrix()
        pert.append(_rigid(Rotation.from_matrix(rot).as_rotvec()[None],
                           (centre - rot @ centre)[None])[0])
    estimate = truth @ np.stack(pert)
    result = stabilization_errors(estimate, truth, stab)
    np.testing.assert_allclose(result.offset, np.eye(4), atol=1e-9)
    np.testing.assert_allclose(result.rotation_deg, [2.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(result.translation_cm, [0.0, 0.0], atol=1e-9)
    radius = np.linalg.norm((stab[0] - centre)[:, :2], axis=1)
    chord = radius * 2 * np.sin(theta / 2)
    np.testing.assert_allclose(result.per_vertex, np.stack([chord, chord]), atol=1e-9)


def test_stabilization_errors_of_opposite_translations():
    truth, stab = _truth(num_frames=2, seed=4)
    stab[1] = stab[0]  # same shape in both frames: the offset averages to the identity
    estimate = truth @ _rigid(np.zeros((2, 3)), np.array([[0.3, 0, 0], [-0.3, 0, 0]]))
    result = stabilization_errors(estimate, truth, stab)
    np.testing.assert_allclose(result.per_vertex, 0.3, atol=1e-9)
    np.testing.assert_allclose(result.translation_cm, 0.3, atol=1e-9)
    np.testing.assert_allclose(result.rotation_deg, 0.0, atol=1e-6)


def test_summary_statistics():
    rng = np.random.default_rng(5)
    truth, stab = _truth(seed=5)
    estimate = truth @ _rigid(rng.normal(0, 0.02, (8, 3)), rng.normal(0, 0.2, (8, 3)))
    result = stabilization_errors(estimate, truth, stab)
    summary = result.summary()
    flat = result.per_vertex.ravel()
    assert summary == pytest.approx({
        "median_cm": np.median(flat), "mean_cm": flat.mean(), "p95_cm": np.percentile(flat, 95),
        "rot_median_deg": np.median(result.rotation_deg), "rot_max_deg": result.rotation_deg.max(),
        "trans_median_cm": np.median(result.translation_cm),
        "trans_max_cm": result.translation_cm.max()})
    assert all(type(value) is float for value in summary.values())
    assert summary["median_cm"] <= summary["p95_cm"] <= flat.max()


@pytest.mark.parametrize("args, match", [
    ((np.zeros((3, 3, 3)), np.zeros((3, 4, 4)), np.zeros((3, 5, 3))),
     r"estimate: expected shape \(F, 4, 4\), found \(3, 3, 3\)"),
    ((np.zeros((3, 4, 4)), np.zeros((2, 4, 4)), np.zeros((3, 5, 3))),
     r"truth_rigid: expected 3 frames \(as estimate\), found 2"),
    ((np.zeros((3, 4, 4)), np.zeros((3, 4, 4)), np.zeros((4, 5, 3))),
     r"truth_stabilized: expected 3 frames \(as estimate\), found 4"),
    ((np.zeros((3, 4, 4)), np.zeros((3, 4, 4)), np.zeros((3, 5, 2))),
     r"truth_stabilized: expected shape \(F, V, 3\)"),
])
def test_stabilization_errors_reject_bad_shapes(args, match):
    with pytest.raises(ValueError, match=match):
        stabilization_errors(*args)


def _node_inputs(seed=6):
    rng = np.random.default_rng(seed)
    truth, stab = _truth(seed=seed)
    estimate = truth @ _rigid(rng.normal(0, 0.02, (8, 3)), rng.normal(0, 0.2, (8, 3)))
    mesh = MeshSequence(stab.astype(np.float32), groups={"front": np.arange(10, dtype=np.int32)})
    return dict(estimate=RigidSequence(estimate), truth_rigid=RigidSequence(truth), truth=mesh)


def test_stabilization_error_node_tabulates_one_row():
    inputs = _node_inputs()
    table = run_node(StabilizationError, {"label": "procrustes"}, **inputs)["table"]
    assert isinstance(table, Table)
    assert table.columns == ["label", "median_cm", "mean_cm", "p95_cm", "rot_median_deg",
                             "trans_median_cm"]
    summary = stabilization_errors(inputs["estimate"].matrices, inputs["truth_rigid"].matrices,
                                   inputs["truth"].vertices).summary()
    assert table.rows == [["procrustes"] + [pytest.approx(summary[c]) for c in table.columns[1:]]]
    assert "procrustes" in table.format()


def test_stabilization_error_node_measures_a_group():
    inputs = _node_inputs()
    table = run_node(StabilizationError, {"label": "x", "group": "front"}, **inputs)["table"]
    summary = stabilization_errors(inputs["estimate"].matrices, inputs["truth_rigid"].matrices,
                                   inputs["truth"].vertices[:, :10]).summary()
    assert table.column("median_cm") == [pytest.approx(summary["median_cm"])]


def test_stabilization_error_node_rejects_a_missing_group():
    with pytest.raises(NodeError, match=r"report.StabilizationError.*'group': expected a vertex "
                                        r"group 'nose' in 'truth', found groups \['front'\]"):
        run_node(StabilizationError, {"group": "nose"}, **_node_inputs())


def test_stabilization_error_node_rejects_mismatched_frames():
    inputs = _node_inputs()
    inputs["truth_rigid"] = RigidSequence(inputs["truth_rigid"].matrices[:5])
    with pytest.raises(NodeError, match=r"'truth_rigid'.*expected 8 frames, found 5"):
        run_node(StabilizationError, {}, **inputs)
