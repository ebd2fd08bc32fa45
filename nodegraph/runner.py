"""Run a graph: plan it, run the plan's tasks on dask, gather the outputs into a `RunResult`.

Every task catches its own failure and returns it as a record, so one failing node never
stops independent branches; tasks below a failure are skipped. The run then reports each
failed chunk (node id, frames, exception, traceback, input keys) and ends non-zero.

Outputs are all-or-nothing (`nodegraph.staging`): writer tasks write into staging folders
next to their destinations, and the run moves the staged files onto the destinations only
when every task succeeded; a failed run deletes them ("nothing written: ... held back").

The parts live in their own modules: `nodegraph.tasks` (what one task does in a worker),
`nodegraph.dask_run` (the dask graph and the schedulers), `nodegraph.progress` (bars and
JSON lines), `nodegraph.explain` (why a task is not a cache hit). This module re-exports
their public names that callers import from `nodegraph.runner`.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

from .cache import Cache, resolve_cache
from .dask_run import CONNECT_TIMEOUT_S, SCHEDULERS, check_scheduler, dask_graph, execute, task_specs
from .errors import NodeError
from .explain import explain
from .graph import Graph
from .params import field_flag
from .pathcheck import check_output_paths
from .ports import PortType
from .progress import Reporter, progress_mode, warnings_as_events
from .plan_names import TaskName
from .schedule import Plan, check_run_frames, plan_run
from .staging import commit, discard, new_token
from .tasks import IN_PROCESS, OK_STATUSES, TaskResult, TaskSpec, combine, import_now, preload, wait_for_preloads

__all__ = ["TaskSpec", "TaskResult", "RunResult", "run", "explain", "check_scheduler", "SCHEDULERS",
           "CONNECT_TIMEOUT_S"]


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
    store = resolve_cache(cache)
    mode = progress_mode(progress)
    started = time.perf_counter()
    with warnings_as_events(mode):
        try:
            return _run(graph, frames, chunk, scheduler, store, outputs, force, mode, workers, device, started)
        finally:
            wait_for_preloads()  # an import left running would abort the interpreter's exit


def _run(graph: Graph, frames: range | None, chunk: int, scheduler: Any, store: Cache | None,
         outputs: Iterable[str] | None, force: Iterable[str], mode: str, workers: int | None, device: str,
         started: float) -> RunResult:
    token = new_token()  # names this run's staging folders (see nodegraph.staging)
    # Node preloads start after planning, never during it: planning reads the input files'
    # headers, which imports their readers' C extensions (pxr, OpenImageIO, av) on this thread,
    # and a preload importing torch at the same time deadlocked (stabilize.json on a USD capture
    # with --no-cache hung forever: pxr's library initialisers and torch's both waited on the other).
    for attempt in range(2):
        plan = plan_run(graph, frames=frames, chunk=chunk, cache=store, targets=list(outputs or []) or None,
                        force=force, device=device, check_frames=False)
        if attempt == 0:
            # outputs that would destroy inputs, unwritable folders, outputs in the cache: exit 2
            check_output_paths(plan, cache_root=store.root if store is not None else None)
            check_run_frames(plan)  # then what the run's frames cannot give (e.g. no training row)
        names = plan.needed()
        specs = task_specs(plan, names, store, mode, token)
        dsk = dask_graph(plan, names, specs)
        value_names = [t for node in plan.targets for t in plan.by_node[node]]
        reporter = Reporter(plan, names, mode)
        gpu_tasks = {n for n in names if not plan.tasks[n].hit and plan.tasks[n].device != "cpu"
                     and plan.nodes[plan.tasks[n].node].resources}
        writers = _writing(plan, names)
        if scheduler in IN_PROCESS:
            running = [plan.nodes[plan.tasks[n].node] for n in names if not plan.tasks[n].hit]
            import_now([m for node in dict.fromkeys(running) for m in node.import_first()])  # before any task thread
            preload([m for node in running for m in node.preload])
        try:
            metas, results, staged = execute(dsk, names, value_names, scheduler, reporter, workers,
                                             {n: dict(plan.nodes[plan.tasks[n].node].resources) for n in gpu_tasks})
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
        if any(p.status not in OK_STATUSES for p in parts):
            continue
        out[node] = {}
        for port, decl in plan.nodes[node].outputs.items():
            out[node][port] = combine([p.values[port] for p in parts], decl.per_frame)
    failures = [m["error"] for m in metas if m["status"] == "failed"]
    held_back: list[str] = []
    cause = ""
    if not failures and all(m["status"] in OK_STATUSES for m in metas):
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
    _record(plan, names, metas, store)
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
            if field_flag(node.Params, name, "output_file", False) and isinstance(value, str) and value:
                paths.append(value)
    return paths


def _commit_failure(err: OSError) -> dict[str, Any]:
    message = f"could not move the run's staged outputs onto their paths: {err}"
    return {"node": "", "type": "nodegraph", "frames": None, "message": message, "reason": message, "port": "",
            "bad_input": False, "traceback": "", "exception": type(err).__name__, "input_keys": {},
            "time": time.time()}



def _record(plan: Plan, names: Sequence[TaskName], metas: list[dict[str, Any]], store: Cache | None) -> None:
    """Write error records of failed chunks and the key descriptions used (for --explain);
    `metas` are the records of the tasks `names`, in that order."""
    if store is None:
        return
    by_node: dict[str, dict[str, Any]] = {}
    for name, meta in zip(names, metas, strict=True):
        task = plan.tasks[name]
        frames = tuple(meta["frames"]) if task.mode != "static" else None
        if meta["status"] == "failed":
            meta["error"]["record"] = str(store.write_error(meta["error"]))
        elif meta["status"] in OK_STATUSES:
            store.clear_error(task.node, frames if task.mode == "chunk" else None)
            by_node.setdefault(task.node, store.read_last(task.node))[str(task.name)] = task.description
    for node, descriptions in by_node.items():
        store.write_last(node, descriptions)
