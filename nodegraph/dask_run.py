"""The dask side of a run: a plan's tasks as a dask graph, executed on a local scheduler
(sync, threads, processes) or a `dask.distributed` cluster.

Everything cached is read in-process without importing dask. On a cluster each task is
submitted with the resources its node declares (`resources = {"gpu": 1}`), when some worker
offers them.

The dask keys are text: a task's value under its name's text ("fit|0:64"), its record under
"meta|fit|0:64" and a writer's staged files under "stage|fit|0:64" (`value_key`, `meta_key`,
`stage_key`); they are made from `TaskName`s and never taken apart again.
"""

from __future__ import annotations

import contextlib
import re
from typing import Any, Mapping

from .cache import Cache
from .errors import SchedulerError
from .plan_names import TaskName
from .progress import Reporter
from .schedule import Plan
from .staging import StagedFile
from .tasks import (IN_PROCESS, TaskResult, TaskSpec, compute_logged_task, compute_task, in_process_run,
                    load_task, task_meta, task_staged)

__all__ = ["SCHEDULERS", "CONNECT_TIMEOUT_S", "check_scheduler", "task_specs", "dask_graph", "execute",
           "value_key", "meta_key", "stage_key"]

SCHEDULERS = ("sync", "threads", "processes")
"""The local schedulers by name (anything else is a dask.distributed address or Client)."""

CONNECT_TIMEOUT_S = 10.0
"""Seconds to wait for a dask.distributed scheduler to answer before the run fails (exit 2)."""

_ADDRESS = re.compile(r"(?:(?:tcp|tls|ucx|ws|wss)://)?[^\s/]+:\d+|inproc://\S+")


def value_key(name: TaskName) -> str:
    """The dask key of a task's `TaskResult`."""
    return str(name)


def meta_key(name: TaskName) -> str:
    """The dask key of a task's record (`TaskResult.meta`)."""
    return f"meta|{name}"


def stage_key(name: TaskName) -> str:
    """The dask key of the files a writer task staged."""
    return f"stage|{name}"


def task_specs(plan: Plan, names: list[TaskName], cache: Cache | None, progress: str,
               stage: str = "") -> dict[TaskName, TaskSpec]:
    """One `TaskSpec` per planned task in `names` (plain data a worker can run)."""
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


def dask_graph(plan: Plan, names: list[TaskName], specs: dict[TaskName, TaskSpec]) -> dict[str, Any]:
    """The dask graph of the tasks `names`: per task its value (loaded or computed), its record
    and, for writers that write, its staged files (see the module docstring for the keys)."""
    dsk: dict[str, Any] = {}
    for name in names:
        task = plan.tasks[name]
        deps = [value_key(dep) for dep in task.deps]
        if task.hit:
            dsk[value_key(name)] = (load_task, specs[name])
        elif specs[name].node_cls.uses_run_log:
            upstream = [meta_key(a) for a in _ancestors(plan, name) if a in specs]  # those this run has
            dsk[value_key(name)] = (compute_logged_task, specs[name], len(deps), *deps, *upstream)
        else:
            dsk[value_key(name)] = (compute_task, specs[name], *deps)
        dsk[meta_key(name)] = (task_meta, value_key(name))
        if task.writes and (not task.hit or task.restore):
            dsk[stage_key(name)] = (task_staged, value_key(name))
    return dsk


def _ancestors(plan: Plan, name: TaskName) -> list[TaskName]:
    """Every task `name` depends on, directly or not, in plan order."""
    seen: set[TaskName] = set()
    todo = list(plan.tasks[name].deps)
    while todo:
        dep = todo.pop()
        if dep not in seen:
            seen.add(dep)
            todo.extend(plan.tasks[dep].deps)
    return [t for t in plan.tasks if t in seen]


def execute(dsk: dict[str, Any], names: list[TaskName], value_names: list[TaskName], scheduler: Any,
            reporter: Reporter, workers: int | None,
            resources: Mapping[TaskName, dict[str, float]] | None = None
            ) -> tuple[list[dict], list[TaskResult], list[StagedFile]]:
    """Run the dask graph; return the records of the tasks `names` (in that order), the results
    of the tasks `value_names`, and every file the run's writers staged.

    `resources`: what the node of a task needs on a dask.distributed worker ({"gpu": 1})."""
    meta_keys = [meta_key(name) for name in names]
    value_keys = [value_key(name) for name in value_names]
    stage_keys = [key for key, task in dsk.items() if task[0] is task_staged]
    needs_by_key = {value_key(name): needs for name, needs in (resources or {}).items()}
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
        # a record's and a staging task's one argument is the key of the task's value
        return ([loaded[dsk[k][1]].meta() for k in meta_keys], [loaded[k] for k in value_keys],
                [entry for k in stage_keys for entry in loaded[dsk[k][1]].staged])
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
        with in_process_run() if scheduler in IN_PROCESS else contextlib.nullcontext():
            with _Progress():
                out = get(dsk, keys, **kwargs)
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
                  for key, res in needs_by_key.items()}
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
    except Exception as err:  # something answers that does not speak dask's protocol (a proxy, a web
        # server): its bytes read as a frame length give MemoryError, ValueError, msgpack errors...
        raise SchedulerError(address, f"expected a dask.distributed scheduler answering at {address}, "
                                      f"found something else answering there ({type(err).__name__}: "
                                      f"{str(err)[:120]})") from err
