"""Tests of nodes.io.sequences (rigid and parameter sequences as JSON and NPZ)."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodegraph import NodeError, ParamSequence, RigidSequence, run_node
from nodegraph.node import execute
from nodes.io.sequences import (LoadParamSequence, LoadRigidSequence, SaveParamSequence,
                                SaveRigidSequence)


def make_rigid(frames: int = 7, seed: int = 0) -> RigidSequence:
    rng = np.random.default_rng(seed)
    matrices = np.tile(np.eye(4), (frames, 1, 1))
    matrices[:, :3, :3] = Rotation.random(frames, random_state=seed).as_matrix()
    matrices[:, :3, 3] = rng.normal(scale=5.0, size=(frames, 3))
    return RigidSequence(matrices=matrices)


def make_params(frames: int = 7, seed: int = 0) -> ParamSequence:
    values = np.random.default_rng(seed).normal(size=(frames, 4)).astype(np.float32)
    return ParamSequence(values=values, names=["jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthFunnel"])


def load_rigid(path, frames=None) -> RigidSequence:
    return run_node(LoadRigidSequence, {"path": str(path)}, frames=frames)["rigid"]


def load_params(path, frames=None) -> ParamSequence:
    return run_node(LoadParamSequence, {"path": str(path)}, frames=frames)["sequence"]


def save_params(path, params: ParamSequence):
    # run_node(..., params=...) would collide with run_node's own `params` argument
    frames = range(params.num_frames)
    return execute(SaveParamSequence({"path": str(path)}), {"sequence": params}, frames, frames)


@pytest.mark.parametrize("name", ["rigid.json", "rigid.npz"])
def test_rigid_round_trip_is_exact(tmp_path, name):
    rigid = make_rigid()
    files = run_node(SaveRigidSequence, {"path": str(tmp_path / name)}, rigid=rigid)["files"]
    assert files.sha256 == [hashlib.sha256((tmp_path / name).read_bytes()).hexdigest()]
    back = load_rigid(tmp_path / name)
    assert back.matrices.dtype == np.float64
    np.testing.assert_array_equal(back.matrices, rigid.matrices)
    assert LoadRigidSequence({"path": str(tmp_path / name)}).frame_count() == 7


def test_rigid_json_layout_and_convention(tmp_path):
    run_node(SaveRigidSequence, {"path": str(tmp_path / "r.json")}, rigid=make_rigid(2))
    data = json.loads((tmp_path / "r.json").read_text())
    assert data["convention"] == "skull_to_world"
    assert np.asarray(data["matrices"]).shape == (2, 4, 4)


@pytest.mark.parametrize("name", ["rigid.json", "rigid.npz"])
def test_rigid_chunked_load_equals_full(tmp_path, name):
    rigid = make_rigid()
    run_node(SaveRigidSequence, {"path": str(tmp_path / name)}, rigid=rigid)
    for frames in [range(2, 5), range(6, 7)]:
        np.testing.assert_array_equal(load_rigid(tmp_path / name, frames).matrices,
                                      rigid.matrices[frames.start:frames.stop])


def test_rigid_npz_key_rigid_is_accepted(tmp_path):
    rigid = make_rigid(3)
    np.savez(tmp_path / "r.npz", rigid=rigid.matrices)
    np.testing.assert_array_equal(load_rigid(tmp_path / "r.npz").matrices, rigid.matrices)


@pytest.mark.parametrize("name", ["params.json", "params.npz"])
def test_params_round_trip_is_exact(tmp_path, name):
    params = make_params()
    files = save_params(tmp_path / name, params)["files"]
    assert files.paths == [str(tmp_path / name)]
    back = load_params(tmp_path / name)
    assert back.names == params.names and back.values.dtype == np.float32
    np.testing.assert_array_equal(back.values, params.values)
    for frames in [range(2, 5), range(0, 1)]:
        np.testing.assert_array_equal(load_params(tmp_path / name, frames).values,
                                      params.values[frames.start:frames.stop])


# -- bad input -------------------------------------------------------------------------------

def test_error_rigid_non_rigid_matrix_names_file_and_frame(tmp_path):
    rigid = make_rigid(5)
    rigid.matrices[3, :3, :3] *= 1.1
    np.savez(tmp_path / "r.npz", matrices=rigid.matrices)
    with pytest.raises(NodeError, match=r"frame 3 \(file '.*r\.npz'\): expected a rigid matrix") as err:
        load_rigid(tmp_path / "r.npz", range(2, 5))
    assert err.value.bad_input and err.value.port == "path"


def test_error_rigid_reflection_and_nan(tmp_path):
    rigid = make_rigid(4)
    rigid.matrices[1, :3, 0] *= -1
    rigid.matrices[2, 0, 3] = np.nan
    np.savez(tmp_path / "r.npz", matrices=rigid.matrices)
    with pytest.raises(NodeError, match=r"frame 2 \(file .*\): expected finite values"):
        load_rigid(tmp_path / "r.npz")
    with pytest.raises(NodeError, match=r"frame 1 \(file .*\).*det R = -1"):
        load_rigid(tmp_path / "r.npz", range(0, 2))


def test_error_rigid_json_wrong_shape_names_frame(tmp_path):
    matrices = make_rigid(3).matrices.tolist()
    matrices[2] = matrices[2][:3]
    (tmp_path / "r.json").write_text(json.dumps({"matrices": matrices}))
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*r\.json'\): expected 'matrices' of "
                                        r"shape \(4, 4\), found \(3, 4\)"):
        load_rigid(tmp_path / "r.json")


def test_error_rigid_json_other_convention_and_missing_key(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps({"convention": "world_to_skull", "matrices": []}))
    with pytest.raises(NodeError, match=r"file '.*a\.json': expected convention 'skull_to_world', "
                                        r"found 'world_to_skull'"):
        load_rigid(tmp_path / "a.json", range(0, 0))
    (tmp_path / "b.json").write_text(json.dumps({"poses": []}))
    with pytest.raises(NodeError, match=r"expected a key 'matrices', found keys \['poses'\]"):
        load_rigid(tmp_path / "b.json", range(0, 0))


def test_error_truncated_files(tmp_path):
    run_node(SaveRigidSequence, {"path": str(tmp_path / "r.json")}, rigid=make_rigid(3))
    text = (tmp_path / "r.json").read_text()
    (tmp_path / "r.json").write_text(text[: len(text) // 2])
    with pytest.raises(NodeError, match=r"file '.*r\.json'.*unreadable or truncated"):
        load_rigid(tmp_path / "r.json", range(0, 1))
    save_params(tmp_path / "p.npz", make_params())
    data = (tmp_path / "p.npz").read_bytes()
    (tmp_path / "p.npz").write_bytes(data[: len(data) // 2])
    with pytest.raises(NodeError, match=r"file '.*p\.npz'.*unreadable or truncated"):
        load_params(tmp_path / "p.npz", range(0, 1))


def test_error_params_names_do_not_match_columns(tmp_path):
    (tmp_path / "p.json").write_text(json.dumps({"names": ["a", "b"], "values": [[1, 2, 3]]}))
    with pytest.raises(NodeError, match=r"file '.*p\.json': expected 3 names .*found 2"):
        load_params(tmp_path / "p.json")
    np.savez(tmp_path / "p.npz", values=np.zeros((2, 3), np.float32), names=np.array(["a"]))
    with pytest.raises(NodeError, match=r"file '.*p\.npz': expected 3 names .*found 1"):
        load_params(tmp_path / "p.npz")


def test_error_params_ragged_row_names_frame(tmp_path):
    (tmp_path / "p.json").write_text(json.dumps({"names": ["a", "b"],
                                                 "values": [[1, 2], [3, 4], [5]]}))
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*p\.json'\): expected 'values' of shape "
                                        r"\(2,\), found \(1,\)"):
        load_params(tmp_path / "p.json", range(1, 3))


def test_error_frames_beyond_file_and_missing_file(tmp_path):
    save_params(tmp_path / "p.npz", make_params(3))
    with pytest.raises(NodeError, match=r"frame 4 \(file '.*p\.npz'\).*has 3 frame"):
        load_params(tmp_path / "p.npz", range(2, 5))
    with pytest.raises(NodeError, match=r"file '.*none\.json': expected a rigid sequence, found it "
                                        r"missing"):
        load_rigid(tmp_path / "none.json", range(0, 1))


def test_error_unknown_extension(tmp_path):
    with pytest.raises(NodeError, match=r"'path'.*\.json or \.npz, found '.*r\.csv'"):
        run_node(SaveRigidSequence, {"path": str(tmp_path / "r.csv")}, rigid=make_rigid(2))
