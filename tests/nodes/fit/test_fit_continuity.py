"""The fit's answer is a continuous function of its input (issue 30: it followed the thread count).

Why: a run with another number of threads rounds the float32 renders and network readings
differently (measured with OMP_NUM_THREADS 1 against 2 on a 6-frame synthetic shot: plate
landmarks 6e-5 px apart, renders 4e-6). A fit whose answer jumps under such a change gives a
studio different animation on a laptop and a farm node. The jumps came from two places, each
fixed and tested here:

- the photometric term read the plate bilinearly, whose derivative jumps at every pixel
  boundary: its energy had a kink every few 1e-5 px of motion and Levenberg-Marquardt stalled
  where the last bits decided. It reads it bicubically (`sample_bicubic`, C1);
- the expression weights' bounds were a stiff penalty (1e4 w^2 past 0 or 1): every step that
  took a weight across 0 was wrong by the penalty, the steps shrank to a stall. The bounds are
  the solver's (`levenberg_marquardt(lower=, upper=)`, an active set).

The end-to-end test runs the chain of graphs/fit_video.json (identity, appearance, photometric
identity, rigid pose, expression) twice, once with torch on 1 thread and once on 4 threads with
the plate landmarks moved by 1e-4 px (twice the measured thread difference), and bounds the
change by issue 30's tolerances.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodes.fit.photometric import sample_bicubic  # noqa: E402
from nodes.geometry.lm import LMSchedule, from_jacobian, levenberg_marquardt  # noqa: E402

f64 = torch.float64


def test_sample_bicubic_is_exact_at_centres_and_its_gradient_is_the_derivative():
    g = torch.Generator().manual_seed(0)
    images = torch.rand(2, 9, 11, 3, generator=g, dtype=f64)
    ys, xs = torch.meshgrid(torch.arange(9.0, dtype=f64), torch.arange(11.0, dtype=f64), indexing="ij")
    centres = torch.stack([xs, ys], -1).reshape(1, -1, 2).expand(2, -1, 2)
    torch.testing.assert_close(sample_bicubic(images, centres), images.reshape(2, -1, 3), atol=1e-12, rtol=0)
    xy = torch.rand(2, 40, 2, generator=g, dtype=f64) * torch.tensor([9.0, 7.0], dtype=f64) + 0.5  # inside
    value, grad = sample_bicubic(images, xy, gradient=True)
    for axis in range(2):
        tangent = torch.zeros_like(xy)
        tangent[..., axis] = 1.0
        _, ref = torch.func.jvp(lambda p: sample_bicubic(images, p), (xy,), (tangent,))
        torch.testing.assert_close(grad[..., axis], ref, atol=1e-10, rtol=0)


def test_sample_bicubic_derivative_is_continuous_across_pixel_boundaries():
    """The derivative on both sides of x = 4 agrees to O(eps) (bilinear: it jumps by the
    difference of the neighbouring slopes, order 1 here)."""
    g = torch.Generator().manual_seed(1)
    images = torch.rand(1, 8, 8, 1, generator=g, dtype=f64)
    eps = 1e-9
    xy = torch.tensor([[[4.0 - eps, 3.3], [4.0 + eps, 3.3], [2.7, 5.0 - eps], [2.7, 5.0 + eps]]], dtype=f64)
    _, grad = sample_bicubic(images, xy, gradient=True)
    assert abs(float(grad[0, 0, 0, 0] - grad[0, 1, 0, 0])) < 1e-6
    assert abs(float(grad[0, 2, 0, 1] - grad[0, 3, 0, 1])) < 1e-6
    assert float(grad.abs().max()) > 0.05  # a real slope, not a flat image


def test_levenberg_marquardt_bounds_reach_the_box_constrained_minimum():
    """min |A x - y|^2 with x in [0, 1] (some components pinned at each bound at the optimum),
    against scipy's bounded linear least squares; the unbounded unknown stays free."""
    optimize = pytest.importorskip("scipy.optimize")
    g = torch.Generator().manual_seed(2)
    b, m, p = 4, 30, 6
    a = torch.randn(b, m, p, generator=g, dtype=f64)
    y = torch.randn(b, m, generator=g, dtype=f64) * 3.0
    lower = torch.tensor([0.0] * (p - 1) + [-float("inf")], dtype=f64)
    upper = torch.tensor([1.0] * (p - 1) + [float("inf")], dtype=f64)
    out = levenberg_marquardt(lambda x: (a @ x[..., None])[..., 0] - y, from_jacobian(lambda x: a),
                              torch.full((b, p), 0.5, dtype=f64), iterations=200,
                              schedule=LMSchedule(rel_tol=1e-15), lower=lower, upper=upper)
    pinned = 0
    for i in range(b):
        ref = optimize.lsq_linear(a[i].numpy(), y[i].numpy(), bounds=(lower.numpy(), upper.numpy()),
                                  tol=1e-14, lsmr_tol="auto").x
        np.testing.assert_allclose(out.x[i].numpy(), ref, atol=1e-7)
        pinned += int(((ref[:-1] <= 1e-9) | (ref[:-1] >= 1 - 1e-9)).sum())
    assert pinned >= 4  # the bounds are active, not a test of the unbounded solve
    assert float(out.x[:, :-1].min()) >= 0.0 and float(out.x[:, :-1].max()) <= 1.0


FRAMES = 2
SIZE = 256
NUDGE_PX = 1e-4
"""Plate landmarks moved by this much (twice the 6e-5 px that OMP_NUM_THREADS 1 against 2 gave)."""


def _rotation_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between rotations, degrees: 2 asin(|A - B|_F / sqrt 8) (accurate near 0, unlike acos)."""
    d = np.linalg.norm((a.astype(np.float64) - b.astype(np.float64)).reshape(len(a), -1), axis=1)
    return np.degrees(2 * np.arcsin(np.clip(d / 8 ** 0.5, 0, 1)))


def _chain(model, cam, seq, boxes, marks: dict, threads: int) -> dict:
    """graphs/fit_video.json's fit: identity, appearance, photometric identity, rigid, expression."""
    from nodegraph import run_node
    from nodes.fit import EstimateAppearance, EstimateIdentity, Expression, RigidPose

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        where = dict(frames=range(FRAMES), boxes=[boxes], cameras=[cam])
        ip = {"frames_used": FRAMES, "rounds": 3}
        first = run_node(EstimateIdentity, ip, landmarks=[marks["landmarks468"]], model=model, **where)
        app = run_node(EstimateAppearance, {"rounds": 2}, frames=range(FRAMES), images=seq,
                       landmarks=marks["landmarks68"], boxes=boxes, camera=cam, model=first["fitted_model"])
        photo = dict(where, appearance=app["appearance"], images=[seq])
        ident = run_node(EstimateIdentity, ip, landmarks=[marks["landmarks468"]], model=model, **photo)
        common = dict(landmarks=[marks["landmarks68"]], model=ident["fitted_model"], **photo)
        rigid = run_node(RigidPose, {"rounds": 2}, **common)
        expr = run_node(Expression, {"rounds": 2}, pose=rigid["pose"], **common)
    finally:
        torch.set_num_threads(before)
    v = expr["fitted"].values
    return {"identity": np.asarray(ident["identity"].value["identity"]), "rot": v[:, :9].reshape(-1, 3, 3),
            "trans": v[:, 9:12], "weights": v[:, 12:], "sh": np.asarray(app["appearance"].value["sh"])}


@pytest.mark.slow
def test_the_fit_chain_moves_little_when_its_input_moves_by_a_thread_count_rounding():
    pytest.importorskip("numba")
    pytest.importorskip("tflite")
    from nodegraph import Camera, ImageSequence, Landmarks2D, run_node
    from nodes.io.face_model import load_face_model
    from nodes.landmarks import DetectFaces, FaceLandmarks
    from tests.support.synthetic import random_face_parameters, render_truth_plates

    model = load_face_model()
    cam = Camera.from_fov(SIZE, SIZE, 30.0)
    truth = random_face_parameters(model, FRAMES, seed=1, distance_cm=65.0)
    seq = ImageSequence(render_truth_plates(model, [cam], truth, noise=0.005)[0], colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)
    rng = np.random.default_rng(0)
    nudged = {k: Landmarks2D(points=(marks[k].points + NUDGE_PX * rng.choice([-1.0, 1.0], marks[k].points.shape))
                             .astype(np.float32), confidence=marks[k].confidence)
              for k in ("landmarks468", "landmarks68")}
    assert max(np.abs(nudged[k].points - marks[k].points).max() for k in nudged) > 0.5 * NUDGE_PX
    ref = _chain(model, cam, seq, boxes, marks, 1)
    got = _chain(model, cam, seq, boxes, nudged, 4)
    assert np.isfinite(ref["weights"]).all() and np.isfinite(ref["rot"]).all()
    # a fit, not a failure twice: measured 2.0 deg median on this shot (2 frames; 1.5 and 2.5)
    assert np.median(_rotation_deg(ref["rot"], truth["rotation"])) < 10.0
    dw = np.abs(got["weights"] - ref["weights"]).max()
    drot = _rotation_deg(got["rot"], ref["rot"]).max()
    dt = np.abs(got["trans"] - ref["trans"]).max()
    di = np.abs(got["identity"] - ref["identity"]).max()
    print(f"nudged and 4 threads against 1: weights {dw:.2e}, rotation {drot:.2e} deg, translation {dt:.2e} cm, "
          f"identity {di:.2e}, lighting {np.abs(got['sh'] - ref['sh']).max():.2e}")
    assert dw < 0.02, dw  # issue 30's tolerances
    assert drot < 0.1, drot
    assert dt < 0.05, dt  # cm: 0.1 deg at the head's ~10 cm lever, twice over
    assert di < IDENTITY_TOLERANCE, di


IDENTITY_TOLERANCE = 0.05
"""Identity components (unit: one standard deviation of the model's population). Per unit the
bundled model's components move the median vertex by 0.24 mm (all components; the first: 3.1 mm
median, 15 mm at most), so 0.05 of the first is 0.15 mm at the median vertex and 0.76 mm at most,
under 0.6 px at 65 cm on this 256 px plate."""
