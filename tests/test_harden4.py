"""Issue 30, fourth hardening round: refusals that come while planning, not after the work.

- A training run whose frames cannot give one training row (`dynamics_train.json --frames 0:20`:
  the descriptor window reaches 11 frames at 96 fps and 14 at 128 fps, each side) is refused
  while planning, from the producers' parameters (frame rate, segment labels), not after both
  synthetic performances were made (401 s at load 6-9 before).
- The takes trainers check their take selection (`held`, `held_out`, `takes`) and the run's
  frames of the chosen takes from the takes' headers while planning.
- `dynamics.LoadNeutral` reads its file once a run (while planning; run() reuses that read).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, NodeError, runner
from nodegraph.schedule import plan_run
from nodes.dynamics import take_files
from nodes.dynamics.synthesis import TrainSynthesis
from nodes.synth.dynamics import DynamicPerformance

GRAPHS = Path(__file__).resolve().parents[1] / "graphs"


def test_dynamics_train_too_few_frames_is_refused_while_planning(tmp_path):
    graph = Graph.load(GRAPHS / "dynamics_train.json")
    graph.apply({"model": str(tmp_path / "f.safetensors"), "synthesis_model": str(tmp_path / "h.safetensors")})
    for frames in (range(0, 4), range(0, 20)):
        with pytest.raises(NodeError) as caught:
            plan_run(graph, frames=frames)
        message = str(caught.value)
        assert caught.value.bad_input and "'train_removal'" in message and "'captures'" in message, message
        # 96 fps: reach ceil(10 * 96 / 120) + 3 = 11; 128 fps: ceil(10.67) + 3 = 14
        assert f"--frames {frames.start}:{frames.stop}" in message and "11/14" in message, message
        assert f"[{len(frames)}, {len(frames)}] frames" in message, message
    # 40 frames: frames 11..28 of the 96 fps capture lie 11 frames from both ends
    plan_run(graph, frames=range(0, 40))
    assert not any(tmp_path.iterdir())


def test_synthesis_trainer_counts_segment_changes_while_planning():
    """The margin applies at segment changes too (windows never straddle one): 30 frames across
    the change at frame 80 give no row at 128 fps (reach 14), 40 frames within one segment do."""
    perf = DynamicPerformance({"fps": 128.0, "segment_frames": 80, "motions": ["still", "walk"],
                               "expressions": ["neutral"]})
    train = TrainSynthesis({})
    producers = {"captures": [perf], "segments": [perf]}
    train.check_frames(range(0, 40), producers)
    for frames in (range(0, 28), range(70, 100), range(60, 100)):
        with pytest.raises(Exception, match=f"'captures'.*--frames {frames.start}:{frames.stop}.*at least 14"):
            train.check_frames(frames, producers)
    # without segment labels, 60:100 is one stretch of 40 frames: rows 14..25
    train.check_frames(range(60, 100), {"captures": [perf]})
    # a producer that cannot tell its frame rate: nothing is judged while planning (run() does)
    train.check_frames(range(0, 4), {"captures": [object()]})


def _takes_graph(folder: Path, **parameters) -> Graph:
    """dynamics_train_captures.json on two 60-frame NPZ takes of 30 points at 120 fps (with skull
    motion) and their one-frame neutral: planning needs only the headers."""
    rng = np.random.default_rng(0)
    neutral = rng.normal(scale=5.0, size=(30, 3)).astype(np.float32)
    faces = (np.arange(30, dtype=np.int32) % 30).reshape(10, 3)
    (folder / "takes").mkdir()
    for name in ("hold_a", "hold_b"):
        np.savez(folder / "takes" / f"{name}.npz", vertices=np.repeat(neutral[None], 60, 0), faces=faces,
                 fps=120.0, rigid=np.repeat(np.eye(4)[None], 60, 0))
    np.savez(folder / "neutral.npz", vertices=neutral[None], faces=faces)
    graph = Graph.load(GRAPHS / "dynamics_train_captures.json")
    graph.apply({"captures": str(folder / "takes"), "neutral": str(folder / "neutral.npz"),
                 "model": str(folder / "f.safetensors"), "synthesis_model": str(folder / "h.safetensors"),
                 "report": str(folder / "r.json")} | parameters)
    return graph


@pytest.mark.parametrize("parameters, frames, port, found", [
    ({"held": "nosuch_*"}, None, "'held'", "found none among ['hold_a', 'hold_b']"),
    ({"held_out": "nosuch"}, None, "'held_out'", "found 'nosuch'"),
    ({"held": "hold_a", "held_out": "hold_a"}, None, "'held_out'", "found only"),
    ({"held_out": "-"}, range(0, 26), "'takes'", "at least 13 frames"),  # 120 fps: reach 13, half-width 12
    ({"synthesis_takes": "none_*"}, None, "'takes'", "expected takes matching 'none_*'"),
])
def test_takes_trainers_refuse_while_planning(tmp_path, parameters, frames, port, found):
    graph = _takes_graph(tmp_path, **parameters)
    with pytest.raises(NodeError) as caught:
        plan_run(graph, frames=frames)
    message = str(caught.value)
    assert caught.value.bad_input and port in message and found in message, message
    assert "'train" in message, message  # node 'train' or 'train_synthesis'


def test_takes_trainers_accept_a_range_with_rows(tmp_path):
    plan_run(_takes_graph(tmp_path, held_out="-"), frames=range(0, 27))  # 27 > 2 x 13: frame 13


def test_load_neutral_reads_its_file_once_a_run(tmp_path, monkeypatch):
    path = tmp_path / "neutral.npz"
    np.savez(path, vertices=np.zeros((1, 4, 3), np.float32) + np.arange(4)[None, :, None],
             faces=np.array([[0, 1, 2], [1, 2, 3]], np.int32))
    reads = []
    real = take_files.load_mesh_sequence
    monkeypatch.setattr(take_files, "load_mesh_sequence", lambda *a, **k: reads.append(a) or real(*a, **k))
    graph = Graph.from_json({"schema": "nodegraph/1",
                             "nodes": {"neutral": {"type": "dynamics.LoadNeutral", "params": {"path": str(path)}}},
                             "edges": []})
    result = runner.run(graph, frames=range(0, 1), scheduler="sync", cache=False, progress="none")
    assert result.exit_code == 0, result.summary()
    np.testing.assert_array_equal(result.outputs["neutral"]["mesh"].vertices[0, :, 0], np.arange(4))
    assert len(reads) == 1, reads
    # a file changed after planning is read again (the planned read is keyed by size and time)
    node = take_files.LoadNeutral({"path": str(path)})
    node.check_plan({})
    np.savez(path, vertices=np.ones((1, 5, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32))
    assert node.run()["mesh"].num_vertices == 5


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc")
def test_cache_under_proc_is_refused_before_anything_runs(tmp_path, capsys):
    """root passes os.access in /proc, yet no folder can be made there: exit 2 at once (was exit 1
    after the outputs were committed, when the run's record could not be written)."""
    from nodegraph.cli import main

    capture = tmp_path / "c.npz"
    np.savez(capture, vertices=np.zeros((2, 3, 3), np.float32), faces=np.array([[0, 1, 2]], np.int32), fps=30.0)
    code = main(["run", str(GRAPHS / "stabilize.json"), f"capture={capture}", f"output={tmp_path}/s.npz",
                 f"report={tmp_path}/r", "--cache", "/proc/nodegraph_cache", "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 2 and "--cache" in err and "/proc" in err and "Traceback" not in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.npz"]


def test_an_output_path_problem_is_reported_before_a_frames_problem(tmp_path):
    """The runner checks output paths, then the nodes' check_frames: a run with both problems
    names the output (what a user fixes first; the data check needs the right files)."""
    from nodegraph import GraphError

    (tmp_path / "a_file").write_text("a file")
    graph = Graph.load(GRAPHS / "dynamics_train.json")
    graph.apply({"model": str(tmp_path / "a_file" / "f.safetensors"), "synthesis_model": str(tmp_path / "h.safetensors")})
    with pytest.raises(GraphError, match="'save_removal'.*is a file, not a folder"):
        runner.run(graph, frames=range(0, 4), scheduler="sync", cache=False, progress="none")
    graph.apply({"model": str(tmp_path / "f.safetensors")})
    with pytest.raises(NodeError, match="'train_removal'.*--frames 0:4"):
        runner.run(graph, frames=range(0, 4), scheduler="sync", cache=False, progress="none")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]
