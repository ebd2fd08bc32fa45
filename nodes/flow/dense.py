"""Differentiable dense optical flow in torch: coarse-to-fine robust Horn-Schunck with warping.

Model (per pyramid level, per warp; Horn and Schunck 1981 with the coarse-to-fine warping of
Brox et al. 2004 and a lagged Charbonnier data weight, "Secrets of optical flow", Sun et al.
2010)::

    E(u) = sum_x c(x) psi(I2(x + u) - I1(x)) + alpha^2 sum_x |grad u|^2 + |grad v|^2

`I2(x + u)` is linearized about the current flow `u0` (I2 warped by `u0`, bilinear), the
robust weight `c / sqrt(rho^2 + eps^2)` is frozen for the warp, and the Euler-Lagrange
equations are relaxed by a fixed number of Jacobi iterations
`u <- ubar - Ix (Ix (ubar - u0) + Iy (vbar - v0) + It) w / (alpha^2 + w (Ix^2 + Iy^2))`
(`ubar` the 8-neighbour average, weights 1/6 edges, 1/12 corners). A separable 3x3 median filter
of the flow follows each level (it removes the outliers warping leaves, and is differentiable
almost everywhere). Pixels whose warped position leaves the image get no data term.

Every count (levels, warps, iterations) is fixed, so the flow is a plain differentiable
function of both images: gradients reach `image1` and `image2` through the warps, the image
gradients and the updates. Images are converted to luminance and, per pair, scaled by a
common robust contrast (so `alpha` does not depend on exposure).

Conventions: images (B, C, H, W) float, any linear scale; flow (B, 2, H, W) pixels, channel
0 = x (right), 1 = y (down); `flow[b, :, y, x]` maps pixel (x, y) of image1 to
`(x, y) + flow` in image2 (`image1(p) ~ image2(p + flow(p))`). Pixel centres at integers.

This module imports torch at the top: import it from node `run()` methods only.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from ..geometry.image import pyramid_down, resize_bilinear, sample_bilinear

__all__ = ["FlowSettings", "chebyshev_weights", "dense_flow", "upsample_flow", "warp_image", "luminance", "endpoint_error"]


class FlowSettings(NamedTuple):
    """Parameters of `dense_flow`.

    Attributes:
        alpha: smoothness weight, in units of the normalized intensity (contrast ~ 1).
        levels: pyramid levels at most (each halves the size; stops at `min_size`).
        min_size: smallest side of the coarsest level, pixels.
        warps: warps per level, but the finest.
        finest_warps: warps at the finest level when it has more than `FEW_WARPS_PIXELS`
            (128^2) pixels: the motion is mostly found on the coarser levels, and the finest
            costs 4x the next (at 256^2: 2 warps, 0.80 px end-point error, 8 warps 0.71 px in
            1.6x the time). Smaller images keep `warps` there (cheap, and their small faces
            need them).
        iterations: Jacobi iterations per warp at the coarsest level.
        acceleration: the largest eigenvalue assumed for the Jacobi iteration (the Chebyshev
            acceleration's upper bound, `chebyshev_weights`); 0 is plain Jacobi.
        finest_iterations: Jacobi iterations per warp at the finest level (levels in between
            interpolate geometrically; the finest level is the costly one).
        eps: Charbonnier epsilon of the data term, normalized intensity.
        median: 3x3 median filter of the flow after each level (or warp).
        median_every_warp: filter after every warp rather than once per level.
        skip_levels: finest pyramid levels not solved: the flow of the finest solved level is
            upsampled (bilinear) to the full size (1: a quarter of the work, coarser flow).
    """

    alpha: float = 0.06
    levels: int = 5
    min_size: int = 12
    warps: int = 6
    iterations: int = 12
    finest_iterations: int = 6
    eps: float = 0.01
    median: bool = True
    median_every_warp: bool = False
    skip_levels: int = 0
    finest_warps: int = 2
    acceleration: float = 0.99


JACOBI_LOWEST_EIGENVALUE = -1.0 / 3.0
"""The smallest eigenvalue of the 8-neighbour average (`(2 + 2 cos a)(2 + 2 cos b) - 4) / 12` at
a = b = pi): the lower end of the Chebyshev interval of the Jacobi iteration."""


def chebyshev_weights(iterations: int, highest: float,
                      lowest: float = JACOBI_LOWEST_EIGENVALUE) -> tuple[list[float], float]:
    """Chebyshev semi-iteration for a Jacobi iteration `x <- J(x)` whose iteration matrix has its
    eigenvalues in [lowest, highest] (Golub and Varga 1961; Saad, Iterative Methods, 12.3):
    `x_k+1 = omega_k+1 (gamma J(x_k) + (1 - gamma) x_k - x_k-1) + x_k-1`, `x_-1 = x_0`.

    Args:
        iterations: number of sweeps.
        highest: the largest eigenvalue assumed, < 1 (0 with `lowest` 0: plain Jacobi).
        lowest: the smallest eigenvalue assumed.
    Returns:
        (omegas, gamma): the extrapolation of each sweep (the first 1) and the shift `gamma`
        = 2 / (2 - lowest - highest) that centres the interval.

    Example:
        >>> chebyshev_weights(3, 0.0, 0.0)
        ([1.0, 1.0, 1.0], 1.0)
    """
    if not lowest <= highest < 1.0:
        raise ValueError(f"acceleration: expected {lowest:.3f} <= highest eigenvalue < 1, found {highest}")
    if highest == 0.0 and lowest == 0.0:
        return [1.0] * iterations, 1.0
    sigma = (highest - lowest) / (2.0 - lowest - highest)
    omegas: list[float] = []
    omega = 1.0
    for k in range(iterations):
        omega = 1.0 if k == 0 else (1.0 / (1.0 - 0.5 * sigma * sigma) if k == 1
                                    else 1.0 / (1.0 - 0.25 * sigma * sigma * omega))
        omegas.append(omega)
    return omegas, 2.0 / (2.0 - lowest - highest)


def luminance(images: Tensor) -> Tensor:
    """(B, C, H, W) -> (B, 1, H, W): Rec. 709 luma for C = 3, the channel mean otherwise."""
    if images.shape[1] == 3:
        w = torch.tensor([0.2126, 0.7152, 0.0722], dtype=images.dtype, device=images.device)
        return (images * w[:, None, None]).sum(1, keepdim=True)
    return images.mean(1, keepdim=True)


def _base_grid(height: int, width: int, like: Tensor) -> Tensor:
    ys = torch.arange(height, dtype=like.dtype, device=like.device)
    xs = torch.arange(width, dtype=like.dtype, device=like.device)
    gy, gx = torch.meshgrid(ys, xs, indexing="ij")
    return torch.stack([gx, gy])[None]  # (1, 2, H, W)


def warp_image(image: Tensor, flow: Tensor) -> tuple[Tensor, Tensor]:
    """Sample `image` at `p + flow(p)` (bilinear, border clamped).

    Args:
        image: (B, C, H, W).
        flow: (B, 2, H, W) pixels (x, y).
    Returns:
        warped (B, C, H, W) and inside (B, 1, H, W) float: 1 where the sample lies within the
        image (pixel centres 0..W-1, 0..H-1), else 0.
    """
    _, _, h, w = image.shape
    pos = _base_grid(h, w, flow) + flow
    warped = sample_bilinear(image.permute(0, 2, 3, 1), pos.permute(0, 2, 3, 1), padding="border",
                             method="grid_sample")
    inside = ((pos[:, 0] >= 0) & (pos[:, 0] <= w - 1) & (pos[:, 1] >= 0) & (pos[:, 1] <= h - 1))
    return warped.permute(0, 3, 1, 2), inside[:, None].to(image.dtype)


def _gradients(image: Tensor) -> tuple[Tensor, Tensor]:
    # 5-point central differences (1, -8, 0, 8, -1) / 12, replicate borders
    k = torch.tensor([1.0, -8.0, 0.0, 8.0, -1.0], dtype=image.dtype, device=image.device) / 12.0
    gx = F.conv2d(F.pad(image, (2, 2, 0, 0), mode="replicate"), k.view(1, 1, 1, 5))
    gy = F.conv2d(F.pad(image, (0, 0, 2, 2), mode="replicate"), k.view(1, 1, 5, 1))
    return gx, gy


def _sum121(x: Tensor, dim: int) -> Tensor:
    # x_{i-1} + 2 x_i + x_{i+1} along dim, replicate borders (slices, no padding copies)
    n = x.shape[dim]
    out = 2.0 * x
    out.narrow(dim, 1, n - 1).add_(x.narrow(dim, 0, n - 1))
    out.narrow(dim, 0, 1).add_(x.narrow(dim, 0, 1))
    out.narrow(dim, 0, n - 1).add_(x.narrow(dim, 1, n - 1))
    out.narrow(dim, n - 1, 1).add_(x.narrow(dim, n - 1, 1))
    return out


def _neighbour_average(flow: Tensor) -> Tensor:
    # 8-neighbour average, weights 2/12 edges and 1/12 corners = ([1 2 1]^T [1 2 1] - 4 delta) / 12
    return (_sum121(_sum121(flow, 3), 2) - 4.0 * flow) * (1.0 / 12.0)


def _median3_1d(x: Tensor, dim: int) -> Tensor:
    n = x.shape[dim]
    prev = torch.cat([x.narrow(dim, 0, 1), x.narrow(dim, 0, n - 1)], dim)
    nxt = torch.cat([x.narrow(dim, 1, n - 1), x.narrow(dim, n - 1, 1)], dim)
    return torch.maximum(torch.minimum(prev, x), torch.minimum(torch.maximum(prev, x), nxt))


def _median3(flow: Tensor) -> Tensor:
    # separable 3x3 median (median of 3 along x, then along y): a cheap, edge-preserving
    # stand-in for the full 3x3 median (9x fewer comparisons, no sort)
    return _median3_1d(_median3_1d(flow, 3), 2)


def _iterations_at(level: int, levels: int, s: FlowSettings) -> int:
    if levels <= 1:
        return s.finest_iterations
    t = level / (levels - 1)  # 0 finest, 1 coarsest
    return max(1, round(s.finest_iterations * (s.iterations / s.finest_iterations) ** t))


FEW_WARPS_PIXELS = 128 * 128
"""A finest level with more pixels than this gets `finest_warps` warps (smaller: `warps`)."""


def _warps_at(level: int, pixels: int, s: FlowSettings) -> int:
    return s.finest_warps if level == 0 and pixels > FEW_WARPS_PIXELS else s.warps


def dense_flow(image1: Tensor, image2: Tensor, settings: FlowSettings = FlowSettings(),
               init: Tensor | None = None) -> Tensor:
    """Estimate the flow from image1 to image2 (see the module docstring for the model).

    Args:
        image1, image2: (B, C, H, W) float, same shape; colour is reduced to luminance.
        settings: counts and weights (`FlowSettings`).
        init: (B, 2, H, W) initial flow at full resolution, pixels, or None (zero).
    Returns:
        (B, 2, H, W) flow, pixels (x right, y down), same dtype/device; differentiable in
        both images (and `init`).
    Raises:
        ValueError: for images of different or non-4D shapes.

    Example:
        >>> img = torch.rand(1, 1, 32, 32)
        >>> dense_flow(img, img).abs().max().item() < 1e-4
        True
    """
    if image1.ndim != 4 or image1.shape != image2.shape:
        raise ValueError(f"image1, image2: expected two (B, C, H, W) tensors of one shape, found "
                         f"{tuple(image1.shape)} and {tuple(image2.shape)}")
    s = settings
    i1, i2 = luminance(image1), luminance(image2)
    # common contrast normalization per pair (robust: mean absolute deviation)
    mean = 0.5 * (i1.mean((1, 2, 3), keepdim=True) + i2.mean((1, 2, 3), keepdim=True))
    scale = 0.5 * ((i1 - mean).abs().mean((1, 2, 3), keepdim=True)
                   + (i2 - mean).abs().mean((1, 2, 3), keepdim=True)).clamp_min(1e-6)
    i1, i2 = (i1 - mean) / scale * 0.25, (i2 - mean) / scale * 0.25
    pyr1, pyr2 = [i1], [i2]
    while len(pyr1) < s.levels and min(pyr1[-1].shape[-2:]) // 2 >= s.min_size:
        pyr1.append(pyramid_down(pyr1[-1].permute(0, 2, 3, 1)).permute(0, 3, 1, 2))
        pyr2.append(pyramid_down(pyr2[-1].permute(0, 2, 3, 1)).permute(0, 3, 1, 2))
    levels = len(pyr1)
    b = image1.shape[0]
    flow = None
    last = min(max(s.skip_levels, 0), levels - 1)
    for level in range(levels - 1, last - 1, -1):
        a1, a2 = pyr1[level], pyr2[level]
        h, w = a1.shape[-2:]
        if flow is None:
            if init is None:
                flow = a1.new_zeros(b, 2, h, w)
            else:
                f = 2.0 ** -level
                flow = resize_bilinear(init.permute(0, 2, 3, 1), (h, w)).permute(0, 3, 1, 2) * f
        else:
            flow = upsample_flow(flow, (h, w))
        iters = _iterations_at(level, levels, s)
        for _ in range(_warps_at(level, h * w, s)):
            warped, inside = warp_image(a2, flow)
            gx2, gy2 = _gradients(warped)
            gx1, gy1 = _gradients(a1)
            ix, iy = 0.5 * (gx1 + gx2), 0.5 * (gy1 + gy2)
            it = warped - a1
            weight = inside * s.eps / torch.sqrt(it * it + s.eps * s.eps)  # lagged Charbonnier, 1 at 0
            grad = torch.cat([ix, iy], 1)
            step = grad * (weight / (s.alpha * s.alpha + weight * (ix * ix + iy * iy)))
            const = it - (grad * flow).sum(1, keepdim=True)
            omegas, gamma = chebyshev_weights(iters, s.acceleration, *(() if s.acceleration else (0.0,)))
            prev = flow
            for omega in omegas:
                avg = _neighbour_average(flow)
                jacobi = gamma * (avg - step * ((grad * avg).sum(1, keepdim=True) + const)) + (1.0 - gamma) * flow
                flow, prev = omega * (jacobi - prev) + prev, flow
            if s.median and s.median_every_warp:
                flow = _median3(flow)
        if s.median and not s.median_every_warp:
            flow = _median3(flow)
    return upsample_flow(flow, image1.shape[-2:])


def upsample_flow(flow: Tensor, size: tuple[int, int]) -> Tensor:
    """(B, 2, h, w) flow -> (B, 2, H, W): bilinear, vectors scaled by the size ratio."""
    h, w = int(size[0]), int(size[1])
    if flow.shape[-2:] == (h, w):
        return flow
    sy, sx = h / flow.shape[2], w / flow.shape[3]
    flow = resize_bilinear(flow.permute(0, 2, 3, 1), (h, w)).permute(0, 3, 1, 2)
    return flow * torch.tensor([sx, sy], dtype=flow.dtype, device=flow.device).view(1, 2, 1, 1)


def endpoint_error(flow: Tensor, truth: Tensor, mask: Tensor | None = None) -> Tensor:
    """Mean end-point error `|flow - truth|` over the (masked) pixels, per batch element.

    Args:
        flow, truth: (B, 2, H, W) pixels.
        mask: (B, H, W) bool or None (all pixels).
    Returns:
        (B,) mean EPE, pixels.
    """
    err = (flow - truth).norm(dim=1)
    if mask is None:
        return err.mean((1, 2))
    m = mask.to(err.dtype)
    return (err * m).sum((1, 2)) / m.sum((1, 2)).clamp_min(1)
