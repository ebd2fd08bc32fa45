"""fit.FittedLandmarks: the fitted head's 68 points as the face mesh reads them on its render.

On a synthetic plate rendered from known parameters, the points read on the render of the true
fit land where the network reads the plate (the model's fixed landmark vertices do not: the
network's convention differs from theirs by a few % of the eye distance); they follow the fit, not
the plate; failed frames are not read; fit.SaveFit saves them beside the projected vertices."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, ImageSequence, JsonValue, NodeError, ParamSequence, run_node  # noqa: E402
from nodes.fit import FittedLandmarks, SaveFit  # noqa: E402
from nodes.fit.output_nodes import projected_landmarks68  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402
from nodes.render.appearance import appearance_json, culled_faces, default_albedo  # noqa: E402
from nodes.render.renderer import sh_from_lights  # noqa: E402
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402

NOISE = 0.005  # linear plate noise of render_truth_plates


@pytest.fixture(scope="module")
def shot():
    """Two frames of the mean identity (+-30 deg yaw) at 55 cm in a 256^2, 30 deg camera, the
    plate's points and boxes from DetectFaces + FaceLandmarks, the true appearance and fit."""
    model = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0)
    truth = random_face_parameters(model, 2, seed=5)
    truth["identity"] = np.zeros_like(truth["identity"])
    plates = render_truth_plates(model, [cam], truth, noise=NOISE)[0]
    seq = ImageSequence(plates, colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)["landmarks68"]
    light = truth["light"]
    albedo = np.clip(default_albedo(model) * truth["albedo_tint"], 0, 1)
    app = JsonValue(appearance_json(albedo, sh_from_lights(light["ambient"], light["direction"], light["intensity"]),
                                    tuple(truth["background"]), culled_faces(model.faces, model.neutral.shape[0]))
                    | {"noise": NOISE})
    k = len(model.expression_names)
    fitted = np.concatenate([truth["rotation"].reshape(2, 9), truth["translation"], truth["weights"]], 1)
    fitted = ParamSequence(fitted.astype(np.float32), [f"v{i}" for i in range(12 + k)])
    return model, cam, marks, boxes, app, fitted


def _read(shot, fitted=None, flags=None):
    model, cam, marks, boxes, app, truth = shot
    inputs = dict(fitted=truth if fitted is None else fitted, landmarks=marks, boxes=boxes, camera=cam, model=model,
                  appearance=app)
    if flags is not None:
        inputs["flags"] = flags
    return run_node(FittedLandmarks, **inputs)["landmarks68"]


def _eye(points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(points[:, 36:42].mean(1) - points[:, 42:48].mean(1), axis=-1)


def test_the_true_fit_reads_where_the_network_reads_the_plate(shot):
    model, cam, marks, _, _, truth = shot
    read = _read(shot)
    assert read.points.shape == (2, 68, 2) and (read.confidence == 1).all()
    eye = _eye(marks.points)
    off = np.linalg.norm(read.points - marks.points, axis=-1).mean(1) / eye
    vertices = projected_landmarks68(truth.values.astype(np.float64), model, cam).pixels
    off_vertices = np.linalg.norm(vertices - marks.points, axis=-1).mean(1) / eye
    # The render and the plate differ by their noise (two draws of 0.005) and the render path only;
    # the face mesh reads two noise draws of one face ~1% of the eye distance apart (TrackFaces'
    # jitter, README), so 2% bounds a read of the same face; the fixed vertices sit in another
    # convention (the network's 68 points on renders: 4.5% of the eye distance from them).
    assert (off < 0.02).all(), off
    assert (off < 0.5 * off_vertices).all(), (off, off_vertices)


def test_the_points_follow_the_fit_not_the_plate(shot):
    model, cam, _, _, _, truth = shot
    moved = truth.values.copy()
    moved[:, 9] += 1.0  # 1 cm to the camera's right
    read = _read(shot).points
    shifted = _read(shot, ParamSequence(moved, truth.names)).points
    # the model's landmark vertices move by the same translation: their mean image shift
    vertex_shift = (projected_landmarks68(moved.astype(np.float64), model, cam).pixels
                    - projected_landmarks68(truth.values.astype(np.float64), model, cam).pixels).mean(1)
    shift = (shifted - read).mean(1)
    # the read points sit on the same face, within a few mm of those vertices' depth: 10% of the shift
    assert np.allclose(shift[:, 0], vertex_shift[:, 0], rtol=0.1), (shift, vertex_shift)
    assert (np.abs(shift[:, 1] - vertex_shift[:, 1]) < 0.1 * vertex_shift[:, 0]).all(), (shift, vertex_shift)


def test_failed_or_unfitted_frames_are_not_read(shot):
    _, _, _, _, _, truth = shot
    flags = ParamSequence(np.array([[1.0], [0.0]], np.float32), ["failed"])
    read = _read(shot, flags=flags)
    assert np.isnan(read.points[0]).all() and (read.confidence[0] == 0).all()
    assert np.isfinite(read.points[1]).all() and (read.confidence[1] == 1).all()
    nan = truth.values.copy()
    nan[1] = np.nan
    read = _read(shot, ParamSequence(nan, truth.names))
    assert np.isfinite(read.points[0]).all() and np.isnan(read.points[1]).all()


def test_a_fit_of_the_wrong_width_is_refused_naming_the_port(shot):
    _, _, _, _, _, truth = shot
    with pytest.raises(NodeError, match="'fitted'.*expected \\(2, 65\\) pose \\+ 53 weights, found \\(2, 60\\)"):
        _read(shot, ParamSequence(truth.values[:, :60], truth.names[:60]))


def test_save_fit_saves_the_read_points_and_the_projected_vertices(shot, tmp_path):
    model, cam, _, _, _, truth = shot
    read = _read(shot)
    common = dict(fitted=truth, flags=ParamSequence(np.zeros((2, 1), np.float32), ["failed"]),
                  energy=ParamSequence(np.ones((2, 1), np.float32), ["energy"]),
                  identity=JsonValue({"identity": [0.0] * model.identity_deltas.shape[0]}), model=model, camera=cam)
    path = tmp_path / "fit.npz"
    run_node(SaveFit, {"path": str(path)}, landmarks68=read, **common)
    saved = np.load(path)
    assert np.array_equal(saved["landmarks68"], read.points)
    vertices = projected_landmarks68(truth.values, model, cam).pixels
    assert np.allclose(saved["landmarks68_vertices"], vertices, atol=1e-3)
    run_node(SaveFit, {"path": str(tmp_path / "plain.npz")}, **common)  # without the input: the vertices
    plain = np.load(tmp_path / "plain.npz")
    assert "landmarks68_vertices" not in plain and np.allclose(plain["landmarks68"], vertices, atol=1e-3)
    with pytest.raises(NodeError, match="'landmarks68'.*expected \\(2, 68, 2\\)"):
        run_node(SaveFit, {"path": str(tmp_path / "bad.npz")}, landmarks68=type(read)(read.points[:, :60],
                                                                                       read.confidence[:, :60]),
                 **common)
    assert not (tmp_path / "bad.npz").exists()
