"""The secondary-dynamics capture generator (nodes/synth/dynamics.py)."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import NodeError, run_node
from nodes.dynamics.features import dynamic_offsets, stabilize_points
from nodes.synth.dynamics import (DynamicPerformance, looseness_field, parse_program, simulate_dynamics,
                                  skull_motion)

from ._data import face_model


def _small(**kwargs):
    args = dict(motions=["still", "oscillate@9"], expressions=["neutral", "smile"], segment_frames=40,
                fps=100.0, seed=3)
    args.update(kwargs)
    return simulate_dynamics(face_model(), **args)


def test_simulate_dynamics_shapes_and_truth():
    out = _small()
    v = face_model().neutral.shape[0]
    assert out.capture.vertices.shape == (160, v, 3) and out.capture.vertices.dtype == np.float32
    assert out.quasistatic.vertices.shape == (160, v, 3) and out.skull.matrices.shape == (160, 4, 4)
    assert out.neutral.vertices.shape == (1, v, 3) and out.capture.fps == 100.0
    np.testing.assert_array_equal(out.segments.values[:, 0], np.repeat(np.arange(4), 40))
    # capture = quasistatic + T(t) u(t): the offsets recovered from the two sequences match
    offsets = dynamic_offsets(out.capture.vertices, out.quasistatic.vertices, out.skull.matrices)
    np.testing.assert_allclose(offsets, out.offsets, atol=2e-4)
    # held expression: the quasistatic sequence is rigid (constant in the skull frame)
    local = stabilize_points(out.quasistatic.vertices[:40], out.skull.matrices[:40])
    assert np.abs(local - local[0]).max() < 1e-3
    # stabilized: the (noise-free) capture in the true skull frame
    np.testing.assert_allclose(out.stabilized.vertices, stabilize_points(out.capture.vertices, out.skull.matrices),
                               atol=2e-4)
    noisy = _small(noise_cm=0.05)
    np.testing.assert_allclose(noisy.stabilized.vertices, out.stabilized.vertices, atol=1e-6)


def test_simulate_dynamics_jiggle_where_loose_and_with_fast_motion():
    out = _small()
    mag = np.linalg.norm(out.offsets, axis=-1)  # (F, V) cm
    still, osc = mag[:40], mag[40:80]
    assert np.sqrt((still ** 2).mean()) < 0.1 * np.sqrt((osc ** 2).mean())
    loose = looseness_field(out.neutral.vertices[0])
    rms = np.sqrt((osc ** 2).mean(axis=0))
    assert rms[loose > 0.8].mean() > 1.5 * rms[loose < 0.2].mean()
    assert 0.05 < np.sqrt((osc ** 2).mean()) < 1.0  # millimetres, not centimetres


def test_simulate_dynamics_is_deterministic_and_seeded():
    a, b = _small(), _small()
    np.testing.assert_array_equal(a.capture.vertices, b.capture.vertices)
    c = _small(seed=4)
    assert not np.array_equal(a.neutral.vertices, c.neutral.vertices)


def test_stretch_stiffens_the_skin():
    soft = _small(expressions=["jaw_open"], stretch_stiffening=0.0)
    stiff = _small(expressions=["jaw_open"], stretch_stiffening=8.0)
    assert np.abs(stiff.offsets).mean() < np.abs(soft.offsets).mean()


def test_skull_motion_programs():
    t = np.arange(0, 2, 0.01)
    for program in ("still", "walk", "run", "jump", "oscillate@7.5"):
        ang, trans = skull_motion(program, t, np.random.default_rng(0))
        assert ang.shape == trans.shape == (len(t), 3) and np.isfinite(trans).all()
    _, trans = skull_motion("oscillate@10", t, np.random.default_rng(0))
    spectrum = np.abs(np.fft.rfft(trans[:, 1]))
    assert np.fft.rfftfreq(len(t), 0.01)[np.argmax(spectrum)] == pytest.approx(10.0, abs=0.5)
    assert parse_program("oscillate@6") == ("oscillate", 6.0)
    with pytest.raises(ValueError, match="oscillate@HZ"):
        parse_program("oscillate")
    with pytest.raises(ValueError, match="expected one of"):
        parse_program("swim")


def test_dynamic_performance_node_and_param_errors():
    out = run_node(DynamicPerformance, {"motions": ["walk"], "expressions": ["speech"],
                                        "segment_frames": 30, "fps": 96.0}, model=face_model())
    assert out["capture"].num_frames == 30 and out["neutral"].num_frames == 1
    with pytest.raises(NodeError, match="unknown expression"):
        DynamicPerformance({"expressions": ["grin"]})
    with pytest.raises(NodeError, match="oscillate@HZ"):
        DynamicPerformance({"motions": ["oscillate"]})
