"""Image sampling, crops and filters on batched tensors (torch), channels last.

Conventions: images are (B, H, W, C) float tensors, channels last (the layout of the
project's frames, renders and crops; a (B, C, H, W) caller permutes, which copies nothing).
Pixel centres lie at integer coordinates, origin top-left, x to the right, y down: pixel
(i, j) covers `[j - 1/2, j + 1/2] x [i - 1/2, i + 1/2]` and the whole image is
`[-1/2, W - 1/2] x [-1/2, H - 1/2]`. A crop box is `(x0, y0, x1, y1)` in those coordinates,
the crop covering `[x0, x1] x [y0, y1]`; crop pixel j (of S) has its centre at
`x0 + (j + 1/2) (x1 - x0) / S`.

- `sample_bilinear`: bilinear samples at pixel coordinates, outside the image either clamped
  to the border or zero; by gathers (forward-mode autodiff goes through it, and its
  derivative in x and y comes on request) or by torch's fused `grid_sample` (faster).
- `resize_bilinear`: resize to a given size (torch's `interpolate`, pixel-centre aligned,
  optionally antialiased when shrinking).
- `box_downsample`: mean over k x k blocks (the image padded with zeros to a multiple of k).
- `separable_filter`, `gaussian_kernel`, `gaussian_blur`, `pyramid_down`: separable
  convolutions with replicated edges; one level of a Gaussian pyramid (binomial 1-4-6-4-1).
- `crop_and_resize`: crop (possibly turned) boxes and resize them to S x S, bilinearly, with
  a k x k box filter first when the box is k >= 2 times larger than S (no aliasing).
- `crop_to_image`, `image_to_crop`, `crop_intrinsics`: the coordinate maps of a crop box.

Not a node area: imports torch at the top and nothing else of `nodes`; import it from node
`run()` methods only.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["Padding", "Method", "sample_bilinear", "sample_separable", "resize_bilinear", "box_downsample", "separable_filter", "gaussian_kernel",
           "gaussian_blur", "pyramid_down", "crop_and_resize", "crop_to_image", "image_to_crop", "crop_intrinsics"]

Padding = Literal["border", "zeros"]
Method = Literal["gather", "grid_sample"]

_BINOMIAL = (1.0, 4.0, 6.0, 4.0, 1.0)


def _check_images(images: Tensor, name: str = "images") -> None:
    if not isinstance(images, Tensor) or images.ndim != 4:
        found = tuple(images.shape) if isinstance(images, Tensor) else type(images).__name__
        raise ValueError(f"{name}: expected a tensor of shape (B, H, W, C), found {found}")


def sample_bilinear(images: Tensor, xy: Tensor, *, padding: Padding = "border", gradient: bool = False,
                    method: Method = "gather") -> Tensor | tuple[Tensor, Tensor]:
    """Sample images bilinearly at pixel coordinates (differentiable in the pixels and in xy).

    Args:
        images: (N, H, W, C) float.
        xy: (N, ..., 2) float pixel coordinates x, y (centres at integers, see the module
            docstring).
        padding: "border": coordinates are clamped into `[0, W - 1] x [0, H - 1]` (the
            image's edge pixels extend outwards); "zeros": pixels outside the image are 0, so
            a sample fades to 0 over the half pixel beyond the outer centres.
        gradient: also return the samples' derivative in x and y (with "border", 0 along an
            axis where that coordinate is clamped); "gather" only.
        method: "gather": written with gathers and elementwise arithmetic, so forward-mode
            autodiff (`torch.func.jvp`, `jacfwd`) goes through it, and `gradient` is
            available. "grid_sample": torch's fused `grid_sample` kernel (at `align_corners`
            True for "border", False for "zeros", each the exact identity on pixel
            coordinates), reverse-mode autodiff only, several times faster (`python
            bench/image.py` prints both). The two agree to float rounding (a few units in the
            last place).
    Returns:
        (N, ..., C) samples, and with `gradient` (N, ..., C, 2) their derivative in x and y,
        per pixel.

    Raises:
        ValueError: `images` is not 4-D, `xy` is not (N, ..., 2), `padding` or `method` is
            unknown, or `gradient` is asked of "grid_sample".
    Note:
        On a 1-pixel axis with "border" the sample is that pixel's value and its derivative 0.
    """
    _check_images(images)
    if xy.ndim < 2 or xy.shape[0] != images.shape[0] or xy.shape[-1] != 2:
        raise ValueError(f"xy: expected shape ({images.shape[0]}, ..., 2), found {tuple(xy.shape)}")
    if padding not in ("border", "zeros"):
        raise ValueError(f"padding: expected 'border' or 'zeros', found {padding!r}")
    if method not in ("gather", "grid_sample"):
        raise ValueError(f"method: expected 'gather' or 'grid_sample', found {method!r}")
    if method == "grid_sample":
        if gradient:
            raise ValueError("gradient: the samples' derivative is computed by method='gather' only, found "
                             "method='grid_sample'")
        return _sample_grid(images, xy, padding)
    n, h, w, c = images.shape
    batch_shape = xy.shape[1:-1]
    xy = xy.reshape(n, -1, 2)
    flat = images.reshape(n, h * w, c)

    def at(yy: Tensor, xx: Tensor) -> Tensor:
        return torch.gather(flat, 1, (yy * w + xx)[..., None].expand(*xx.shape, c))

    if padding == "border":
        x = xy[..., 0].clamp(0.0, w - 1.0)
        y = xy[..., 1].clamp(0.0, h - 1.0)
        x0 = torch.floor(x).clamp(0, w - 2) if w > 1 else torch.zeros_like(x)
        y0 = torch.floor(y).clamp(0, h - 2) if h > 1 else torch.zeros_like(y)
        fx, fy = (x - x0)[..., None], (y - y0)[..., None]
        xi, yi = x0.long(), y0.long()
        dx, dy = int(w > 1), int(h > 1)
        c00, c01, c10, c11 = at(yi, xi), at(yi, xi + dx), at(yi + dy, xi), at(yi + dy, xi + dx)
    else:
        x0, y0 = torch.floor(xy[..., 0]), torch.floor(xy[..., 1])
        fx, fy = (xy[..., 0] - x0)[..., None], (xy[..., 1] - y0)[..., None]
        # corners masked when outside; indices first clamped to [-2, W] (both corners of a
        # sample beyond the image stay outside; no integer overflow), then into it for the gather
        xi, yi = x0.clamp(-2, w).long(), y0.clamp(-2, h).long()
        zero = images.new_zeros(())

        def corner(yy: Tensor, xx: Tensor) -> Tensor:
            valid = ((xx >= 0) & (xx < w) & (yy >= 0) & (yy < h))[..., None]
            return torch.where(valid, at(yy.clamp(0, h - 1), xx.clamp(0, w - 1)), zero)

        c00, c01, c10, c11 = corner(yi, xi), corner(yi, xi + 1), corner(yi + 1, xi), corner(yi + 1, xi + 1)
    top = c00 + (c01 - c00) * fx
    bottom = c10 + (c11 - c10) * fx
    value = top + (bottom - top) * fy
    if not gradient:
        return value.reshape(n, *batch_shape, c)
    d_x = (c01 - c00) * (1 - fy) + (c11 - c10) * fy
    d_y = bottom - top
    if padding == "border":
        inside_x = ((xy[..., 0] >= 0) & (xy[..., 0] <= w - 1) & (w > 1)).to(images.dtype)[..., None]
        inside_y = ((xy[..., 1] >= 0) & (xy[..., 1] <= h - 1) & (h > 1)).to(images.dtype)[..., None]
        d_x, d_y = d_x * inside_x, d_y * inside_y
    return value.reshape(n, *batch_shape, c), torch.stack([d_x, d_y], -1).reshape(n, *batch_shape, c, 2)


def _sample_grid(images: Tensor, xy: Tensor, padding: Padding) -> Tensor:
    """`sample_bilinear` by torch's `grid_sample` (see there)."""
    n, h, w, c = images.shape
    grid = xy if xy.ndim == 4 else xy.reshape(n, 1, -1, 2)
    x, y = grid[..., 0], grid[..., 1]
    if padding == "border":  # align_corners=True: -1 and 1 are the outer pixel centres
        grid = torch.stack([2.0 * x / max(w - 1, 1) - 1.0, 2.0 * y / max(h - 1, 1) - 1.0], -1)
    else:  # align_corners=False: -1 and 1 are the image's outer edges
        grid = torch.stack([(x + 0.5) / w * 2 - 1, (y + 0.5) / h * 2 - 1], -1)
    out = F.grid_sample(images.permute(0, 3, 1, 2), grid, mode="bilinear", padding_mode=padding,
                        align_corners=padding == "border")
    return out.permute(0, 2, 3, 1).reshape(*xy.shape[:-1], c)


def sample_separable(images: Tensor, xs: Tensor, ys: Tensor) -> Tensor:
    """Bilinear samples on a separable grid: output pixel (i, j) of image n is the image at
    (`xs[n, j]`, `ys[n, i]`), pixel coordinates (centres at integers); pixels outside the image
    are 0 ("zeros" padding of `sample_bilinear`). Interpolates along y, then along x.

    Each sample depends only on its coordinates and the pixels around them, not on the image's
    size (`grid_sample` normalizes coordinates by the size, which rounds differently for each
    size: a fit's renders, whose side is the largest box of the batch, differed by 1.7e-6
    between batches). Differentiable in the pixels (not in xs, ys).

    Args:
        images: (N, H, W, C) float.
        xs: (N, S_x) x coordinates of the output columns; ys: (N, S_y) y of the output rows.
    Returns:
        (N, S_y, S_x, C).
    """
    _check_images(images)
    n, h, w, c = images.shape
    if xs.ndim != 2 or ys.ndim != 2 or xs.shape[0] != n or ys.shape[0] != n:
        raise ValueError(f"xs, ys: expected shapes ({n}, S_x) and ({n}, S_y), found {tuple(xs.shape)} and "
                         f"{tuple(ys.shape)}")

    def taps(t: Tensor, size: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        lo = torch.floor(t)
        frac = (t - lo).to(images.dtype)
        i0 = lo.long()
        w0 = torch.where((i0 >= 0) & (i0 < size), 1 - frac, torch.zeros_like(frac))
        w1 = torch.where((i0 + 1 >= 0) & (i0 + 1 < size), frac, torch.zeros_like(frac))
        return i0.clamp(0, size - 1), (i0 + 1).clamp(0, size - 1), w0, w1

    y0, y1, wy0, wy1 = taps(ys, h)
    x0, x1, wx0, wx1 = taps(xs, w)
    rows = torch.arange(n, device=images.device)[:, None]
    along_y = images[rows, y0] * wy0[..., None, None] + images[rows, y1] * wy1[..., None, None]  # (N, S_y, W, C)

    def columns(x: Tensor) -> Tensor:  # (N, S_y, S_x, C): along_y's columns x (N, S_x)
        return along_y.gather(2, x[:, None, :, None].expand(n, ys.shape[1], xs.shape[1], c))

    return columns(x0) * wx0[:, None, :, None] + columns(x1) * wx1[:, None, :, None]


def resize_bilinear(images: Tensor, size: tuple[int, int], *, antialias: bool = False) -> Tensor:
    """Resize images to (H', W') bilinearly, pixel-centre aligned (torch's `interpolate`).

    Output pixel (i, j) samples the input at `((j + 1/2) W / W' - 1/2, (i + 1/2) H / H' - 1/2)`,
    clamped to the border; `antialias` widens the filter to the shrink factor when shrinking
    (area-weighted, so fine detail does not alias).

    Args:
        images: (B, H, W, C) float.
        size: (H', W') pixels, each >= 1.
        antialias: low-pass filter when shrinking (no effect when enlarging).
    Returns:
        (B, H', W', C).
    """
    _check_images(images)
    h, w = int(size[0]), int(size[1])
    if h < 1 or w < 1:
        raise ValueError(f"size: expected (H', W') >= 1, found {tuple(size)}")
    nchw = images.permute(0, 3, 1, 2)
    return F.interpolate(nchw, size=(h, w), mode="bilinear", antialias=antialias, align_corners=False).permute(0, 2, 3, 1)


def box_downsample(images: Tensor, k: int) -> Tensor:
    """Mean over k x k blocks: output pixel (i, j) is the mean of input rows k i .. k i + k - 1
    and columns k j .. k j + k - 1.

    An image whose side is not a multiple of k is padded with zeros (bottom and right), which
    count in the last blocks' means. Output pixel j's centre is at input coordinate
    `k j + (k - 1) / 2`.

    Args:
        images: (B, H, W, C) float.
        k: block side, >= 1.
    Returns:
        (B, ceil(H / k), ceil(W / k), C).
    """
    _check_images(images)
    if int(k) < 1:
        raise ValueError(f"k: expected a block side >= 1, found {k}")
    k = int(k)
    nchw = images.permute(0, 3, 1, 2)
    pad_h, pad_w = -images.shape[1] % k, -images.shape[2] % k
    if pad_h or pad_w:
        nchw = F.pad(nchw, (0, pad_w, 0, pad_h))
    # channels-last storage (free for a contiguous (B, H, W, C) input): pooling a strided
    # window of a larger image in place takes torch's slow generic path
    nchw = nchw.contiguous(memory_format=torch.channels_last)
    return F.avg_pool2d(nchw, k).permute(0, 2, 3, 1)


def separable_filter(images: Tensor, kernel: Tensor) -> Tensor:
    """Convolve each channel with `kernel` along x, then along y; edges replicated.

    Args:
        images: (B, H, W, C) float.
        kernel: (K,) weights, K odd (centred: tap r of 2R + 1 weighs the pixel at offset r - R).
    Returns:
        (B, H, W, C).
    """
    _check_images(images)
    if kernel.ndim != 1 or kernel.shape[0] % 2 != 1:
        raise ValueError(f"kernel: expected shape (K,) with K odd, found {tuple(kernel.shape)}")
    radius = kernel.shape[0] // 2
    n, h, w, c = images.shape
    taps = kernel.detach().cpu().tolist()
    t = images.permute(0, 3, 1, 2).reshape(n * c, 1, h, w)
    t = F.pad(t, (radius, radius, radius, radius), mode="replicate")[:, 0]
    # weighted sums of shifted views: each pixel's sum runs over its own taps in a fixed order,
    # so an image's result does not depend on the batch it came in (a convolution's did), and
    # on one thread it is ~10x faster than `conv2d` with a 1-channel kernel (8 crops of 192^2:
    # 6.8 against 73 ms)
    along_x = taps[0] * t[:, :, :w]
    for i in range(1, len(taps)):
        along_x = along_x + taps[i] * t[:, :, i:i + w]
    out = taps[0] * along_x[:, :h]
    for i in range(1, len(taps)):
        out = out + taps[i] * along_x[:, i:i + h]
    return out.reshape(n, c, h, w).permute(0, 2, 3, 1)


def gaussian_kernel(sigma: float, *, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu",
                    truncate: float = 2.5) -> Tensor:
    """(2 R + 1,) normalized Gaussian weights of `sigma` pixels, R = max(1, ceil(truncate sigma)).

    Raises:
        ValueError: sigma <= 0.
    """
    if not sigma > 0:
        raise ValueError(f"sigma: expected > 0 pixels, found {sigma}")
    radius = max(1, int(np.ceil(truncate * sigma)))
    x = torch.arange(-radius, radius + 1, dtype=dtype, device=device)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def gaussian_blur(images: Tensor, sigma: float) -> Tensor:
    """Blur images by a separable Gaussian of `sigma` pixels (2.5 sigma wide, edges replicated).

    Args:
        images: (B, H, W, C) float.
        sigma: standard deviation, pixels; <= 0 returns `images` unchanged.
    Returns:
        (B, H, W, C).
    """
    if sigma <= 0:
        return images
    return separable_filter(images, gaussian_kernel(sigma, dtype=images.dtype, device=images.device))


def pyramid_down(images: Tensor) -> Tensor:
    """One level of a Gaussian pyramid: binomial blur (1, 4, 6, 4, 1) / 16, edges replicated,
    then every second pixel (output pixel j is input pixel 2 j).

    Args:
        images: (B, H, W, C) float.
    Returns:
        (B, ceil(H / 2), ceil(W / 2), C).
    """
    kernel = torch.tensor(_BINOMIAL, dtype=images.dtype, device=images.device) / 16.0
    return separable_filter(images, kernel)[:, ::2, ::2]


# -- crops ---------------------------------------------------------------------------------
_UNIT_STEPS: dict[tuple[int, torch.device, torch.dtype], Tensor] = {}


def _unit_steps(size: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """`(j + 1/2) / S` for j = 0 .. S - 1, (S,), cached per size, device and dtype (read only)."""
    key = (size, device, dtype)
    steps = _UNIT_STEPS.get(key)
    if steps is None:
        steps = _UNIT_STEPS[key] = (torch.arange(size, device=device, dtype=dtype) + 0.5) / size
    return steps


def crop_and_resize(images: Tensor, boxes: Tensor | np.ndarray, size: int,
                    angles: Tensor | np.ndarray | None = None) -> Tensor:
    """Crop each image to its box and resize to size x size, bilinearly (differentiable in pixels).

    For a shrink by `k = int(min(box width, box height) / S) >= 2` the image is first averaged
    over k x k blocks (`box_downsample`; blocks at multiples of k from the image's corner),
    and the crop samples those block means, so fine detail does not alias.

    Args:
        images: (B, H, W, C) float.
        boxes: (B, 4) x0 y0 x1 y1, pixels (see the module docstring); held constant.
        size: output side S, pixels.
        angles: (B,) radians or None (0): the crop is the box turned by this angle about its
            centre (x towards y, i.e. clockwise on screen): crop pixel offset d from the crop
            centre samples the image at `centre + R(angle) d`, so a face rolled by `angle`
            comes out upright.
    Returns:
        (B, S, S, C) contiguous; samples outside the image are 0 (black).

    Raises:
        ValueError: `images` is not 4-D, `boxes` / `angles` do not have one row per image or
            are not finite.
    Note:
        The images sharing a shrink factor, a pooled window and whether they are turned are
        cropped together: one `box_downsample` and one `grid_sample` per such group (one for a
        whole batch of untilted crops with k <= 1, or of the same box), the sampling grid built
        for the group at once from the cached `(j + 1/2) / S` steps. The coordinates are those of
        cropping each image on its own, computed in the images' dtype in the same order (the
        box's corner, side and centre rounded once from float64), so the crops are the same
        to the bit.
    """
    _check_images(images)
    n, height, width, _ = images.shape
    dtype, device = images.dtype, images.device
    boxes = torch.as_tensor(np.asarray(boxes, np.float64) if not isinstance(boxes, Tensor) else boxes,
                            dtype=dtype, device=device).reshape(-1, 4)
    if len(boxes) != n:
        raise ValueError(f"boxes: expected shape ({n}, 4), found {tuple(boxes.shape)}")
    # the boxes as the images' dtype rounds them, in float64 for the window and k arithmetic
    box = boxes.detach().cpu().to(torch.float64).numpy()
    if not np.isfinite(box).all():
        raise ValueError(f"boxes: expected finite x0 y0 x1 y1, found {box[~np.isfinite(box).all(1)][0].tolist()}")
    if angles is not None:
        angles = np.asarray(angles.detach().cpu() if isinstance(angles, Tensor) else angles, np.float64).reshape(-1)
        if len(angles) != n:
            raise ValueError(f"angles: expected shape ({n},), found {angles.shape}")
        if not np.isfinite(angles).all():
            raise ValueError(f"angles: expected finite radians, found {angles.tolist()}")
        turned = angles != 0.0
        cos, sin = np.cos(angles), np.sin(angles)
    else:
        turned = np.zeros(n, bool)
        cos, sin = np.ones(n), np.zeros(n)
    if n == 0:
        return images.new_zeros(0, size, size, images.shape[3])
    x0, y0, x1, y1 = box.T
    ks = np.trunc(np.minimum(x1 - x0, y1 - y0) / size).astype(np.int64)
    # pooled window per image (k >= 2): the part of the image the crop samples, with a margin
    # of 2 pooled pixels, cut at multiples of k so that the blocks are those of pooling the
    # whole image (pooled pixel i covers k i .. k i + k - 1); 0s for k <= 1
    windows = np.zeros((n, 4), np.int64)
    pooled = ks >= 2
    if pooled.any():
        k = ks[pooled].astype(np.float64)
        c, s = np.abs(cos[pooled]), np.abs(sin[pooled])
        bw, bh = (x1 - x0)[pooled], (y1 - y0)[pooled]
        reach_x, reach_y = (c * bw + s * bh) / 2 + 2 * k, (s * bw + c * bh) / 2 + 2 * k
        cx, cy = ((x0 + x1) / 2)[pooled], ((y0 + y1) / 2)[pooled]
        ki = ks[pooled]
        left = np.minimum(np.maximum(np.floor((cx - reach_x) / k).astype(np.int64) * ki, 0), (width - 1) // ki * ki)
        top = np.minimum(np.maximum(np.floor((cy - reach_y) / k).astype(np.int64) * ki, 0), (height - 1) // ki * ki)
        right = np.minimum(np.maximum(np.ceil((cx + reach_x) / k).astype(np.int64) * ki, left + ki),
                           width + (-width) % ki)
        bottom = np.minimum(np.maximum(np.ceil((cy + reach_y) / k).astype(np.int64) * ki, top + ki),
                            height + (-height) % ki)
        windows[pooled] = np.stack([left, top, right, bottom], 1)
    # corners relative to the window, as cropping the window alone computes them (float64)
    x0, x1 = x0 - windows[:, 0], x1 - windows[:, 0]
    y0, y1 = y0 - windows[:, 1], y1 - windows[:, 1]
    keys = np.concatenate([np.maximum(ks, 1)[:, None], windows, turned[:, None]], 1)
    if (keys == keys[0]).all():  # one group (a single image, or a batch cropped alike): no sort
        groups, group_of = keys[:1], np.zeros(n, np.int64)
    else:
        groups, group_of = np.unique(keys, axis=0, return_inverse=True)
        group_of = group_of.reshape(-1)
    steps = _unit_steps(size, device, dtype)
    # per image, rounded once to the images' dtype (as cropping each image on its own does):
    # corner, side and centre along x and y, cos and sin of the angle; (8, B, 1, 1)
    params = torch.from_numpy(np.stack([x0, x1 - x0, y0, y1 - y0, (x0 + x1) / 2, (y0 + y1) / 2, cos, sin]))
    params = params.to(device=device, dtype=dtype).reshape(8, n, 1, 1)

    crops, order = [], []
    for g, (k, left, top, right, bottom, is_turned) in enumerate(groups.tolist()):
        if len(groups) == 1:
            rows, index, img, p = np.arange(n), None, images, params
        else:
            rows = np.flatnonzero(group_of == g)
            index = torch.from_numpy(rows).to(device)
            img, p = images.index_select(0, index), params.index_select(1, index)
        if k >= 2:
            img = box_downsample(img[:, top:bottom, left:right], k)
        along = steps.reshape(1, 1, -1)  # (1, 1, S): x varies along a row, y down a column
        corner_x, side_x, corner_y, side_y, centre_x, centre_y, c, s = p
        h, w = img.shape[1], img.shape[2]
        # x, y of each crop pixel, in place in one (G, S, S, 2) grid (few large temporaries)
        grid = torch.empty(len(rows), size, size, 2, dtype=dtype, device=device)
        gx, gy = grid[..., 0], grid[..., 1]
        if not is_turned:  # separable: x along a row, y down a column, broadcast into the grid
            xs = corner_x + along * side_x
            ys = (corner_y + along * side_y).transpose(1, 2)
            if k >= 2:  # to pooled pixel-centre coordinates
                xs, ys = (xs - (k - 1) / 2.0) / float(k), (ys - (k - 1) / 2.0) / float(k)
            gx.copy_((xs + 0.5) / w * 2 - 1)
            gy.copy_((ys + 0.5) / h * 2 - 1)
        else:  # offsets from the box centre, turned by the angle
            dx = (along - 0.5) * side_x
            dy = ((along - 0.5) * side_y).transpose(1, 2)
            torch.sub(centre_x + c * dx, s * dy, out=gx)
            torch.add(centre_y + s * dx, c * dy, out=gy)
            if k >= 2:  # to pooled pixel-centre coordinates
                grid.sub_((k - 1) / 2.0).div_(float(k))
            # grid_sample's align_corners=False coordinates: -1 and 1 are the image's outer edges
            grid.add_(0.5)
            gx.div_(w)
            gy.div_(h)
            grid.mul_(2).sub_(1)
        sampled = F.grid_sample(img.permute(0, 3, 1, 2), grid, mode="bilinear", padding_mode="zeros",
                                align_corners=False)
        crops.append(sampled.permute(0, 2, 3, 1))
        order.append(rows)
    if len(crops) == 1:
        return crops[0].contiguous()
    out = torch.cat(crops)
    inverse = np.empty(n, np.int64)
    inverse[np.concatenate(order)] = np.arange(n)
    return out.index_select(0, torch.from_numpy(inverse).to(device))


def crop_to_image(points: Tensor, boxes: Tensor, size: int) -> Tensor:
    """Map crop pixel coordinates to image pixels: `x0 + (p + 1/2) (x1 - x0) / S`.

    Args:
        points: (..., L, 2) x, y in the S x S crop's pixels (centres at integers).
        boxes: (..., 4) x0 y0 x1 y1 crop boxes, image pixels (square: the x scale serves both).
        size: S.
    Returns:
        (..., L, 2) image pixels.
    """
    k = ((boxes[..., 2] - boxes[..., 0]) / size)[..., None, None]
    return boxes[..., None, :2] + (points + 0.5) * k


def image_to_crop(points: Tensor, boxes: Tensor, size: int) -> Tensor:
    """Inverse of `crop_to_image`: (..., L, 2) image pixels -> crop pixels of the (..., 4) boxes."""
    k = ((boxes[..., 2] - boxes[..., 0]) / size)[..., None, None]
    return (points - boxes[..., None, :2]) / k - 0.5


def crop_intrinsics(intrinsics: Tensor, boxes: Tensor, size: int) -> Tensor:
    """Pinhole intrinsics of an S x S render of each crop box (what `crop_and_resize` of a
    full-size render shows): `f' = f S / s`, `c' = (c - x0) S / s - 1/2` (s the box's width).

    Args:
        intrinsics: (C, 4) fx fy cx cy of the image, pixels.
        boxes: (B, C, 4) x0 y0 x1 y1 square boxes, pixels.
        size: S.
    Returns:
        (B, C, 4) fx fy cx cy of the render, render pixels.
    """
    k = size / (boxes[..., 2] - boxes[..., 0]).clamp_min(1e-6)
    fx, fy, cx, cy = intrinsics[None].expand(*boxes.shape[:2], 4).unbind(-1)
    return torch.stack([fx * k, fy * k, (cx - boxes[..., 0]) * k - 0.5, (cy - boxes[..., 1]) * k - 0.5], -1)
