"""Robust point-to-plane ICP of many point sets (one per frame) onto one reference surface.

Iteratively reweighted Gauss-Newton ICP (Chen & Medioni 1992 point-to-plane; Besl & McKay
1992 point-to-point) with a robust loss (Geman-McClure or Huber, IRLS weights; Zhang 1994).
No correspondences are assumed: every iteration pairs each transformed source point with its
nearest target vertex (a k-d tree built once on the target). All frames are solved together:
the nearest-neighbour query covers every active frame's points at once and the linearized
6x6 normal equations are solved batched over frames. Each frame's iterates depend only on its
own points, so the result of a frame does not depend on which other frames are in the batch.

Conventions: cm; matrices act on column vectors; the returned `T_target_src` maps source
points onto the target surface.
"""

from __future__ import annotations

from typing import Callable, Literal, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from ..geometry.rigid import apply_rigid, rigid_matrix
from ..geometry.rotation import axis_angle_to_rotmat, skew

__all__ = ["IcpResult", "robust_weights", "robust_icp"]

Loss = Literal["geman_mcclure", "huber", "l2"]


class IcpResult(NamedTuple):
    """Result of `robust_icp`.

    Attributes:
        matrices: (F, 4, 4) float64 `T_target_src` per frame (source -> target frame), cm.
        iterations: (F,) int, Gauss-Newton steps taken per frame.
        converged: (F,) bool, True where the last step moved no point by more than
            `tolerance_cm`.
        rms_cm: (F,) float64, weighted RMS of the residuals (point-to-plane distances, or
            point distances) at the last linearization, cm.
    """

    matrices: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    rms_cm: np.ndarray


def robust_weights(residuals: np.ndarray, scale: np.ndarray | float, loss: Loss) -> np.ndarray:
    """Return IRLS weights `rho'(r) / r` of a robust loss (1 at r = 0).

    Geman-McClure `rho(r) = (r^2 / 2) / (1 + r^2 / s^2)` gives `w = 1 / (1 + r^2 / s^2)^2`;
    Huber (quadratic below `s`, linear above) gives `w = min(1, s / |r|)`; "l2" gives 1.

    Args:
        residuals: (...) residual magnitudes, cm.
        scale: scale `s` (cm), broadcast against `residuals`, > 0.
        loss: "geman_mcclure", "huber" or "l2".
    Returns:
        (...) float64 weights in (0, 1].
    """
    r = np.abs(np.asarray(residuals, np.float64))
    s = np.asarray(scale, np.float64)
    if loss == "geman_mcclure":
        return 1.0 / (1.0 + (r / s) ** 2) ** 2
    if loss == "huber":
        return np.minimum(1.0, s / np.maximum(r, 1e-300))
    if loss == "l2":
        return np.ones_like(r)
    raise ValueError(f"loss: expected 'geman_mcclure', 'huber' or 'l2', found {loss!r}")


def robust_icp(points: np.ndarray, target: np.ndarray, target_normals: np.ndarray | None = None,
               init: np.ndarray | None = None, *, iterations: int = 30,
               robust_scale_cm: float = 0.1, loss: Loss = "geman_mcclure",
               tolerance_cm: float = 1e-4, anneal: float = 3.0, tree: cKDTree | None = None,
               workers: int = 1,
               progress: Callable[[float, str], None] | None = None) -> IcpResult:
    """Rigidly align each frame's points to a target surface with robust ICP.

    For each frame f, minimise over the rigid `T_f`
        point-to-plane: `sum_i rho(n_j(i) . (T_f x_fi - y_j(i)))`, or
        point-to-point: `sum_i rho(|T_f x_fi - y_j(i)|)` when `target_normals` is None,
    where `j(i)` is the target vertex nearest to `T_f x_fi` (re-found every iteration) and
    `n_j` its unit normal. Each iteration linearizes the rotation about the centroid `c` of
    the transformed points (`x' -> c + (I + [w]x)(x' - c) + dt`), solves the weighted 6x6
    normal equations (IRLS weights of `rho`, see `robust_weights`) batched over frames, and
    applies the step as an exact rotation. The robust scale is annealed: per frame and
    iteration `s = max(robust_scale_cm, anneal * 1.4826 * median|r|)`, so that a large
    initial misalignment is first treated nearly as least squares (set `anneal=0` for a
    fixed scale). A frame stops when its step moves no point by more than `tolerance_cm`
    (bound `|w| * max|x' - c| + |dt|`) or after `iterations` steps.

    Args:
        points: (F, N, 3) float, cm, source points of each frame.
        target: (M, 3) float, cm, target surface vertices.
        target_normals: (M, 3) unit normals of the target vertices for point-to-plane, or
            None for point-to-point. Zero normals make their points inert.
        init: (F, 4, 4) initial `T_target_src`, or None for the translations that move each
            frame's centroid onto the target's centroid.
        iterations: maximum Gauss-Newton steps per frame (>= 0).
        robust_scale_cm: robust loss scale `s`, cm (> 0).
        loss: "geman_mcclure", "huber" or "l2".
        tolerance_cm: convergence threshold on the largest point motion of a step, cm.
        anneal: factor of the annealed scale (>= 0; 0 = fixed scale).
        tree: a `cKDTree` built on `target` (built here when None).
        workers: threads for the nearest-neighbour queries (-1 = all cores); does not
            change results.
        progress: optional callback (fraction, message), called once per iteration.
    Returns:
        IcpResult with `T_target_src` per frame.
    Raises:
        ValueError: on bad shapes or parameter values.
    Note:
        A Levenberg damping of `1e-9 * trace(A) / 6` keeps the 6x6 systems solvable when the
        matched surface leaves a direction unconstrained (e.g. a plane slides in itself); such
        directions then barely move.
    """
    points = np.asarray(points, np.float64)
    target = np.asarray(target, np.float64)
    if points.ndim != 3 or points.shape[2] != 3 or points.shape[1] == 0:
        raise ValueError(f"points: expected shape (F, N, 3) with N > 0, found {points.shape}")
    if target.ndim != 2 or target.shape[1] != 3 or target.shape[0] == 0:
        raise ValueError(f"target: expected shape (M, 3) with M > 0, found {target.shape}")
    if target_normals is not None:
        target_normals = np.asarray(target_normals, np.float64)
        if target_normals.shape != target.shape:
            raise ValueError(f"target_normals: expected shape {target.shape} (from target), "
                             f"found {target_normals.shape}")
    if iterations < 0 or not robust_scale_cm > 0 or tolerance_cm < 0 or anneal < 0:
        raise ValueError(f"expected iterations >= 0, robust_scale_cm > 0, tolerance_cm >= 0, "
                         f"anneal >= 0, found {iterations}, {robust_scale_cm}, {tolerance_cm}, "
                         f"{anneal}")
    robust_weights(np.zeros(1), 1.0, loss)  # validates `loss`
    num_frames, n = points.shape[:2]
    if init is None:
        shift = target.mean(0) - points.mean(1)
        matrices = rigid_matrix(np.broadcast_to(np.eye(3), (num_frames, 3, 3)), shift)
    else:
        init = np.asarray(init, np.float64)
        if init.shape != (num_frames, 4, 4):
            raise ValueError(f"init: expected shape ({num_frames}, 4, 4), found {init.shape}")
        matrices = init.copy()
    if tree is None:
        tree = cKDTree(target)
    used = np.zeros(num_frames, np.int64)
    converged = np.zeros(num_frames, bool)
    rms = np.full(num_frames, np.nan)
    active = np.arange(num_frames)
    for it in range(iterations):
        if active.size == 0:
            break
        moved = apply_rigid(matrices[active], points[active])           # (A, N, 3)
        _, nearest = tree.query(moved.reshape(-1, 3), workers=workers)
        nearest = nearest.reshape(active.size, n)
        matched = target[nearest]                                        # (A, N, 3)
        centre = moved.mean(1, keepdims=True)
        local = moved - centre
        if target_normals is not None:
            normal = target_normals[nearest]
            resid = np.einsum("anc,anc->an", normal, moved - matched)    # (A, N)
            jac = np.concatenate([np.cross(local, normal), normal], -1)  # (A, N, 6)
            size = np.abs(resid)
        else:
            resid3 = moved - matched                                     # (A, N, 3)
            jac = np.concatenate([-skew(local), np.broadcast_to(np.eye(3), local.shape + (3,))],
                                 -1)                                     # (A, N, 3, 6)
            size = np.linalg.norm(resid3, axis=-1)
        scale = np.maximum(robust_scale_cm, anneal * 1.4826 * np.median(size, axis=1))
        weight = robust_weights(size, scale[:, None], loss)              # (A, N)
        if target_normals is not None:
            normal_mat = np.einsum("an,ani,anj->aij", weight, jac, jac)
            rhs = -np.einsum("an,ani,an->ai", weight, jac, resid)
        else:
            normal_mat = np.einsum("an,anki,ankj->aij", weight, jac, jac)
            rhs = -np.einsum("an,anki,ank->ai", weight, jac, resid3)
        rms[active] = np.sqrt((weight * size ** 2).sum(1) / np.maximum(weight.sum(1), 1e-300))
        damping = 1e-9 * np.trace(normal_mat, axis1=1, axis2=2) / 6.0 + 1e-300
        normal_mat = normal_mat + damping[:, None, None] * np.eye(6)
        step = np.linalg.solve(normal_mat, rhs[..., None])[..., 0]      # (A, 6)
        rot = axis_angle_to_rotmat(step[:, :3])
        c = centre[:, 0]
        update = rigid_matrix(rot, c + step[:, 3:] - np.einsum("aij,aj->ai", rot, c))
        matrices[active] = update @ matrices[active]
        used[active] += 1
        reach = np.linalg.norm(local, axis=-1).max(1)
        motion = np.linalg.norm(step[:, :3], axis=1) * reach + np.linalg.norm(step[:, 3:], axis=1)
        done = motion <= tolerance_cm
        converged[active[done]] = True
        active = active[~done]
        if progress is not None:
            progress((it + 1) / iterations, f"ICP iteration {it + 1}/{iterations}, "
                                            f"{active.size} frame(s) still moving")
    return IcpResult(matrices, used, converged, rms)
