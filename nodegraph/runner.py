"""Run a plan on dask: any local scheduler or a `dask.distributed` cluster.

Every task catches its own failure and returns it as a record, so one failing node never
stops independent branches; tasks below a failure are skipped. The run then reports each
failed chunk (node id, frames, exception, traceback, input keys) and ends non-zero.

Outputs are all-or-nothing (`nodegraph.staging`): writer tasks write into staging folders
next to their destinations, and the run moves the staged files onto the destinations only
when every task succeeded; a failed run deletes them ("nothing written: ... held back").
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing
import os
import re
import sys
import threading
import time
import warnings
import weakref
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

from .cache import COPY_LIMIT, Cache, CorruptEntry, cache_dir_from_env
from .errors import NodeError, SchedulerError
from .graph import Graph
from .node import Node, _field_flag, execute, format_exception, task_seed
from .pathcheck import check_output_paths
from .schedule import Plan, TaskPlan, explain_miss, plan_run
from .staging import StagedFile, commit, discard, new_token, publish, staging
from .types import Files, PortType

__all__ = ["TaskSpec", "TaskResult", "RunResult", "run", "explain", "check_scheduler", "SCHEDULERS",
           "CONNECT_TIMEOUT_S"]

SCHEDULERS = ("sync", "threads", "processes")
CONNECT_TIMEOUT_S = 10.0
"""Seconds to wait for a dask.distributed scheduler to answer before the run fails (exit 2)."""

_ADDRESS = re.compile(r"(?:(?:tcp|tls|ucx|ws|wss)://)?[^\s/]+:\d+|inproc://\S+")
_OK = ("executed", "cached", "restored")


@dataclass(frozen=True)
class TaskSpec:
    """Everything a worker needs to run one task (plain data plus the node class)."""

    name: str
    node: str
    node_cls: type[Node]
    params: dict[str, Any]
    frames: tuple[int, int]
    out_frames: tuple[int, int]
    full_frames: tuple[int, int]
    inputs: tuple[tuple[str, tuple[tuple[int, str, int, int], ...]], ...]
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

    name: str
    node: str
    frames: tuple[int, int]
    status: str  # executed | cached | restored | failed | skipped | corrupt
    values: dict[str, PortType] | None = None
    error: dict[str, Any] | None = None
    seconds: float = 0.0
    staged: tuple[StagedFile, ...] = ()  # a writer's files held back in staging folders

    def meta(self) -> dict[str, Any]:
        return {"name": self.name, "node": self.node, "frames": list(self.frames), "status": self.status,
                "error": self.error, "seconds": self.seconds}


_STDERR_LOCK = threading.Lock()


def emit_json(event: Mapping[str, Any]) -> None:
    """Write one JSON line to stderr in one write (threads never interleave inside a line)."""
    line = json.dumps(event, default=str) + "\n"
    with _STDERR_LOCK:
        sys.stderr.write(line)
        sys.stderr.flush()


def _progress_callback(spec: TaskSpec) -> Callable[[float, str], None] | None:
    if spec.progress == "none":
        return None
    last = [0.0]

    def report(fraction: float, message: str) -> None:
        now = time.monotonic()
        if now - last[0] < 1.0 and fraction < 1.0:
            return
        last[0] = now
        if spec.progress == "json":
            emit_json({"event": "progress", "node": spec.node, "frames": list(spec.out_frames),
                       "fraction": round(fraction, 4), "message": message})
        else:
            print(f"  {spec.node} [{spec.out_frames[0]}:{spec.out_frames[1]}] {100 * fraction:5.1f}% {message}",
                  file=sys.stderr, flush=True)
    return report


def _trim(node: Node, values: dict[str, PortType], frames: tuple[int, int],
          out: tuple[int, int]) -> dict[str, PortType]:
    if frames == out:
        return values
    a, b = out[0] - frames[0], out[1] - frames[0]
    return {port: (value.slice_frames(a, b) if node.outputs[port].per_frame else value)
            for port, value in values.items()}


def _combine(parts: list[PortType], per_frame: bool) -> PortType:
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
        self.active = False  # set by `_execute` around a sync or threads run
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
            return _combine(parts(), per_frame)
        sources = [deps[p[0]] for p in pieces]
        key = tuple((id(src), port, lo, hi) for src, (_, port, lo, hi) in zip(sources, pieces)) + (per_frame,)
        with self._lock:
            key_lock = self._key_locks.setdefault(key, threading.Lock())
        with key_lock:
            with self._lock:
                hit = self._entries.get(key)
                if hit is not None and self._valid(hit[1], sources):
                    return hit[0]
            value = _combine(parts(), per_frame)
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
    bad = [d for d in deps if d.status not in _OK]
    if bad:
        return TaskResult(spec.name, spec.node, spec.out_frames, "skipped",
                          error={"cause": f"upstream {bad[0].name} {bad[0].status}"})
    if spec.progress == "json" and warnings.showwarning is not _json_warning \
            and multiprocessing.current_process().name != "MainProcess":
        warnings.showwarning = _json_warning  # a worker process: its stderr is the farm log too
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
            "frames": list(spec.out_frames) if spec.name.split("|")[1] != "all" else None,
            "key": spec.key, "exception": type(err.__cause__ or err).__name__, "message": str(error),
            "reason": error.message,
            "port": getattr(error, "port", ""), "bad_input": bool(getattr(error, "bad_input", False)),
            "traceback": format_exception(err),
            "input_keys": {port: [spec.description["inputs"][port][i][0] for i in range(len(pieces))]
                           for port, pieces in spec.inputs},
            "time": time.time(),
        }
        return TaskResult(spec.name, spec.node, spec.out_frames, "failed", error=record,
                          seconds=time.perf_counter() - start,
                          staged=tuple(stage.entries()) if stage is not None else ())
    staged = tuple(stage.entries()) if stage is not None else ()
    if spec.cacheable and spec.cache_root is not None:
        _STORES.submit(_store_task, spec, values, {entry.final: entry.staged for entry in staged})
    return TaskResult(spec.name, spec.node, spec.out_frames, "executed", values,
                      seconds=time.perf_counter() - start, staged=staged)


def _compute(spec: TaskSpec, deps: Sequence[TaskResult]) -> dict[str, PortType]:
    """The node's values for one task: its inputs joined from `deps`, run, trimmed to the chunk."""
    node = spec.node_cls(spec.params, node_id=spec.node)
    node.run_log = [dict(record) for record in spec.run_log]
    inputs: dict[str, Any] = {}
    for port, pieces in spec.inputs:
        value = _COMBINED.get(deps, pieces, pieces[0][2] >= 0)
        name, many, _ = port.partition("#")
        if many:  # a list port: one value per connection, in edge order ("port#0", "port#1", ...)
            inputs.setdefault(name, []).append(value)
        else:
            inputs[name] = value
    values = execute(node, inputs, range(*spec.frames), range(*spec.full_frames), _progress_callback(spec),
                     seed=task_seed(spec.key), device=spec.device)
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

    While `active` (set by `_execute` around a sync or threads run), `submit` hands the write
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

_IN_PROCESS = ("sync", "threads")
"""Schedulers whose tasks run in this process (shared joins, background cache writes, preloads)."""


def _preload(modules: Sequence[str]) -> None:
    """Import slow modules that planned nodes will import (`Node.preload`) in a background
    thread, so the import overlaps upstream work instead of delaying the node. An import
    that fails here is left for the node itself to report."""
    missing = [m for m in dict.fromkeys(modules) if m not in sys.modules]
    if not missing:
        return

    def work() -> None:
        import importlib

        for name in missing:
            try:
                importlib.import_module(name)
            except Exception:  # noqa: BLE001 - the node's own import raises it properly
                pass

    threading.Thread(target=work, name="nodegraph-preload", daemon=True).start()


def _written_files(values: Mapping[str, PortType]) -> Files | None:
    """The Files a writer's outputs list (several Files ports are joined)."""
    parts = [v for v in values.values() if isinstance(v, Files)]
    return Files.merge_chunks(parts) if parts else None


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
    return result.meta()


def task_staged(result: TaskResult) -> tuple[StagedFile, ...]:
    """The files a writer task held back (what the run commits or discards)."""
    return result.staged


@dataclass
class RunResult:
    """Outcome of a run.

    Attributes:
        outputs: target node id -> output port -> value (chunks concatenated); a failed run
            leaves out the writers it held back.
        tasks: one record per scheduled task: name, node, frames, status, error, seconds.
        plan: the plan that ran.
        held_back: writer nodes whose files a failed run discarded (outputs are all-or-nothing:
            a run writes files only when every task succeeded), with `held_back_cause`.
    """

    outputs: dict[str, dict[str, PortType]]
    tasks: list[dict[str, Any]]
    plan: Plan
    seconds: float = 0.0
    failures: list[dict[str, Any]] = field(default_factory=list)
    held_back: list[str] = field(default_factory=list)
    held_back_cause: str = ""  # "node 'load' failed", or "tasks were skipped"

    def count(self, status: str, node: str | None = None) -> int:
        return sum(1 for t in self.tasks if t["status"] == status and (node is None or t["node"] == node))

    def executed(self, node: str | None = None) -> int:
        """Tasks that ran (not read from the cache), for `node` or all."""
        return self.count("executed", node)

    @property
    def ok(self) -> bool:
        return not self.failures and not any(t["status"] == "skipped" for t in self.tasks)

    @property
    def exit_code(self) -> int:
        if self.ok:
            return 0
        if self.failures and all(f.get("bad_input") for f in self.failures):
            return 2
        return 1

    def failure_groups(self) -> list[list[dict[str, Any]]]:
        """The failures grouped by node and message: a node failing the same way in several
        chunks is one group (its records in frame order); groups in order of first failure."""
        groups: dict[tuple, list[dict[str, Any]]] = {}
        for f in self.failures:
            key = (f.get("node"), f.get("port", ""), f.get("reason", f.get("message")), bool(f.get("bad_input")))
            groups.setdefault(key, []).append(f)
        return list(groups.values())

    def failure_line(self, group: list[dict[str, Any]]) -> str:
        """One line for a group of `failure_groups`: the message once, with the chunks it hit."""
        first = group[0]
        if len(group) == 1:
            return first["message"]
        where = NodeError(first["node"], first["type"], first.get("reason", ""), port=first.get("port", ""))
        chunks = sum(1 for t in self.tasks if t["node"] == first["node"])
        if len(group) == chunks:
            return f"{where} (in {len(group)} of {chunks} chunks)"
        frames = ", ".join(f"{f['frames'][0]}:{f['frames'][1]}" for f in group[:4] if f.get("frames"))
        more = ", ..." if len(group) > 4 else ""
        return f"{where} (in {len(group)} of {chunks} chunks: frames {frames}{more})"

    def summary(self) -> str:
        restored = f", {self.count('restored')} restored" if self.count("restored") else ""
        lines = [f"{len(self.tasks)} tasks: {self.executed()} executed, {self.count('cached')} cached{restored}, "
                 f"{self.count('failed')} failed, {self.count('skipped')} skipped ({self.seconds:.2f} s)"]
        for group in self.failure_groups():
            lines.append(f"FAILED {self.failure_line(group)}")
        if self.held_back:
            lines.append(f"nothing written: {len(self.held_back)} writer(s) held back "
                         f"({', '.join(self.held_back)}) because {self.held_back_cause}")
        return "\n".join(lines)


class _Reporter:
    """Per-node progress: tqdm bars on a terminal, JSON lines otherwise, or nothing."""

    def __init__(self, plan: Plan, names: list[str], mode: str):
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

    def close(self, result: RunResult) -> None:
        for bar in self.bars.values():
            bar.close()
        if self.mode == "json":
            self.emit({"event": "end", "executed": result.executed(), "cached": result.count("cached"),
                       "failed": result.count("failed"), "skipped": result.count("skipped"),
                       "held_back": result.held_back, "seconds": round(result.seconds, 3)})


def _specs(plan: Plan, names: list[str], cache: Cache | None, progress: str, stage: str = "") -> dict[str, TaskSpec]:
    full = (plan.frames.start, plan.frames.stop)
    specs = {}
    for name in names:
        task = plan.tasks[name]
        deps = task.deps
        inputs = tuple((port, tuple((deps.index(p.task), p.port, p.start, p.stop) for p in pieces))
                       for port, pieces in task.inputs.items())
        specs[name] = TaskSpec(name, task.node, type(plan.nodes[task.node]),
                               plan.graph.resolved_params(task.node), task.frames, task.out_frames, full,
                               inputs, task.key, task.description,
                               str(cache.root) if cache is not None else None, task.cacheable, progress,
                               writes=task.writes, restore=task.restore, device=task.device,
                               stage=stage if task.writes else "")
    return specs


def _dask_graph(plan: Plan, names: list[str], specs: dict[str, TaskSpec]) -> dict[str, Any]:
    dsk: dict[str, Any] = {}
    for name in names:
        task = plan.tasks[name]
        if task.hit:
            dsk[name] = (load_task, specs[name])
        elif specs[name].node_cls.uses_run_log:
            upstream = [f"meta|{a}" for a in _ancestors(plan, name) if a in specs]  # those this run has
            dsk[name] = (compute_logged_task, specs[name], len(task.deps), *task.deps, *upstream)
        else:
            dsk[name] = (compute_task, specs[name], *task.deps)
        dsk[f"meta|{name}"] = (task_meta, name)
        if task.writes and (not task.hit or task.restore):
            dsk[f"stage|{name}"] = (task_staged, name)
    return dsk


def _ancestors(plan: Plan, name: str) -> list[str]:
    """Every task `name` depends on, directly or not, in plan order."""
    seen: set[str] = set()
    todo = list(plan.tasks[name].deps)
    while todo:
        dep = todo.pop()
        if dep not in seen:
            seen.add(dep)
            todo.extend(plan.tasks[dep].deps)
    return [t for t in plan.tasks if t in seen]


def _execute(dsk: dict[str, Any], meta_keys: list[str], value_keys: list[str], scheduler: Any,
             reporter: _Reporter, workers: int | None,
             resources: Mapping[str, dict[str, float]] | None = None
             ) -> tuple[list[dict], list[TaskResult], list[StagedFile]]:
    """Run the dask graph; return the meta records, the values asked for, and every file the
    run's writers staged (`stage|` keys)."""
    stage_keys = [key for key in dsk if key.startswith("stage|")]
    keys = meta_keys + value_keys + stage_keys
    count = len(meta_keys) + len(value_keys)
    if isinstance(scheduler, str) and scheduler in SCHEDULERS and all(
            task[0] in (load_task, task_meta, task_staged) for task in dsk.values()):
        # Everything is cached: read the entries in-process (no dask import, no pool start-up).
        loaded: dict[str, TaskResult] = {}
        for key, task in dsk.items():
            if task[0] is load_task:
                loaded[key] = load_task(task[1])
                reporter.update(loaded[key].meta())
        return ([loaded[k.partition("|")[2]].meta() for k in meta_keys], [loaded[k] for k in value_keys],
                [entry for k in stage_keys for entry in loaded[k.partition("|")[2]].staged])
    if isinstance(scheduler, str) and scheduler in SCHEDULERS:
        import dask.local
        from dask.callbacks import Callback

        class _Progress(Callback):
            def _posttask(self, key, result, dsk, state, id):  # noqa: A002 (dask's signature)
                if isinstance(result, TaskResult):
                    reporter.update(result.meta())

        if scheduler == "sync":
            get = dask.local.get_sync
            kwargs = {}
        elif scheduler == "threads":
            import dask.threaded

            get, kwargs = dask.threaded.get, ({"num_workers": workers} if workers else {})
        else:
            import dask.multiprocessing

            get, kwargs = dask.multiprocessing.get, ({"num_workers": workers} if workers else {})
        _STORES.active = _COMBINED.active = scheduler in _IN_PROCESS
        try:
            with _Progress():
                out = get(dsk, keys, **kwargs)
            _STORES.drain()
        finally:
            _STORES.active = _COMBINED.active = False
            _COMBINED.clear()
        return (list(out[: len(meta_keys)]), list(out[len(meta_keys):count]),
                [entry for staged in out[count:] for entry in staged])
    from distributed import Client, as_completed

    client = scheduler if isinstance(scheduler, Client) else _connect(scheduler)
    try:
        offered: set[str] = set()
        for worker in client.scheduler_info().get("workers", {}).values():
            offered |= set(worker.get("resources") or {})
        # Only ask for resources some worker offers, else the tasks would wait forever.
        wanted = {key: {r: amount for r, amount in res.items() if r in offered}
                  for key, res in (resources or {}).items()}
        wanted = {key: res for key, res in wanted.items() if res}
        # One submit per task (dsk is in dependency order): per-task resources are honoured this
        # way, whereas `Client.get(resources=...)` applies one requirement to every task.
        submitted: dict[str, Any] = {}
        for key, (func, *args) in dsk.items():
            args = [submitted[a] if isinstance(a, str) and a in submitted else a for a in args]
            submitted[key] = client.submit(func, *args, key=key, pure=False, resources=wanted.get(key))
        metas_f, values_f = [submitted[k] for k in meta_keys], [submitted[k] for k in value_keys]
        for future in as_completed(metas_f):
            reporter.update(future.result())
        metas = client.gather(metas_f)
        values = client.gather(values_f)
        staged = client.gather([submitted[k] for k in stage_keys])
    finally:
        if client is not scheduler:
            client.close()
    return metas, values, [entry for files in staged for entry in files]


def check_scheduler(scheduler: Any) -> None:
    """Raise SchedulerError unless `scheduler` is a local scheduler's name or a dask.distributed
    address (`tcp://host:port`); any other object (a `distributed.Client`) is passed on as is."""
    if isinstance(scheduler, str) and scheduler not in SCHEDULERS and not _ADDRESS.fullmatch(scheduler):
        raise SchedulerError(scheduler, "expected sync, threads, processes or a dask.distributed address "
                                        f"tcp://host:port, found {scheduler!r}")


def _connect(address: str) -> Any:
    """A `distributed.Client` of the scheduler at `address`, or SchedulerError after
    `CONNECT_TIMEOUT_S` (distributed's own default waits 30 s)."""
    from distributed import Client

    try:
        return Client(address, timeout=CONNECT_TIMEOUT_S)
    except OSError as err:  # distributed raises OSError for timeouts, refusals and unknown hosts
        raise SchedulerError(address, f"expected a dask.distributed scheduler answering at {address}, "
                                      f"found none within {CONNECT_TIMEOUT_S:g} s") from err


def _resolve_cache(cache: Cache | str | os.PathLike | bool | None) -> Cache | None:
    if cache is False:
        return None
    if cache is None or cache is True:
        return Cache(cache_dir_from_env())
    return cache if isinstance(cache, Cache) else Cache(cache)


def _progress_mode(progress: str | bool | None) -> str:
    if progress in (False, "none"):
        return "none"
    if progress in ("tty", "json"):
        return str(progress)
    if progress is None:
        return "none"
    return "tty" if sys.stderr.isatty() else "json"


def run(graph: Graph | str | os.PathLike, *, frames: range | None = None, chunk: int = 64,
        scheduler: Any = "threads", cache: Cache | str | os.PathLike | bool | None = None,
        outputs: Iterable[str] | None = None, force: Iterable[str] = (),
        progress: str | bool | None = None, workers: int | None = None,
        parameters: Mapping[str, Any] | None = None, device: str = "auto") -> RunResult:
    """Run a graph and return the outputs of its target nodes.

    Args:
        graph: a Graph or a path to a graph JSON file.
        frames: frames to compute (default: what the sources produce).
        chunk: frames per chunk for framewise and windowed nodes.
        scheduler: "sync", "threads", "processes", a `dask.distributed` address
            ("tcp://host:port") or a `distributed.Client`.
        cache: cache folder or Cache; None: `NODEGRAPH_CACHE` or `.nodegraph/cache`;
            False: no cache.
        outputs: node ids whose outputs to return (default: the graph's sinks).
        force: node ids to recompute even when cached (and their descendants).
        progress: "tty", "json", "auto" (tty when stderr is a terminal) or None (quiet).
        workers: number of workers for the local thread/process pools.
        parameters: graph parameters by name (e.g. {"capture": "shot.npz"}).
        device: "auto" (CUDA where the worker's torch sees a GPU), "cpu" or "cuda": the
            `self.device` of nodes whose graph entry does not pin one. On a dask.distributed
            cluster, tasks of nodes declaring `resources = {"gpu": 1}` are sent only to
            workers started with `--resources gpu=1` (one at a time per GPU) when the cluster
            has such workers and the device is not "cpu".
    Returns:
        RunResult: `outputs[node][port]`, task records, failures, `exit_code`.
    Raises:
        GraphError: the graph or its parameters are invalid (nothing ran).
        NodeError: a node rejected its parameters or input files while planning.
        SchedulerError: `scheduler` is unknown, or no dask.distributed scheduler answers at
            its address within `CONNECT_TIMEOUT_S`.
    """
    if not isinstance(graph, Graph):
        graph = Graph.load(graph)
    if parameters:
        graph.apply(dict(parameters))
    if device not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device: expected auto, cpu or cuda, found {device!r}")
    check_scheduler(scheduler)
    store = _resolve_cache(cache)
    mode = _progress_mode(progress)
    started = time.perf_counter()
    with _warnings_as_events(mode):
        return _run(graph, frames, chunk, scheduler, store, outputs, force, mode, workers, device, started)


def _run(graph: Graph, frames: range | None, chunk: int, scheduler: Any, store: Cache | None,
         outputs: Iterable[str] | None, force: Iterable[str], mode: str, workers: int | None, device: str,
         started: float) -> RunResult:
    token = new_token()  # names this run's staging folders (see nodegraph.staging)
    for attempt in range(2):
        plan = plan_run(graph, frames=frames, chunk=chunk, cache=store, targets=list(outputs or []) or None,
                        force=force, device=device)
        if attempt == 0:
            check_output_paths(plan)  # outputs that would destroy inputs, unwritable folders: exit 2
        names = plan.needed()
        specs = _specs(plan, names, store, mode, token)
        dsk = _dask_graph(plan, names, specs)
        value_names = [t for node in plan.targets for t in plan.by_node[node]]
        reporter = _Reporter(plan, names, mode)
        gpu_tasks = {n for n in names if not plan.tasks[n].hit and plan.tasks[n].device != "cpu"
                     and plan.nodes[plan.tasks[n].node].resources}
        writers = _writing(plan, names)
        if scheduler in _IN_PROCESS:
            _preload([m for n in names if not plan.tasks[n].hit for m in plan.nodes[plan.tasks[n].node].preload])
        try:
            metas, results, staged = _execute(dsk, [f"meta|{n}" for n in names], value_names, scheduler, reporter,
                                              workers, {n: dict(plan.nodes[plan.tasks[n].node].resources)
                                                        for n in gpu_tasks})
        except BaseException:
            discard([], token, _destinations(plan, writers))
            raise
        if any(m["status"] == "corrupt" for m in metas) and attempt == 0:
            discard(staged, token, _destinations(plan, writers))
            reporter.close(RunResult({}, metas, plan))
            continue  # corrupt entries were removed: plan again, they are now misses
        break
    by_name = dict(zip(value_names, results))
    out: dict[str, dict[str, PortType]] = {}
    for node in plan.targets:
        parts = [by_name[name] for name in plan.by_node[node]]
        if any(p.status not in _OK for p in parts):
            continue
        out[node] = {}
        for port, decl in plan.nodes[node].outputs.items():
            out[node][port] = _combine([p.values[port] for p in parts], decl.per_frame)
    failures = [m["error"] for m in metas if m["status"] == "failed"]
    held_back: list[str] = []
    cause = ""
    if not failures and all(m["status"] in _OK for m in metas):
        try:
            commit(staged)
        except OSError as err:
            failures.append(_commit_failure(err))
    else:
        discard(staged, token, _destinations(plan, writers))
        held_back = writers
        for node in held_back:
            out.pop(node, None)  # its Files name paths this run did not write
        failed = list(dict.fromkeys(m["node"] for m in metas if m["status"] == "failed"))
        cause = (f"node{'s' if len(failed) > 1 else ''} {', '.join(repr(n) for n in failed)} failed" if failed
                 else "tasks were skipped")
    result = RunResult(out, metas, plan, time.perf_counter() - started, failures, held_back, cause)
    _record(plan, metas, store)
    reporter.close(result)
    return result


def _writing(plan: Plan, names: Sequence[str]) -> list[str]:
    """Writer nodes of `names` that would write files in this run (not intact cache hits)."""
    return list(dict.fromkeys(plan.tasks[n].node for n in names
                              if plan.tasks[n].writes and (not plan.tasks[n].hit or plan.tasks[n].restore)))


def _destinations(plan: Plan, nodes: Iterable[str]) -> list[str]:
    """The output path values of `nodes` (where their staging folders may be)."""
    paths = []
    for nid in nodes:
        node = plan.nodes[nid]
        for name in node.Params.model_fields:
            value = getattr(node.params, name)
            if _field_flag(node.Params, name, "output_file", False) and isinstance(value, str) and value:
                paths.append(value)
    return paths


def _commit_failure(err: OSError) -> dict[str, Any]:
    message = f"could not move the run's staged outputs onto their paths: {err}"
    return {"node": "", "type": "nodegraph", "frames": None, "message": message, "reason": message, "port": "",
            "bad_input": False, "traceback": "", "exception": type(err).__name__, "input_keys": {},
            "time": time.time()}


class _warnings_as_events:
    """In JSON-lines progress mode, print warnings as {"event": "warning"} lines on stderr
    (so that every stderr line of a farm log is JSON); otherwise leave them alone."""

    def __init__(self, mode: str):
        self.mode = mode
        self.saved: Any = None

    def __enter__(self) -> None:
        if self.mode == "json":
            self.saved = warnings.showwarning
            warnings.showwarning = _json_warning

    def __exit__(self, *exc: Any) -> None:
        if self.saved is not None:
            warnings.showwarning = self.saved


def _json_warning(message: Any, category: type, filename: str, lineno: int, file: Any = None,
                  line: str | None = None) -> None:
    emit_json({"event": "warning", "category": category.__name__, "message": str(message),
               "where": f"{os.path.basename(filename)}:{lineno}"})


def _record(plan: Plan, metas: list[dict[str, Any]], store: Cache | None) -> None:
    """Write error records of failed chunks and the key descriptions used (for --explain)."""
    if store is None:
        return
    by_node: dict[str, dict[str, Any]] = {}
    for meta in metas:
        task = plan.tasks[meta["name"]]
        frames = tuple(meta["frames"]) if task.mode != "static" else None
        if meta["status"] == "failed":
            meta["error"]["record"] = str(store.write_error(meta["error"]))
        elif meta["status"] in _OK:
            store.clear_error(task.node, frames if task.mode == "chunk" else None)
            by_node.setdefault(task.node, store.read_last(task.node))[task.name] = task.description
    for node, descriptions in by_node.items():
        store.write_last(node, descriptions)


def explain(graph: Graph, *, frames: range | None = None, chunk: int = 64,
            cache: Cache | str | os.PathLike | bool | None = None, outputs: Iterable[str] | None = None,
            force: Iterable[str] = ()) -> list[dict[str, Any]]:
    """Per node and chunk: would it be a cache hit, and if not, why. Runs nothing.

    Returns:
        one dict per task: node, frames, hit (bool), reason.
    """
    store = _resolve_cache(cache)
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
            reason = explain_miss(task, last.get(name) or _same_node_other_chunk(last, task), store)
        rows.append({"node": task.node, "task": name, "frames": list(task.out_frames), "hit": task.hit,
                     "reason": reason})
    return rows


def _same_node_other_chunk(last: dict[str, Any], task: TaskPlan) -> dict[str, Any] | None:
    """For a sequence or static task whose frame range changed, compare with its last run."""
    if task.mode == "chunk" or not last:
        return None
    return next(iter(last.values()))

