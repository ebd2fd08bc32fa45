"""Quaternions and dual quaternions on batched torch tensors.

Conventions:
    - A quaternion is `(..., 4)` `(w, x, y, z)`; a rotation quaternion has unit norm, its
      sign is not canonicalised (`q` and `-q` are the same rotation).
    - A dual quaternion is `(..., 8)`: real part `[..., :4]`, dual part `[..., 4:]`, both
      `(w, x, y, z)`. The rigid motion `x -> R x + t` is `q_r = quat(R)`,
      `q_d = 0.5 (0, t) q_r`; it is a unit dual quaternion (`|q_r| = 1`, `q_r . q_d = 0`).
    - Matrices act on column vectors; a 4x4 rigid matrix is `[[R, t], [0, 1]]`.
    - Translations are in the caller's length unit (cm in this project).

`quat_to_rotmat` and `rotmat_to_quat` are `nodes.geometry.rotation`'s torch conversions,
re-exported here under the names this module's users know.

Every function is differentiable and works for any leading batch shape (including `()`).
Dual-quaternion linear blending (DLB) follows Kavan et al., "Geometric skinning with
approximate dual quaternion blending", ACM TOG 2008.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .rotation import quat_to_rotmat_torch as quat_to_rotmat  # the conversions live in rotation
from .rotation import rotmat_to_quat_torch as rotmat_to_quat

__all__ = [
    "quat_multiply", "quat_conjugate", "quat_to_rotmat", "rotmat_to_quat",
    "dualquat_identity", "dualquat_from_rotation_translation", "dualquat_to_rotation_translation",
    "dualquat_to_rotmat_translation", "dualquat_from_matrix", "dualquat_to_matrix",
    "dualquat_multiply", "dualquat_conjugate", "dualquat_normalize", "dualquat_blend",
    "dualquat_transform_points", "dualquat_align_hemisphere",
]


def _check_last(x: Tensor, size: int, name: str) -> None:
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, found {type(x).__name__}")
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(f"{name}: expected shape (..., {size}), found {tuple(x.shape)}")


def quat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Return the Hamilton product `a b`.

    Args:
        a: (..., 4) quaternion (w, x, y, z).
        b: (..., 4) quaternion, broadcastable with `a`.
    Returns:
        (..., 4) quaternion `a b` (rotation `b` first, then `a`).

    Example:
        >>> quat_multiply(torch.tensor([0., 1, 0, 0]), torch.tensor([0., 0, 1, 0]))
        tensor([0., 0., 0., 1.])
    """
    _check_last(a, 4, "a")
    _check_last(b, 4, "b")
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ], dim=-1)


def quat_conjugate(q: Tensor) -> Tensor:
    """Return `(w, -x, -y, -z)`, the inverse of a unit quaternion.

    Args:
        q: (..., 4) quaternion.
    Returns:
        (..., 4) conjugate.
    """
    _check_last(q, 4, "q")
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def dualquat_identity(*shape: int, dtype: torch.dtype = torch.float32,
                      device: torch.device | str | None = None) -> Tensor:
    """Return identity dual quaternions `(1, 0, 0, 0, 0, 0, 0, 0)` of shape `(*shape, 8)`."""
    out = torch.zeros(*shape, 8, dtype=dtype, device=device)
    out[..., 0] = 1.0
    return out


def dualquat_from_rotation_translation(quat: Tensor, trans: Tensor) -> Tensor:
    """Return the dual quaternion of `x -> R(quat) x + trans`.

    Args:
        quat: (..., 4) unit quaternion (w, x, y, z).
        trans: (..., 3) translation.
    Returns:
        (..., 8) unit dual quaternion `(q, 0.5 (0, t) q)`.
    """
    _check_last(quat, 4, "quat")
    _check_last(trans, 3, "trans")
    quat, trans = torch.broadcast_tensors(quat, torch.cat([torch.zeros_like(trans[..., :1]), trans], -1))
    return torch.cat([quat, 0.5 * quat_multiply(trans, quat)], dim=-1)


def dualquat_to_rotation_translation(dq: Tensor) -> tuple[Tensor, Tensor]:
    """Return `(quat, trans)` of a (not necessarily unit) dual quaternion.

    The real part is normalised; the translation is `2 vec(q_d conj(q_r)) / |q_r|^2`, which
    ignores the component of `q_d` along `q_r` (Kavan's DLB extraction).

    Args:
        dq: (..., 8) dual quaternion with non-zero real part.
    Returns:
        quat: (..., 4) unit quaternion; trans: (..., 3) translation.
    """
    _check_last(dq, 8, "dq")
    real, dual = dq[..., :4], dq[..., 4:]
    norm2 = (real * real).sum(-1, keepdim=True)
    trans = 2.0 * quat_multiply(dual, quat_conjugate(real))[..., 1:] / norm2
    return real / norm2.sqrt(), trans


def dualquat_to_rotmat_translation(dq: Tensor) -> tuple[Tensor, Tensor]:
    """Return `(R, t)` of a (not necessarily unit) dual quaternion: `x -> R x + t`.

    Args:
        dq: (..., 8) dual quaternion with non-zero real part.
    Returns:
        rot: (..., 3, 3) rotation matrix; trans: (..., 3).
    """
    quat, trans = dualquat_to_rotation_translation(dq)
    return quat_to_rotmat(quat), trans


def dualquat_from_matrix(matrix: Tensor) -> Tensor:
    """Return the unit dual quaternion of a rigid 4x4 matrix (real part with w >= 0).

    Args:
        matrix: (..., 4, 4) rigid transform `[[R, t], [0, 1]]`.
    Returns:
        (..., 8) unit dual quaternion.
    """
    if not isinstance(matrix, Tensor) or matrix.ndim < 2 or matrix.shape[-2:] != (4, 4):
        raise ValueError(f"matrix: expected shape (..., 4, 4), found "
                         f"{tuple(getattr(matrix, 'shape', ()))}")
    return dualquat_from_rotation_translation(rotmat_to_quat(matrix[..., :3, :3]), matrix[..., :3, 3])


def dualquat_to_matrix(dq: Tensor) -> Tensor:
    """Return the rigid 4x4 matrix of a (not necessarily unit) dual quaternion.

    Args:
        dq: (..., 8) dual quaternion.
    Returns:
        (..., 4, 4) `[[R, t], [0, 1]]`.
    """
    rot, trans = dualquat_to_rotmat_translation(dq)
    top = torch.cat([rot, trans[..., None]], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])
    bottom[..., 0, 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def dualquat_multiply(a: Tensor, b: Tensor) -> Tensor:
    """Return the dual-quaternion product `a b` (apply `b` first, then `a`).

    Args:
        a: (..., 8) dual quaternion.
        b: (..., 8) dual quaternion, broadcastable with `a`.
    Returns:
        (..., 8) `(a_r b_r, a_r b_d + a_d b_r)`.
    """
    _check_last(a, 8, "a")
    _check_last(b, 8, "b")
    ar, ad, br, bd = a[..., :4], a[..., 4:], b[..., :4], b[..., 4:]
    return torch.cat([quat_multiply(ar, br), quat_multiply(ar, bd) + quat_multiply(ad, br)], -1)


def dualquat_conjugate(dq: Tensor) -> Tensor:
    """Return the quaternion conjugate of both parts: the inverse of a unit dual quaternion.

    Args:
        dq: (..., 8) dual quaternion.
    Returns:
        (..., 8) `(conj(q_r), conj(q_d))`.
    """
    _check_last(dq, 8, "dq")
    return dq * dq.new_tensor([1.0, -1.0, -1.0, -1.0, 1.0, -1.0, -1.0, -1.0])


def dualquat_normalize(dq: Tensor) -> Tensor:
    """Return the unit dual quaternion closest in the DLB sense.

    `q_r / |q_r|` and `q_d / |q_r|` with its component along `q_r` removed, so that
    `|q_r| = 1` and `q_r . q_d = 0`. The rigid motion (as `dualquat_to_rotation_translation`
    reads it) is unchanged.

    Args:
        dq: (..., 8) dual quaternion with non-zero real part.
    Returns:
        (..., 8) unit dual quaternion.
    """
    _check_last(dq, 8, "dq")
    real, dual = dq[..., :4], dq[..., 4:]
    norm = real.norm(dim=-1, keepdim=True)
    real, dual = real / norm, dual / norm
    dual = dual - (real * dual).sum(-1, keepdim=True) * real
    return torch.cat([real, dual], dim=-1)


def dualquat_align_hemisphere(dq: Tensor, reference: Tensor | None = None, dim: int = -2) -> Tensor:
    """Flip signs so that real parts lie in one hemisphere (`q ~ -q`, same motion).

    Args:
        dq: (..., N, 8) dual quaternions.
        reference: (..., 8) reference, or None to chain along `dim`: each element is flipped
            to agree with its (already flipped) predecessor, which keeps a sequence continuous.
        dim: the sequence axis for chaining (default -2).
    Returns:
        (..., N, 8) with `dot(real_i, real_ref) >= 0`.
    """
    _check_last(dq, 8, "dq")
    if reference is not None:
        sign = torch.where((dq[..., :4] * reference[..., None, :4]).sum(-1, keepdim=True) < 0, -1.0, 1.0)
        return dq * sign.to(dq.dtype)
    x = dq.movedim(dim, 0)
    flips = torch.where((x[1:, ..., :4] * x[:-1, ..., :4]).sum(-1) < 0, -1.0, 1.0).to(dq.dtype)
    sign = torch.cat([torch.ones_like(flips[:1]), torch.cumprod(flips, dim=0)], dim=0)
    return (x * sign[..., None]).movedim(0, dim)


def dualquat_blend(dq: Tensor, weights: Tensor, *, align: bool = True) -> Tensor:
    """Dual-quaternion linear blending (DLB): `normalize(sum_i w_i q_i)` (Kavan 2008).

    Args:
        dq: (..., N, 8) dual quaternions.
        weights: (..., N) blending weights (broadcastable with `dq[..., 0]`).
        align: first flip each `q_i` into the hemisphere of `q_0` (shortest path).
    Returns:
        (..., 8) unit dual quaternion.
    """
    _check_last(dq, 8, "dq")
    if align:
        dq = dualquat_align_hemisphere(dq, dq[..., 0, :])
    return dualquat_normalize((weights[..., None] * dq).sum(-2))


def dualquat_transform_points(dq: Tensor, points: Tensor) -> Tensor:
    """Apply the rigid motion of `dq` to points: `R p + t`.

    Args:
        dq: (..., 8) dual quaternion (normalised internally).
        points: (..., N, 3) points.
    Returns:
        (..., N, 3) transformed points.
    """
    _check_last(points, 3, "points")
    rot, trans = dualquat_to_rotmat_translation(dq)
    return points @ rot.transpose(-1, -2) + trans[..., None, :]
