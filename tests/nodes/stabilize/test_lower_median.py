"""`robust.lower_median` (numpy partition on the CPU) against `torch.median` (lower middle)."""

from __future__ import annotations

import pytest
import torch

from nodes.stabilize.robust import lower_median


@pytest.mark.parametrize("frames", [1, 2, 7, 10])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_lower_median_is_torch_median(frames: int, dtype: torch.dtype):
    gen = torch.Generator().manual_seed(frames)
    x = torch.randn(frames, 3, 50, generator=gen, dtype=dtype)
    x[:, 0, 0] = 1.0  # ties
    for dim in (0, 1, 2, -1):
        assert torch.equal(lower_median(x, dim=dim), x.median(dim=dim).values)
    assert torch.equal(lower_median(x), x.median())
    strided = x.permute(2, 0, 1)  # a non-contiguous view
    assert torch.equal(lower_median(strided, dim=1), strided.median(dim=1).values)
    assert lower_median(x, dim=0).dtype == dtype


def test_lower_median_keeps_the_gradient_path():
    x = torch.randn(5, 4, requires_grad=True)
    lower_median(x, dim=0).sum().backward()  # torch.median: differentiable
    assert x.grad is not None and float(x.grad.sum()) == 4.0
