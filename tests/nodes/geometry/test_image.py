"""Tests of nodes.geometry.image against independent references: scipy.ndimage's
map_coordinates (bilinear sampling, resizing), block means in numpy (box filter), scipy's 1-D
filters (Gaussian, binomial pyramid), hand-built crops of known boxes (plain, shrunk by a box
filter, turned by 90 degrees and by an arbitrary angle); gradients by torch.autograd.gradcheck
in float64 and by forward-mode autodiff.

Tolerances: every comparison is float64, where the two computations differ only in the order
of a few roundings of numbers of order 1 (errors of order 1e-15); 1e-10 leaves a wide margin
and still fails on any wrong weight, index or half-pixel shift (those move results by 1e-2 or
more on uniform random images).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from nodes.geometry.image import (box_downsample, crop_and_resize, crop_intrinsics, crop_to_image, gaussian_blur,
                                  gaussian_kernel, image_to_crop, pyramid_down, resize_bilinear, sample_bilinear)

TOL = 1e-10
SCIPY_MODE = {"border": "nearest", "zeros": "grid-constant"}  # order-1 map_coordinates equivalents


def _images(rng: np.random.Generator, n: int, h: int, w: int, c: int) -> torch.Tensor:
    return torch.from_numpy(rng.uniform(size=(n, h, w, c)))


def _map_coordinates(image: np.ndarray, xy: np.ndarray, mode: str) -> np.ndarray:
    """(H, W, C) image sampled at (..., 2) x, y by scipy, order 1 -> (..., C)."""
    coords = np.stack([xy[..., 1].ravel(), xy[..., 0].ravel()])
    out = [ndimage.map_coordinates(image[..., k], coords, order=1, mode=mode, cval=0.0) for k in range(image.shape[-1])]
    return np.stack(out, -1).reshape(*xy.shape[:-1], image.shape[-1])


# -- sampling --------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["gather", "grid_sample"])
@pytest.mark.parametrize("padding", ["border", "zeros"])
def test_sample_bilinear_matches_map_coordinates(padding, method):
    rng = np.random.default_rng(0)
    images = _images(rng, 2, 7, 11, 3)
    xy = torch.from_numpy(rng.uniform([-3.0, -3.0], [14.0, 10.0], size=(2, 5, 40, 2)))  # some outside
    xy[0, 0, :4] = torch.tensor([[0.0, 0.0], [10.0, 6.0], [-0.5, 3.0], [10.5, 6.5]], dtype=torch.float64)
    ours = sample_bilinear(images, xy, padding=padding, method=method)
    assert ours.shape == (2, 5, 40, 3)
    for b in range(2):
        ref = _map_coordinates(images[b].numpy(), xy[b].numpy(), SCIPY_MODE[padding])
        np.testing.assert_allclose(ours[b].numpy(), ref, atol=TOL, rtol=0)


def test_sample_bilinear_zeros_fades_over_the_half_pixel_outside():
    image = torch.ones(1, 3, 4, 1, dtype=torch.float64)
    xy = torch.tensor([[[-0.5, 1.0], [-0.25, 1.0], [-1.0, 1.0], [-7.0, 1.0], [3.5, 1.0], [1.0, 2.75], [40.0, 1.0]]],
                      dtype=torch.float64)
    for method in ("gather", "grid_sample"):
        out = sample_bilinear(image, xy, padding="zeros", method=method)[0, :, 0]
        np.testing.assert_allclose(out.numpy(), [0.5, 0.75, 0.0, 0.0, 0.5, 0.25, 0.0], atol=TOL)


def test_sample_bilinear_gradient_matches_finite_differences_and_is_zero_where_clamped():
    rng = np.random.default_rng(1)
    images = _images(rng, 2, 6, 9, 2)
    cell = rng.integers([-2, -2], [10, 7], size=(2, 30, 2))  # x, y cells, some outside
    xy = torch.from_numpy(cell + rng.uniform(0.1, 0.9, size=cell.shape))  # away from the cell edges
    step = 1e-5
    for padding in ("border", "zeros"):
        value, grad = sample_bilinear(images, xy, padding=padding, gradient=True)
        np.testing.assert_allclose(value.numpy(), sample_bilinear(images, xy, padding=padding).numpy(), atol=0)
        for axis in range(2):
            shift = torch.zeros(2, dtype=torch.float64)
            shift[axis] = step
            ref = np.stack([_map_coordinates(images[b].numpy(), (xy[b] + shift).numpy(), SCIPY_MODE[padding])
                            - _map_coordinates(images[b].numpy(), (xy[b] - shift).numpy(), SCIPY_MODE[padding])
                            for b in range(2)]) / (2 * step)  # exact on a linear piece, but for rounding / step
            np.testing.assert_allclose(grad[..., axis].numpy(), ref, atol=1e-8, rtol=0)
    _, grad = sample_bilinear(images, xy, padding="border", gradient=True)
    outside_x = (xy[..., 0] < 0) | (xy[..., 0] > 8)
    assert outside_x.any() and float(grad[..., 0][outside_x].abs().max()) == 0.0


def test_sample_bilinear_gather_goes_through_forward_mode_autodiff():
    rng = np.random.default_rng(2)
    images = _images(rng, 1, 5, 6, 3)
    xy = torch.from_numpy(rng.uniform(-1.0, 6.0, size=(1, 20, 2)))
    for padding in ("border", "zeros"):
        _, grad = sample_bilinear(images, xy, padding=padding, gradient=True)
        for axis in range(2):
            tangent = torch.zeros_like(xy)
            tangent[..., axis] = 1.0
            _, jvp = torch.func.jvp(lambda p: sample_bilinear(images, p, padding=padding), (xy,), (tangent,))
            np.testing.assert_allclose(jvp.numpy(), grad[..., axis].numpy(), atol=TOL)


@pytest.mark.parametrize("method", ["gather", "grid_sample"])
@pytest.mark.parametrize("padding", ["border", "zeros"])
def test_sample_bilinear_gradcheck(padding, method):
    rng = np.random.default_rng(3)
    images = _images(rng, 1, 4, 5, 2).requires_grad_(True)
    cell = rng.integers([-1, -1], [6, 5], size=(1, 6, 2))
    xy = torch.from_numpy(cell + rng.uniform(0.1, 0.9, size=cell.shape)).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda i, p: sample_bilinear(i, p, padding=padding, method=method), (images, xy))


def test_sample_bilinear_one_pixel_axis_with_border():
    images = torch.tensor([[[[2.0], [5.0]]]], dtype=torch.float64)  # H = 1, W = 2
    value, grad = sample_bilinear(images, torch.tensor([[[0.25, 0.7], [0.5, -3.0]]], dtype=torch.float64),
                                  gradient=True)
    np.testing.assert_allclose(value[0, :, 0].numpy(), [2.75, 3.5])
    np.testing.assert_allclose(grad[0, :, 0].numpy(), [[3.0, 0.0], [3.0, 0.0]])


def test_sample_bilinear_rejects_bad_input():
    images = torch.zeros(2, 4, 4, 3)
    with pytest.raises(ValueError, match=r"images: expected a tensor of shape \(B, H, W, C\), found \(4, 4, 3\)"):
        sample_bilinear(images[0], torch.zeros(4, 5, 2))
    with pytest.raises(ValueError, match=r"xy: expected shape \(2, \.\.\., 2\), found \(3, 5, 2\)"):
        sample_bilinear(images, torch.zeros(3, 5, 2))
    with pytest.raises(ValueError, match="padding: expected 'border' or 'zeros', found 'reflect'"):
        sample_bilinear(images, torch.zeros(2, 5, 2), padding="reflect")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="gradient: .*method='gather' only"):
        sample_bilinear(images, torch.zeros(2, 5, 2), gradient=True, method="grid_sample")


def test_resize_bilinear_matches_map_coordinates_at_pixel_centres():
    rng = np.random.default_rng(4)
    images = _images(rng, 2, 6, 9, 3)
    for size in [(13, 20), (4, 5), (6, 9)]:
        out = resize_bilinear(images, size)
        ys, xs = np.meshgrid((np.arange(size[0]) + 0.5) * 6 / size[0] - 0.5, (np.arange(size[1]) + 0.5) * 9 / size[1] - 0.5,
                             indexing="ij")
        for b in range(2):
            ref = _map_coordinates(images[b].numpy(), np.stack([xs, ys], -1), "nearest")
            np.testing.assert_allclose(out[b].numpy(), ref, atol=TOL, rtol=0)
    flat = torch.full((1, 12, 16, 3), 0.25, dtype=torch.float64)
    np.testing.assert_allclose(resize_bilinear(flat, (5, 7), antialias=True).numpy(), 0.25, atol=TOL)


# -- filters ---------------------------------------------------------------------------------
@pytest.mark.parametrize("k", [1, 2, 3])
def test_box_downsample_is_the_block_mean_with_zero_padding(k):
    rng = np.random.default_rng(5)
    images = _images(rng, 2, 7, 8, 3)
    out = box_downsample(images, k)
    h, w = -(-7 // k), -(-8 // k)
    padded = np.zeros((2, h * k, w * k, 3))
    padded[:, :7, :8] = images.numpy()
    ref = padded.reshape(2, h, k, w, k, 3).mean((2, 4))
    assert out.shape == (2, h, w, 3)
    np.testing.assert_allclose(out.numpy(), ref, atol=TOL, rtol=0)
    x = images[:1, :4, :6, :1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: box_downsample(t, k), (x,))


def test_box_downsample_of_a_window_of_a_larger_image():
    rng = np.random.default_rng(6)
    images = _images(rng, 1, 20, 24, 3)
    window = images[:, 3:15, 5:17]  # a strided view, pooled in place
    np.testing.assert_allclose(box_downsample(window, 4).numpy(),
                               window.numpy().reshape(1, 3, 4, 3, 4, 3).mean((2, 4)), atol=TOL, rtol=0)


@pytest.mark.parametrize("sigma", [0.6, 1.0, 2.3])
def test_gaussian_blur_matches_scipy(sigma):
    rng = np.random.default_rng(7)
    images = _images(rng, 2, 15, 18, 3)
    radius = max(1, int(np.ceil(2.5 * sigma)))
    ref = ndimage.gaussian_filter(images.numpy(), (0, sigma, sigma, 0), mode="nearest", truncate=radius / sigma)
    np.testing.assert_allclose(gaussian_blur(images, sigma).numpy(), ref, atol=TOL, rtol=0)
    kernel = gaussian_kernel(sigma, dtype=torch.float64)
    assert kernel.shape == (2 * radius + 1,) and abs(float(kernel.sum()) - 1.0) < 1e-15
    assert gaussian_blur(images, 0.0) is images
    x = images[:1, :5, :6, :1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: gaussian_blur(t, sigma), (x,))


def test_pyramid_down_is_the_binomial_blur_at_even_pixels():
    rng = np.random.default_rng(8)
    images = _images(rng, 1, 11, 14, 2)
    kernel = np.array([1.0, 4.0, 6.0, 4.0, 1.0]) / 16
    ref = ndimage.correlate1d(ndimage.correlate1d(images.numpy(), kernel, axis=1, mode="nearest"), kernel, axis=2,
                              mode="nearest")[:, ::2, ::2]
    out = pyramid_down(images)
    assert out.shape == (1, 6, 7, 2)
    np.testing.assert_allclose(out.numpy(), ref, atol=TOL, rtol=0)


# -- crops -----------------------------------------------------------------------------------
def test_crop_of_the_whole_image_at_its_size_is_the_image():
    rng = np.random.default_rng(9)
    images = _images(rng, 2, 10, 10, 3)
    box = np.array([[-0.5, -0.5, 9.5, 9.5]] * 2)
    np.testing.assert_allclose(crop_and_resize(images, box, 10).numpy(), images.numpy(), atol=TOL, rtol=0)


def test_crop_turned_by_90_degrees_is_the_image_turned():
    rng = np.random.default_rng(10)
    images = _images(rng, 1, 8, 8, 3)
    out = crop_and_resize(images, np.array([[-0.5, -0.5, 7.5, 7.5]]), 8, np.array([np.pi / 2]))
    # crop pixel (i, j) samples centre + R d with d = (j - 3.5, i - 3.5): image x = 7 - i, y = j
    ref = images[0].numpy()[:, ::-1].transpose(1, 0, 2)
    np.testing.assert_allclose(out[0].numpy(), ref, atol=TOL, rtol=0)


def test_crop_shrinking_by_k_is_the_block_mean():
    rng = np.random.default_rng(11)
    images = _images(rng, 1, 12, 12, 3)
    out = crop_and_resize(images, np.array([[-0.5, -0.5, 11.5, 11.5]]), 4)  # k = 3: samples at block centres
    np.testing.assert_allclose(out[0].numpy(), images[0].numpy().reshape(4, 3, 4, 3, 3).mean((1, 3)), atol=TOL, rtol=0)


@pytest.mark.parametrize("size, angle", [(6, 0.0), (6, 0.4), (16, -1.1), (5, 2.5)])
def test_crop_matches_a_numpy_reference(size, angle):
    """Box filter (for k >= 2) and rotated sampling positions, built in numpy; scipy samples."""
    rng = np.random.default_rng(12)
    h, w = 23, 29
    images = _images(rng, 2, h, w, 3)
    boxes = np.array([[3.2, 2.7, 17.9, 17.4], [-6.0, -4.0, 20.0, 22.0]])  # the second leaves the image
    out = crop_and_resize(images, boxes, size, np.array([angle, -angle]))
    for b, (x0, y0, x1, y1) in enumerate(boxes):
        k = int(min(x1 - x0, y1 - y0) / size)
        image = images[b].numpy()
        if k >= 2:  # block means of the zero-padded image; pooled pixel j is centred at k j + (k - 1) / 2
            hp, wp = -(-h // k), -(-w // k)
            padded = np.zeros((hp * k, wp * k, 3))
            padded[:h, :w] = image
            image = padded.reshape(hp, k, wp, k, 3).mean((1, 3))
        else:
            k = 1
        theta = angle if b == 0 else -angle
        t = (np.arange(size) + 0.5) / size - 0.5
        dx, dy = np.meshgrid(t * (x1 - x0), t * (y1 - y0))  # (S, S): offsets from the box centre, crop axes
        x = (x0 + x1) / 2 + np.cos(theta) * dx - np.sin(theta) * dy
        y = (y0 + y1) / 2 + np.sin(theta) * dx + np.cos(theta) * dy
        ref = _map_coordinates(image, np.stack([(x - (k - 1) / 2) / k, (y - (k - 1) / 2) / k], -1), "grid-constant")
        np.testing.assert_allclose(out[b].numpy(), ref, atol=TOL, rtol=0)


def test_crop_gradcheck_in_the_pixels():
    rng = np.random.default_rng(13)
    images = _images(rng, 2, 8, 9, 2).requires_grad_(True)
    boxes = np.array([[0.3, 0.6, 7.3, 7.6], [1.1, -0.8, 5.1, 3.2]])  # 7 px -> 3: k = 2; 4 px -> 3: k = 1
    assert torch.autograd.gradcheck(lambda t: crop_and_resize(t, boxes, 3, np.array([0.3, -0.2])), (images,))


def test_crop_rejects_bad_input():
    images = torch.zeros(2, 8, 8, 3)
    with pytest.raises(ValueError, match=r"boxes: expected shape \(2, 4\), found \(1, 4\)"):
        crop_and_resize(images, np.zeros((1, 4)), 4)
    with pytest.raises(ValueError, match=r"angles: expected shape \(2,\), found \(3,\)"):
        crop_and_resize(images, np.zeros((2, 4)), 4, np.zeros(3))
    with pytest.raises(ValueError, match=r"images: expected a tensor of shape \(B, H, W, C\)"):
        crop_and_resize(images[0], np.zeros((2, 4)), 4)


def test_crop_coordinate_maps_agree_with_the_crop_intrinsics():
    rng = np.random.default_rng(14)
    intrinsics = torch.tensor([[500.0, 500.0, 320.0, 240.0], [400.0, 410.0, 300.0, 200.0]], dtype=torch.float64)
    boxes = torch.from_numpy(np.concatenate([rng.uniform(50, 150, (3, 2, 2)), np.zeros((3, 2, 2))], -1))
    boxes[..., 2:] = boxes[..., :2] + torch.from_numpy(rng.uniform(80, 300, (3, 2, 1)))
    points = torch.from_numpy(rng.uniform(-5, 5, (3, 2, 10, 3)) + np.array([0.0, 0.0, 60.0]))  # camera frame, cm
    image = points[..., :2] / points[..., 2:] * intrinsics[None, :, None, :2] + intrinsics[None, :, None, 2:]
    crop_k = crop_intrinsics(intrinsics, boxes, 192)
    crop = points[..., :2] / points[..., 2:] * crop_k[..., None, :2] + crop_k[..., None, 2:]
    np.testing.assert_allclose(image_to_crop(image, boxes, 192).numpy(), crop.numpy(), atol=1e-9)
    np.testing.assert_allclose(crop_to_image(crop, boxes, 192).numpy(), image.numpy(), atol=1e-9)
    # crop pixel j's centre is at x0 + (j + 1/2) s / S
    corner = crop_to_image(torch.zeros(3, 2, 1, 2, dtype=torch.float64), boxes, 192)[..., 0, :]
    np.testing.assert_allclose(corner.numpy(), (boxes[..., :2] + (boxes[..., 2:3] - boxes[..., 0:1]) / 384).numpy())
