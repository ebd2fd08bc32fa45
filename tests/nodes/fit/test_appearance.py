"""nodes.fit.appearance.estimate_appearance against renders of a known albedo and lighting: one
frame, several frames (the light fixed in the world, the head turned), and a noisy plate whose
albedo the evidence pooling (`smooth_steps`) makes closer to the truth; the noise-adaptive
defaults of fit.EstimateAppearance and the fit's photometric weight."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, JsonValue  # noqa: E402
from nodes.fit.appearance import albedo_smoothing_steps, estimate_appearance  # noqa: E402
from nodes.fit.frame_selection import _render_noise, painting_frame_count  # noqa: E402
from nodes.fit.tuning import PHOTOMETRIC_REFERENCE_NOISE, photometric_weight_for  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.render.appearance import default_albedo, visible_faces  # noqa: E402
from nodes.render.renderer import render_mesh, sh_from_lights  # noqa: E402

SIZE = 256


@pytest.fixture(scope="module")
def scene():
    face = load_face_model()
    faces = visible_faces(face.faces, face.neutral.shape[0])
    cam = Camera.from_fov(SIZE, SIZE, 30.0)
    tint = np.array([1.1, 0.9, 0.95], np.float32)
    a0 = default_albedo(face)
    albedo = np.clip(a0 * tint, 0, 1)
    sh = sh_from_lights(np.array([0.3, 0.3, 0.3]), np.array([-0.7, 0.2, 1.0]), 0.7)
    verts = []
    for yaw in (0.0, -25.0, 25.0):
        c, s = np.cos(np.radians(yaw)), np.sin(np.radians(yaw))
        rot = np.diag([1.0, -1.0, -1.0]) @ np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        verts.append(face.neutral @ rot.T + np.array([0.0, 0.0, 55.0]))
    verts = np.stack(verts).astype(np.float32)
    with torch.no_grad():
        out = render_mesh(torch.as_tensor(verts), faces, torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None]
                          .expand(3, 4, 4), torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]]).expand(3, 4), SIZE, SIZE,
                          albedo=torch.as_tensor(albedo)[None], sh=torch.as_tensor(sh, dtype=torch.float32)[None],
                          background=torch.tensor([0.2, 0.2, 0.2]), antialias=False)
    plates = out.image.clamp(0, 1).numpy()
    return dict(face=face, faces=faces, cam=cam, a0=a0, albedo=albedo, sh=sh, verts=verts, plates=plates)


def _estimate(scene, frames, plates=None, **kw):
    cam = scene["cam"]
    plates = scene["plates"] if plates is None else plates
    return estimate_appearance(plates[frames], scene["verts"][frames], scene["faces"], cam.world_to_camera,
                               np.array([cam.fx, cam.fy, cam.cx, cam.cy]), scene["a0"], **kw)


def _albedo_error(scene, app, mask=None) -> float:
    """Mean absolute albedo error on the face's seen vertices, up to a scale per channel (albedo
    times lighting is what a plate shows: the lighting takes a colour tint the albedo lacks)."""
    face = scene["face"].groups["face"]
    seen = np.zeros(len(app.albedo), bool)
    seen[face] = True
    seen &= app.seen if mask is None else mask
    est, true = app.albedo[seen], scene["albedo"][seen]
    k = (est * true).sum(0) / (est * est).sum(0)
    return float(np.abs(est * k - true).mean())


def test_one_frame_recovers_the_albedo_and_the_lighting(scene):
    app = _estimate(scene, [0], prior_weight=0.01)
    assert _albedo_error(scene, app) < 0.02
    # the lighting's constant term, up to the same per-channel scale
    face = scene["face"].groups["face"]
    k = (app.albedo[face] * scene["albedo"][face]).sum(0) / (app.albedo[face] ** 2).sum(0)
    assert np.allclose(app.sh[0] / k, scene["sh"][0], rtol=0.1), (app.sh[0] / k, scene["sh"][0])
    assert np.allclose(app.background, 0.2, atol=1e-3)


def test_painting_under_a_given_lighting_keeps_it(scene):
    app = _estimate(scene, [0], prior_weight=0.01, sh=scene["sh"])
    assert np.allclose(app.sh, scene["sh"], atol=1e-6)
    face = scene["face"].groups["face"]
    seen = np.zeros(len(app.albedo), bool)
    seen[face] = True
    seen &= app.seen
    assert np.abs(app.albedo[seen] - scene["albedo"][seen]).mean() < 0.02  # the tint too: no scale to take


def test_several_frames_see_more_of_the_head_and_agree_with_one(scene):
    one = _estimate(scene, [0], prior_weight=0.01)
    three = _estimate(scene, [0, 1, 2], prior_weight=0.01)
    assert three.seen.sum() > 1.1 * one.seen.sum()  # the turned head shows its sides
    assert _albedo_error(scene, three) < 0.02
    assert _albedo_error(scene, three, one.seen) < 0.02
    with pytest.raises(ValueError, match="vertices"):
        estimate_appearance(scene["plates"][:2], scene["verts"][:1], scene["faces"], scene["cam"].world_to_camera,
                            np.ones(4), scene["a0"])


def test_pooling_the_evidence_of_a_noisy_plate_brings_the_albedo_closer(scene):
    noise = 0.03
    rng = np.random.default_rng(0)
    noisy = np.clip(scene["plates"] + rng.normal(0, noise, scene["plates"].shape), 0, 1).astype(np.float32)
    steps = albedo_smoothing_steps(noise)
    raw = _estimate(scene, [0], noisy, prior_weight=0.01)
    pooled = _estimate(scene, [0], noisy, prior_weight=0.01, smooth_steps=steps)
    e_raw, e_pooled = _albedo_error(scene, raw, raw.seen), _albedo_error(scene, pooled, raw.seen)
    print(f"albedo error, noise {noise}: {e_raw:.4f} per pixel, {e_pooled:.4f} pooled ({steps} steps)")
    assert e_pooled < 0.7 * e_raw, (e_pooled, e_raw)


def _pitched(verts: np.ndarray, degrees: float) -> np.ndarray:
    """The heads of `verts` (F, V, 3) turned by `degrees` about the camera's x through their centre."""
    c, s = np.cos(np.radians(degrees)), np.sin(np.radians(degrees))
    rot = np.array([[1, 0, 0], [0, c, -s], [0, s, c]], np.float32)
    centre = verts.mean(1, keepdims=True)
    return (verts - centre) @ rot.T + centre


def test_a_relative_albedo_keeps_the_features_where_the_model_puts_them(scene):
    """Painted at a wrong pose (4 deg of pitch), the painting puts the brows, eyes and lips where
    that pose sees them; the relative albedo (the default's times a pooled ratio) stays close to
    the truth, and at the right pose it is as close as the painting."""
    cam = scene["cam"]
    wrong = _pitched(scene["verts"][:1], 4.0)
    args = (scene["plates"][:1], wrong, scene["faces"], cam.world_to_camera, np.array([cam.fx, cam.fy, cam.cx, cam.cy]),
            scene["a0"])
    painted = estimate_appearance(*args, prior_weight=0.01)
    relative = estimate_appearance(*args, prior_weight=0.01, relative_steps=32)
    e_painted = _albedo_error(scene, painted, painted.seen)
    e_relative = _albedo_error(scene, relative, painted.seen)
    print(f"albedo error painted at 4 deg off: {e_painted:.4f}, relative: {e_relative:.4f}")
    assert e_relative < 0.6 * e_painted, (e_relative, e_painted)
    right = _estimate(scene, [0], prior_weight=0.01, relative_steps=32)
    assert _albedo_error(scene, right) < 0.02
    assert relative.seen.sum() == painted.seen.sum()


def test_the_defaults_adapt_to_the_plates_noise():
    assert albedo_smoothing_steps(0.005) == 0 and painting_frame_count(0.005) == 1
    assert 0 < albedo_smoothing_steps(0.02) < albedo_smoothing_steps(0.05) <= 64
    assert painting_frame_count(0.02) == 4 and painting_frame_count(0.1) == 8
    assert albedo_smoothing_steps(float("nan")) == 0 and painting_frame_count(float("nan")) == 1
    assert _render_noise(-2, 0.015) == 0.0 and _render_noise(-2, 0.03) == 0.03
    assert _render_noise(-1, 0.005) == 0.005 and _render_noise(0.02, 0.005) == 0.02
    assert photometric_weight_for(500.0, None) == 500.0
    assert photometric_weight_for(500.0, JsonValue({"plate_noise": PHOTOMETRIC_REFERENCE_NOISE / 2})) == 500.0
    assert photometric_weight_for(500.0, JsonValue({"plate_noise": 6 * PHOTOMETRIC_REFERENCE_NOISE})) == \
        pytest.approx(3000.0)


def test_linear_plates_of_some_frames_are_those_of_the_whole_shot():
    from nodegraph import ImageSequence
    from nodes.fit.node_inputs import _linear_rgb

    rng = np.random.default_rng(0)
    seq = ImageSequence(rng.uniform(0, 1, (5, 8, 9, 3)).astype(np.float32), colour_space="srgb")
    full = seq.to_linear().pixels
    assert np.allclose(_linear_rgb(seq), full)
    assert np.allclose(_linear_rgb(seq, 2), full[2])
    assert np.allclose(_linear_rgb(seq, np.array([3, 1])), full[[3, 1]])
    grey = ImageSequence(rng.uniform(0, 1, (2, 4, 4, 1)).astype(np.float32), channels=["Y"], colour_space="srgb")
    assert _linear_rgb(grey, 1).shape == (4, 4, 3) and _linear_rgb(grey).shape == (2, 4, 4, 3)


def test_the_passes_model_reads_what_the_appearance_json_holds():
    """fit.EstimateAppearance hands a pass's appearance to the next as arrays, not as its JSON lists:
    the FitModel built from them is the one built from `appearance_json`'s value."""
    import torch

    from nodes.fit.estimation_nodes import _appearance_arrays
    from nodes.fit.node_inputs import _fit_model
    from nodes.render.appearance import appearance_json

    model = load_face_model()
    rng = np.random.default_rng(3)
    albedo = rng.uniform(-0.1, 1.1, (model.neutral.shape[0], 3)).astype(np.float32)
    albedo[:3] = [[0.123455, 0.5, 1e-7], [0.999995, -0.0, 0.3333333], [0.2500049, 0.75, 0.1]]  # rounding's edges
    sh = rng.normal(0, 0.5, (9, 3)).astype(np.float32)
    background, hidden = np.array([0.2, 0.25, 0.3], np.float32), np.array([0, 5, 7])
    value = appearance_json(albedo, sh, tuple(background), hidden)
    value["noise"] = 0.0125
    a = _fit_model(model, JsonValue(value), "cpu")
    b = _fit_model(model, JsonValue(_appearance_arrays(albedo, sh, background, hidden, 0.0125)), "cpu")
    for name in ("albedo", "sh", "background", "faces", "neutral"):
        assert torch.equal(torch.as_tensor(getattr(a, name)), torch.as_tensor(getattr(b, name))), name
    assert a.noise == b.noise
