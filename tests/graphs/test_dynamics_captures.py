"""graphs/dynamics_remove.json on the capture a user has (a whole head, or the wrong topology)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import NodeError, runner
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import simulate_dynamics

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


def test_remove_graph_refuses_another_topology_once_before_anything_runs(tmp_path):
    test = simulate_dynamics(load_face_model(region="face", max_vertices=300), motions=["still"],
                             expressions=["neutral"], segment_frames=200, fps=120.0, seed=1)
    capture = tmp_path / "capture.npz"
    np.savez(capture, vertices=test.capture.vertices, faces=test.capture.faces, rigid=test.skull.matrices)
    with pytest.raises(NodeError) as err:
        runner.run(GRAPHS / "dynamics_remove.json", scheduler="sync", cache=False, chunk=32,
                   parameters={"capture": str(capture), "skull": str(capture), "model": "",
                               "output": str(tmp_path / "out.npz")})
    message = str(err.value)
    assert err.value.bad_input and message.count("expected") == 1, message
    assert "'remove'" in message and "9409 vertices" in message and "found 300 vertices" in message
    assert "mesh.SelectRegion" in message and "dynamics_train_captures.json" in message
    assert not (tmp_path / "out.npz").exists()
