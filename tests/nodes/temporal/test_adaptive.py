"""Adaptive edge-preserving smoothing (nodes.temporal.adaptive, temporal.AdaptiveSmooth) on curves
whose truth is known: the noise is measured, the error to the truth falls below 3-frame
averaging's, a blink keeps its depth, failed frames are left alone, and a head turned 180 degrees
(the fit's world) is smoothed like any other."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import ParamSequence, run_node
from nodegraph.performance import POSE_COLUMNS
from nodes.temporal import AdaptiveSmooth, Average
from nodes.temporal.adaptive import noise_sigma, smooth_curve, whittaker

F = 150


def _curves(seed: int, sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """A slow curve and a blink (0.05 -> 0.95 over 4 frames), with white noise of `sigma`."""
    t = np.arange(F)
    slow = 0.4 + 0.2 * np.sin(t / 9.0) + 0.1 * np.sin(t / 23.0)
    blink = np.full(F, 0.05)
    blink[70:74] = [0.5, 0.95, 0.95, 0.5]
    truth = np.stack([slow, blink], 1)
    return truth, truth + np.random.default_rng(seed).normal(0, sigma, truth.shape)


def _average(x: np.ndarray) -> np.ndarray:
    out = x.copy()
    out[1:-1] = 0.25 * x[:-2] + 0.5 * x[1:-1] + 0.25 * x[2:]
    return out


def test_whittaker_solves_its_normal_equations():
    rng = np.random.default_rng(0)
    x, m, c = rng.normal(size=12), rng.uniform(0.5, 1, 12), rng.uniform(0.1, 1, 10)
    d2 = np.zeros((10, 12))
    for r in range(10):
        d2[r, r:r + 3] = [1, -2, 1]
    lam = 3.0
    dense = np.linalg.solve(np.diag(m) + lam * d2.T @ np.diag(c) @ d2, m * x)
    np.testing.assert_allclose(whittaker(x, lam, m, c), dense, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("sigma", [0.005, 0.02, 0.05])
def test_noise_is_measured_from_the_curve(sigma):
    truth, noisy = _curves(1, sigma)
    for j in range(2):
        assert noise_sigma(noisy[:, j]) == pytest.approx(sigma, rel=0.25)


@pytest.mark.parametrize(("sigma", "least_depth"), [(0.005, 0.95), (0.02, 0.92), (0.05, 0.80)])
def test_adaptive_smoothing_beats_averaging_and_keeps_the_blink(sigma, least_depth):
    """The blink's depth is the mean of its two full frames less the curve's median, over 0.9.
    3-frame averaging keeps 0.875 of it (both full frames become 0.25 * 0.5 + 0.75 * 0.95 = 0.8375:
    (0.8375 - 0.05) / 0.9), so a smoother that flattens a blink like averaging fails at sigma <= 0.02; the
    depth measured over 4 seeds varies by about sigma / (0.9 * sqrt(8)), 0.02 at sigma 0.05,
    where the bound leaves room for the noise's own loss (bench/smoothing.py: 0.87)."""
    errors = {"raw": [], "average": [], "adaptive": []}
    depths = []
    for seed in range(4):
        truth, noisy = _curves(seed, sigma)
        smoothed = np.stack([smooth_curve(noisy[:, j]).values for j in range(2)], 1)
        for name, y in (("raw", noisy), ("average", _average(noisy)), ("adaptive", smoothed)):
            errors[name].append(np.sqrt(np.mean((y - truth) ** 2)))
        depths.append((smoothed[71:73, 1].mean() - np.median(smoothed[:, 1])) / 0.9)
    mean = {k: np.mean(v) for k, v in errors.items()}
    assert mean["adaptive"] < min(mean["average"], mean["raw"]), mean  # at 0.005, averaging is worse than raw
    assert np.mean(depths) > least_depth, depths


def test_a_clean_curve_is_left_nearly_alone():
    truth, _ = _curves(0, 0.0)
    out = smooth_curve(truth[:, 1] + np.random.default_rng(0).normal(0, 1e-4, F)).values
    assert np.abs(out - truth[:, 1]).max() < 2e-3


def _fitted(rotvecs: np.ndarray, weights: np.ndarray) -> ParamSequence:
    from scipy.spatial.transform import Rotation

    flip = Rotation.from_matrix(np.diag([1.0, -1.0, -1.0]))  # the fit's world: 180 degrees about x
    rot = (flip * Rotation.from_rotvec(rotvecs)).as_matrix().reshape(-1, 9)
    trans = np.tile([0.0, 0.0, 60.0], (len(rotvecs), 1))
    names = list(POSE_COLUMNS) + ["jawOpen", "eyeBlink_L"]
    return ParamSequence(np.concatenate([rot, trans, weights], 1).astype(np.float32), names)


def test_adaptive_smooth_node_smooths_pose_and_weights_of_a_fit():
    from scipy.spatial.transform import Rotation

    t = np.arange(F)
    rng = np.random.default_rng(3)
    true_rot = np.stack([0.1 * np.sin(t / 15), 0.3 * np.sin(t / 20), 0.05 * np.sin(t / 11)], 1)
    truth_w, noisy_w = _curves(3, 0.02)
    noisy = _fitted(true_rot + rng.normal(0, 0.01, (F, 3)), np.clip(noisy_w, 0, 1))
    failed = np.zeros((F, 1), np.float32)
    failed[40] = 1
    flags = ParamSequence(failed, ["failed"])
    out = run_node(AdaptiveSmooth, fitted=noisy, failed=flags)["smoothed"]
    avg = run_node(Average, fitted=noisy, failed=flags)["averaged"]
    truth = _fitted(true_rot, truth_w)
    np.testing.assert_array_equal(out.values[40], noisy.values[40])  # failed: left as given
    assert out.values[:, 12:].min() >= 0 and out.values[:, 12:].max() <= 1

    def rot_err(seq):
        a = Rotation.from_matrix(seq.values[:, :9].reshape(-1, 3, 3).astype(np.float64))
        b = Rotation.from_matrix(truth.values[:, :9].reshape(-1, 3, 3).astype(np.float64))
        return np.delete((a.inv() * b).magnitude(), 40).mean()

    def weight_err(seq):
        return np.sqrt(np.mean(np.delete(seq.values[:, 12:] - truth.values[:, 12:], 40, axis=0) ** 2))

    assert rot_err(out) < rot_err(avg) < rot_err(noisy)
    assert weight_err(out) < weight_err(avg) < weight_err(noisy)
    pose_only = run_node(AdaptiveSmooth, {"weights": False}, fitted=noisy)["smoothed"]
    np.testing.assert_array_equal(pose_only.values[:, 12:], noisy.values[:, 12:])


def test_adaptive_smooth_node_keeps_blinks_and_beats_averaging_on_a_known_head_performance():
    """A known head performance (slow pose, a jaw snap, blinks 0.05 -> 0.95 over 4 frames) under
    fit-like noise (0.01 rad, 0.15 cm, weights 0.03), 3 seeds, as bench/smoothing.py's
    known_shot_rows (5 seeds there: rotation error 0.234 deg against averaging's 0.286, blink
    depth 0.94 against 0.86). Averaging keeps 0.875 of a noise-free blink; the depth estimate over
    4 blinks x 3 seeds varies by about 0.03 / 0.9 / sqrt(24) = 0.007, so 0.90 fails a smoother
    that flattens blinks like averaging."""
    from nodegraph import ParamSequence, run_node
    from nodes.temporal import AdaptiveSmooth, Average
    from nodes.temporal.layout import RIGID_NAMES
    from tests.support.synthetic import head_motion

    names = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "eyeBlinkRight"]
    frames, errors, depths = 90, {"average": [], "adaptive": []}, []
    for seed in range(3):
        truth = head_motion(frames, names, seed=seed, mouth_frames=(40, 46)).astype(np.float64)
        truth[:, 8:10] = 0.05
        truth[20:24, 8:10] = truth[65:69, 8:10] = np.array([0.5, 0.95, 0.95, 0.5])[:, None]
        rng = np.random.default_rng(100 + seed)
        noisy = truth + np.concatenate([rng.normal(0, 0.01, (frames, 3)), rng.normal(0, 0.15, (frames, 3)),
                                        rng.normal(0, 0.03, (frames, 4))], 1)
        fitted = ParamSequence(noisy.astype(np.float32), list(RIGID_NAMES) + names)
        outs = {"average": run_node(Average, fitted=fitted)["averaged"].values,
                "adaptive": run_node(AdaptiveSmooth, fitted=fitted)["smoothed"].values}
        for name, y in outs.items():
            errors[name].append(np.abs(y[:, :6] - truth[:, :6]).mean(0))
        y = outs["adaptive"]
        depths += [(y[s:s + 2, b].mean() - np.median(y[:, b])) / 0.9 for b in (8, 9) for s in (21, 66)]
    mean = {k: np.mean(v, 0) for k, v in errors.items()}
    assert np.all(mean["adaptive"] < mean["average"]), mean  # each rotation and translation component
    assert np.mean(depths) > 0.90, depths
