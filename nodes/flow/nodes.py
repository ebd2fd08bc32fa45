"""Flow nodes: `flow.OpticalFlow` (image sequence -> flow from every frame to the next).

Torch is imported inside `run()` (see tests/test_startup.py).
"""

from __future__ import annotations

import numpy as np

from nodegraph import FlowSequence, ImageSequence, InputError, Node, NodeParams, Param, windowed
from nodegraph import In, Out

__all__ = ["OpticalFlow"]


class OpticalFlow(Node):
    """Dense optical flow from each frame to the next (coarse-to-fine robust Horn-Schunck, Chebyshev-accelerated Jacobi; compiled on the CPU)."""

    type_name = "flow.OpticalFlow"
    version = 3  # 3: Chebyshev-accelerated sweeps (`acceleration`), fewer iterations
    kind = windowed(1)
    resources = {"gpu": 1}

    class Params(NodeParams):
        alpha: float = Param(0.06, gt=0, description="Smoothness weight (normalized intensity units).")
        levels: int = Param(5, ge=1, le=8, description="Pyramid levels at most.")
        warps: int = Param(6, ge=1, le=20, description="Warps per level but the finest: each warp re-linearises "
                         "the data term about the flow found so far, which motions of several pixels per level "
                         "need; 6 with the accelerated sweeps (bench/temporal.py: 8 is a little more accurate "
                         "and slower).")
        finest_warps: int = Param(2, ge=1, le=20, description="Warps at the finest level when it is over 128x128 pixels "
                               "(smaller images keep `warps`: they are cheap, and their small faces need them). "
                               "The finest level costs about 4x the next and starts from the motion the coarser "
                               "levels found, so 2 warps keep most of the accuracy of 8 at a fraction of the "
                               "time (bench/temporal.py prints both).")
        iterations: int = Param(12, ge=1, le=500, description="Jacobi iterations per warp, coarsest level.")
        finest_iterations: int = Param(6, ge=1, le=500, description="Jacobi iterations per warp, finest level.")
        acceleration: float = Param(0.99, ge=0, lt=1, description="Chebyshev acceleration of the Jacobi "
                                    "iterations: the largest eigenvalue assumed for the Jacobi iteration "
                                    "(0: plain Jacobi). With 0.99, 6 / 12 iterations (finest / coarsest) and 6 "
                                    "warps are more accurate than plain Jacobi's 12 / 40 and 8 warps, in less "
                                    "time (bench/temporal.py).")
        skip_levels: int = Param(0, ge=0, le=3, description="Finest pyramid levels not solved (the flow of the "
                                 "next coarser level is upsampled): skipping the finest roughly halves the time, at "
                                 "a coarser flow; 0 (every level solved) is the accurate setting.")
        median_every_warp: bool = Param(False, description="3x3 median of the flow after every warp instead of "
                                        "after every level: outliers are removed before the next warp builds on "
                                        "them; off by default, where the per-level median suffices; "
                                        "bench/temporal.py's fast setting (skip_levels 1) turns it on.")

    images = In(ImageSequence, doc="Plates (F, H, W, C); colour channels reduced to luminance (linear light).")
    flow = Out(FlowSequence, doc="(F, H, W, 2) pixels, x right y down: frame f -> f + 1; the last frame "
               "of the shot is invalid (zero flow).")

    def run(self, images: ImageSequence) -> dict[str, FlowSequence]:
        import torch

        from .dense import FlowSettings, dense_flow

        p = self.params
        colour = images.colour_channels()
        if not colour:
            raise InputError("images", f"expected colour channels, found {images.channels}")
        pix = images.to_linear().pixels[..., colour]
        f, h, w = pix.shape[:3]
        settings = FlowSettings(alpha=p.alpha, levels=p.levels, warps=p.warps, finest_warps=p.finest_warps,
                                iterations=p.iterations,
                                finest_iterations=p.finest_iterations, skip_levels=p.skip_levels,
                                median_every_warp=p.median_every_warp, acceleration=p.acceleration)
        compiled = self.device == "cpu"  # the same flow, compiled (nodes.flow.fast); torch on CUDA
        if compiled:
            from .fast import dense_flow_numpy
        out = np.zeros((f, h, w, 2), np.float32)
        valid = np.zeros(f, bool)
        with torch.no_grad():
            for i in range(f - 1):  # one pair per call: a pair's flow never depends on its chunk
                a = torch.as_tensor(pix[i:i + 2], device=self.device).permute(0, 3, 1, 2)
                if compiled:
                    out[i] = dense_flow_numpy(a[:1], a[1:], settings).transpose(1, 2, 0)
                else:
                    out[i] = dense_flow(a[:1], a[1:], settings)[0].permute(1, 2, 0).cpu().numpy()
                valid[i] = True
                self.progress((i + 1) / max(f - 1, 1), f"flow {i + 1}/{f - 1} pairs")
        return {"flow": FlowSequence(out, valid)}
