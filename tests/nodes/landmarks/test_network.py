"""Landmark network: tflite replay against the reference interpreter, gradients, detection on a
photograph and on face-free images, the heatmap head, crops."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("tflite")

from nodes.landmarks.correspondence import MEDIAPIPE_TO_68, inter_ocular_distance, mediapipe_to_68  # noqa: E402
from nodes.landmarks.heatmap import HeatmapLandmarks, soft_argmax_patch  # noqa: E402
from nodes.geometry.image import crop_and_resize  # noqa: E402
from nodes.landmarks.network import (FACE_DETECTOR_MODEL, FACE_LANDMARK_MODEL,  # noqa: E402
                                     decode_detections, detect_faces, face_landmarks, load_face_detector,
                                     load_face_mesh, mediapipe_path, ssd_anchors, weighted_nms)
from nodes.landmarks.tflite_torch import TfliteModule, read_tflite  # noqa: E402


@pytest.fixture(scope="module")
def astronaut() -> np.ndarray:
    data = pytest.importorskip("skimage.data")
    return data.astronaut().astype(np.float32) / 255.0


def _litert(path):
    interpreter = pytest.importorskip("ai_edge_litert.interpreter")
    it = interpreter.Interpreter(model_path=str(path))
    it.allocate_tensors()
    return it


def _reference(it, x: np.ndarray) -> dict[str, np.ndarray]:
    it.set_tensor(it.get_input_details()[0]["index"], x)
    it.invoke()
    return {d["name"]: it.get_tensor(d["index"]) for d in it.get_output_details()}


def test_read_tflite_lists_operators_and_io():
    graph = read_tflite(mediapipe_path(FACE_LANDMARK_MODEL))
    assert graph.tensors[graph.inputs[0]].shape == (1, 192, 192, 3)
    assert [graph.tensors[i].name for i in graph.outputs] == ["conv2d_21", "conv2d_31"]
    assert {op.name for op in graph.operators} == {"DEQUANTIZE", "CONV_2D", "DEPTHWISE_CONV_2D", "PRELU", "ADD",
                                                   "MAX_POOL_2D", "PAD"}
    params = sum(t.data.size for t in graph.tensors if t.data is not None and t.dtype == np.float16)
    assert params == pytest.approx(604_685, rel=0.01)


def test_read_tflite_rejects_other_files(tmp_path):
    bad = tmp_path / "x.tflite"
    bad.write_bytes(b"not a model at all")
    with pytest.raises(ValueError, match="not a TFLite flatbuffer"):
        read_tflite(bad)


def test_face_mesh_matches_reference_interpreter_on_crops(astronaut):
    it = _litert(mediapipe_path(FACE_LANDMARK_MODEL))
    mesh = load_face_mesh()
    det = detect_faces(torch.from_numpy(astronaut)[None])
    crops = [crop_and_resize(torch.from_numpy(astronaut)[None], det.boxes * s + (1 - s) * det.boxes.mean(), 192)
             for s in (1.0, 0.8, 1.3)]
    rng = np.random.default_rng(0)
    crops.append(torch.from_numpy(rng.uniform(0, 1, (1, 192, 192, 3)).astype(np.float32)))
    for crop in crops:
        ref = _reference(it, crop.numpy())
        with torch.no_grad():
            coords, logit = mesh.net(crop)
        np.testing.assert_allclose(coords.numpy().reshape(-1), ref["conv2d_21"].reshape(-1), atol=1e-3)
        np.testing.assert_allclose(logit.numpy().reshape(-1), ref["conv2d_31"].reshape(-1), atol=1e-3)


def test_face_detector_matches_reference_interpreter(astronaut):
    it = _litert(mediapipe_path(FACE_DETECTOR_MODEL))
    module = TfliteModule(read_tflite(mediapipe_path(FACE_DETECTOR_MODEL)), ["regressors", "classificators"])
    x = crop_and_resize(torch.from_numpy(astronaut)[None], np.array([[-0.5, -0.5, 511.5, 511.5]]), 128) * 2 - 1
    ref = _reference(it, x.numpy())
    with torch.no_grad():
        regressors, logits = module(x)
    np.testing.assert_allclose(regressors.numpy(), ref["regressors"], atol=1e-3)
    np.testing.assert_allclose(logits.numpy(), ref["classificators"], atol=1e-3)


def test_face_mesh_gradient_matches_finite_differences(astronaut):
    mesh = load_face_mesh().double()
    try:
        det = detect_faces(torch.from_numpy(astronaut)[None])
        crop = crop_and_resize(torch.from_numpy(astronaut)[None].double(), det.boxes, 192).detach()
        weights = torch.as_tensor(np.random.default_rng(1).standard_normal((1, 468, 2)))

        def loss(x):
            return (mesh(x)[0] * weights).sum()

        x = crop.clone().requires_grad_()
        loss(x).backward()
        assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
        rng = np.random.default_rng(2)
        for _ in range(1):
            direction = torch.as_tensor(rng.standard_normal(crop.shape))
            h = 1e-7  # small: ReLU, PReLU and max-pool kinks stay uncrossed
            with torch.no_grad():
                numeric = (loss(crop + h * direction) - loss(crop - h * direction)).item() / (2 * h)
            assert (x.grad * direction).sum().item() == pytest.approx(numeric, rel=1e-4)
    finally:
        mesh.float()


def test_detect_faces_finds_the_astronaut_and_68_points_fall_on_the_face(astronaut):
    images = torch.from_numpy(astronaut)[None]
    det = detect_faces(images)
    assert det.found[0] and det.scores[0] > 0.8
    x0, y0, x1, y1 = det.face_boxes[0]
    assert 160 < x0 < 200 and 60 < y0 < 100 and 250 < x1 < 290 and 155 < y1 < 195  # her face
    points, presence = face_landmarks(images, det.boxes, load_face_mesh())
    assert presence.item() > 0.9
    p68 = mediapipe_to_68(points[0]).numpy()
    w, h = x1 - x0, y1 - y0
    assert ((p68[:, 0] > x0 - 0.1 * w) & (p68[:, 0] < x1 + 0.1 * w)).all()
    assert ((p68[:, 1] > y0 - 0.1 * h) & (p68[:, 1] < y1 + 0.3 * h)).all()
    # anatomy: brows over eyes over nose tip over mouth over chin; her right eye on the image left
    assert p68[17:27, 1].mean() < p68[36:48, 1].mean() < p68[30, 1] < p68[48:68, 1].mean() < p68[8, 1]
    assert p68[36:42, 0].mean() < p68[30, 0] < p68[42:48, 0].mean()
    iod = inter_ocular_distance(p68)
    assert 45 < iod < 80


@pytest.mark.parametrize("name", ["rocket", "coins", "page"])
def test_detect_faces_reports_no_face_on_face_free_images(name):
    data = pytest.importorskip("skimage.data")
    img = getattr(data, name)().astype(np.float32) / 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, -1)
    det = detect_faces(torch.from_numpy(img)[None])
    assert not det.found[0] and np.isnan(det.boxes[0]).all() and det.scores[0] == 0


def test_ssd_anchors_and_decoding():
    anchors = ssd_anchors()
    assert anchors.shape == (896, 2)
    np.testing.assert_allclose(anchors[0], [1 / 32, 1 / 32])
    np.testing.assert_allclose(anchors[512], [1 / 16, 1 / 16])
    raw = torch.zeros(1, 896, 16)
    raw[0, 5, :4] = torch.tensor([12.8, -6.4, 32.0, 64.0])
    boxes, kps, scores = decode_detections(raw, torch.zeros(1, 896, 1))
    cx, cy = anchors[5] + [0.1, -0.05]
    np.testing.assert_allclose(boxes[0, 5].numpy(), [cx - 0.125, cy - 0.25, cx + 0.125, cy + 0.25], atol=1e-6)
    np.testing.assert_allclose(kps[0, 5, 0].numpy(), anchors[5], atol=1e-6)
    assert scores[0, 5].item() == pytest.approx(0.5)


def test_weighted_nms_averages_overlapping_boxes():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [50, 50, 60, 60]], float)
    kps = np.zeros((3, 6, 2))
    faces = weighted_nms(boxes, kps, np.array([0.9, 0.6, 0.7]), min_score=0.5)
    assert len(faces) == 2
    np.testing.assert_allclose(faces[0][0], [0.4, 0, 10.4, 10])
    assert faces[0][2] == pytest.approx(0.9) and faces[1][2] == pytest.approx(0.7)


def test_crop_and_resize_identity_and_gradient():
    rng = np.random.default_rng(0)
    img = torch.tensor(rng.uniform(0, 1, (1, 16, 16, 3)), dtype=torch.float64, requires_grad=True)
    out = crop_and_resize(img, np.array([[-0.5, -0.5, 15.5, 15.5]]), 16)
    np.testing.assert_allclose(out.detach().numpy(), img.detach().numpy(), atol=1e-12)
    half = crop_and_resize(img, np.array([[3.5, 3.5, 11.5, 11.5]]), 4)  # 2x2 blocks of pixels 4..11
    want = img.detach()[0, 4:12, 4:12].reshape(4, 2, 4, 2, 3).mean((1, 3))
    np.testing.assert_allclose(half[0].detach().numpy(), want.numpy(), atol=1e-12)
    half.sum().backward()
    assert img.grad[0, 4:12, 4:12].sum().item() == pytest.approx(48.0)
    assert img.grad[0, :4].abs().sum().item() == 0


def test_soft_argmax_patch_weights_the_3x3_window():
    h = torch.zeros(2, 8, 8, dtype=torch.float64)
    h[0, 3, 4] = 1.0
    h[0, 3, 5] = 0.9
    h[0, 0, 0] = 0.95  # outside the window of the maximum: ignored
    h[1, 0, 0] = 1.0  # at the corner: the window is cut
    m = soft_argmax_patch(h, beta=50.0)
    w = np.exp(50 * np.array([1.0, 0.9]))
    w = np.concatenate([w, np.ones(7)])
    x = (4 * w[0] + 5 * w[1] + 3 * 3 + 4 * 2 + 5 * 2) / w.sum()
    y = (3 * (w[0] + w[1]) + 3 * 1 + 2 * 3 + 4 * 3) / w.sum()
    assert m[0].tolist() == pytest.approx([x, y])
    assert m[1, 0].item() < 0.01 and m[1, 1].item() < 0.01
    hh = h.clone().requires_grad_()
    soft_argmax_patch(hh)[0, 0].backward()
    assert hh.grad[0, 3, 5].item() > 0 and hh.grad[0, 3, 3].item() < 0


def test_heatmap_landmarks_plugs_a_heatmap_network_in():
    targets = torch.tensor([[10.25, 20.0], [40.0, 33.5]])  # heatmap pixels of a 64 x 64 map

    class Toy(torch.nn.Module):
        def forward(self, x):
            ys, xs = torch.meshgrid(torch.arange(64.0), torch.arange(64.0), indexing="ij")
            d2 = (xs[None] - targets[:, 0, None, None]) ** 2 + (ys[None] - targets[:, 1, None, None]) ** 2
            return (torch.exp(-d2 / 2.0)[None] * (1 + 0 * x.mean())).expand(len(x), -1, -1, -1)

    net = HeatmapLandmarks(Toy(), 256)
    crops = torch.zeros(1, 256, 256, 3)
    points, presence = net(crops)
    assert net.num_points == 2 and presence.item() > 0.5
    # soft-argmax on the 3x3 patch pulls towards the true peak; 64 -> 256: (m + 1/2) * 4
    np.testing.assert_allclose(points[0].numpy(), (targets.numpy() + 0.5) * 4, atol=1.2)
    pts, _ = face_landmarks(torch.zeros(1, 300, 300, 3), np.array([[10.0, 20.0, 138.0, 148.0]]), net)
    np.testing.assert_allclose(pts[0].numpy(), [10, 20] + points[0].numpy() / 2, atol=1e-4)


def test_mediapipe_to_68_table_is_valid_and_symmetric():
    assert MEDIAPIPE_TO_68.shape == (68,) and len(set(MEDIAPIPE_TO_68.tolist())) == 68
    assert MEDIAPIPE_TO_68.min() >= 0 and MEDIAPIPE_TO_68.max() < 468
    with pytest.raises(ValueError, match=r"points: expected shape \(\.\.\., 468, D\)"):
        mediapipe_to_68(np.zeros((68, 2)))


def test_load_face_detector_is_cached():
    assert load_face_detector() is load_face_detector()


def test_grid_anchors_extend_the_128_anchors():
    from nodes.landmarks.network import grid_anchors

    np.testing.assert_allclose(grid_anchors(128, 128), ssd_anchors() * 128)
    assert grid_anchors(256, 384).shape == (32 * 48 * 2 + 16 * 24 * 6, 2)


def test_pyramid_scales_adapt_to_the_frame():
    from nodes.landmarks.network import pyramid_scales

    assert pyramid_scales(256, 256, 40.0) == [] and pyramid_scales(4000, 4000, 0.0) == []
    scales = pyramid_scales(2160, 3840, 40.0)
    assert scales[-1] == pytest.approx(0.5) and all(b <= 2 * a + 1e-12 for a, b in zip(scales, scales[1:]))


def test_crop_and_resize_turned_by_90_degrees_is_rot90():
    rng = np.random.default_rng(3)
    img = torch.tensor(rng.uniform(0, 1, (1, 16, 16, 3)), dtype=torch.float64)
    box = np.array([[-0.5, -0.5, 15.5, 15.5]])
    out = crop_and_resize(img, box, 16, np.array([np.pi / 2]))
    # crop pixel (u, v) samples centre + R(90) (u - c, v - c) = image (x = 15 - v, y = u)
    v, u = np.meshgrid(np.arange(16), np.arange(16), indexing="ij")
    np.testing.assert_allclose(out[0].numpy(), img[0].numpy()[u, 15 - v], atol=1e-9)


def test_face_landmarks_turns_points_back_and_points_roll():
    from nodes.landmarks.network import points_roll

    class Corner(torch.nn.Module):  # one point at the crop's (x, y) = (12, 4) of 16
        input_size = 16
        num_points = 1

        def forward(self, crops):
            return torch.tensor([[[12.0, 4.0]]]).expand(len(crops), 1, 2), torch.ones(len(crops))

    box = np.array([[10.0, 20.0, 26.0, 36.0]])  # centre (18, 28), 1 px per crop pixel
    pts, _ = face_landmarks(torch.zeros(1, 40, 40, 3), box, Corner(), np.array([np.pi / 2]))
    np.testing.assert_allclose(pts[0, 0].numpy(), [18 - (-4.0), 28 + 4.0], atol=1e-5)  # (4, -4) turned by 90 deg
    p68 = np.zeros((68, 2))
    p68[42:48] = [10.0, 10.0]  # left eye below-right of the right eye at the origin: 45 deg
    assert np.rad2deg(points_roll(p68)) == pytest.approx(45.0)
