"""B-spline curves over frames: basis by the Cox-de Boor recursion, midpoint refinement, fitting.

A curve over frames is `c(f) = sum_i B_i(x_f) P_i` with control points `P` of shape `(n, D)`.
Each frame touches only `degree + 1` consecutive control points, so a basis is stored banded:
`start` (F,) int64, the first control point index, and `weights` (F, degree + 1), the basis
values `B_{start}, ..., B_{start + degree}` at that frame.

Uniform frame splines (the case used for head motion) are cubic with knots every `spacing`
frames, `t_i = (i - 3) * spacing`, and `n = ceil((F - 1) / spacing) + 3` control points, so
frame 0 is at the start of the valid domain `[t_3, t_n]` and the last frame inside it.
Midpoint refinement (inserting a knot in the middle of every knot interval, the
Lane-Riesenfeld rule for cubics) halves the spacing and leaves the curve unchanged.

Reference: C. de Boor, "A Practical Guide to Splines", 1978; L. Piegl and W. Tiller, "The
NURBS Book", 1997 (algorithm A2.2).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

__all__ = [
    "SplineBasis", "bspline_basis", "uniform_knots", "num_control_points", "frame_basis",
    "evaluate_spline", "basis_matrix", "refine_midpoint", "fit_control_points",
]


class SplineBasis(NamedTuple):
    """Banded B-spline basis at sample points.

    Attributes:
        start: (N,) int64, index of the first control point touching each sample.
        weights: (N, degree + 1) basis values for control points `start .. start + degree`.
        num_control: number of control points n.
    """

    start: Tensor
    weights: Tensor
    num_control: int


def bspline_basis(x: Tensor, knots: Tensor, degree: int = 3) -> SplineBasis:
    """Evaluate the non-zero B-spline basis functions at `x` (Cox-de Boor recursion).

    `B_{i,0}(x) = 1 if t_i <= x < t_{i+1} else 0`,
    `B_{i,p}(x) = (x - t_i) / (t_{i+p} - t_i) B_{i,p-1}(x)
                 + (t_{i+p+1} - x) / (t_{i+p+1} - t_{i+1}) B_{i+1,p-1}(x)`,
    evaluated in the triangular, division-safe form of The NURBS Book's algorithm A2.2.

    Args:
        x: (N,) float parameters inside the valid domain `[t_p, t_n]` (the right end is
            assigned to the last interval).
        knots: (n + degree + 1,) non-decreasing knot vector.
        degree: spline degree p >= 0.
    Returns:
        SplineBasis with weights (N, p + 1) in `x`'s dtype.
    Raises:
        ValueError: when a parameter lies outside the domain or the knots are too few.
    """
    if degree < 0:
        raise ValueError(f"degree: expected >= 0, found {degree}")
    knots = knots.to(dtype=x.dtype, device=x.device)
    n = knots.numel() - degree - 1
    if n < degree + 1:
        raise ValueError(f"knots: expected at least {2 * degree + 2} knots for degree {degree}, "
                         f"found {knots.numel()}")
    lo, hi = knots[degree], knots[n]
    if x.numel() and (x.min() < lo or x.max() > hi):
        raise ValueError(f"x: expected values in the spline domain [{float(lo)}, {float(hi)}], "
                         f"found [{float(x.min())}, {float(x.max())}]")
    span = torch.searchsorted(knots, x.contiguous(), right=True) - 1
    span = span.clamp(degree, n - 1)
    basis = [torch.ones_like(x)]
    left = [None] + [x - knots[span + 1 - k] for k in range(1, degree + 1)]
    right = [None] + [knots[span + k] - x for k in range(1, degree + 1)]
    for k in range(1, degree + 1):
        saved = torch.zeros_like(x)
        new = []
        for r in range(k):
            denom = right[r + 1] + left[k - r]
            temp = basis[r] / torch.where(denom == 0, torch.ones_like(denom), denom)
            new.append(saved + right[r + 1] * temp)
            saved = left[k - r] * temp
        new.append(saved)
        basis = new
    return SplineBasis(span - degree, torch.stack(basis, dim=-1), n)


def uniform_knots(num_control: int, spacing: float, degree: int = 3, *,
                  dtype: torch.dtype = torch.float64, device: torch.device | str | None = None) -> Tensor:
    """Return the uniform knots `t_i = (i - degree) * spacing`, i = 0 .. n + degree.

    Args:
        num_control: number of control points n.
        spacing: knot spacing (frames).
        degree: spline degree.
    Returns:
        (n + degree + 1,) knots; the valid domain is `[0, (n - degree) * spacing]`.
    """
    i = torch.arange(num_control + degree + 1, dtype=dtype, device=device)
    return (i - degree) * spacing


def num_control_points(num_frames: int, spacing: float) -> int:
    """Return `n = max(ceil((F - 1) / spacing) + 3, 4)`: the cubic control points covering F frames.

    The last frame lies in the last knot interval (possibly at its end), so every control
    point influences at least one frame.

    Args:
        num_frames: F >= 1.
        spacing: control-point (knot) spacing in frames, > 0.
    """
    if num_frames < 1:
        raise ValueError(f"num_frames: expected >= 1, found {num_frames}")
    if not spacing > 0:
        raise ValueError(f"spacing: expected > 0 frames, found {spacing}")
    return max(int(math.ceil((num_frames - 1) / spacing - 1e-9)) + 3, 4)


def frame_basis(num_frames: int, spacing: float, *, dtype: torch.dtype = torch.float64,
                device: torch.device | str | None = None) -> SplineBasis:
    """Return the uniform cubic basis at frames 0 .. F-1 (knots every `spacing` frames).

    Args:
        num_frames: F.
        spacing: control-point spacing in frames (> 0; need not be an integer).
    Returns:
        SplineBasis with `num_control = num_control_points(F, spacing)`.
    """
    n = num_control_points(num_frames, spacing)
    knots = uniform_knots(n, spacing, dtype=torch.float64, device=device)
    frames = torch.arange(num_frames, dtype=torch.float64, device=device)
    basis = bspline_basis(frames, knots, 3)
    return SplineBasis(basis.start, basis.weights.to(dtype), n)


def evaluate_spline(control: Tensor, basis: SplineBasis) -> Tensor:
    """Return `sum_i B_i(x) P_i` at every sample.

    Args:
        control: (n, D) control points (n == basis.num_control).
        basis: banded basis with N samples.
    Returns:
        (N, D) curve values, differentiable in `control`.
    """
    if control.ndim != 2 or control.shape[0] != basis.num_control:
        raise ValueError(f"control: expected shape ({basis.num_control}, D), "
                         f"found {tuple(control.shape)}")
    k = basis.weights.shape[1]
    index = basis.start[:, None] + torch.arange(k, device=control.device)
    weights = basis.weights.to(control.dtype)
    return (control[index] * weights[..., None]).sum(1)


def basis_matrix(basis: SplineBasis) -> Tensor:
    """Return the dense (N, n) basis matrix of a banded basis (for tests and small fits)."""
    k = basis.weights.shape[1]
    out = basis.weights.new_zeros(basis.start.numel(), basis.num_control)
    index = basis.start[:, None] + torch.arange(k, device=basis.start.device)
    return out.scatter_add_(1, index, basis.weights)


def refine_midpoint(control: Tensor) -> Tensor:
    """Insert a knot in the middle of every interval of a uniform cubic spline.

    New points (Lane-Riesenfeld): edge points `(P_i + P_{i+1}) / 2` and vertex points
    `(P_{i-1} + 6 P_i + P_{i+1}) / 8`, interleaved `e_0, v_1, e_1, ..., v_{n-2}, e_{n-2}`.
    With the spacing halved (knots `t'_i = (i - 3) * spacing / 2`) the curve is unchanged
    on the whole domain.

    Args:
        control: (n, D) control points, n >= 4.
    Returns:
        (2n - 3, D) refined control points.
    """
    if control.ndim != 2 or control.shape[0] < 4:
        raise ValueError(f"control: expected shape (n >= 4, D), found {tuple(control.shape)}")
    edge = 0.5 * (control[:-1] + control[1:])                            # (n-1, D)
    vert = (control[:-2] + 6.0 * control[1:-1] + control[2:]) / 8.0      # (n-2, D)
    out = control.new_empty(2 * control.shape[0] - 3, control.shape[1])
    out[0::2] = edge
    out[1::2] = vert
    return out


def fit_control_points(values: Tensor, basis: SplineBasis, *, smoothing: float = 1e-9) -> Tensor:
    """Least-squares control points: `argmin_P |B P - values|^2 + s |D2 P|^2`.

    `D2` takes second differences of consecutive control points; its small weight
    `s = smoothing * mean(diag(B^T B))` only decides what the samples leave free (fewer samples than control points)
    (continued linearly) and otherwise moves the fit by about 1e-9 relative.

    Args:
        values: (N, D) samples of the curve.
        basis: banded basis at the N samples.
        smoothing: relative weight of the second-difference regulariser (>= 0).
    Returns:
        (n, D) control points in float64 (values' device).
    """
    if values.ndim != 2 or values.shape[0] != basis.start.numel():
        raise ValueError(f"values: expected shape ({basis.start.numel()}, D), "
                         f"found {tuple(values.shape)}")
    n, k = basis.num_control, basis.weights.shape[1]
    w = basis.weights.to(torch.float64)
    index = basis.start[:, None] + torch.arange(k, device=basis.start.device)     # (N, k)
    normal = torch.zeros(n, n, dtype=torch.float64, device=values.device)
    rows = index[:, :, None].expand(-1, k, k).reshape(-1)
    cols = index[:, None, :].expand(-1, k, k).reshape(-1)
    normal.index_put_((rows, cols), (w[:, :, None] * w[:, None, :]).reshape(-1), accumulate=True)
    rhs = torch.zeros(n, values.shape[1], dtype=torch.float64, device=values.device)
    rhs.index_add_(0, index.reshape(-1), (w[..., None] * values.to(torch.float64)[:, None, :]).reshape(-1, values.shape[1]))
    if smoothing > 0:
        d2 = torch.zeros(max(n - 2, 0), n, dtype=torch.float64, device=values.device)
        i = torch.arange(n - 2, device=values.device)
        d2[i, i], d2[i, i + 1], d2[i, i + 2] = 1.0, -2.0, 1.0
        scale = smoothing * float(normal.diagonal().mean())
        normal = normal + scale * d2.T @ d2
    return torch.linalg.solve(normal, rhs)
