"""What the fit caches between its iterations gives what recomputing gives, bit for bit:
`nodes.fit.views.at_anchors` (shapes gathered from cached vertex-major rows) against the plain
gather of each shape, a cached copy not reused after its tensor changed in place, gradients
through it; `nodes.fit.photometric.PhotoTerm.about` with a cache reused only while the
inactive weights are equal."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from nodes.fit.photometric import PhotoSamples, PhotoTerm  # noqa: E402
from nodes.fit.views import FitViews, at_anchors  # noqa: E402


def _plain(values: torch.Tensor, vertices: torch.Tensor, bary: torch.Tensor) -> torch.Tensor:
    """Each shape's corners gathered on their own and summed in corner order: (B, C, L, K, 3)."""
    out = []
    for k in range(values.shape[0]):
        c = values[k][vertices]  # (B, C, L, 3, 3)
        out.append(c[..., 0, :] * bary[..., 0, None] + c[..., 1, :] * bary[..., 1, None]
                   + c[..., 2, :] * bary[..., 2, None])
    return torch.stack(out, -2)


def _anchors(v: int, shape: tuple[int, ...], seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    vertices = torch.randint(0, v, (*shape, 3), generator=g)
    bary = torch.rand(*shape, 3, generator=g, dtype=torch.float64).to(torch.float32)
    return vertices, bary / bary.sum(-1, keepdim=True)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_at_anchors_is_the_plain_weighted_sum_bit_for_bit(dtype):
    g = torch.Generator().manual_seed(1)
    values = (torch.randn(7, 500, 3, generator=g, dtype=torch.float64) * 2.0).to(dtype)
    vertices, bary = _anchors(500, (2, 3, 41), 2)
    bary = bary.to(dtype)
    got = at_anchors(values, vertices, bary)
    assert got.shape == (2, 3, 41, 7, 3)
    assert torch.equal(got, _plain(values, vertices, bary))
    assert torch.equal(at_anchors(values, vertices, bary), got)  # again, from the cached rows
    neutral = values[0]
    ref = (neutral[vertices] * bary[..., None]).sum(-2)  # the one-vector case: 3 terms, summed in order
    assert torch.equal(at_anchors(neutral, vertices, bary), ref)


def test_at_anchors_sees_an_in_place_change_and_passes_gradients():
    g = torch.Generator().manual_seed(3)
    values = torch.randn(4, 60, 3, generator=g)
    vertices, bary = _anchors(60, (1, 1, 9), 4)
    first = at_anchors(values, vertices, bary)
    values[:, vertices[0, 0, 0, 0]] += 1.0  # an in-place edit of an anchored vertex
    second = at_anchors(values, vertices, bary)
    assert not torch.equal(first, second)
    assert torch.equal(second, _plain(values, vertices, bary))
    leaf = values.clone().requires_grad_(True)
    out = at_anchors(leaf, vertices, bary)
    out.sum().backward()
    expected = torch.zeros(60).index_add_(0, vertices.reshape(-1), bary.reshape(-1))  # each vertex's total weight
    torch.testing.assert_close(leaf.grad, expected[None, :, None].expand(4, 60, 3))


def test_photo_term_cache_is_reused_only_for_equal_inactive_weights():
    g = torch.Generator().manual_seed(5)
    b, n, k, s = 2, 30, 6, 16
    samples = PhotoSamples(torch.zeros(b, 1, n, 3, dtype=torch.long), torch.full((b, 1, n, 3), 1 / 3),
                           torch.rand(b, 1, n, 3, generator=g), torch.full((b, 1, n), 1 / n),
                           torch.rand(b, s, s, 3, generator=g), s, torch.randn(b, 1, n, 3, generator=g),
                           torch.randn(b, 1, n, k, 3, generator=g))
    views = FitViews(torch.zeros(b, 1, 68, 2), torch.tensor([[[0.0, 0.0, 16.0, 16.0]]]).expand(b, 1, 4),
                     torch.ones(b, 1, dtype=torch.bool), torch.eye(4)[None], torch.tensor([[20.0, 20.0, 8.0, 8.0]]),
                     None, torch.tensor([[16.0, 16.0]]))
    active = [1, 3]
    basis = samples.deltas[:, :, :, active].transpose(-1, -2)
    weights = torch.rand(b, k, generator=g)
    cache: dict = {}
    first = PhotoTerm.about(samples, views, 500.0, weights, active, basis, cache=cache)
    moved = weights.clone()
    moved[:, active] += 0.25  # only the active weights move: the same term
    assert PhotoTerm.about(samples, views, 500.0, moved, active, basis, cache=cache) is first
    other = weights.clone()
    other[0, 0] += 0.25  # an inactive weight moved: a new term, as without the cache
    fresh = PhotoTerm.about(samples, views, 500.0, other, active, basis, cache=cache)
    assert fresh is not first
    assert torch.equal(fresh.local0, PhotoTerm.about(samples, views, 500.0, other, active, basis).local0)
    assert not torch.equal(fresh.local0, first.local0)
