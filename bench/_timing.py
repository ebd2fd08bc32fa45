"""Timing helper shared by the bench scripts (imported as `from _timing import median_ms, best_ms`: the
scripts run as `python bench/NAME.py`, so this folder is on the import path)."""

from __future__ import annotations

import statistics
import time
from typing import Callable


def times_ms(fn: Callable[[], object], repeat: int = 3) -> list[float]:
    """Wall times of `fn()` in ms over `repeat` runs after one warm-up (CUDA synchronized)."""
    import torch

    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    return times


def median_ms(fn: Callable[[], object], repeat: int = 3) -> float:
    """Median of `times_ms`."""
    return statistics.median(times_ms(fn, repeat))


def best_ms(fn: Callable[[], object], repeat: int = 3) -> float:
    """Least of `times_ms`: the run least disturbed by other work on a shared machine."""
    return min(times_ms(fn, repeat))
