"""eyeLook weights from the iris centres (nodes.fit.energy.iris_model_points, nodes.fit.solve.eye_stage,
fit.Expression's `iris` port) on synthetic frames with known weights: the model's 68 landmark vertices
and its iris centres projected, the iris centres turned exactly (not by the fit's linear model) and
with noise."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, InputError, Landmarks2D, NodeError, ParamSequence, run_node  # noqa: E402
from nodes.fit import Expression  # noqa: E402
from nodes.fit.energy import EYE_LOOK_ROTATIONS, IRIS_EYEBALLS, eye_look_shapes, iris_model_points  # noqa: E402
from nodes.fit.node_inputs import POSE_NAMES  # noqa: E402
from nodes.fit.output_nodes import projected_landmarks68  # noqa: E402
from nodes.geometry.camera import project_points  # noqa: E402
from nodes.geometry.rotation import axis_angle_to_rotmat  # noqa: E402
from nodes.io.arkit import EYE_RANGE_RAD  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402

NOISE_PX = 0.3
FRAMES = 4
FACING = np.diag([1.0, -1.0, -1.0])  # the model (y up, z out of the face) facing a camera looking down +z
BOX = ["x0", "y0", "x1", "y1"]


def _true_iris(model, weights: np.ndarray) -> np.ndarray:
    """(F, 2, 3) iris centres, model frame: each eyeball's front vertex turned exactly by its yaw and
    pitch (`nodes.io.arkit.eye_angles`: EYE_RANGE_RAD per unit weight, R = R_y(yaw) R_x(pitch))."""
    names = list(model.expression_names)
    w = {n: weights[:, names.index(n)] for n in EYE_LOOK_ROTATIONS}
    out = np.zeros((len(weights), 2, 3))
    for e, side in enumerate("RL"):
        ball = model.neutral[model.groups[IRIS_EYEBALLS[e]]].astype(np.float64)
        a = np.concatenate([2.0 * ball, np.ones((len(ball), 1))], 1)
        centre = np.linalg.lstsq(a, (ball ** 2).sum(1), rcond=None)[0][:3]
        front = ball[np.argmax(ball[:, 2])]
        yaw = (w[f"eyeLookOut_{side}"] - w[f"eyeLookIn_{side}"]) * (1 if side == "L" else -1) * EYE_RANGE_RAD
        pitch = (w[f"eyeLookDown_{side}"] - w[f"eyeLookUp_{side}"]) * EYE_RANGE_RAD
        for f in range(len(weights)):
            rot = axis_angle_to_rotmat(np.array([0.0, yaw[f], 0.0])) @ axis_angle_to_rotmat(np.array([pitch[f], 0, 0]))
            out[f, e] = centre + rot @ (front - centre)
    return out


@pytest.fixture(scope="module")
def shot():
    """Four frames of the model 60-70 cm in front of a 512 px, 30 deg camera, turned up to 12 deg,
    jaw slightly open, each eye looking in a random direction (one of In/Out and one of Up/Down at
    0.15-0.8); the 68 landmark vertices projected with NOISE_PX of noise, the iris centres too."""
    model = load_face_model()
    camera = Camera.from_fov(512, 512, 30.0)
    names = list(model.expression_names)
    rng = np.random.default_rng(3)
    k = len(names)
    truth = np.zeros((FRAMES, 12 + k))
    for f in range(FRAMES):
        rot = FACING @ axis_angle_to_rotmat(rng.uniform(-0.2, 0.2, 3))
        truth[f, :12] = np.concatenate([rot.ravel(), [rng.uniform(-2, 2), rng.uniform(-2, 2), rng.uniform(60, 70)]])
        truth[f, 12 + names.index("jawOpen")] = 0.2
        for side in "LR":
            for pair in (("In", "Out"), ("Up", "Down")):
                truth[f, 12 + names.index(f"eyeLook{pair[rng.integers(2)]}_{side}")] = rng.uniform(0.15, 0.8)
    pixels = projected_landmarks68(truth, model, camera).pixels
    marks = pixels + rng.normal(scale=NOISE_PX, size=pixels.shape)
    iris_local = _true_iris(model, truth[:, 12:])
    rot = truth[:, :9].reshape(-1, 3, 3)
    world = iris_local @ rot.transpose(0, 2, 1) + truth[:, None, 9:12]
    iris_px = project_points(world, camera.world_to_camera, np.array([camera.fx, camera.fy, camera.cx, camera.cy]))
    iris_noisy = iris_px + rng.normal(scale=NOISE_PX, size=iris_px.shape)
    iris = np.full((FRAMES, 10, 2), np.nan, np.float32)
    iris[:, 0], iris[:, 5] = iris_noisy[:, 0], iris_noisy[:, 1]  # centres; the rim points are not read
    lo, hi = marks.min(1), marks.max(1)
    half, centre = 0.65 * (hi - lo).max(1, keepdims=True), (lo + hi) / 2
    boxes = np.concatenate([centre - half, centre + half], 1)
    eyes = iris_model_points(model.neutral, [model.groups[g] for g in IRIS_EYEBALLS], names)
    return dict(model=model, camera=camera, truth=truth, boxes=boxes,
                marks=Landmarks2D(marks.astype(np.float32), np.ones((FRAMES, 68), np.float32)),
                box_seq=ParamSequence(boxes.astype(np.float32), BOX),
                iris=Landmarks2D(iris, np.ones((FRAMES, 10), np.float32)),
                eyes=eyes)


def _tolerance(shot, prior: float) -> float:
    """Largest eyeLook weight error the arithmetic allows, from the iris centres alone (the other
    points only add exact information): at the true weights a shape moves its iris centre G
    256-crop pixels per unit weight (the least of the eight shapes over the frames, the projected
    derivative of `iris_points`); the prior shrinks a weight w by at most lambda w / (G^2 + lambda),
    and noise of 4 sigma moves it by 4 sigma sqrt(3/2) (crop pixels: the iris centre's noise and
    half the two corners', `iris_relative`) / G."""
    from nodes.fit.energy import iris_points

    truth, camera = shot["truth"], shot["camera"]
    scale = 256.0 / (shot["boxes"][:, 2] - shot["boxes"][:, 0])
    rot = truth[:, :9].reshape(-1, 3, 3)
    k_vec = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
    front, centres, turns = (torch.as_tensor(a) for a in shot["eyes"])
    point, deriv = iris_points(front, centres, turns, torch.as_tensor(truth[:, 12:]))
    gains = []
    step = 1e-3
    for k in eye_look_shapes(list(shot["model"].expression_names)):
        e = int(np.abs(turns[k].numpy()).sum(1).argmax())
        ends = np.stack([point[:, e].numpy(), (point[:, e] + step * deriv[:, e, k]).numpy()], 1)  # (F, 2, 3)
        px = project_points(ends @ rot.transpose(0, 2, 1) + truth[:, None, 9:12], camera.world_to_camera, k_vec)
        gains.append(np.linalg.norm(px[:, 1] - px[:, 0], axis=-1) / step * scale)
    g = float(np.min(gains))
    top = 0.8
    return prior * top / (g * g + prior) + 4 * NOISE_PX * 1.5 ** 0.5 * float(scale.max()) / g


def _eye_error(shot, weights: np.ndarray) -> np.ndarray:
    idx = eye_look_shapes(list(shot["model"].expression_names))
    return np.abs(weights[:, idx] - shot["truth"][:, 12:][:, idx])


def test_the_iris_model_turns_each_eye_the_way_its_shape_names_say(shot):
    from nodes.fit.energy import iris_points

    names = list(shot["model"].expression_names)
    front, centres, turns = shot["eyes"]
    assert len(eye_look_shapes(names)) == 8
    assert front[0, 0] < 0 < front[1, 0]  # eye 0 the subject's right (model -x)
    assert 1.4 < np.linalg.norm(front[0] - centres[0]) < 1.8  # the front vertex 1.63 cm from the centre
    eye = torch.eye(len(names), dtype=torch.float64)
    moved, _ = iris_points(*(torch.as_tensor(a) for a in shot["eyes"]), eye)  # every shape at weight 1
    moved = moved.numpy() - front[None]
    for name, (e, _) in EYE_LOOK_ROTATIONS.items():
        k = names.index(name)
        assert np.abs(moved[k, 1 - e]).max() < 1e-12
        assert 0.7 < np.linalg.norm(moved[k, e, :2]) < 0.9  # r sin 30 deg
    assert moved[names.index("eyeLookOut_L"), 1, 0] > 0 and moved[names.index("eyeLookIn_R"), 0, 0] > 0  # to the left
    assert moved[names.index("eyeLookDown_L"), 1, 1] < 0 and moved[names.index("eyeLookUp_R"), 0, 1] > 0
    others = [i for i in range(len(names)) if i not in eye_look_shapes(names)]
    assert np.abs(moved[others]).max() < 1e-12
    # the exact turn of the test's truth (R_y(yaw) R_x(pitch), written out here) is `iris_points`'
    w = shot["truth"][:, 12:]
    ref = _true_iris(shot["model"], w)
    got, _ = iris_points(*(torch.as_tensor(a) for a in shot["eyes"]), torch.as_tensor(w))
    assert np.abs(got.numpy() - ref).max() < 1e-9


def test_the_eye_stage_recovers_the_eye_look_weights(shot):
    from nodes.fit.node_inputs import _fit_model, _state_from, _views
    from nodes.fit.solve import eye_stage, solve_stage
    from nodes.fit.views import landmark_anchors

    model, truth = shot["model"], shot["truth"]
    fm = _fit_model(model, None, "cpu", iris=True)
    views = _views([shot["marks"]], [shot["box_seq"]], [shot["camera"]], "cpu", iris=[shot["iris"]])
    start = truth[:, 12:].copy()
    start[:, eye_look_shapes(list(model.expression_names))] = 0.0
    state = _state_from(truth[:, :12].astype(np.float32), start.astype(np.float32), "cpu")
    prior = 4.0
    stage = eye_stage(list(model.expression_names), iris_weight=1.0, prior=prior)
    out, _ = solve_stage(stage, fm, views, landmark_anchors(fm, FRAMES, 1), state, prior=100.0, edge_weight=1.0,
                         eyelid_weight=0.0, iterations=30)
    err = _eye_error(shot, out.weights.numpy())
    tol = _tolerance(shot, prior)
    assert tol < 0.2  # the test can tell a look from none (the weights are 0.15-0.8)
    assert err.max() < tol, (err.max(), tol)
    assert np.allclose(out.rot.numpy(), state.rot.numpy()) and np.allclose(out.trans.numpy(), state.trans.numpy())
    # without the iris the same stage leaves the weights where the eyelids' exact points are: not at 0
    no_iris = _views([shot["marks"]], [shot["box_seq"]], [shot["camera"]], "cpu")
    blind, _ = solve_stage(stage, fm, no_iris, landmark_anchors(fm, FRAMES, 1), state, prior=100.0, edge_weight=1.0,
                           eyelid_weight=0.0, iterations=30)
    assert _eye_error(shot, blind.weights.numpy()).max() > 2 * err.max()


def _expression(shot, **ports):
    truth = shot["truth"]
    return run_node(Expression, {"rounds": 1, "iterations": 10}, landmarks=[shot["marks"]],
                    boxes=[shot["box_seq"]], cameras=[shot["camera"]], model=shot["model"],
                    pose=ParamSequence(truth[:, :12].astype(np.float32), list(POSE_NAMES)), **ports)


def test_expression_reads_the_iris_and_is_unchanged_without_it(shot):
    plain = _expression(shot)["fitted"].values
    blank = Landmarks2D(np.full((FRAMES, 10, 2), np.nan, np.float32), np.ones((FRAMES, 10), np.float32))
    unread = _expression(shot, iris=[blank])["fitted"].values
    with_iris = _expression(shot, iris=[shot["iris"]])["fitted"].values
    eyes = [12 + i for i in eye_look_shapes(list(shot["model"].expression_names))]
    assert np.array_equal(plain, unread)  # no iris read: the result of no iris port
    assert np.abs(plain[:, eyes]).max() == 0.0  # without the iris the eyeLook weights are not solved
    rest = [i for i in range(plain.shape[1]) if i not in eyes]
    assert np.array_equal(plain[:, rest], with_iris[:, rest])  # the eye stage comes last and moves only them
    err = np.abs(with_iris[:, eyes] - shot["truth"][:, eyes])
    # Here the plate's 68 points are the model's landmark vertices, but the node compares them with the
    # network's reading of its renders (anchors + offsets), which sits a few pixels off those vertices
    # (the eye corners too), so the pose is off by up to 2 cm in depth and the relative iris by the
    # corners' offsets: the plumbing is checked here (the weights move most of the way to the truth:
    # measured mean error 0.09 against 0.25 for no look), the accuracy in the stage test above.
    err = np.abs(with_iris[:, eyes] - shot["truth"][:, eyes]).mean()
    assert err < 0.5 * np.abs(shot["truth"][:, eyes]).mean(), err


def test_the_relative_iris_rows_jacobian_matches_forward_autodiff(shot):
    from nodes.fit.node_inputs import _fit_model, _state_from, _views
    from nodes.fit.solve import _iris_rows, _stage_jacobian, _stage_residuals, _with_iris, eye_stage
    from nodes.fit.views import at_anchors, landmark_anchors

    model, truth = shot["model"], shot["truth"]
    fm = _fit_model(model, None, "cpu", iris=True)
    views = _views([shot["marks"]], [shot["box_seq"]], [shot["camera"]], "cpu", iris=[shot["iris"]])
    anchors = landmark_anchors(fm, FRAMES, 1)
    stage = eye_stage(list(model.expression_names))
    w_lm = torch.full((68,), 0.5)
    views, anchors, w_lm, used = _with_iris(stage, fm, views, anchors, w_lm)
    assert used and w_lm.shape == (FRAMES, 1, 74)
    d64 = torch.float64
    views = type(views)(**{k: (v.to(d64) if torch.is_tensor(v) and v.is_floating_point() else v)
                           for k, v in vars(views).items()})
    state = _state_from(truth[:, :12].astype(np.float32), truth[:, 12:].astype(np.float32) * 0.5, "cpu")
    weights = state.weights.to(d64)
    rows = _iris_rows(fm, weights, 1)
    neutral = torch.cat([at_anchors(fm.neutral, anchors.vertices, anchors.bary).to(d64), rows[0]], 2)
    deltas = torch.cat([at_anchors(fm.deltas, anchors.vertices, anchors.bary).to(d64), rows[1]], 2)
    anchors = anchors._replace(offset=anchors.offset.to(d64))
    shapes = torch.as_tensor(stage.shapes)
    x = torch.cat([torch.zeros(FRAMES, 3, dtype=d64), state.trans.to(d64), weights[:, shapes]], 1)
    kw = dict(prior=4.0, edge_weight=1.0, rigid_prior=None, rigid_prior_weight=0.0, iris=True)
    rot0 = state.rot.to(d64)
    jac = _stage_jacobian(neutral, deltas, views, rot0, weights, shapes, w_lm.to(d64), x, **kw)
    fn = _stage_residuals(neutral, deltas, views, anchors, rot0, weights, shapes, w_lm.to(d64), **kw)
    ref = torch.func.jacfwd(lambda d: fn(x + d[None]))(torch.zeros(x.shape[1], dtype=d64))
    torch.testing.assert_close(jac, ref, atol=1e-8, rtol=1e-8)


def test_iris_inputs_are_checked(shot):
    with pytest.raises((InputError, NodeError), match="iris.*expected"):
        _expression(shot, iris=[Landmarks2D(np.zeros((FRAMES, 5, 2), np.float32), np.ones((FRAMES, 5), np.float32))])
    with pytest.raises((InputError, NodeError), match="iris.*expected"):
        _expression(shot, iris=[shot["iris"], shot["iris"]])


def test_the_eyes_sit_at_the_mean_heads_place_from_the_corners_whatever_the_identity():
    """`iris_model_points_at_corners` (what the fit uses) reproduces the mean head's own eyeballs
    (`iris_model_points`: its constants are that measurement, rounded to 1e-4 eye distances, so
    within 6.5e-4 cm x sqrt(3) of it), and under an extreme identity (3 sigma on every component)
    keeps the eyes at the mean head's offsets from that identity's corners, where the identity's
    own eyeballs drift away."""
    from nodes.fit.energy import IRIS_CORNERS_68, IRIS_FRONT_FROM_CORNERS, iris_model_points_at_corners

    model = load_face_model()
    names = list(model.expression_names)
    balls = [model.groups[g] for g in IRIS_EYEBALLS]
    front, centres, turns = iris_model_points(model.neutral, balls, names)
    got = iris_model_points_at_corners(model.neutral, model.landmarks, names)
    assert np.abs(got[0] - front).max() < 1.2e-3 and np.abs(got[1] - centres).max() < 1.2e-3
    assert np.array_equal(got[2], turns)
    rng = np.random.default_rng(0)
    neutral = model.neutral + np.einsum("i,ivc->vc", 3.0 * np.sign(rng.normal(size=40)), model.identity_deltas)
    points = neutral[model.landmarks].astype(np.float64)
    eye_distance = np.linalg.norm(points[36:42].mean(0) - points[42:48].mean(0))
    mid = points[IRIS_CORNERS_68].mean(1)
    placed = iris_model_points_at_corners(neutral, model.landmarks, names)[0]
    assert np.allclose((placed - mid) / eye_distance, IRIS_FRONT_FROM_CORNERS, atol=1e-9)
