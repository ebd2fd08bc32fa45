"""Task execution: what one task of a run does in a worker.

A task is a plain-data `TaskSpec` (the node class, its parameters, its frames and where its
inputs come from); `compute_task` joins its inputs from the upstream `TaskResult`s, runs the
node and stores the values in the cache, `load_task` reads a cached task back. Every task
catches its own failure and returns it as a record, so one failing node never stops
independent branches; tasks below a failure are skipped.

Two fast paths for runs whose tasks run in this process (the sync and threads schedulers,
`in_process_run`): joins of the same upstream chunks are shared between tasks, and cache
writes happen in a background thread.
"""

from __future__ import annotations

import contextlib
import dataclasses
import multiprocessing
import os
import sys
import threading
import time
import warnings
import weakref
from dataclasses import dataclass
from typing import Any, Callable, Iterator, Mapping, Sequence

from .cache import COPY_LIMIT, Cache, CorruptEntry
from .errors import NodeError
from .node import Node, execute, format_exception, task_seed
from .plan_names import PortSlot, TaskName
from .ports import PortType
from .progress import json_warning, progress_callback
from .staging import StagedFile, publish, staging
from .values import Files

__all__ = ["TaskSpec", "TaskResult", "OK_STATUSES", "IN_PROCESS", "combine", "compute_task",
           "compute_logged_task", "load_task", "task_meta", "task_staged", "in_process_run", "preload",
           "import_now"]

OK_STATUSES = ("executed", "cached", "restored")
"""Statuses of a task that has values."""

IN_PROCESS = ("sync", "threads")
"""Schedulers whose tasks run in this process (shared joins, background cache writes, preloads)."""


@dataclass(frozen=True)
class TaskSpec:
    """Everything a worker needs to run one task (plain data plus the node class)."""

    name: TaskName
    node: str
    node_cls: type[Node]
    params: dict[str, Any]
    frames: tuple[int, int]
    out_frames: tuple[int, int]
    full_frames: tuple[int, int]
    inputs: tuple[tuple[PortSlot, tuple[tuple[int, str, int, int], ...]], ...]  # (dep, port, lo, hi) pieces
    key: str
    description: dict[str, Any]
    cache_root: str | None
    cacheable: bool
    progress: str
    writes: bool = False
    restore: bool = False
    device: str = "cpu"
    run_log: tuple[dict[str, Any], ...] = ()
    stage: str = ""  # the run's staging token: a writer's files are held back until the run commits


@dataclass
class TaskResult:
    """What a task returns: its values, or why it has none."""

    name: TaskName
    node: str
    frames: tuple[int, int]
    status: str  # executed | cached | restored | failed | skipped | corrupt
    values: dict[str, PortType] | None = None
    error: dict[str, Any] | None = None
    seconds: float = 0.0
    staged: tuple[StagedFile, ...] = ()  # a writer's files held back in staging folders
    started: float = 0.0  # time.time() when the task began (0: never ran), for timelines of a run

    def meta(self) -> dict[str, Any]:
        return {"name": str(self.name), "node": self.node, "frames": list(self.frames), "status": self.status,
                "error": self.error, "seconds": self.seconds, "started": self.started}


def _trim(node: Node, values: dict[str, PortType], frames: tuple[int, int],
          out: tuple[int, int]) -> dict[str, PortType]:
    if frames == out:
        return values
    a, b = out[0] - frames[0], out[1] - frames[0]
    return {port: (value.slice_frames(a, b) if node.outputs[port].per_frame else value)
            for port, value in values.items()}


def combine(parts: list[PortType], per_frame: bool) -> PortType:
    """One value from the chunks' values: frames concatenated, or whole values merged."""
    if len(parts) == 1:
        return parts[0]
    kind = type(parts[0])
    return kind.concat_frames(parts) if per_frame else kind.merge_chunks(parts)


class _CombinedInputs:
    """Joined chunk values shared by the tasks of one process that read the same chunks.

    Several whole-sequence tasks often read the same upstream chunks (a loaded capture feeds
    the reference, the solver and the report): concatenating 651 frames x 26,719 vertices
    costs ~0.3 s and 210 MB each time. An entry is keyed by the identity of the upstream
    `TaskResult` objects and the frame ranges read; it holds the joined value strongly and
    the upstream results weakly, and is valid only while every upstream result is still the
    very object it was made from (so a reused `id` can never return another run's value).
    Entries die with their upstream results (released by dask when their last reader ran)
    and all of them at the end of a run (`clear`). In worker processes (processes or
    distributed schedulers) the upstream results are fresh copies per task, so it is only
    active around in-process runs (sync and threads schedulers).
    """

    def __init__(self) -> None:
        self.active = False  # set by `in_process_run`
        self._entries: dict[tuple, tuple[PortType, tuple[weakref.ref, ...]]] = {}
        self._lock = threading.Lock()
        self._key_locks: dict[tuple, threading.Lock] = {}

    def _valid(self, refs: tuple[weakref.ref, ...], sources: Sequence[TaskResult]) -> bool:
        return all(ref() is source for ref, source in zip(refs, sources))

    def get(self, deps: Sequence[TaskResult], pieces: Sequence[tuple[int, str, int, int]],
            per_frame: bool) -> PortType:
        """The value of one input port read from `pieces` (dep index, port, lo, hi) of `deps`."""
        def parts() -> list[PortType]:
            out = []
            for dep_index, out_port, lo, hi in pieces:
                value = deps[dep_index].values[out_port]
                out.append(value if lo < 0 else value.slice_frames(lo, hi))
            return out

        if len(pieces) == 1 or not self.active:
            return combine(parts(), per_frame)
        sources = [deps[p[0]] for p in pieces]
        key = tuple((id(src), port, lo, hi) for src, (_, port, lo, hi) in zip(sources, pieces)) + (per_frame,)
        with self._lock:
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                hit = self._entries.get(key)
                if hit is not None and self._valid(hit[1], sources):
                    return hit[0]
            value = combine(parts(), per_frame)
            with self._lock:
                for k in [k for k, (_, refs) in self._entries.items() if any(r() is None for r in refs)]:
                    del self._entries[k]
                    self._key_locks.pop(k, None)
                self._entries[key] = (value, tuple(weakref.ref(src) for src in sources))
        return value

    def clear(self) -> None:
        with self._lock:
            self._entries.clear()
            self._key_locks.clear()


_COMBINED = _CombinedInputs()


def compute_task(spec: TaskSpec, *deps: TaskResult) -> TaskResult:
    """Run one task on its upstream results (dask calls this in a worker)."""
    start = time.perf_counter()
    began = time.time()
    bad = [d for d in deps if d.status not in OK_STATUSES]
    if bad:
        return TaskResult(spec.name, spec.node, spec.out_frames, "skipped",
                          error={"cause": f"upstream {bad[0].name} {bad[0].status}"})
    if spec.progress == "json" and warnings.showwarning is not json_warning \
            and multiprocessing.current_process().name != "MainProcess":
        warnings.showwarning = json_warning  # a worker process: its stderr is the farm log too
    stage = None
    try:
        # Files that upstream writers staged in this run are read at their paths by their
        # readers (report.Html embeds report PNGs): put them there now, undoably.
        publish([entry for dep in deps for entry in dep.staged])
        with staging(spec.stage if spec.writes else None) as stage:
            values = _compute(spec, deps)
    except Exception as err:
        error = err if isinstance(err, NodeError) else NodeError(
            spec.node, spec.node_cls.type_name, f"{type(err).__name__}: {err}")
        record = {
            "node": spec.node, "type": spec.node_cls.type_name,
            "frames": list(spec.out_frames) if spec.name.frames is not None else None,
            "key": spec.key, "exception": type(err.__cause__ or err).__name__, "message": str(error),
            "reason": error.message,
            "port": getattr(error, "port", ""), "bad_input": bool(getattr(error, "bad_input", False)),
            "traceback": format_exception(err),
            "input_keys": {str(slot): [spec.description["inputs"][str(slot)][i][0] for i in range(len(pieces))]
                           for slot, pieces in spec.inputs},
            "time": time.time(),
        }
        return TaskResult(spec.name, spec.node, spec.out_frames, "failed", error=record,
                          seconds=time.perf_counter() - start,
                          staged=tuple(stage.entries()) if stage is not None else (), started=began)
    staged = tuple(stage.entries()) if stage is not None else ()
    if spec.cacheable and spec.cache_root is not None:
        _STORES.submit(_store_task, spec, values, {entry.final: entry.staged for entry in staged})
    return TaskResult(spec.name, spec.node, spec.out_frames, "executed", values,
                      seconds=time.perf_counter() - start, staged=staged, started=began)


def _compute(spec: TaskSpec, deps: Sequence[TaskResult]) -> dict[str, PortType]:
    """The node's values for one task: its inputs joined from `deps`, run, trimmed to the chunk."""
    node = spec.node_cls(spec.params, node_id=spec.node)
    node.run_log = [dict(record) for record in spec.run_log]
    node.cache_root = spec.cache_root  # the run's cache folder (None: no cache), for nodes that keep
    # finer entries of their own there (nodegraph.takes.cached_take: one per file read)
    inputs: dict[str, Any] = {}
    for slot, pieces in spec.inputs:
        value = _COMBINED.get(deps, pieces, pieces[0][2] >= 0)
        if slot.index is not None:  # a list port: one value per connection, in edge order
            inputs.setdefault(slot.port, []).append(value)
        else:
            inputs[slot.port] = value
    values = execute(node, inputs, range(*spec.frames), range(*spec.full_frames), progress_callback(spec.progress, spec.node, spec.out_frames),
                     seed=task_seed(spec.key), device=spec.device, wanted=spec.description.get("outputs"))
    return _trim(node, values, spec.frames, spec.out_frames)


def compute_logged_task(spec: TaskSpec, count: int, *args: Any) -> TaskResult:
    """`compute_task` for a node that `uses_run_log`: `args` are its `count` upstream results,
    then the meta records of every task upstream of it (its `run_log`)."""
    return compute_task(dataclasses.replace(spec, run_log=tuple(args[count:])), *args[:count])


def _store_task(spec: TaskSpec, values: dict[str, PortType], where: Mapping[str, str] | None = None) -> None:
    """Write a task's values (and a writer's file record) into the cache.

    `where`: absolute path -> staged copy of each file the writer wrote (see
    `nodegraph.staging`): the record holds the size and mtime the destination gets when the run
    commits the file by a rename, so the next run finds it intact."""
    store = Cache(spec.cache_root)
    written = _written_files(values) if spec.writes else None
    where = dict(where or {})
    try:
        copies = None
        if written is not None:
            sizes = [os.stat(where.get(os.path.abspath(path), path)).st_size for path in written.paths]
            copies = list(written.paths) if sum(sizes) <= COPY_LIMIT else None
        store.store(spec.key, values, spec.description, copies=copies, where=where)
        if written is not None:
            store.record_written(spec.key, written, where=where)
    except OSError as err:
        warnings.warn(f"could not cache {spec.name}: {err}", RuntimeWarning)


class _BackgroundStores:
    """Cache writes off the critical path, for the in-process schedulers.

    While `active` (set by `in_process_run`), `submit` hands the write
    to one background thread and the task returns at once, so that its dependents start
    while its values are being written (saving, hashing and renaming a 210 MB entry takes
    ~0.6 s). `drain` waits for every pending write and is called before the run returns, so
    a finished run has all its entries on disk, exactly as with synchronous writes. Elsewhere
    (worker processes, distributed workers) writes stay synchronous.
    """

    def __init__(self) -> None:
        self.active = False
        self._executor: Any = None
        self._pending: list[Any] = []
        self._lock = threading.Lock()

    def submit(self, fn: Callable[..., None], *args: Any) -> None:
        if not self.active:
            fn(*args)
            return
        with self._lock:
            if self._executor is None:
                from concurrent.futures import ThreadPoolExecutor

                self._executor = ThreadPoolExecutor(1, thread_name_prefix="nodegraph-cache")
            self._pending.append(self._executor.submit(fn, *args))
            backlog = [f for f in self._pending if not f.done()]
        if len(backlog) > 4:  # back-pressure: never hold more than a few unwritten results
            backlog[0].result()

    def drain(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for future in pending:
            future.result()


_STORES = _BackgroundStores()


PRELOAD_WAIT_S = 120.0
"""How long a run waits at its end for a preload still importing (`wait_for_preloads`)."""

_PRELOADS: list[threading.Thread] = []


def wait_for_preloads(timeout: float = PRELOAD_WAIT_S) -> None:
    """Wait for the preload threads still importing (`nodegraph.runner.run` calls it as it ends).

    A run that failed within seconds returned, and the `nodegraph` command exited, while the
    daemon preload thread was most likely still inside an import (torch, numba's kernels): the
    process aborted after printing its exit-2 error ("terminate called without an active
    exception", exit -6; once in 419 probes of bench/probe_bad_inputs.py, stabilize.json with
    init_group=nosuch beside a CI run). Waiting at interpreter exit instead (atexit) let the
    import finish after torch's own exit hooks had run, and torch printed ignored exceptions.
    """
    for thread in _PRELOADS:
        thread.join(timeout)


def import_now(modules: Sequence[str]) -> None:
    """Import `modules` on this thread, now (`Node.import_first`; `preload` runs it on its own
    thread); an import that fails here is left for the node itself to report."""
    import importlib

    for name in dict.fromkeys(modules):
        if name not in sys.modules:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the node's own import raises it properly
                pass


def preload(modules: Sequence[str]) -> None:
    """Import slow modules that planned nodes will import (`Node.preload`) in a background
    thread, so the import overlaps upstream work instead of delaying the node. An import
    that fails here is left for the node itself to report. The run waits for the thread as it
    ends (`wait_for_preloads`)."""
    missing = [m for m in dict.fromkeys(modules) if m not in sys.modules]
    if not missing:
        return
    thread = threading.Thread(target=import_now, args=(missing,), name="nodegraph-preload", daemon=True)
    _PRELOADS[:] = [t for t in _PRELOADS if t.is_alive()] + [thread]
    thread.start()


def _written_files(values: Mapping[str, PortType]) -> Files | None:
    """The Files a writer's outputs list (several Files ports are joined)."""
    parts = [v for v in values.values() if isinstance(v, Files)]
    return Files.merge_chunks(parts) if parts else None


@contextlib.contextmanager
def in_process_run() -> Iterator[None]:
    """Around a run whose tasks run in this process: share joins of the same upstream chunks
    and write the cache in the background; every pending write is done when the block ends
    normally, and the shared joins are dropped however it ends."""
    _STORES.active = _COMBINED.active = True
    try:
        yield
        _STORES.drain()
    finally:
        _STORES.active = _COMBINED.active = False
        _COMBINED.clear()


def load_task(spec: TaskSpec) -> TaskResult:
    """Read a task's values from the cache, rewriting a writer's changed files from the
    entry's copies first when planned so (dask calls this in a worker)."""
    start = time.perf_counter()
    store = Cache(spec.cache_root)
    status = "cached"
    stage = None
    try:
        with staging(spec.stage if spec.restore else None) as stage:  # restored files are held back too
            if spec.restore:
                status = "restored" if store.restore_written(spec.key) else "cached"
        values = store.load(spec.key)
    except (CorruptEntry, KeyError) as err:
        return TaskResult(spec.name, spec.node, spec.out_frames, "corrupt", error={"cause": str(err)},
                          staged=tuple(stage.entries()) if stage is not None else ())
    except OSError as err:
        return TaskResult(spec.name, spec.node, spec.out_frames, "corrupt",
                          error={"cause": f"cannot restore written files: {err}"},
                          staged=tuple(stage.entries()) if stage is not None else ())
    return TaskResult(spec.name, spec.node, spec.out_frames, status, values,
                      seconds=time.perf_counter() - start, staged=tuple(stage.entries()) if stage is not None else ())


def task_meta(result: TaskResult) -> dict[str, Any]:
    """The task's record without its values (what the run's report and progress read)."""
    return result.meta()


def task_staged(result: TaskResult) -> tuple[StagedFile, ...]:
    """The files a writer task held back (what the run commits or discards)."""
    return result.staged
