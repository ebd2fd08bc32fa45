"""Tests of nodes.stabilize.penalty: psi against the paper's piecewise form, the velocity filter."""

import numpy as np
import pytest
import torch

from nodes.stabilize.penalty import (VELOCITY_COEFFS, central_velocity, central_velocity_adjoint, psi,
                                     psi_derivative, psi_sum_and_grad_)


def _psi_piecewise(x: np.ndarray, w: float) -> np.ndarray:
    """The paper's eq. 1 (n = 2), written branch by branch in float64."""
    u = np.abs(x) / w
    return np.where(u < 0.5, 2 * u**2, np.where(u < 1.0, 1 - 2 * (1 - u) ** 2, 1.0))


def test_psi_matches_piecewise_definition():
    x = np.linspace(-3.0, 3.0, 2001)
    for w in (0.05, 0.8, 2.0):
        np.testing.assert_allclose(psi(torch.tensor(x), w).numpy(), _psi_piecewise(x, w), atol=1e-14)


def test_psi_properties_bounded_even_and_continuous_derivative():
    x = torch.linspace(-2.0, 2.0, 4001, dtype=torch.float64)
    y = psi(x, 1.0)
    assert float(y.min()) >= 0.0 and float(y.max()) == 1.0
    assert float(psi(torch.zeros(1), 1.0)) == 0.0
    np.testing.assert_allclose(y.numpy(), psi(-x, 1.0).numpy(), atol=0)
    d = psi_derivative(x, 1.0).numpy()
    assert np.abs(np.diff(d)).max() < 0.01           # C1: no jumps in the derivative
    assert d[np.abs(x.numpy()) >= 1.0].tolist() == [0.0] * int((np.abs(x.numpy()) >= 1.0).sum())


def test_psi_derivative_matches_finite_differences_and_gradcheck():
    rng = np.random.default_rng(0)
    x = torch.tensor(rng.uniform(-1.5, 1.5, 500))
    x = x[(x.abs() - 0.35).abs() > 1e-3]                     # avoid the kinks at |x| = w/2, w
    x = x[(x.abs() - 0.7).abs() > 1e-3]
    h = 1e-6
    fd = (psi(x + h, 0.7) - psi(x - h, 0.7)) / (2 * h)
    np.testing.assert_allclose(psi_derivative(x, 0.7).numpy(), fd.numpy(), atol=1e-6)
    xg = x[:50].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda t: psi(t, 0.7), (xg,))


def test_psi_sum_and_grad_fused_matches_reference():
    x = torch.randn(7, 300, generator=torch.Generator().manual_seed(1), dtype=torch.float32) * 0.6
    w = 0.45
    total, h = psi_sum_and_grad_((x / w).clone())
    np.testing.assert_allclose(float(total), float(psi(x.double(), w).sum()), rtol=1e-5)
    np.testing.assert_allclose((4.0 * h / w).numpy(), psi_derivative(x.double(), w).numpy(), atol=1e-4)


def test_central_velocity_exact_on_degree_6_polynomials():
    rng = np.random.default_rng(2)
    t = np.arange(20, dtype=np.float64)
    coeffs = rng.normal(size=(7, 4))                         # 4 polynomials of degree 6
    poly = sum(coeffs[k] * ((t[:, None] - 10) / 10) ** k for k in range(7))
    deriv = sum(k * coeffs[k] * ((t[:, None] - 10) / 10) ** (k - 1) / 10 for k in range(1, 7))
    got = central_velocity(torch.tensor(poly), dim=0).numpy()
    np.testing.assert_allclose(got, deriv[3:-3], atol=1e-11)
    full = central_velocity(torch.tensor(poly), dim=0, ends="one_sided").numpy()
    np.testing.assert_allclose(full, deriv, atol=1e-9)
    # reduced ends: interior unchanged, ends exact on the orders their stencils have
    reduced = central_velocity(torch.tensor(poly), dim=0, ends="reduced").numpy()
    np.testing.assert_allclose(reduced[3:-3], deriv[3:-3], atol=1e-11)
    line = torch.tensor(3.0 * t - 2.0)
    np.testing.assert_allclose(central_velocity(line, ends="reduced").numpy(), 3.0, atol=1e-12)
    quartic = torch.tensor((t / 10) ** 4)
    red = central_velocity(quartic, ends="reduced").numpy()
    np.testing.assert_allclose(red[[2, -3]], (4 * (t / 10) ** 3 / 10)[[2, -3]], atol=1e-12)
    np.testing.assert_allclose(red[[1, -2]], [(t[2] ** 4 - t[0] ** 4) / 2e4, (t[-1] ** 4 - t[-3] ** 4) / 2e4],
                               atol=1e-12)
    # not exact at degree 7: the filter really is 6th order
    p7 = ((t - 10) / 10) ** 7
    assert np.abs(central_velocity(torch.tensor(p7)).numpy() - 0.7 * ((t[3:-3] - 10) / 10) ** 6).max() > 1e-9


def test_central_velocity_coefficients_and_dim():
    assert VELOCITY_COEFFS == pytest.approx((0.75, -0.15, 1.0 / 60.0))
    x = torch.randn(3, 12, 5, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    v = central_velocity(x, dim=1)
    assert v.shape == (3, 6, 5)
    np.testing.assert_allclose(v.numpy(), central_velocity(x.transpose(0, 1), dim=0).transpose(0, 1).numpy())


def test_central_velocity_adjoint_is_transpose():
    x = torch.randn(15, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(4), requires_grad=True)
    g = torch.randn(9, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    (want,) = torch.autograd.grad((central_velocity(x) * g).sum(), x)
    np.testing.assert_allclose(central_velocity_adjoint(g, 15).numpy(), want.numpy(), atol=1e-14)


def test_bad_arguments_name_what_is_wrong():
    with pytest.raises(ValueError, match=r"width: expected > 0, found 0"):
        psi(torch.zeros(3), 0.0)
    with pytest.raises(ValueError, match=r"x: expected at least 7 frames along dim 0, found 6"):
        central_velocity(torch.zeros(6, 3))
    with pytest.raises(ValueError, match=r"ends: expected 'valid', 'one_sided' or 'reduced', found 'wrap'"):
        central_velocity(torch.zeros(9, 3), ends="wrap")
    with pytest.raises(ValueError, match=r"grad: expected 9 frames along dim 0 for num_frames=15, found 8"):
        central_velocity_adjoint(torch.zeros(8, 3), 15)
