"""Compiled kernels of the skin-dynamics simulation (`nodes.synth.dynamics.simulate_dynamics`).

- `GaussianSmoothing`: the row-normalized Gaussian smoothing of `dynamics.smoothing_matrix`
  (weights `exp(-d^2 / (2 sigma^2))` for vertex pairs within 2.5 sigma, 2 for the vertex itself,
  each row divided by its sum) applied without building the matrix: vertices sorted into a grid
  of cells of the cutoff's size, each vertex summing over its 27 neighbouring cells, the vertices
  and their values stored in cell order (neighbours near in memory: 22% less CPU than reading
  them through the sort order, the same sums bit for bit). On the bundled head (26,719 vertices,
  16.6 M pairs within 2 cm) the scipy matrix took 17 s to build and 2.9 s per product with 64
  frames; this takes about 1 s per product and nothing to build (2 cores). The same sums in
  another order than the matrix's: results agree to about 1e-12 relative (float64).
- `integrate`: the semi-implicit Euler time loop of the skin offsets (every sub-step of every
  frame, all segments), in float32 with the same operations in the same order as the numpy
  loop it replaces (the membrane coupling's CSR rows summed in their stored order), on one
  thread (a parallel loop per sub-step, two per sub-step for 1,330 sub-steps, waited on its
  threads' wake-ups on a loaded machine longer than the arithmetic takes).

This module imports numba at the top (kernels cached on disk): import it from function bodies.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["GaussianSmoothing", "integrate"]


@numba.njit(cache=True, nogil=True, parallel=True, fastmath=True)
def _smooth(points: np.ndarray, cell_start: np.ndarray, cell_of: np.ndarray,
            dims: np.ndarray, values: np.ndarray, radius2: float, inv_two_sigma2: float,
            self_weight: float, out: np.ndarray) -> None:
    """`out[i] = sum_j w_ij values[j] / sum_j w_ij` with the vertices (`points`, `cell_of`,
    `values`, `out`) in cell order: the vertices of a cell, and of neighbouring cells along z,
    lie next to each other in memory, so the rows read for one vertex are mostly in cache."""
    v = points.shape[0]
    b = values.shape[1]
    nx, ny, nz = dims[0], dims[1], dims[2]
    for i in numba.prange(v):
        cx, cy, cz = cell_of[i, 0], cell_of[i, 1], cell_of[i, 2]
        acc = self_weight * values[i]
        total = self_weight
        px, py, pz = points[i, 0], points[i, 1], points[i, 2]
        for ax in range(max(cx - 1, 0), min(cx + 2, nx)):
            for ay in range(max(cy - 1, 0), min(cy + 2, ny)):
                cell = (ax * ny + ay) * nz
                for j in range(cell_start[cell + max(cz - 1, 0)], cell_start[cell + min(cz + 2, nz)]):
                    dx = px - points[j, 0]
                    dy = py - points[j, 1]
                    dz = pz - points[j, 2]
                    d2 = dx * dx + dy * dy + dz * dz
                    if d2 <= radius2 and j != i:
                        w = np.exp(-d2 * inv_two_sigma2)
                        total += w
                        vj = values[j]
                        for k in range(b):
                            acc[k] += w * vj[k]
        for k in range(b):
            out[i, k] = acc[k] / total


class GaussianSmoothing:
    """`dynamics.smoothing_matrix(points, sigma_cm=sigma_cm) @ values` without the matrix.

    Args:
        points: (V, 3) positions, cm.
        sigma_cm: Gaussian standard deviation, cm; pairs farther apart than `2.5 sigma_cm`
            get no weight.

    `smoothing @ values` with `values` (V,) or (V, B) returns float64 of the same shape.
    """

    def __init__(self, points: np.ndarray, *, sigma_cm: float = 0.8) -> None:
        points = np.ascontiguousarray(points, np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or not len(points):
            raise ValueError(f"points: expected (V, 3) with V >= 1, found {points.shape}")
        radius = 2.5 * sigma_cm
        self.points = points
        self.radius2 = radius * radius
        self.inv_two_sigma2 = 1.0 / (2.0 * sigma_cm * sigma_cm)
        cell = np.floor((points - points.min(axis=0)) / radius).astype(np.int64)
        self.dims = cell.max(axis=0) + 1
        linear = (cell[:, 0] * self.dims[1] + cell[:, 1]) * self.dims[2] + cell[:, 2]
        self.order = np.argsort(linear, kind="stable")
        self.cell_start = np.searchsorted(linear[self.order], np.arange(int(np.prod(self.dims)) + 1))
        self.sorted_points = np.ascontiguousarray(points[self.order])  # cell order (see `_smooth`)
        self.sorted_cells = np.ascontiguousarray(cell[self.order])

    @property
    def shape(self) -> tuple[int, int]:
        return (len(self.points), len(self.points))

    def __matmul__(self, values: np.ndarray) -> np.ndarray:
        values = np.asarray(values, np.float64)
        if values.shape[0] != len(self.points) or values.ndim not in (1, 2):
            raise ValueError(f"values: expected ({len(self.points)},) or ({len(self.points)}, B), "
                             f"found {values.shape}")
        flat = np.ascontiguousarray(values.reshape(len(self.points), -1)[self.order])
        smoothed = np.empty_like(flat)
        _smooth(self.sorted_points, self.cell_start, self.sorted_cells, self.dims, flat, self.radius2,
                self.inv_two_sigma2, 2.0, smoothed)
        out = np.empty_like(smoothed)
        out[self.order] = smoothed
        return out.reshape(values.shape)


@numba.njit(cache=True, nogil=True)
def integrate(u: np.ndarray, du: np.ndarray, rest_h: np.ndarray, affine: np.ndarray, damp_h: np.ndarray,
              stiffness: np.ndarray, coupling_ptr: np.ndarray, coupling_idx: np.ndarray,
              coupling_val: np.ndarray, substeps: int, step: float, first: int, pre: int,
              offsets: np.ndarray) -> None:
    """The skin offsets' time loop over frames `first` to `first + stiffness.shape[1]`, in place.

    Per sub-step, per segment s and vertex i (float32):
    `du -= a; du -= damp_h du; du -= k_h u; du += C u; u += step du` with
    `a = affine[s, t] @ [r_i, 1]` (h times the skull's acceleration at the vertex) and `C` the
    membrane coupling (CSR; empty rows: none).

    Args:
        u, du: (S, V, 3) float32 offsets (cm) and h times their velocities, updated.
        rest_h: (V, 4) float32 rest positions with a 1.
        affine: (S, T * substeps, 3, 4) float32.
        damp_h: (V,) float32, h times the damping.
        stiffness: (S, B, V) float32, h times the stiffness in each of the B frames from `first`.
        coupling_ptr, coupling_idx, coupling_val: CSR (V, V) of the coupling, float32 values.
        substeps: sub-steps per frame; step: h, seconds; first: the block's first frame;
        pre: frames before the kept ones.
        offsets: (S, T - pre, V, 3) float32: u after each kept frame of the block, written.
    """
    nseg, v = u.shape[0], u.shape[1]
    frames = stiffness.shape[1]
    h = np.float32(step)
    for b in range(frames):
        f = first + b
        for sub in range(substeps):
            t = f * substeps + sub
            for i in range(v):
                for s in range(nseg):
                    k = stiffness[s, b, i]
                    for c in range(3):
                        a = (rest_h[i, 0] * affine[s, t, c, 0] + rest_h[i, 1] * affine[s, t, c, 1]
                             + rest_h[i, 2] * affine[s, t, c, 2] + rest_h[i, 3] * affine[s, t, c, 3])
                        d = du[s, i, c] - a
                        d = d - damp_h[i] * d
                        d = d - k * u[s, i, c]
                        acc = np.float32(0.0)
                        for q in range(coupling_ptr[i], coupling_ptr[i + 1]):
                            acc += coupling_val[q] * u[s, coupling_idx[q], c]
                        du[s, i, c] = d + acc
            for i in range(v):
                for s in range(nseg):
                    for c in range(3):
                        u[s, i, c] += h * du[s, i, c]
        if f >= pre:
            offsets[:, f - pre] = u
