"""A removal network records its region of the whole head: dynamics.RemoveDynamics then cleans a
whole-head capture (the region cut, cleaned, put back; the rest unchanged), and a capture of
neither topology is one clear error. Also: the propagation matrix is built once per mesh."""

from __future__ import annotations

import dataclasses
from functools import lru_cache

import numpy as np
import pytest

from nodegraph import InputError, MeshSequence, NodeError, run_node
from nodes.dynamics.evaluate import rms_distance
from nodes.dynamics.files import LoadModel
from nodes.dynamics.propagate import cached_interpolation_matrix, interpolation_matrix
from nodes.dynamics.removal import RemoveDynamics, TrainRemoval, locate_region, topology_problem
from nodes.geometry.mesh import vertex_neighbours
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import simulate_dynamics
from nodes.synth.performance import transform_points

from ._data import face_model, training_capture


@lru_cache(maxsize=None)
def head():
    return load_face_model()


def embed(region_mesh: MeshSequence, skull: np.ndarray, ids: np.ndarray) -> MeshSequence:
    """A whole-head capture: the region's frames at `ids`, the rest of the head rigid on the skull."""
    whole = head()
    rest = np.broadcast_to(whole.neutral, (region_mesh.num_frames,) + whole.neutral.shape)
    vertices = transform_points(skull, np.ascontiguousarray(rest)).astype(np.float32)
    vertices[:, ids] = region_mesh.vertices
    return MeshSequence(vertices=vertices, faces=whole.faces, fps=region_mesh.fps)


def test_locate_region_finds_a_subsample_in_any_order():
    whole, part = head(), face_model()
    ids = locate_region(part, whole)
    np.testing.assert_allclose(whole.neutral[ids], part.neutral, atol=1e-6)
    order = np.random.default_rng(0).permutation(len(part.neutral))
    shuffled = dataclasses.replace(part, neutral=part.neutral[order],
                                   identity_deltas=part.identity_deltas[:, order],
                                   expression_deltas=part.expression_deltas[:, order])
    np.testing.assert_array_equal(locate_region(shuffled, whole), ids[order])
    moved = dataclasses.replace(part, neutral=part.neutral + np.float32(0.01))
    with pytest.raises(InputError, match="region of the whole model"):
        locate_region(moved, whole)


def test_bundled_network_cleans_a_whole_head_capture_and_keeps_the_rest():
    face = load_face_model(region="face")
    ids = np.unique(head().groups["face"])
    test = simulate_dynamics(face, motions=["run"], expressions=["neutral"], segment_frames=150, fps=120.0,
                             seed=11, noise_cm=0.01)
    capture = embed(test.capture, test.skull.matrices, ids)
    model = run_node(LoadModel, {})["model"]
    assert model.config["region"] == "face" and int(model.config["whole_vertices"]) == len(head().neutral)
    out = run_node(RemoveDynamics, capture=capture, skull=test.skull, model=model)
    quasi, offsets = out["quasistatic"].vertices, out["offsets"].vertices
    outside = np.setdiff1d(np.arange(capture.num_vertices), ids)
    np.testing.assert_array_equal(quasi[:, outside], capture.vertices[:, outside])
    assert not offsets[:, outside].any()
    # the same result as the network on the face region alone
    alone = run_node(RemoveDynamics, capture=test.capture, skull=test.skull, model=model)["quasistatic"]
    np.testing.assert_allclose(quasi[:, ids], alone.vertices, rtol=0, atol=1e-5)
    before = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    after = rms_distance(quasi[:, ids], test.quasistatic.vertices)
    assert after < 0.75 * before, (before, after)


def test_another_topology_is_one_clear_error():
    model = run_node(LoadModel, {})["model"]
    problem = topology_problem(model, 500)
    assert "9409 vertices: region 'face' of a 26719-vertex mesh" in problem
    assert "or of that whole 26719-vertex mesh" in problem and "found 500 vertices" in problem
    assert "mesh.SelectRegion (group 'face')" in problem and "dynamics_train_captures.json" in problem
    assert topology_problem(model, 9409) == topology_problem(model, 26719) == ""
    other = simulate_dynamics(face_model(300), motions=["still"], expressions=["neutral"], segment_frames=20,
                              fps=120.0, seed=1)
    with pytest.raises(NodeError, match="training topology.*found 300 vertices"):
        run_node(RemoveDynamics, capture=other.capture, skull=other.skull, model=model)


def test_trained_network_records_the_subsampled_region_and_cleans_the_whole_head():
    data = training_capture()  # 400 points of the face region
    out = run_node(TrainRemoval, {"num_samples": 100, "epochs": 8, "max_rows": 40000, "batch_size": 2000,
                                  "region_name": "face", "seed": 0},
                   frames=range(data.capture.num_frames), captures=[data.capture], skulls=[data.skull],
                   quasistatic=[data.quasistatic], segments=[data.segments], whole=head(),
                   region_model=face_model())
    model = out["model"]
    ids = model.normalization["region_ids"]
    np.testing.assert_array_equal(ids, locate_region(face_model(), head()))
    test = simulate_dynamics(face_model(), motions=["oscillate@9"], expressions=["neutral"], segment_frames=150,
                             fps=120.0, seed=5)
    whole = embed(test.capture, test.skull.matrices, ids)
    cleaned = run_node(RemoveDynamics, capture=whole, skull=test.skull, model=model)["quasistatic"]
    alone = run_node(RemoveDynamics, capture=test.capture, skull=test.skull, model=model)["quasistatic"]
    np.testing.assert_allclose(cleaned.vertices[:, ids], alone.vertices, rtol=0, atol=1e-5)
    before = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    after = rms_distance(cleaned.vertices[:, ids], test.quasistatic.vertices)
    assert after < 0.6 * before, (before, after)
    with pytest.raises(NodeError, match="both `whole` and `region_model`"):
        run_node(TrainRemoval, {"epochs": 1, "max_rows": 1000}, frames=range(data.capture.num_frames),
                 captures=[data.capture], skulls=[data.skull], quasistatic=[data.quasistatic], whole=head())


def test_propagation_matrix_is_built_once_and_matches():
    mesh = face_model()
    edges = vertex_neighbours(mesh.neutral, mesh.faces)
    samples = np.arange(0, len(mesh.neutral), 7)
    first = cached_interpolation_matrix(edges, len(mesh.neutral), samples)
    assert cached_interpolation_matrix(edges, len(mesh.neutral), samples.copy()) is first
    assert cached_interpolation_matrix(edges, len(mesh.neutral), samples, constraint_weight=10.0) is not first
    exact = interpolation_matrix(edges, len(mesh.neutral), samples)
    np.testing.assert_allclose(first, exact, rtol=0, atol=1e-6 * np.abs(exact).max())
    assert not first.flags.writeable
