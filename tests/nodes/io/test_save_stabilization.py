"""`io.SaveStabilization` hashes the NPZ while writing it (no read-back): the recorded sha256
is the file's, and the forward-only archive (data descriptors) reads back, also row-wise."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import MeshSequence, RigidSequence, run_node
from nodegraph.files import file_sha256, write_npz_atomic
from nodes.io._files import read_npz_rows
from nodes.io.mesh import load_mesh_sequence
from nodes.io.stabilization import SaveStabilization


def test_saved_hash_is_the_file_hash_and_the_file_reads_back(tmp_path):
    rng = np.random.default_rng(0)
    vertices = rng.normal(size=(7, 40, 3)).astype(np.float32)
    rigid = np.tile(np.eye(4), (7, 1, 1))
    rigid[:, :3, 3] = rng.normal(size=(7, 3))
    mesh = MeshSequence(vertices=vertices, faces=np.array([[0, 1, 2]], np.int32), fps=24.0)
    path = tmp_path / "out.npz"
    files = run_node(SaveStabilization, {"path": str(path)}, rigid=RigidSequence(rigid), mesh=mesh)["files"]
    assert files.paths == [str(path)]
    assert files.sha256 == [file_sha256(path, memo=False)]
    with np.load(path) as data:
        assert np.array_equal(data["vertices"], vertices)
        assert np.array_equal(data["rigid"], rigid)
        assert float(data["fps"]) == 24.0
    assert np.array_equal(read_npz_rows(path, "vertices", 2, 5), vertices[2:5])  # memory-mapped rows
    assert np.array_equal(load_mesh_sequence(str(path), range(1, 6)).vertices, vertices[1:6])


def test_write_npz_atomic_returns_the_sha256_of_the_file(tmp_path):
    path = tmp_path / "a.npz"
    digest = write_npz_atomic(path, {"x": np.arange(100000, dtype=np.float64), "y": np.float32(2.5)})
    assert digest == file_sha256(path, memo=False)
    with np.load(path) as data:
        assert data["x"][-1] == 99999.0 and float(data["y"]) == 2.5


def test_npz_rows_with_nan_or_inf_are_refused_naming_frame_and_vertex(tmp_path):
    """The loader proves rows finite and in range by their min and max; a failure still names
    the first bad frame and vertex (NaN, +inf, -inf)."""
    import pytest

    from nodegraph import InputError

    for bad in (np.nan, np.inf, -np.inf):
        vertices = np.zeros((6, 9, 3), np.float32)
        vertices[4, 7, 2] = bad
        path = tmp_path / "bad.npz"
        np.savez(path, vertices=vertices, faces=np.array([[0, 1, 2]], np.int32))
        with pytest.raises(InputError, match=r"frame 4 .*NaN/inf at vertex 7"):
            load_mesh_sequence(str(path), range(0, 6))
        assert load_mesh_sequence(str(path), range(0, 4)).num_frames == 4  # rows before it are fine


@pytest.mark.parametrize("path", ["out/stab.txt", "out/folder", "out/stab.npz.tmp"])
def test_an_output_that_is_not_npz_is_refused_before_anything_runs(path):
    """stabilize.json output=stab.txt was refused only after mode pursuit had run (issue 30)."""
    from nodegraph import NodeError
    from nodes.io.stabilization import SaveStabilization

    with pytest.raises(NodeError, match=r"'path'.*\.npz"):
        SaveStabilization({"path": path})


@pytest.mark.parametrize("path", ["out/r.obj", "out/r"])
def test_a_rigid_sequence_output_must_be_json_or_npz(path):
    from nodegraph import NodeError
    from nodes.io.sequences import SaveRigidSequence

    with pytest.raises(NodeError, match=r"'path'.*\.json or \.npz"):
        SaveRigidSequence({"path": path})
    SaveRigidSequence({"path": "out/r.json"})
