"""Rotations: every conversion between axis-angle vectors, matrices, quaternions and Euler
angles, batched, in numpy (plain names) and torch (`_torch` names) where both are needed.

Conventions:
    - Angles in radians. An axis-angle vector (also "rotation vector", OpenCV's Rodrigues
      vector) is `(..., 3)`: the unit axis times the angle; `|omega| <= pi` on output.
    - Matrices are `(..., 3, 3)`, act on column vectors (`x' = R @ x`), det = +1.
    - Quaternions are `(..., 4)` `(w, x, y, z)`; outputs have unit norm and `w >= 0`
      (`q` and `-q` are the same rotation; inputs may have either sign and any non-zero norm).
    - Euler angles follow scipy's `Rotation.from_euler` names: three distinct axes, lower
      case extrinsic (about the fixed axes, the first axis applied first), upper case
      intrinsic (about the moving axes). Extrinsic `"xyz"` with angles `(a, b, c)` is
      `R = Rz(c) @ Ry(b) @ Rx(a)` (the synthetic head motion, the reports' plots); intrinsic
      `"YXZ"` is `R = Ry(a) @ Rx(b) @ Rz(c)` (ARKit's yaw, pitch, roll). Output ranges: the
      first and last angle in [-pi, pi], the middle one in [-pi/2, pi/2]; at gimbal lock
      (middle angle +-pi/2) the third angle is set to 0, as scipy does.

This module imports numpy only; the torch functions import torch when called, so area
modules can import it at module level and stay light. Tested against
`scipy.spatial.transform.Rotation` (tests/nodes/geometry/test_rotation.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "skew", "axis_angle_to_rotmat", "rotmat_to_axis_angle", "axis_angle_to_quat",
    "quat_to_axis_angle", "quat_to_rotmat", "rotmat_to_quat", "quat_mean", "quat_sequence_continuous",
    "euler_to_rotmat", "rotmat_to_euler",
    "skew_torch", "axis_angle_to_rotmat_torch", "quat_to_rotmat_torch", "rotmat_to_quat_torch",
]

_AXES = {"x": 0, "y": 1, "z": 2}


def _check_last(name: str, value: Any, shape: tuple[int, ...]) -> None:
    found = tuple(getattr(value, "shape", ()))
    if len(found) < len(shape) or found[len(found) - len(shape):] != shape:
        raise ValueError(f"{name}: expected shape (..., {', '.join(map(str, shape))}), found {found}")


# -- skew-symmetric (cross-product) matrices ------------------------------------------------

def skew(v: np.ndarray) -> np.ndarray:
    """Return the cross-product matrices `[v]x` with `[v]x @ u = v x u`.

    Args:
        v: (..., 3) vectors.
    Returns:
        (..., 3, 3) skew-symmetric matrices, dtype of `v` (float64 for integers).

    Example:
        >>> skew(np.array([1.0, 2.0, 3.0])).tolist()
        [[0.0, -3.0, 2.0], [3.0, 0.0, -1.0], [-2.0, 1.0, 0.0]]
    """
    v = np.asarray(v)
    if v.dtype.kind != "f":
        v = v.astype(np.float64)
    _check_last("v", v, (3,))
    out = np.zeros(v.shape + (3,), v.dtype)
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def skew_torch(v: Tensor) -> Tensor:
    """Torch twin of `skew`: (..., 3) -> (..., 3, 3) `[v]x`, differentiable."""
    import torch

    _check_last("v", v, (3,))
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v.unbind(-1)
    return torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).reshape(*v.shape[:-1], 3, 3)


# -- axis-angle <-> matrix -------------------------------------------------------------------

def axis_angle_to_rotmat(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, as OpenCV's `cv2.Rodrigues` and scipy's `Rotation.from_rotvec`.

    Args:
        omega: (..., 3) axis times angle, radians.
    Returns:
        (..., 3, 3) float64 rotations: `R = I + sin(t) [k]x + (1 - cos(t)) [k]x^2` with
        `t = |omega|`, `k = omega / t`.
    Note:
        Below t = 1e-12 the result is `I + [omega]x` (the first-order term; the second is
        below float64's resolution).

    Example:
        >>> axis_angle_to_rotmat(np.array([0.0, 0.0, np.pi / 2])).round(6).tolist()
        [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]
    """
    omega = np.asarray(omega, np.float64)
    _check_last("omega", omega, (3,))
    theta = np.linalg.norm(omega, axis=-1)[..., None]                  # (..., 1)
    small = theta < 1e-12
    k = skew(omega / np.where(small, 1.0, theta))
    theta, small = theta[..., None], small[..., None]                     # (..., 1, 1)
    rot = np.eye(3) + np.sin(theta) * k + (1.0 - np.cos(theta)) * (k @ k)
    return np.where(small, np.eye(3) + skew(omega), rot)


def axis_angle_to_rotmat_torch(omega: Tensor) -> Tensor:
    """Rodrigues' formula in torch, differentiable everywhere (Taylor series near 0).

    Args:
        omega: (..., 3) axis times angle, radians.
    Returns:
        (..., 3, 3) rotation matrices, dtype and device of `omega`:
        `R = I + a [omega]x + b [omega]x^2`, `a = sin(t) / t`, `b = (1 - cos(t)) / t^2`.
    Note:
        Below t^2 = 1e-8 the coefficients are their Taylor series `1 - t^2 / 6` and
        `1/2 - t^2 / 24`, so the gradient at 0 is exact.

    Example:
        >>> import torch
        >>> axis_angle_to_rotmat_torch(torch.tensor([0.0, 0.0, 3.14159265 / 2]))[0, 1].item() < -0.99
        True
    """
    import torch

    _check_last("omega", omega, (3,))
    theta2 = (omega * omega).sum(-1)[..., None, None]
    small = theta2 < 1e-8
    theta = theta2.clamp_min(1e-8).sqrt()
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / theta2.clamp_min(1e-8))
    k = skew_torch(omega)
    eye = torch.eye(3, dtype=omega.dtype, device=omega.device).expand_as(k)
    return eye + a * k + b * (k @ k)


def rotmat_to_axis_angle(rot: np.ndarray) -> np.ndarray:
    """Return the axis-angle vectors of rotation matrices (through `rotmat_to_quat`).

    Args:
        rot: (..., 3, 3) rotations (a matrix slightly off a rotation, e.g. stored in float32,
            gives the rotation of its quaternion, see `rotmat_to_quat`).
    Returns:
        (..., 3) float64 axis times angle, radians, angle in [0, pi].

    Example:
        >>> rotmat_to_axis_angle(axis_angle_to_rotmat(np.array([0.1, -0.2, 0.3]))).round(12).tolist()
        [0.1, -0.2, 0.3]
    """
    return quat_to_axis_angle(rotmat_to_quat(rot))


# -- quaternions ------------------------------------------------------------------------------

def axis_angle_to_quat(omega: np.ndarray) -> np.ndarray:
    """Return the unit quaternions of axis-angle vectors.

    Args:
        omega: (..., 3) axis times angle, radians.
    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z): `(cos(t/2), sin(t/2) omega / t)`,
        w >= 0 for angles up to pi.
    Note:
        Below t = 1e-12 the factor `sin(t/2) / t` is its series `1/2 - t^2 / 48`.
    """
    omega = np.asarray(omega, np.float64)
    _check_last("omega", omega, (3,))
    angle = np.linalg.norm(omega, axis=-1, keepdims=True)
    half = 0.5 * angle
    scale = np.where(angle > 1e-12, np.sin(half) / np.maximum(angle, 1e-12), 0.5 - angle ** 2 / 48.0)
    return np.concatenate([np.cos(half), omega * scale], -1)


def quat_to_axis_angle(quat: np.ndarray) -> np.ndarray:
    """Return the axis-angle vectors of quaternions.

    Args:
        quat: (..., 4) quaternions (w, x, y, z), any non-zero norm, either sign.
    Returns:
        (..., 3) float64 axis times angle, radians, angle in [0, pi]:
        `2 atan2(|v|, w) v / |v|` for the normalised `(w, v)` with w >= 0.
    """
    q = np.asarray(quat, np.float64)
    _check_last("quat", q, (4,))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    q = np.where(q[..., :1] < 0, -q, q)
    s = np.linalg.norm(q[..., 1:], axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(s, q[..., :1])
    factor = np.where(s > 1e-12, angle / np.maximum(s, 1e-12), 2.0)
    return q[..., 1:] * factor


def quat_to_rotmat(quat: np.ndarray) -> np.ndarray:
    """Return the rotation matrices of quaternions (normalised first).

    Args:
        quat: (..., 4) quaternions (w, x, y, z), any non-zero norm, either sign.
    Returns:
        (..., 3, 3) float64 rotations, det = +1.
    """
    q = np.asarray(quat, np.float64)
    _check_last("quat", q, (4,))
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    xx, yy, zz, xy, xz, yz = x * x, y * y, z * z, x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
            2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
            2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)]
    return np.stack(rows, -1).reshape(q.shape[:-1] + (3, 3))


def quat_to_rotmat_torch(q: Tensor) -> Tensor:
    """Torch twin of `quat_to_rotmat`: (..., 4) (w, x, y, z), any non-zero norm -> (..., 3, 3)
    rotations, det = +1, differentiable."""
    import torch

    _check_last("q", q, (4,))
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    rows = [
        1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy),
        2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx),
        2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy),
    ]
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def _quat_candidates(r: Any, stack: Any) -> Any:
    """Shepperd's four candidate quaternions of (..., 3, 3) matrices, each scaled by 4 times
    its largest component: (..., 4 candidates, 4)."""
    r00, r11, r22 = r[..., 0, 0], r[..., 1, 1], r[..., 2, 2]
    trace = r00 + r11 + r22
    return stack([
        stack([1 + trace, r[..., 2, 1] - r[..., 1, 2], r[..., 0, 2] - r[..., 2, 0],
               r[..., 1, 0] - r[..., 0, 1]], -1),
        stack([r[..., 2, 1] - r[..., 1, 2], 1 + r00 - r11 - r22,
               r[..., 0, 1] + r[..., 1, 0], r[..., 0, 2] + r[..., 2, 0]], -1),
        stack([r[..., 0, 2] - r[..., 2, 0], r[..., 0, 1] + r[..., 1, 0],
               1 - r00 + r11 - r22, r[..., 1, 2] + r[..., 2, 1]], -1),
        stack([r[..., 1, 0] - r[..., 0, 1], r[..., 0, 2] + r[..., 2, 0],
               r[..., 1, 2] + r[..., 2, 1], 1 - r00 - r11 + r22], -1),
    ], -2), stack([trace, r00, r11, r22], -1)


def rotmat_to_quat(rot: np.ndarray) -> np.ndarray:
    """Return the unit quaternions of rotation matrices (Shepperd's method, w >= 0).

    Args:
        rot: (..., 3, 3) rotations.
    Returns:
        (..., 4) float64 unit quaternions (w, x, y, z), w >= 0.
    Note:
        Each matrix uses the best-conditioned of the four candidate formulas (largest of
        trace, R00, R11, R22), accurate for every angle, 180 degrees included. A matrix
        slightly off a rotation gives the normalised candidate (as scipy's `from_matrix`).
    """
    rot = np.asarray(rot, np.float64)
    _check_last("rot", rot, (3, 3))
    cand, diag = _quat_candidates(rot, np.stack)
    best = diag.argmax(-1)[..., None, None]
    q = np.take_along_axis(cand, np.broadcast_to(best, best.shape[:-1] + (4,)), -2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def rotmat_to_quat_torch(rot: Tensor) -> Tensor:
    """Torch twin of `rotmat_to_quat`: (..., 3, 3) -> (..., 4) unit (w, x, y, z), w >= 0."""
    import torch

    if not isinstance(rot, torch.Tensor) or rot.ndim < 2 or rot.shape[-2:] != (3, 3):
        raise ValueError(f"rot: expected shape (..., 3, 3), found {tuple(getattr(rot, 'shape', ()))}")
    cand, diag = _quat_candidates(rot, torch.stack)        # (..., 4 candidates, 4), (..., 4)
    best = diag.argmax(dim=-1, keepdim=True)               # (..., 1)
    q = torch.take_along_dim(cand, best[..., None].expand(*best.shape, 4), dim=-2)[..., 0, :]
    q = q / q.norm(dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_mean(quats: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Weighted mean rotation: the unit quaternion maximising `sum_n w_n (q . q_n)^2`, the
    eigenvector of the largest eigenvalue of `sum_n w_n q_n q_n^T` (Markley et al. 2007, "Averaging
    quaternions"; scipy's `Rotation.mean`), blind to the signs of the `q_n`.

    Args:
        quats: (..., N, 4) unit quaternions (w, x, y, z), any signs.
        weights: (..., N) >= 0, not all 0.
    Returns:
        (..., 4) unit quaternion, w >= 0.

    Example:
        >>> q = np.array([[1.0, 0, 0, 0], [-1.0, 0, 0, 0]])
        >>> quat_mean(q, np.array([0.5, 0.5])).round(6).tolist()
        [1.0, 0.0, 0.0, 0.0]
    """
    m = np.einsum("...n,...ni,...nj->...ij", weights, quats, quats)
    _, vecs = np.linalg.eigh(m)
    q = vecs[..., :, -1]
    return np.where(q[..., :1] < 0, -q, q)


def quat_sequence_continuous(quats: np.ndarray) -> np.ndarray:
    """Flip signs along a sequence so that consecutive quaternions lie in one hemisphere.

    `q` and `-q` are the same rotation, but an animation curve that interpolates its keys
    component-wise (or a slerp that does not pick the shorter arc) turns the long way round
    between `q` and a neighbour near `-q`. Each quaternion keeps or flips its sign so that
    `q_i . q_(i-1) >= 0`, the first one as given.

    Args:
        quats: (F, 4) quaternions (any order of components, any signs).
    Returns:
        (F, 4) the same rotations, float64, sign-continuous along F.
    """
    q = np.asarray(quats, np.float64)
    if q.ndim != 2 or q.shape[1] != 4:
        raise ValueError(f"quats: expected shape (F, 4), found {q.shape}")
    flips = np.where((q[1:] * q[:-1]).sum(1) < 0, -1.0, 1.0)
    return q * np.concatenate([[1.0], np.cumprod(flips)])[:, None]


# -- Euler angles -----------------------------------------------------------------------------

def _euler_order(order: str) -> tuple[list[int], bool]:
    """(axis indices in extrinsic order, intrinsic?) of an order such as "xyz" or "YXZ"."""
    if (not isinstance(order, str) or len(order) != 3 or not (order.islower() or order.isupper())
            or sorted(order.lower()) != ["x", "y", "z"]):
        raise ValueError(f"order: expected three distinct axes, all lower case (extrinsic) or all "
                         f"upper case (intrinsic), e.g. 'xyz' or 'YXZ', found {order!r}")
    axes = [_AXES[c] for c in order.lower()]
    intrinsic = order.isupper()
    return (axes[::-1] if intrinsic else axes), intrinsic


def _permutation(axes: list[int]) -> tuple[np.ndarray, float]:
    """Indices `p` and sign `e` such that, for R' = R[p][:, p], R = R_k(c) R_j(b) R_i(a) about
    axes (i, j, k) reads as R' = Rz(e c) Ry(e b) Rx(e a) (an odd permutation flips angles)."""
    p = np.array(axes)
    sign = 1.0 if (axes[1] - axes[0]) % 3 == 1 else -1.0
    return p, sign


def euler_to_rotmat(angles: np.ndarray, order: str = "xyz") -> np.ndarray:
    """Return the rotation matrices of Euler angles (see the module's conventions).

    Args:
        angles: (..., 3) radians, in the order the axes are named.
        order: three distinct axes, lower case extrinsic ("xyz": `Rz(c) Ry(b) Rx(a)`),
            upper case intrinsic ("YXZ": `Ry(a) Rx(b) Rz(c)`).
    Returns:
        (..., 3, 3) float64 rotations acting on column vectors.
    Raises:
        ValueError: a bad order or shape.

    Example:
        >>> np.round(euler_to_rotmat(np.array([0.0, 0.0, np.pi / 2])) @ [1, 0, 0], 6).tolist()
        [0.0, 1.0, 0.0]
    """
    axes, intrinsic = _euler_order(order)
    angles = np.asarray(angles, dtype=np.float64)
    _check_last("angles", angles, (3,))
    if intrinsic:
        angles = angles[..., ::-1]
    p, sign = _permutation(axes)
    if sign < 0:
        angles = -angles
    ca, cb, cc = np.cos(angles[..., 0]), np.cos(angles[..., 1]), np.cos(angles[..., 2])
    sa, sb, sc = np.sin(angles[..., 0]), np.sin(angles[..., 1]), np.sin(angles[..., 2])
    rot = np.empty(angles.shape[:-1] + (3, 3))  # Rz(c) Ry(b) Rx(a) on the permuted axes
    rot[..., 0, 0] = cc * cb
    rot[..., 0, 1] = cc * sb * sa - sc * ca
    rot[..., 0, 2] = cc * sb * ca + sc * sa
    rot[..., 1, 0] = sc * cb
    rot[..., 1, 1] = sc * sb * sa + cc * ca
    rot[..., 1, 2] = sc * sb * ca - cc * sa
    rot[..., 2, 0] = -sb
    rot[..., 2, 1] = cb * sa
    rot[..., 2, 2] = cb * ca
    if list(p) == [0, 1, 2]:
        return rot
    inverse = np.argsort(p)
    return rot[..., inverse, :][..., :, inverse]


def rotmat_to_euler(rot: np.ndarray, order: str = "xyz") -> np.ndarray:
    """Return the Euler angles of rotation matrices (inverse of `euler_to_rotmat`).

    Args:
        rot: (..., 3, 3) rotations.
        order: as in `euler_to_rotmat`.
    Returns:
        (..., 3) float64 radians: first and last in [-pi, pi], middle in [-pi/2, pi/2].
    Note:
        At gimbal lock (`cos(middle) < 1e-9`) only the sum or difference of the outer angles
        is defined: the third angle of the order is set to 0 (as scipy does).
    """
    axes, intrinsic = _euler_order(order)
    rot = np.asarray(rot, np.float64)
    _check_last("rot", rot, (3, 3))
    p, sign = _permutation(axes)
    r = rot[..., p, :][..., :, p]  # = Rz(e c) Ry(e b) Rx(e a)
    cos_b = np.hypot(r[..., 0, 0], r[..., 1, 0])
    b = np.arctan2(-r[..., 2, 0], cos_b)
    locked = cos_b < 1e-9  # only a + c (or a - c) is defined: the third named angle is 0
    if intrinsic:  # the third named angle is a: R' = Rz(c) Ry(b)
        a = np.where(locked, 0.0, np.arctan2(r[..., 2, 1], r[..., 2, 2]))
        c = np.where(locked, np.arctan2(-r[..., 0, 1], r[..., 1, 1]), np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    else:  # the third named angle is c: R' = Ry(b) Rx(a)
        a = np.where(locked, np.arctan2(-r[..., 1, 2], r[..., 1, 1]), np.arctan2(r[..., 2, 1], r[..., 2, 2]))
        c = np.where(locked, 0.0, np.arctan2(r[..., 1, 0], r[..., 0, 0]))
    angles = sign * np.stack([a, b, c], -1)
    return angles[..., ::-1] if intrinsic else angles
