"""Timing helper shared by the bench scripts (imported as `from _timing import median_ms`: the
scripts run as `python bench/NAME.py`, so this folder is on the import path)."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def median_ms(fn: Callable[[], object], repeat: int = 3) -> float:
    """Median wall time of `fn()` in ms over `repeat` runs after one warm-up (CUDA synchronized)."""
    import torch

    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(times)
