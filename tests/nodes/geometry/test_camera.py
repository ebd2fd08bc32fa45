"""Tests of nodes.geometry.camera: pinhole projection with radial distortion, numpy and torch."""

import doctest
import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nodes.geometry import camera
from nodes.geometry.camera import project_points, project_points_torch, unproject_pixels, unproject_pixels_torch

INTRINSICS = np.array([800.0, 780.0, 320.0, 240.0])  # fx, fy, cx, cy (pixels)
DISTORTION = np.array([-0.12, 0.03])                 # k1, k2


def _world_to_camera(rng, batch=()):
    count = int(np.prod(batch, dtype=int))
    m = np.tile(np.eye(4), (count, 1, 1))
    m[:, :3, :3] = Rotation.from_rotvec(rng.normal(scale=0.3, size=(count, 3))).as_matrix()
    m[:, :3, 3] = rng.normal(scale=2.0, size=(count, 3)) + [0.0, 0.0, 60.0]
    return m.reshape(batch + (4, 4))


def _points_in_front(rng, world_to_camera, n):
    """(..., n, 3) world points at camera depth 40..80 cm inside a +-25 deg cone."""
    batch = world_to_camera.shape[:-2]
    z = rng.uniform(40.0, 80.0, batch + (n,))
    xy = rng.uniform(-0.45, 0.45, batch + (n, 2)) * z[..., None]
    cam = np.concatenate([xy, z[..., None]], -1)
    rot, trans = world_to_camera[..., :3, :3], world_to_camera[..., :3, 3]
    return np.einsum("...ji,...nj->...ni", rot, cam - trans[..., None, :])


def _naive_project(point, world_to_camera, intrinsics, distortion):
    """One point, plain float64 arithmetic (the reference)."""
    cam = [sum(world_to_camera[i][j] * point[j] for j in range(3)) + world_to_camera[i][3] for i in range(3)]
    x, y = cam[0] / cam[2], cam[1] / cam[2]
    k1, k2 = distortion
    r2 = x * x + y * y
    f = 1.0 + k1 * r2 + k2 * r2 * r2
    fx, fy, cx, cy = intrinsics
    return [fx * x * f + cx, fy * y * f + cy]


def test_project_points_matches_naive_float64_loop():
    rng = np.random.default_rng(0)
    m = _world_to_camera(rng)
    pts = _points_in_front(rng, m, 25)
    got = project_points(pts, m, INTRINSICS, DISTORTION)
    want = [_naive_project(p, m.tolist(), INTRINSICS.tolist(), DISTORTION.tolist()) for p in pts.tolist()]
    assert got.shape == (25, 2) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    undistorted = [_naive_project(p, m.tolist(), INTRINSICS.tolist(), [0.0, 0.0]) for p in pts.tolist()]
    np.testing.assert_allclose(project_points(pts, m, INTRINSICS), undistorted, rtol=0, atol=1e-9)


def test_project_points_follows_opencv_axes():
    k = [100.0, 100.0, 32.0, 24.0]
    centre, right, down = project_points(np.array([[0.0, 0, 10], [1, 0, 10], [0, 1, 10]]), np.eye(4), k)
    assert centre.tolist() == [32.0, 24.0]       # the optical axis hits the principal point
    assert right[0] > 32.0 and right[1] == 24.0  # camera +x is image right
    assert down[1] > 24.0 and down[0] == 32.0    # camera +y is image down


@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_project_unproject_round_trip_and_batch_shapes(batch):
    rng = np.random.default_rng(1)
    m = _world_to_camera(rng, batch)
    pts = _points_in_front(rng, m, 7)
    k = np.broadcast_to(INTRINSICS, batch + (4,))
    d = np.broadcast_to(DISTORTION, batch + (2,))
    px = project_points(pts, m, k, d)
    assert px.shape == batch + (7, 2)
    depth = (pts @ np.swapaxes(m[..., :3, :3], -1, -2) + m[..., None, :3, 3])[..., 2]
    back = unproject_pixels(px, depth, m, k, d)
    assert back.shape == batch + (7, 3)
    np.testing.assert_allclose(back, pts, rtol=0, atol=1e-9)


def test_unproject_pixels_matches_naive_float64_loop():
    rng = np.random.default_rng(2)
    m = _world_to_camera(rng)
    px = rng.uniform([0.0, 0.0], [640.0, 480.0], (30, 2))
    depth = rng.uniform(40.0, 80.0, 30)
    got = unproject_pixels(px, depth, m, INTRINSICS, DISTORTION)
    fx, fy, cx, cy = INTRINSICS.tolist()
    k1, k2 = DISTORTION.tolist()
    rot, trans = m[:3, :3].tolist(), m[:3, 3].tolist()
    for (u, v), z, point in zip(px.tolist(), depth.tolist(), got.tolist()):
        xd, yd = (u - cx) / fx, (v - cy) / fy
        rd = math.hypot(xd, yd)
        lo, hi = 0.0, 2.0 * rd + 1e-12            # bisection on r_u (1 + k1 r_u^2 + k2 r_u^4) = r_d
        for _ in range(200):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if mid * (1 + k1 * mid ** 2 + k2 * mid ** 4) < rd else (lo, mid)
        ratio = lo / rd if rd > 0 else 1.0
        cam = [xd * ratio * z, yd * ratio * z, z]
        want = [sum(rot[j][i] * (cam[j] - trans[j]) for j in range(3)) for i in range(3)]
        np.testing.assert_allclose(point, want, rtol=0, atol=1e-9)


def test_torch_versions_match_numpy_in_float32_and_float64():
    rng = np.random.default_rng(3)
    m = _world_to_camera(rng, (4,))
    pts = _points_in_front(rng, m, 11)
    px = project_points(pts, m, INTRINSICS, DISTORTION)
    depth = (pts @ np.swapaxes(m[..., :3, :3], -1, -2) + m[..., None, :3, 3])[..., 2]
    for dtype, atol_px, atol_cm in ((torch.float64, 1e-9, 1e-9), (torch.float32, 2e-3, 2e-4)):
        got = project_points_torch(torch.tensor(pts, dtype=dtype), torch.tensor(m, dtype=dtype),
                                   torch.tensor(INTRINSICS, dtype=dtype), torch.tensor(DISTORTION, dtype=dtype))
        assert got.dtype == dtype and got.shape == (4, 11, 2)
        np.testing.assert_allclose(got.numpy(), px, rtol=0, atol=atol_px)
        back = unproject_pixels_torch(torch.tensor(px, dtype=dtype), torch.tensor(depth, dtype=dtype),
                                      torch.tensor(m, dtype=dtype), INTRINSICS.tolist(), DISTORTION.tolist())
        assert back.dtype == dtype
        np.testing.assert_allclose(back.numpy(), pts, rtol=0, atol=atol_cm)
    # mixed dtypes promote; plain sequences are accepted for the intrinsics
    mixed = project_points_torch(torch.tensor(pts, dtype=torch.float32), torch.tensor(m), INTRINSICS.tolist())
    assert mixed.dtype == torch.float64


def test_project_points_torch_gradcheck():
    rng = np.random.default_rng(4)
    m = _world_to_camera(rng, (2,))
    pts = torch.tensor(_points_in_front(rng, m, 5), requires_grad=True)
    m = torch.tensor(m, requires_grad=True)
    k = torch.tensor(INTRINSICS, requires_grad=True)
    d = torch.tensor(DISTORTION, requires_grad=True)
    assert torch.autograd.gradcheck(project_points_torch, (pts, m, k, d))
    assert torch.autograd.gradcheck(lambda p, mm, kk: project_points_torch(p, mm, kk), (pts, m, k))


def test_unproject_pixels_torch_gradcheck():
    rng = np.random.default_rng(5)
    px = torch.tensor(rng.uniform([100.0, 80.0], [540.0, 400.0], (6, 2)), requires_grad=True)
    depth = torch.tensor(rng.uniform(40.0, 80.0, 6), requires_grad=True)
    m = torch.tensor(_world_to_camera(rng), requires_grad=True)
    k = torch.tensor(INTRINSICS, requires_grad=True)
    d = torch.tensor(DISTORTION, requires_grad=True)
    assert torch.autograd.gradcheck(unproject_pixels_torch, (px, depth, m, k, d))


@pytest.mark.parametrize("call, match", [
    (lambda: project_points(np.zeros((5, 2)), np.eye(4), INTRINSICS),
     r"points: expected shape \(\.\.\., N, 3\), found \(5, 2\)"),
    (lambda: project_points(np.zeros(3), np.eye(4), INTRINSICS),
     r"points: expected shape \(\.\.\., N, 3\), found \(3,\)"),
    (lambda: project_points(np.zeros((5, 3)), np.eye(3), INTRINSICS),
     r"world_to_camera: expected shape \(\.\.\., 4, 4\), found \(3, 3\)"),
    (lambda: project_points(np.zeros((5, 3)), np.eye(4), [1.0, 1.0, 0.0]),
     r"intrinsics: expected shape \(\.\.\., 4\) \(fx, fy, cx, cy\), found \(3,\)"),
    (lambda: project_points(np.zeros((5, 3)), np.eye(4), INTRINSICS, [0.1, 0.0, 0.0]),
     r"distortion: expected shape \(\.\.\., 2\) \(k1, k2\), found \(3,\)"),
    (lambda: unproject_pixels(np.zeros((5, 2)), np.ones(4), np.eye(4), INTRINSICS),
     r"depth: expected shape \(5,\) .*, found \(4,\)"),
    (lambda: project_points_torch(torch.zeros(5, 2), torch.eye(4), INTRINSICS),
     r"points: expected shape \(\.\.\., N, 3\), found \(5, 2\)"),
    (lambda: unproject_pixels_torch(torch.zeros(5, 2), torch.ones(5, 1), torch.eye(4), INTRINSICS),
     r"depth: expected shape \(5,\) .*, found \(5, 1\)"),
])
def test_camera_functions_reject_bad_shapes(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_camera_docstring_examples():
    result = doctest.testmod(camera)
    assert result.attempted > 0 and result.failed == 0
