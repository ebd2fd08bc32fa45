"""nodes.fit.views.render_crops renders what `crop_and_resize` makes of the plate (the head
rendered at the plate's size, then cropped and resized), for a face smaller and larger than
the network's crop; the plate's noise, when added, does not depend on the batch;
nodes.fit.appearance.estimate_noise on known noise."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera  # noqa: E402
from nodes.fit.appearance import estimate_noise  # noqa: E402
from nodes.fit.views import FitModel, FitViews, render_crops  # noqa: E402
from nodes.geometry.image import crop_and_resize, crop_intrinsics  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.render.appearance import default_albedo, default_sh, visible_faces  # noqa: E402
from nodes.render.renderer import render_mesh  # noqa: E402


@pytest.fixture(scope="module")
def model():
    face = load_face_model()
    faces = visible_faces(face.faces, face.neutral.shape[0])
    return FitModel.build(face.neutral, face.expression_deltas, face.expression_names, faces, face.landmarks,
                          default_albedo(face), default_sh(), np.array([0.2, 0.25, 0.3]))


def _scene(model: FitModel, size: int, distance: float, boxes: list[list[float]]):
    cam = Camera.from_fov(size, size, 30.0)
    views = FitViews(target=torch.zeros(len(boxes), 1, 68, 2), boxes=torch.tensor(boxes)[:, None],
                     seen=torch.ones(len(boxes), 1, dtype=torch.bool),
                     world_to_camera=torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None],
                     intrinsics=torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]]), distortion=None,
                     image_size=torch.tensor([[size, size]]))
    rot = torch.diag(torch.tensor([1.0, -1.0, -1.0])).expand(len(boxes), 3, 3)
    trans = torch.tensor([[0.5, -1.0, distance]]).expand(len(boxes), 3)
    verts = model.vertices(torch.zeros(len(boxes), model.deltas.shape[0]), rot, trans)
    return cam, views, verts


@pytest.mark.parametrize("size, distance, box", [
    (256, 65.0, [70.3, 60.7, 190.1, 180.5]),  # box 120 px < 192: upsampled
    (800, 50.0, [230.6, 180.2, 650.4, 600.0]),  # box 420 px: box-filtered by 2, then resampled
])
def test_render_crops_is_the_crop_of_a_plate_sized_render(model, size, distance, box):
    cam, views, verts = _scene(model, size, distance, [box])
    with torch.no_grad():
        crop, triangle, pix = render_crops(model, views, verts, size=192, supersample=2)
        full = render_mesh(verts, model.faces, views.world_to_camera, views.intrinsics, size, size,
                           albedo=model.albedo, sh=model.sh, background=model.background, supersample=2,
                           adjacency=model.adjacency).image
        reference = crop_and_resize(full, torch.tensor([box]), 192)
    diff = (crop - reference).abs()
    assert crop.shape == (1, 192, 192, 3) and triangle.shape == (1, 192, 192)
    assert diff.mean() < 1e-3 and diff.max() < 0.2, (diff.mean(), diff.max())  # max: silhouette pixels
    direct = render_mesh(verts, model.faces, views.world_to_camera,  # the head rendered straight at 192^2
                         crop_intrinsics(views.intrinsics, views.boxes, 192)[0], 192, 192, albedo=model.albedo,
                         sh=model.sh, background=model.background, supersample=2, adjacency=model.adjacency).image
    print("mean difference to the plate's crop: ours", diff.mean().item(), "direct",
          (direct - reference).abs().mean().item())
    assert (direct - reference).abs().mean() > 3 * diff.mean()
    assert (triangle >= 0).float().mean() > 0.3  # the head fills the crop
    # the projected vertices are in crop pixels: the visible triangles lie under their corners
    ys, xs = torch.nonzero(triangle[0] >= 0, as_tuple=True)
    corner = pix[0, torch.as_tensor(model.faces)[triangle[0, ys, xs]]].mean(1)
    assert (corner - torch.stack([xs, ys], -1)).norm(dim=-1).median() < 1.5


def test_render_noise_is_the_same_in_any_batch(model):
    box = [70.3, 60.7, 190.1, 180.5]
    noisy = FitModel(**{**model.__dict__, "noise": 0.02})
    _, one, v1 = _scene(model, 256, 65.0, [box])
    _, two, v2 = _scene(model, 256, 65.0, [[60.0, 50.0, 200.0, 190.0], box])
    with torch.no_grad():
        alone = render_crops(noisy, one, v1)[0]
        batch = render_crops(noisy, two, v2)[0]
        clean = render_crops(model, one, v1)[0]
    torch.testing.assert_close(alone[0], batch[1], atol=1e-5, rtol=0)  # another render size: float rounding
    # box 120 px, upsampled to 192: the plate's per-pixel noise is bilinearly interpolated
    assert 0.005 < (alone - clean).std().item() < 0.02


def test_estimate_noise_on_known_noise():
    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:200, 0:240] / 200.0
    smooth = np.stack([0.3 + 0.2 * x, 0.4 + 0.1 * np.sin(3 * y), 0.5 * x * y], -1)
    smooth[80:120, 60:180] += 0.3  # an edge: a minority of pixels
    assert estimate_noise(smooth) < 1e-3
    for sigma in (0.003, 0.02):
        est = estimate_noise(smooth + rng.normal(0, sigma, smooth.shape))
        assert abs(est - sigma) < 0.1 * sigma, (est, sigma)
    assert estimate_noise(np.zeros((2, 5, 3))) == 0.0


def test_identity_from_the_468_face_mesh_points():
    pytest.importorskip("tflite")
    from nodegraph import ImageSequence, Landmarks2D, NodeError, run_node
    from nodes.fit import EstimateIdentity
    from tests.support.synthetic import random_face_parameters, render_truth_plates
    from nodes.landmarks import DetectFaces, FaceLandmarks

    face = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0)
    truth = random_face_parameters(face, 2, seed=5, distance_cm=65.0)
    seq = ImageSequence(render_truth_plates(face, [cam], truth)[0], colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    marks = run_node(FaceLandmarks, images=seq, boxes=boxes)
    where = dict(frames=range(2), boxes=[boxes], cameras=[cam], model=face)
    params = {"frames_used": 2, "iterations": 10, "rounds": 2}
    i68 = np.asarray(run_node(EstimateIdentity, params, landmarks=[marks["landmarks68"]], **where)
                     ["identity"].value["identity"])
    i468 = np.asarray(run_node(EstimateIdentity, params, landmarks=[marks["landmarks468"]], **where)
                      ["identity"].value["identity"])
    effect = np.abs(i468 - i68).max()
    assert np.isfinite(i468).all() and effect > 0.05  # the 400 other points count (0.28 here)
    none = np.asarray(run_node(EstimateIdentity, dict(params, mesh_weight=0.0), landmarks=[marks["landmarks468"]],
                               **where)["identity"].value["identity"])
    # weight 0: the 68 alone. The two solves sum different arrays (68 against 468 points, zeros
    # included) through 20 Levenberg-Marquardt steps of a weakly conditioned identity. In
    # float32 they agreed to 9e-3 on one 2-core machine, 4e-4 on another (issue 30); the solves
    # are float64 now (fit.solve.SOLVE_DTYPE): sums of ~4e3 terms round at ~4e3 * 1.1e-16 =
    # 4.4e-13 relative, and even through a normal matrix of condition 1e7 the identity (|a| < 3)
    # moves by < 1e-5, below the 1e-4 bound; the float32 result rounds at 2.4e-7 (measured: 0).
    # The looser bound is relative to what the test tells apart: a tenth of the 400 points' effect.
    assert np.abs(none - i68).max() < 1e-4, (np.abs(none - i68).max(), effect)
    assert np.abs(none - i68).max() < 0.1 * effect, (np.abs(none - i68).max(), effect)
    bad = Landmarks2D(marks["landmarks468"].points[:, :100], marks["landmarks468"].confidence[:, :100])
    with pytest.raises(NodeError, match="landmarks.*468, 2"):
        run_node(EstimateIdentity, params, landmarks=[bad], **where)


def test_default_appearance_carries_the_plates_noise_when_asked():
    pytest.importorskip("tflite")
    from nodegraph import NodeError, run_node
    from nodes.fit import EstimateAppearance
    from tests.support.synthetic import random_face_parameters, read_plates, render_truth_plates

    face = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0)
    truth = random_face_parameters(face, 2, seed=5, distance_cm=65.0)
    seq, boxes, marks = read_plates(render_truth_plates(face, [cam], truth, noise=0.03)[0])
    where = dict(images=seq, landmarks=marks, boxes=boxes, camera=cam, model=face)
    assert run_node(EstimateAppearance, {"mode": "default", "noise": 0}, **where)["appearance"].value["noise"] == 0.0
    for asked in (-1, -2):  # the plate's; by default (-2) the plate's where it is above 0.02
        noise = run_node(EstimateAppearance, {"mode": "default", "noise": asked}, **where)["appearance"].value["noise"]
        assert abs(noise - 0.03) < 0.003
    with pytest.raises(NodeError, match="'frame': expected a frame of the shot"):
        run_node(EstimateAppearance, {"mode": "default", "noise": -1, "frame": 7}, **where)


def test_view_spread_counts_the_frames_turns_and_the_cameras():
    from scipy.spatial.transform import Rotation

    from nodes.fit.frame_selection import view_spread_deg
    from tests.support.synthetic import orbit_camera

    cam0 = Camera.from_fov(256, 256, 30.0)
    cam1 = orbit_camera(cam0, 35.0, [0.0, 0.0, 65.0])
    w2c = torch.as_tensor(np.stack([cam0.world_to_camera, cam1.world_to_camera]), dtype=torch.float32)
    turns = torch.as_tensor(Rotation.from_euler("y", [[0.0], [12.0], [-5.0]], degrees=True).as_matrix(), dtype=torch.float32)
    one = torch.tensor([[True, False]] * 3)
    assert abs(view_spread_deg(turns, w2c, one) - 12.0) < 1e-3  # the largest turn from the first frame
    assert view_spread_deg(turns[:1], w2c, one[:1]) == 0.0  # one view
    still = turns[:1].expand(3, 3, 3)
    assert abs(view_spread_deg(still, w2c, torch.tensor([[True, True]] * 3)) - 35.0) < 1e-3  # the second camera
    assert view_spread_deg(turns, w2c, torch.zeros(3, 2, dtype=torch.bool)) == 0.0  # nothing seen


def test_checked_plates_of_selected_frames_are_those_rows_of_all_the_plates():
    """fit.EstimateIdentity converts only the frames it uses (4 of a shot) to linear colour: the
    same values as those rows of the whole shot's conversion."""
    from nodegraph import ImageSequence
    from nodes.fit.node_inputs import _checked_plates

    pixels = np.random.default_rng(0).random((6, 8, 10, 4)).astype(np.float32)
    seq = ImageSequence(pixels, channels=["R", "G", "B", "A"], colour_space="srgb")
    cam = Camera.from_fov(10, 8, 40.0)
    pick = np.array([1, 4])
    whole = _checked_plates([seq], [cam], 6)[0]
    part = _checked_plates([seq], [cam], 6, select=pick)[0]
    assert part.shape == (2, 8, 10, 3)
    np.testing.assert_array_equal(part, whole[pick])
