"""Tests of nodes.geometry.dualquat against scipy Rotation and 4x4 matrix algebra."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nodes.geometry.dualquat import (dualquat_align_hemisphere, dualquat_blend, dualquat_conjugate,
                                      dualquat_from_matrix, dualquat_from_rotation_translation,
                                      dualquat_identity, dualquat_multiply, dualquat_normalize,
                                      dualquat_to_matrix, dualquat_to_rotation_translation,
                                      dualquat_transform_points, quat_conjugate, quat_multiply,
                                      quat_to_rotmat, rotmat_to_quat)


def _random_rigid(count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    m = np.tile(np.eye(4), (count, 1, 1))
    m[:, :3, :3] = Rotation.random(count, random_state=seed).as_matrix()
    m[:, :3, 3] = rng.normal(scale=5.0, size=(count, 3))
    return m


def _wxyz(rot: Rotation) -> np.ndarray:
    return np.roll(rot.as_quat(), 1, axis=-1)


def test_quat_multiply_matches_scipy_composition():
    a, b = Rotation.random(20, random_state=1), Rotation.random(20, random_state=2)
    got = quat_multiply(torch.tensor(_wxyz(a)), torch.tensor(_wxyz(b))).numpy()
    want = _wxyz(a * b)
    # q ~ -q: compare up to sign
    sign = np.sign((got * want).sum(-1, keepdims=True))
    np.testing.assert_allclose(got * sign, want, atol=1e-12)


def test_quat_to_rotmat_matches_scipy_and_conjugate_inverts():
    rot = Rotation.random(50, random_state=3)
    q = torch.tensor(_wxyz(rot))
    np.testing.assert_allclose(quat_to_rotmat(q).numpy(), rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(quat_conjugate(q)).numpy(), rot.inv().as_matrix(), atol=1e-12)
    # scaling the quaternion does not change the rotation
    np.testing.assert_allclose(quat_to_rotmat(3.0 * q).numpy(), rot.as_matrix(), atol=1e-12)


@pytest.mark.parametrize("angle_deg", [0.0, 45.0, 179.9, 180.0])
def test_rotmat_to_quat_round_trip_all_angles(angle_deg):
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(30, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    rot = Rotation.from_rotvec(axes * np.deg2rad(angle_deg))
    q = rotmat_to_quat(torch.tensor(rot.as_matrix())).numpy()
    assert np.all(q[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
    want = _wxyz(rot)
    sign = np.sign((q * want).sum(-1, keepdims=True))
    np.testing.assert_allclose(q * sign, want, atol=1e-9)


def test_dualquat_matrix_round_trip_and_shapes():
    m = _random_rigid(12, 5)
    dq = dualquat_from_matrix(torch.tensor(m))
    assert dq.shape == (12, 8)
    # unit dual quaternion: |q_r| = 1, q_r . q_d = 0
    np.testing.assert_allclose(dq[:, :4].norm(dim=1).numpy(), 1.0, atol=1e-12)
    np.testing.assert_allclose((dq[:, :4] * dq[:, 4:]).sum(1).numpy(), 0.0, atol=1e-12)
    np.testing.assert_allclose(dualquat_to_matrix(dq).numpy(), m, atol=1e-12)
    # sign flip is the same motion
    np.testing.assert_allclose(dualquat_to_matrix(-dq).numpy(), m, atol=1e-12)
    # batch shapes () and (2, 3)
    assert dualquat_from_matrix(torch.tensor(m[0])).shape == (8,)
    assert dualquat_to_matrix(dq[:6].reshape(2, 3, 8)).shape == (2, 3, 4, 4)


def test_dualquat_multiply_matches_matrix_product():
    a, b = _random_rigid(10, 6), _random_rigid(10, 7)
    prod = dualquat_multiply(dualquat_from_matrix(torch.tensor(a)), dualquat_from_matrix(torch.tensor(b)))
    np.testing.assert_allclose(dualquat_to_matrix(prod).numpy(), a @ b, atol=1e-10)


def test_dualquat_conjugate_is_inverse():
    m = _random_rigid(10, 8)
    dq = dualquat_from_matrix(torch.tensor(m))
    np.testing.assert_allclose(dualquat_to_matrix(dualquat_conjugate(dq)).numpy(), np.linalg.inv(m), atol=1e-10)
    ident = dualquat_multiply(dq, dualquat_conjugate(dq))
    np.testing.assert_allclose(ident.numpy(), dualquat_identity(10, dtype=torch.float64).numpy(), atol=1e-12)


def test_dualquat_transform_points_matches_matrix():
    m = _random_rigid(4, 9)
    pts = np.random.default_rng(9).normal(size=(4, 25, 3))
    got = dualquat_transform_points(dualquat_from_matrix(torch.tensor(m)), torch.tensor(pts)).numpy()
    want = pts @ np.swapaxes(m[:, :3, :3], 1, 2) + m[:, None, :3, 3]
    np.testing.assert_allclose(got, want, atol=1e-10)


def test_rotation_translation_round_trip_with_unnormalised_input():
    rot = Rotation.random(8, random_state=10)
    t = torch.tensor(np.random.default_rng(10).normal(size=(8, 3)))
    dq = dualquat_from_rotation_translation(torch.tensor(_wxyz(rot)), t)
    q, t2 = dualquat_to_rotation_translation(2.5 * dq)      # a scaled dual quaternion
    np.testing.assert_allclose(t2.numpy(), t.numpy(), atol=1e-12)
    np.testing.assert_allclose(quat_to_rotmat(q).numpy(), rot.as_matrix(), atol=1e-12)


def test_dualquat_normalize_gives_unit_and_keeps_motion():
    m = _random_rigid(6, 11)
    dq = dualquat_from_matrix(torch.tensor(m))
    # perturb: scale, and add a dual component along the real part (ignored by DLB extraction)
    bad = torch.cat([3.0 * dq[:, :4], 3.0 * dq[:, 4:] + 0.7 * dq[:, :4]], dim=1)
    unit = dualquat_normalize(bad)
    np.testing.assert_allclose(unit[:, :4].norm(dim=1).numpy(), 1.0, atol=1e-12)
    np.testing.assert_allclose((unit[:, :4] * unit[:, 4:]).sum(1).numpy(), 0.0, atol=1e-12)
    np.testing.assert_allclose(dualquat_to_matrix(unit).numpy(), m, atol=1e-10)


def test_dualquat_blend_endpoints_and_same_axis_interpolation():
    # Blending two rotations about one axis (no translation) with weights (1-a, a) gives a
    # rotation about that axis; the weight 0/1 endpoints are exact.
    axis = np.array([0.0, 0.6, 0.8])
    m0, m1 = np.eye(4), np.eye(4)
    m1[:3, :3] = Rotation.from_rotvec(axis * 1.2).as_matrix()
    dq = dualquat_from_matrix(torch.tensor(np.stack([m0, m1])))
    for a in (0.0, 0.3, 1.0):
        out = dualquat_to_matrix(dualquat_blend(dq, torch.tensor([1 - a, a], dtype=torch.float64))).numpy()
        rv = Rotation.from_matrix(out[:3, :3]).as_rotvec()
        np.testing.assert_allclose(np.cross(rv, axis), 0.0, atol=1e-12)
        if a in (0.0, 1.0):
            np.testing.assert_allclose(out, [m0, m1][int(a)], atol=1e-12)
    # antipodal input (q and -q) blends as the same rotation when aligned
    flipped = torch.stack([dq[0], -dq[1]])
    np.testing.assert_allclose(dualquat_blend(flipped, torch.tensor([0.5, 0.5], dtype=torch.float64)).numpy(),
                               dualquat_blend(dq, torch.tensor([0.5, 0.5], dtype=torch.float64)).numpy(), atol=1e-12)


def test_dualquat_blend_is_coordinate_invariant():
    # DLB commutes with a change of frame: blend(T q_i) = T blend(q_i) (Kavan 2008).
    m = _random_rigid(4, 12)
    m[:, :3, :3] = Rotation.from_rotvec(np.random.default_rng(12).normal(scale=0.3, size=(4, 3))).as_matrix()
    w = torch.tensor([0.1, 0.4, 0.3, 0.2], dtype=torch.float64)
    frame = dualquat_from_matrix(torch.tensor(_random_rigid(1, 13)[0]))
    dq = dualquat_from_matrix(torch.tensor(m))
    left = dualquat_blend(dualquat_multiply(frame, dq), w)
    right = dualquat_multiply(frame, dualquat_blend(dq, w))
    np.testing.assert_allclose(dualquat_to_matrix(left).numpy(), dualquat_to_matrix(right).numpy(), atol=1e-10)


def test_dualquat_align_hemisphere_chains_sequence():
    m = _random_rigid(1, 14)
    dq = dualquat_from_matrix(torch.tensor(m)).expand(5, 8).clone()
    signs = torch.tensor([1.0, -1.0, -1.0, 1.0, -1.0], dtype=torch.float64)[:, None]
    aligned = dualquat_align_hemisphere(dq * signs, dim=0)
    np.testing.assert_allclose(aligned.numpy(), dq.numpy(), atol=0)


def test_dualquat_to_matrix_gradcheck():
    dq = dualquat_from_matrix(torch.tensor(_random_rigid(3, 15))) + 0.05
    dq.requires_grad_(True)
    assert torch.autograd.gradcheck(dualquat_to_matrix, (dq,))


def test_bad_shapes_name_the_argument():
    with pytest.raises(ValueError, match=r"dq: expected shape \(\.\.\., 8\), found \(3, 7\)"):
        dualquat_to_matrix(torch.zeros(3, 7))
    with pytest.raises(ValueError, match=r"matrix: expected shape \(\.\.\., 4, 4\), found \(3, 3\)"):
        dualquat_from_matrix(torch.zeros(3, 3))
    with pytest.raises(ValueError, match=r"rot: expected shape \(\.\.\., 3, 3\)"):
        rotmat_to_quat(torch.zeros(2, 4, 4))
    with pytest.raises(ValueError, match=r"b: expected shape \(\.\.\., 4\)"):
        quat_multiply(torch.zeros(4), torch.zeros(3))
