"""Mesh geometry shared by the areas: area-weighted vertex normals, edges of a triangle mesh (or a
k-nearest-neighbour graph of a point set), the uniform graph Laplacian over them, and each
triangle's neighbours across its edges. numpy / scipy;
pure functions. (The renderer's differentiable torch normals live in nodes/render/renderer.py.)"""

from __future__ import annotations

import numpy as np

__all__ = ["vertex_normals", "vertex_neighbours", "uniform_laplacian", "triangle_adjacency"]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Return area-weighted unit vertex normals.

    Args:
        vertices: (V, 3) float, cm.
        faces: (T, 3) int vertex indices, counter-clockwise seen from outside.
    Returns:
        (V, 3) float64 unit normals; zero rows for vertices in no face (or only in
        zero-area faces).
    """
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices: expected shape (V, 3), found {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (T, 3), found {faces.shape}")
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    face_n = np.cross(b - a, c - a)  # length = 2 * area: area weighting for free
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face_n)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)


def vertex_neighbours(rest: np.ndarray, faces: np.ndarray, *, k: int = 6) -> np.ndarray:
    """Undirected edges: the mesh edges, or a k-nearest-neighbour graph for a point set.

    Args:
        rest: (V, 3) positions, cm (used only when `faces` is empty).
        faces: (T, 3) int triangles; (0, 3) for a point set.
        k: neighbours per point for a point set.
    Returns:
        (E, 2) int64 unique edges (i < j), sorted.
    """
    faces = np.asarray(faces)
    if faces.size:
        edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    else:
        from scipy.spatial import cKDTree

        count = min(k + 1, len(rest))
        _, idx = cKDTree(np.asarray(rest, np.float64)).query(rest, count)
        edges = np.stack([np.repeat(np.arange(len(rest)), count - 1), idx[:, 1:].reshape(-1)], 1)
    edges = np.sort(edges.astype(np.int64), axis=1)
    edges = edges[edges[:, 0] != edges[:, 1]]
    return np.unique(edges, axis=0)


def uniform_laplacian(edges: np.ndarray, count: int):
    """Return `L = I - Deg^-1 A` (scipy.sparse csr, (V, V)) of undirected edges (E, 2)."""
    from scipy import sparse

    i, j = edges[:, 0], edges[:, 1]
    adj = sparse.csr_matrix((np.ones(2 * len(edges)), (np.concatenate([i, j]), np.concatenate([j, i]))),
                            shape=(count, count))
    degree = np.asarray(adj.sum(axis=1)).ravel()
    inv = sparse.diags(np.where(degree > 0, 1.0 / np.maximum(degree, 1e-12), 0.0))
    return (sparse.identity(count, format="csr") - inv @ adj).tocsr()


def triangle_adjacency(faces: np.ndarray) -> np.ndarray:
    """The neighbour of each triangle across each of its edges.

    Args:
        faces: (T, 3) int vertex indices.
    Returns:
        (T, 3) int64: entry [t, i] is the triangle sharing the edge opposite corner i (corners
        i + 1 and i + 2, mod 3), or -1 on a boundary. On a non-manifold edge (more than two
        triangles) the first two in face order are paired and the others see -1.

    Example:
        >>> triangle_adjacency(np.array([[0, 1, 2], [2, 1, 3]])).tolist()
        [[1, -1, -1], [-1, -1, 0]]
    """
    faces = np.asarray(faces, np.int64)
    t = len(faces)
    a = np.concatenate([faces[:, 1], faces[:, 2], faces[:, 0]])
    b = np.concatenate([faces[:, 2], faces[:, 0], faces[:, 1]])
    key = np.minimum(a, b) * (int(faces.max(initial=0)) + 1) + np.maximum(a, b)
    slot = np.arange(3 * t)  # slot s: triangle s % t, edge opposite corner s // t
    order = np.lexsort((slot, key))
    ks = key[order]
    adjacency = np.full(3 * t, -1, np.int64)
    first = np.ones(len(ks), bool)
    first[1:] = ks[1:] != ks[:-1]
    pair = np.flatnonzero(first[:-1] & (ks[1:] == ks[:-1]))  # the first two slots of each edge
    s0, s1 = order[pair], order[pair + 1]
    adjacency[s0] = s1 % t
    adjacency[s1] = s0 % t
    return adjacency.reshape(3, t).T.copy()
