"""A network applied to inputs it never saw vary: columns constant over its training rows are read
as their training value (issue 30, a silent wrong answer: `dynamics_train.json --frames 100:400`,
frames of one held expression, gave a synthesis network that put 158 cm offsets on a smile in
`dynamics_retarget.json`)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from nodegraph import run_node  # noqa: E402
from nodes.dynamics.evaluate import rms_distance  # noqa: E402
from nodes.dynamics.networks import STD_FLOOR, standardize_inputs, standardize_stats  # noqa: E402
from nodes.dynamics.synthesis import SynthesizeDynamics, TrainSynthesis  # noqa: E402
from nodes.synth.dynamics import simulate_dynamics  # noqa: E402

from ._data import face_model  # noqa: E402


def test_a_column_constant_in_training_does_not_move_the_input():
    train = np.array([[1.0, 5.0], [3.0, 5.0], [2.0, 5.0]], np.float32)
    mean, std = standardize_stats(train)
    assert std[1] == np.float32(STD_FLOOR)
    z = standardize_inputs(np.array([[2.0, 6.0]], np.float32), mean, std)
    np.testing.assert_array_equal(z, [[0.0, 0.0]])  # without the rule: 1e6 in the second column


def test_synthesis_trained_on_one_held_expression_stays_near_the_quasistatic_face_on_another():
    face = face_model()
    train = simulate_dynamics(face, motions=["walk", "oscillate@8"], expressions=["neutral"], segment_frames=120,
                              fps=120.0, seed=1)
    model = run_node(TrainSynthesis, {"num_samples": 60, "epochs": 4, "seed": 0},
                     frames=range(train.capture.num_frames), captures=[train.capture],
                     quasistatic=[train.quasistatic], skulls=[train.skull], neutral=[train.neutral],
                     segments=[train.segments])["model"]
    constant = int((model.normalization["input_std"] <= np.float32(STD_FLOOR)).sum())
    assert constant > 0  # the stretch of a held neutral: columns the smile below moves
    test = simulate_dynamics(face, motions=["oscillate@9"], expressions=["smile"], segment_frames=120,
                             fps=120.0, seed=2)
    out = run_node(SynthesizeDynamics, {}, quasistatic=test.quasistatic, skull=test.skull, neutral=test.neutral,
                   model=model)
    # the truth's dynamic offsets are mm; an untrained direction must not add more than they are
    # (before: offsets of metres). Bound: the quasistatic face's own distance to the truth, x 2.
    baseline = rms_distance(test.quasistatic.vertices, test.capture.vertices)
    synthesized = rms_distance(out["capture"].vertices, test.capture.vertices)
    print(f"{constant} constant columns; RMS to the truth: quasistatic {10 * baseline:.3f} mm, "
          f"synthesized {10 * synthesized:.3f} mm")
    assert synthesized < 2.0 * baseline, (baseline, synthesized)
