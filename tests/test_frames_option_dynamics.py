"""`--frames a:b` on graphs/dynamics_train_captures.json: the run's frames are the takes' frames
(dynamics.LoadTakes is the frame source, the one-frame neutral is a whole value), so a:b trains
on frames a:b of every take. Issue 30: every shipped graph accepts `--frames a:b`; this one
refused any b > 1 (the neutral, an io.LoadMeshSequence of one frame, was the frame source)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")

from nodegraph import Graph, GraphError, NodeError, run_node, runner  # noqa: E402
from nodes.dynamics.take_files import LoadNeutral, LoadTakes  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.synth.dynamics import simulate_dynamics  # noqa: E402

GRAPHS = Path(__file__).resolve().parents[1] / "graphs"
LENGTHS = {"hold_a": 90, "hold_b": 120, "hold_c": 40}  # frames of each take (120 fps)


def _takes(folder: Path) -> Path:
    """Three held-expression takes of one face (120 points) with their skull motion, of 90, 120
    and 40 frames, and the neutral (one frame); returns the neutral's path."""
    face = load_face_model(region="face", max_vertices=120)
    (folder / "takes").mkdir()
    for seed, (name, frames) in enumerate(LENGTHS.items()):
        data = simulate_dynamics(face, motions=["oscillate@8"], expressions=["smile"], segment_frames=frames,
                                 fps=120.0, seed=seed)
        np.savez(folder / "takes" / f"{name}.npz", vertices=data.capture.vertices, faces=face.faces,
                 fps=120.0, rigid=data.skull.matrices)
    np.savez(folder / "neutral.npz", vertices=data.neutral.vertices, faces=face.faces)
    return folder / "neutral.npz"


def _graph() -> Graph:
    graph = Graph.load(GRAPHS / "dynamics_train_captures.json")
    graph.set("train", hidden=[16], batch_size=2000)
    graph.set("train_synthesis", hidden=[16])
    return graph


def _parameters(folder: Path, neutral: Path) -> dict:
    return {"captures": str(folder / "takes"), "neutral": str(neutral), "model": str(folder / "f.safetensors"),
            "synthesis_model": str(folder / "h.safetensors"), "report": str(folder / "report.json"),
            "held_out": "-", "epochs": 1, "rows": 2000, "samples": 16, "synthesis_samples": 16,
            "synthesis_epochs": 1}


def test_load_takes_keeps_the_run_frames_of_every_take(tmp_path):
    _takes(tmp_path)
    assert LoadTakes({"captures": str(tmp_path / "takes")}).frame_count() == 120  # the longest take
    out = run_node(LoadTakes, {"captures": str(tmp_path / "takes")}, frames=range(30, 100))
    takes, coverage = out["takes"], out["coverage"]
    # hold_a: 30..89 (60 frames), hold_b: 30..99 (70), hold_c: 30..39 (10)
    assert takes.names == ["hold_a", "hold_b", "hold_c"] and takes.lengths.tolist() == [60, 70, 10]
    with np.load(tmp_path / "takes" / "hold_b.npz") as whole:
        np.testing.assert_array_equal(takes.take(1).vertices, whole["vertices"][30:100])
        np.testing.assert_array_equal(takes.skull(1).matrices, whole["rigid"][30:100])
    assert coverage.names == ["hold_a", "hold_b", "hold_c"] and coverage.values.shape == (70, 3)
    assert coverage.values.sum(axis=0).tolist() == [60.0, 70.0, 10.0]
    # a take with fewer than 2 frames in the range is left out (its coverage column is zero)
    out = run_node(LoadTakes, {"captures": str(tmp_path / "takes")}, frames=range(39, 100))
    assert out["takes"].names == ["hold_a", "hold_b"] and out["coverage"].values[:, 2].sum() == 1.0
    with pytest.raises(NodeError, match="'captures'.*--frames 119:125.*at least 2 frames"):
        run_node(LoadTakes, {"captures": str(tmp_path / "takes")}, frames=range(119, 125))


def test_load_neutral_refuses_a_take_given_as_the_neutral(tmp_path):
    neutral = _takes(tmp_path)
    assert run_node(LoadNeutral, {"path": str(neutral)})["mesh"].num_frames == 1
    take = tmp_path / "takes" / "hold_c.npz"
    with pytest.raises(NodeError, match="'path'.*expected one frame.*found 40 frames"):
        run_node(LoadNeutral, {"path": str(take)})
    with np.load(take) as data:
        np.testing.assert_array_equal(run_node(LoadNeutral, {"path": str(take), "frame": 7})["mesh"].vertices[0],
                                      data["vertices"][7])
    with pytest.raises(NodeError, match="'frame'.*0..39.*found 40"):
        run_node(LoadNeutral, {"path": str(take), "frame": 40})


def test_train_captures_graph_trains_on_the_frames_asked_for(tmp_path):
    neutral = _takes(tmp_path)
    result = runner.run(_graph(), frames=range(10, 80), scheduler="sync", cache=False,
                        parameters=_parameters(tmp_path, neutral))
    assert result.exit_code == 0, result.summary()
    report = json.loads((tmp_path / "report.json").read_text())
    removal, synthesis = report["removal"], report["synthesis"]
    # frames 10..79 of hold_a (70), hold_b (70) and hold_c (10..39: 30)
    assert removal["takes"] == ["hold_a", "hold_b", "hold_c"] and removal["frames"] == 70 + 70 + 30
    assert synthesis["takes"] == ["hold_a", "hold_b", "hold_c"]
    assert (tmp_path / "f.safetensors").is_file() and (tmp_path / "h.safetensors").is_file()


def test_train_captures_graph_refuses_a_range_past_every_take_before_anything_runs(tmp_path):
    neutral = _takes(tmp_path)
    with pytest.raises(GraphError, match="'takes'.*--frames 100:130.*120 frame"):
        runner.run(_graph(), frames=range(100, 130), scheduler="sync", cache=False,
                   parameters=_parameters(tmp_path, neutral))
    assert not (tmp_path / "f.safetensors").exists() and not (tmp_path / "report.json").exists()


def test_train_captures_graph_on_a_range_too_short_to_train_names_the_takes_port_once(tmp_path):
    """--frames 0:4: no frame lies far enough from the takes' ends for the descriptor windows and
    the moving-average target: refused while planning (from the takes' headers, before any take
    is read or stabilized) naming node 'train', its port 'takes' (not the training function's
    'captures'), the takes' frames and what to change; nothing written."""
    neutral = _takes(tmp_path)
    with pytest.raises(NodeError) as caught:
        runner.run(_graph(), frames=range(0, 4), scheduler="sync", cache=False,
                   parameters=_parameters(tmp_path, neutral))
    message = str(caught.value)
    assert caught.value.bad_input and "'train'" in message and "'takes'" in message, message
    assert "longer --frames range" in message and "[4, 4, 4] frames" in message, message
    assert message.count("expected") == 1, message
    assert not (tmp_path / "f.safetensors").exists() and not (tmp_path / "report.json").exists()
