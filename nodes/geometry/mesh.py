"""Mesh connectivity shared by the areas: edges of a triangle mesh (or a k-nearest-neighbour graph of
a point set) and the uniform graph Laplacian over them. numpy / scipy; pure functions."""

from __future__ import annotations

import numpy as np

__all__ = ["vertex_neighbours", "uniform_laplacian"]


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
