"""Plan a run: frame chunks, halos, cache keys and hits, computed from data alone (no dask, no I/O
beyond hashing input files and checking the cache's manifests).

Each node runs in one of three modes:
- "chunk": framewise and windowed nodes, one task per chunk of frames. Chunks lie on a grid
  of absolute frame numbers (multiples of the chunk size), so widening the frame range adds
  chunks without changing the existing ones. A windowed node receives its chunk plus `halo`
  frames on each side (cut at the ends of the run) and its per-frame outputs are trimmed back.
- "sequence": one task over the whole range.
- "static": nodes without per-frame inputs or outputs (e.g. loading a face model): one task
  whose key does not depend on the frame range.
"""

from __future__ import annotations

import inspect
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from .cache import Cache, make_key
from .files import file_sha256
from .errors import GraphError, GraphIssue, NodeError
from .graph import Graph
from .node import SEQUENCE, Node, wrap_error
from .params import field_flag
from .plan_names import PortSlot, TaskName

__all__ = ["Piece", "TaskPlan", "Plan", "PortSlot", "TaskName", "plan_run", "chunk_bounds", "explain_miss",
           "parse_frames", "check_run_frames"]


@dataclass(frozen=True)
class Piece:
    """A part of an input value: `task`'s output `port`, frames [start, stop) relative to that
    task's value, or the whole value when start == -1."""

    task: TaskName
    port: str
    start: int = -1
    stop: int = -1


@dataclass
class TaskPlan:
    """One (node, chunk) task."""

    name: TaskName
    node: str
    node_type: str
    mode: str
    frames: tuple[int, int]
    out_frames: tuple[int, int]
    inputs: dict[PortSlot, list[Piece]]  # in edge order, a list port's connections one slot each
    key: str
    description: dict[str, Any]
    cacheable: bool
    writes: bool = False
    device: str = "cpu"
    hit: bool = False
    forced: bool = False
    restore: bool = False  # a writer whose changed files are rewritten from the entry's copies
    stale_files: list[str] = field(default_factory=list)
    input_ports: dict[str, bool] = field(default_factory=dict)  # the node's declared inputs: name -> many

    @property
    def deps(self) -> list[TaskName]:
        seen: dict[TaskName, None] = {}
        for pieces in self.inputs.values():
            for piece in pieces:
                seen.setdefault(piece.task, None)
        return list(seen)


@dataclass
class Plan:
    """Every task of a run, in topological order, with the nodes' instances."""

    graph: Graph
    frames: range
    chunk: int
    tasks: dict[TaskName, TaskPlan] = field(default_factory=dict)
    by_node: dict[str, list[TaskName]] = field(default_factory=dict)
    nodes: dict[str, Node] = field(default_factory=dict)
    targets: list[str] = field(default_factory=list)
    cache: Cache | None = None
    verify: bool = False  # check entries' contents (sha256), not only their sizes

    def needed(self) -> list[TaskName]:
        """Tasks to schedule: the targets' tasks and, below each miss, what it consumes.

        The cache is consulted here, only for the tasks visited, and `TaskPlan.hit` set.
        """
        need: dict[TaskName, None] = {}
        stack = [t for node in self.targets for t in self.by_node[node]]
        while stack:
            name = stack.pop()
            if name in need:
                continue
            need[name] = None
            task = self.tasks[name]
            task.hit = bool(self.cache is not None and task.cacheable and not task.forced
                            and self.cache.contains(task.key, verify=self.verify))
            if task.hit and task.writes:
                state, task.stale_files = self.cache.written_state(task.key)  # type: ignore[union-attr]
                task.hit = state != "stale"
                task.restore = state == "restorable"
            if not task.hit:
                stack.extend(task.deps)
        return [name for name in self.tasks if name in need]


def parse_frames(text: str) -> range:
    """Parse "a:b" (b exclusive) or "n" (= 0:n) into a range."""
    try:
        if ":" in text:
            a, b = text.split(":", 1)
            frames = range(int(a or 0), int(b))
        else:
            frames = range(0, int(text))
    except ValueError:
        raise ValueError(f"--frames: expected 'start:stop', found {text!r}") from None
    if frames.start < 0 or frames.stop <= frames.start:
        raise ValueError(f"--frames: expected 0 <= start < stop, found {text!r}")
    return frames


def chunk_bounds(frames: range, chunk: int) -> list[tuple[int, int]]:
    """Split `frames` on the grid of multiples of `chunk` (absolute frame numbers)."""
    if chunk <= 0:
        raise ValueError(f"chunk size must be > 0, found {chunk}")
    cuts = [frames.start]
    cut = (frames.start // chunk + 1) * chunk
    while cut < frames.stop:
        cuts.append(cut)
        cut += chunk
    cuts.append(frames.stop)
    return list(zip(cuts[:-1], cuts[1:]))


def _mode(node: Node, connected: Iterable[str]) -> str:
    """"static", "sequence" or "chunk" (see the module docstring)."""
    per_frame_in = any(node.inputs[p].per_frame for p in connected)
    per_frame_out = any(o.per_frame for o in node.outputs.values())
    if not per_frame_in and not per_frame_out:
        return "static"
    return "sequence" if node.kind == SEQUENCE else "chunk"


def plan_run(graph: Graph, *, frames: range | None = None, chunk: int = 64,
             cache: Cache | None = None, targets: list[str] | None = None,
             force: Iterable[str] = (), device: str = "cpu", check_frames: bool = True) -> Plan:
    """Turn a validated graph into tasks with cache keys.

    Args:
        graph: the graph (validated here).
        frames: frames to compute; default: what the source nodes can produce.
        chunk: frames per chunk for framewise and windowed nodes (a node's own `chunk` in
            the graph overrides it).
        device: "cpu", "cuda" or "auto" for nodes that do not pin their own.
        cache: where hits are looked up (None: no cache, everything runs).
        targets: node ids whose outputs are wanted (default: the sinks).
        force: node ids to recompute even when cached (with their descendants).
        check_frames: call the nodes' `check_frames` hooks (`check_run_frames`) at the end; the
            runner passes False and calls them after checking the output paths (a wrong output
            path is reported before a data problem).
    Raises:
        GraphError: invalid graph, unknown target, or sources that disagree on the frame count.
        NodeError: a node rejected its parameters or files while planning (bad_input), or its
            optional `check_plan(producers)` hook (input port -> the producing node instances,
            in edge order) raised: a node can so refuse, before anything runs, what its
            producers' parameters and files already tell (e.g. a network file that does not fit
            the capture file's topology); or its optional `check_frames(frames, producers)`
            hook raised (`check_run_frames`).
    """
    graph.check()
    order = graph.topological_order()
    nodes = {nid: graph.instantiate(nid) for nid in order}
    ups = {nid: graph.upstream_lists(nid) for nid in order}
    modes = {nid: _mode(nodes[nid], ups[nid]) for nid in order}
    for nid in order:  # optional early check of a node against its direct producers (before anything runs)
        check = getattr(nodes[nid], "check_plan", None)
        if check is not None:
            try:
                check({port: [nodes[src.node] for src in sources] for port, sources in ups[nid].items()})
            except Exception as err:
                raise wrap_error(nodes[nid], err, bad_input=True) from err
    issues = []
    for nid in order:
        if modes[nid] == "chunk":
            whole = [name for name, port in nodes[nid].outputs.items()
                     if not port.per_frame and not port.type.mergeable()]
            if whole:
                issues.append(GraphIssue(nid, whole[0], f"{nodes[nid].kind} node cannot have a whole-value "
                                         "output; make the node 'sequence'"))
    targets = list(targets) if targets else graph.sinks()
    for target in targets:
        if target not in graph.nodes:
            issues.append(GraphIssue(target, "", "unknown target node"))
    if issues:
        raise GraphError(issues)

    counts = {}
    for nid in order:
        node = nodes[nid]
        if modes[nid] != "static" and not any(node.inputs[p].per_frame for p in ups[nid]):
            try:
                count = node.frame_count()
            except Exception as err:  # a source that cannot read its files
                raise wrap_error(node, err, bad_input=True) from err
            if count is not None:
                counts[nid] = int(count)
    if frames is not None:  # a range past a source's end fails in every chunk there: refuse it now
        short = [GraphIssue(nid, "", f"--frames {frames.start}:{frames.stop}: expected frames within the "
                                     f"{count} frame(s) this source has (0:{count}), found stop {frames.stop}")
                 for nid, count in counts.items() if frames.stop > count]
        if short:
            raise GraphError(short)
    if frames is None:
        if not counts:
            raise GraphError([GraphIssue("", "", "no source node knows how many frames to produce; "
                                         "pass frames (--frames a:b)")])
        if len(set(counts.values())) > 1:
            found = ", ".join(f"'{k}' has {v}" for k, v in counts.items())
            raise GraphError([GraphIssue("", "", f"source nodes disagree on the frame count ({found}); "
                                         "pass frames (--frames a:b)")])
        frames = range(0, next(iter(counts.values())))
    if len(frames) == 0:
        raise GraphError([GraphIssue("", "", "the frame range is empty")])

    forced = set(force)
    for nid in list(forced):
        if nid not in graph.nodes:
            raise GraphError([GraphIssue(nid, "", "unknown node for --force")])
        forced |= graph.descendants(nid)

    read = _read_outputs(graph, nodes, targets)
    plan = Plan(graph, frames, chunk, nodes=nodes, targets=targets, cache=cache)
    full = (frames.start, frames.stop)
    hash_file = cache.file_hash if cache is not None else file_sha256
    for nid in order:
        node, mode, spec = nodes[nid], modes[nid], graph.nodes[nid]
        cls = type(node)
        code = cls.code_hash()
        if cache is not None:
            try:
                cache.record_code(code, cls.code_sources())
            except OSError:
                pass  # only --explain's detail depends on it
        base = {"type": cls.type_name, "version": cls.version, "code": code, "params": node.key_params()}
        if mode == "static":
            spans = [(None, None)]
        elif mode == "sequence":
            spans = [(full, full)]
        else:
            halo = node.kind.halo
            spans = [((max(full[0], s - halo), min(full[1], e + halo)), (s, e))
                     for s, e in chunk_bounds(frames, spec.chunk or chunk)]
        all_files: list[str] | None = None
        names = []
        for span, out in spans:
            try:
                if mode == "chunk" and _takes_frames(node):
                    files = _hash_inputs(node, node.input_files(range(*span)), hash_file)
                else:
                    if all_files is None:
                        all_files = _hash_inputs(node, node.input_files(), hash_file)
                    files = all_files
            except Exception as err:
                raise wrap_error(node, err, bad_input=True) from err
            inputs: dict[PortSlot, list[Piece]] = {}
            for port, sources in ups[nid].items():
                decl = node.inputs[port]
                for index, src in enumerate(sources):
                    slot = PortSlot(port, index) if decl.many else PortSlot(port)
                    inputs[slot] = _pieces(plan, src.node, src.port, span if decl.per_frame else None)
            description = dict(base)
            description["files"] = files
            # the slots' text ("views#1") is what cache keys have always held
            description["inputs"] = {str(slot): [[plan.tasks[p.task].key, p.port, p.start, p.stop] for p in pieces]
                                     for slot, pieces in sorted(inputs.items(), key=lambda item: str(item[0]))}
            description["frames"] = list(span) if span else None
            description["out"] = list(out) if out else None
            if nid in read:  # only these outputs are computed: part of the key (never an entry without one)
                description["outputs"] = read[nid]
            name = TaskName(nid, out)
            task = TaskPlan(name, nid, cls.type_name, mode, span or full, out or full, inputs,
                            make_key(description), description, cls.cacheable, writes=cls.writes_files,
                            device=spec.device or device,
                            input_ports={port: decl.many for port, decl in node.inputs.items()})
            task.forced = nid in forced
            plan.tasks[name] = task
            names.append(name)
        plan.by_node[nid] = names
    if check_frames:
        check_run_frames(plan)
    return plan


def _read_outputs(graph: Graph, nodes: dict[str, Node], targets: list[str]) -> dict[str, list[str]]:
    """Per node that `skips_unread_outputs` and has outputs nobody reads: the outputs some edge
    reads (sorted). A target's outputs are all read (the run returns them)."""
    read: dict[str, set[str]] = {}
    for src, _ in graph.edges:
        read.setdefault(src.node, set()).add(src.port)
    out = {}
    for nid, node in nodes.items():
        if node.skips_unread_outputs and nid not in targets:
            ports = read.get(nid, set())
            if ports != set(node.outputs):
                out[nid] = sorted(ports)
    return out


def check_run_frames(plan: Plan) -> None:
    """Call each node's optional `check_frames(frames, producers)` hook with the run's frames
    (input port -> the producing node instances, in edge order), before anything runs.

    Raises:
        NodeError: (bad input) a hook raised: e.g. a trainer whose captures, as the run slices
            them, cannot give one training row (`--frames 0:4`).
    """
    graph, nodes = plan.graph, plan.nodes
    for nid in graph.topological_order():
        check = getattr(nodes[nid], "check_frames", None)
        if check is not None:
            ups = graph.upstream_lists(nid)
            try:
                check(plan.frames, {port: [nodes[src.node] for src in sources] for port, sources in ups.items()})
            except Exception as err:
                raise wrap_error(nodes[nid], err, bad_input=True) from err


def _hash_inputs(node: Node, paths: Iterable[Path], hash_file: Callable[[Path], str]) -> list[str]:
    """The content hashes of the files a node reads; a missing or unreadable one is bad input
    (exit 2) naming the node, its parameter and the path, not Python's raw OSError text."""
    hashes = []
    for path in paths:
        try:
            hashes.append(hash_file(path))
        except OSError as err:
            if isinstance(err, FileNotFoundError):
                found = f"no file '{path}'"
            elif isinstance(err, IsADirectoryError):
                found = f"a folder '{path}'"
            else:
                found = f"'{path}' unreadable ({err.strerror or err})"
            raise NodeError(node.node_id, node.type_name, f"expected a readable input file, found {found}",
                            port=_input_param(node, path), bad_input=True) from err
    return hashes


def _input_param(node: Node, path: Path) -> str:
    """The `input_file` parameter of `node` that names `path` (the only one when none does), or ""."""
    names = [name for name in node.Params.model_fields if field_flag(node.Params, name, "input_file", False)]
    for name in names:
        value = getattr(node.params, name)
        values = value if isinstance(value, (list, tuple)) else [value]
        if any(isinstance(v, str) and v and os.path.normpath(v) == os.path.normpath(path) for v in values):
            return name
    return names[0] if len(names) == 1 else ""


def _takes_frames(node: Node) -> bool:
    """Whether the node's `input_files` accepts the chunk's frames (older plugins may not)."""
    try:
        return "frames" in inspect.signature(node.input_files).parameters
    except (TypeError, ValueError):
        return False


def _pieces(plan: Plan, node_id: str, port: str, span: tuple[int, int] | None) -> list[Piece]:
    """Pieces of `node_id.port` covering `span` (None: the whole value)."""
    names = plan.by_node[node_id]
    producer = plan.nodes[node_id]
    if not producer.outputs[port].per_frame:
        return [Piece(name, port) for name in names]  # several only for mergeable types (Files)
    if span is None:
        span = (plan.frames.start, plan.frames.stop)
    pieces = []
    for name in names:
        task = plan.tasks[name]
        s, e = task.out_frames
        lo, hi = max(s, span[0]), min(e, span[1])
        if lo < hi:
            pieces.append(Piece(name, port, lo - s, hi - s))
    return pieces


def explain_miss(task: TaskPlan, last: dict[str, Any] | None, cache: Cache | None = None) -> str:
    """Why `task` is not a cache hit, comparing its key description with the last run's.

    With `cache`, a code change names the source files that changed.
    """
    if task.forced:
        return "forced"
    if not task.cacheable:
        return "not cacheable: always runs"
    if last is None:
        return "new: never computed with these frames"
    now = task.description
    reasons = []
    if last.get("type") != now["type"]:
        reasons.append(f"node type changed ({last.get('type')} -> {now['type']})")
    if last.get("version") != now["version"]:
        reasons.append(f"node version changed ({last.get('version')} -> {now['version']})")
    if last.get("code") != now["code"]:
        reasons.append(_code_change(last.get("code"), now["code"], cache))
    old_params, new_params = last.get("params", {}), now["params"]
    for name in sorted(set(old_params) | set(new_params)):
        if old_params.get(name) != new_params.get(name):
            reasons.append(f"param {name} changed ({old_params.get(name)!r} -> {new_params.get(name)!r})")
    if last.get("files") != now["files"]:
        reasons.append("input files changed")
    old_inputs, new_inputs = last.get("inputs", {}), now["inputs"]
    port_of = _slot_ports(task, len(old_inputs))
    changed_ports = [port_of.get(text, text) for text in sorted(set(old_inputs) | set(new_inputs))
                     if old_inputs.get(text) != new_inputs.get(text)]
    reasons.extend(f"upstream '{port}' changed" for port in dict.fromkeys(changed_ports))
    if last.get("outputs") != now.get("outputs"):
        reasons.append(f"outputs read changed ({_outputs_text(last.get('outputs'))} -> "
                       f"{_outputs_text(now.get('outputs'))}: the node computes only the outputs an edge reads)")
    if last.get("frames") != now["frames"] and not reasons:
        reasons.append(f"frames changed ({last.get('frames')} -> {now['frames']})")
    if not reasons and task.writes and task.stale_files:
        return "written files missing or changed: " + ", ".join(task.stale_files)
    if not reasons and task.writes:
        return "written files not recorded (written by an older nodegraph, or the record was lost)"
    return "; ".join(reasons) if reasons else "entry missing from the cache (evicted or corrupt)"


def _outputs_text(outputs: list[str] | None) -> str:
    """A task description's "outputs" (None: every output computed) as text."""
    return "all" if outputs is None else ", ".join(outputs)


def _slot_ports(task: TaskPlan, count: int) -> dict[str, str]:
    """The text of every input slot the task's node can have, up to `count` connections per list
    port, mapped to its port name (a last run's description names its slots by their text)."""
    slots = [PortSlot(port, index) for port, many in task.input_ports.items() if many for index in range(count)]
    slots += [PortSlot(port) for port, many in task.input_ports.items() if not many]
    return {str(slot): slot.port for slot in [*slots, *task.inputs]}


def _code_change(old: Any, new: str, cache: Cache | None) -> str:
    before = cache.code_sources(old) if cache is not None and isinstance(old, str) else None
    after = cache.code_sources(new) if cache is not None else None
    if before is None or after is None:
        return "code changed"
    changed = sorted(path for path in set(before) | set(after) if before.get(path) != after.get(path))
    return "code changed: " + ", ".join(changed) if changed else "code changed"
