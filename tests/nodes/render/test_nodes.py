"""Render nodes: the default appearance of the bundled head, render.Render ports and errors."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import Camera, ImageSequence, JsonValue, MeshSequence, NodeError, run_node
from nodes.io.face_model import load_face_model
from nodes.render import DefaultAppearance, Render
from nodes.render.appearance import COLOURS, ICT_HIDDEN_VERTEX_RANGES, default_albedo, hidden_faces

pytest.importorskip("torch")
pytest.importorskip("numba")


def test_default_albedo_colours_the_regions_of_the_ict_head():
    model = load_face_model()
    albedo = default_albedo(model)
    assert albedo.shape == (model.neutral.shape[0], 3) and albedo.min() >= 0 and albedo.max() <= 1
    lm = model.landmarks
    face = model.groups["face"]
    inside = 0.6 * model.neutral[lm[51]] + 0.4 * model.neutral[lm[62]]  # within the upper lip
    lip = face[np.argmin(np.linalg.norm(model.neutral[face] - inside, axis=1))]
    np.testing.assert_allclose(albedo[lip], COLOURS["lips"], atol=0.02)
    np.testing.assert_allclose(albedo[lm[19]], COLOURS["brows"], atol=0.02)
    np.testing.assert_allclose(albedo[lm[30]], COLOURS["skin"], atol=1e-6)  # nose tip
    np.testing.assert_allclose(albedo[model.groups["teeth"]].mean(0), COLOURS["teeth"], atol=1e-4)
    eye = model.groups["eyeball_left"]
    front = eye[np.argmax(model.neutral[eye, 2])]
    np.testing.assert_allclose(albedo[front], COLOURS["pupil"], atol=0.02)
    hidden = hidden_faces(model.faces)
    first, last = ICT_HIDDEN_VERTEX_RANGES[0][0], ICT_HIDDEN_VERTEX_RANGES[-1][1]
    assert ((model.faces[hidden] >= first) & (model.faces[hidden] <= last)).any(1).all()
    assert len(hidden) == ((model.faces >= first) & (model.faces <= last)).any(1).sum()


def _quad_scene():
    verts = np.array([[[-5.0, -5, 50], [5, -5, 50], [5, 5, 50], [-5, 5, 50]]], np.float32)
    mesh = MeshSequence(np.repeat(verts, 2, 0), np.array([[0, 1, 2], [0, 2, 3]]))
    camera = Camera(fx=100.0, fy=100.0, cx=15.5, cy=15.5, width=32, height=24)
    return mesh, camera


def test_render_node_with_a_background_plate_and_uniform_albedo():
    mesh, camera = _quad_scene()
    from nodes.render.renderer import sh_from_lights

    appearance = JsonValue({"albedo": [0.5, 0.5, 0.5], "sh": sh_from_lights(1.0).tolist(), "background": [0, 0, 0]})
    plate = ImageSequence(np.full((2, 24, 32, 3), 0.25, np.float32), colour_space="linear")
    out = run_node(Render, {"supersample": 1}, mesh=mesh, camera=camera, appearance=appearance, background=plate)
    pix = out["images"].pixels
    assert pix.shape == (2, 24, 32, 3)
    np.testing.assert_allclose(pix[0, 12, 16], 0.5, atol=1e-6)
    np.testing.assert_allclose(pix[0, 0, 0], 0.25, atol=1e-6)
    buffers = out["buffers"].pixels
    assert buffers[0, 12, 16, 0] == pytest.approx(50.0) and buffers[0, 0, 0, 1] == -1


def test_render_node_errors_name_the_port():
    mesh, camera = _quad_scene()
    with pytest.raises(NodeError, match=r"appearance.*'albedo' expected \(4, 3\)"):
        run_node(Render, mesh=mesh, camera=camera, appearance=JsonValue({"albedo": [[1, 1, 1]], "sh": [[0] * 3] * 9}))
    with pytest.raises(NodeError, match=r"background.*expected \(F, 24, 32, 3\)"):
        run_node(Render, mesh=mesh, camera=camera,
                 appearance=JsonValue({"albedo": [1, 1, 1], "sh": [[0] * 3] * 9}),
                 background=ImageSequence(np.zeros((2, 8, 8, 3), np.float32)))


def test_default_appearance_node_hides_eye_shells_and_lashes():
    model = load_face_model()
    value = run_node(DefaultAppearance, model=model)["appearance"].value
    assert len(value["albedo"]) == model.neutral.shape[0] and np.asarray(value["sh"]).shape == (9, 3)
    assert len(value["hidden_faces"]) == len(hidden_faces(model.faces))
