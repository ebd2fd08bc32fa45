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

With the face's projected landmarks as a function of the parameters (`smooth_pose_and_weights`'s
`landmarks`), the pose and the weights are smoothed together in the metric of the landmarks
(`smooth_in_landmark_metric`) instead of curve by curve. A per-frame fit's weights are far
noisier than what they move: many shapes move the landmarks in nearly the same way, so their
noise is correlated (jawLeft against jawRight), often pinned at a bound with one-frame spikes,
and partly cancelled by the pose; a curve's own noise estimate then misjudges what is signal.
Measured and smoothed in the landmarks' image space, the noise is one number (pixels), shared by
every direction the landmarks see, and the directions they barely see are smoothed hardest.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np

from ..geometry.rotation import (axis_angle_to_rotmat, quat_mean, quat_to_rotmat, rotmat_to_axis_angle,
                                 rotmat_to_quat)

__all__ = ["FACE68_GROUPS", "noise_sigma", "whittaker", "whittaker_batch", "SmoothedCurve", "smooth_curve", "smooth_curves",
           "landmark_jacobian", "smooth_in_landmark_metric", "smooth_pose_and_weights"]

_MAD_TO_SIGMA = 1.4826
_SQRT6 = np.sqrt(6.0)
_UNSEEN_SMOOTHING = 1e-6
"""`smooth_in_landmark_metric`'s extra smoothing of the directions the landmarks barely see: their
curvature is also penalized in the parameters' own units with this share of the largest singular
value squared, so a direction with singular value s gets `1 + 1e-6 s_max^2 / s^2` times the common
lambda (s_max is the head rotation's, ~700 px/rad on a 256^2 plate: a weight direction moving the
68 points under 0.7 px per unit is smoothed at least twice as hard; one they do not see at all is a
straight line). Measured on bench/smoothing.py's synthetic fits (noise 0.3 px, 3 seeds): 1e-4
lowered the weights' error to the truth by 2% but kept blinks at 0.57 of their depth against
0.68 at 1e-6 and 0; on the kept astronaut fits, 1e-6 to 1e-4 give the same landmark jitter and
deviation within 5% (both measured before the curvature weights were capped at the data's)."""


FACE68_GROUPS = np.repeat([0] * 17 + [1] * 5 + [2] * 5 + [3] * 9 + [4] * 6 + [5] * 6 + [6] * 12 + [7] * 8, 2)
"""(136,) region of each coordinate of the 68 Multi-PIE points flattened (x0, y0, x1, ...): jaw
line, the two brows, nose, the two eyes, outer and inner lips. A blink moves 4 points of 68 a few
pixels; measured against the noise of all 136 coordinates it drowns, against its eye's it stands
out (`smooth_in_landmark_metric`'s events are judged region by region)."""


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


def landmark_jacobian(landmarks: Callable[[np.ndarray], np.ndarray], x0: np.ndarray, step: float = 1e-2) -> np.ndarray:
    """Central finite differences of the landmarks at one parameter vector.

    Args:
        landmarks: (N, D) parameter vectors -> (N, M) landmark coordinates (e.g. 68 projected
            points flattened, pixels).
        x0: (D,) where to differentiate.
        step: the difference step in each parameter's units (the landmarks of a blendshape
            model are linear in the weights and smooth in the pose, so 0.01 rad / cm / weight
            is well inside the linear range).
    Returns:
        (M, D) float64 Jacobian, landmark units per parameter unit.
    """
    x0 = np.asarray(x0, np.float64)
    d = len(x0)
    rows = np.concatenate([x0 + step * np.eye(d), x0 - step * np.eye(d)])
    points = np.asarray(landmarks(rows), np.float64).reshape(2 * d, -1)
    return ((points[:d] - points[d:]) / (2 * step)).T


def smooth_in_landmark_metric(x: np.ndarray, jacobian: np.ndarray, mask: np.ndarray | None = None, *,
                              edge_k: float = 3.0, fidelity: float = 0.85, reweight: int = 4,
                              groups: np.ndarray | None = None) -> tuple[np.ndarray, float, float, float]:
    """Adaptive edge-preserving smoothing of D curves together, in the metric of the landmarks they move.

    Minimizes, over (F, D) curves y,

        sum_t m_t |J (y_t - x_t)|^2 + lambda sum_t c_t (|J D2y_t|^2 + nu s_max^2 |D2y_t|^2)

    with J the (M, D) Jacobian of the landmarks (the deviation and the curvature are measured
    where the user sees them, in landmark units), `nu = _UNSEEN_SMOOTHING` (directions J barely
    sees are smoothed in the parameters' own units), robust curvature weights c_t and lambda by
    the discrepancy principle: the largest whose landmark residual RMS per frame is
    `fidelity * sigma`. In the right singular vectors of J (`J = U S V^T`) the problem falls
    apart into D independent Whittaker smoothers, component i with data weight s_i^2 and lambda
    `lambda (1 + nu s_max^2 / s_i^2)`, solved in one `whittaker_batch`.

    The curvature weights judge events region by region (`groups`, e.g. `FACE68_GROUPS`):
    `c_t = 1 / (1 + max_g |D2 L_g,t|^2 / (edge_k^2 sigma_g^2))`, L_g the landmark coordinates of
    region g, sigma_g^2 its noise energy per frame (`median_t |D2 L_g,t|^2 / 6` of the data), so a
    blink, a few pixels on 4 of 68 points, counts against its eye's noise, not the whole face's.
    They are taken from the data lightly averaged, then from each solve, never above the data's
    (a smoothed event must not talk itself out of being one).

    sigma, the landmarks' noise per frame (the RMS over frames of |J n_t| for the fit's noise
    n_t), is measured from the data's second differences: `median_t |J D2x_t|^2 / 6` (white
    noise: `E|D2 n|^2 = 6 E|n|^2`; the median ignores the rare sharp events).

    Args:
        x: (F, D) curves (pose and weights in any units; NaN: treated as failed).
        jacobian: (M, D) landmark units per unit of each curve.
        mask: (F,) bool, frames that count (the others are filled from their neighbours); None:
            the finite ones.
        edge_k, fidelity, reweight: as `smooth_curve`.
        groups: (M,) region label of each landmark coordinate, or None (one region).
    Returns:
        (F, D) float64 curves, sigma (landmark units), lambda (0: left as they are), the
        residual RMS per frame (landmark units).
    """
    x = np.asarray(x, np.float64)
    f, d = x.shape
    ok = np.isfinite(x).all(axis=1) if mask is None else (np.asarray(mask, bool) & np.isfinite(x).all(axis=1))
    xf = np.where(ok[:, None], x, 0.0)
    filled = xf.copy()
    if 0 < ok.sum() < f:
        for j in range(d):
            filled[:, j] = np.interp(np.arange(f), np.flatnonzero(ok), xf[ok, j])
    if ok.sum() < 3 or f < 5:
        return filled, 0.0, 0.0, 0.0
    u, s_values, vt = np.linalg.svd(np.asarray(jacobian, np.float64), full_matrices=True)
    s = np.zeros(d)
    s[:min(len(s_values), d)] = s_values[:d]
    z = xf @ vt.T  # (F, D) components
    d2 = (z[:-2] - 2 * z[1:-1] + z[2:]) * s
    triple = ok[:-2] & ok[1:-1] & ok[2:]
    if not triple.any() or s[0] <= 0:
        return filled, 0.0, 0.0, 0.0
    sigma = float(np.sqrt(np.median(np.sum(d2[triple] ** 2, axis=1)) / 6.0))
    if sigma <= 0:
        return filled, 0.0, 0.0, 0.0
    stiffness = np.where(s > 1e-9 * s[0], (s ** 2 + _UNSEEN_SMOOTHING * s[0] ** 2) / np.maximum(s, 1e-300) ** 2, 1e12)
    stiffness = np.minimum(stiffness, 1e12)
    m = np.tile(ok.astype(np.float64), (d, 1))
    zt = z.T.copy()
    zf = (filled @ vt.T).T
    pre = zf.copy()
    pre[:, 1:-1] = 0.25 * zf[:, :-2] + 0.5 * zf[:, 1:-1] + 0.25 * zf[:, 2:]
    rank = min(len(s_values), d)
    to_landmarks = u[:, :rank] * s[:rank]  # (M, rank): components -> landmark coordinates
    labels = np.zeros(u.shape[0], np.int64) if groups is None else np.unique(np.asarray(groups), return_inverse=True)[1]
    member = np.eye(labels.max() + 1)[labels]  # (M, G) one-hot

    def group_curvature(y: np.ndarray) -> np.ndarray:
        """(G, F - 2) squared landmark curvature of each group for (D, F) components."""
        seen = to_landmarks @ (y[:rank, :-2] - 2 * y[:rank, 1:-1] + y[:rank, 2:])
        return member.T @ seen ** 2

    group_noise = np.median(group_curvature(z.T)[:, triple], axis=1) / 6.0  # (G,) each group's noise energy
    scale2 = edge_k ** 2 * np.maximum(group_noise, 1e-12 * sigma ** 2)[:, None]

    def curvature_weights(y: np.ndarray) -> np.ndarray:
        """(F - 2,) robust weights: the frame's largest group curvature against that group's noise."""
        return 1.0 / (1.0 + np.max(group_curvature(y) / scale2, axis=0))

    c_first = curvature_weights(pre)

    def solve(lam: float) -> tuple[np.ndarray, float]:
        c = c_first
        y = whittaker_batch(zt, lam * stiffness, m, np.broadcast_to(c, (d, f - 2)))
        for _ in range(reweight):
            c = np.minimum(curvature_weights(y), c_first)
            y = whittaker_batch(zt, lam * stiffness, m, np.broadcast_to(c, (d, f - 2)))
        residual = ((y - zt) * s[:, None])[:, ok]
        return y, float(np.sqrt(np.sum(residual ** 2) / ok.sum()))

    target = fidelity * sigma
    lo, hi = -4.0, 8.0  # log10 lambda
    y, r = solve(10.0 ** hi)
    if r <= target:
        return y.T @ vt, sigma, 10.0 ** hi, r
    best = None
    for _ in range(24):
        mid = 0.5 * (lo + hi)
        y, r = solve(10.0 ** mid)
        if r <= target:
            lo, best = mid, (y, r, 10.0 ** mid)
        else:
            hi = mid
    if best is None:
        y, r = solve(10.0 ** lo)
        best = (y, r, 10.0 ** lo)
    return best[0].T @ vt, sigma, best[2], best[1]


def smooth_pose_and_weights(values: np.ndarray, rotation: np.ndarray, linear: np.ndarray,
                            failed: np.ndarray | None = None, *, matrix: bool = True,
                            landmarks: Callable[[np.ndarray], np.ndarray] | None = None,
                            landmark_groups: np.ndarray | None = None, **kwargs) -> np.ndarray:
    """Adaptive smoothing of a fitted sequence: the rotation and the linear columns (translation, weights).

    Rotations are smoothed as the rotation vectors of `R_mean^T R_t` (small for a head, whatever
    its absolute orientation, so the axis-angle's discontinuity at pi never enters), `R_mean` the
    chordal mean. Without `landmarks` every curve (3 rotation-vector components and each linear
    column) is smoothed on its own, with its own noise and lambda (`smooth_curves`). With
    `landmarks`, the curves the landmarks depend on are smoothed together in their metric
    (`smooth_in_landmark_metric`, the Jacobian taken at the mean of the frames that count), the
    others on their own. Linear columns are then clipped to the range their input took (a weight
    in [0, 1] stays there).

    Args:
        values: (F, V) parameters.
        rotation: column indices of the rotation: 9 (row-major matrix, `matrix`) or 3 (axis-angle rad), or none.
        linear: column indices of the other smoothed curves.
        failed: (F,) bool, frames neither used nor changed; None: none.
        landmarks: (N, V) parameter rows in `values`' layout -> (N, M) landmark coordinates
            (e.g. the projected 68 points, pixels), or None.
        landmark_groups: (M,) region of each landmark coordinate (events are judged region by
            region, e.g. `FACE68_GROUPS`), or None (one region).
        kwargs: `smooth_curve`'s options (edge_k, fidelity, reweight).
    Returns:
        (F, V) float64; other columns and failed frames as given.
    """
    v = np.asarray(values, np.float64)
    f = len(v)
    out = v.copy()
    bad = np.zeros(f, bool) if failed is None else np.asarray(failed, bool)
    ok = ~bad & np.isfinite(v).all(axis=1)
    if ok.sum() < 3:
        return out
    rotation, linear = np.asarray(rotation, np.int64), np.asarray(linear, np.int64)
    n_rot = 3 * bool(len(rotation))
    curves = np.zeros((f, n_rot + len(linear)))
    mean = np.eye(3)
    if len(rotation):
        rows = v[ok][:, rotation]
        rot = quat_to_rotmat(rotmat_to_quat(rows.reshape(-1, 3, 3))) if matrix else axis_angle_to_rotmat(rows)
        mean = quat_to_rotmat(quat_mean(rotmat_to_quat(rot), np.ones(len(rot))))
        curves[ok, :3] = rotmat_to_axis_angle(mean.T @ rot)  # each frame's rotation relative to the mean
    curves[:, n_rot:] = v[:, linear]

    def to_values(c: np.ndarray, base: np.ndarray) -> np.ndarray:
        """(N, D) curves -> (N, V) rows of `values`' layout (other columns from `base`)."""
        rows = np.tile(base, (len(c), 1))
        if len(rotation):
            back = mean @ axis_angle_to_rotmat(c[:, :3])
            rows[:, rotation] = back.reshape(-1, 9) if matrix else rotmat_to_axis_angle(back)
        rows[:, linear] = c[:, n_rot:]
        return rows

    options = {k: kwargs[k] for k in ("edge_k", "fidelity", "reweight") if k in kwargs}
    smoothed = curves.copy()
    alone = np.arange(curves.shape[1])
    if landmarks is not None:
        centre = curves[ok].mean(axis=0)
        jac = landmark_jacobian(lambda c: landmarks(to_values(c, v[ok].mean(axis=0))), centre)
        seen = np.flatnonzero(np.abs(jac).max(axis=0) > 0)
        alone = np.setdiff1d(alone, seen)
        if seen.size:
            smoothed[:, seen] = smooth_in_landmark_metric(curves[:, seen] - centre[seen], jac[:, seen], ok,
                                                          groups=landmark_groups, **options)[0] + centre[seen]
    if alone.size:
        smoothed[:, alone] = smooth_curves(curves[:, alone], ok, **options)[0]  # each its own noise and lambda
    result = to_values(smoothed[ok], np.zeros(v.shape[1]))
    if len(rotation):
        out[np.flatnonzero(ok)[:, None], rotation[None]] = result[:, rotation]
    if len(linear):
        lo, hi = v[ok][:, linear].min(axis=0), v[ok][:, linear].max(axis=0)
        out[np.flatnonzero(ok)[:, None], linear[None]] = np.clip(result[:, linear], lo, hi)
    return out
