"""Adaptive, edge-preserving smoothing of parameter curves (pose and expression weights).

Each curve `x` (F frames) is replaced by the minimizer of

    E(y) = sum_t m_t (y_t - x_t)^2 + lambda sum_t c_t (y_{t-1} - 2 y_t + y_{t+1})^2

a Whittaker smoother (Eilers 2003, "A perfect smoother") with robust curvature weights
`c_t = 1 / (1 + (D2y_t / (k sigma))^2)` found by iterative reweighting (a Cauchy penalty on the
second difference), so a blink, a jaw snap or a fast head turn, whose curvature is many times
the noise's, keeps its depth, while jitter is removed. Nothing is tuned per shot:

- `sigma`, the curve's noise, is measured from its own second differences (for white noise
  `var(D2 x) = 6 sigma^2`; the median absolute deviation ignores the rare sharp events);
- `lambda` follows from it by the discrepancy principle (Morozov): the largest smoothing whose
  residual RMS, over the frames that count, is `sigma` (a bisection on log lambda), so a clean
  curve is left nearly alone and a noisy one is smoothed as far as its noise allows;
- `m_t` is 0 on failed frames (filled from their neighbours) and 1 elsewhere.

The banded system is solved with `scipy.linalg.solveh_banded` (O(F) per solve).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..geometry.rotation import (axis_angle_to_rotmat, quat_mean, quat_to_rotmat, rotmat_to_axis_angle,
                                 rotmat_to_quat)

__all__ = ["noise_sigma", "whittaker", "SmoothedCurve", "smooth_curve", "smooth_curves", "smooth_pose_and_weights"]

_MAD_TO_SIGMA = 1.4826
_SQRT6 = np.sqrt(6.0)


def noise_sigma(x: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Noise std of a curve from its second differences: `1.4826 MAD(D2 x) / sqrt(6)`.

    Args:
        x: (F,) values.
        mask: (F,) bool, frames that count (a second difference needs its three frames), or None.
    Returns:
        sigma >= 0 (0 for fewer than 3 usable frames).
    """
    x = np.asarray(x, np.float64)
    ok = np.ones(len(x), bool) if mask is None else np.asarray(mask, bool)
    if len(x) < 3:
        return 0.0
    d2 = x[:-2] - 2 * x[1:-1] + x[2:]
    d2 = d2[ok[:-2] & ok[1:-1] & ok[2:]]
    if not d2.size:
        return 0.0
    return float(_MAD_TO_SIGMA * np.median(np.abs(d2 - np.median(d2))) / _SQRT6)


def whittaker(x: np.ndarray, lam: float, mask: np.ndarray, curvature_weights: np.ndarray) -> np.ndarray:
    """Solve `(M + lambda D2^T C D2) y = M x` for one curve.

    Args:
        x: (F,) values; mask: (F,) data weights m_t >= 0 (not all 0 unless lambda > 0);
        lam: lambda >= 0; curvature_weights: (F - 2,) c_t >= 0.
    Returns:
        (F,) float64 smoothed curve.
    """
    from scipy.linalg import solveh_banded

    f = len(x)
    m = np.asarray(mask, np.float64)
    if f < 3 or lam <= 0:
        return np.asarray(x, np.float64).copy()
    c = lam * np.asarray(curvature_weights, np.float64)
    # D2^T C D2 is symmetric pentadiagonal; row t of D2 is (1, -2, 1) at t, t+1, t+2.
    diag = m.copy()
    diag[:-2] += c
    diag[1:-1] += 4 * c
    diag[2:] += c
    off1 = np.zeros(f - 1)
    off1[:-1] += -2 * c
    off1[1:] += -2 * c
    off2 = c.copy()
    bands = np.zeros((3, f))
    bands[0, 2:] = off2
    bands[1, 1:] = off1
    bands[2] = diag + 1e-12 * (1.0 + lam)  # regularization: a curve with no data at all stays defined
    return solveh_banded(bands, m * np.asarray(x, np.float64), lower=False, check_finite=False)


class SmoothedCurve(NamedTuple):
    """Result of `smooth_curve`.

    Attributes:
        values: (F,) smoothed curve.
        sigma: the measured noise std.
        lam: the lambda chosen (0: left as it is).
        residual_rms: RMS of `values - x` over the frames that count.
    """

    values: np.ndarray
    sigma: float
    lam: float
    residual_rms: float


def smooth_curve(x: np.ndarray, mask: np.ndarray | None = None, *, edge_k: float = 3.0, fidelity: float = 0.85,
                 reweight: int = 4, sigma: float | None = None) -> SmoothedCurve:
    """Adaptive edge-preserving smoothing of one curve (see the module docstring).

    Args:
        x: (F,) values (NaN where unknown: treated as failed).
        mask: (F,) bool, frames whose values count; None: all finite ones.
        edge_k: curvature over `edge_k * sigma` is an event to keep (the Cauchy penalty's scale).
        fidelity: the residual RMS aimed at, in units of the measured sigma (1: the discrepancy
            principle; smaller smooths less).
        reweight: reweighting rounds of the curvature weights.
        sigma: the noise std, or None to measure it (`noise_sigma`).
    Returns:
        SmoothedCurve.
    """
    x = np.asarray(x, np.float64)
    ok = np.isfinite(x) if mask is None else (np.asarray(mask, bool) & np.isfinite(x))
    xf = np.where(ok, x, 0.0)
    f = len(x)
    s = noise_sigma(xf, ok) if sigma is None else float(sigma)
    filled = xf if ok.all() or not ok.any() else np.interp(np.arange(f), np.flatnonzero(ok), xf[ok])
    if f < 5 or ok.sum() < 3 or s <= 0:
        return SmoothedCurve(filled, s, 0.0, 0.0)
    m = ok.astype(np.float64)
    target = fidelity * s

    # first curvature weights from the data itself (lightly averaged), so a sharp event is
    # recognised before the first solve could smooth it away
    pre = filled.copy()
    pre[1:-1] = 0.25 * filled[:-2] + 0.5 * filled[1:-1] + 0.25 * filled[2:]
    d2_pre = pre[:-2] - 2 * pre[1:-1] + pre[2:]
    c_first = 1.0 / (1.0 + (d2_pre / (edge_k * s)) ** 2)

    def solve(lam: float) -> tuple[np.ndarray, float]:
        c = c_first
        y = whittaker(xf, lam, m, c)
        for _ in range(reweight):
            d2 = y[:-2] - 2 * y[1:-1] + y[2:]
            c = 1.0 / (1.0 + (d2 / (edge_k * s)) ** 2)
            y = whittaker(xf, lam, m, c)
        rms = float(np.sqrt(np.sum(m * (y - xf) ** 2) / m.sum()))
        return y, rms

    lo, hi = -4.0, 8.0  # log10 lambda
    best = (xf, 0.0, 0.0)
    y_hi, r_hi = solve(10.0 ** hi)
    if r_hi <= target:
        return SmoothedCurve(y_hi, s, 10.0 ** hi, r_hi)
    for _ in range(18):
        mid = 0.5 * (lo + hi)
        y, r = solve(10.0 ** mid)
        if r <= target:
            lo, best = mid, (y, 10.0 ** mid, r)
        else:
            hi = mid
    if best[1] == 0.0:
        y, r = solve(10.0 ** lo)
        best = (y, 10.0 ** lo, r)
    return SmoothedCurve(best[0], s, best[1], best[2])


def smooth_curves(values: np.ndarray, mask: np.ndarray | None = None, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """`smooth_curve` on every column of (F, D) values; returns (F, D) curves and (D,) sigmas."""
    values = np.asarray(values, np.float64)
    out = np.empty_like(values)
    sigmas = np.zeros(values.shape[1])
    for j in range(values.shape[1]):
        result = smooth_curve(values[:, j], mask, **kwargs)
        out[:, j], sigmas[j] = result.values, result.sigma
    return out, sigmas


def smooth_pose_and_weights(values: np.ndarray, rotation: np.ndarray, linear: np.ndarray,
                            failed: np.ndarray | None = None, *, matrix: bool = True, **kwargs) -> np.ndarray:
    """Adaptive smoothing of a fitted sequence: the rotation, and every linear column alone.

    Rotations are smoothed as the rotation vectors of `R_mean^T R_t` (small for a head, whatever
    its absolute orientation, so the axis-angle's discontinuity at pi never enters), `R_mean` the
    chordal mean; each linear column (translation, weights) on its own, with its own noise and
    lambda, then clipped to the range its input took (a weight in [0, 1] stays there).

    Args:
        values: (F, D) parameters.
        rotation: column indices of the rotation: 9 (row-major matrix, `matrix`) or 3 (axis-angle rad).
        linear: column indices smoothed one by one.
        failed: (F,) bool, frames neither used nor changed; None: none.
        kwargs: `smooth_curve`'s options.
    Returns:
        (F, D) float64; other columns and failed frames as given.
    """
    v = np.asarray(values, np.float64)
    f = len(v)
    out = v.copy()
    bad = np.zeros(f, bool) if failed is None else np.asarray(failed, bool)
    ok = ~bad & np.isfinite(v).all(axis=1)
    if ok.sum() < 3:
        return out
    if len(rotation):
        rows = v[ok][:, rotation]
        rot = quat_to_rotmat(rotmat_to_quat(rows.reshape(-1, 3, 3))) if matrix else axis_angle_to_rotmat(rows)
        mean = quat_to_rotmat(quat_mean(rotmat_to_quat(rot), np.ones(len(rot))))
        local = np.zeros((f, 3))
        local[ok] = rotmat_to_axis_angle(mean.T @ rot)  # each frame's rotation relative to the mean
        smoothed, _ = smooth_curves(local, ok, **kwargs)
        back = mean @ axis_angle_to_rotmat(smoothed[ok])
        out[np.flatnonzero(ok)[:, None], np.asarray(rotation)[None]] = \
            back.reshape(-1, 9) if matrix else rotmat_to_axis_angle(back)
    for j in linear:
        column = v[:, j]
        smoothed = smooth_curve(np.where(ok, column, np.nan), ok, **kwargs).values
        lo, hi = np.min(column[ok]), np.max(column[ok])
        out[ok, j] = np.clip(smoothed[ok], lo, hi)
    return out
