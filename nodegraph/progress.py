"""Progress output of a run: tqdm bars on a terminal, JSON lines on stderr otherwise (one
event per line, never interleaved between threads), or nothing; warnings as JSON events in
JSON mode, so that every stderr line of a farm log is JSON."""

from __future__ import annotations

import json
import os
import sys
import threading
import time
import warnings
from typing import TYPE_CHECKING, Any, Callable, Mapping

if TYPE_CHECKING:
    from .plan_names import TaskName
    from .runner import RunResult
    from .schedule import Plan

__all__ = ["emit_json", "progress_mode", "progress_callback", "Reporter", "warnings_as_events",
           "json_warning"]

_STDERR_LOCK = threading.Lock()


def emit_json(event: Mapping[str, Any]) -> None:
    """Write one JSON line to stderr in one write (threads never interleave inside a line)."""
    line = json.dumps(event, default=str) + "\n"
    with _STDERR_LOCK:
        sys.stderr.write(line)
        sys.stderr.flush()


def progress_mode(progress: str | bool | None) -> str:
    """The run's progress mode ("tty", "json" or "none") from `run`'s `progress` argument:
    "auto" (or True) means tty when stderr is a terminal, else JSON lines."""
    if progress in (False, "none"):
        return "none"
    if progress in ("tty", "json"):
        return str(progress)
    if progress is None:
        return "none"
    return "tty" if sys.stderr.isatty() else "json"


def progress_callback(mode: str, node: str, frames: tuple[int, int]) -> Callable[[float, str], None] | None:
    """The `report(fraction, message)` a task's node calls (`Node.progress`), at most once a
    second until done; None in mode "none"."""
    if mode == "none":
        return None
    last = [0.0]

    def report(fraction: float, message: str) -> None:
        now = time.monotonic()
        if now - last[0] < 1.0 and fraction < 1.0:
            return
        last[0] = now
        if mode == "json":
            emit_json({"event": "progress", "node": node, "frames": list(frames),
                       "fraction": round(fraction, 4), "message": message})
        else:
            print(f"  {node} [{frames[0]}:{frames[1]}] {100 * fraction:5.1f}% {message}",
                  file=sys.stderr, flush=True)
    return report


class Reporter:
    """Per-node progress: tqdm bars on a terminal, JSON lines otherwise, or nothing."""

    def __init__(self, plan: "Plan", names: list["TaskName"], mode: str):
        self.mode = mode
        self.totals: dict[str, int] = {}
        for name in names:
            node = plan.tasks[name].node
            self.totals[node] = self.totals.get(node, 0) + 1
        self.done = {node: 0 for node in self.totals}
        self.lock = threading.Lock()
        self.bars = {}
        if mode == "tty":
            from tqdm import tqdm

            for position, node in enumerate(self.totals):
                self.bars[node] = tqdm(total=self.totals[node], desc=node, position=position, leave=True,
                                       unit="chunk", file=sys.stderr, dynamic_ncols=True)
        elif mode == "json":
            self.emit({"event": "start", "tasks": len(names), "nodes": self.totals})

    def emit(self, event: dict[str, Any]) -> None:
        emit_json(event)

    def update(self, meta: Mapping[str, Any]) -> None:
        with self.lock:
            node = meta["node"]
            self.done[node] += 1
            if self.mode == "tty":
                self.bars[node].update(1)
                if meta["status"] == "cached":
                    self.bars[node].set_postfix_str("cached", refresh=False)
            elif self.mode == "json":
                self.emit({"event": "task", "node": node, "frames": meta["frames"], "status": meta["status"],
                           "done": self.done[node], "total": self.totals[node],
                           "seconds": round(meta["seconds"], 4)})

    def close(self, result: "RunResult") -> None:
        for bar in self.bars.values():
            bar.close()
        if self.mode == "json":
            self.emit({"event": "end", "executed": result.executed(), "cached": result.count("cached"),
                       "failed": result.count("failed"), "skipped": result.count("skipped"),
                       "held_back": result.held_back, "seconds": round(result.seconds, 3)})

class warnings_as_events:
    """In JSON-lines progress mode, print warnings as {"event": "warning"} lines on stderr
    (so that every stderr line of a farm log is JSON); otherwise leave them alone."""

    def __init__(self, mode: str):
        self.mode = mode
        self.saved: Any = None

    def __enter__(self) -> None:
        if self.mode == "json":
            self.saved = warnings.showwarning
            warnings.showwarning = json_warning

    def __exit__(self, *exc: Any) -> None:
        if self.saved is not None:
            warnings.showwarning = self.saved


def json_warning(message: Any, category: type, filename: str, lineno: int, file: Any = None,
                 line: str | None = None) -> None:
    """A `warnings.showwarning` that prints the warning as one {"event": "warning"} JSON line."""
    emit_json({"event": "warning", "category": category.__name__, "message": str(message),
               "where": f"{os.path.basename(filename)}:{lineno}"})
