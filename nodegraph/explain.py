"""`explain`: per task of a planned run, would it be a cache hit, and if not, why (runs nothing)."""

from __future__ import annotations

import os
from typing import Any, Iterable

from .cache import Cache, resolve_cache
from .graph import Graph
from .schedule import TaskPlan, explain_miss, plan_run

__all__ = ["explain"]


def explain(graph: Graph, *, frames: range | None = None, chunk: int = 64,
            cache: Cache | str | os.PathLike | bool | None = None, outputs: Iterable[str] | None = None,
            force: Iterable[str] = ()) -> list[dict[str, Any]]:
    """Per node and chunk: would it be a cache hit, and if not, why. Runs nothing.

    Returns:
        one dict per task: node, frames, hit (bool), reason.
    """
    store = resolve_cache(cache)
    plan = plan_run(graph, frames=frames, chunk=chunk, cache=store, targets=list(outputs or []) or None,
                    force=force)
    plan.verify = True  # read every entry's bytes: a corrupt entry is a miss here too
    rows = []
    last_by_node: dict[str, dict[str, Any]] = {}
    for name in plan.needed():
        task: TaskPlan = plan.tasks[name]
        if task.hit and task.restore:
            reason = "cached; will rewrite from the cache: " + ", ".join(task.stale_files)
        elif task.hit:
            reason = "cached"
        elif store is None:
            reason = "no cache"
        else:
            last = last_by_node.setdefault(task.node, store.read_last(task.node))
            reason = explain_miss(task, last.get(str(name)) or _same_node_other_chunk(last, task), store)
        rows.append({"node": task.node, "task": str(name), "frames": list(task.out_frames), "hit": task.hit,
                     "reason": reason})
    return rows


def _same_node_other_chunk(last: dict[str, Any], task: TaskPlan) -> dict[str, Any] | None:
    """For a sequence or static task whose frame range changed, compare with its last run."""
    if task.mode == "chunk" or not last:
        return None
    return next(iter(last.values()))
