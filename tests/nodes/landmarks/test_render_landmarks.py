"""Render -> network: the landmark network's 68 points on renders of the bundled head lie on the
projected landmark vertices; gradients flow from the landmarks into the render's parameters."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")
pytest.importorskip("tflite")

from nodegraph import Camera, MeshSequence, run_node  # noqa: E402
from nodes.geometry.camera import project_points  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402
from nodes.landmarks.correspondence import MULTIPIE_68_GROUPS, inter_ocular_distance  # noqa: E402
from nodes.render import DefaultAppearance, Render  # noqa: E402

# (yaw deg, pitch deg, jawOpen): none of these is among the poses the 68-point table was chosen on
POSES = [(0.0, 0.0, 0.0), (20.0, -5.0, 0.2), (-25.0, 5.0, 0.3), (10.0, 8.0, 0.6), (-10.0, -8.0, 0.0)]


def _rotation(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("yx", [yaw_deg, pitch_deg], degrees=True).as_matrix()


@pytest.fixture(scope="module")
def scene():
    model = load_face_model()
    jaw = model.expression_names.index("jawOpen")
    verts = []
    for yaw, pitch, opening in POSES:
        w = np.zeros(len(model.expression_names), np.float32)
        w[jaw] = opening
        verts.append(model.evaluate(w) @ _rotation(yaw, pitch).T)
    mesh = MeshSequence(np.asarray(verts, np.float32), model.faces)
    # camera 55 cm in front of the face (world: y up, z out of the face), looking at it
    extrinsics = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, -1, 55.0], [0, 0, 0, 1]])
    camera = Camera(fx=520.0, fy=520.0, cx=127.5, cy=127.5, width=256, height=256, world_to_camera=extrinsics)
    appearance = run_node(DefaultAppearance, model=model)["appearance"]
    rendered = run_node(Render, {"supersample": 2}, mesh=mesh, camera=camera, appearance=appearance)
    return model, mesh, camera, appearance, rendered


def test_render_node_outputs_images_and_buffers(scene):
    model, mesh, camera, _, rendered = scene
    images, buffers = rendered["images"], rendered["buffers"]
    assert images.pixels.shape == (len(POSES), 256, 256, 3) and images.colour_space == "linear"
    assert buffers.channels == ["Z", "triangle", "bary0", "bary1", "bary2"]
    tri = buffers.pixels[0, 128, 128, 1]
    assert tri >= 0 and (model.faces[int(tri)] < 9409).all()  # the face, not a hidden part
    assert 40 < buffers.pixels[0, 128, 128, 0] < 50  # cm from the camera
    lashes = np.flatnonzero((model.faces >= 24591).any(1))
    assert not np.isin(buffers.pixels[..., 1], lashes).any()


def test_network_68_points_on_renders_match_projected_model_landmarks(scene):
    model, mesh, camera, _, rendered = scene
    det = run_node(DetectFaces, images=rendered["images"])
    assert (det["failed"].values == 0).all() and (det["scores"].values > 0.8).all()
    out = run_node(FaceLandmarks, images=rendered["images"], boxes=det["boxes"])
    assert (out["presence"].values > 0.9).all()
    found = out["landmarks68"].points
    truth = project_points(mesh.vertices[:, model.landmarks].astype(np.float64), camera.world_to_camera,
                           [camera.fx, camera.fy, camera.cx, camera.cy])
    iod = inter_ocular_distance(truth)
    err = np.linalg.norm(found - truth, axis=-1) / iod[:, None]  # (F, 68) in inter-ocular distances
    assert err.mean() < 0.05
    assert err.mean(1).max() < 0.06
    non_jaw = np.setdiff1d(np.arange(68), MULTIPIE_68_GROUPS["jaw"])
    assert err[:, non_jaw].mean() < 0.04
    # the nose tip of the two schemes (face-mesh 4 vs the model's landmark 30) nearly coincide
    nose = (found[:, 30] - truth[:, 30]) / iod[:, None]
    assert np.linalg.norm(nose, axis=1).mean() < 0.03


def test_landmark_gradients_reach_the_render_parameters(scene):
    from nodes.landmarks.network import detect_faces, face_landmarks, load_face_mesh, srgb_encode
    from nodes.render.appearance import parse_appearance
    from nodes.render.renderer import render_mesh

    model, mesh, camera, appearance, rendered = scene
    albedo, sh, background, hidden = parse_appearance(appearance.value, mesh.num_vertices, len(mesh.faces))
    faces = np.delete(model.faces, hidden, axis=0)
    det = detect_faces(torch.as_tensor(rendered["images"].to_srgb().pixels[:1]))
    translation = torch.zeros(3, requires_grad=True)
    sh_t = torch.as_tensor(sh)[None].clone().requires_grad_()
    verts = torch.as_tensor(mesh.vertices[:1]) + translation
    out = render_mesh(verts, faces, torch.as_tensor(camera.world_to_camera, dtype=torch.float32)[None],
                      torch.tensor([[camera.fx, camera.fy, camera.cx, camera.cy]]), 256, 256,
                      albedo=torch.as_tensor(albedo)[None], sh=sh_t, background=torch.as_tensor(background),
                      supersample=2)
    points, _ = face_landmarks(srgb_encode(out.image.clamp(0, 1)), det.boxes, load_face_mesh())
    points[0, :, 0].mean().backward()
    # moving the head along world x moves the landmarks right: d(mean x)/dt_x ~ fx / depth px/cm
    assert translation.grad[0].item() == pytest.approx(520.0 / 45.0, rel=0.5)
    assert torch.isfinite(sh_t.grad).all() and sh_t.grad.abs().sum() > 0
