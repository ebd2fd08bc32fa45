"""Three-frame weighted averaging of pose and expression parameters (the paper's appendix A).

`average_params` replaces every frame's parameters by the weighted mean over frames
i - 1, i, i + 1 (weights (1 - c) / 2, c, (1 - c) / 2, renormalized over the frames that
exist and are not failed): translations and weights linearly, rotations by the weighted
quaternion mean of Markley et al. 2007 ("Averaging quaternions", the eigenvector of the
largest eigenvalue of `sum_j w_j q_j q_j^T`, sign-invariant).

numpy only.
"""

from __future__ import annotations

import numpy as np

from ..geometry.rotation import axis_angle_to_quat, quat_mean, quat_to_axis_angle

__all__ = ["average_params"]


def average_params(values: np.ndarray, rotation: np.ndarray, others: np.ndarray, *, centre_weight: float = 0.5,
                   failed: np.ndarray | None = None) -> np.ndarray:
    """Three-frame weighted average of a parameter sequence.

    Args:
        values: (F, D) parameters.
        rotation: (3,) columns of the axis-angle rotation, rad.
        others: column indices averaged linearly (translation cm, weights).
        centre_weight: c, the weight of the frame itself, in (0, 1].
        failed: (F,) bool, frames neither averaged nor used as neighbours (kept as they are).
    Returns:
        (F, D) float64 averaged parameters (other columns copied).
    """
    v = np.nan_to_num(np.asarray(values, np.float64))
    f = len(v)
    ok = np.ones(f, bool) if failed is None else ~np.asarray(failed, bool)
    side = 0.5 * (1.0 - centre_weight)
    w = np.zeros((f, 3))
    w[:, 1] = centre_weight
    w[1:, 0] = side * ok[:-1]
    w[:-1, 2] = side * ok[1:]
    w /= w.sum(1, keepdims=True)
    idx = np.clip(np.arange(f)[:, None] + np.array([-1, 0, 1]), 0, f - 1)  # (F, 3)
    out = v.copy()
    others = np.asarray(others, np.int64)
    out[:, others] = np.einsum("fn,fnd->fd", w, v[idx][:, :, others])
    rotation = np.asarray(rotation, np.int64)
    if len(rotation):
        quats = axis_angle_to_quat(v[:, rotation])[idx]  # (F, 3, 4)
        out[:, rotation] = quat_to_axis_angle(quat_mean(quats, w))
    out[~ok] = np.asarray(values, np.float64)[~ok]  # as given, NaN included
    return out
