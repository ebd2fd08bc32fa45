"""Run a compiled kernel's two fixed halves side by side on two threads (numba kernels compiled
with `nogil=True` release the GIL), or one after the other.

The renderer's CPU kernels split their work into two fixed halves (image rows, pixels, pixel
pairs) whose results are merged in a fixed order, so the output is the same bits whether the
halves ran on one thread or two; only the wall time changes. The halves run side by side when
torch may use more than one intra-op thread (`torch.get_num_threads()`, which
`nodegraph.Node.torch_threads` pins per node) and the work is large enough to pay for a thread
hand-off (tens of microseconds). Python threads are used, not numba's parallel layer, so no
second OpenMP runtime is loaded beside torch's.
"""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Any, Callable

__all__ = ["run_halves", "halves_in_parallel", "MIN_PARALLEL_WORK"]

MIN_PARALLEL_WORK = 20_000
"""Work items (pixels, triangles) below which the two halves run on the calling thread."""

_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _pool() -> ThreadPoolExecutor:
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="render-half")
        return _POOL


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def halves_in_parallel(work: int) -> bool:
    """Whether `run_halves(..., work)` would run its halves side by side (torch may use 2+
    threads and `work` >= MIN_PARALLEL_WORK). A kernel whose one-pass result is the same bits as
    its two halves' (disjoint writes) runs in one pass when not, skipping work the halves repeat."""
    return work >= MIN_PARALLEL_WORK and _threads() >= 2


def run_halves(first: Callable[[], Any], second: Callable[[], Any], work: int) -> tuple[Any, Any]:
    """Results of `first()` and `second()`: `first` on a pool thread while `second` runs here when
    torch may use 2+ threads and `work` >= MIN_PARALLEL_WORK, else both here, in order. The two
    must write to disjoint memory (each its own output, or disjoint parts of one)."""
    if not halves_in_parallel(work):
        return first(), second()
    future = _pool().submit(first)
    try:
        b = second()
    finally:
        a = future.result()
    return a, b
