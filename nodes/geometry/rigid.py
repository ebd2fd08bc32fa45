"""Rigid transforms: weighted Kabsch / Umeyama alignment and 4x4 matrix helpers, batched.

Numpy (float64): `fit_rigid` (weighted rigid or similarity alignment of point sets),
`rigid_matrix` (build from rotation + translation), `invert_rigid`, `apply_rigid`,
`stabilize_vertices` (world vertices into the skull frame, in blocks of frames) and
`rotation_angle`. Torch: `invert_rigid_torch` (same formula, any dtype and device,
differentiable). Torch is not imported here: the torch functions only call tensor methods.

Conventions: matrices act on column vectors, `y = R @ x + t`; `T_ref_src` maps points of
frame "src" into frame "ref". The numpy functions compute in float64 (closed-form solves on
small 3x3 systems; the node outputs are float64 4x4 matrices anyway).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, NamedTuple

import numpy as np

if TYPE_CHECKING:
    from torch import Tensor

__all__ = [
    "RigidFit", "fit_rigid", "rigid_matrix", "invert_rigid", "apply_rigid", "stabilize_vertices",
    "rotation_angle", "invert_rigid_torch", "rigid_fit_problem",
]


class RigidFit(NamedTuple):
    """Result of `fit_rigid`; apply as `y = scale * rotation @ x + translation`.

    Attributes:
        rotation: (..., 3, 3) float64, det = +1.
        translation: (..., 3) float64, cm.
        scale: (...,) float64; exactly 1 unless `with_scale`.
    """

    rotation: np.ndarray
    translation: np.ndarray
    scale: np.ndarray

    def matrix(self) -> np.ndarray:
        """Return the (..., 4, 4) float64 homogeneous matrix `[[s R, t], [0, 1]]`."""
        return rigid_matrix(self.scale[..., None, None] * self.rotation, self.translation)


def _check_points(name: str, value: np.ndarray) -> np.ndarray:
    value = np.asarray(value, dtype=np.float64)
    if value.ndim < 2 or value.shape[-1] != 3:
        raise ValueError(f"{name}: expected shape (..., N, 3), found {value.shape}")
    return value


def fit_rigid(points_src: np.ndarray, points_ref: np.ndarray, weights: np.ndarray | None = None,
              *, with_scale: bool = False) -> RigidFit:
    """Minimise `sum_i w_i |s R x_i + t - y_i|^2` over R in SO(3), t and (optionally) s > 0.

    Weighted Kabsch (Kabsch 1976) / Umeyama (1991): centre both sets on their weighted
    centroids, take the SVD of the weighted cross-covariance `H = U S V^T`, then
    `R = U diag(1, 1, d) V^T` with `d = sign(det(U V^T))` (no reflections),
    `s = trace(diag(S) diag(1, 1, d)) / var_src`, `t = mean_ref - s R mean_src`.
    The rotation does not depend on whether the scale is estimated.

    Args:
        points_src: (..., N, 3) float, cm, frame "src" (the points `x_i` that are moved).
        points_ref: (..., N, 3) float, cm, frame "ref" (the targets `y_i`); batch dims
            broadcast against `points_src`.
        weights: (..., N) >= 0 (broadcast), or None for uniform weights.
        with_scale: estimate an isotropic scale `s`; otherwise `s = 1`.
    Returns:
        RigidFit with `T_ref_src`: `y ~ s R x + t`, float64.
    Raises:
        ValueError: on bad shapes, negative weights, or weights summing to 0.
    Note:
        With fewer than three non-collinear points (of non-zero weight) the rotation about
        their line is not determined; the SVD then returns one of the minimisers.

    Example:
        >>> x = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> fit = fit_rigid(x, x + [1.0, 2.0, 3.0])
        >>> np.round(fit.translation, 6).tolist(), np.allclose(fit.rotation, np.eye(3))
        ([1.0, 2.0, 3.0], True)
    """
    src = _check_points("points_src", points_src)
    ref = _check_points("points_ref", points_ref)
    if src.shape[-2] != ref.shape[-2]:
        raise ValueError(f"points_ref: expected (..., N, 3) with N = {src.shape[-2]} (from "
                         f"points_src), found {ref.shape}")
    batch = np.broadcast_shapes(src.shape[:-2], ref.shape[:-2])
    n = src.shape[-2]
    if weights is None:
        w = np.ones(batch + (n,), np.float64)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if w.ndim < 1 or w.shape[-1] != n:
            raise ValueError(f"weights: expected shape (..., {n}), found {w.shape}")
        if (w < 0).any():
            raise ValueError(f"weights: expected values >= 0, found minimum {w.min():.3g}")
        batch = np.broadcast_shapes(batch, w.shape[:-1])
        w = np.broadcast_to(w, batch + (n,))
    total = w.sum(-1)
    if n == 0 or not (total > 0).all():
        raise ValueError(f"weights: expected a positive total weight per batch element, found "
                         f"{'no points' if n == 0 else f'a total of {total.min():.3g}'}")
    wn = w / total[..., None]
    # Moments by batched matrix products (BLAS), without forming centred (..., N, 3) copies:
    # cov = sum_i w_i y_i x_i^T - mean_ref mean_src^T (float64; the cancellation costs ~1e-14
    # relative for heads within metres of the origin). 5-10x faster than einsum on whole heads.
    mean_src = (wn[..., None, :] @ src)[..., 0, :]
    mean_ref = (wn[..., None, :] @ ref)[..., 0, :]
    if weights is None:  # x^T y with the small transposed operand: no (..., N, 3) temporary
        moment = np.swapaxes(np.swapaxes(src, -1, -2) @ ref, -1, -2) / n
    else:
        moment = np.swapaxes(ref * wn[..., None], -1, -2) @ src
    cov = moment - mean_ref[..., :, None] * mean_src[..., None, :]
    u, sing, vt = np.linalg.svd(cov)
    d = np.sign(np.linalg.det(u @ vt))
    d = np.where(d == 0, 1.0, d)
    flip = np.ones(batch + (3,), np.float64)
    flip[..., 2] = d
    rotation = (u * flip[..., None, :]) @ vt
    if with_scale:
        var_src = (wn[..., None, :] @ (src * src).sum(-1)[..., None])[..., 0, 0] - (mean_src * mean_src).sum(-1)
        if not (var_src > 0).all():
            raise ValueError("points_src: expected points with non-zero spread to estimate a "
                             "scale, found all (weighted) points at one place")
        scale = (sing * flip).sum(-1) / var_src
    else:
        scale = np.ones(batch, np.float64)
    translation = mean_ref - scale[..., None] * np.einsum("...ij,...j->...i", rotation, mean_src)
    return RigidFit(rotation, translation, scale)



def rigid_fit_problem(points: np.ndarray, *, least: int = 3, thickness: float = 1e-3) -> str:
    """Why (N, 3) points (cm) cannot carry a rigid fit: too few, or on a line ('' when fine).

    The points must be at least `least` distinct ones, and their spread across their main axis
    (second singular value of the centred points) at least `thickness` times the spread along it,
    since a rotation about the line through collinear points is not observed.
    """
    unique = np.unique(np.asarray(points, np.float64).reshape(-1, 3), axis=0)
    if len(unique) < least:
        return f"expected at least {least} distinct vertices for a rigid fit, found {len(unique)}"
    sv = np.linalg.svd(unique - unique.mean(0), compute_uv=False)
    if sv[1] <= thickness * sv[0]:
        return (f"expected vertices spread in more than one direction, found them on a line (singular values "
                f"{sv.round(6).tolist()}): the rotation about it is not observed")
    return ""

def rigid_matrix(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Return the (..., 4, 4) float64 matrix `[[R, t], [0, 0, 0, 1]]`.

    Args:
        rotation: (..., 3, 3) rotation (or scaled rotation).
        translation: (..., 3) cm; batch dims broadcast with `rotation`.
    """
    rotation = np.asarray(rotation, np.float64)
    translation = np.asarray(translation, np.float64)
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros(batch + (4, 4), np.float64)
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def invert_rigid(matrices: np.ndarray) -> np.ndarray:
    """Return the inverse of rigid (..., 4, 4) matrices, `[[R^T, -R^T t], [0, 1]]`, float64."""
    matrices = np.asarray(matrices, np.float64)
    rot_t = np.swapaxes(matrices[..., :3, :3], -1, -2)
    return rigid_matrix(rot_t, -np.einsum("...ij,...j->...i", rot_t, matrices[..., :3, 3]))


def apply_rigid(matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return `R @ x + t` for every point, in float64.

    Args:
        matrices: (..., 4, 4) transforms.
        points: (..., N, 3) points, cm; batch dims broadcast with `matrices`.
    Returns:
        (..., N, 3) float64, cm.
    """
    matrices = np.asarray(matrices, np.float64)
    points = np.asarray(points, np.float64)
    # A contiguous R^T lets matmul use BLAS per frame (4x faster than the strided view).
    out = points @ np.ascontiguousarray(np.swapaxes(matrices[..., :3, :3], -1, -2))
    out += matrices[..., None, :3, 3]
    return out


def stabilize_vertices(vertices: np.ndarray, matrices: np.ndarray, *, block_frames: int = 256) -> np.ndarray:
    """Return `S_f = M_f^-1 X_f`: world vertices moved into the skull frame.

    Args:
        vertices: (F, V, 3) world vertices, cm.
        matrices: (F, 4, 4) float64 skull-to-world transforms.
        block_frames: frames per block (bounds the float64 temporaries).
    Returns:
        (F, V, 3) float32 skull-frame vertices, cm.
    Raises:
        ValueError: `vertices` is not (F, V, 3) or `matrices` not (F, 4, 4).
    """
    vertices = np.asarray(vertices)
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise ValueError(f"vertices: expected shape (F, V, 3), found {vertices.shape}")
    if matrices.shape != (vertices.shape[0], 4, 4):
        raise ValueError(f"matrices: expected shape ({vertices.shape[0]}, 4, 4), found {matrices.shape}")
    out = np.empty(vertices.shape, dtype=np.float32)
    inverse = invert_rigid(matrices)
    if vertices.dtype == np.float32:
        # float32 in, float32 out: multiply in float32 straight into the output (no float64
        # temporaries; the extra rounding is a few ulp, ~1e-6 cm at head scale).
        rot_t = np.ascontiguousarray(np.swapaxes(inverse[:, :3, :3], -1, -2), dtype=np.float32)
        np.matmul(vertices, rot_t, out=out)
        out += inverse[:, None, :3, 3].astype(np.float32)
        return out
    for a in range(0, vertices.shape[0], block_frames):
        b = min(vertices.shape[0], a + block_frames)
        out[a:b] = apply_rigid(inverse[a:b], vertices[a:b])
    return out


def rotation_angle(rotation: np.ndarray) -> np.ndarray:
    """Return the angle (radians, in [0, pi]) of (..., 3, 3) rotation matrices.

    Uses `atan2(|axis term|, trace term)`, accurate for small and for near-pi angles alike.
    """
    rotation = np.asarray(rotation, np.float64)
    cos = (np.trace(rotation, axis1=-2, axis2=-1) - 1.0) / 2.0
    skew = np.stack([rotation[..., 2, 1] - rotation[..., 1, 2],
                     rotation[..., 0, 2] - rotation[..., 2, 0],
                     rotation[..., 1, 0] - rotation[..., 0, 1]], -1)
    sin = np.linalg.norm(skew, axis=-1) / 2.0
    return np.arctan2(sin, cos)


def invert_rigid_torch(matrices: Tensor) -> Tensor:
    """Return the inverses of rigid 4x4 matrices `[[R, t], [0, 1]] -> [[R^T, -R^T t], [0, 1]]`.

    The tensor twin of `invert_rigid` (same formula; no float64 conversion).

    Args:
        matrices: (..., 4, 4) rigid transforms, any float dtype and device.
    Returns:
        (..., 4, 4) inverses, same dtype and device; differentiable.
    """
    rot_t = matrices[..., :3, :3].transpose(-1, -2)
    out = matrices.new_zeros(matrices.shape)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ matrices[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out
