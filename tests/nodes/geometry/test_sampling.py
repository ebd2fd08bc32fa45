"""Tests of nodes.geometry.sampling: farthest-point sampling in numpy and torch."""

import numpy as np
import pytest
import torch

from nodes.geometry.sampling import farthest_point_sampling, farthest_point_sampling_torch


def test_farthest_point_sampling_matches_naive_loop():
    points = np.random.default_rng(1).standard_normal((200, 3))
    got = farthest_point_sampling(points, 25, seed=3)
    first = np.random.default_rng(3).integers(200)
    chosen = [int(first)]
    while len(chosen) < 25:
        best, best_d = -1, -1.0
        for i in range(200):
            d = min(float(np.sum((points[i] - points[j]) ** 2)) for j in chosen)
            if d > best_d:
                best, best_d = i, d
        chosen.append(best)
    np.testing.assert_array_equal(got, np.sort(chosen))
    np.testing.assert_array_equal(farthest_point_sampling(points, 500), np.arange(200))


def test_farthest_point_sampling_rejects_bad_input():
    with pytest.raises(ValueError, match=r"points: expected shape \(N, 3\), found \(10, 2\)"):
        farthest_point_sampling(np.zeros((10, 2)), 3)
    with pytest.raises(ValueError, match=r"first: expected an index in 0..9, found 10"):
        farthest_point_sampling(np.zeros((10, 3)), 3, first=10)


def test_farthest_point_sampling_torch_is_deterministic_and_spread():
    pts = torch.tensor(np.random.default_rng(0).normal(size=(500, 3)))
    a = farthest_point_sampling_torch(pts, 40)
    assert torch.equal(a, farthest_point_sampling_torch(pts, 40)) and len(set(a.tolist())) == 40
    # spread: the sampled set's smallest pairwise distance beats random subsets of the same size
    def min_gap(idx):
        d = torch.cdist(pts[idx], pts[idx])
        return float(d[~torch.eye(len(idx), dtype=torch.bool)].min())
    rand = [min_gap(torch.tensor(np.random.default_rng(s).choice(500, 40, replace=False))) for s in range(20)]
    assert min_gap(a) > max(rand)
    assert torch.equal(farthest_point_sampling_torch(pts, 900), torch.arange(500))


def test_farthest_point_sampling_torch_starts_nearest_the_centroid():
    pts = np.random.default_rng(2).normal(size=(300, 3))
    first = int(((pts - pts.mean(0)) ** 2).sum(1).argmin())
    got = farthest_point_sampling_torch(torch.tensor(pts, dtype=torch.float32), 30)
    assert got.dtype == torch.int64 and first in got.tolist()
    np.testing.assert_array_equal(got.numpy(), farthest_point_sampling(pts.astype(np.float32), 30, first=first))
