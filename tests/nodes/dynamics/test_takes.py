"""A day of capture as one value: dynamics.LoadTakes (takes of different formats, lengths and frame
rates, read once per file through the cache), the Takes port type, dynamics.StabilizeTakes (mode
pursuit into the neutral's frame) and the checks of dynamics.TrainRemovalTakes."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import InputError, MeshSequence, NodeError, RigidSequence, run_node
from nodegraph.cache import Cache
from nodegraph.takes import Takes, cached_take
from nodes.dynamics.take_files import LoadTakes, find_takes
from nodes.dynamics.takes import StabilizeTakes, TrainRemovalTakes
from nodes.geometry.rigid import stabilize_vertices
from nodes.io.mesh import save_mesh_sequence
from nodes.synth.dynamics import simulate_dynamics

from ._data import face_model


def _mesh(frames: int, fps: float, seed: int) -> MeshSequence:
    face = face_model()
    rng = np.random.default_rng(seed)
    vertices = face.neutral[None] + rng.normal(scale=0.1, size=(frames,) + face.neutral.shape)
    return MeshSequence(vertices=vertices.astype(np.float32), faces=face.faces, fps=fps)


def test_load_takes_of_different_formats_lengths_and_rates(tmp_path):
    a, b, c = _mesh(50, 96.0, 1), _mesh(70, 120.0, 2), _mesh(30, 60.0, 3)
    rigid = np.tile(np.eye(4), (50, 1, 1))
    rigid[:, 1, 3] = np.linspace(0, 2, 50)
    np.savez(tmp_path / "a.npz", vertices=a.vertices, faces=a.faces, fps=96.0, rigid=rigid)
    save_mesh_sequence(str(tmp_path / "b.usda"), b, range(70))
    save_mesh_sequence(str(tmp_path / "c.%04d.obj"), c, range(30), first_frame=1)
    (tmp_path / "notes.txt").write_text("ignored in a folder")
    takes = run_node(LoadTakes, {"captures": str(tmp_path), "fps": 60.0})["takes"]
    assert takes.names == ["a", "b", "c"]
    assert takes.lengths.tolist() == [50, 70, 30] and takes.fps.tolist() == [96.0, 120.0, 60.0]
    assert takes.has_rigid.tolist() == [True, False, False]
    np.testing.assert_array_equal(takes.skull(0).matrices, rigid)
    assert takes.skull(1) is None
    for i, mesh in enumerate((a, b, c)):
        np.testing.assert_allclose(takes.take(i).vertices, mesh.vertices, rtol=0, atol=1e-5)
    back = Takes.from_arrays(takes.to_arrays())
    back.validate()
    assert back.names == takes.names and back.lengths.tolist() == [50, 70, 30]
    # a glob of one kind; OBJ without a frame rate anywhere is refused, naming the take
    assert [name for name, _, _ in find_takes(str(tmp_path / "*.npz"))] == ["a"]
    with pytest.raises(NodeError, match="take 'c'.*frame rate"):
        run_node(LoadTakes, {"captures": str(tmp_path)})
    with pytest.raises(NodeError, match="expected take files"):
        run_node(LoadTakes, {"captures": str(tmp_path / "*.txt")})
    with pytest.raises(NodeError, match="found none"):
        run_node(LoadTakes, {"captures": str(tmp_path / "nothing_*.npz")})


def test_takes_of_another_topology_are_refused(tmp_path):
    np.savez(tmp_path / "a.npz", vertices=_mesh(20, 30.0, 1).vertices, fps=30.0)
    np.savez(tmp_path / "b.npz", vertices=_mesh(20, 30.0, 1).vertices[:, :-1], fps=30.0)
    with pytest.raises(NodeError, match="take 'b'.*topology of take 'a'"):
        run_node(LoadTakes, {"captures": str(tmp_path / "*.npz")})


def test_a_take_is_read_once_per_file_content(tmp_path):
    cache = Cache(tmp_path / "cache")
    calls = []

    def read():
        calls.append(1)
        return _mesh(5, 30.0, 1), RigidSequence(matrices=np.tile(np.eye(4), (5, 1, 1)))

    first = cached_take(["aa"], "reader/1", read, cache)
    again = cached_take(["aa"], "reader/1", read, cache)
    assert len(calls) == 1
    np.testing.assert_array_equal(first[0].vertices, again[0].vertices)
    np.testing.assert_array_equal(again[1].matrices, first[1].matrices)
    cached_take(["bb"], "reader/1", read, cache)  # another file content
    cached_take(["aa"], "reader/2", read, cache)  # another reader
    assert len(calls) == 3


def test_stabilize_takes_finds_the_skull_in_the_neutrals_frame():
    data = simulate_dynamics(face_model(), motions=["walk"], expressions=["smile"], segment_frames=150,
                             fps=120.0, seed=4)
    tracked = simulate_dynamics(face_model(), motions=["run"], expressions=["neutral"], segment_frames=60,
                                fps=96.0, seed=4)
    takes = Takes.from_sequences(["smile_walk", "neutral_run"], [data.capture, tracked.capture],
                                 [None, tracked.skull])
    out = run_node(StabilizeTakes, takes=takes, neutral=data.neutral)
    stabilized, report = out["stabilized"], out["report"].value
    assert report["smile_walk"]["skull"] == "mode pursuit" and report["neutral_run"]["skull"] == "tracked"
    np.testing.assert_array_equal(stabilized.skull(1).matrices, tracked.skull.matrices)
    local = stabilize_vertices(data.capture.vertices, stabilized.skull(0).matrices)
    error = np.linalg.norm(local - data.stabilized.vertices, axis=-1)
    assert np.median(error) < 0.02, np.median(error)  # cm; the smile moves half the face


def test_train_removal_takes_checks_its_inputs():
    data = simulate_dynamics(face_model(), motions=["walk"], expressions=["neutral"], segment_frames=60,
                             fps=120.0, seed=4)
    takes = Takes.from_sequences(["a", "b"], [data.capture, data.capture], [data.skull, None])
    with pytest.raises(NodeError, match="skull motion for every take.*'b'"):
        run_node(TrainRemovalTakes, takes=takes, neutral=data.neutral)
    takes = Takes.from_sequences(["a", "b"], [data.capture, data.capture], [data.skull, data.skull])
    with pytest.raises(NodeError, match="'held'.*matching 'hold_\\*'"):
        run_node(TrainRemovalTakes, {"held": "hold_*"}, takes=takes, neutral=data.neutral)
    with pytest.raises(NodeError, match="'neutral'.*one frame of 400 vertices"):
        run_node(TrainRemovalTakes, takes=takes, neutral=data.capture)
    with pytest.raises(NodeError, match="take left to train on"):
        run_node(TrainRemovalTakes, {"held": "a", "held_out": "a"}, takes=takes, neutral=data.neutral)


def test_load_takes_reads_only_changed_files_through_the_runs_cache(tmp_path, monkeypatch):
    import nodes.dynamics.take_files as module

    folder = tmp_path / "takes"
    folder.mkdir()
    for name, seed in (("a", 1), ("b", 2)):
        np.savez(folder / f"{name}.npz", vertices=_mesh(10, 30.0, seed).vertices, fps=30.0)
    reads = []
    real = module.read_take
    monkeypatch.setattr(module, "read_take", lambda name, path, fps: reads.append(name) or real(name, path, fps))

    def load():
        node = LoadTakes({"captures": str(folder)})
        node.cache_root = str(tmp_path / "cache")  # what the runner sets
        return run_node(node)["takes"]

    load()
    np.savez(folder / "b.npz", vertices=_mesh(12, 30.0, 3).vertices, fps=30.0)
    np.savez(folder / "c.npz", vertices=_mesh(8, 30.0, 4).vertices, fps=30.0)
    takes = load()
    assert reads == ["a", "b", "b", "c"]
    assert takes.lengths.tolist() == [10, 12, 8]


@pytest.mark.parametrize("fps", [-5.0, float("nan"), 1e308])
def test_a_take_storing_a_bad_frame_rate_is_refused_while_planning(tmp_path, fps):
    """LoadTakes is the run's frame source: its frame_count (called while planning) reads each NPZ
    take's stored 'fps' and refuses a bad one naming the take (it was a FAILED task after reading)."""
    np.savez(tmp_path / "a.npz", vertices=_mesh(20, 30.0, 1).vertices, fps=30.0)
    np.savez(tmp_path / "b.npz", vertices=_mesh(20, 30.0, 2).vertices, fps=fps)
    with pytest.raises(InputError, match="take 'b'.*'fps'.*found"):
        LoadTakes({"captures": str(tmp_path)}).frame_count()
