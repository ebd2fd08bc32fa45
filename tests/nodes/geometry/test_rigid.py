"""Tests of nodes.geometry.rigid: weighted Kabsch/Umeyama and the 4x4 rigid helpers (numpy, torch)."""

import doctest

import numpy as np
import pytest
import torch
import trimesh
from scipy.linalg import orthogonal_procrustes
from scipy.spatial.transform import Rotation

from nodes.geometry import rigid
from nodes.geometry.rigid import (apply_rigid, fit_rigid, invert_rigid, invert_rigid_torch, rigid_matrix,
                                  rotation_angle, stabilize_vertices)


def _random_rigid(rng, batch, max_deg=90.0, max_trans=10.0):
    count = int(np.prod(batch, dtype=int))
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.deg2rad(rng.uniform(0, max_deg, (count, 1)))
    rot = Rotation.from_rotvec(axis * angle).as_matrix().reshape(batch + (3, 3))
    trans = rng.uniform(-max_trans, max_trans, batch + (3,))
    return rot, trans


@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_fit_rigid_recovers_known_transform(batch):
    rng = np.random.default_rng(0)
    rot, trans = _random_rigid(rng, batch)
    src = rng.normal(0, 5, batch + (20, 3))
    ref = np.einsum("...ij,...nj->...ni", rot, src) + trans[..., None, :]
    fit = fit_rigid(src, ref)
    assert fit.rotation.shape == batch + (3, 3)
    assert fit.translation.shape == batch + (3,)
    assert fit.scale.shape == batch
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-10)
    np.testing.assert_allclose(fit.translation, trans, atol=1e-9)
    np.testing.assert_array_equal(fit.scale, 1.0)
    np.testing.assert_allclose(np.linalg.det(fit.rotation), 1.0, atol=1e-12)
    np.testing.assert_allclose(fit.matrix(), rigid_matrix(rot, trans), atol=1e-9)


def test_fit_rigid_matches_scipy_orthogonal_procrustes_on_noisy_points():
    rng = np.random.default_rng(1)
    rot, trans = _random_rigid(rng, ())
    src = rng.normal(0, 5, (50, 3))
    ref = src @ rot.T + trans + rng.normal(0, 0.3, (50, 3))
    fit = fit_rigid(src, ref)
    xs, ys = src - src.mean(0), ref - ref.mean(0)
    r_t, _ = orthogonal_procrustes(xs, ys)  # minimises |xs @ r_t - ys|
    np.testing.assert_allclose(fit.rotation, r_t.T, atol=1e-10)
    np.testing.assert_allclose(fit.translation, ref.mean(0) - r_t.T @ src.mean(0),
                               atol=1e-9)


def test_fit_rigid_integer_weights_equal_repeated_points():
    rng = np.random.default_rng(2)
    src = rng.normal(0, 3, (12, 3))
    ref = rng.normal(0, 3, (12, 3))  # unrelated sets: the optimum is non-trivial
    weights = rng.integers(1, 5, 12)
    weighted = fit_rigid(src, ref, weights.astype(float))
    repeated = fit_rigid(np.repeat(src, weights, 0), np.repeat(ref, weights, 0))
    np.testing.assert_allclose(weighted.rotation, repeated.rotation, atol=1e-10)
    np.testing.assert_allclose(weighted.translation, repeated.translation, atol=1e-10)


def test_fit_rigid_zero_weights_ignore_outliers():
    rng = np.random.default_rng(3)
    rot, trans = _random_rigid(rng, ())
    src = rng.normal(0, 5, (30, 3))
    ref = src @ rot.T + trans
    ref[:5] += rng.normal(0, 20, (5, 3))
    weights = np.ones(30)
    weights[:5] = 0
    fit = fit_rigid(src, ref, weights)
    np.testing.assert_allclose(fit.rotation, rot, atol=1e-10)
    np.testing.assert_allclose(fit.translation, trans, atol=1e-9)
    assert not np.allclose(fit_rigid(src, ref).rotation, rot, atol=1e-3)


def test_fit_rigid_with_scale_matches_trimesh_procrustes_without_noise():
    rng = np.random.default_rng(4)
    rot, trans = _random_rigid(rng, ())
    src = rng.normal(0, 5, (40, 3))
    ref = 1.7 * src @ rot.T + trans
    fit = fit_rigid(src, ref, with_scale=True)
    expected = trimesh.registration.procrustes(src, ref, reflection=False, scale=True,
                                               return_cost=False)
    np.testing.assert_allclose(fit.matrix(), expected, atol=1e-8)
    np.testing.assert_allclose(fit.scale, 1.7, atol=1e-12)


def test_fit_rigid_with_scale_is_least_squares_optimal_with_noise():
    # trimesh uses another scale estimator (ratio of RMS radii), so check optimality directly
    rng = np.random.default_rng(4)
    rot, trans = _random_rigid(rng, ())
    src = rng.normal(0, 5, (40, 3))
    ref = 1.7 * src @ rot.T + trans + rng.normal(0, 0.5, (40, 3))
    fit = fit_rigid(src, ref, with_scale=True)
    np.testing.assert_allclose(fit.rotation, fit_rigid(src, ref).rotation, atol=1e-12)

    def cost(scale, shift=np.zeros(3)):
        return ((scale * src @ fit.rotation.T + fit.translation + shift - ref) ** 2).sum()

    best = cost(fit.scale)
    eps = 1e-4
    assert cost(fit.scale + eps) > best and cost(fit.scale - eps) > best
    for shift in np.eye(3) * eps:
        assert cost(fit.scale, shift) > best and cost(fit.scale, -shift) > best
    # gradient in s vanishes (central finite difference)
    assert abs(cost(fit.scale + eps) - cost(fit.scale - eps)) / (2 * eps) < 1e-3


def test_fit_rigid_never_returns_a_reflection():
    rng = np.random.default_rng(5)
    src = rng.normal(0, 5, (20, 3))
    ref = src * [1, 1, -1]  # a mirror image: the best rotation is not the reflection
    fit = fit_rigid(src, ref)
    np.testing.assert_allclose(np.linalg.det(fit.rotation), 1.0, atol=1e-12)
    np.testing.assert_allclose(fit.rotation @ fit.rotation.T, np.eye(3), atol=1e-12)
    # brute-force check of optimality against random rotations near the solution
    cost = ((apply_rigid(fit.matrix(), src) - ref) ** 2).sum()
    for rotvec in rng.normal(0, 0.05, (50, 3)):
        other = Rotation.from_rotvec(rotvec).as_matrix() @ fit.rotation
        t = ref.mean(0) - other @ src.mean(0)
        assert ((src @ other.T + t - ref) ** 2).sum() >= cost - 1e-9


@pytest.mark.parametrize("args, match", [
    ((np.zeros((4, 2)), np.zeros((4, 3))), r"points_src: expected shape \(\.\.\., N, 3\)"),
    ((np.zeros((4, 3)), np.zeros((5, 3))), r"points_ref: .*N = 4 .*found \(5, 3\)"),
    ((np.zeros((4, 3)), np.zeros((4, 3)), np.ones(3)), r"weights: expected shape \(\.\.\., 4\)"),
    ((np.zeros((4, 3)), np.zeros((4, 3)), -np.ones(4)), r"weights: expected values >= 0"),
    ((np.zeros((4, 3)), np.zeros((4, 3)), np.zeros(4)), r"weights: expected a positive total"),
])
def test_fit_rigid_rejects_bad_input(args, match):
    with pytest.raises(ValueError, match=match):
        fit_rigid(*args)


def test_fit_rigid_with_scale_rejects_coincident_points():
    with pytest.raises(ValueError, match="points_src: .*non-zero spread"):
        fit_rigid(np.ones((4, 3)), np.zeros((4, 3)), with_scale=True)


def test_invert_and_apply_rigid_match_numpy():
    rng = np.random.default_rng(6)
    rot, trans = _random_rigid(rng, (5,))
    mats = rigid_matrix(rot, trans)
    np.testing.assert_allclose(invert_rigid(mats), np.linalg.inv(mats), atol=1e-12)
    pts = rng.normal(size=(5, 7, 3))
    homog = np.concatenate([pts, np.ones((5, 7, 1))], -1)
    expected = np.einsum("fij,fnj->fni", mats, homog)[..., :3]
    np.testing.assert_allclose(apply_rigid(mats, pts), expected, atol=1e-12)


def test_stabilize_vertices_and_invert_rigid_torch_match_matrix_inverse():
    rng = np.random.default_rng(1)
    m = np.tile(np.eye(4), (5, 1, 1))
    m[:, :3, :3] = Rotation.random(5, random_state=1).as_matrix()
    m[:, :3, 3] = rng.normal(size=(5, 3))
    x = rng.normal(size=(5, 7, 3)).astype(np.float32)
    want = np.stack([(np.linalg.inv(m[f]) @ np.c_[x[f], np.ones(7)].T).T[:, :3] for f in range(5)])
    got = stabilize_vertices(x, m, block_frames=2)
    assert got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=1e-5)
    np.testing.assert_allclose(invert_rigid_torch(torch.tensor(m)).numpy(), np.linalg.inv(m), atol=1e-12)
    np.testing.assert_array_equal(invert_rigid_torch(torch.tensor(m)).numpy(), invert_rigid(m))


@pytest.mark.parametrize("batch", [(), (2, 3)])
def test_invert_rigid_torch_shapes_dtype_and_gradient(batch):
    rot, trans = _random_rigid(np.random.default_rng(8), batch)
    m = torch.tensor(rigid_matrix(rot, trans), requires_grad=True)
    inv = invert_rigid_torch(m)
    assert inv.shape == batch + (4, 4) and inv.dtype == torch.float64
    assert torch.allclose(inv @ m, torch.eye(4, dtype=torch.float64).expand_as(m), atol=1e-12)
    assert invert_rigid_torch(m.detach().float()).dtype == torch.float32
    assert torch.autograd.gradcheck(invert_rigid_torch, (m,))


def test_stabilize_vertices_rejects_bad_shapes():
    with pytest.raises(ValueError, match=r"vertices: expected shape \(F, V, 3\), found \(4, 3\)"):
        stabilize_vertices(np.zeros((4, 3)), np.tile(np.eye(4), (4, 1, 1)))
    with pytest.raises(ValueError, match=r"matrices: expected shape \(4, 4, 4\), found \(3, 4, 4\)"):
        stabilize_vertices(np.zeros((4, 5, 3)), np.tile(np.eye(4), (3, 1, 1)))


def test_rotation_angle_matches_scipy_including_near_pi():
    rng = np.random.default_rng(7)
    rotvec = rng.normal(size=(20, 3))
    rotvec *= (rng.uniform(0, np.pi, 20) / np.linalg.norm(rotvec, axis=1))[:, None]
    rotvec[0] = [0, 0, 1e-9]
    rotvec[1] = [np.pi - 1e-7, 0, 0]
    mats = Rotation.from_rotvec(rotvec).as_matrix()
    np.testing.assert_allclose(rotation_angle(mats), np.linalg.norm(rotvec, axis=1), atol=1e-7)


def test_rigid_docstring_examples():
    result = doctest.testmod(rigid)
    assert result.attempted > 0 and result.failed == 0
