"""fit.FlagFailures: no face, energy outliers against the shot's median, and the absolute checks
(the fitted landmarks projected into the camera against the plate's, and the energy as an RMS per
landmark, both in the fitted head's eye distances), which flag a one-frame shot that landed in a
wrong minimum."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, Landmarks2D, ParamSequence, run_node  # noqa: E402
from nodes.fit import FlagFailures  # noqa: E402
from nodes.fit.output_nodes import (FIT_FAILURE_REASONS, MAX_ENERGY_RMS, MAX_REPROJECTION,  # noqa: E402
                                    MIN_OUTLIER_ENERGY_RMS, LandmarkProjection, energy_rms, projected_landmarks68, reprojection_error)
from nodes.io.face_model import load_face_model  # noqa: E402

NOISE_PX = 0.3  # per axis, on the synthetic plate landmarks
BOX = ["x0", "y0", "x1", "y1"]


def _rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


FACING = np.diag([1.0, -1.0, -1.0])  # the model (y up, z out of the face) facing a camera looking down +z


@pytest.fixture(scope="module")
def shot():
    """One frame: the model turned 11.5 deg, 65 cm in front of a 30 deg camera; plate landmarks are its
    68 landmark vertices projected, with 0.3 px of noise."""
    model = load_face_model()
    camera = Camera.from_fov(256, 256, 30.0)
    k = len(model.expression_names)
    truth = np.concatenate([(FACING @ _rot_y(0.2)).ravel(), [1.0, -2.0, 65.0], np.zeros(k)])[None]
    pixels = projected_landmarks68(truth, model, camera).pixels
    marks = pixels + np.random.default_rng(0).normal(scale=NOISE_PX, size=pixels.shape)
    lo, hi = marks[0].min(0), marks[0].max(0)
    half, centre = 0.65 * (hi - lo).max(), (lo + hi) / 2
    box = np.concatenate([centre - half, centre + half])[None]
    return model, camera, truth, Landmarks2D(marks.astype(np.float32), np.ones((1, 68), np.float32)), \
        ParamSequence(box.astype(np.float32), BOX)


def _rigid_fit(shot, rot: np.ndarray | None, iterations: int) -> tuple[np.ndarray, float]:
    """The rigid stages on the model's landmark vertices from the usual start (`rot` None) or from
    that start turned to `rot`; (1, 12 + K) fitted values and the final energy."""
    from nodes.fit.node_inputs import _fit_model, _pose_values, _views
    from nodes.fit.solve import RIGID_STAGES, PoseState, initial_pose, solve_stage
    from nodes.fit.views import landmark_anchors

    model, camera, _, marks, boxes = shot
    fm = _fit_model(model, None, "cpu")
    views = _views([marks], [boxes], [camera], "cpu")
    state = initial_pose(fm, views)
    if rot is not None:
        state = PoseState(torch.as_tensor(rot, dtype=state.rot.dtype)[None], state.trans, state.weights)
    for stage in RIGID_STAGES:
        state, energy = solve_stage(stage, fm, views, landmark_anchors(fm, 1, 1), state, prior=100.0,
                                    edge_weight=1.0, eyelid_weight=0.2, iterations=iterations)
    return np.concatenate([_pose_values(state), state.weights.numpy()], 1), float(energy[0])


def _flags(shot, fitted: np.ndarray, energy: float, **params) -> ParamSequence:
    model, camera, _, marks, boxes = shot
    names = [f"v{i}" for i in range(fitted.shape[1])]
    return run_node(FlagFailures, params, energy=ParamSequence(np.array([[energy]], np.float32), ["energy"]),
                    failed=ParamSequence(np.zeros((1, 1), np.float32), ["failed"]),
                    fitted=ParamSequence(fitted.astype(np.float32), names), model=model, camera=camera,
                    landmarks=marks, boxes=boxes)["flags"]


def test_reprojection_error_and_energy_rms_in_eye_distances(shot):
    plate = np.zeros((3, 68, 2))
    depth = np.full((3, 68), 50.0)
    eye = np.full(3, 20.0)  # eye distance 20 px
    moved = plate + [3.0, 4.0]  # every point 5 px off: 0.25 eye distances
    np.testing.assert_allclose(reprojection_error(LandmarkProjection(moved, depth, eye), plate), 0.25)
    moved[1] = np.nan  # no pose
    depth[2, 7] = -1.0  # one point behind the camera: a pose that cannot be seen
    got = reprojection_error(LandmarkProjection(moved, depth, eye), plate)
    assert got[0] == pytest.approx(0.25) and np.isnan(got[1]) and got[2] == np.inf
    # energy 68 * 4^2 256-crop px^2 = 4 crop px per point; a 512 px box: 8 image px = 0.4 eye distances
    assert energy_rms(np.array([68 * 16.0]), np.array([[0.0, 0.0, 512.0, 512.0]]), np.array([20.0]))[0] == \
        pytest.approx(0.4)
    # the fitted head's eye distance does not shrink as it turns: f * |v36 - v45| / depth of their midpoint
    model, camera, truth, _, _ = shot
    turned = truth.copy()
    turned[0, :9] = (FACING @ _rot_y(1.2)).ravel()  # 69 deg
    b = projected_landmarks68(turned, model, camera)
    eye_cm = np.linalg.norm(np.subtract(*model.neutral[model.landmarks][[36, 45]]))
    assert b.eye_px[0] == pytest.approx(camera.fx * eye_cm / b.depth[0, [36, 45]].mean(), rel=1e-6)  # float32 model
    assert np.linalg.norm(b.pixels[0, 36] - b.pixels[0, 45]) < 0.6 * b.eye_px[0]  # the plate's 2D one does


def test_a_one_frame_wrong_minimum_is_flagged_and_a_good_fit_is_not(shot):
    model, camera, truth, marks, _ = shot
    eye = float(np.linalg.norm(marks.points[0, 36] - marks.points[0, 45]))
    good, good_energy = _rigid_fit(shot, None, iterations=10)
    # the usual start converges: the translation within 1 cm of the truth, and the landmarks within the noise
    assert np.abs(good[0, 9:12] - truth[0, 9:12]).max() < 1.0
    flags = _flags(shot, good, good_energy)
    reproj = flags.values[0, flags.names.index("reprojection")]
    # 68 points with N(0, 0.3 px) per axis: RMS distance ~ 0.3 * sqrt(2) = 0.42 px; 3x that, over the eye distance
    assert reproj < 3 * NOISE_PX * np.sqrt(2) / eye < MAX_REPROJECTION
    assert flags.values[0, flags.names.index("energy_rms")] < MAX_ENERGY_RMS
    assert flags.values[0, 0] == 0 and flags.values[0, flags.names.index("reason")] == 0

    # a deliberately wrong start (the head turned away from the camera) with a short budget: a wrong minimum
    bad, bad_energy = _rigid_fit(shot, FACING @ _rot_y(np.pi), iterations=2)
    assert np.abs(bad[0, 9:12] - truth[0, 9:12]).max() > 10.0  # truly wrong (cm)
    flags = _flags(shot, bad, bad_energy)
    failed, ratio, reproj, rms, reason = flags.values[0]
    assert ratio == pytest.approx(1.0)  # one frame: the median check cannot see it
    assert reproj > MAX_REPROJECTION and rms > MAX_ENERGY_RMS and failed == 1 and reason == 3
    assert FIT_FAILURE_REASONS[3].startswith("landmarks reprojected")
    only_energy = _flags(shot, bad, bad_energy, max_reprojection=0.0)  # 0 turns a check off
    assert only_energy.values[0, 0] == 1 and only_energy.values[0, 4] == 4
    off = _flags(shot, bad, bad_energy, max_reprojection=0.0, max_energy_rms=0.0)
    assert off.values[0, 0] == 0 and off.values[0, 2] == pytest.approx(reproj)


def test_the_median_check_and_no_face_keep_their_reasons_and_the_inputs_go_together(shot):
    model, camera, _, marks, _ = shot
    energy = ParamSequence(np.array([[10.0], [11.0], [100.0], [np.nan]], np.float32), ["energy"])
    failed = ParamSequence(np.array([[0.0], [0.0], [0.0], [1.0]], np.float32), ["failed"])
    flags = run_node(FlagFailures, energy=energy, failed=failed)["flags"]
    assert flags.names == ["failed", "energy_ratio", "reprojection", "energy_rms", "reason"]
    assert flags.values[:, 0].tolist() == [0, 0, 1, 1] and flags.values[:, 4].tolist() == [0, 0, 2, 1]
    assert np.isnan(flags.values[:, 2:4]).all()  # no check without its inputs
    with pytest.raises(Exception, match="'camera'.*together.*camera, landmarks not connected"):
        run_node(FlagFailures, energy=energy, failed=failed, model=model,
                 fitted=ParamSequence(np.zeros((4, 12 + len(model.expression_names)), np.float32),
                                      [f"v{i}" for i in range(12 + len(model.expression_names))]))


def test_a_relative_outlier_that_still_fits_well_is_not_a_failure(shot):
    """A shot fitted to a few % of the eye distance has a tiny median energy: a frame 10x above it
    is no failure while its energy_rms stays under min_outlier_energy_rms; above that it is."""
    model, camera, _, marks, boxes = shot
    good, good_energy = _rigid_fit(shot, None, iterations=10)
    three = np.repeat(good, 3, 0)
    box = boxes.values.astype(np.float64)
    eye = projected_landmarks68(good, model, camera).eye_px
    rms_good = float(energy_rms(np.array([good_energy]), box, eye)[0])
    # energy_rms grows as the square root of the energy: pick the outlier's energy for a target rms
    just_under = (0.9 * MIN_OUTLIER_ENERGY_RMS / rms_good) ** 2 * good_energy
    between = ((MIN_OUTLIER_ENERGY_RMS + MAX_ENERGY_RMS) / 2 / rms_good) ** 2 * good_energy
    assert just_under > 4 * good_energy  # a relative outlier by the factor 4

    def flags(outlier: float, **params) -> np.ndarray:
        energy = np.array([[good_energy], [good_energy], [outlier]], np.float32)
        return run_node(FlagFailures, params, energy=ParamSequence(energy, ["energy"]),
                        failed=ParamSequence(np.zeros((3, 1), np.float32), ["failed"]),
                        fitted=ParamSequence(three.astype(np.float32), [f"v{i}" for i in range(three.shape[1])]),
                        model=model, camera=camera,
                        landmarks=Landmarks2D(np.repeat(marks.points, 3, 0), np.repeat(marks.confidence, 3, 0)),
                        boxes=ParamSequence(np.repeat(boxes.values, 3, 0), BOX))["flags"].values

    kept = flags(just_under)
    assert kept[2, 1] > 4 and kept[2, 3] == pytest.approx(0.9 * MIN_OUTLIER_ENERGY_RMS, rel=1e-3)
    assert kept[:, 4].tolist() == [0, 0, 0]
    assert flags(just_under, min_outlier_energy_rms=0.0)[:, 4].tolist() == [0, 0, 2]  # the ratio alone
    assert flags(between)[:, 4].tolist() == [0, 0, 2]  # above the floor, under max_energy_rms: the ratio decides
