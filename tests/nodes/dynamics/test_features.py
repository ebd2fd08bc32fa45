"""Features of secondary dynamics (nodes/dynamics/features.py) and the feature nodes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from nodegraph import MeshSequence, RigidSequence, run_node
from nodes.dynamics.descriptors import QuasistaticTarget, SkinDescriptor, SkullDescriptor, SurfaceStretch
from nodes.dynamics.features import (moving_average_target, select_samples, skin_descriptor,
                                     skull_descriptor, skull_landmarks, stretch_stencil,
                                     surface_stretch, window_weights)
from nodes.geometry.rigid import rigid_matrix
from nodes.synth.dynamics import simulate_dynamics
from nodes.synth.head_motion import euler_xyz_to_rotmat

from ._data import face_model


@pytest.fixture(scope="module")
def capture():
    return simulate_dynamics(face_model(), motions=["walk", "oscillate@9"], expressions=["smile"],
                             segment_frames=50, fps=110.0, seed=5)


def _moved(data, g: np.ndarray):
    """The whole capture under one constant rigid transform g (world -> g world)."""
    x = np.einsum("ij,fvj->fvi", g[:3, :3], data.capture.vertices.astype(np.float64)) + g[:3, 3]
    return x.astype(np.float64), g @ data.skull.matrices


def test_descriptor_shapes(capture):
    rest = capture.neutral.vertices[0]
    ids = select_samples(rest, 30)
    b = skull_descriptor(capture.skull.matrices, skull_landmarks(rest), 110.0, feature_fps=120.0)
    x = skin_descriptor(capture.capture.vertices[:, ids], capture.skull.matrices, 110.0, feature_fps=120.0)
    s = surface_stretch(capture.quasistatic.vertices, rest, stretch_stencil(rest, ids))
    assert b.shape == (100, 5 * 21 * 3) and b.dtype == np.float32
    assert x.shape == (100, 30, 21 * 3) and s.shape == (100, 30, 2)
    assert len(ids) == 30 and len(np.unique(ids)) == 30


def test_features_invariant_to_a_constant_rigid_transform(capture):
    g = rigid_matrix(euler_xyz_to_rotmat(np.array([0.4, -1.1, 0.3])), np.array([12.0, -30.0, 55.0]))
    x2, skull2 = _moved(capture, g)
    rest = capture.neutral.vertices[0]
    ids = select_samples(rest, 30)
    lm = skull_landmarks(rest)
    np.testing.assert_allclose(skull_descriptor(skull2, lm, 110.0), skull_descriptor(capture.skull.matrices, lm, 110.0),
                               atol=2e-3)
    a = skin_descriptor(x2[:, ids], skull2, 110.0, feature_fps=120.0)
    b = skin_descriptor(capture.capture.vertices[:, ids], capture.skull.matrices, 110.0, feature_fps=120.0)
    np.testing.assert_allclose(a, b, atol=2e-3 * 110)  # float32 positions: ~1e-5 cm per frame
    stencil = stretch_stencil(rest, ids)
    np.testing.assert_allclose(surface_stretch(x2, rest, stencil),
                               surface_stretch(capture.capture.vertices, rest, stencil), atol=1e-4)
    y2 = moving_average_target(x2[:, ids], skull2)
    y = moving_average_target(capture.capture.vertices[:, ids], capture.skull.matrices)
    np.testing.assert_allclose(np.einsum("ij,fvj->fvi", g[:3, :3], y) + g[:3, 3], y2, atol=1e-4)


def test_moving_average_target_equals_direct_computation(capture):
    x = capture.capture.vertices[:, :7].astype(np.float64)
    skull = capture.skull.matrices
    w, f = 10, len(x)
    expected = np.empty_like(x)
    for t in range(f):  # eq. 5 with end frames repeated, one frame at a time
        acc = np.zeros((7, 3))
        for k in range(t - w, t + w + 1):
            kk = min(max(k, 0), f - 1)
            inv = np.linalg.inv(skull[kk])
            acc += x[kk] @ inv[:3, :3].T + inv[:3, 3]
        acc /= 2 * w + 1
        expected[t] = acc @ skull[t][:3, :3].T + skull[t][:3, 3]
    np.testing.assert_allclose(moving_average_target(x, skull, window=w), expected, atol=1e-9)


def test_window_at_the_native_rate_is_the_papers_feature(capture):
    skull, x = capture.skull.matrices, capture.capture.vertices[:, :3].astype(np.float64)
    got = skin_descriptor(x, skull, 110.0, window=10).reshape(100, 3, 21, 3)
    t = 50
    for k in range(-10, 11):  # eq. 4 directly
        a, b = np.linalg.inv(skull[t + k]), np.linalg.inv(skull[t + k - 1])
        vel = ((x[t + k] @ a[:3, :3].T + a[:3, 3]) - (x[t + k - 1] @ b[:3, :3].T + b[:3, 3])) * 110.0
        np.testing.assert_allclose(got[t, :, k + 10], vel, rtol=1e-4, atol=1e-3)
    lm = skull_landmarks(capture.neutral.vertices[0])
    b_feat = skull_descriptor(skull, lm, 110.0).reshape(100, 5, 21, 3)
    step = np.linalg.inv(skull[t]) @ skull[t - 1]  # eq. 2 directly
    np.testing.assert_allclose(b_feat[t, :, 10], (lm - (lm @ step[:3, :3].T + step[:3, 3])) * 110.0,
                               rtol=1e-4, atol=1e-3)
    offsets, weights = window_weights(10, 96.0, 120.0)
    np.testing.assert_allclose(weights.sum(1), 1.0)
    ramp = np.arange(-30, 31, dtype=np.float64)  # Catmull-Rom is exact on linear signals
    value = (ramp[30 + offsets] * weights).sum(1)
    np.testing.assert_allclose(value, np.arange(-10, 11) * 96.0 / 120.0, atol=1e-12)


def test_stretch_is_zero_on_the_neutral_and_positive_when_stretched(capture):
    rest = capture.neutral.vertices[0].astype(np.float64)
    ids = select_samples(rest, 20)
    stencil = stretch_stencil(rest, ids)
    assert np.abs(surface_stretch(rest[None], rest, stencil)).max() < 1e-6
    scaled = rest * np.array([1.1, 1.0, 1.0])  # 10 % wider: u (skull x) stretches
    s = surface_stretch(scaled[None], rest, stencil)[0]
    assert (s[:, 0] > -1e-6).all() and s[:, 0].mean() > 0.02
    assert s[:, 0].mean() > 1.5 * np.abs(s[:, 1]).mean()


def _mesh(vertices, fps=110.0):
    return MeshSequence(vertices=np.ascontiguousarray(vertices, np.float32), fps=fps)


def test_feature_nodes_chunk_independent(capture, tmp_path):
    from nodegraph import Graph, runner

    np.savez(tmp_path / "cap.npz", vertices=capture.capture.vertices, fps=np.float64(110.0))
    np.savez(tmp_path / "skull.npz", rigid=capture.skull.matrices)
    results = []
    for chunk in (7, 40):
        g = Graph()
        g.add("io.LoadMeshSequence", "load", path=str(tmp_path / "cap.npz"))
        g.add("io.LoadRigidSequence", "skull", path=str(tmp_path / "skull.npz"))
        g.add("dynamics.QuasistaticTarget", "target")
        g.connect("load.mesh", "target.capture")
        g.connect("skull.rigid", "target.skull")
        res = runner.run(g, scheduler="sync", cache=False, chunk=chunk)
        assert res.exit_code == 0, res.summary()
        results.append(res.outputs["target"]["quasistatic"].vertices)
    np.testing.assert_array_equal(results[0], results[1])
    whole = moving_average_target(capture.capture.vertices, capture.skull.matrices)
    np.testing.assert_allclose(results[0], whole, atol=1e-4)


def test_feature_nodes_run(capture):
    rest = dataclasses.replace(capture.neutral, fps=110.0)
    out = run_node(SkullDescriptor, {}, skull=capture.skull, rest=rest)
    assert out["descriptor"].values.shape == (100, 315)
    out = run_node(SkinDescriptor, {"num_samples": 12, "feature_fps": 120.0}, capture=capture.capture,
                   skull=capture.skull, rest=rest)
    assert out["descriptor"].values.shape == (100, 12 * 63)
    out = run_node(SurfaceStretch, {"num_samples": 12}, mesh=capture.quasistatic, neutral=rest)
    assert out["stretch"].values.shape == (100, 24)
    out = run_node(QuasistaticTarget, {}, capture=capture.capture, skull=capture.skull)
    assert out["offsets"].vertices.shape == capture.capture.vertices.shape
