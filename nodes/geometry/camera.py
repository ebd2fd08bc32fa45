"""Pinhole camera projection with radial distortion (OpenCV convention), numpy and torch.

Conventions:
    - World points in cm; `world_to_camera` is the rigid (..., 4, 4) `T_camera_world`
      (`x_cam = R x_world + t`, matrices act on column vectors).
    - Camera frame: x to the right, y down, z forward: the camera looks down +z and a point
      is in front of it when z > 0.
    - Pixels: origin at the top-left of the image, u (x) to the right, v (y) down; pixel
      (0, 0) is the centre of the top-left pixel, as in OpenCV.
    - `intrinsics` (..., 4) = (fx, fy, cx, cy) in pixels; `distortion` (..., 2) = (k1, k2),
      unitless, radial distortion of the normalized coordinates `(x, y) = (X / Z, Y / Z)`:
      `(x_d, y_d) = (x, y) * (1 + k1 r^2 + k2 r^4)` with `r^2 = x^2 + y^2`; then
      `u = fx x_d + cx`, `v = fy y_d + cy`.

`project_points` / `unproject_pixels` compute in float64 numpy; `project_points_torch` /
`unproject_pixels_torch` are the differentiable tensor versions (same formulas: both call the
private kernels below, which use only array operators, so the two cannot drift apart). Batch
dims of points, transforms, intrinsics and distortion broadcast against each other.
Torch is imported only inside the torch functions.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["look_at", "project_points", "project_points_torch", "unproject_pixels", "unproject_pixels_torch"]

UNDISTORT_ITERATIONS = 12
"""Newton steps of the radial undistortion in `unproject_pixels` (converged to float64
rounding for |k1| r^2 + |k2| r^4 up to about 0.3)."""


# --------------------------------------------------------------------------------------
# Kernels shared by numpy and torch (operators, slicing and `swapaxes` only)
# --------------------------------------------------------------------------------------
def _project(points: Any, world_to_camera: Any, intrinsics: Any, distortion: Any | None,
             stack: Callable[[Sequence[Any], int], Any]) -> Any:
    """(..., N, 3) world points -> (..., N, 2) pixels (see the module docstring)."""
    rot = world_to_camera[..., :3, :3]
    cam = points @ rot.swapaxes(-1, -2) + world_to_camera[..., None, :3, 3]
    z = cam[..., 2]
    x = cam[..., 0] / z
    y = cam[..., 1] / z
    if distortion is not None:
        r2 = x * x + y * y
        factor = 1.0 + r2 * (distortion[..., 0:1] + distortion[..., 1:2] * r2)
        x = x * factor
        y = y * factor
    u = intrinsics[..., 0:1] * x + intrinsics[..., 2:3]
    v = intrinsics[..., 1:2] * y + intrinsics[..., 3:4]
    return stack([u, v], -1)


def _unproject(pixels: Any, depth: Any, world_to_camera: Any, intrinsics: Any, distortion: Any | None,
               iterations: int, stack: Callable[[Sequence[Any], int], Any]) -> Any:
    """(..., N, 2) pixels + (..., N) camera depth -> (..., N, 3) world points."""
    x = (pixels[..., 0] - intrinsics[..., 2:3]) / intrinsics[..., 0:1]
    y = (pixels[..., 1] - intrinsics[..., 3:4]) / intrinsics[..., 1:2]
    if distortion is not None:
        # Solve s (1 + a s^2 + b s^4) = 1 for s = r_undistorted / r_distorted by Newton from
        # s = 1, with a = k1 r_d^2 and b = k2 r_d^4 (no division by r_d, exact at r_d = 0).
        r2 = x * x + y * y
        a = distortion[..., 0:1] * r2
        b = distortion[..., 1:2] * r2 * r2
        s = 1.0 + 0.0 * r2
        for _ in range(iterations):
            s2 = s * s
            s = s - (s * (1.0 + s2 * (a + b * s2)) - 1.0) / (1.0 + s2 * (3.0 * a + 5.0 * b * s2))
        x = x * s
        y = y * s
    cam = stack([x * depth, y * depth, depth], -1)
    # x_world = R^T (x_cam - t), written for row vectors: (x_cam - t) @ R
    return (cam - world_to_camera[..., None, :3, 3]) @ world_to_camera[..., :3, :3]


def _check_last(name: str, shape: tuple[int, ...], want: tuple[int, ...], expected: str) -> None:
    if len(shape) < len(want) or tuple(shape[len(shape) - len(want):]) != want:
        raise ValueError(f"{name}: expected shape {expected}, found {tuple(shape)}")


def _check(points_name: str, points_shape: tuple[int, ...], last: int, world_to_camera_shape: tuple[int, ...],
           intrinsics_shape: tuple[int, ...], distortion_shape: tuple[int, ...] | None) -> None:
    _check_last(points_name, points_shape, (last,), f"(..., N, {last})")
    if len(points_shape) < 2:
        raise ValueError(f"{points_name}: expected shape (..., N, {last}), found {tuple(points_shape)}")
    _check_last("world_to_camera", world_to_camera_shape, (4, 4), "(..., 4, 4)")
    _check_last("intrinsics", intrinsics_shape, (4,), "(..., 4) (fx, fy, cx, cy)")
    if distortion_shape is not None:
        _check_last("distortion", distortion_shape, (2,), "(..., 2) (k1, k2)")


# --------------------------------------------------------------------------------------
# numpy
# --------------------------------------------------------------------------------------
def project_points(points: np.ndarray, world_to_camera: np.ndarray, intrinsics: np.ndarray | Sequence[float],
                   distortion: np.ndarray | Sequence[float] | None = None) -> np.ndarray:
    """Project world points to pixels through a pinhole camera with radial distortion.

    Args:
        points: (..., N, 3) world points, cm.
        world_to_camera: (..., 4, 4) rigid `T_camera_world`.
        intrinsics: (..., 4) (fx, fy, cx, cy), pixels.
        distortion: (..., 2) (k1, k2), or None for none.
    Returns:
        (..., N, 2) float64 pixel coordinates (u right, v down, origin top-left).
    Raises:
        ValueError: an argument has the wrong trailing shape (named, with the shape found).
    Note:
        Points at z = 0 in the camera frame give inf / nan; points behind the camera (z < 0)
        project through the centre to the mirrored position (no culling).

    Example:
        >>> project_points(np.array([[1.0, -2.0, 10.0]]), np.eye(4), [100.0, 100.0, 32.0, 24.0]).tolist()
        [[42.0, 4.0]]
    """
    points = np.asarray(points, np.float64)
    world_to_camera = np.asarray(world_to_camera, np.float64)
    intrinsics = np.asarray(intrinsics, np.float64)
    distortion = None if distortion is None else np.asarray(distortion, np.float64)
    _check("points", points.shape, 3, world_to_camera.shape, intrinsics.shape,
           None if distortion is None else distortion.shape)
    return _project(points, world_to_camera, intrinsics, distortion, np.stack)


def unproject_pixels(pixels: np.ndarray, depth: np.ndarray, world_to_camera: np.ndarray,
                     intrinsics: np.ndarray | Sequence[float],
                     distortion: np.ndarray | Sequence[float] | None = None) -> np.ndarray:
    """Return the world points seen at `pixels` at camera depth `depth` (inverse of `project_points`).

    The radial distortion is inverted by `UNDISTORT_ITERATIONS` Newton steps on the radius
    ratio (vectorized over pixels).

    Args:
        pixels: (..., N, 2) pixel coordinates (u right, v down, origin top-left).
        depth: (..., N) camera-frame z of the points, cm (> 0 in front of the camera).
        world_to_camera: (..., 4, 4) rigid `T_camera_world`.
        intrinsics: (..., 4) (fx, fy, cx, cy), pixels.
        distortion: (..., 2) (k1, k2), or None for none.
    Returns:
        (..., N, 3) float64 world points, cm.
    Raises:
        ValueError: an argument has the wrong trailing shape (named, with the shape found).
    Note:
        The inverse is unique where the distortion is monotonic,
        `1 + 3 k1 r^2 + 5 k2 r^4 > 0` up to the point's undistorted radius r; outside (strong
        barrel distortion far from the centre) the result is meaningless.

    Example:
        >>> unproject_pixels(np.array([[42.0, 4.0]]), np.array([10.0]), np.eye(4),
        ...                  [100.0, 100.0, 32.0, 24.0]).tolist()
        [[1.0, -2.0, 10.0]]
    """
    pixels = np.asarray(pixels, np.float64)
    depth = np.asarray(depth, np.float64)
    world_to_camera = np.asarray(world_to_camera, np.float64)
    intrinsics = np.asarray(intrinsics, np.float64)
    distortion = None if distortion is None else np.asarray(distortion, np.float64)
    _check("pixels", pixels.shape, 2, world_to_camera.shape, intrinsics.shape,
           None if distortion is None else distortion.shape)
    if depth.shape != pixels.shape[:-1]:
        raise ValueError(f"depth: expected shape {pixels.shape[:-1]} (pixels without the last "
                         f"axis), found {depth.shape}")
    return _unproject(pixels, depth, world_to_camera, intrinsics, distortion, UNDISTORT_ITERATIONS,
                      np.stack)


# --------------------------------------------------------------------------------------
# torch
# --------------------------------------------------------------------------------------
def _as_tensors(first: Tensor, *others: Any) -> list[Any]:
    """Return the arguments as tensors on `first`'s device in one dtype.

    The dtype is the promoted float dtype of the tensor arguments (float32 when none is a
    float tensor); sequences and numpy arrays are converted straight to it (no float32
    detour, so float64 work keeps e.g. k1 = -0.12 exact).
    """
    import torch

    dtype = first.dtype if first.is_floating_point() else torch.float32
    for value in others:
        if isinstance(value, torch.Tensor) and value.is_floating_point():
            dtype = torch.promote_types(dtype, value.dtype)
    return [None if v is None else torch.as_tensor(v, dtype=dtype, device=first.device)
            for v in (first,) + others]


def project_points_torch(points: Tensor, world_to_camera: Tensor, intrinsics: Tensor | Sequence[float],
                         distortion: Tensor | Sequence[float] | None = None) -> Tensor:
    """Project world points to pixels; the differentiable tensor version of `project_points`.

    Args:
        points: (..., N, 3) world points, cm.
        world_to_camera: (..., 4, 4) rigid `T_camera_world`.
        intrinsics: (..., 4) (fx, fy, cx, cy), pixels.
        distortion: (..., 2) (k1, k2), or None for none.
    Returns:
        (..., N, 2) pixels in the promoted float dtype of the inputs, on `points.device`;
        differentiable in every input.
    Raises:
        ValueError: an argument has the wrong trailing shape (named, with the shape found).
    """
    import torch

    points, world_to_camera, intrinsics, distortion = _as_tensors(points, world_to_camera, intrinsics,
                                                                  distortion)
    _check("points", tuple(points.shape), 3, tuple(world_to_camera.shape), tuple(intrinsics.shape),
           None if distortion is None else tuple(distortion.shape))
    return _project(points, world_to_camera, intrinsics, distortion, torch.stack)


def unproject_pixels_torch(pixels: Tensor, depth: Tensor, world_to_camera: Tensor,
                           intrinsics: Tensor | Sequence[float],
                           distortion: Tensor | Sequence[float] | None = None) -> Tensor:
    """Return world points from pixels and depth; the differentiable version of `unproject_pixels`.

    Args:
        pixels: (..., N, 2) pixel coordinates (u right, v down, origin top-left).
        depth: (..., N) camera-frame z, cm.
        world_to_camera: (..., 4, 4) rigid `T_camera_world`.
        intrinsics: (..., 4) (fx, fy, cx, cy), pixels.
        distortion: (..., 2) (k1, k2), or None for none.
    Returns:
        (..., N, 3) world points in the promoted float dtype, on `pixels.device`;
        differentiable in every input (through the Newton steps).
    Raises:
        ValueError: an argument has the wrong trailing shape (named, with the shape found).
    """
    import torch

    pixels, depth, world_to_camera, intrinsics, distortion = _as_tensors(pixels, depth, world_to_camera,
                                                                         intrinsics, distortion)
    _check("pixels", tuple(pixels.shape), 2, tuple(world_to_camera.shape), tuple(intrinsics.shape),
           None if distortion is None else tuple(distortion.shape))
    if tuple(depth.shape) != tuple(pixels.shape[:-1]):
        raise ValueError(f"depth: expected shape {tuple(pixels.shape[:-1])} (pixels without the last "
                         f"axis), found {tuple(depth.shape)}")
    return _unproject(pixels, depth, world_to_camera, intrinsics, distortion, UNDISTORT_ITERATIONS,
                      torch.stack)


def look_at(eye_cm: Sequence[float], target_cm: Sequence[float], up: Sequence[float] = (0.0, 1.0, 0.0)) -> np.ndarray:
    """The world-to-camera transform of a camera at `eye_cm` looking at `target_cm`.

    OpenCV convention: the camera looks down its +z, x to the right, y down; the world's `up`
    appears up in the image.

    Args:
        eye_cm: (3,) camera centre, world, cm.
        target_cm: (3,) point on the optical axis, world, cm.
        up: (3,) world direction shown up (not parallel to the viewing direction).
    Returns:
        (4, 4) float64 rigid transform, `x_cam = E @ x_world`.
    Raises:
        ValueError: when eye and target coincide or `up` is parallel to the viewing direction.

    Example:
        >>> (look_at([0, 0, 60], [0, 0, 0])[:3].round(6) + 0.0).tolist()  # + 0.0: no -0.0
        [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 60.0]]
    """
    eye, target, up_ = (np.asarray(v, np.float64) for v in (eye_cm, target_cm, up))
    forward = target - eye
    if np.linalg.norm(forward) < 1e-9:
        raise ValueError(f"expected a target away from the eye, found both at {eye.tolist()}")
    z = forward / np.linalg.norm(forward)
    down = -(up_ - (up_ @ z) * z)
    if np.linalg.norm(down) < 1e-9 * max(1.0, np.linalg.norm(up_)):
        raise ValueError(f"expected an up direction not parallel to the view {z.round(6).tolist()}, found "
                         f"{up_.tolist()}")
    y = down / np.linalg.norm(down)
    x = np.cross(y, z)
    e = np.eye(4)
    e[:3, :3] = np.stack([x, y, z])
    e[:3, 3] = -e[:3, :3] @ eye
    return e
