"""Tests of nodes/io/face_model.py against the bundled ICT-FaceKit file read directly."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from nodegraph import FaceModel, NodeError, run_node
from nodes.io.face_model import (LoadFaceModel, bundled_model_path, load_face_model, restrict_face_model,
                                 triangulate_polygons)


@pytest.fixture(scope="module")
def raw() -> dict[str, np.ndarray]:
    with np.load(bundled_model_path(), allow_pickle=False) as data:
        return {k: data[k] for k in data.files}


@pytest.fixture(scope="module")
def full() -> FaceModel:
    return load_face_model()


@pytest.fixture(scope="module")
def face() -> FaceModel:
    return load_face_model(region="face")


def _face_rows(faces: np.ndarray) -> set[tuple[int, int, int]]:
    return set(map(tuple, faces.tolist()))


def test_load_face_model_ict_counts_and_dtypes(full, raw):
    assert full.neutral.shape == (26719, 3) and full.neutral.dtype == np.float32
    assert full.expression_deltas.shape == (53, 26719, 3) and full.expression_deltas.dtype == np.float32
    assert full.identity_deltas.shape == (40, 26719, 3) and full.identity_deltas.dtype == np.float32
    assert len(full.expression_names) == 53 and "jawOpen" in full.expression_names
    assert full.landmarks.shape == (68,)
    np.testing.assert_array_equal(full.landmarks, raw["landmarks68"])
    np.testing.assert_array_equal(full.expression_deltas, raw["expression_deltas"].astype(np.float32))
    full.validate()


def test_load_face_model_faces_match_file_triangles_and_uv(full, raw):
    np.testing.assert_array_equal(full.faces, raw["triangles"])
    assert full.uv_faces.shape == full.faces.shape
    assert full.uv.shape == raw["uv"].shape and full.uv_faces.max() < len(full.uv)
    # uv face corners follow polygon corners: the first quad's two triangles
    quad_uv = raw["polygon_uv"][0]
    np.testing.assert_array_equal(full.uv_faces[:2], [quad_uv[[0, 1, 2]], quad_uv[[0, 2, 3]]])


def test_triangulate_polygons_pads_and_order():
    polys = np.array([[0, 1, 2, 3], [4, 5, 6, -1], [7, 8, 9, 10]])
    expected = [[0, 1, 2], [0, 2, 3], [4, 5, 6], [7, 8, 9], [7, 9, 10]]
    assert triangulate_polygons(polys).tolist() == expected
    with pytest.raises(ValueError, match=r"polygons: expected shape \(P, 4\)"):
        triangulate_polygons(np.zeros((3, 3), int))


def test_load_face_model_groups_from_inclusive_ranges(full, raw):
    for name, (first, last) in zip(raw["group_names"].tolist(), raw["group_ranges"].tolist()):
        np.testing.assert_array_equal(full.groups[name], np.arange(first, last + 1))
    np.testing.assert_array_equal(full.groups["rigid"], raw["rigid_vertices"])
    np.testing.assert_array_equal(full.groups["fitting"], raw["fitting_vertices"])


def test_evaluate_numpy_matches_float64_reference_and_torch(face):
    rng = np.random.default_rng(0)
    w = rng.uniform(0, 1, (3, 53)).astype(np.float32)
    a = rng.standard_normal(40).astype(np.float32)
    reference = face.neutral.astype(np.float64)[None].repeat(3, 0)
    for k in range(53):
        reference += w[:, k, None, None].astype(np.float64) * face.expression_deltas[k]
    for i in range(40):
        reference += float(a[i]) * face.identity_deltas[i].astype(np.float64)
    out_np = face.evaluate(w, a)
    out_torch = face.evaluate(torch.from_numpy(w).double(), torch.from_numpy(a).double())
    np.testing.assert_allclose(out_np, reference, atol=2e-4)
    np.testing.assert_allclose(out_torch.numpy(), reference, atol=1e-9)


def test_evaluate_torch_is_differentiable(full):
    small = restrict_face_model(full, np.arange(0, 9000, 900))
    w = torch.rand(1, 53, dtype=torch.float64, requires_grad=True)
    a = torch.randn(40, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda w_, a_: small.evaluate(w_, a_), (w, a))


def test_region_keeps_positions_faces_groups_landmarks(full, face):
    keep = full.groups["face"]
    np.testing.assert_array_equal(face.neutral, full.neutral[keep])
    np.testing.assert_array_equal(face.expression_deltas, full.expression_deltas[:, keep])
    # faces: exactly the full faces with all corners in the region, mapped back
    inside = np.isin(full.faces, keep).all(axis=1)
    assert len(face.faces) == int(inside.sum())
    assert _face_rows(keep[face.faces]) == _face_rows(full.faces[inside])
    np.testing.assert_array_equal(face.uv_faces, full.uv_faces[inside])
    # groups and landmarks map back to the full indices they had, those outside dropped
    for name, idx in full.groups.items():
        np.testing.assert_array_equal(keep[face.groups[name]], idx[np.isin(idx, keep)])
    np.testing.assert_array_equal(keep[face.landmarks], full.landmarks[np.isin(full.landmarks, keep)])
    assert len(face.groups["head_neck"]) == 0
    face.validate()


def test_region_drops_landmarks_outside(full):
    eye = load_face_model(region="eyeball_left")
    assert eye.neutral.shape[0] == len(full.groups["eyeball_left"])
    assert len(eye.landmarks) == int(np.isin(full.landmarks, full.groups["eyeball_left"]).sum())


def test_max_vertices_subset_is_spread_point_set(face):
    sub = load_face_model(region="face", max_vertices=300)
    assert sub.neutral.shape == (300, 3) and sub.faces.shape == (0, 3) and sub.uv is None
    dist, idx = cKDTree(face.neutral).query(sub.neutral)
    np.testing.assert_array_equal(dist, 0.0)  # kept vertices keep their positions
    np.testing.assert_array_equal(sub.expression_deltas, face.expression_deltas[:, idx])
    assert np.all(np.diff(idx) > 0)  # original order kept
    np.testing.assert_array_equal(idx[sub.landmarks], face.landmarks[np.isin(face.landmarks, idx)])
    # better spread than a random subset of the same size (covering radius)
    random = np.sort(np.random.default_rng(0).choice(len(face.neutral), 300, replace=False))
    cover_fps = cKDTree(sub.neutral).query(face.neutral)[0].max()
    cover_random = cKDTree(face.neutral[random]).query(face.neutral)[0].max()
    assert cover_fps < 0.7 * cover_random
    again = load_face_model(region="face", max_vertices=300)
    np.testing.assert_array_equal(again.neutral, sub.neutral)


def test_load_face_model_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere.npz"):
        load_face_model(str(tmp_path / "nothere.npz"))


def test_load_face_model_unknown_region_lists_known():
    with pytest.raises(ValueError, match=r"region: unknown group 'chin'.*'face'.*'rigid'"):
        load_face_model(region="chin")


def test_load_face_model_file_missing_arrays(tmp_path, raw):
    path = tmp_path / "partial.npz"
    np.savez(path, **{k: v for k, v in raw.items() if k not in ("expression_deltas", "identity_deltas")})
    with pytest.raises(ValueError, match=r"lacks the array\(s\) \['expression_deltas', 'identity_deltas'\]"):
        load_face_model(str(path))


def test_load_face_model_unreadable_file(tmp_path):
    for name, content in (("empty.npz", b""), ("garbage.npz", b"PK\x03\x04 not a zip")):
        path = tmp_path / name
        path.write_bytes(content)
        with pytest.raises(ValueError, match=rf"path: '.*{name}' is not a readable .npz face model"):
            load_face_model(str(path))


def test_load_face_model_node_outputs_model():
    out = run_node(LoadFaceModel, {"region": "narrow_face", "max_vertices": 0})
    model = out["model"]
    assert isinstance(model, FaceModel) and model.neutral.shape[0] == 6706


def test_load_face_model_node_errors_name_param(tmp_path):
    with pytest.raises(NodeError, match=r"io.LoadFaceModel.*'region'.*known"):
        run_node(LoadFaceModel, {"region": "chin"})
    with pytest.raises(NodeError, match=r"io.LoadFaceModel.*'path'.*missing.npz"):
        run_node(LoadFaceModel, {"path": str(tmp_path / "missing.npz")})
    with pytest.raises(NodeError, match="max_vertices"):
        LoadFaceModel({"max_vertices": -1})


def test_load_face_model_cache_key_is_location_independent():
    node = LoadFaceModel({})
    assert node.key_params() == {"region": "", "max_vertices": 0}
    assert node.input_files() == [bundled_model_path()]
    assert str(bundled_model_path().parent) not in repr(node.key_params())
