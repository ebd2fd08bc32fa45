"""Importing this module loads the compiled CPU kernels of `robust_kernels` (a `Node.preload`).

numba compiles `robust_kernels` once into its on-disk cache, but every new process still pays
to load them: numba's CPU target is set up on the first call (its type registries, scipy's
BLAS) and each kernel's machine code is read back, about 0.6 s of CPU on this machine after
the 0.5 s of `import numba`. `stabilize.ModePursuit` names this module in its `preload`, so
that work happens in the runner's preload thread while the capture is read, not on the
critical path of the mode pursuit itself. Each kernel is called once on tiny arrays of the
argument types `robust.py` and `mode_pursuit.py` pass (C-contiguous float32 points, float64
transforms and moments), so the run's calls find the specialisation already loaded.
"""

from __future__ import annotations

import numpy as np

from .robust_kernels import MOMENTS, gather_normalized, irls_moments, local_window_still, window_mean_square

__all__ = ["load_kernels"]


def load_kernels() -> None:
    """Call each kernel once on 2 frames x 4 vertices (the results are discarded)."""
    frames, vertices = 2, 4
    points = np.zeros((frames, 3, vertices), np.float32)
    rest = np.zeros((3, vertices), np.float32)
    rotation = np.broadcast_to(np.eye(3), (frames, 3, 3)).copy()
    irls_moments(points, rest, rotation, np.zeros((frames, 3)), 1.0, np.ones((1, vertices), np.float32), 1,
                 np.empty((frames, MOMENTS)), np.empty((0, vertices), np.float32))
    window_mean_square(points, rest, 1, np.empty(vertices))
    local_window_still(points, 1, 1.0, np.empty((frames, vertices), np.float32))
    gather_normalized(np.zeros((frames, vertices, 3), np.float32), np.arange(vertices, dtype=np.int64),
                      np.zeros(3), 1.0, np.empty((frames, 3, vertices), np.float32))


load_kernels()
