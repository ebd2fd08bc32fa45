"""Tests of nodes/synth/head_motion.py against scipy's Rotation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodes.synth.head_motion import (MOTIONS, default_pivot, euler_xyz_to_rotmat, head_motion_curves,
                                     poses_to_matrices)


def test_euler_xyz_to_rotmat_matches_scipy():
    angles = np.random.default_rng(0).uniform(-np.pi, np.pi, (2, 5, 3))
    expected = Rotation.from_euler("xyz", angles.reshape(-1, 3)).as_matrix().reshape(2, 5, 3, 3)
    np.testing.assert_allclose(euler_xyz_to_rotmat(angles), expected, atol=1e-12)
    assert euler_xyz_to_rotmat(np.zeros(3)).shape == (3, 3)
    with pytest.raises(ValueError, match=r"angles: expected shape \(\.\.\., 3\), found \(4, 2\)"):
        euler_xyz_to_rotmat(np.zeros((4, 2)))


def test_poses_to_matrices_rotate_about_pivot():
    rng = np.random.default_rng(1)
    angles, trans, pivot = rng.normal(0, 0.3, (6, 3)), rng.normal(0, 2, (6, 3)), rng.normal(0, 5, 3)
    m = poses_to_matrices(angles, trans, pivot)
    np.testing.assert_allclose(m[:, :3, :3] @ pivot + m[:, :3, 3], pivot + trans, atol=1e-12)
    x = rng.normal(0, 10, 3)
    rot = Rotation.from_euler("xyz", angles).as_matrix()
    np.testing.assert_allclose(m[:, :3, :3] @ x + m[:, :3, 3], (rot @ (x - pivot)) + pivot + trans,
                               atol=1e-12)
    np.testing.assert_array_equal(m[:, 3], np.tile([0, 0, 0, 1.0], (6, 1)))


@pytest.mark.parametrize("motion", ["smooth", "nod", "turn", "walk"])
def test_head_motion_curves_peak_amplitudes(motion):
    angles, trans = head_motion_curves(900, seed=3, motion=motion, rotation_deg=12.0,
                                       translation_cm=1.5)
    peak_rot, peak_trans = np.abs(angles).max(axis=0), np.abs(trans).max(axis=0)
    if motion == "smooth":
        np.testing.assert_allclose(peak_rot, np.deg2rad(12.0), rtol=1e-12)
        np.testing.assert_allclose(peak_trans, 1.5, rtol=1e-12)
    else:
        np.testing.assert_allclose(peak_rot.max(), np.deg2rad(12.0), rtol=1e-12)
        np.testing.assert_allclose(peak_trans.max(), 1.5, rtol=1e-12)
    main_axis = {"smooth": None, "nod": 0, "turn": 1, "walk": 2}[motion]
    if main_axis is not None:
        assert np.argmax(peak_rot) == main_axis


def test_head_motion_curves_smooth_band_limited():
    fps, fmax = 30.0, 0.5
    angles, _ = head_motion_curves(3000, seed=2, fps=fps, motion="smooth", max_frequency_hz=fmax)
    power = np.abs(np.fft.rfft(angles - angles.mean(axis=0), axis=0)) ** 2
    freq = np.fft.rfftfreq(3000, 1 / fps)
    assert power[freq > 3 * fmax].sum() < 1e-2 * power.sum()


def test_head_motion_curves_none_and_zero_amplitude_are_identity():
    for kwargs in ({"motion": "none"}, {"rotation_deg": 0.0, "translation_cm": 0.0}):
        angles, trans = head_motion_curves(50, seed=0, **kwargs)
        assert not angles.any() and not trans.any()


def test_head_motion_curves_seeded():
    a = head_motion_curves(100, seed=4)
    np.testing.assert_array_equal(a[0], head_motion_curves(100, seed=4)[0])
    assert not np.array_equal(a[0], head_motion_curves(100, seed=5)[0])


def test_head_motion_curves_unknown_motion_lists_known():
    with pytest.raises(ValueError, match=r"motion: expected one of .*'nod'.*found 'dance'"):
        head_motion_curves(10, seed=0, motion="dance")
    assert set(MOTIONS) >= {"smooth", "nod", "turn", "walk"}


def test_default_pivot_inside_head_below_eyes():
    neutral = np.array([[-10.0, -20.0, -10.0], [10.0, 15.0, 12.0]])
    np.testing.assert_allclose(default_pivot(neutral), [0.0, -4.25, -1.2])
