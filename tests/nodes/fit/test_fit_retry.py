"""fit.RigidPose's retry (issue 30): a frame whose rigid fit fit.FlagFailures' absolute checks
would flag (landmarks reprojected more than MAX_REPROJECTION eye distances, or the energy above
MAX_ENERGY_RMS) is solved again from other starts (`nodes.fit.solve.retry_from_starts`), and a
frame that fitted well is not touched (bit for bit, no extra solve)."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, Landmarks2D, ParamSequence, run_node  # noqa: E402
from nodes.fit import FlagFailures, RigidPose  # noqa: E402
from nodes.fit.output_nodes import MAX_REPROJECTION, projected_landmarks68  # noqa: E402

from .test_flag_failures import BOX, FACING, NOISE_PX, _rot_y, shot  # noqa: E402,F401  (the fixture)

SIGMAS = 4.0  # the tolerances: this many standard deviations of the least-squares estimate under the noise


def _rigid_solve(fm, views, state, iterations: int = 2):
    """The rigid stages on the model's landmark vertices (test_flag_failures' budget: 2 iterations)."""
    from nodes.fit.solve import RIGID_STAGES, solve_stage
    from nodes.fit.views import landmark_anchors

    for stage in RIGID_STAGES:
        state, energy = solve_stage(stage, fm, views, landmark_anchors(fm, views.seen.shape[0], 1), state,
                                    prior=100.0, edge_weight=1.0, eyelid_weight=0.2, iterations=iterations)
    return state, energy


def _pose_std(truth: np.ndarray, model, camera: Camera) -> tuple[float, float]:
    """(rotation deg, depth cm): the spread of a least-squares pose from the 68 projected points with
    N(0, NOISE_PX) per axis, from the Gauss-Newton covariance sigma^2 (J^T J)^-1 at the truth (J by
    central differences in omega (R = exp([omega]) R0) and t); the rotation as the RMS norm of omega."""
    h = 1e-5

    def pixels(x: np.ndarray) -> np.ndarray:
        w = x[:3]
        skew = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        turned = truth.copy()
        turned[0, :9] = ((np.eye(3) + skew + skew @ skew / 2) @ truth[0, :9].reshape(3, 3)).ravel()
        turned[0, 9:12] += x[3:]
        return projected_landmarks68(turned, model, camera).pixels.ravel()

    jac = np.stack([(pixels(h * e) - pixels(-h * e)) / (2 * h) for e in np.eye(6)], 1)
    cov = NOISE_PX ** 2 * np.linalg.inv(jac.T @ jac)
    return float(np.degrees(np.sqrt(np.trace(cov[:3, :3])))), float(np.sqrt(cov[5, 5]))


def _errors(state, truth: np.ndarray) -> tuple[float, float]:
    """(rotation error deg, depth error cm) of a one-frame state."""
    rot = state.rot[0].double().numpy()
    cos = (np.trace(rot @ truth[0, :9].reshape(3, 3).T) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1)))), abs(float(state.trans[0, 2]) - truth[0, 11])


def test_a_start_turned_away_is_retried_and_lands_on_the_truth(shot):
    from nodes.fit.node_inputs import _fit_model, _pose_values, _views
    from nodes.fit.pose_nodes import _landed_wrong
    from nodes.fit.solve import RETRY_YAWS, PoseState, initial_pose, retry_from_starts

    model, camera, truth, marks, boxes = shot
    fm = _fit_model(model, None, "cpu")
    views = _views([marks], [boxes], [camera], "cpu")
    usual = initial_pose(fm, views)
    turned = PoseState(torch.as_tensor(FACING @ _rot_y(np.pi), dtype=usual.rot.dtype)[None], usual.trans,
                       usual.weights)
    state, energy = _rigid_solve(fm, views, turned)
    assert abs(float(state.trans[0, 2]) - truth[0, 11]) > 100  # test_flag_failures' wrong minimum (269 vs 65 cm)
    wrong = _landed_wrong(_pose_values(state), state.weights.numpy(), energy.numpy(), model, [camera], [marks],
                          [boxes], np.array([0]))
    assert wrong.tolist() == [True]

    rot_std, depth_std = _pose_std(truth, model, camera)
    assert 0.01 < rot_std < 1.0 and 0.01 < depth_std < 2.0  # the arithmetic's scale (0.3 px noise, 65 cm)
    for yaws in (RETRY_YAWS, RETRY_YAWS[1:]):  # with the usual start among the retries, and as RigidPose runs it
        fixed, fixed_energy, chosen = retry_from_starts(fm, views, state, energy, torch.as_tensor(wrong),
                                                        lambda v, s: _rigid_solve(fm, v, s), yaws)
        rot_err, depth_err = _errors(fixed, truth)
        assert rot_err < SIGMAS * rot_std and depth_err < SIGMAS * depth_std, (yaws, rot_err, depth_err)
        assert int(chosen[0]) > 0 and float(fixed_energy[0]) < float(energy[0])
        values = np.concatenate([_pose_values(fixed), fixed.weights.numpy()], 1)
        flags = run_node(FlagFailures, energy=ParamSequence(fixed_energy.numpy()[:, None].astype(np.float32),
                                                            ["energy"]),
                         failed=ParamSequence(np.zeros((1, 1), np.float32), ["failed"]),
                         fitted=ParamSequence(values.astype(np.float32), [f"v{i}" for i in range(values.shape[1])]),
                         model=model, camera=camera, landmarks=marks, boxes=boxes)["flags"]
        assert flags.values[0, 0] == 0 and flags.values[0, flags.names.index("reprojection")] < MAX_REPROJECTION

    # a frame not marked wrong is not solved again: the same values, and `solve` is never called
    def never(v, s):
        raise AssertionError("solved a frame that was not wrong")

    same, same_energy, chosen = retry_from_starts(fm, views, state, energy, torch.zeros(1, dtype=torch.bool), never)
    assert same is state and same_energy is energy and chosen.tolist() == [0]


def _turned_shot(model, camera: Camera, yaw_deg: float) -> tuple[Landmarks2D, ParamSequence]:
    """test_flag_failures' shot with the head turned `yaw_deg`: projected landmark vertices + 0.3 px noise."""
    k = len(model.expression_names)
    truth = np.concatenate([(FACING @ _rot_y(np.radians(yaw_deg))).ravel(), [1.0, -2.0, 65.0], np.zeros(k)])[None]
    pixels = projected_landmarks68(truth, model, camera).pixels
    marks = pixels + np.random.default_rng(0).normal(scale=NOISE_PX, size=pixels.shape)
    lo, hi = marks[0].min(0), marks[0].max(0)
    half, centre = 0.65 * (hi - lo).max(), (lo + hi) / 2
    box = np.concatenate([centre - half, centre + half])[None]
    return Landmarks2D(marks.astype(np.float32), np.ones((1, 68), np.float32)), \
        ParamSequence(box.astype(np.float32), BOX)


def test_rigid_pose_node_retries_only_frames_that_landed_wrong(shot):
    """The node (renders read by the face mesh network): the good frame gives the same bits with and
    without `retry` and is not retried; a frame the absolute checks flag (the head turned 60 deg,
    one round of 2 iterations) is retried and keeps an energy at most the first solve's."""
    model, camera, _, marks, boxes = shot
    runs = {retry: run_node(RigidPose, {"retry": retry}, landmarks=[marks], boxes=[boxes], cameras=[camera],
                            model=model) for retry in (True, False)}
    for port in ("pose", "energy", "failed"):
        np.testing.assert_array_equal(runs[True][port].values, runs[False][port].values)
    assert runs[True]["retried"].names == ["retried", "start"]
    assert runs[True]["retried"].values.tolist() == [[0.0, -1.0]] == runs[False]["retried"].values.tolist()

    marks60, boxes60 = _turned_shot(model, camera, 60.0)
    params = {"iterations": 2, "rounds": 1}
    first = run_node(RigidPose, {**params, "retry": False}, landmarks=[marks60], boxes=[boxes60], cameras=[camera],
                     model=model)
    again = run_node(RigidPose, params, landmarks=[marks60], boxes=[boxes60], cameras=[camera], model=model)
    assert again["retried"].values[0, 0] == 1 and first["retried"].values[0, 0] == 0
    assert again["energy"].values[0, 0] <= first["energy"].values[0, 0]
    if again["retried"].values[0, 1] == 0:  # the first solve kept: the same bits
        np.testing.assert_array_equal(again["pose"].values, first["pose"].values)
