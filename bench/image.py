"""Cost of the image operations of `nodes.geometry.image` on the shapes the pipeline uses.

Run: nice python bench/image.py [--repeat 5] [--threads 1]

Rows (best of `--repeat` runs after one warm-up, ms; the least disturbed by other work on a
shared machine, still noisy there: quote the load beside them):
  sample_bilinear gather|grid_sample  PADDING  a 192 x 192 grid of samples (a crop) on a
                      400 x 400 x 3 image: the two methods of `sample_bilinear`
  crop_and_resize     4 frames of 1920 x 1080 x 3 to 192 x 192, a 480 px box (box filter k = 2),
                      upright and turned by 0.3 rad; and forward + backward
  box_downsample      a 1920 x 1080 x 3 frame by k = 2
  gaussian_blur       4 crops of 192 x 192 x 3, sigma 1
  pyramid_down        a 1 x 512 x 512 luminance image
"""

from __future__ import annotations

import argparse
import os

import numpy as np
import torch
from _timing import best_ms

from nodes.geometry.image import box_downsample, crop_and_resize, gaussian_blur, pyramid_down, sample_bilinear


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print(f"torch {torch.__version__}, {args.threads} thread(s), load {os.getloadavg()[0]:.1f}, "
          f"best of {args.repeat}, ms")
    g = torch.Generator().manual_seed(0)
    image = torch.rand(1, 400, 400, 3, generator=g)
    t = torch.arange(192, dtype=torch.float32) * 1.9 + 10.3
    ys, xs = torch.meshgrid(t, t, indexing="ij")
    xy = torch.stack([xs, ys], -1)[None]
    for padding in ("border", "zeros"):
        for method in ("gather", "grid_sample"):
            ms = best_ms(lambda: sample_bilinear(image, xy, padding=padding, method=method), args.repeat)
            print(f"sample_bilinear {method:11s} {padding:6s}  {ms:8.2f}")
    frames = torch.rand(4, 1080, 1920, 3, generator=g)
    boxes = np.array([[700.3, 300.2, 1180.1, 780.0]] * 4)
    print(f"crop_and_resize upright        {best_ms(lambda: crop_and_resize(frames, boxes, 192), args.repeat):8.2f}")
    angles = np.full(4, 0.3)
    print(f"crop_and_resize turned         "
          f"{best_ms(lambda: crop_and_resize(frames, boxes, 192, angles), args.repeat):8.2f}")
    leaf = frames.clone().requires_grad_(True)
    print(f"crop_and_resize fwd + bwd      "
          f"{best_ms(lambda: crop_and_resize(leaf, boxes, 192).sum().backward(), args.repeat):8.2f}")
    print(f"box_downsample 1080p k=2       {best_ms(lambda: box_downsample(frames[:1], 2), args.repeat):8.2f}")
    crops = torch.rand(4, 192, 192, 3, generator=g)
    print(f"gaussian_blur 4x192^2 s=1      {best_ms(lambda: gaussian_blur(crops, 1.0), args.repeat):8.2f}")
    luma = torch.rand(1, 512, 512, 1, generator=g)
    print(f"pyramid_down 512^2             {best_ms(lambda: pyramid_down(luma), args.repeat):8.2f}")


if __name__ == "__main__":
    main()
