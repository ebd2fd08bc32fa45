"""mesh.SelectRegion / mesh.ReplaceRegion: the region's topology is io.LoadFaceModel(region=...)'s,
replacing puts it back exactly, bad groups and sizes are named."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph.errors import NodeError
from nodegraph import MeshSequence, run_node
from nodes.io.face_model import load_face_model
from nodes.mesh.regions import ReplaceRegion, SelectRegion


def _mesh(frames: int = 3) -> MeshSequence:
    rng = np.random.default_rng(0)
    faces = np.array([[0, 1, 2], [1, 2, 3], [3, 4, 5], [0, 4, 5]], np.int32)
    verts = rng.normal(size=(frames, 6, 3)).astype(np.float32)
    uv = rng.uniform(size=(6, 2)).astype(np.float32)
    return MeshSequence(vertices=verts, faces=faces, uv=uv, groups={"part": np.array([3, 1, 2]), "all": np.arange(6)})


def test_select_keeps_inner_faces_and_reindexes_groups():
    mesh = _mesh()
    region = run_node(SelectRegion, {"group": "part"}, mesh=mesh)["region"]
    np.testing.assert_array_equal(region.vertices, mesh.vertices[:, [1, 2, 3]])
    np.testing.assert_array_equal(region.faces, [[0, 1, 2]])  # only face (1, 2, 3) is inside
    np.testing.assert_array_equal(region.uv, mesh.uv[[1, 2, 3]])
    np.testing.assert_array_equal(region.groups["all"], [0, 1, 2])
    np.testing.assert_array_equal(region.groups["part"], [2, 0, 1])


def test_select_matches_the_face_model_region():
    full = load_face_model()
    face = load_face_model(region="face")
    mesh = MeshSequence(vertices=full.neutral[None], faces=full.faces, groups=dict(full.groups))
    region = run_node(SelectRegion, {"group": "face"}, mesh=mesh)["region"]
    np.testing.assert_array_equal(region.vertices[0], face.neutral)
    np.testing.assert_array_equal(region.faces, face.faces)


def test_replace_round_trip():
    mesh = _mesh()
    region = run_node(SelectRegion, {"group": "part"}, mesh=mesh)["region"]
    moved = MeshSequence(vertices=region.vertices + 1.0, faces=region.faces, groups=region.groups)
    out = run_node(ReplaceRegion, {"group": "part"}, mesh=mesh, region=moved)["replaced"]
    want = mesh.vertices.copy()
    want[:, [1, 2, 3]] += 1.0
    np.testing.assert_array_equal(out.vertices, want)
    np.testing.assert_array_equal(out.faces, mesh.faces)


def test_errors_name_port_and_problem():
    mesh = _mesh()
    with pytest.raises(NodeError, match="'mesh': expected a mesh with a vertex group 'eyes'"):
        run_node(SelectRegion, {"group": "eyes"}, mesh=mesh)
    wrong = MeshSequence(vertices=np.zeros((3, 2, 3), np.float32))
    with pytest.raises(NodeError, match="expected 3 vertices"):
        run_node(ReplaceRegion, {"group": "part"}, mesh=mesh, region=wrong)
