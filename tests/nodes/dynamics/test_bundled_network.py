"""The bundled removal network (nodes/data/dynamics, trained by graphs/dynamics_train.json): read by
dynamics.LoadModel with no path, it cleans a capture of the ICT face region it has not seen."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import NodeError, run_node
from nodes.dynamics.evaluate import rms_distance
from nodes.dynamics.files import BUNDLED_REMOVAL, LoadModel
from nodes.dynamics.removal import RemoveDynamics
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import simulate_dynamics


def test_bundled_network_is_read_and_keyed_by_its_file():
    node = LoadModel({})
    assert node.input_files() == [BUNDLED_REMOVAL] and BUNDLED_REMOVAL.is_file()
    model = run_node(LoadModel, {})["model"]
    assert model.config["kind"] == "removal"
    assert int(model.config["num_vertices"]) == load_face_model(region="face").neutral.shape[0]


def test_bundled_network_removes_dynamics_of_a_new_identity_and_motion():
    face = load_face_model(region="face")
    test = simulate_dynamics(face, motions=["run"], expressions=["neutral"], segment_frames=150, fps=120.0,
                             seed=11, noise_cm=0.01)
    model = run_node(LoadModel, {})["model"]
    out = run_node(RemoveDynamics, capture=test.capture, skull=test.skull, model=model)
    before = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    after = rms_distance(out["quasistatic"].vertices, test.quasistatic.vertices)
    print(f"bundled network: RMS {before * 10:.3f} -> {after * 10:.3f} mm")
    assert after < 0.75 * before, (before, after)


def test_bundled_network_refuses_another_topology():
    other = simulate_dynamics(load_face_model(region="face", max_vertices=300), motions=["still"],
                              expressions=["neutral"], segment_frames=20, fps=120.0, seed=1)
    with pytest.raises(NodeError, match="training topology"):
        run_node(RemoveDynamics, capture=other.capture, skull=other.skull, model=run_node(LoadModel, {})["model"])
