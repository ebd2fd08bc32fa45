"""The fit's render path (nodes.fit.views.render_crops): a second render of the same estimate in
a round (the noise-free one for the photometric samples) reuses the first render instead of
drawing the head again, and gives what a fresh render gives; any changed input renders anew."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera  # noqa: E402
from nodes.fit import views as fit_views  # noqa: E402
from nodes.fit.views import FitModel, FitViews, render_crops  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.render.appearance import default_albedo, default_sh, visible_faces  # noqa: E402


@pytest.fixture(scope="module")
def scene():
    face = load_face_model()
    faces = visible_faces(face.faces, face.neutral.shape[0])
    model = FitModel.build(face.neutral, face.expression_deltas, face.expression_names, faces, face.landmarks,
                           default_albedo(face), default_sh(), np.array([0.2, 0.25, 0.3]), noise=0.02)
    cam = Camera.from_fov(256, 256, 30.0)
    views = FitViews(target=torch.zeros(1, 1, 68, 2), boxes=torch.tensor([[[70.3, 60.7, 190.1, 180.5]]]),
                     seen=torch.ones(1, 1, dtype=torch.bool),
                     world_to_camera=torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None],
                     intrinsics=torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]]), distortion=None,
                     image_size=torch.tensor([[256, 256]]))
    rot = torch.diag(torch.tensor([1.0, -1.0, -1.0]))[None]
    verts = model.vertices(torch.zeros(1, model.deltas.shape[0]), rot, torch.tensor([[0.5, -1.0, 65.0]]))
    return model, views, verts


def _counting(monkeypatch):
    calls = []
    real = fit_views.render_mesh

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(fit_views, "render_mesh", counted)
    return calls


def test_the_noise_free_render_of_the_same_estimate_reuses_the_render(scene, monkeypatch):
    model, views, verts = scene
    clean_model = dataclasses.replace(model, noise=0.0)
    fit_views._LAST_RENDER.entry = None
    with torch.no_grad():
        fresh = render_crops(clean_model, views, verts)  # what a render from scratch gives
        fit_views._LAST_RENDER.entry = None
        calls = _counting(monkeypatch)
        noisy = render_crops(model, views, verts.clone())
        clean = render_crops(clean_model, views, verts.clone())
    assert len(calls) == 1
    for a, b in zip(clean, fresh):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert 0.005 < (noisy[0] - clean[0]).std().item() < 0.03  # the noise is still added to the first


def test_any_changed_input_renders_again(scene, monkeypatch):
    model, views, verts = scene
    fit_views._LAST_RENDER.entry = None
    calls = _counting(monkeypatch)
    with torch.no_grad():
        first = render_crops(model, views, verts)[0]
        moved = verts.clone()
        moved[0, 100, 0] += 1e-3  # one vertex, 10 um
        render_crops(model, views, moved)
        render_crops(dataclasses.replace(model, sh=model.sh * 1.1), views, moved)
        render_crops(model, views, moved, supersample=1)
        brighter = render_crops(dataclasses.replace(model, albedo=model.albedo * 1.2), views, moved)[0]
    assert len(calls) == 5
    assert (brighter - first).abs().max() > 0.05
    # with gradients recorded, never reused (the output carries this call's graph)
    leaf = verts.clone().requires_grad_()
    render_crops(model, views, leaf)
    image = render_crops(model, views, leaf)[0]
    assert len(calls) == 7
    image.sum().backward()
    assert leaf.grad is not None and leaf.grad.abs().sum() > 0
