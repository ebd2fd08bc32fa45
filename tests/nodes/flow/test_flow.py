"""Dense flow on pairs with known flow (translated texture, renders of the head under a known
motion) against OpenCV DIS, gradients of the flow, the geometric render flow, the node."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from nodegraph import ImageSequence, run_node  # noqa: E402
from nodes.flow import OpticalFlow  # noqa: E402
from nodes.flow.dense import FlowSettings, dense_flow, endpoint_error  # noqa: E402
from nodes.flow.geometric import render_flow  # noqa: E402
from tests.support.synthetic import head_motion, make_scene, render_scene_plates, scene_vertices  # noqa: E402


def _texture(size: int, shift: tuple[float, float], seed: int = 0) -> np.ndarray:
    """A smooth periodic noise texture, translated by `shift` (x, y) pixels in the Fourier domain."""
    rng = np.random.default_rng(seed)
    spec = np.fft.fft2(rng.standard_normal((size, size)))
    fy, fx = np.meshgrid(np.fft.fftfreq(size), np.fft.fftfreq(size), indexing="ij")
    spec *= np.exp(-(fx ** 2 + fy ** 2) / (2 * 0.08 ** 2))
    a = np.real(np.fft.ifft2(spec))
    b = np.real(np.fft.ifft2(spec * np.exp(-2j * np.pi * (fx * shift[0] + fy * shift[1]))))
    lo, hi = a.min(), a.max()
    return np.stack([(a - lo) / (hi - lo), (b - lo) / (hi - lo)]).astype(np.float32)


def _dis(i1: np.ndarray, i2: np.ndarray) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    u8 = lambda a: (np.clip(a, 0, 1) * 255).astype(np.uint8)  # noqa: E731
    return dis.calc(u8(i1), u8(i2), None)  # (H, W, 2)


def test_dense_flow_recovers_a_translated_texture():
    pair = _texture(96, (1.3, -0.7))
    img = torch.as_tensor(pair)[:, None]
    flow = dense_flow(img[:1], img[1:])[0]
    inner = (slice(8, -8), slice(8, -8))
    epe = (flow - torch.tensor([1.3, -0.7])[:, None, None]).norm(dim=0)[inner].mean().item()
    assert epe < 0.1
    try:
        import cv2  # noqa: F401
    except ImportError:
        return
    d = _dis(pair[0], pair[1])
    dis_epe = np.linalg.norm(d - np.array([1.3, -0.7]), axis=-1)[inner].mean()
    print(f"texture EPE ours {epe:.3f} px, DIS medium {dis_epe:.3f} px")
    # measured: ours 0.075, DIS 0.031 px: DIS wins on a pure translation (its patch fit is
    # exact for it); both are far below the 0.5 px the temporal solves care about
    assert epe <= 4.0 * dis_epe + 0.02


@pytest.fixture(scope="module")
def face_pair():
    scene = make_scene(80)
    values = head_motion(2, scene.model.expression_names, seed=3, mouth_frames=(0, 2))
    plates = render_scene_plates(scene, values)
    verts = scene_vertices(scene, values)
    cam = scene.camera
    e = torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None]
    k = torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]])
    truth, mask = render_flow(verts[:1], verts[1:], torch.as_tensor(scene.faces), e, k, cam.height, cam.width)
    return plates, truth, mask


def test_dense_flow_on_face_renders_within_1p5x_of_dis(face_pair):
    plates, truth, mask = face_pair
    img = torch.as_tensor(plates.pixels).permute(0, 3, 1, 2)
    flow = dense_flow(img[:1], img[1:])
    epe = endpoint_error(flow, truth, mask).item()
    assert truth.norm(dim=1)[mask].mean() > 0.5  # the motion is not trivial
    assert epe < 0.8
    try:
        import cv2  # noqa: F401
    except ImportError:
        return
    srgb = np.clip(plates.pixels, 0, 1) ** (1 / 2.2)
    grey = srgb @ np.array([0.2126, 0.7152, 0.0722])
    d = torch.as_tensor(_dis(grey[0], grey[1])).permute(2, 0, 1)[None]
    dis_epe = endpoint_error(d, truth, mask).item()
    print(f"face EPE ours {epe:.3f} px, DIS medium {dis_epe:.3f} px")
    assert epe <= 1.5 * dis_epe


def test_dense_flow_gradients_reach_both_images():
    gen = torch.Generator().manual_seed(0)
    a = torch.rand(1, 1, 6, 6, dtype=torch.float64, generator=gen, requires_grad=True)
    b = (a.detach().roll(1, 3) + 0.05 * torch.rand(1, 1, 6, 6, dtype=torch.float64, generator=gen))
    b.requires_grad_(True)
    s = FlowSettings(levels=1, warps=1, finest_warps=1, iterations=2, finest_iterations=2, median=False)
    assert torch.autograd.gradcheck(lambda x, y: dense_flow(x, y, s), (a, b), eps=1e-6, atol=1e-4)


def test_dense_flow_error_names_arguments():
    with pytest.raises(ValueError, match="image1, image2"):
        dense_flow(torch.zeros(1, 1, 8, 8), torch.zeros(1, 1, 8, 9))


def test_render_flow_of_a_translated_triangle_and_its_gradient():
    v = torch.tensor([[[-1.0, -1, 10], [1, -1, 10], [0, 1, 10]]], dtype=torch.float64)
    e = torch.eye(4, dtype=torch.float64)[None]
    k = torch.tensor([[50.0, 50, 15.5, 15.5]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2]])
    moved = (v + torch.tensor([0.2, -0.1, 0.0], dtype=torch.float64)).requires_grad_(True)
    flow, mask = render_flow(v, moved, faces, e, k, 32, 32)
    assert mask.sum() > 40
    np.testing.assert_allclose(flow[0, :, mask[0]].mean(1).detach().numpy(), [1.0, -0.5], atol=1e-9)
    flow[0, 0][mask[0]].sum().backward()
    assert moved.grad[0, :, 0].sum().item() == pytest.approx(5.0 * mask.sum().item(), rel=1e-6)


def test_optical_flow_node_marks_the_last_frame_invalid(face_pair):
    plates, truth, mask = face_pair
    out = run_node(OpticalFlow, {"levels": 3}, images=plates)["flow"]
    assert out.flow.shape == (2, 80, 80, 2) and out.valid.tolist() == [True, False]
    assert np.abs(out.flow[1]).max() == 0
