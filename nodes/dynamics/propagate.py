"""Propagate offsets known at sample vertices to every vertex (Laplacian-regularized interpolation).

The full-mesh offsets `D` (V, 3) minimise `|L D|^2 + c sum_s |D_s - d_s|^2 + eps |D|^2`, with
`L = I - Deg^-1 A` the uniform graph Laplacian of the mesh edges (or of a k-nearest-neighbour
graph for a point set), `c` the constraint weight and `eps = 1e-6`: a smooth (biharmonic-like)
interpolation of the sample offsets `d`. The solution is linear in `d`: `D = W d` with the dense
interpolation matrix `W = (L^T L + c P^T P + eps I)^-1 c P^T` (V, N), computed once with one sparse
LU factorization (scipy.sparse) and then applied per frame (one product of fixed shape, so a
frame's result does not depend on the other frames of its chunk).
"""

from __future__ import annotations

import numpy as np

from ..geometry.mesh import uniform_laplacian

__all__ = ["interpolation_matrix", "propagate_offsets"]


def interpolation_matrix(edges: np.ndarray, count: int, samples: np.ndarray, *,
                         constraint_weight: float = 100.0, eps: float = 1e-6) -> np.ndarray:
    """Dense `W` (V, N) with full-mesh offsets `D = W d` from sample offsets `d` (N, 3).

    Args:
        edges: (E, 2) int undirected edges.
        count: V, number of vertices.
        samples: (N,) int vertex indices of the known offsets.
        constraint_weight: c, how strongly the result follows the samples (vs smoothness).
        eps: Tikhonov weight keeping vertices without edges determined.
    Returns:
        (V, N) float64.
    Raises:
        ValueError: sample indices outside 0..V-1.
    """
    from scipy import sparse
    from scipy.sparse.linalg import splu

    samples = np.asarray(samples, np.int64)
    if samples.size and (samples.min() < 0 or samples.max() >= count):
        raise ValueError(f"samples: expected vertex indices in 0..{count - 1}, found "
                         f"{int(samples.min())}..{int(samples.max())}")
    lap = uniform_laplacian(edges, count)
    pick = sparse.csr_matrix((np.ones(len(samples)), (np.arange(len(samples)), samples)),
                             shape=(len(samples), count))
    system = (lap.T @ lap + constraint_weight * (pick.T @ pick)
              + eps * sparse.identity(count)).tocsc()
    rhs = constraint_weight * pick.T.toarray()  # (V, N)
    return splu(system).solve(rhs)


def propagate_offsets(weights: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Apply `D_f = W d_f` frame by frame.

    Args:
        weights: (V, N) from `interpolation_matrix`.
        offsets: (F, N, 3) sample offsets, cm.
    Returns:
        (F, V, 3) float64, cm.
    """
    out = np.empty((len(offsets), weights.shape[0], 3))
    for f in range(len(offsets)):
        np.matmul(weights, offsets[f], out=out[f])
    return out
