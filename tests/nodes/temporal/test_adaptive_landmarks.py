"""temporal.AdaptiveSmooth with a model and a camera: the pose and the weights smoothed together in
the metric of the projected 68 landmarks (nodes.temporal.adaptive.smooth_in_landmark_metric), on
a per-frame fit whose truth is known.

The per-frame fit is simulated as the real one behaves: each frame's parameters are the least
squares solution from its 68 projected landmarks with white pixel noise (linearized at the truth),
the weights pulled toward 0 by a prior and clipped to [0, 1]. Its weight noise is therefore large
and correlated where the landmarks barely tell shapes apart, and pinned at 0 with spikes, as on
real video (bench/smoothing.py prints the same comparison on more seeds and noise levels).
"""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import Camera, ParamSequence, run_node
from nodes.geometry.rotation import rotmat_to_axis_angle
from nodes.temporal import AdaptiveSmooth, Average
from nodes.temporal.adaptive import smooth_in_landmark_metric
from nodes.temporal.layout import FIT_TRANSLATION_NAMES, MATRIX_NAMES, params_layout
from nodes.temporal.nodes import _projected_landmarks_function
from tests.support.synthetic import (LANDMARK_FIT_BLINKS, LANDMARK_FIT_FRAMES, landmark_fit_truth,
                                     per_frame_landmark_fit)

F = LANDMARK_FIT_FRAMES
BLINKS = LANDMARK_FIT_BLINKS  # first frame of each 4-frame blink: 0.05 -> 0.5, 0.95, 0.95, 0.5 -> 0.05


@pytest.fixture(scope="module")
def scene():
    from nodes.io.face_model import load_face_model

    model = load_face_model()
    camera = Camera.from_fov(256, 256, 40.0)
    names = list(MATRIX_NAMES) + list(FIT_TRANSLATION_NAMES) + list(model.expression_names)
    project = _projected_landmarks_function(model, camera, params_layout(names, list(model.expression_names)))
    return model, camera, names, project


def _measures(y: np.ndarray, truth: np.ndarray, project) -> dict[str, float]:
    """Errors to the truth (rotation deg, landmarks px RMS, weights RMS), landmark roughness
    (px^2) and the blinks' closing of the eyelids (px, frames 1-2 of each blink less the median)."""
    points, true_points = project(y).reshape(F, 68, 2), project(truth).reshape(F, 68, 2)
    relative = np.einsum("fji,fjk->fik", truth[:, :9].reshape(-1, 3, 3), y[:, :9].reshape(-1, 3, 3))
    lid = np.linalg.norm(points[:, [37, 38, 43, 44]] - points[:, [41, 40, 47, 46]], axis=2).mean(1)
    return {"rotation": float(np.degrees(np.linalg.norm(rotmat_to_axis_angle(relative), axis=1)).mean()),
            "landmarks": float(np.sqrt(np.mean(np.sum((points - true_points) ** 2, 2)))),
            "weights": float(np.sqrt(np.mean((y[:, 12:] - truth[:, 12:]) ** 2))),
            "roughness": float(np.mean(np.sum(np.diff(points, 2, axis=0) ** 2, 2))),
            "blink": float(np.median(lid) - np.mean([lid[b + 1:b + 3].mean() for b in BLINKS]))}


def test_landmark_metric_smoothing_beats_averaging_on_a_known_fit(scene):
    """Over 3 seeds at 0.3 px of landmark noise (bench/smoothing.py, 3 seeds: errors rotation
    0.127 / 0.153 deg, landmarks 0.406 / 0.450 px, weights 0.0445 / 0.0482 adaptive / averaged;
    the eyelids' blink 0.80 / 0.83 of the truth's, raw 0.92): every error below averaging's, the
    landmarks at most half as rough as the raw fit's, the blinks at least 0.7 of their depth."""
    model, camera, names, project = scene
    got = {"raw": [], "average": [], "adaptive": []}
    truths = []
    for seed in range(3):
        truth = landmark_fit_truth(seed, list(model.expression_names))
        fitted = per_frame_landmark_fit(truth, project, seed, 0.3)
        seq = ParamSequence(fitted.astype(np.float32), names)
        got["raw"].append(_measures(fitted, truth, project))
        got["average"].append(_measures(run_node(Average, fitted=seq)["averaged"].values.astype(np.float64),
                                        truth, project))
        got["adaptive"].append(_measures(run_node(AdaptiveSmooth, fitted=seq, model=model, camera=camera)[
            "smoothed"].values.astype(np.float64), truth, project))
        truths.append(_measures(truth, truth, project))
    mean = {k: {m: np.mean([r[m] for r in v]) for m in v[0]} for k, v in got.items()}
    for error in ("rotation", "landmarks", "weights"):
        assert mean["adaptive"][error] < mean["average"][error], (error, mean)
    assert mean["adaptive"]["roughness"] < 0.5 * mean["raw"]["roughness"], mean
    assert mean["adaptive"]["blink"] > 0.7 * np.mean([t["blink"] for t in truths]), mean


def test_sigma_is_the_landmark_noise_and_a_clean_shot_is_left_nearly_alone():
    """J orthonormal times 2 (M = D = 6): landmark noise per frame = 2 sqrt(6) x the parameter
    noise; the median of a chi-square with 6 degrees of freedom is 0.89 of its mean, so
    sigma lands within 15% over 400 frames. Noise-free slower curves (second differences up to
    1e-4, which the noise measure takes for noise) move by at most 0.85 of their sigma."""
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
    jac = 2.0 * q
    t = np.arange(400)[:, None]
    slow = np.sin(t / np.array([[20.0, 25, 30, 35, 40, 45]]))
    y, sigma, lam, rms = smooth_in_landmark_metric(slow + rng.normal(0, 0.01, slow.shape), jac)
    assert sigma == pytest.approx(2 * np.sqrt(6) * 0.01, rel=0.15)
    assert rms == pytest.approx(0.85 * sigma, rel=0.05)
    assert np.sqrt(np.mean((y - slow) ** 2)) < 0.01 / 2  # the noise is more than halved
    slower = np.sin(t / np.array([[100.0, 120, 140, 160, 180, 200]]))
    clean, sigma_clean, _, _ = smooth_in_landmark_metric(slower, jac)
    assert sigma_clean < 2 * np.sqrt(6) * 1e-4
    assert np.sqrt(np.mean(np.sum(((clean - slower) @ jac.T) ** 2, 1))) <= 0.85 * sigma_clean + 1e-12


def test_failed_frames_are_filled_not_used_and_left_alone_by_the_node(scene):
    model, camera, names, project = scene
    truth = landmark_fit_truth(0, list(model.expression_names))
    fitted = per_frame_landmark_fit(truth, project, 0, 0.3)
    fitted[30:33] = np.nan
    failed = ParamSequence(np.isnan(fitted[:, :1]).astype(np.float32), ["failed"])
    out = run_node(AdaptiveSmooth, fitted=ParamSequence(fitted.astype(np.float32), names), failed=failed,
                   model=model, camera=camera)["smoothed"].values
    assert np.isnan(out[30:33]).all() and np.isfinite(np.delete(out, [30, 31, 32], 0)).all()


def test_model_without_camera_is_an_input_error(scene):
    model, camera, names, project = scene
    seq = ParamSequence(landmark_fit_truth(0, list(model.expression_names)).astype(np.float32), names)
    with pytest.raises(Exception, match="'camera': expected both 'model' and 'camera'"):
        run_node(AdaptiveSmooth, fitted=seq, model=model)
    with pytest.raises(Exception, match="'model': expected both 'model' and 'camera'"):
        run_node(AdaptiveSmooth, fitted=seq, camera=camera)
