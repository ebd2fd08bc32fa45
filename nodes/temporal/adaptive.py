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

The banded system is solved with `scipy.linalg.solveh_banded` (O(F) per solve), all of a shot's
curves in one call (laid end to end, `whittaker_batch`), their lambda searches in lockstep.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..geometry.rotation import (axis_angle_to_rotmat, quat_mean, quat_to_rotmat, rotmat_to_axis_angle,
                                 rotmat_to_quat)

__all__ = ["noise_sigma", "whittaker", "whittaker_batch", "SmoothedCurve", "smooth_curve", "smooth_curves",
           "smooth_pose_and_weights"]

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
    if len(x) < 3 or lam <= 0:
        return np.asarray(x, np.float64).copy()
    return whittaker_batch(np.asarray(x, np.float64)[None], np.array([float(lam)]),
                           np.asarray(mask, np.float64)[None], np.asarray(curvature_weights, np.float64)[None])[0]


def whittaker_batch(x: np.ndarray, lam: np.ndarray, mask: np.ndarray, curvature_weights: np.ndarray) -> np.ndarray:
    """`whittaker` for D curves at once: one banded solve of the curves laid end to end.

    The D systems are pentadiagonal and independent, so stacked they form one (D F, D F) banded
    matrix of half-bandwidth 2 whose bands are zero across the curves' seams; its banded Cholesky
    factor is the D factors side by side (the seam's zeros add nothing), so each curve's solution
    is what it would be alone, in one LAPACK call instead of D.

    Args:
        x: (D, F) values; lam: (D,) lambdas > 0; mask: (D, F) data weights m_t >= 0;
        curvature_weights: (D, F - 2) c_t >= 0.
    Returns:
        (D, F) float64 smoothed curves.
    """
    from scipy.linalg import solveh_banded

    d, f = x.shape
    m = np.asarray(mask, np.float64)
    lam = np.asarray(lam, np.float64)
    c = lam[:, None] * np.asarray(curvature_weights, np.float64)
    # D2^T C D2 is symmetric pentadiagonal; row t of D2 is (1, -2, 1) at t, t+1, t+2.
    diag = m.copy()
    diag[:, :-2] += c
    diag[:, 1:-1] += 4 * c
    diag[:, 2:] += c
    bands = np.zeros((3, d, f))
    bands[0, :, 2:] = c  # entry (t, t + 2), stored at column t + 2
    bands[1, :, 1:-1] += -2 * c
    bands[1, :, 2:] += -2 * c  # entry (t, t + 1), stored at column t + 1
    bands[2] = diag + 1e-12 * (1.0 + lam[:, None])  # regularization: a curve with no data at all stays defined
    y = solveh_banded(bands.reshape(3, d * f), (m * np.asarray(x, np.float64)).reshape(-1), lower=False,
                      check_finite=False)
    return y.reshape(d, f)


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
    values, sigmas, lams, rms = _smooth_batch(x[None], None if mask is None else np.asarray(mask, bool)[None],
                                              edge_k=edge_k, fidelity=fidelity, reweight=reweight,
                                              sigmas=None if sigma is None else np.array([float(sigma)]))
    return SmoothedCurve(values[0], float(sigmas[0]), float(lams[0]), float(rms[0]))


def _smooth_batch(x: np.ndarray, mask: np.ndarray | None, *, edge_k: float, fidelity: float, reweight: int,
                  sigmas: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """`smooth_curve` on D curves in lockstep: every reweighting and bisection step is one
    `whittaker_batch` over the curves still searching; each curve's result is the one it gets alone.

    Args:
        x: (D, F) values (NaN where unknown); mask: (D, F) bool or None (all finite ones);
        sigmas: (D,) noise std or None (measured per curve).
    Returns:
        (D, F) curves, (D,) sigmas, (D,) lambdas (0: left as it is), (D,) residual RMS.
    """
    d, f = x.shape
    ok = np.isfinite(x) if mask is None else (np.asarray(mask, bool) & np.isfinite(x))
    xf = np.where(ok, x, 0.0)
    s = np.array([noise_sigma(xf[j], ok[j]) for j in range(d)]) if sigmas is None else np.asarray(sigmas, np.float64)
    filled = xf.copy()
    for j in np.flatnonzero(~ok.all(axis=1) & ok.any(axis=1)):  # failed frames filled by interpolation
        filled[j] = np.interp(np.arange(f), np.flatnonzero(ok[j]), xf[j, ok[j]])
    out, lams, rms = filled.copy(), np.zeros(d), np.zeros(d)
    live = np.flatnonzero((ok.sum(axis=1) >= 3) & (s > 0)) if f >= 5 else np.zeros(0, np.int64)
    if not live.size:
        return out, s, lams, rms
    xl, m, sl = xf[live], ok[live].astype(np.float64), s[live]
    target = fidelity * sl
    scale = (edge_k * sl)[:, None]

    # first curvature weights from the data itself (lightly averaged), so a sharp event is
    # recognised before the first solve could smooth it away
    pre = filled[live].copy()
    pre[:, 1:-1] = 0.25 * filled[live, :-2] + 0.5 * filled[live, 1:-1] + 0.25 * filled[live, 2:]
    d2_pre = pre[:, :-2] - 2 * pre[:, 1:-1] + pre[:, 2:]
    c_first = 1.0 / (1.0 + (d2_pre / scale) ** 2)

    def solve(rows: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Reweighted solves of the live curves `rows` at their (len(rows),) lambdas: curves, RMS."""
        c = c_first[rows]
        y = whittaker_batch(xl[rows], lam, m[rows], c)
        for _ in range(reweight):
            d2 = y[:, :-2] - 2 * y[:, 1:-1] + y[:, 2:]
            c = 1.0 / (1.0 + (d2 / scale[rows]) ** 2)
            y = whittaker_batch(xl[rows], lam, m[rows], c)
        return y, np.sqrt(np.sum(m[rows] * (y - xl[rows]) ** 2, axis=1) / m[rows].sum(axis=1))

    n = len(live)
    lo, hi = np.full(n, -4.0), np.full(n, 8.0)  # log10 lambda
    best_y, best_lam, best_r = xl.copy(), np.zeros(n), np.zeros(n)
    y_hi, r_hi = solve(np.arange(n), np.full(n, 10.0 ** 8.0))
    done = r_hi <= target  # smooth enough at the largest lambda: taken as it is
    best_y[done], best_lam[done], best_r[done] = y_hi[done], 10.0 ** 8.0, r_hi[done]
    search = np.flatnonzero(~done)
    if search.size:
        for _ in range(18):
            mid = 0.5 * (lo[search] + hi[search])
            y, r = solve(search, 10.0 ** mid)
            fits = r <= target[search]
            kept = search[fits]
            lo[kept], best_y[kept], best_lam[kept], best_r[kept] = mid[fits], y[fits], 10.0 ** mid[fits], r[fits]
            hi[search[~fits]] = mid[~fits]
        never = search[best_lam[search] == 0.0]  # no lambda met the target: the smallest tried
        if never.size:
            y, r = solve(never, 10.0 ** lo[never])
            best_y[never], best_lam[never], best_r[never] = y, 10.0 ** lo[never], r
    out[live], lams[live], rms[live] = best_y, best_lam, best_r
    return out, s, lams, rms


def smooth_curves(values: np.ndarray, mask: np.ndarray | None = None, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """`smooth_curve` on every column of (F, D) values, all columns in one batch (`_smooth_batch`);
    `mask` is (F,) bool for every column, or None (each column's finite frames). Returns (F, D)
    curves and (D,) sigmas."""
    values = np.asarray(values, np.float64)
    columns = values.T.copy()
    masks = None if mask is None else np.broadcast_to(np.asarray(mask, bool)[None], columns.shape)
    out, sigmas, _, _ = _smooth_batch(columns, masks, edge_k=kwargs.get("edge_k", 3.0),
                                      fidelity=kwargs.get("fidelity", 0.85), reweight=kwargs.get("reweight", 4),
                                      sigmas=None)
    return out.T.copy(), sigmas


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
    rotation, linear = np.asarray(rotation, np.int64), np.asarray(linear, np.int64)
    curves = np.zeros((f, 3 * bool(len(rotation)) + len(linear)))
    if len(rotation):
        rows = v[ok][:, rotation]
        rot = quat_to_rotmat(rotmat_to_quat(rows.reshape(-1, 3, 3))) if matrix else axis_angle_to_rotmat(rows)
        mean = quat_to_rotmat(quat_mean(rotmat_to_quat(rot), np.ones(len(rot))))
        curves[ok, :3] = rotmat_to_axis_angle(mean.T @ rot)  # each frame's rotation relative to the mean
    curves[:, curves.shape[1] - len(linear):] = v[:, linear]
    smoothed, _ = smooth_curves(curves, ok, **kwargs)  # every curve with its own noise and lambda, one batch
    if len(rotation):
        back = mean @ axis_angle_to_rotmat(smoothed[ok, :3])
        out[np.flatnonzero(ok)[:, None], rotation[None]] = back.reshape(-1, 9) if matrix else rotmat_to_axis_angle(back)
    if len(linear):
        lo, hi = v[ok][:, linear].min(axis=0), v[ok][:, linear].max(axis=0)
        out[np.flatnonzero(ok)[:, None], linear[None]] = np.clip(smoothed[ok, curves.shape[1] - len(linear):], lo, hi)
    return out
