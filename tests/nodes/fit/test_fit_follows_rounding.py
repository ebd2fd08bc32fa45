"""How far the fit follows a rounding-size change of its input (issue 30).

The fit's solvers and the landmark nodes run torch on one intra-op thread (`Node.torch_threads`),
so the thread count no longer changes their floats (tests/graphs/test_fit_video_threads.py runs
a real photo with 1, 2 and 4 threads in fresh processes). What stays is how far the fit follows
a rounding: other CPUs, or another library build, round the network's plate points differently
(OMP_NUM_THREADS 1 against 2 moved them by 6e-5 px on a 6-frame shot before the pinning). So the
same small synthetic shot is fitted from the network's points and from the points moved by
+-`NUDGE_PX` (twice that).

A well-conditioned solve moves its answer by such a change over the landmarks' lever (|d w / d px|
< 0.1 per px for a weight seen over ~20 px of lip motion; a degree of rotation moves the
landmarks > 1 px at 65 cm and 256 px): < 1e-4 in the weights and < 1e-3 deg. The bounds below are
issue 30's, 0.02 in weights and 0.1 deg, which a flat valley breaks (the float32 solves: 0.79 and
1.5 deg on a real video). Ten times the estimate above, 1e-3 in the weights and 0.01 deg, held
before the compiled CPU render (weights 6e-5, rotation 1.6e-3 deg) and not after it (3.1e-4,
0.0175 deg): the fit still follows a 1e-4 px change ten times more than a well-conditioned solve
would.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")
pytest.importorskip("tflite")

from nodegraph import Camera, ImageSequence, Landmarks2D, run_node  # noqa: E402
from nodes.fit import EstimateIdentity, Expression, RigidPose  # noqa: E402
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402

FRAMES = 2
SIZE = 256
NUDGE_PX = 1e-4
"""Plate landmarks moved by this much in the two nudged fits (see the module docstring)."""


def _nudged(marks: dict, seed: int) -> dict:
    """The network's 68 and 468 plate points, each coordinate moved by +-NUDGE_PX."""
    rng = np.random.default_rng(seed)
    return {k: Landmarks2D(points=(marks[k].points + NUDGE_PX * rng.choice([-1.0, 1.0], marks[k].points.shape))
                           .astype(np.float32), confidence=marks[k].confidence)
            for k in ("landmarks468", "landmarks68")}


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rotations, degrees: 2 asin(|A - B|_F / sqrt 8), exact for rotations and, unlike
    acos of the trace in float32 (whose floor is sqrt(2 * 1.2e-7) rad = 0.028 deg), accurate near 0."""
    d = np.linalg.norm((a.astype(np.float64) - b.astype(np.float64)).reshape(len(a), -1), axis=1)
    return np.degrees(2 * np.arcsin(np.clip(d / 8 ** 0.5, 0, 1)))


def _fit(model, cam, seq, boxes, marks) -> dict:
    where = dict(frames=range(FRAMES), boxes=[boxes], cameras=[cam])
    ident = run_node(EstimateIdentity, {"frames_used": FRAMES, "iterations": 10, "rounds": 2},
                     landmarks=[marks["landmarks468"]], model=model, **where)
    common = dict(landmarks=[marks["landmarks68"]], model=ident["fitted_model"], **where)
    rigid = run_node(RigidPose, {"rounds": 2}, **common)
    expr = run_node(Expression, {"rounds": 2}, pose=rigid["pose"], **common)
    v = expr["fitted"].values
    return {"identity": np.asarray(ident["identity"].value["identity"]), "rot": v[:, :9].reshape(-1, 3, 3),
            "trans": v[:, 9:12], "weights": v[:, 12:]}


@pytest.mark.slow
def test_plate_points_moved_by_a_rounding_move_the_fit_little():
    model = load_face_model()
    cam = Camera.from_fov(SIZE, SIZE, 30.0)
    truth = random_face_parameters(model, FRAMES, seed=11, distance_cm=65.0)
    seq = ImageSequence(render_truth_plates(model, [cam], truth)[0], colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)
    fits = {n: _fit(model, cam, seq, boxes, marks if n == 1 else _nudged(marks, n)) for n in (1, 2, 4)}
    ref = fits[1]
    assert np.isfinite(ref["weights"]).all() and np.isfinite(ref["rot"]).all()
    # a fit, not a failure repeated three times (measured 7.4 deg median: 2 frames, landmarks
    # only, no appearance; a lost head is tens of degrees off)
    assert np.median(_rotation_deg(ref["rot"], truth["rotation"])) < 15.0
    for n in (2, 4):
        got = fits[n]
        dw = np.abs(got["weights"] - ref["weights"]).max()
        drot = _rotation_deg(got["rot"], ref["rot"]).max()
        print(f"nudged (seed {n}) against the network's points: weights {dw:.2e}, rotation {drot:.2e} deg, translation "
              f"{np.abs(got['trans'] - ref['trans']).max():.2e} cm, identity "
              f"{np.abs(got['identity'] - ref['identity']).max():.2e}")
        assert dw < 0.02, (n, dw)
        assert drot < 0.1, (n, drot)
        # the well-conditioned bound (docstring), 1e-3 and 0.01 deg, is not held: since the compiled
        # CPU render (951ea04) the 4-thread nudged run measured 3.1e-4 and 0.0175 deg (issue 30 open)
        assert np.abs(got["trans"] - ref["trans"]).max() < 0.05, n  # cm: 0.1 deg at the head's 10 cm lever
        assert np.abs(got["identity"] - ref["identity"]).max() < 0.02, n
