"""dynamics.TrainSynthesis on a capture shorter than its feature window: a clear error naming the
port (`dynamics_train.json --frames 0:4` was exit 1, a numpy reshape error)."""

from __future__ import annotations

import pytest

pytest.importorskip("torch")

from nodegraph import InputError, NodeError, run_node  # noqa: E402
from nodes.dynamics.synthesis import TrainSynthesis  # noqa: E402
from nodes.synth.dynamics import simulate_dynamics  # noqa: E402

from ._data import face_model  # noqa: E402


def test_train_synthesis_on_four_frames_says_there_are_no_training_frames():
    data = simulate_dynamics(face_model(), motions=["walk"], expressions=["neutral"], segment_frames=4,
                             fps=120.0, seed=1)
    assert data.capture.num_frames == 4
    with pytest.raises((InputError, NodeError), match="captures.*away from segment changes and ends.*\\[4\\] frames"):
        run_node(TrainSynthesis, {"num_samples": 20, "epochs": 1}, frames=range(4), captures=[data.capture],
                 quasistatic=[data.quasistatic], skulls=[data.skull], neutral=[data.neutral],
                 segments=[data.segments])
