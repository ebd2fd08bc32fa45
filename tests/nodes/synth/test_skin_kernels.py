"""The compiled kernels of the skin-dynamics simulation (nodes/synth/skin_kernels.py) against the
scipy matrix and the numpy time loop they replace."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import sparse

from nodes.synth.dynamics import _coupling_matrix, _kappa, _moving_kappas, smoothing_matrix
from nodes.synth.skin_kernels import GaussianSmoothing, integrate


def _cloud(n: int = 600, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    direction = rng.standard_normal((n, 3))
    return 8.0 * direction / np.linalg.norm(direction, axis=1, keepdims=True)  # a head-sized sphere, cm


@pytest.mark.parametrize("columns", [None, 1, 7])
def test_gaussian_smoothing_equals_the_matrix(columns):
    points = _cloud()
    values = np.random.default_rng(1).standard_normal((len(points),) if columns is None else (len(points), columns))
    expected = smoothing_matrix(points, sigma_cm=1.5) @ values
    got = GaussianSmoothing(points, sigma_cm=1.5) @ values
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12)  # float64 sums in another order


def test_gaussian_smoothing_isolated_point_and_bad_shape():
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [50.0, 0.0, 0.0]])
    got = GaussianSmoothing(points, sigma_cm=0.8) @ np.array([1.0, 3.0, 5.0])
    w = np.exp(-0.25 / (2 * 0.64))  # the pair's weight; the self weight is 2
    np.testing.assert_allclose(got, [(2 + 3 * w) / (2 + w), (6 + w) / (2 + w), 5.0], rtol=1e-12)
    with pytest.raises(ValueError, match="values"):
        GaussianSmoothing(points) @ np.zeros(4)


def test_gaussian_smoothing_columns_do_not_mix():
    """A product over many columns gives each column bit for bit as a product over it alone
    (what lets simulate_dynamics smooth several blocks of frames in one product)."""
    points = _cloud()
    values = np.random.default_rng(3).standard_normal((len(points), 37))
    smoothing = GaussianSmoothing(points, sigma_cm=1.5)
    whole = smoothing @ values
    for a, b in ((0, 16), (16, 33), (33, 37)):
        assert np.array_equal(whole[:, a:b], smoothing @ values[:, a:b])


@pytest.mark.parametrize("segments, columns", [(1, 256), (2, 8), (3, 1)])
def test_moving_kappas_equal_blockwise_kappa(segments, columns):
    """Blocks smoothed together equal `_kappa` block by block, bit for bit, for any grouping
    (`columns`: one block per product, two, or all), the last block short."""
    rest = _cloud(300)
    edges = np.array([(i, j) for i in range(len(rest)) for j in (i + 1, i + 7) if j < len(rest)])
    rng = np.random.default_rng(4)
    frames = 11
    shapes = (rest + 0.2 * rng.standard_normal((segments, frames, len(rest), 3))).astype(np.float32)
    smoothing = GaussianSmoothing(rest, sigma_cm=1.5)
    starts = range(0, frames, 4)
    got = list(_moving_kappas(shapes, rest, edges, 4.0, smoothing, starts, 4, columns=columns))
    assert [f0 for f0, _ in got] == list(starts)
    for f0, kappa in got:
        expected = _kappa(shapes[:, f0:f0 + 4], rest, edges, 4.0, smoothing)
        assert kappa.dtype == np.float32 and np.array_equal(kappa, expected)


def test_integrate_equals_the_numpy_loop():
    rng = np.random.default_rng(2)
    points = _cloud(300)
    v, nseg, frames, substeps, pre = len(points), 2, 7, 3, 2
    edges = np.array(sparse.triu(smoothing_matrix(points, sigma_cm=0.6) > 0, k=1).nonzero()).T
    h = 1e-3
    coupling = _coupling_matrix(points, edges, 100.0 ** 2 * h)
    rest_h = np.concatenate([points, np.ones((v, 1))], axis=1).astype(np.float32)
    affine = (0.1 * rng.standard_normal((nseg, frames * substeps, 3, 4))).astype(np.float32)
    damp_h = (h * rng.uniform(20, 60, v)).astype(np.float32)
    stiff = (h * rng.uniform(2e3, 2e4, (nseg, frames, v))).astype(np.float32)
    u, du = np.zeros((nseg, v, 3), np.float32), np.zeros((nseg, v, 3), np.float32)
    offsets = np.zeros((nseg, frames - pre, v, 3), np.float32)
    for f0 in range(0, frames, 4):  # in blocks, as simulate_dynamics calls it
        integrate(u, du, rest_h, affine, damp_h, stiff[:, f0:f0 + 4], coupling.indptr.astype(np.int64),
                  coupling.indices.astype(np.int64), coupling.data.astype(np.float32), substeps, h, f0, pre,
                  offsets)
    # the numpy loop of simulate_dynamics before the kernel
    nu, ndu = np.zeros_like(u), np.zeros_like(du)
    expected = np.zeros_like(offsets)
    for f in range(frames):
        k_h = stiff[:, f, :, None]
        for sub in range(substeps):
            a = rest_h @ np.swapaxes(affine[:, f * substeps + sub], 1, 2)
            ndu -= a
            ndu -= damp_h[None, :, None] * ndu
            ndu -= k_h * nu
            ndu += (coupling @ nu.transpose(1, 0, 2).reshape(v, -1)).reshape(v, nseg, 3).transpose(1, 0, 2)
            nu += np.float32(h) * ndu
        if f >= pre:
            expected[:, f - pre] = nu
    assert np.abs(expected).max() > 1e-4  # it moved
    np.testing.assert_allclose(offsets, expected, rtol=1e-4, atol=1e-4 * np.abs(expected).max())
    np.testing.assert_allclose(u, nu, rtol=1e-4, atol=1e-4 * np.abs(nu).max())
