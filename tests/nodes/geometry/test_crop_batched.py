"""crop_and_resize, batched (one grid and one grid_sample per group of images cropped alike),
against the per-image implementation it replaced, kept here as `reference_crop_and_resize`.

The two compute every sampling coordinate in the images' dtype by the same float operations in
the same order (the box's corner, side and centre rounded once from float64), and bilinear
`grid_sample` gives each output pixel the same arithmetic whether its image is sampled alone or
in a batch, so the crops agree to the bit on this machine (measured: max difference 0 on 300
random cases of 1-4 images, k = 0-4, turned and not). The tolerance allowed, 1e-6 on values in
[0, 1] (about 16 units in the last place of float32 at 1), leaves room for a kernel that
vectorises a batch differently and still fails on any half-pixel or block shift (those move
uniform random pixels by 1e-2 or more). The face mesh's and the iris model's points on the real
photos are compared with the reference crops in place (<= 1e-3 px, the issue's bound).
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from nodes.geometry import image as image_module
from nodes.geometry.image import box_downsample, crop_and_resize

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "landmarks"))

TOL = 1e-6


def reference_crop_and_resize(images: torch.Tensor, boxes: torch.Tensor | np.ndarray, size: int,
                              angles: torch.Tensor | np.ndarray | None = None) -> torch.Tensor:
    """crop_and_resize as it was at fe0ab08: a Python loop over the images, each with its own
    pooled window, grid and grid_sample (see `nodes.geometry.image.crop_and_resize`)."""
    boxes = torch.as_tensor(np.asarray(boxes, np.float64) if not isinstance(boxes, torch.Tensor) else boxes,
                            dtype=images.dtype, device=images.device).reshape(-1, 4)
    if angles is not None:
        angles = np.asarray(angles.detach().cpu() if isinstance(angles, torch.Tensor) else angles,
                            np.float64).reshape(-1)
    out = []
    t = (torch.arange(size, device=images.device, dtype=images.dtype) + 0.5) / size
    for b in range(len(images)):
        x0, y0, x1, y1 = boxes[b].tolist()
        img = images[b:b + 1]
        k = int(min(x1 - x0, y1 - y0) / size)
        offset, step = 0.0, 1.0
        if k >= 2:
            c = float(np.cos(angles[b])) if angles is not None else 1.0
            s = float(np.sin(angles[b])) if angles is not None else 0.0
            reach_x = (abs(c) * (x1 - x0) + abs(s) * (y1 - y0)) / 2 + 2 * k
            reach_y = (abs(s) * (x1 - x0) + abs(c) * (y1 - y0)) / 2 + 2 * k
            cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
            left = min(max(int(np.floor((cx - reach_x) / k)) * k, 0), (img.shape[2] - 1) // k * k)
            top = min(max(int(np.floor((cy - reach_y) / k)) * k, 0), (img.shape[1] - 1) // k * k)
            right = min(max(int(np.ceil((cx + reach_x) / k)) * k, left + k), img.shape[2] + (-img.shape[2]) % k)
            bottom = min(max(int(np.ceil((cy + reach_y) / k)) * k, top + k), img.shape[1] + (-img.shape[1]) % k)
            img = box_downsample(img[:, top:bottom, left:right], k)
            offset, step = (k - 1) / 2.0, float(k)
            x0, x1, y0, y1 = x0 - left, x1 - left, y0 - top, y1 - top
        if angles is None or angles[b] == 0.0:
            xs, ys = torch.broadcast_tensors((x0 + t * (x1 - x0))[None, :], (y0 + t * (y1 - y0))[:, None])
        else:
            dx, dy = torch.broadcast_tensors(((t - 0.5) * (x1 - x0))[None, :], ((t - 0.5) * (y1 - y0))[:, None])
            c, s = float(np.cos(angles[b])), float(np.sin(angles[b]))
            xs, ys = (x0 + x1) / 2 + c * dx - s * dy, (y0 + y1) / 2 + s * dx + c * dy
        x, y = (xs - offset) / step, (ys - offset) / step
        h, w = img.shape[1], img.shape[2]
        grid = torch.stack([(x + 0.5) / w * 2 - 1, (y + 0.5) / h * 2 - 1], -1)[None]
        sampled = F.grid_sample(img.permute(0, 3, 1, 2), grid, mode="bilinear", padding_mode="zeros",
                                align_corners=False)
        out.append(sampled.permute(0, 2, 3, 1))
    return torch.cat(out)


def _images(seed: int, n: int, h: int, w: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    return torch.rand(n, h, w, 3, generator=torch.Generator().manual_seed(seed), dtype=dtype)


S = 16
# (boxes, angles) on 4 images of 90 x 120 (H x W): k from the box side over S = 16
CASES = {
    "k1 inside": ([[30.3, 20.1, 52.7, 44.9]] * 4, None),
    "k1 rolled": ([[30.3, 20.1, 52.7, 44.9], [10.0, 5.0, 40.0, 35.0], [60.5, 40.5, 90.5, 70.5], [0, 0, 16, 16]],
                  [0.3, -1.2, 2.9, 0.0]),
    "k2 shrunk": ([[20.2, 10.7, 58.9, 49.4]] * 4, [0.1, 0.1, 0.1, 0.1]),
    "k3 shrunk rolled": ([[10.4, 3.3, 62.0, 54.9], [40.0, 20.0, 90.0, 70.0], [5.0, 5.0, 57.0, 57.0],
                          [30.0, 30.0, 82.0, 82.0]], [0.5, 0.0, -0.7, 3.1]),
    "out of the image": ([[-30.0, -25.0, 10.0, 15.0], [100.0, 70.0, 150.0, 120.0], [-60.0, -60.0, 200.0, 200.0],
                          [110.0, -40.0, 130.0, -20.0]], [0.2, 0.0, 0.4, -0.3]),
    "mixed k and angles": ([[30.0, 20.0, 45.0, 35.0], [20.0, 10.0, 58.0, 48.0], [10.0, 3.0, 62.0, 55.0],
                            [-70.0, -60.0, 190.0, 150.0]], [0.0, 0.4, 0.0, -2.0]),
    "non-square": ([[20.0, 30.0, 80.0, 45.0], [10.0, 5.0, 20.0, 80.0], [0.0, 0.0, 119.0, 89.0],
                    [50.0, 40.0, 51.0, 41.0]], [0.0, 0.25, 0.0, 1.0]),
}


@pytest.mark.parametrize("name", list(CASES))
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_matches_the_per_image_crops(name: str, dtype: torch.dtype) -> None:
    boxes, angles = CASES[name]
    images = _images(1, 4, 90, 120, dtype)
    boxes = np.asarray(boxes, np.float64)
    angles = None if angles is None else np.asarray(angles)
    got = crop_and_resize(images, boxes, S, angles)
    want = reference_crop_and_resize(images, boxes, S, angles)
    assert got.shape == (4, S, S, 3) and got.dtype == dtype and got.is_contiguous()
    assert (got - want).abs().max().item() <= TOL
    # each image alone gives its row of the batch (no image's crop depends on the others')
    for b in range(4):
        alone = crop_and_resize(images[b:b + 1], boxes[b:b + 1], S, None if angles is None else angles[b:b + 1])
        assert (alone[0] - got[b]).abs().max().item() <= TOL


def test_random_batches_match_the_per_image_crops() -> None:
    rng = np.random.default_rng(0)
    worst = 0.0
    for trial in range(60):
        n, h, w = int(rng.integers(1, 5)), int(rng.integers(20, 120)), int(rng.integers(20, 120))
        size = int(rng.choice([4, 7, 16]))
        images = _images(trial, n, h, w)
        centre_x, centre_y = rng.uniform(-20, w + 20, n), rng.uniform(-20, h + 20, n)
        side = rng.uniform(1, 4.5 * size, n)  # k = 0 .. 4
        boxes = np.stack([centre_x - side / 2, centre_y - side / 2 * rng.uniform(0.8, 1.2, n),
                          centre_x + side / 2, centre_y + side / 2], 1)
        angles = None if trial % 4 == 0 else np.where(rng.random(n) < 0.3, 0.0, rng.uniform(-3.2, 3.2, n))
        got = crop_and_resize(images, torch.from_numpy(boxes), size, angles)
        worst = max(worst, (got - reference_crop_and_resize(images, boxes, size, angles)).abs().max().item())
    assert worst <= TOL


def test_pixel_gradients_match_the_per_image_crops() -> None:
    boxes, angles = CASES["mixed k and angles"]
    weights = torch.rand(4, S, S, 3, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    grads = []
    for crop in (crop_and_resize, reference_crop_and_resize):
        images = _images(2, 4, 90, 120, torch.float64).requires_grad_(True)
        (crop(images, np.asarray(boxes), S, np.asarray(angles)) * weights).sum().backward()
        grads.append(images.grad)
    assert grads[0].abs().sum().item() > 1.0  # the crops do reach the pixels
    assert (grads[0] - grads[1]).abs().max().item() <= 1e-12  # float64: sums of the same few products


def test_unit_steps_are_cached_and_read_only_in_use() -> None:
    first = image_module._unit_steps(8, torch.device("cpu"), torch.float32)
    assert image_module._unit_steps(8, torch.device("cpu"), torch.float32) is first
    np.testing.assert_array_equal(first.numpy(), (np.arange(8, dtype=np.float32) + 0.5) / 8)
    crop_and_resize(_images(3, 1, 30, 30), np.array([[1.0, 2.0, 20.0, 21.0]]), 8, np.array([0.3]))
    np.testing.assert_array_equal(first.numpy(), (np.arange(8, dtype=np.float32) + 0.5) / 8)


def test_bad_boxes_and_angles_are_named() -> None:
    images = _images(4, 2, 20, 20)
    with pytest.raises(ValueError, match="boxes: expected shape"):
        crop_and_resize(images, np.zeros((3, 4)), 8)
    with pytest.raises(ValueError, match="boxes: expected finite"):
        crop_and_resize(images, np.array([[0.0, 0.0, 9.0, 9.0], [0.0, np.nan, 9.0, 9.0]]), 8)
    with pytest.raises(ValueError, match="angles: expected shape"):
        crop_and_resize(images, np.zeros((2, 4)), 8, np.zeros(3))
    with pytest.raises(ValueError, match="angles: expected finite"):
        crop_and_resize(images, np.zeros((2, 4)), 8, np.array([0.0, np.inf]))
    assert crop_and_resize(images[:0], np.zeros((0, 4)), 8).shape == (0, 8, 8, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cuda_matches_cpu() -> None:
    boxes, angles = CASES["mixed k and angles"]
    images = _images(6, 4, 90, 120)
    cpu = crop_and_resize(images, np.asarray(boxes), S, np.asarray(angles))
    cuda = crop_and_resize(images.cuda(), torch.tensor(boxes, device="cuda"), S, torch.tensor(angles, device="cuda"))
    assert cuda.device.type == "cuda"
    assert (cuda.cpu() - cpu).abs().max().item() <= 1e-5  # fused multiply-adds on the GPU: a few ulps


def test_photo_landmarks_do_not_move(monkeypatch: pytest.MonkeyPatch) -> None:
    """Face mesh points and iris points on the real photos with the batched crops and with the
    reference crops patched into the landmark code: <= 1e-3 px apart."""
    from cases import PHOTOS, photo  # noqa: E402

    from nodes.landmarks import iris as iris_module
    from nodes.landmarks import network as network_module
    from nodes.landmarks.iris import iris_landmarks, load_iris_network
    from nodes.landmarks.network import detect_faces, face_landmarks, load_face_mesh

    mesh, iris_net = load_face_mesh(), load_iris_network()
    for name in PHOTOS:
        img = torch.from_numpy(photo(name))[None]
        boxes = detect_faces(img).boxes
        results = []
        for crop in (crop_and_resize, reference_crop_and_resize):
            monkeypatch.setattr(network_module, "crop_and_resize", crop)
            monkeypatch.setattr(iris_module, "crop_and_resize", crop)
            with torch.no_grad():
                points, _ = face_landmarks(img, boxes, mesh, np.array([0.2]))
            results.append((points.double().numpy(), iris_landmarks(img, points.double().numpy(), iris_net)))
        (points, iris), (points_ref, iris_ref) = results
        assert np.isfinite(points).all() and np.isfinite(iris).all()
        assert np.abs(points - points_ref).max() <= 1e-3, name
        assert np.abs(iris - iris_ref).max() <= 1e-3, name
