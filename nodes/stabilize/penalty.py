"""The mode-pursuit penalty `psi_w` and the 7-tap central-difference velocity over frames.

`psi_w` (mode-pursuit paper, eq. 1, n = 2) is a smooth, bounded stand-in for the l0 "norm":

    u = min(|x| / w, 1)
    psi_w(x) = 2 u^2                  for u < 1/2
             = 1 - 2 (1 - u)^2        for 1/2 <= u < 1
             = 1                      for u >= 1          (outliers all cost 1)

written leanly as `2 u^2 - 4 relu(u - 1/2)^2`. It is C1 with derivative
`psi_w'(x) = (4 / w) sign(x) min(u, 1 - u)` (zero beyond the width).

The velocity filter is the 7-point central difference, exact for polynomials of degree <= 6
(error O(h^6)):

    v_f = 3/4 (x_{f+1} - x_{f-1}) - 3/20 (x_{f+2} - x_{f-2}) + 1/60 (x_{f+3} - x_{f-3})

Sequence ends (the first and last three frames have no full stencil), three choices:
- `ends="valid"` (default of `central_velocity`): only the F - 6 frames with a full stencil.
  The end frames are then tied to the rest only through the tiny outer taps (1/60).
- `ends="one_sided"`: all F frames, the end frames with shifted 7-point stencils, also exact
  for degree <= 6 but amplifying noise about 12x (coefficients up to 7.5).
- `ends="reduced"` (used by the stabilization energy): all F frames, the end frames with the
  central differences that fit, of lower order: `x_1 - x_0` (frame 0),
  `(x_2 - x_0) / 2` (frame 1), `(x_0 - 8 x_1 + 8 x_3 - x_4) / 12` (frame 2), mirrored at the
  other end. They amplify noise no more than the 7-tap filter and tie every end frame to its
  neighbours with weights near 1, which keeps the spline's end control points from drifting
  when their position terms are saturated.
"""

from __future__ import annotations

from fractions import Fraction

import torch
from torch import Tensor

__all__ = ["psi", "psi_derivative", "psi_sum_and_grad_", "VELOCITY_COEFFS", "REDUCED_END_COEFFS",
           "central_velocity", "central_velocity_adjoint"]

#: Coefficients `a_k` of `v_f = sum_k a_k (x_{f+k} - x_{f-k})`, k = 1, 2, 3 (per frame).
VELOCITY_COEFFS: tuple[float, float, float] = (3.0 / 4.0, -3.0 / 20.0, 1.0 / 60.0)


#: Stencils of the frames 0, 1, 2 on samples 0..4 for `ends="reduced"` (the last three frames
#: use the mirror image with opposite sign).
REDUCED_END_COEFFS: tuple[tuple[float, ...], ...] = (
    (-1.0, 1.0, 0.0, 0.0, 0.0),
    (-0.5, 0.0, 0.5, 0.0, 0.0),
    (1.0 / 12.0, -8.0 / 12.0, 0.0, 8.0 / 12.0, -1.0 / 12.0),
)


def _check_width(width: float, name: str = "width") -> None:
    if not width > 0:
        raise ValueError(f"{name}: expected > 0, found {width}")


def psi(x: Tensor, width: float) -> Tensor:
    """Return the mode-pursuit penalty `psi_w(x)` elementwise (see the module docstring).

    Args:
        x: (...) residuals, any unit.
        width: w > 0, same unit as `x`; residuals with |x| >= w cost 1.
    Returns:
        (...) values in [0, 1], differentiable (C1).

    Example:
        >>> psi(torch.tensor([0.0, 0.25, 0.5, 0.75, 2.0]), 1.0)
        tensor([0.0000, 0.1250, 0.5000, 0.8750, 1.0000])
    """
    _check_width(width)
    u = (x.abs() / width).clamp(max=1.0)
    return 2.0 * u * u - 4.0 * torch.relu(u - 0.5).square()


def psi_derivative(x: Tensor, width: float) -> Tensor:
    """Return `d psi_w / dx = (4 / w) sign(x) min(u, relu(1 - u))`, u = |x| / w.

    Args:
        x: (...) residuals.
        width: w > 0.
    Returns:
        (...) derivative, same unit as 1 / x.
    """
    _check_width(width)
    c = (x / width).clamp(-1.0, 1.0)
    return (4.0 / width) * (2.0 * c.clamp(-0.5, 0.5) - c)


def psi_sum_and_grad_(z: Tensor) -> tuple[Tensor, Tensor]:
    """Return `sum psi_1(z)` and `d psi_1 / dz / 4`, overwriting `z` (fused, for speed).

    With `c = clamp(z, -1, 1)`, `p = clamp(c, -1/2, 1/2)` and `e = c - p`:
    `psi_1(z) = 2 c^2 - 4 e^2` and `psi_1'(z) = 4 (p - e)`. For a width w, call it with
    `z = x / w`; then `psi_w'(x) = 4 h / w` with `h` the returned gradient.

    Args:
        z: (...) float tensor of scaled residuals x / w; destroyed (becomes `e`).
    Returns:
        total: () sum of psi over all elements, float64.
        h: (...) `p - e` (a new tensor, same dtype as z): a quarter of the derivative.
    """
    c = z.clamp_(-1.0, 1.0)
    flat = c.reshape(-1)
    total = torch.dot(flat, flat).double() * 2.0
    p = c.clamp(-0.5, 0.5)
    e = c.sub_(p)
    flat = e.reshape(-1)
    total = total - 4.0 * torch.dot(flat, flat).double()
    return total, p.sub_(e)


def _one_sided_coeffs() -> list[list[Fraction]]:
    """Weights of the 7-point stencils on samples 0..6 for the derivative at points 0, 1, 2."""
    rows = []
    for at in range(3):
        # Solve the Vandermonde system sum_j c_j (j - at)^m = [m == 1], m = 0..6, exactly.
        a = [[Fraction(j - at) ** m for j in range(7)] for m in range(7)]
        b = [Fraction(int(m == 1)) for m in range(7)]
        for col in range(7):
            piv = next(r for r in range(col, 7) if a[r][col] != 0)
            a[col], a[piv], b[col], b[piv] = a[piv], a[col], b[piv], b[col]
            for r in range(7):
                if r != col and a[r][col] != 0:
                    f = a[r][col] / a[col][col]
                    a[r] = [x - f * y for x, y in zip(a[r], a[col])]
                    b[r] -= f * b[col]
        rows.append([b[r] / a[r][r] for r in range(7)])
    return rows


def central_velocity(x: Tensor, dim: int = 0, ends: str = "valid") -> Tensor:
    """Return the 7-tap central-difference derivative of `x` along `dim` (per frame).

    Args:
        x: (..., F, ...) samples, F >= 7 along `dim`.
        dim: the frame axis.
        ends: "valid" (F - 6 output frames: frames 3 .. F-4), "one_sided" (F frames;
            the first and last three use shifted 7-point stencils) or "reduced" (F frames;
            lower-order central differences at the ends), see the module docstring.
    Returns:
        (..., F - 6 or F, ...) derivative, unit of x per frame.
    Raises:
        ValueError: F < 7 or an unknown `ends`.
    """
    if ends not in ("valid", "one_sided", "reduced"):
        raise ValueError(f"ends: expected 'valid', 'one_sided' or 'reduced', found {ends!r}")
    x = x.movedim(dim, 0)
    f = x.shape[0]
    if f < 7:
        raise ValueError(f"x: expected at least 7 frames along dim {dim}, found {f}")
    a1, a2, a3 = VELOCITY_COEFFS
    vel = (a1 * (x[4:f - 2] - x[2:f - 4]) + a2 * (x[5:f - 1] - x[1:f - 5])
           + a3 * (x[6:] - x[:f - 6]))
    if ends != "valid":
        if ends == "one_sided":
            coeffs = x.new_tensor([[float(c) for c in row] for row in _one_sided_coeffs()])  # (3, 7)
        else:
            coeffs = x.new_tensor(REDUCED_END_COEFFS)                                       # (3, 5)
        k = coeffs.shape[1]
        head = torch.einsum("aj,j...->a...", coeffs, x[:k])
        tail = -torch.einsum("aj,j...->a...", coeffs, x[f - k:].flip(0)).flip(0)
        vel = torch.cat([head, vel, tail], dim=0)
    return vel.movedim(0, dim)


def central_velocity_adjoint(grad: Tensor, num_frames: int, dim: int = 0) -> Tensor:
    """Return the adjoint (transpose) of `central_velocity(..., ends="valid")`.

    Args:
        grad: (..., F - 6, ...) gradient with respect to the velocities.
        num_frames: F.
        dim: the frame axis.
    Returns:
        (..., F, ...) gradient with respect to the samples.
    """
    g = grad.movedim(dim, 0)
    f = num_frames
    if g.shape[0] != f - 6:
        raise ValueError(f"grad: expected {f - 6} frames along dim {dim} for num_frames={f}, "
                         f"found {g.shape[0]}")
    out = g.new_zeros(f, *g.shape[1:])
    for k, a in enumerate(VELOCITY_COEFFS, start=1):
        out[3 + k:f - 3 + k] += a * g
        out[3 - k:f - 3 - k] -= a * g
    return out.movedim(0, dim)
