"""Tests of nodes.io.mesh (and the shared helpers of nodes.io._files)."""

from __future__ import annotations

import hashlib
import os
import zipfile

import numpy as np
import pytest
import trimesh

from nodegraph import InputError, MeshSequence, NodeError, run_node
from nodegraph.files import atomic_path, files_value
from nodes.io._files import expand_frame_pattern, find_frame_numbers, frame_token, read_npz_rows
from nodes.io.mesh import LoadMeshSequence, SaveMeshFrames, SaveMeshSequence, read_obj
from nodes.io.mesh_frame import fan_triangulate

FORMATS = ["face.%04d.obj", "face.####.ply", "seq.npz", "seq.usda", "seq.usdc"]


def make_mesh(frames: int = 6, *, face_varying: bool = False, seed: int = 0) -> MeshSequence:
    """An icosphere (162 vertices, radius 10 cm) jittered per frame, with uv and groups."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    rng = np.random.default_rng(seed)
    base = np.asarray(sphere.vertices, np.float32)
    vertices = base + rng.normal(scale=0.3, size=(frames, *base.shape)).astype(np.float32)
    faces = np.asarray(sphere.faces, np.int32)
    if face_varying:
        uv = rng.random((faces.size, 2)).astype(np.float32)
        uv_faces = np.arange(faces.size, dtype=np.int32).reshape(-1, 3)
    else:
        uv, uv_faces = rng.random((len(base), 2)).astype(np.float32), None
    groups = {"face": np.arange(0, 40), "left-eye": np.array([3, 7, 11])}
    return MeshSequence(vertices=vertices, faces=faces, uv=uv, uv_faces=uv_faces, groups=groups,
                        fps=24.0)


def save(mesh: MeshSequence, path: str, **params) -> dict:
    return run_node(SaveMeshSequence, {"path": path, **params}, mesh=mesh)


def load(path: str, frames: range | None = None, **params) -> MeshSequence:
    return run_node(LoadMeshSequence, {"path": path, **params}, frames=frames)["mesh"]


# -- _files helpers ------------------------------------------------------------------------

@pytest.mark.parametrize("pattern, expected", [
    ("a/face.%04d.obj", "a/face.0012.obj"), ("face.%d.obj", "face.12.obj"),
    ("face.####.ply", "face.0012.ply"), ("face.{frame:05d}.obj", "face.00012.obj"),
    ("face.{frame}.obj", "face.12.obj"), ("face.##.obj", "face.12.obj"),
])
def test_expand_frame_pattern_styles(pattern, expected):
    assert expand_frame_pattern(pattern, 12) == expected


def test_frame_token_plain_path_and_two_tokens():
    assert frame_token("seq.npz") is None
    with pytest.raises(InputError, match="one frame token.*found 2"):
        frame_token("take%02d/face.####.obj")


def test_find_frame_numbers_keeps_only_names_of_the_pattern(tmp_path):
    for name in ["f.0003.obj", "f.0010.obj", "f.00004.obj", "f.0005.ply", "g.0006.obj"]:
        (tmp_path / name).write_text("")
    assert find_frame_numbers(str(tmp_path / "f.%04d.obj")) == [3, 10]
    assert find_frame_numbers(str(tmp_path / "missing" / "f.%04d.obj")) == []


def test_atomic_path_leaves_target_untouched_on_error(tmp_path):
    target = tmp_path / "sub" / "out.txt"
    with atomic_path(target) as tmp:
        tmp.write_text("one")
    assert target.read_text() == "one"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("writer crashed")
    assert target.read_text() == "one"
    assert sorted(os.listdir(target.parent)) == ["out.txt"]


def test_files_value_hashes_a_rewritten_file_of_the_same_size(tmp_path):
    target = tmp_path / "out.txt"
    hashes = []
    for text in ("aaaa", "bbbb"):  # same size, possibly the same mtime tick
        with atomic_path(target) as tmp:
            tmp.write_text(text)
        hashes.append(files_value([target]).sha256[0])
    assert hashes == [hashlib.sha256(b"aaaa").hexdigest(), hashlib.sha256(b"bbbb").hexdigest()]
    assert files_value([target]).paths == [str(target)]


@pytest.mark.parametrize("compressed", [False, True])
def test_read_npz_rows_equals_full_load(tmp_path, compressed):
    data = np.random.default_rng(1).normal(size=(9, 5, 3)).astype(np.float32)
    path = tmp_path / "a.npz"
    (np.savez_compressed if compressed else np.savez)(path, x=data)
    with zipfile.ZipFile(path) as zf:
        assert (zf.getinfo("x.npy").compress_type == zipfile.ZIP_STORED) != compressed
    for start, stop in [(0, 9), (2, 5), (8, 9), (4, 4)]:
        np.testing.assert_array_equal(read_npz_rows(path, "x", start, stop), data[start:stop])


# -- pure functions ------------------------------------------------------------------------

def test_fan_triangulate_matches_loop_reference():
    counts = np.array([3, 5, 4, 3, 6])
    tris, start = [], 0
    for n in counts:
        tris += [[start, start + k, start + k + 1] for k in range(1, n - 1)]
        start += n
    np.testing.assert_array_equal(fan_triangulate(counts), np.array(tris))
    with pytest.raises(ValueError, match="found 2 at polygon 1"):
        fan_triangulate(np.array([3, 2]))


def test_read_obj_quads_negative_indices_and_seams(tmp_path):
    path = tmp_path / "quad.obj"
    path.write_text("o a\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\n"
                    "vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvt 0.5 0.5\nvn 0 0 1\n"
                    "g top\nusemtl skin\nf 1/1/1 2/2/1 3/3/1 4/4/1\nf -4/5/1 5/2/1 -3/3/1\n")
    mesh = read_obj(path)
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    np.testing.assert_array_equal(mesh.uv_faces, [[0, 1, 2], [0, 2, 3], [4, 1, 2]])
    assert mesh.vertices.dtype == np.float32 and mesh.vertices.shape == (5, 3)
    np.testing.assert_array_equal(mesh.uv[4], [0.5, 0.5])


# -- round trips -----------------------------------------------------------------------------

@pytest.mark.parametrize("name", FORMATS)
def test_round_trip_keeps_vertices_topology_uv(tmp_path, name):
    mesh = make_mesh()
    path = str(tmp_path / name)
    out = save(mesh, path, first_frame=1)["files"]
    assert len(out.paths) == (mesh.num_frames if "%" in name or "#" in name else 1)
    for p, digest in zip(out.paths, out.sha256):
        assert hashlib.sha256(open(p, "rb").read()).hexdigest() == digest
    back = load(path)
    assert back.num_frames == mesh.num_frames
    np.testing.assert_allclose(back.vertices, mesh.vertices, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_allclose(back.uv, mesh.uv, rtol=0, atol=1e-7)
    assert back.uv_faces is None
    if not name.endswith("ply"):  # PLY carries no vertex groups
        assert sorted(back.groups) == sorted(mesh.groups)
        for key, idx in mesh.groups.items():
            np.testing.assert_array_equal(back.groups[key], idx)
    else:
        assert back.groups == {}
    if name.endswith(("npz", "usda", "usdc")):
        assert back.fps == mesh.fps
    else:
        assert back.fps == 30.0


@pytest.mark.parametrize("name", ["face.%04d.obj", "seq.npz", "seq.usda"])
def test_round_trip_face_varying_uv(tmp_path, name):
    mesh = make_mesh(3, face_varying=True)
    save(mesh, str(tmp_path / name))
    back = load(str(tmp_path / name))
    assert back.num_vertices == mesh.num_vertices
    # compare uv per face corner (the indexing may differ, the corner values may not)
    np.testing.assert_allclose(back.uv[back.uv_faces], mesh.uv[mesh.uv_faces], atol=1e-7)
    np.testing.assert_array_equal(back.faces, mesh.faces)


@pytest.mark.parametrize("name", FORMATS)
def test_chunked_load_equals_full_load(tmp_path, name):
    mesh = make_mesh(7)
    path = str(tmp_path / name)
    save(mesh, path)
    full = load(path)
    for frames in [range(2, 5), range(0, 1), range(6, 7)]:
        part = load(path, frames)
        np.testing.assert_array_equal(part.vertices, full.vertices[frames.start:frames.stop])
        np.testing.assert_array_equal(part.faces, full.faces)


def test_usd_stage_metadata_and_time_samples(tmp_path):
    from pxr import Usd, UsdGeom

    mesh = make_mesh(4, face_varying=True)
    path = str(tmp_path / "seq.usda")
    run_node(SaveMeshSequence, {"path": path, "prim": "/scan/face"}, mesh=mesh, frames=range(10, 14))
    stage = Usd.Stage.Open(path)
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert stage.GetTimeCodesPerSecond() == 24.0
    geom = UsdGeom.Mesh(stage.GetPrimAtPath("/scan/face"))
    assert list(geom.GetPointsAttr().GetTimeSamples()) == [10.0, 11.0, 12.0, 13.0]
    st = UsdGeom.PrimvarsAPI(geom.GetPrim()).GetPrimvar("st")
    assert st.GetInterpolation() == UsdGeom.Tokens.faceVarying and st.IsIndexed()
    np.testing.assert_array_equal(np.asarray(geom.GetPointsAttr().Get(12.0)), mesh.vertices[2])


def test_usd_quads_in_meters_are_triangulated_moved_to_world_and_scaled(tmp_path):
    from pxr import Usd, UsdGeom, Vt

    path = str(tmp_path / "quad.usda")
    stage = Usd.Stage.CreateNew(path)
    UsdGeom.SetStageMetersPerUnit(stage, 1.0)
    UsdGeom.Xform.Define(stage, "/root").AddTranslateOp().Set((0.0, 0.0, 2.0))  # metres
    geom = UsdGeom.Mesh.Define(stage, "/root/quad")
    points = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float32)
    geom.CreateFaceVertexCountsAttr(Vt.IntArray([4]))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray([0, 1, 2, 3]))
    for t in range(3):
        geom.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(points + 0.5 * t), float(t))
    stage.Save()
    assert run_node(LoadMeshSequence, {"path": path}).keys() == {"mesh"}
    back = load(path, fps=48.0)
    np.testing.assert_array_equal(back.faces, [[0, 1, 2], [0, 2, 3]])
    np.testing.assert_allclose(back.vertices[2], (points + [1.0, 1.0, 3.0]) * 100.0, atol=1e-4)
    assert back.fps == 48.0  # no timeCodesPerSecond authored: the param applies


def test_first_frame_and_frame_count_of_numbered_files(tmp_path):
    mesh = make_mesh(5)
    save(mesh, str(tmp_path / "face.%04d.ply"), first_frame=101)
    node = LoadMeshSequence({"path": str(tmp_path / "face.%04d.ply")})
    assert node.frame_count() == 5
    assert [p.name for p in node.input_files()] == [f"face.{n:04d}.ply" for n in range(101, 106)]
    late = load(str(tmp_path / "face.%04d.ply"), first_frame=103)
    np.testing.assert_array_equal(late.vertices, mesh.vertices[2:])


def test_save_mesh_frames_writes_only_its_chunk(tmp_path):
    mesh = make_mesh(6)
    pattern = str(tmp_path / "out" / "face.{frame:03d}.obj")
    chunk = mesh.slice_frames(2, 4)
    files = run_node(SaveMeshFrames, {"path": pattern, "first_frame": 1}, mesh=chunk,
                     frames=range(2, 4))["files"]
    assert files.paths == [str(tmp_path / "out" / "face.003.obj"), str(tmp_path / "out" / "face.004.obj")]
    assert sorted(os.listdir(tmp_path / "out")) == ["face.003.obj", "face.004.obj"]
    back = load(pattern)
    np.testing.assert_array_equal(back.vertices, mesh.vertices[2:4])


# -- bad input -------------------------------------------------------------------------------

def _write_numbered(tmp_path, ext="obj", frames=4) -> tuple[MeshSequence, str]:
    mesh = make_mesh(frames)
    pattern = str(tmp_path / f"face.%04d.{ext}")
    save(mesh, pattern, first_frame=1)
    return mesh, pattern


def test_error_missing_frame_names_file_and_frame(tmp_path):
    _, pattern = _write_numbered(tmp_path)
    os.remove(expand_frame_pattern(pattern, 3))
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*face\.0003\.obj'\).*missing") as err:
        load(pattern)
    assert err.value.bad_input and err.value.port == "path"
    load(pattern, range(2, 2 + 0))  # an empty chunk reads no frame file but frame 0's


def test_error_vertex_count_differs_from_frame_0(tmp_path):
    mesh, pattern = _write_numbered(tmp_path, "ply")
    sphere = trimesh.creation.icosphere(subdivisions=1)
    sphere.export(expand_frame_pattern(pattern, 4))
    with pytest.raises(NodeError, match=r"frame 3 \(file '.*face\.0004\.ply'\): expected 162 "
                                        r"vertices as in frame 0 .*found 42"):
        load(pattern, range(2, 4))


def test_error_topology_differs_from_frame_0(tmp_path):
    mesh, pattern = _write_numbered(tmp_path)
    faces = mesh.faces.copy()
    faces[5] = faces[5, ::-1]
    from nodes.io.mesh import write_obj
    write_obj(expand_frame_pattern(pattern, 2), mesh.vertices[1], faces, mesh.uv)
    with pytest.raises(NodeError, match=r"frame 1 \(file '.*face\.0002\.obj'\).*different "
                                        r"topology \(first different face 5\)"):
        load(pattern)


def test_error_truncated_ply_names_file_and_frame(tmp_path):
    _, pattern = _write_numbered(tmp_path, "ply")
    file = expand_frame_pattern(pattern, 2)
    data = open(file, "rb").read()
    open(file, "wb").write(data[: len(data) // 2])
    with pytest.raises(NodeError, match=r"frame 1 \(file '.*face\.0002\.ply'\)"):
        load(pattern)


def test_error_nan_vertex_names_file_frame_and_vertex(tmp_path):
    mesh, pattern = _write_numbered(tmp_path)
    vertices = mesh.vertices[2].copy()
    vertices[17, 1] = np.nan
    from nodes.io.mesh import write_obj
    write_obj(expand_frame_pattern(pattern, 3), vertices, mesh.faces)
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*face\.0003\.obj'\).*NaN/inf at vertex 17"):
        load(pattern)


def test_error_nan_in_npz_names_frame(tmp_path):
    mesh = make_mesh(5)
    mesh.vertices[3, 9, 0] = np.nan
    path = str(tmp_path / "seq.npz")
    np.savez(path, vertices=mesh.vertices, faces=mesh.faces)
    with pytest.raises(NodeError, match=r"frame 3 \(file '.*seq\.npz'\).*vertex 9"):
        load(path, range(2, 5))


def test_error_truncated_npz_and_usd(tmp_path):
    mesh = make_mesh(3)
    for name in ["seq.npz", "seq.usdc"]:
        path = str(tmp_path / name)
        save(mesh, path)
        data = open(path, "rb").read()
        open(path, "wb").write(data[: len(data) // 3])
        with pytest.raises(NodeError, match=rf"file '.*{name}'.*unreadable or truncated"):
            load(path)


def test_error_npz_without_vertices_lists_keys(tmp_path):
    path = str(tmp_path / "seq.npz")
    np.savez(path, points=np.zeros((2, 3, 3), np.float32))
    with pytest.raises(NodeError, match=r"expected an array 'vertices'.*found keys \['points'\]"):
        load(path)


def test_error_unknown_extension_and_single_obj(tmp_path):
    with pytest.raises(NodeError, match=r"'path'.*expected an extension among.*found '\.stl'"):
        load(str(tmp_path / "face.%04d.stl"))
    with pytest.raises(NodeError, match="expected a numbered pattern"):
        save(make_mesh(2), str(tmp_path / "face.obj"))


def test_error_no_files_match_pattern(tmp_path):
    with pytest.raises(NodeError, match=r"expected files matching '.*face\.%04d\.obj', found none"):
        load(str(tmp_path / "face.%04d.obj"))


def test_error_frames_beyond_npz_length(tmp_path):
    path = str(tmp_path / "seq.npz")
    save(make_mesh(3), path)
    with pytest.raises(NodeError, match=r"frame 4 \(file '.*seq\.npz'\).*has 3 frame"):
        load(path, range(2, 5))


def test_error_usd_prim_is_not_a_mesh(tmp_path):
    path = str(tmp_path / "seq.usda")
    save(make_mesh(2), path, prim="/root/mesh")
    with pytest.raises(NodeError, match=r"'prim'.*expected a UsdGeom.Mesh at '/root', found"):
        load(path, prim="/root")
    np.testing.assert_array_equal(load(path, prim="/root/mesh").faces, make_mesh(2).faces)


def test_error_face_varying_uv_to_ply(tmp_path):
    with pytest.raises(NodeError, match="PLY stores per-vertex uv only") as err:
        save(make_mesh(2, face_varying=True), str(tmp_path / "face.%04d.ply"))
    assert err.value.port == "mesh"
    assert not os.listdir(tmp_path)


# -- vertex groups ---------------------------------------------------------------------------

def test_obj_g_lines_give_vertex_groups(tmp_path):
    """A foreign OBJ (no #vg lines): a group's vertices are its faces' corners; a face under
    `g a b` is in both; `g default` and faces before any `g` are in none."""
    path = tmp_path / "groups.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
                    "f 1 2 3\ng cheek skin\nf 2 5 6\ng default\nf 1 3 4\ng skin\nf 3 2 6\n")
    mesh = read_obj(path)
    assert sorted(mesh.groups) == ["cheek", "skin"]
    np.testing.assert_array_equal(mesh.groups["cheek"], [1, 4, 5])
    np.testing.assert_array_equal(mesh.groups["skin"], [1, 2, 4, 5])


def test_obj_group_written_exactly_and_face_order_kept(tmp_path):
    mesh = make_mesh(2)
    mesh.groups["one"] = np.array([17])  # a single vertex: no face holds it, #vg keeps it
    mesh.groups["cap"] = np.unique(mesh.faces[:4])
    save(mesh, str(tmp_path / "f.%02d.obj"))
    text = (tmp_path / "f.00.obj").read_text()
    assert "#vg one 18\n" in text and "\ng cap\n" in text
    back = load(str(tmp_path / "f.%02d.obj"))
    np.testing.assert_array_equal(back.faces, mesh.faces)
    np.testing.assert_array_equal(back.groups["one"], [17])
    np.testing.assert_array_equal(back.groups["face"], mesh.groups["face"])


def test_obj_group_name_with_space_is_refused(tmp_path):
    mesh = make_mesh(1)
    mesh.groups["left eye"] = np.array([1, 2])
    with pytest.raises(NodeError, match="group names OBJ can hold.*left eye"):
        save(mesh, str(tmp_path / "f.%02d.obj"))
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("name", ["seq.npz", "seq.usda", "face.%04d.obj"])
def test_select_region_on_a_loaded_capture(tmp_path, name):
    """Groups survive the file, so mesh.SelectRegion cuts the region of a loaded capture."""
    from nodes.mesh.regions import SelectRegion

    mesh = make_mesh(3)
    save(mesh, str(tmp_path / name))
    region = run_node(SelectRegion, {"group": "face"}, mesh=load(str(tmp_path / name)))["region"]
    np.testing.assert_allclose(region.vertices, mesh.vertices[:, :40], rtol=0, atol=1e-6)
