"""Tests of nodes.geometry.bspline against scipy.interpolate.BSpline."""

import numpy as np
import pytest
import torch
from scipy.interpolate import BSpline

from nodes.geometry.bspline import (basis_matrix, bspline_basis, evaluate_spline, fit_control_points,
                                     frame_basis, num_control_points, refine_midpoint, uniform_knots)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_bspline_basis_matches_scipy_on_nonuniform_knots(degree):
    rng = np.random.default_rng(0)
    inner = np.sort(rng.uniform(0.0, 10.0, 9))
    knots = np.concatenate([[0.0] * (degree + 1), inner, [10.0] * (degree + 1)])
    x = np.concatenate([rng.uniform(0.0, 10.0, 200), inner, [0.0, 10.0]])
    basis = bspline_basis(torch.tensor(x), torch.tensor(knots), degree)
    want = BSpline.design_matrix(x, knots, degree).toarray()
    np.testing.assert_allclose(basis_matrix(basis).numpy(), want, atol=1e-12)


def test_frame_basis_matches_scipy_and_uniform_closed_form():
    frames, spacing = 50, 4.5
    basis = frame_basis(frames, spacing)
    n = num_control_points(frames, spacing)
    assert basis.num_control == n == int(np.ceil(49 / 4.5)) + 3
    knots = uniform_knots(n, spacing).numpy()
    want = BSpline.design_matrix(np.arange(frames, dtype=float), knots, 3).toarray()
    np.testing.assert_allclose(basis_matrix(basis).numpy(), want, atol=1e-12)
    # closed form of the uniform cubic: ((1-u)^3, 3u^3 - 6u^2 + 4, -3u^3 + 3u^2 + 3u + 1, u^3) / 6
    u = torch.arange(frames, dtype=torch.float64) / spacing
    u = u - u.floor()
    closed = torch.stack([(1 - u) ** 3, 3 * u**3 - 6 * u**2 + 4, -3 * u**3 + 3 * u**2 + 3 * u + 1, u**3], 1) / 6
    np.testing.assert_allclose(basis.weights.numpy(), closed.numpy(), atol=1e-12)
    np.testing.assert_allclose(basis.weights.sum(1).numpy(), 1.0, atol=1e-12)


def test_every_control_point_touches_a_frame():
    for frames in (7, 8, 50, 651):
        for spacing in (1.0, 2.0, 3.0, 4.0, 7.5, 16.0):
            m = basis_matrix(frame_basis(frames, spacing))
            assert (m.sum(0) > 0).all(), (frames, spacing)


def test_evaluate_spline_matches_scipy_curve():
    frames, spacing = 40, 5.0
    basis = frame_basis(frames, spacing)
    control = torch.tensor(np.random.default_rng(1).normal(size=(basis.num_control, 8)))
    knots = uniform_knots(basis.num_control, spacing).numpy()
    want = BSpline(knots, control.numpy(), 3)(np.arange(frames, dtype=float))
    np.testing.assert_allclose(evaluate_spline(control, basis).numpy(), want, atol=1e-12)


@pytest.mark.parametrize("frames,spacing", [(100, 16.0), (651, 8.0), (33, 5.0), (20, 3.0)])
def test_refine_midpoint_leaves_curve_unchanged(frames, spacing):
    basis = frame_basis(frames, spacing)
    control = torch.tensor(np.random.default_rng(2).normal(size=(basis.num_control, 3)))
    coarse = evaluate_spline(control, basis)
    fine_control = refine_midpoint(control)
    assert fine_control.shape == (2 * basis.num_control - 3, 3)
    # the refined polygon spans the same domain with half the spacing (evaluate on a dense
    # grid too, not only on frames)
    n_fine = fine_control.shape[0]
    x = np.linspace(0.0, (basis.num_control - 3) * spacing, 997)
    want = BSpline(uniform_knots(basis.num_control, spacing).numpy(), control.numpy(), 3)(x)
    got = BSpline(uniform_knots(n_fine, spacing / 2).numpy(), fine_control.numpy(), 3)(x)
    np.testing.assert_allclose(got, want, atol=1e-12)
    # trimmed to the frames' needs, the refined spline is identical on every frame
    fine_basis = frame_basis(frames, spacing / 2)
    trimmed = fine_control[:fine_basis.num_control]
    np.testing.assert_allclose(evaluate_spline(trimmed, fine_basis).numpy(), coarse.numpy(), atol=1e-12)


def test_fit_control_points_reproduces_spline_and_least_squares():
    frames, spacing = 60, 6.0
    basis = frame_basis(frames, spacing)
    control = torch.tensor(np.random.default_rng(3).normal(size=(basis.num_control, 4)))
    values = evaluate_spline(control, basis)
    np.testing.assert_allclose(fit_control_points(values, basis, smoothing=0.0).numpy(), control.numpy(), atol=1e-9)
    # noisy samples: matches numpy's least squares
    noisy = values + torch.tensor(np.random.default_rng(4).normal(scale=0.1, size=values.shape))
    want = np.linalg.lstsq(basis_matrix(basis).numpy(), noisy.numpy(), rcond=None)[0]
    np.testing.assert_allclose(fit_control_points(noisy, basis, smoothing=0.0).numpy(), want, atol=1e-9)
    # the default tiny regulariser changes the fitted curve by a negligible amount
    fitted = evaluate_spline(fit_control_points(noisy, basis), basis)
    exact = basis_matrix(basis).numpy() @ want
    np.testing.assert_allclose(fitted.numpy(), exact, atol=1e-6)


def test_evaluate_spline_gradcheck():
    basis = frame_basis(12, 3.0)
    control = torch.randn(basis.num_control, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(5),
                          requires_grad=True)
    assert torch.autograd.gradcheck(lambda c: evaluate_spline(c, basis), (control,))


def test_bad_arguments_name_what_is_wrong():
    with pytest.raises(ValueError, match=r"x: expected values in the spline domain \[0.0, 10.0\]"):
        bspline_basis(torch.tensor([11.0], dtype=torch.float64), uniform_knots(5, 5.0), 3)
    with pytest.raises(ValueError, match=r"spacing: expected > 0 frames, found 0"):
        frame_basis(10, 0.0)
    with pytest.raises(ValueError, match=r"control: expected shape \(6, D\), found \(5, 8\)"):
        evaluate_spline(torch.zeros(5, 8), frame_basis(10, 3.0))
    with pytest.raises(ValueError, match=r"control: expected shape \(n >= 4, D\), found \(3, 8\)"):
        refine_midpoint(torch.zeros(3, 8))
