"""The photometric term where it carries no evidence (issue 30): frames whose plate the albedo was
painted from, and views whose residuals the model does not explain (a real photo's hair, brows,
texture), must not decide the fit, since there the term turns rounding-size changes into other
minima. Unit checks of the two rules, and the node rule on a synthetic one-frame shot."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")
pytest.importorskip("tflite")

from nodegraph import Camera, ImageSequence, JsonValue, run_node  # noqa: E402
from nodes.fit import EstimateAppearance, RigidPose  # noqa: E402
from nodes.fit.photometric import RESIDUAL_SCALE_REFERENCE, residual_scale_weight  # noqa: E402
from nodes.fit.tuning import photometric_frame_weights  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402


def test_painted_frames_get_no_photometric_weight():
    painted = JsonValue({"albedo_source": "painted", "frames": [3, 7]})
    assert photometric_frame_weights(painted, [2, 3, 7, 8]).tolist() == [1.0, 0.0, 0.0, 1.0]
    assert photometric_frame_weights(painted, np.array([3])).tolist() == [0.0]
    for other in ({"albedo_source": "default", "frames": []}, {"albedo_source": "relative", "frames": [3]}, {}):
        assert photometric_frame_weights(JsonValue(other), [3, 4]).tolist() == [1.0, 1.0]
    assert photometric_frame_weights(None, [0]).tolist() == [1.0]


def test_residual_scale_weight_is_one_up_to_the_reference_then_inverse_square():
    ref = RESIDUAL_SCALE_REFERENCE
    scale = torch.tensor([0.0, 0.01, ref, ref * (1 + 1e-6), 2 * ref, 10 * ref], dtype=torch.float64)
    got = residual_scale_weight(scale)
    assert got[:3].tolist() == [1.0, 1.0, 1.0]  # exactly 1: a model's own plates are fitted to the bit as before
    assert got[3].item() == pytest.approx(1.0, abs=1e-5)  # continuous at the reference
    assert got[4:].tolist() == pytest.approx([0.25, 0.01], rel=1e-12)


@pytest.fixture(scope="module")
def one_photo():
    """One synthetic 192^2 plate (seed 3), its network landmarks and the appearance EstimateAppearance
    paints from it (one view: albedo 'painted', frames [0])."""
    model = load_face_model()
    cam = Camera.from_fov(192, 192, 30.0)
    truth = random_face_parameters(model, 1, seed=3, distance_cm=60.0)
    seq = ImageSequence(render_truth_plates(model, [cam], truth)[0], colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)
    app = run_node(EstimateAppearance, {"passes": 1, "rounds": 1}, images=seq, landmarks=marks["landmarks68"],
                   boxes=boxes, camera=cam, model=model)["appearance"]
    return model, cam, seq, boxes, marks, app


def _rigid(one_photo, appearance, weight=None):
    model, cam, seq, boxes, marks, _ = one_photo
    params = {"rounds": 2, "iterations": 10} | ({} if weight is None else {"photometric_weight": weight})
    return run_node(RigidPose, params, landmarks=[marks["landmarks68"]], boxes=[boxes], cameras=[cam], model=model,
                    appearance=appearance, images=[seq])["pose"].values


def test_a_painted_frame_is_fitted_without_the_photometric_term(one_photo):
    app = one_photo[-1]
    assert app.value["albedo_source"] == "painted" and app.value["frames"] == [0]
    painted = _rigid(one_photo, app)
    np.testing.assert_array_equal(painted, _rigid(one_photo, app, weight=0.0))
    # the same appearance said to be painted from another frame: frame 0 keeps the term, and it acts
    elsewhere = _rigid(one_photo, JsonValue(dict(app.value, frames=[5])))
    assert np.abs(elsewhere - painted).max() > 1e-4
