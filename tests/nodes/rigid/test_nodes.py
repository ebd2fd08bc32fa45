"""Tests of the rigid-stabilization nodes: ReferenceFrame, ThreePoint, Procrustes, ICP."""

import dataclasses
import doctest

import numpy as np
import pytest
import trimesh
from scipy.linalg import orthogonal_procrustes
from scipy.spatial.transform import Rotation

from nodegraph import MeshSequence, NodeError, run_node
from nodes.geometry.rigid import apply_rigid, invert_rigid, rigid_matrix, rotation_angle
from nodes.rigid import (ICP, Procrustes, ReferenceFrame, ThreePoint, spread_triple, three_point_frames,
                         triangle_quality)

BASELINES = [ThreePoint, Procrustes, ICP]


def _head():
    """A bumpy ellipsoid head (cm) with 'rigid' (upper front) and 'jaw' groups."""
    sphere = trimesh.creation.icosphere(subdivisions=3)
    v = sphere.vertices * [7.5, 10.0, 9.0]
    radial = v / np.linalg.norm(v, axis=1, keepdims=True)
    bumps = sum(h * np.exp(-((v - c) ** 2).sum(1) / (2 * w ** 2))
                for c, w, h in [([0, 1, 9], 1.5, 2.0), ([3, 4, 8], 2.0, 0.8),
                                ([-3, 4, 8], 2.0, 0.8), ([5, -2, 6], 1.5, 0.6)])
    v = v + radial * bumps[:, None]
    groups = {"rigid": np.flatnonzero((v[:, 1] > -1) & (v[:, 2] > 2)).astype(np.int32),
              "jaw": np.flatnonzero((v[:, 1] < -3) & (v[:, 2] > 0)).astype(np.int32)}
    return v, np.asarray(sphere.faces, np.int32), groups


def _capture(num_frames=10, seed=0, max_deg=15.0, noise_cm=0.0, faces=True):
    """World meshes m_f (S_f) (+ noise) with jaw-only expression; returns mesh, m, S, rest."""
    rng = np.random.default_rng(seed)
    v, f, groups = _head()
    axis = rng.normal(size=(num_frames, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    rot = Rotation.from_rotvec(axis * np.deg2rad(rng.uniform(0, max_deg, (num_frames, 1))))
    truth = rigid_matrix(rot.as_matrix(), rng.uniform(-4, 4, (num_frames, 3)) + [0, 0, 50])
    skull = np.repeat(v[None], num_frames, 0)
    skull[:, groups["jaw"], 1] -= rng.uniform(0, 2, (num_frames, 1))  # jaw opens, cm
    world = apply_rigid(truth, skull) + rng.normal(0, noise_cm, skull.shape)
    mesh = MeshSequence(world.astype(np.float32), f if faces else np.zeros((0, 3), np.int32),
                        uv=rng.uniform(0, 1, (len(v), 2)).astype(np.float32), groups=groups,
                        fps=24.0)
    rest = dataclasses.replace(mesh, vertices=v[None].astype(np.float32))
    return mesh, truth, skull, rest


def _errors(estimate, truth, centre):
    rel = invert_rigid(truth) @ estimate
    moved = apply_rigid(rel, centre[None])[:, 0]
    return np.rad2deg(rotation_angle(rel[:, :3, :3])), np.linalg.norm(moved - centre, axis=1)


# -- pure helpers --------------------------------------------------------------------------
def test_three_point_frames_match_scipy_align_vectors():
    rng = np.random.default_rng(0)
    points = rng.normal(0, 5, (4, 3, 3))
    frames = three_point_frames(points)
    for k in range(4):
        a, b, c = points[k]
        # frame axes: e1 along b - a exactly, e2 in the plane towards c
        rot, _ = Rotation.align_vectors([b - a, c - a], [[1, 0, 0], [0, 1, 0]],
                                        weights=[np.inf, 1])
        np.testing.assert_allclose(frames[k, :3, :3], rot.as_matrix(), atol=1e-10)
        np.testing.assert_allclose(frames[k, :3, 3], points[k].mean(0), atol=1e-12)


def test_three_point_frames_reject_collinear_points():
    points = np.array([[[0., 0, 0], [1, 0, 0], [0, 1, 0]], [[0., 0, 0], [1, 1, 1], [2, 2, 2]]])
    np.testing.assert_allclose(triangle_quality(points), [0.5, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match=r"degenerate .*batch index \(1,\)"):
        three_point_frames(points)
    with pytest.raises(ValueError, match=r"degenerate .*batch index \(\)"):
        three_point_frames(points[1])  # a single (unbatched) triple


def test_rigid_nodes_docstring_examples():
    from nodes.rigid import nodes as rigid_nodes
    result = doctest.testmod(rigid_nodes)
    assert result.attempted > 0 and result.failed == 0


def test_spread_triple_picks_extremes():
    points = np.array([[0., 0, 0], [10, 0, 0], [1, 0, 0], [5, 4, 0], [5, 1, 0], [-0.5, 0, 0]])
    assert sorted(spread_triple(points)) == [1, 3, 5]


# -- ReferenceFrame ------------------------------------------------------------------------
def test_reference_frame_picks_an_absolute_frame():
    mesh, _, _, _ = _capture(5)
    out = run_node(ReferenceFrame, {"frame": 7}, frames=range(5, 10), mesh=mesh)["reference"]
    np.testing.assert_array_equal(out.vertices, mesh.vertices[2:3])
    np.testing.assert_array_equal(out.faces, mesh.faces)
    assert out.groups.keys() == mesh.groups.keys() and out.fps == 24.0


def test_reference_frame_defaults_to_the_runs_first_frame():
    mesh, _, _, _ = _capture(5)
    out = run_node(ReferenceFrame, {}, frames=range(5, 10), mesh=mesh)["reference"]
    np.testing.assert_array_equal(out.vertices, mesh.vertices[0:1])


def test_reference_frame_rejects_a_frame_outside_the_run():
    mesh, _, _, _ = _capture(5)
    with pytest.raises(NodeError, match=r"rigid.ReferenceFrame.*'frame': expected a frame in "
                                        r"5\.\.9 .*found 3"):
        run_node(ReferenceFrame, {"frame": 3}, frames=range(5, 10), mesh=mesh)


# -- baselines -----------------------------------------------------------------------------
@pytest.mark.parametrize("node", BASELINES)
def test_baseline_recovers_noise_free_motion(node):
    mesh, truth, skull, rest = _capture()
    out = run_node(node, {}, mesh=mesh, reference=rest)
    rot_deg, trans_cm = _errors(out["rigid"].matrices, truth, rest.vertices[0].mean(0))
    assert rot_deg.max() < 1e-3 and trans_cm.max() < 1e-3
    stabilized = out["stabilized"]
    assert stabilized.vertices.dtype == np.float32
    np.testing.assert_allclose(stabilized.vertices, skull, atol=2e-3)
    np.testing.assert_array_equal(stabilized.faces, mesh.faces)
    np.testing.assert_array_equal(stabilized.uv, mesh.uv)
    assert stabilized.fps == mesh.fps and stabilized.groups is mesh.groups


@pytest.mark.parametrize("node", BASELINES)
def test_baseline_is_the_same_whatever_the_chunk(node):
    mesh, _, _, _ = _capture(10, seed=1, noise_cm=0.03)
    reference = run_node(ReferenceFrame, {"frame": 0}, mesh=mesh)["reference"]
    whole = run_node(node, {}, mesh=mesh, reference=reference)
    parts = [run_node(node, {}, frames=range(a, b), mesh=mesh.slice_frames(a, b),
                      reference=reference) for a, b in [(0, 5), (5, 10)]]
    np.testing.assert_allclose(np.concatenate([p["rigid"].matrices for p in parts]),
                               whole["rigid"].matrices, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.concatenate([p["stabilized"].vertices for p in parts]),
                                  whole["stabilized"].vertices)


@pytest.mark.parametrize("group", ["rigid", ""])
def test_procrustes_matches_scipy_per_frame(group):
    mesh, _, _, rest = _capture(6, seed=2, noise_cm=0.05)
    out = run_node(Procrustes, {"group": group}, mesh=mesh, reference=rest)["rigid"].matrices
    idx = mesh.groups["rigid"] if group else np.arange(mesh.num_vertices)
    ref = rest.vertices[0, idx].astype(np.float64)
    for f in range(6):
        cur = mesh.vertices[f, idx].astype(np.float64)
        r_t, _ = orthogonal_procrustes(ref - ref.mean(0), cur - cur.mean(0))
        np.testing.assert_allclose(out[f, :3, :3], r_t.T, atol=1e-9)
        np.testing.assert_allclose(out[f, :3, 3], cur.mean(0) - r_t.T @ ref.mean(0), atol=1e-8)


def test_three_point_matches_scipy_align_vectors_with_explicit_vertices():
    mesh, _, _, rest = _capture(4, seed=3, noise_cm=0.05)
    chosen = [int(i) for i in mesh.groups["rigid"][[0, 40, 90]]]
    out = run_node(ThreePoint, {"vertices": chosen}, mesh=mesh, reference=rest)["rigid"].matrices
    ref = rest.vertices[0, chosen].astype(np.float64)
    for f in range(4):
        cur = mesh.vertices[f, chosen].astype(np.float64)
        rot, _ = Rotation.align_vectors([cur[1] - cur[0], cur[2] - cur[0]],
                                        [ref[1] - ref[0], ref[2] - ref[0]], weights=[np.inf, 1])
        np.testing.assert_allclose(out[f, :3, :3], rot.as_matrix(), atol=1e-9)
        np.testing.assert_allclose(out[f, :3, 3], cur.mean(0) - rot.apply(ref.mean(0)), atol=1e-8)


def test_region_fits_beat_three_points_under_noise():
    mesh, truth, _, rest = _capture(20, seed=4, noise_cm=0.05)
    centre = rest.vertices[0].mean(0)
    rot = {node.__name__: _errors(run_node(node, {}, mesh=mesh, reference=rest)["rigid"].matrices,
                                  truth, centre)[0] for node in BASELINES}
    assert np.median(rot["Procrustes"]) < 0.2 and np.median(rot["ICP"]) < 0.6
    assert np.median(rot["ThreePoint"]) > 1.5 * np.median(rot["Procrustes"])


def test_icp_without_faces_falls_back_to_point_to_point():
    mesh, truth, _, rest = _capture(5, seed=5, max_deg=3.0, faces=False)
    out = run_node(ICP, {"iterations": 100, "tolerance_cm": 1e-8}, mesh=mesh, reference=rest)
    rot_deg, trans_cm = _errors(out["rigid"].matrices, truth, rest.vertices[0].mean(0))
    assert rot_deg.max() < 1e-3 and trans_cm.max() < 1e-3


def test_icp_target_group_restricts_the_surface():
    mesh, truth, _, rest = _capture(5, seed=6)
    out = run_node(ICP, {"target_group": "rigid"}, mesh=mesh, reference=rest)
    rot_deg, _ = _errors(out["rigid"].matrices, truth, rest.vertices[0].mean(0))
    assert rot_deg.max() < 1e-3


def test_icp_workers_do_not_enter_the_cache_key():
    assert ICP({"workers": 4}).key_params() == ICP({}).key_params()
    assert ICP({"robust_scale_cm": 0.5}).key_params() != ICP({}).key_params()


# -- bad input -----------------------------------------------------------------------------
@pytest.mark.parametrize("node, params, match", [
    (Procrustes, {"group": "nope"}, r"'group': expected a vertex group 'nope'.*found groups "
                                    r"\['jaw', 'rigid'\]"),
    (ICP, {"group": "nope"}, r"'group': expected a vertex group 'nope'"),
    (ICP, {"target_group": "nope"}, r"'target_group': expected a vertex group 'nope'"),
    (ThreePoint, {"vertices": [0, 1, 100000]}, r"'vertices': expected indices in 0\.\.641"),
    (ThreePoint, {"vertices": [0, 1, 1]}, r"'vertices': expected three distinct"),
    (ThreePoint, {"vertices": [0, 1]}, r"'vertices': expected three distinct"),
])
def test_nodes_reject_bad_params(node, params, match):
    mesh, _, _, rest = _capture(3)
    with pytest.raises(NodeError, match=f"{node.type_name}.*{match}") as info:
        run_node(node, params, mesh=mesh, reference=rest)
    assert info.value.bad_input


@pytest.mark.parametrize("node", BASELINES)
def test_nodes_reject_a_bad_reference(node):
    mesh, _, _, rest = _capture(3)
    two = dataclasses.replace(rest, vertices=np.repeat(rest.vertices, 2, 0))
    with pytest.raises(NodeError, match=r"'reference': expected a one-frame mesh .*found 2 frames"):
        run_node(node, {}, mesh=mesh, reference=two)
    fewer = MeshSequence(rest.vertices[:, :100].copy())
    with pytest.raises(NodeError, match=r"'reference': expected 642 vertices .*found 100"):
        run_node(node, {}, mesh=mesh, reference=fewer)


def test_three_point_needs_a_rigid_group_when_vertices_are_empty():
    mesh, _, _, rest = _capture(3)
    mesh = dataclasses.replace(mesh, groups={"jaw": mesh.groups["jaw"]})
    with pytest.raises(NodeError, match=r"'vertices': is empty.*groups \['jaw'\]"):
        run_node(ThreePoint, {}, mesh=mesh, reference=rest)


def test_three_point_rejects_degenerate_triples():
    mesh, _, _, rest = _capture(4)
    verts = rest.vertices.copy()
    verts[0, 2] = (verts[0, 0] + verts[0, 1]) / 2  # vertex 2 on the segment 0-1
    flat = dataclasses.replace(rest, vertices=verts)
    with pytest.raises(NodeError, match=r"'vertices': vertices \[0, 1, 2\] on the reference: "
                                        r".*degenerate"):
        run_node(ThreePoint, {"vertices": [0, 1, 2]}, mesh=mesh, reference=flat)
    moving = mesh.vertices.copy()
    moving[2, 2] = moving[2, 0]  # coincident in frame 2 (absolute 12)
    mesh = dataclasses.replace(mesh, vertices=moving)
    with pytest.raises(NodeError, match=r"'mesh': .*degenerate .* at frame 12"):
        run_node(ThreePoint, {"vertices": [0, 1, 2]}, frames=range(10, 14), mesh=mesh,
                 reference=rest)
