"""graphs/dynamics_remove.json on the capture a user has (a whole head, or the wrong topology)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import NodeError, runner
from nodes.dynamics.evaluate import rms_distance
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


# -- training on one's own takes -------------------------------------------------------------

MOTIONS = ["walk", "run", "oscillate@6", "oscillate@8", "oscillate@11"]


def _takes_folder(folder: Path, order: np.ndarray, face) -> tuple[np.ndarray, np.ndarray]:
    """Generated takes of one identity (seed 3) in a shuffled vertex order: held expressions under
    five motions at 96, 120 and 128 fps, 150-230 frames each; the 120 fps ones without `rigid`
    (stabilized by mode pursuit in the graph). Returns the neutral and the shuffled faces."""
    inverse = np.argsort(order)
    faces = inverse[face.faces].astype(np.int32)
    for fps, expressions, frames, rigid in ((96.0, ["neutral", "smile"], 150, True),
                                            (120.0, ["jaw_open"], 190, False),
                                            (128.0, ["pucker"], 230, True)):
        data = simulate_dynamics(face, motions=MOTIONS, expressions=expressions, segment_frames=frames,
                                 fps=fps, seed=3)
        pairs = [(e, m) for e in expressions for m in MOTIONS]
        for k, (expression, motion) in enumerate(pairs):
            cut = slice(k * frames, (k + 1) * frames)
            arrays = {"vertices": data.capture.vertices[cut][:, order], "faces": faces, "fps": fps}
            if rigid:
                arrays["rigid"] = data.skull.matrices[cut]
            np.savez(folder / f"take_{expression}_{motion.replace('@', '')}.npz", **arrays)
    return data.neutral.vertices[:, order], faces


def test_train_captures_graph_learns_in_any_vertex_order_and_cleans_another_take(tmp_path):
    from nodegraph import Graph

    face = load_face_model(region="face", max_vertices=400)
    order = np.random.default_rng(5).permutation(len(face.neutral))
    takes = tmp_path / "takes"
    takes.mkdir()
    neutral, faces = _takes_folder(takes, order, face)
    np.savez(tmp_path / "neutral.npz", vertices=neutral, faces=faces)
    graph = Graph.load(GRAPHS / "dynamics_train_captures.json")
    graph.set("train", hidden=[64, 64], batch_size=2000)
    graph.set("train_synthesis", hidden=[64, 64])
    model, report = tmp_path / "removal.safetensors", tmp_path / "report.json"
    result = runner.run(graph, scheduler="sync", cache=tmp_path / "cache",
                        parameters={"captures": str(takes / "take_*.npz"), "neutral": str(tmp_path / "neutral.npz"),
                                    "model": str(model), "report": str(report), "epochs": 12, "rows": 40000,
                                    "samples": 100, "synthesis_model": str(tmp_path / "synthesis.safetensors"),
                                    "synthesis_samples": 60, "synthesis_epochs": 4})
    assert result.exit_code == 0, result.summary()
    import json

    everything = json.loads(report.read_text())
    data, synthesis = everything["removal"], everything["synthesis"]
    assert len(synthesis["takes"]) == 20 and synthesis["loss_per_epoch"][-1] < synthesis["loss_per_epoch"][0]
    assert (tmp_path / "synthesis.safetensors").is_file()
    assert len(data["takes"]) == 19 and "jaw_open" in " ".join(data["takes"])
    assert data["loss_per_epoch"][-1] < 0.5 * data["loss_per_epoch"][0], data["loss_per_epoch"]
    assert data["held_out"]["take"] == "take_smile_walk" and data["held_out"]["reduction_pct"] > 10, data  # a walk: little jiggle
    # another expression (frown) at another frequency (9 Hz) and frame rate (110 fps), against the truth
    test = simulate_dynamics(face, motions=["oscillate@9"], expressions=["frown"], segment_frames=200,
                             fps=110.0, seed=3)
    np.savez(tmp_path / "test.npz", vertices=test.capture.vertices[:, order], faces=faces, fps=110.0,
             rigid=test.skull.matrices)
    out = tmp_path / "quasistatic.npz"
    result = runner.run(GRAPHS / "dynamics_remove.json", scheduler="sync", cache=False,
                        parameters={"capture": str(tmp_path / "test.npz"), "skull": str(tmp_path / "test.npz"),
                                    "model": str(model), "output": str(out)})
    assert result.exit_code == 0, result.summary()
    with np.load(out) as saved:
        removed = saved["vertices"]
    truth = test.quasistatic.vertices[:, order]
    before, after = rms_distance(test.capture.vertices[:, order], truth), rms_distance(removed, truth)
    print(f"takes network on frown at 9 Hz: RMS {10 * before:.3f} -> {10 * after:.3f} mm; held out {data['held_out']}")
    assert after < 0.6 * before, (before, after)


def test_train_captures_graph_refuses_a_neutral_of_another_topology_before_anything_runs(tmp_path, capsys):
    """Read from the NPZ headers while planning: one exit 2 naming the take, not a failure after
    every take was read (it was a FAILED dynamics.StabilizeTakes task)."""
    from nodegraph.cli import main

    face = load_face_model(region="face", max_vertices=60)
    (tmp_path / "takes").mkdir()
    rng = np.random.default_rng(0)
    np.savez(tmp_path / "takes" / "hold_a.npz", faces=face.faces, fps=120.0,
             vertices=(face.neutral[None] + rng.normal(scale=0.01, size=(30, 60, 3))).astype(np.float32))
    np.savez(tmp_path / "neutral.npz", vertices=face.neutral[None, :50].astype(np.float32))
    code = main(["run", str(GRAPHS / "dynamics_train_captures.json"), f"captures={tmp_path / 'takes'}",
                 f"neutral={tmp_path / 'neutral.npz'}", f"model={tmp_path / 'f.safetensors'}",
                 f"synthesis_model={tmp_path / 'h.safetensors'}", f"report={tmp_path / 'r.json'}", "--no-cache",
                 "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "'stabilize'" in err and "'neutral'" in err and "take 'hold_a' has 60" in err and "found 50" in err, err
    assert "FAILED" not in err and err.count("expected") == 1, err
    assert not (tmp_path / "f.safetensors").exists() and not (tmp_path / "r.json").exists()
