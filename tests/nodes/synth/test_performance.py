"""Tests of nodes/synth/performance.py: truth consistency, artefacts, chunking, the node."""

from __future__ import annotations

import time

import numpy as np
import pytest

from nodegraph import FaceModel, MeshSequence, NodeError, ParamSequence, RigidSequence, run_node
from nodes.io.face_model import load_face_model, restrict_face_model
from nodes.synth.performance import Performance, generate_performance, upper_face_weights

FRAMES = 90


@pytest.fixture(scope="module")
def face() -> FaceModel:
    return load_face_model(region="face")


@pytest.fixture(scope="module")
def small() -> FaceModel:
    return load_face_model(region="face", max_vertices=400)


def _apply(matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Independent float64 reference of M_f @ x."""
    return (np.einsum("fij,fvj->fvi", matrices[:, :3, :3], points.astype(np.float64))
            + matrices[:, None, :3, 3])


def test_generate_performance_capture_is_rigid_times_truth_plus_noise(face):
    perf = generate_performance(face, num_frames=FRAMES, seed=1, noise_cm=0.05)
    assert perf.capture.vertices.shape == (FRAMES, 9409, 3) and perf.capture.vertices.dtype == np.float32
    residual = perf.capture.vertices - _apply(perf.rigid.matrices, perf.stabilized.vertices)
    assert abs(residual.std() / 0.05 - 1.0) < 0.1
    assert abs(residual.mean()) < 1e-3
    # the truth stabilized mesh is the model evaluated at the truth weights (plus an identity)
    shape = perf.stabilized.vertices - face.evaluate(perf.expressions.values)
    np.testing.assert_allclose(shape, np.broadcast_to(shape[:1], shape.shape), atol=2e-4)


def test_generate_performance_static_noise_free_capture_equals_truth(small):
    for kwargs in ({"motion": "none"}, {"rotation_deg": 0.0, "translation_cm": 0.0}):
        perf = generate_performance(small, num_frames=40, seed=2, **kwargs)
        np.testing.assert_array_equal(perf.capture.vertices, perf.stabilized.vertices)
        np.testing.assert_array_equal(perf.rigid.matrices, np.tile(np.eye(4), (40, 1, 1)))


def test_generate_performance_rest_fraction(small):
    perf = generate_performance(small, num_frames=600, seed=3, rest_fraction=0.85)
    assert ((perf.expressions.values < 0.05).mean(axis=0) >= 0.85).all()
    assert perf.expressions.names == small.expression_names


def test_generate_performance_seeded(small):
    a = generate_performance(small, num_frames=30, seed=4, noise_cm=0.01)
    b = generate_performance(small, num_frames=30, seed=4, noise_cm=0.01)
    c = generate_performance(small, num_frames=30, seed=5, noise_cm=0.01)
    np.testing.assert_array_equal(a.capture.vertices, b.capture.vertices)
    np.testing.assert_array_equal(a.rigid.matrices, b.rigid.matrices)
    assert not np.array_equal(a.capture.vertices, c.capture.vertices)
    assert not np.array_equal(a.stabilized.vertices, c.stabilized.vertices)  # identity differs


def test_generate_performance_chunk_equals_slice_of_whole(face):
    kwargs = dict(num_frames=FRAMES, seed=6, noise_cm=0.02, sliding_cm=0.5, outlier_fraction=0.01,
                  motion="walk")
    whole = generate_performance(face, **kwargs)
    for a, b in ((0, 1), (17, 53), (53, FRAMES)):
        part = generate_performance(face, frames=range(a, b), **kwargs)
        for name in ("capture", "stabilized"):
            np.testing.assert_array_equal(getattr(part, name).vertices,
                                          getattr(whole, name).vertices[a:b])
        np.testing.assert_array_equal(part.rigid.matrices, whole.rigid.matrices[a:b])
        np.testing.assert_array_equal(part.expressions.values, whole.expressions.values[a:b])


def test_generate_performance_blinks_present(small):
    perf = generate_performance(small, num_frames=450, seed=7, rest_fraction=0.5)
    names = perf.expressions.names
    blink = perf.expressions.values[:, [names.index("eyeBlink_L"), names.index("eyeBlink_R")]]
    closed = blink > 0.5
    assert closed[:, 0].sum() >= 2
    np.testing.assert_array_equal(closed[:, 0], closed[:, 1])


def test_generate_performance_sliding_moves_only_upper_face(face):
    keep = np.union1d(np.arange(0, len(face.neutral), 7), face.landmarks)  # keeps all 68 landmarks
    face = restrict_face_model(face, keep)
    assert len(face.landmarks) == 68
    kwargs = dict(num_frames=900, seed=0, rest_fraction=0.3, motion="none", identity_scale=0.0)
    plain = generate_performance(face, **kwargs)
    slid = generate_performance(face, sliding_cm=0.4, **kwargs)
    np.testing.assert_array_equal(slid.stabilized.vertices, plain.stabilized.vertices)
    offset = np.linalg.norm(slid.capture.vertices - plain.capture.vertices, axis=2)  # (F, V)
    moved = offset.max(axis=0) > 1e-4
    brow_y = face.neutral[face.landmarks[17:27], 1].min()
    assert moved.sum() > 100
    assert (face.neutral[moved, 1] > brow_y - 1e-3).all()  # above the brows only
    assert offset.max() <= 0.4 * (1 + 1e-4)
    assert offset.max() > 0.2  # brows were raised strongly at some point
    weights = upper_face_weights(face.neutral, face.landmarks)
    np.testing.assert_array_equal(moved, weights > 0)


def test_generate_performance_outliers(small):
    perf = generate_performance(small, num_frames=200, seed=9, outlier_fraction=0.02,
                                outlier_cm=1.5, motion="turn")
    size = np.linalg.norm(perf.capture.vertices - _apply(perf.rigid.matrices, perf.stabilized.vertices),
                          axis=2)
    hits = size > 1e-3
    n = hits.size
    assert abs(hits.mean() - 0.02) < 4 * np.sqrt(0.02 * 0.98 / n)
    assert size[hits].min() >= 1.5 - 1e-3 and size[hits].max() <= 4.5 + 1e-3


def test_generate_performance_errors(small):
    with pytest.raises(ValueError, match=r"frames: expected a sub-range of range\(0, 10\)"):
        generate_performance(small, num_frames=10, seed=0, frames=range(5, 12))
    with pytest.raises(ValueError, match="motion: expected one of"):
        generate_performance(small, num_frames=10, seed=0, motion="jump")
    with pytest.raises(ValueError, match="outlier_fraction"):
        generate_performance(small, num_frames=10, seed=0, outlier_fraction=2.0)


def test_generate_performance_full_head_600_frames_runs_in_seconds():
    model = load_face_model()
    start = time.perf_counter()
    perf = generate_performance(model, num_frames=600, seed=0, noise_cm=0.02)
    elapsed = time.perf_counter() - start
    print(f"600 frames x {model.neutral.shape[0]} vertices: {elapsed:.2f} s")
    assert perf.capture.vertices.shape == (600, 26719, 3)


def test_performance_node_outputs_and_chunk(small):
    params = {"num_frames": 60, "seed": 3, "noise_cm": 0.01, "motion": "nod"}
    node = Performance(params)
    assert node.frame_count() == 60
    out = run_node(Performance, params, model=small)
    assert isinstance(out["capture"], MeshSequence) and out["capture"].num_frames == 60
    assert isinstance(out["rigid"], RigidSequence) and isinstance(out["expressions"], ParamSequence)
    for port in ("capture", "stabilized"):
        mesh = out[port]
        assert mesh.groups.keys() == small.groups.keys() and mesh.fps == 30.0
        np.testing.assert_array_equal(mesh.faces, small.faces)
    part = run_node(Performance, params, frames=range(20, 35), model=small)
    np.testing.assert_array_equal(part["capture"].vertices, out["capture"].vertices[20:35])


def test_performance_node_carries_faces_and_uv(face):
    out = run_node(Performance, {"num_frames": 2, "fps": 24.0}, model=face)
    mesh = out["capture"]
    assert mesh.fps == 24.0 and mesh.uv is face.uv
    np.testing.assert_array_equal(mesh.uv_faces, face.uv_faces)


def test_performance_node_errors_name_param(small):
    with pytest.raises(NodeError, match=r"synth.Performance.*'motion'.*found 'jump'"):
        run_node(Performance, {"num_frames": 5, "motion": "jump"}, model=small)
    with pytest.raises(NodeError, match=r"'pivot_cm'.*3 numbers"):
        run_node(Performance, {"num_frames": 5, "pivot_cm": [1.0, 2.0]}, model=small)
    with pytest.raises(NodeError, match=r"'num_frames'.*frames 0:8"):
        run_node(Performance, {"num_frames": 5}, frames=range(0, 8), model=small)
    with pytest.raises(NodeError, match="noise_cm"):
        Performance({"noise_cm": -1.0})
