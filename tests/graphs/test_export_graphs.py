"""The graphs graphs/video_to_animation.json and graphs/livelink_to_render.json: valid; from
synthetic plates the first writes the NPZ, a Live Link CSV, a USD and a glTF that agree with each
other and with the truth; the second renders a CSV take on the ICT head."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

from .helpers import check_graph_file

pytest.importorskip("torch")
pytest.importorskip("tflite")

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
FRAMES = 4


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(F,) angle of a_f b_f^T, degrees (atan2 form: accurate at small angles, unlike arccos of the trace)."""
    from nodes.geometry.rigid import rotation_angle

    return np.degrees(rotation_angle(np.einsum("fij,fkj->fik", a, b)))


def test_export_graphs_types_ports_params_exist():
    spec = check_graph_file(GRAPHS / "video_to_animation.json")
    temporal = json.loads((GRAPHS / "fit_video_temporal.json").read_text())
    assert set(spec["parameters"]) == set(temporal["parameters"]) | {"csv", "usd", "gltf"}
    spec = check_graph_file(GRAPHS / "livelink_to_render.json")
    assert set(spec["parameters"]) == {"csv", "images", "fps", "distance_cm"}


@pytest.fixture(scope="module")
def animation(tmp_path_factory):
    """Run video_to_animation.json on FRAMES synthetic plates of a turning head."""
    from scipy.spatial.transform import Rotation

    from nodegraph import Camera
    from tests.support.synthetic import random_face_parameters, render_truth_plates
    from nodes.io.face_model import load_face_model
    from nodes.io.image import write_image

    tmp = tmp_path_factory.mktemp("animation")
    model = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0, name="cam0")
    truth = random_face_parameters(model, FRAMES, seed=5, distance_cm=65.0)
    t = np.arange(FRAMES, dtype=np.float64)
    r_model = Rotation.from_euler("YXZ", np.stack([4.0 * t, 3.0 + 0 * t, 0 * t], 1), degrees=True).as_matrix()
    truth["rotation"] = np.diag([1.0, -1.0, -1.0])[None] @ r_model
    truth["translation"] = np.stack([0 * t, 0 * t, 65.0 + 0 * t], 1)
    truth["weights"] = np.zeros((FRAMES, len(model.expression_names)), np.float32)
    truth["weights"][:, model.expression_names.index("jawOpen")] = 0.1 + 0.05 * np.sin(t)
    for i, frame in enumerate(render_truth_plates(model, [cam], truth)[0]):
        write_image(tmp / f"plate.{i:04d}.png", np.clip(frame, 0, 1) ** (1 / 2.2), ["R", "G", "B"], "uint8")
    params = {"images": str(tmp / "plate.%04d.png"), "output": str(tmp / "fit.npz"), "report": str(tmp / "fit"),
              "motion_report": str(tmp / "motion"), "csv": str(tmp / "take.csv"), "usd": str(tmp / "head.usdc"),
              "gltf": str(tmp / "head.glb")}
    result = runner.run(Graph.load(GRAPHS / "video_to_animation.json"), parameters=params, scheduler="threads",
                        workers=2, cache=False, outputs=["csv", "usd", "gltf", "save"])
    assert result.exit_code == 0, result.summary()
    return tmp, r_model, model


def test_video_to_animation_files_agree_with_the_npz_and_the_truth(animation):
    import pygltflib
    from pxr import Usd, UsdSkel
    from scipy.spatial.transform import Rotation

    from nodes.io.arkit import ARKIT_NAMES, head_angles, head_rotation
    from nodes.io.livelink import read_live_link_csv

    tmp, r_model, model = animation
    with np.load(tmp / "fit.npz") as fit:
        names = list(fit["expression_names"])
        jaw = fit["weights"][:, names.index("jawOpen")].astype(np.float64)
        rotation = fit["rotation"].astype(np.float64)
    # the default camera is the world (identity): the file frame is diag(1, -1, -1) of it
    in_file = np.diag([1.0, -1.0, -1.0])[None] @ rotation
    take = read_live_link_csv(tmp / "take.csv")
    np.testing.assert_allclose(take.arkit[:, ARKIT_NAMES.index("jawOpen")], jaw, atol=5.1e-7)
    assert _angle_deg(head_rotation(take.angles[:, :3]), in_file).max() < 1e-3
    # near the truth: a wrong frame convention would be off by twice the 3 deg pitch or more; the
    # monocular fit of 4 frames keeps its known offset (3.2-3.7 deg here, mostly pitch)
    assert _angle_deg(head_rotation(take.angles[:, :3]), r_model).max() < 5.0
    yaw = np.degrees(head_angles(in_file)[:, 0])
    assert np.all(np.diff(yaw) > 0), yaw  # the head turns to its left, as rendered

    stage = Usd.Stage.Open(str(tmp / "head.usdc"))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Head/Skeleton/Animation"))
    shapes = list(anim.GetBlendShapesAttr().Get())
    assert shapes[:52] == list(ARKIT_NAMES)
    usd_jaw = [anim.GetBlendShapeWeightsAttr().Get(t)[shapes.index("jawOpen")] for t in range(FRAMES)]
    np.testing.assert_allclose(usd_jaw, jaw, atol=1e-6)
    quats = [anim.GetRotationsAttr().Get(t)[0] for t in range(FRAMES)]
    usd_rot = Rotation.from_quat([[*q.GetImaginary(), q.GetReal()] for q in quats]).as_matrix()
    assert _angle_deg(usd_rot, in_file).max() < 0.01

    doc = pygltflib.GLTF2().load(str(tmp / "head.glb"))
    assert doc.meshes[0].extras["targetNames"][:52] == list(ARKIT_NAMES)
    blob = doc.binary_blob()
    channel = {c.target.path: c for c in doc.animations[0].channels}
    acc = doc.accessors[doc.animations[0].samplers[channel["rotation"].sampler].output]
    view = doc.bufferViews[acc.bufferView]
    quat = np.frombuffer(blob, np.float32, acc.count * 4, view.byteOffset).reshape(-1, 4)
    assert _angle_deg(Rotation.from_quat(quat).as_matrix(), in_file).max() < 0.01


def test_livelink_to_render_draws_the_take(tmp_path):
    from nodes.export.livelink import live_link_rows, live_link_text
    from nodes.io.arkit import ARKIT_NAMES, head_rotation
    from nodes.io.image import read_image

    arkit = np.zeros((3, 52))
    arkit[1, ARKIT_NAMES.index("jawOpen")] = 1.0
    angles = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.5, 0.0, 0.0]])  # frame 2: yaw 0.5 rad
    (tmp_path / "take.csv").write_text(live_link_text(live_link_rows(arkit, head_rotation(angles), 30.0)))
    graph = Graph.load(GRAPHS / "livelink_to_render.json")
    graph.nodes["camera"].params = {**graph.nodes["camera"].params, "width": 96, "height": 96}
    result = runner.run(graph, parameters={"csv": str(tmp_path / "take.csv"), "fps": 30.0,
                                           "images": str(tmp_path / "render.%04d.png")}, cache=False,
                        outputs=["save", "pose", "camera", "model"])
    assert result.exit_code == 0, result.summary()
    frames = [read_image(tmp_path / f"render.{i:04d}.png")[0][..., :3] for i in range(3)]
    background = frames[0][0, 0]
    head = [np.any(np.abs(f - background) > 0.05, axis=-1) for f in frames]
    assert all(h.mean() > 0.2 for h in head)  # the head fills a good part of the frame at 60 cm
    assert np.abs(frames[1] - frames[0]).max() > 0.1  # the jaw opened
    # turning to the subject's left (positive yaw) moves the nose tip to the image's right
    from nodes.geometry.camera import project_points

    camera = result.outputs["camera"]["camera"]
    nose = result.outputs["pose"]["mesh"].vertices[:, result.outputs["model"]["model"].landmarks[30]]
    x = project_points(nose.astype(np.float64)[:, None], camera.world_to_camera,
                       [camera.fx, camera.fy, camera.cx, camera.cy])[:, 0, 0]
    assert x[2] > x[0] + 5 and abs(x[0] - camera.cx) < 2, x
