"""All of a shot's curves are smoothed in one batch (`whittaker_batch`, `_smooth_batch`): each curve
comes out exactly as it does alone, whatever the other curves' noise, lambda, mask or failures."""

from __future__ import annotations

import numpy as np

from nodes.temporal.adaptive import smooth_curve, smooth_curves, smooth_pose_and_weights, whittaker, whittaker_batch


def _curves(frames: int = 80) -> np.ndarray:
    """(frames, 5): a slow sine at noise 0.005, one at 0.05, a blink at 0.02, a constant, a ramp with NaNs."""
    rng = np.random.default_rng(3)
    t = np.arange(frames, dtype=np.float64)
    blink = np.full(frames, 0.05)
    blink[40:44] = [0.5, 0.95, 0.95, 0.5]
    curves = np.stack([np.sin(t / 15) + rng.normal(0, 0.005, frames), 0.3 * np.cos(t / 9) + rng.normal(0, 0.05, frames),
                       blink + rng.normal(0, 0.02, frames), np.full(frames, 0.2),
                       0.01 * t + rng.normal(0, 0.01, frames)], 1)
    curves[[5, 6, 30], 4] = np.nan
    return curves


def test_the_batched_solve_is_each_curve_solved_alone():
    rng = np.random.default_rng(0)
    d, f = 4, 30
    x = rng.normal(size=(d, f))
    lam = np.array([0.1, 3.0, 100.0, 1e6])
    mask = (rng.random((d, f)) > 0.2).astype(np.float64)
    c = rng.random((d, f - 2))
    batch = whittaker_batch(x, lam, mask, c)
    for j in range(d):
        np.testing.assert_array_equal(batch[j], whittaker(x[j], lam[j], mask[j], c[j]))
        dense_d2 = np.diff(np.eye(f), 2, axis=0)  # (f - 2, f) second difference
        normal = np.diag(mask[j] + 1e-12 * (1 + lam[j])) + lam[j] * dense_d2.T @ np.diag(c[j]) @ dense_d2
        # both solves are backward stable: they agree to about eps * cond(normal) (1e6 lambda: ~1e-4)
        tolerance = 1e-14 * np.linalg.cond(normal) * np.abs(batch[j]).max()
        np.testing.assert_allclose(batch[j], np.linalg.solve(normal, mask[j] * x[j]), rtol=0, atol=tolerance)


def test_the_batched_smoothing_is_each_curve_smoothed_alone():
    curves = _curves()
    batch, sigmas = smooth_curves(curves)
    for j in range(curves.shape[1]):
        alone = smooth_curve(curves[:, j])
        np.testing.assert_array_equal(batch[:, j], alone.values)
        assert sigmas[j] == alone.sigma
    assert sigmas[3] == 0.0 and np.array_equal(batch[:, 3], curves[:, 3])  # a constant is left alone
    assert np.isfinite(batch[:, 4]).all()  # its unknown frames filled from the neighbours


def test_pose_and_weights_are_each_smoothed_alone():
    """One batch of rotation vectors and linear columns against the columns smoothed one by one."""
    curves = _curves()[:, [0, 1, 2, 4]]
    curves[:, :3] *= 0.1  # radians
    failed = np.zeros(len(curves), bool)
    failed[[10, 11, 50]] = True
    out = smooth_pose_and_weights(curves, np.zeros(0, np.int64), np.arange(4), failed)
    ok = ~failed & np.isfinite(curves).all(1)
    for j in range(4):
        alone = smooth_curve(np.where(ok, curves[:, j], np.nan), ok).values
        np.testing.assert_array_equal(out[ok, j], np.clip(alone[ok], curves[ok, j].min(), curves[ok, j].max()))
    np.testing.assert_array_equal(out[~ok], curves[~ok])  # failed frames as given, NaN included
