"""nodes.geometry.mesh: vertex normals against a plain per-face loop (an independent reference) and a
sphere, whose normals are its positions; edges and the uniform Laplacian of a small mesh."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nodes.geometry.mesh import uniform_laplacian, vertex_neighbours, vertex_normals


def test_vertex_normals_match_a_float64_loop_and_a_sphere():
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    v = sphere.vertices * rng.uniform(0.8, 1.2, (len(sphere.vertices), 1))  # a lumpy closed surface
    f = sphere.faces
    expected = np.zeros_like(v)
    for a, b, c in f:  # accumulate area-weighted face normals
        n = np.cross(v[b] - v[a], v[c] - v[a])
        for i in (a, b, c):
            expected[i] += n
    expected /= np.linalg.norm(expected, axis=1, keepdims=True)
    np.testing.assert_allclose(vertex_normals(v, f), expected, atol=1e-12)  # float64, a few ulps of 1
    fine = trimesh.creation.icosphere(subdivisions=4)  # unit sphere: normal ~ position
    assert (vertex_normals(fine.vertices, fine.faces) * fine.vertices).sum(1).min() > 0.999


def test_vertex_normals_are_zero_for_unused_vertices_and_check_shapes():
    v = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]])
    normals = vertex_normals(v, np.array([[0, 1, 2]]))
    np.testing.assert_allclose(normals[:3], [[0, 0, 1]] * 3)
    np.testing.assert_array_equal(normals[3], 0)
    with pytest.raises(ValueError, match=r"vertices: expected shape \(V, 3\)"):
        vertex_normals(v[:, :2], np.array([[0, 1, 2]]))
    with pytest.raises(ValueError, match=r"faces: expected shape \(T, 3\)"):
        vertex_normals(v, np.array([0, 1, 2]))


def test_edges_and_uniform_laplacian_of_a_tetrahedron():
    v = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])
    edges = vertex_neighbours(v, f)
    assert edges.tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    lap = uniform_laplacian(edges, 4).toarray()
    np.testing.assert_allclose(lap, np.eye(4) - (1 - np.eye(4)) / 3)
    np.testing.assert_allclose(lap @ np.ones(4), 0, atol=1e-15)
