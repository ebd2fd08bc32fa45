"""Tests of nodes.rigid.icp: vertex normals, robust weights and robust ICP."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from nodes.geometry.mesh import vertex_normals
from nodes.rigid.icp import robust_icp, robust_weights
from nodes.geometry.rigid import apply_rigid, invert_rigid, rigid_matrix, rotation_angle


def _head(subdivisions=3):
    """A bumpy ellipsoid (cm): distinct axes, a nose and brows, so that no rotation slides it."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = sphere.vertices * [7.5, 10.0, 9.0]
    radial = v / np.linalg.norm(v, axis=1, keepdims=True)
    bumps = sum(h * np.exp(-((v - c) ** 2).sum(1) / (2 * w ** 2))
                for c, w, h in [([0, 1, 9], 1.5, 2.0), ([3, 4, 8], 2.0, 0.8),
                                ([-3, 4, 8], 2.0, 0.8), ([5, -2, 6], 1.5, 0.6)])
    return v + radial * bumps[:, None], np.asarray(sphere.faces)


def _motions(rng, count, max_deg, max_cm):
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    rot = Rotation.from_rotvec(axis * np.deg2rad(rng.uniform(0, max_deg, (count, 1))))
    return rigid_matrix(rot.as_matrix(), rng.uniform(-max_cm, max_cm, (count, 3)))


def _region(vertices):
    return np.flatnonzero((vertices[:, 1] > -1) & (vertices[:, 2] > 2))


def _centroid_init(points, region):
    """Translations moving each frame's centroid onto the region's centroid."""
    shift = region.mean(0) - points.mean(1)
    return rigid_matrix(np.broadcast_to(np.eye(3), (len(points), 3, 3)), shift)


def _errors(estimate, truth, centre):
    """Rotation (deg) and centre displacement (cm) of estimate vs truth, per frame."""
    rel = invert_rigid(truth) @ estimate
    moved = apply_rigid(rel, centre[None])[:, 0]
    return np.rad2deg(rotation_angle(rel[:, :3, :3])), np.linalg.norm(moved - centre, axis=1)


@pytest.mark.parametrize("loss", ["geman_mcclure", "huber"])
def test_robust_weights_are_derivative_over_residual(loss):
    scale = 0.3
    def rho(r):
        if loss == "geman_mcclure":
            return 0.5 * r ** 2 / (1 + r ** 2 / scale ** 2)
        return np.where(np.abs(r) <= scale, 0.5 * r ** 2, scale * (np.abs(r) - 0.5 * scale))
    r = np.array([0.01, 0.1, 0.25, 0.35, 1.0, -2.0, 5.0])
    h = 1e-6
    derivative = (rho(r + h) - rho(r - h)) / (2 * h)
    np.testing.assert_allclose(robust_weights(r, scale, loss), derivative / r, rtol=1e-5)
    np.testing.assert_array_equal(robust_weights(r, scale, "l2"), 1.0)


def test_robust_weights_reject_unknown_loss():
    with pytest.raises(ValueError, match="loss: expected .*found 'cauchy'"):
        robust_weights(np.ones(3), 1.0, "cauchy")


def test_icp_point_to_plane_recovers_known_motion_exactly():
    rng = np.random.default_rng(0)
    v, f = _head()
    idx = _region(v)
    truth = _motions(rng, 8, 15.0, 3.0)                     # T_target_src
    points = apply_rigid(invert_rigid(truth), v[idx])       # src = truth^-1 target
    result = robust_icp(points, v, vertex_normals(v, f), _centroid_init(points, v[idx]),
                        iterations=50, tolerance_cm=1e-9)
    rot_deg, trans_cm = _errors(result.matrices, truth, v[idx].mean(0))
    assert result.converged.all()
    assert rot_deg.max() < 1e-5 and trans_cm.max() < 1e-6
    assert (result.rms_cm < 1e-5).all()


def test_icp_point_to_point_recovers_small_motion():
    rng = np.random.default_rng(1)
    v, _ = _head()
    idx = _region(v)
    truth = _motions(rng, 6, 3.0, 0.5)
    points = apply_rigid(invert_rigid(truth), v[idx])
    result = robust_icp(points, v, None, _centroid_init(points, v[idx]), iterations=100,
                        tolerance_cm=1e-9)
    rot_deg, trans_cm = _errors(result.matrices, truth, v[idx].mean(0))
    assert rot_deg.max() < 1e-4 and trans_cm.max() < 1e-4


def test_icp_geman_mcclure_resists_outliers_where_l2_does_not():
    rng = np.random.default_rng(2)
    v, f = _head()
    idx = _region(v)
    truth = _motions(rng, 6, 10.0, 2.0)
    src = np.repeat(v[idx][None], 6, 0)
    bad = rng.choice(idx.size, idx.size // 6, replace=False)   # 1/6 of the points moved 1-2 cm
    direction = rng.normal(size=(6, bad.size, 3))
    direction /= np.linalg.norm(direction, axis=-1, keepdims=True)
    src[:, bad] += direction * rng.uniform(1, 2, (6, bad.size, 1))
    src += rng.normal(0, 0.01, src.shape)
    points = apply_rigid(invert_rigid(truth), src)
    normals = vertex_normals(v, f)
    centre = v[idx].mean(0)
    init = _centroid_init(points, v[idx])
    robust = robust_icp(points, v, normals, init, loss="geman_mcclure", robust_scale_cm=0.05,
                        iterations=60)
    plain = robust_icp(points, v, normals, init, loss="l2", iterations=60)
    rot_robust, trans_robust = _errors(robust.matrices, truth, centre)
    rot_plain, trans_plain = _errors(plain.matrices, truth, centre)
    assert rot_robust.max() < 0.3 and trans_robust.max() < 0.04  # measured 0.14 deg, 0.013 cm
    assert np.median(rot_plain) > 3 * np.median(rot_robust)


def test_icp_frames_are_independent_of_the_batch():
    rng = np.random.default_rng(3)
    v, f = _head()
    idx = _region(v)
    truth = _motions(rng, 6, 12.0, 2.0)
    points = apply_rigid(invert_rigid(truth), v[idx]) + rng.normal(0, 0.02, (6, idx.size, 3))
    normals = vertex_normals(v, f)
    init = _centroid_init(points, v[idx])
    together = robust_icp(points, v, normals, init, iterations=30)
    for k in range(6):
        alone = robust_icp(points[k:k + 1], v, normals, init[k:k + 1], iterations=30)
        np.testing.assert_allclose(alone.matrices[0], together.matrices[k], rtol=0, atol=1e-12)
        assert alone.iterations[0] == together.iterations[k]


def test_icp_default_init_aligns_centroids():
    v, f = _head(2)
    points = v[None] + [[[1.0, -2.0, 0.5]]]
    result = robust_icp(points, v, vertex_normals(v, f), iterations=0)
    np.testing.assert_allclose(result.matrices[0, :3, 3], [-1.0, 2.0, -0.5], atol=1e-12)
    np.testing.assert_array_equal(result.matrices[0, :3, :3], np.eye(3))


def test_icp_uses_init_and_zero_iterations_return_it():
    rng = np.random.default_rng(4)
    v, f = _head()
    init = _motions(rng, 3, 5.0, 1.0)
    result = robust_icp(v[None].repeat(3, 0), v, vertex_normals(v, f), init, iterations=0)
    np.testing.assert_array_equal(result.matrices, init)
    assert (result.iterations == 0).all() and not result.converged.any()


def test_icp_reports_progress():
    v, f = _head(2)
    calls = []
    robust_icp(v[None] + 0.5, v, vertex_normals(v, f), iterations=3, tolerance_cm=0,
               progress=lambda fraction, message: calls.append(fraction))
    assert calls == pytest.approx([1 / 3, 2 / 3, 1.0])


@pytest.mark.parametrize("kwargs, match", [
    (dict(points=np.zeros((2, 3))), r"points: expected shape \(F, N, 3\)"),
    (dict(target=np.zeros((0, 3))), r"target: expected shape \(M, 3\) with M > 0"),
    (dict(target_normals=np.zeros((4, 3))), r"target_normals: expected shape \(10, 3\)"),
    (dict(init=np.zeros((3, 4, 4))), r"init: expected shape \(2, 4, 4\)"),
    (dict(robust_scale_cm=0.0), r"robust_scale_cm > 0"),
    (dict(loss="cauchy"), r"loss: expected"),
])
def test_icp_rejects_bad_input(kwargs, match):
    args = dict(points=np.zeros((2, 5, 3)), target=np.arange(30.0).reshape(10, 3),
                target_normals=None)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        robust_icp(**args)
