"""nodes.geometry.rotation against scipy.spatial.transform.Rotation (an independent reference),
with round trips, batch shapes, the small-angle and 180-degree cases and torch twins.

Tolerances: every conversion is a few float64 operations on values of size <= pi, so results agree
with scipy to a few ulps of 1 (1e-14 here, ~50 ulps); conversions back to angles near gimbal lock
or near 180 degrees lose precision as 1 / sin of the distance to them, so those cases are checked
on the matrices they reproduce (1e-12)."""

from __future__ import annotations

import doctest

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodes.geometry import rotation
from nodes.geometry.rotation import (axis_angle_to_quat, axis_angle_to_rotmat, euler_to_rotmat, quat_mean,
                                     quat_to_axis_angle, quat_to_rotmat, rotmat_to_axis_angle, rotmat_to_euler,
                                     rotmat_to_quat, skew)

ORDERS = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]


def _rotvecs(count: int, seed: int = 0) -> np.ndarray:
    """Random axis-angle vectors with angles over [0, pi), plus the hard cases."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0.0, np.pi, (count, 1))
    hard = np.array([[0.0, 0.0, 0.0], [1e-14, -2e-14, 3e-14], [1e-7, 0.0, 0.0], [0.0, 0.0, np.pi],
                     [np.pi - 1e-9, 0.0, 0.0], [0.0, 0.0, -np.pi / 2]])
    return np.concatenate([axes * angles, hard])


def _wxyz(rot: Rotation) -> np.ndarray:
    return rot.as_quat(canonical=True)[..., [3, 0, 1, 2]]


def test_skew_is_the_cross_product():
    rng = np.random.default_rng(1)
    v, u = rng.normal(size=(2, 5, 3))
    np.testing.assert_allclose(np.einsum("nij,nj->ni", skew(v), u), np.cross(v, u), atol=1e-14)
    assert skew(np.arange(3)).dtype == np.float64 and skew(v.astype(np.float32)).dtype == np.float32
    with pytest.raises(ValueError, match=r"v: expected shape \(\.\.\., 3\), found \(4, 2\)"):
        skew(np.zeros((4, 2)))


def test_axis_angle_to_rotmat_matches_scipy():
    w = _rotvecs(200)
    np.testing.assert_allclose(axis_angle_to_rotmat(w), Rotation.from_rotvec(w).as_matrix(), atol=1e-14)
    for rvec in w[-6:]:  # one vector at a time (OpenCV's Rodrigues vectors in io.camera)
        np.testing.assert_allclose(axis_angle_to_rotmat(rvec), Rotation.from_rotvec(rvec).as_matrix(), atol=1e-14)


def test_rotmat_to_axis_angle_matches_scipy():
    w = _rotvecs(200)[:-2]  # near 180 degrees the axis' sign is arbitrary: checked by round trip below
    m = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(rotmat_to_axis_angle(m), Rotation.from_matrix(m).as_rotvec(), atol=1e-14)
    near_pi = Rotation.from_rotvec(_rotvecs(1)[-2:]).as_matrix()
    np.testing.assert_allclose(axis_angle_to_rotmat(rotmat_to_axis_angle(near_pi)), near_pi, atol=1e-12)
    assert (np.linalg.norm(rotmat_to_axis_angle(m), axis=-1) <= np.pi + 1e-15).all()


def test_quaternions_match_scipy():
    w = _rotvecs(200)
    q = axis_angle_to_quat(w)
    ref = _wxyz(Rotation.from_rotvec(w))
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", q, ref)), 1.0, atol=1e-14)  # same rotation, q ~ -q
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    m = Rotation.from_rotvec(w).as_matrix()
    np.testing.assert_allclose(quat_to_rotmat(q), m, atol=1e-14)
    np.testing.assert_allclose(quat_to_rotmat(-3.0 * q), m, atol=1e-14)  # any norm, either sign
    got = rotmat_to_quat(m)
    assert (got[:, 0] >= 0).all()
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", got, ref)), 1.0, atol=1e-14)
    np.testing.assert_allclose(quat_to_axis_angle(ref[:-2]), w[:-2], atol=1e-14)
    np.testing.assert_allclose(quat_to_axis_angle(-ref[:-2]), w[:-2], atol=1e-14)


def test_rotmat_to_quat_of_a_float32_rotation_matches_scipy():
    m = Rotation.from_rotvec(_rotvecs(50, seed=2)).as_matrix().astype(np.float32)  # ~1e-7 off orthonormal
    got, ref = rotmat_to_quat(m), _wxyz(Rotation.from_matrix(m.astype(np.float64)))
    np.testing.assert_allclose(np.abs(np.einsum("ni,ni->n", got, ref)), 1.0, atol=1e-12)


def test_quat_mean_matches_scipy_and_ignores_signs():
    rng = np.random.default_rng(4)
    w = rng.normal(0, 0.4, (3, 7, 3)) + np.array([0.3, -1.0, 0.5])  # three clusters of 7 rotations
    weights = rng.uniform(0.1, 1.0, (3, 7))
    q = axis_angle_to_quat(w) * rng.choice([-1.0, 1.0], (3, 7, 1))
    got = quat_mean(q, weights)
    for k in range(3):
        ref = _wxyz(Rotation.from_rotvec(w[k]).mean(weights=weights[k]))
        np.testing.assert_allclose(abs(got[k] @ ref), 1.0, atol=1e-12)  # eigh's accuracy, a few ulps of 1
    assert (got[:, 0] >= 0).all()


@pytest.mark.parametrize("order", ORDERS)
def test_euler_angles_match_scipy(order):
    rng = np.random.default_rng(3)
    angles = rng.uniform(-np.pi, np.pi, (300, 3))
    angles[:, 1] = rng.uniform(-1.5, 1.5, 300)  # the middle angle in its range, away from gimbal lock
    m = euler_to_rotmat(angles, order)
    np.testing.assert_allclose(m, Rotation.from_euler(order, angles).as_matrix(), atol=1e-14)
    back = rotmat_to_euler(m, order)
    np.testing.assert_allclose(back, Rotation.from_matrix(m).as_euler(order), atol=1e-12)
    np.testing.assert_allclose(back, angles, atol=1e-12)


@pytest.mark.parametrize("order", ["xyz", "YXZ", "zxy", "ZYX"])
def test_euler_angles_at_gimbal_lock_reproduce_the_matrix(order):
    angles = np.array([[0.3, np.pi / 2, -0.7], [1.1, -np.pi / 2, 0.2]])
    m = euler_to_rotmat(angles, order)
    back = rotmat_to_euler(m, order)
    np.testing.assert_allclose(euler_to_rotmat(back, order), m, atol=1e-12)
    np.testing.assert_array_equal(back[:, 2], 0.0)  # only a sum or difference is defined: the third is 0
    with pytest.warns(UserWarning, match="Gimbal lock"):
        np.testing.assert_allclose(back, Rotation.from_matrix(m).as_euler(order), atol=1e-12)


def test_euler_xyz_is_rz_ry_rx():
    a, b, c = 0.3, -0.4, 1.2

    def about(axis: int, t: float) -> np.ndarray:
        return Rotation.from_rotvec(np.eye(3)[axis] * t).as_matrix()

    np.testing.assert_allclose(euler_to_rotmat([a, b, c], "xyz"), about(2, c) @ about(1, b) @ about(0, a), atol=1e-15)
    np.testing.assert_allclose(euler_to_rotmat([a, b, c], "YXZ"), about(1, a) @ about(0, b) @ about(2, c), atol=1e-15)


def test_shapes_and_errors():
    for shape in [(), (2, 3)]:
        w = np.zeros(shape + (3,))
        assert axis_angle_to_rotmat(w).shape == shape + (3, 3)
        assert rotmat_to_axis_angle(axis_angle_to_rotmat(w)).shape == shape + (3,)
        assert axis_angle_to_quat(w).shape == shape + (4,)
        assert rotmat_to_quat(np.broadcast_to(np.eye(3), shape + (3, 3))).shape == shape + (4,)
        assert euler_to_rotmat(w, "YXZ").shape == shape + (3, 3)
        assert rotmat_to_euler(np.broadcast_to(np.eye(3), shape + (3, 3)), "xyz").shape == shape + (3,)
    assert axis_angle_to_rotmat(np.zeros((0, 3))).shape == (0, 3, 3)
    assert rotmat_to_axis_angle(np.zeros((0, 3, 3))).shape == (0, 3)
    with pytest.raises(ValueError, match=r"rot: expected shape \(\.\.\., 3, 3\), found \(4, 3\)"):
        rotmat_to_quat(np.zeros((4, 3)))
    with pytest.raises(ValueError, match=r"order: expected three distinct axes.*found 'xyx'"):
        euler_to_rotmat(np.zeros(3), "xyx")
    with pytest.raises(ValueError, match=r"order: .*found 'xYz'"):
        rotmat_to_euler(np.eye(3), "xYz")


def test_torch_twins_match_numpy():
    torch = pytest.importorskip("torch")
    w = _rotvecs(100)
    m = axis_angle_to_rotmat(w)
    np.testing.assert_allclose(rotation.axis_angle_to_rotmat_torch(torch.tensor(w)).numpy(), m, atol=1e-14)
    np.testing.assert_array_equal(rotation.skew_torch(torch.tensor(w)).numpy(), skew(w))
    q = rotation.rotmat_to_quat_torch(torch.tensor(m)).numpy()
    np.testing.assert_allclose(q, rotmat_to_quat(m), atol=1e-14)
    np.testing.assert_allclose(rotation.quat_to_rotmat_torch(torch.tensor(q)).numpy(), m, atol=1e-14)
    small = torch.tensor([[1e-6, -2e-6, 0.5e-6]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotation.axis_angle_to_rotmat_torch, (small,))
    big = torch.tensor([[0.4, -1.0, 2.0]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rotation.axis_angle_to_rotmat_torch, (big,))


def test_docstring_examples():
    assert doctest.testmod(rotation).failed == 0


def test_quat_sequence_continuous_keeps_consecutive_quaternions_in_one_hemisphere():
    from nodes.geometry.rotation import quat_sequence_continuous

    angles = np.linspace(0.0, 4 * np.pi, 97)  # two turns about a tilted axis: w changes sign twice
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    canonical = rotmat_to_quat(axis_angle_to_rotmat(angles[:, None] * axis))  # w >= 0: jumps to -q
    assert ((canonical[1:] * canonical[:-1]).sum(1) < 0).sum() >= 1
    smooth = quat_sequence_continuous(canonical)
    assert ((smooth[1:] * smooth[:-1]).sum(1) > 0).all()
    np.testing.assert_allclose(np.abs(smooth), np.abs(canonical), atol=0)  # only signs change
    np.testing.assert_allclose(quat_to_rotmat(smooth), quat_to_rotmat(canonical), atol=1e-15)
    np.testing.assert_array_equal(smooth[0], canonical[0])
    with pytest.raises(ValueError, match=r"expected shape \(F, 4\)"):
        quat_sequence_continuous(canonical[:, :3])
