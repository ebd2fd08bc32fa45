"""The fit's answer does not follow the thread count (issue 30): identity, rigid pose and
expression of a small synthetic shot with torch using 1, 2 and 4 threads.

Why they can differ at all: torch splits a reduction across threads, so float32 sums round
differently. The solves are float64 (`nodes.fit.solve.SOLVE_DTYPE`), where that rounding is
~1e-16 relative; what stays float32 is the render and the network's reading of it (each outer
round re-anchors on a render), whose thread-dependent rounding (~1e-7 relative of a pixel
value) moves a landmark by well under 1e-3 px. A well-conditioned solve moves its answer by
that over the landmarks' lever (|d w / d px| < 0.1 per px for a weight seen over ~20 px of
lip motion; a degree of rotation moves the landmarks > 1 px at 65 cm and 256 px): < 1e-4 in
the weights and < 1e-3 deg. The bounds below are issue 30's, 0.02 in weights and 0.1 deg,
which a flat valley (the float32 solves: 0.79 and 1.5 deg on a real video) breaks, and ten
times the estimate above, 1e-3 in the weights and 0.01 deg, which the float32 solves broke even
on this small shot (measured on a 2-core machine, 4 threads against 1: weights 1.15e-3, rotation
0.0205 deg, translation 4.7e-3 cm; the float64 solves: all 0.0).

In one process torch's thread count alone left these solves bit-identical, so the runs at 2 and
4 threads also read plate landmarks moved by +-`NUDGE_PX` (twice the 6e-5 px that
OMP_NUM_THREADS 1 against 2 moved the network's plate points on a 6-frame shot): what the test
bounds is how far the fit follows such a rounding, which a jump (a render landmark changing the
triangle it is anchored on, a stalled solve) makes far more than the linear estimate above. The
test asserts issue 30's bounds; the ten-times-the-estimate bound held before the compiled CPU
render (weights 6e-5, rotation 1.6e-3 deg) and not after it (3.1e-4, 0.0175 deg at 4 threads): the
fit still follows a 1e-4 px change ten times more than a well-conditioned solve would.
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
"""Plate landmarks moved by this much in the 2- and 4-thread runs (see the module docstring)."""


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


def _fit(model, cam, seq, boxes, marks, threads: int) -> dict:
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        where = dict(frames=range(FRAMES), boxes=[boxes], cameras=[cam])
        ident = run_node(EstimateIdentity, {"frames_used": FRAMES, "iterations": 10, "rounds": 2},
                         landmarks=[marks["landmarks468"]], model=model, **where)
        common = dict(landmarks=[marks["landmarks68"]], model=ident["fitted_model"], **where)
        rigid = run_node(RigidPose, {"rounds": 2}, **common)
        expr = run_node(Expression, {"rounds": 2}, pose=rigid["pose"], **common)
    finally:
        torch.set_num_threads(before)
    v = expr["fitted"].values
    return {"identity": np.asarray(ident["identity"].value["identity"]), "rot": v[:, :9].reshape(-1, 3, 3),
            "trans": v[:, 9:12], "weights": v[:, 12:]}


@pytest.mark.slow
def test_one_two_and_four_threads_give_the_same_fit():
    model = load_face_model()
    cam = Camera.from_fov(SIZE, SIZE, 30.0)
    truth = random_face_parameters(model, FRAMES, seed=11, distance_cm=65.0)
    seq = ImageSequence(render_truth_plates(model, [cam], truth)[0], colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)
    fits = {n: _fit(model, cam, seq, boxes, marks if n == 1 else _nudged(marks, n), n) for n in (1, 2, 4)}
    ref = fits[1]
    assert np.isfinite(ref["weights"]).all() and np.isfinite(ref["rot"]).all()
    # a fit, not a failure repeated three times (measured 7.4 deg median: 2 frames, landmarks
    # only, no appearance; a lost head is tens of degrees off)
    assert np.median(_rotation_deg(ref["rot"], truth["rotation"])) < 15.0
    for n in (2, 4):
        got = fits[n]
        dw = np.abs(got["weights"] - ref["weights"]).max()
        drot = _rotation_deg(got["rot"], ref["rot"]).max()
        print(f"threads {n} (nudged) against 1: weights {dw:.2e}, rotation {drot:.2e} deg, translation "
              f"{np.abs(got['trans'] - ref['trans']).max():.2e} cm, identity "
              f"{np.abs(got['identity'] - ref['identity']).max():.2e}")
        assert dw < 0.02, (n, dw)
        assert drot < 0.1, (n, drot)
        # the well-conditioned bound (docstring), 1e-3 and 0.01 deg, is not held: since the compiled
        # CPU render (951ea04) the 4-thread nudged run measured 3.1e-4 and 0.0175 deg (issue 30 open)
        assert np.abs(got["trans"] - ref["trans"]).max() < 0.05, n  # cm: 0.1 deg at the head's 10 cm lever
        assert np.abs(got["identity"] - ref["identity"]).max() < 0.02, n
