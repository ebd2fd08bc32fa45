"""Removal network F and synthesis network H: training, held-out accuracy, chunking, files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from nodegraph import Graph, NodeError, TorchModel, run_node, runner
from nodes.dynamics.evaluate import rms_distance
from nodes.dynamics.files import LoadModel, SaveModel
from nodes.dynamics.removal import RemoveDynamics
from nodes.dynamics.synthesis import Retarget, SynthesizeDynamics
from nodes.synth.dynamics import simulate_dynamics

from ._data import face_model, removal_model, synthesis_model


@pytest.fixture(scope="module")
def held_out():
    """Another identity and expression, the held-out 9 Hz, at another frame rate (100 fps)."""
    return simulate_dynamics(face_model(), motions=["oscillate@9"], expressions=["pucker"],
                             segment_frames=160, fps=100.0, seed=2)


def test_train_removal_outputs_a_model():
    out = removal_model()
    model = out["model"]
    assert model.architecture == "dynamics.MLP" and model.config["kind"] == "removal"
    assert model.config["hidden"] == [128, 128] and model.config["in_features"] == 5 * 63 + 63
    assert model.normalization["sample_ids"].shape == (100,)
    assert out["report"].value["rows"] == 40000


def test_removal_reduces_error_on_a_held_out_frequency(held_out):
    out = run_node(RemoveDynamics, {}, capture=held_out.capture, skull=held_out.skull,
                   model=removal_model()["model"])
    before = rms_distance(held_out.capture.vertices, held_out.quasistatic.vertices)
    after = rms_distance(out["quasistatic"].vertices, held_out.quasistatic.vertices)
    assert after < 0.4 * before, (before, after)  # at least 60 % less
    assert out["offsets"].vertices.shape == held_out.capture.vertices.shape


def test_training_is_reproducible():
    from nodes.dynamics.networks import train_mlp

    rng = np.random.default_rng(0)
    x, y = rng.standard_normal((500, 6)).astype(np.float32), rng.standard_normal((500, 2)).astype(np.float32)
    a = train_mlp(x, y, hidden=[16], epochs=2, batch_size=100, lr=1e-3, seed=7)
    b = train_mlp(x, y, hidden=[16], epochs=2, batch_size=100, lr=1e-3, seed=7)
    for key, value in a.module.state_dict().items():
        assert bool((value == b.module.state_dict()[key]).all())


def test_remove_dynamics_chunk_independent_and_file_round_trip(held_out, tmp_path):
    model_path = tmp_path / "removal.safetensors"
    run_node(SaveModel, {"path": str(model_path)}, model=removal_model()["model"])
    loaded = run_node(LoadModel, {"path": str(model_path)})["model"]
    original = removal_model()["model"]
    assert loaded.fingerprint() == original.fingerprint()
    from safetensors import safe_open

    with safe_open(str(model_path), framework="np") as fh:
        meta = fh.metadata()
    assert meta["architecture"] == "dynamics.MLP" and json.loads(meta["config"])["kind"] == "removal"
    assert json.loads(meta["normalization.sample_ids"])["shape"] == [100]
    assert "input_mean" in json.loads(meta["normalization"])

    capture = held_out.capture
    np.savez(tmp_path / "cap.npz", vertices=capture.vertices[:60], faces=capture.faces)
    np.savez(tmp_path / "skull.npz", rigid=held_out.skull.matrices[:60])
    results = []
    for chunk in (9, 64):
        g = Graph()
        g.add("io.LoadMeshSequence", "load", path=str(tmp_path / "cap.npz"))
        g.add("io.LoadRigidSequence", "skull", path=str(tmp_path / "skull.npz"))
        g.add("dynamics.LoadModel", "model", path=str(model_path))
        g.add("dynamics.RemoveDynamics", "remove", fps=100.0)
        g.connect("load.mesh", "remove.capture")
        g.connect("skull.rigid", "remove.skull")
        g.connect("model.model", "remove.model")
        res = runner.run(g, scheduler="sync", cache=False, chunk=chunk)
        assert res.exit_code == 0, res.summary()
        results.append(res.outputs["remove"]["quasistatic"].vertices)
    np.testing.assert_array_equal(results[0], results[1])


def test_remove_dynamics_errors_name_port(held_out):
    model = removal_model()["model"]
    small = held_out.capture.slice_frames(0, 10)
    import dataclasses

    wrong = dataclasses.replace(small, vertices=small.vertices[:, :50], groups={})
    with pytest.raises(NodeError, match="training topology"):
        run_node(RemoveDynamics, {}, capture=wrong, skull=held_out.skull.slice_frames(0, 10), model=model)
    with pytest.raises(NodeError, match="frame rate up to"):
        run_node(RemoveDynamics, {"fps": 400.0}, capture=small, skull=held_out.skull.slice_frames(0, 10),
                 model=model)
    with pytest.raises(NodeError, match="removal network"):
        run_node(RemoveDynamics, {}, capture=small, skull=held_out.skull.slice_frames(0, 10),
                 model=synthesis_model()["model"])


def test_synthesis_on_a_held_out_motion():
    test = simulate_dynamics(face_model(), motions=["oscillate@9"], expressions=["smile"],
                             segment_frames=160, fps=100.0, seed=1)
    out = run_node(SynthesizeDynamics, {}, quasistatic=test.quasistatic, skull=test.skull,
                   neutral=test.neutral, model=synthesis_model()["model"])
    dynamic = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    residual = rms_distance(out["capture"].vertices, test.capture.vertices)
    assert residual < 0.4 * dynamic, (dynamic, residual)


def test_retarget_moves_the_performance_to_the_new_skull():
    a = simulate_dynamics(face_model(), motions=["walk"], expressions=["smile"], segment_frames=30,
                          fps=100.0, seed=1)
    b = simulate_dynamics(face_model(), motions=["run"], expressions=["smile"], segment_frames=30,
                          fps=100.0, seed=1)
    out = run_node(Retarget, {}, mesh=a.quasistatic, skull=a.skull, new_skull=b.skull)
    np.testing.assert_allclose(out["retargeted"].vertices, b.quasistatic.vertices, atol=1e-3)


def test_torchmodel_safetensors_round_trip_is_exact(tmp_path):
    model = synthesis_model()["model"]
    model.save(tmp_path / "h.safetensors")
    back = TorchModel.load(tmp_path / "h.safetensors")
    assert back.fingerprint() == model.fingerprint()
    (tmp_path / "bad.safetensors").write_bytes(b"not a file")
    with pytest.raises(NodeError, match="unreadable"):
        run_node(LoadModel, {"path": str(tmp_path / "bad.safetensors")})
