"""The heatmap head of the paper (soft-argmax on a 3x3 patch) and the landmark-network interface.

Deep energies (paper 2, eq. 3): for heatmap `H_i`, take the argmax `m_i`, then the
soft-argmax over the patch `M_i` of pixels around it:
`m^_i = sum_{m in M_i} m exp(beta H_i(m)) / sum_{m in M_i} exp(beta H_i(m))`, beta = 50.
The argmax is discrete (no gradient); the weighted mean is differentiable in the heatmap
values, hence in the network input.

A landmark network, for the nodes of `nodes.landmarks`, is any callable with attributes
`input_size` (S, the square crop side in pixels) and `num_points` (L), taking crops
(B, S, S, 3) float RGB in [0, 1] (sRGB-encoded, NHWC) and returning `(points, presence)`:
points (B, L, 2) in crop pixels with 0 at the crop's top-left corner (pixel j's centre at
j + 0.5), presence (B,) in [0, 1]. `MediaPipeFaceMesh` (`nodes.landmarks.network`) is one;
`HeatmapLandmarks` adapts a user's heatmap network (3D-FAN style: NCHW input, (B, L, h, w)
heatmaps) to it.

This module imports torch at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

from typing import Callable, Protocol

import torch
from torch import Tensor, nn

__all__ = ["LandmarkNetwork", "soft_argmax_patch", "HeatmapLandmarks"]


class LandmarkNetwork(Protocol):
    """What the landmark nodes call (see the module docstring)."""

    input_size: int
    num_points: int

    def __call__(self, crops: Tensor) -> tuple[Tensor, Tensor]: ...


def soft_argmax_patch(heatmaps: Tensor, beta: float = 50.0, patch: int = 3) -> Tensor:
    """Soft-argmax of each heatmap over a `patch` x `patch` window around its maximum.

    Args:
        heatmaps: (..., h, w) heatmap values.
        beta: inverse temperature (the paper: 50).
        patch: odd window side, pixels (the paper: 3). Pixels of the window outside the
            heatmap are left out.
    Returns:
        (..., 2) (x, y) in heatmap pixels, pixel centres at integers, x to the right, y down;
        differentiable in `heatmaps` (the argmax itself is not).

    Example:
        >>> h = torch.zeros(5, 5); h[2, 3] = 1.0; h[2, 4] = 1.0
        >>> soft_argmax_patch(h).tolist()
        [3.5, 2.0]
    """
    if patch < 1 or patch % 2 == 0:
        raise ValueError(f"patch: expected an odd window side >= 1, found {patch}")
    if heatmaps.ndim < 2:
        raise ValueError(f"heatmaps: expected shape (..., h, w), found {tuple(heatmaps.shape)}")
    *batch, h, w = heatmaps.shape
    flat = heatmaps.reshape(-1, h, w)
    index = flat.reshape(len(flat), -1).argmax(-1)
    cy, cx = index // w, index % w
    r = patch // 2
    offsets = torch.arange(-r, r + 1, device=heatmaps.device)
    ys = (cy[:, None] + offsets[None]).reshape(-1, patch, 1).expand(-1, patch, patch)
    xs = (cx[:, None] + offsets[None]).reshape(-1, 1, patch).expand(-1, patch, patch)
    inside = (ys >= 0) & (ys < h) & (xs >= 0) & (xs < w)
    rows = torch.arange(len(flat), device=heatmaps.device)[:, None, None].expand_as(ys)
    values = flat[rows, ys.clamp(0, h - 1), xs.clamp(0, w - 1)]
    logits = torch.where(inside, beta * values, torch.full_like(values, float("-inf")))
    weights = torch.softmax(logits.reshape(len(flat), -1), -1).reshape(values.shape)
    x = (weights * xs.to(values.dtype)).sum((-1, -2))
    y = (weights * ys.to(values.dtype)).sum((-1, -2))
    return torch.stack([x, y], -1).reshape(*batch, 2)


class HeatmapLandmarks(nn.Module):
    """Adapt a heatmap network (3D-FAN style) to the landmark-network interface.

    Args:
        network: module mapping (B, 3, S, S) RGB in [0, 1] (or as `normalize` makes it) to
            heatmaps (B, L, h, w) (a tuple/list output: its last element, as stacked
            hourglasses return).
        input_size: S, crop side in pixels (3D-FAN: 256).
        beta, patch: of `soft_argmax_patch` (the paper: 50, 3).
        normalize: optional function applied to the NCHW crop before the network.
        presence: optional function heatmaps -> (B,) presence in [0, 1]; default: the mean
            over landmarks of the heatmap maxima, clipped to [0, 1].

    Call: crops (B, S, S, 3) -> points (B, L, 2) in crop pixels (0 at the top-left corner:
    heatmap pixel centre m maps to (m + 1/2) S / h, the paper's 4 m^ for 64 -> 256 up to the
    half-pixel convention), presence (B,).
    """

    def __init__(self, network: nn.Module, input_size: int = 256, *, beta: float = 50.0, patch: int = 3,
                 normalize: Callable[[Tensor], Tensor] | None = None,
                 presence: Callable[[Tensor], Tensor] | None = None):
        super().__init__()
        self.network = network
        self.input_size = int(input_size)
        self.beta, self.patch = float(beta), int(patch)
        self.normalize = normalize
        self.presence_fn = presence
        self.num_points = -1  # known after the first call

    def forward(self, crops: Tensor) -> tuple[Tensor, Tensor]:
        if crops.ndim != 4 or crops.shape[1] != self.input_size or crops.shape[2] != self.input_size:
            raise ValueError(f"crops: expected shape (B, {self.input_size}, {self.input_size}, 3), found "
                             f"{tuple(crops.shape)}")
        x = crops.permute(0, 3, 1, 2)
        if self.normalize is not None:
            x = self.normalize(x)
        heatmaps = self.network(x)
        if isinstance(heatmaps, (tuple, list)):
            heatmaps = heatmaps[-1]
        if heatmaps.ndim != 4:
            raise ValueError(f"heatmap network: expected heatmaps (B, L, h, w), found {tuple(heatmaps.shape)}")
        self.num_points = int(heatmaps.shape[1])
        m = soft_argmax_patch(heatmaps, self.beta, self.patch)
        scale = torch.tensor([self.input_size / heatmaps.shape[3], self.input_size / heatmaps.shape[2]],
                             dtype=m.dtype, device=m.device)
        points = (m + 0.5) * scale
        if self.presence_fn is not None:
            presence = self.presence_fn(heatmaps)
        else:
            presence = heatmaps.flatten(2).amax(-1).mean(-1).clamp(0.0, 1.0)
        return points, presence

