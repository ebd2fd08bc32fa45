"""The `nodegraph` command.

    nodegraph run GRAPH.json [name=value ...] [--set node.param=value] [--frames a:b] [--chunk N]
                  [--scheduler sync|threads|processes|ADDRESS] [--cache DIR | --no-cache]
                  [--to NODE] [--force NODE] [--explain]
    nodegraph run GRAPH.json --help      # the graph's parameters, types and defaults
    nodegraph validate GRAPH.json ...
    nodegraph nodes [NAME]
    nodegraph show GRAPH.json [--image out.png]
    nodegraph upgrade GRAPH.json [--check]
    nodegraph cache info|clear|gc [--max-size 10G] [--cache DIR]

Exit codes: 0 ok, 2 bad graph, parameter or input data (the message names node and port),
1 a node raised.
"""

from __future__ import annotations

import argparse
import difflib
import json
import os
import sys
import tempfile
import traceback
from pathlib import Path
from typing import Any, Sequence

from . import registry
from .cache import Cache, NotACache, cache_dir_from_env
from .errors import GraphError, GraphIssue, NodeError, SchedulerError
from .files import write_text_atomic
from .graph import Graph
from .runner import check_scheduler, explain, run
from .schedule import parse_frames
from .staging import nearest_existing
from .types import Files, JsonValue, PortType, Table

__all__ = ["main", "UsageError", "nodes_markdown"]


class UsageError(ValueError):
    """A malformed command-line value (exit 2)."""


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nodegraph", description="Typed dataflow graphs for facial capture.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("run", help="run a graph", add_help=False)
    p.add_argument("graph", nargs="?", help="graph JSON file")
    p.add_argument("assignments", nargs="*", help="graph parameters as name=value (anywhere on the line)")
    p.add_argument("-h", "--help", action="store_true", help="show this help (and the graph's parameters)")
    p.add_argument("--set", action="append", default=[], metavar="NODE.PARAM=VALUE",
                   help="set any node parameter")
    p.add_argument("--frames", help="frames to compute, 'start:stop' (stop exclusive)")
    p.add_argument("--chunk", type=int, default=64, help="frames per chunk (default 64)")
    p.add_argument("--scheduler", default="threads",
                   help="sync | threads | processes | a dask.distributed address tcp://host:port (default threads)")
    p.add_argument("--workers", type=int, help="workers of the local thread/process pool")
    p.add_argument("--cache", help="cache folder (default $NODEGRAPH_CACHE or .nodegraph/cache)")
    p.add_argument("--no-cache", action="store_true", help="compute everything, store nothing")
    p.add_argument("--to", action="append", default=[], metavar="NODE", help="compute only up to these nodes")
    p.add_argument("--force", action="append", default=[], metavar="NODE",
                   help="recompute these nodes (and what depends on them) even when cached")
    p.add_argument("--explain", action="store_true", help="print cache hit/miss and why per task; run nothing")
    p.add_argument("--progress", choices=["auto", "tty", "json", "none"], default="auto",
                   help="progress display (default: bars on a terminal, JSON lines otherwise)")
    p.add_argument("--device", choices=["auto", "cpu", "cuda"], default="auto",
                   help="torch device of nodes that do not pin one (default auto: CUDA when present)")
    p.add_argument("--report-html", metavar="FILE",
                   help="write one self-contained HTML page: the graph, per-node timings and cache hits, failures")

    p = sub.add_parser("validate", help="check graph files (or every *.json in folders) without running them")
    p.add_argument("graphs", nargs="+")

    p = sub.add_parser("nodes", help="list node types, or describe one")
    p.add_argument("name", nargs="?")
    p.add_argument("--markdown", action="store_true",
                   help="print the catalogue of every node type as a markdown table (docs/nodes.md)")

    p = sub.add_parser("show", help="print a graph's outline (and draw it with graphviz)")
    p.add_argument("graph")
    p.add_argument("--image", help="write a picture (needs the graphviz package and 'dot')")

    p = sub.add_parser("upgrade", help="migrate a graph file to the installed node versions")
    p.add_argument("graph")
    p.add_argument("--check", action="store_true", help="only show the diff; exit 1 if the file is outdated")

    p = sub.add_parser("cache", help="inspect or trim the cache")
    p.add_argument("action", choices=["info", "clear", "gc"])
    p.add_argument("--cache", help="cache folder")
    p.add_argument("--max-size", default="10G", help="for gc: size to trim down to, e.g. 500M, 10G")
    return parser


def _parse_size(text: str) -> int:
    units = {"": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}
    text = text.strip().upper().rstrip("B")
    unit = text[-1] if text and text[-1] in units else ""
    try:
        return int(float(text[: len(text) - len(unit)]) * units[unit])
    except ValueError:
        raise UsageError(f"--max-size: expected a size like 500M or 10G, found {text!r}") from None


def _split_assignments(items: Sequence[str], what: str) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise UsageError(f"{what}: expected name=value, found {item!r}")
        out[name] = value
    return out


def _describe(value: PortType) -> str:
    if isinstance(value, Files):
        return ", ".join(value.paths)
    if isinstance(value, Table):
        return "\n" + value.format() if value.rows else "(empty table)"
    if isinstance(value, JsonValue):
        return json.dumps(value.value)
    shapes = {k: tuple(v.shape) for k, v in value.to_arrays().items() if hasattr(v, "shape") and v.ndim > 0}
    first = next(iter(shapes.items()), None)
    return f"{value.type_name} {first[0]} {first[1]}" if first else value.type_name


def _graph_help(graph: Graph, path: str) -> str:
    lines = [f"usage: nodegraph run {path} [name=value ...] [options]", ""]
    if graph.description:
        lines += [graph.description, ""]
    lines.append("graph parameters:")
    if not graph.parameters:
        lines.append("  (none)")
    for name, gp in graph.parameters.items():
        cls = graph.node_class(gp.node)
        info = cls.Params.model_fields[gp.param]
        current = graph.nodes[gp.node].params.get(gp.param, info.get_default(call_default_factory=True))
        kind = getattr(info.annotation, "__name__", str(info.annotation))
        doc = gp.description or info.description or ""
        lines.append(f"  {name}={json.dumps(current)}  ({kind}; sets {gp.target}) {doc}".rstrip())
    lines += ["", "options: --set NODE.PARAM=VALUE, --frames a:b, --chunk N, --scheduler sync|threads|processes|ADDRESS,",
              "         --cache DIR, --no-cache, --to NODE, --force NODE, --explain, --progress MODE"]
    return "\n".join(lines)


def _cmd_run(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    if args.graph is None:
        print(_run_usage())
        return 0 if args.help else 2
    graph = Graph.load(args.graph)
    if graph.migrations:
        print(f"note: {args.graph} uses old node versions, migrated in memory "
              f"({'; '.join(graph.migrations)}); `nodegraph upgrade {args.graph}` rewrites it", file=sys.stderr)
    if args.help:
        print(_graph_help(graph, args.graph))
        return 0
    check_scheduler(args.scheduler)
    graph.apply(_split_assignments(args.assignments, "graph parameter"), strings=True)
    graph.set_strings(_split_assignments(args.set, "--set"))
    try:
        frames = parse_frames(args.frames) if args.frames else None
    except ValueError as err:
        raise UsageError(str(err)) from None
    if args.chunk < 1:
        raise UsageError(f"--chunk: expected a number of frames >= 1, found {args.chunk}")
    if args.workers is not None and args.workers < 1:
        raise UsageError(f"--workers: expected >= 1, found {args.workers}")
    cache: Any = False if args.no_cache else (args.cache or None)
    _check_cache_folder(cache)
    if args.explain:
        rows = explain(graph, frames=frames, chunk=args.chunk, cache=cache, outputs=args.to or None,
                       force=args.force)
        width = max((len(r["task"]) for r in rows), default=4)
        for row in rows:
            print(f"{row['task']:<{width}}  {'hit ' if row['hit'] else 'MISS'}  {row['reason']}")
        print(f"{sum(r['hit'] for r in rows)} hit, {sum(not r['hit'] for r in rows)} miss")
        return 0
    progress = None if args.progress == "none" else args.progress
    result = run(graph, frames=frames, chunk=args.chunk, scheduler=args.scheduler, cache=cache,
                 outputs=args.to or None, force=args.force, progress=progress, workers=args.workers,
                 device=args.device)
    for node, ports in result.outputs.items():
        for port, value in ports.items():
            print(f"{node}.{port}: {_describe(value)}")
    sys.stdout.flush()
    if args.report_html:
        from .html_report import run_report_html

        write_text_atomic(args.report_html, run_report_html(result, graph, title=f"nodegraph run {args.graph}"))
        print(f"wrote {args.report_html}", file=sys.stderr)
    _print_tracebacks(result.failures)
    print(result.summary(), file=sys.stderr)
    for group in result.failure_groups():
        records = [f["record"] for f in group if f.get("record")]
        if len(records) == 1:
            print(f"  error record: {records[0]}", file=sys.stderr)
        elif records:
            print(f"  error records: {records[0]} and {len(records) - 1} more in {Path(records[0]).parent}",
                  file=sys.stderr)
    return result.exit_code


def _check_cache_folder(cache: Any) -> None:
    """Refuse (exit 2, before anything runs) a cache path that names a file or lies under one,
    or whose nearest existing folder cannot be written: `--cache DIR`, else $NODEGRAPH_CACHE or
    the default. `cache` is False for --no-cache (nothing to check)."""
    if cache is False:
        return
    root = Path(cache) if cache else cache_dir_from_env()
    origin = "--cache" if cache else ("$NODEGRAPH_CACHE" if os.environ.get("NODEGRAPH_CACHE") else "the cache")
    here = nearest_existing(root)
    if not here.is_dir():
        what = "is a file" if here == Path(os.path.abspath(root)) else f"lies under the file '{here}'"
        raise UsageError(f"{origin}: expected a folder for the cache, found '{root}', which {what}")
    if not os.access(here, os.W_OK | os.X_OK):
        raise UsageError(f"{origin}: expected a writable folder for the cache, found '{here}' not writable")
    try:  # root passes os.access everywhere, yet cannot write in /proc, /sys or a read-only mount
        os.rmdir(tempfile.mkdtemp(prefix=".nodegraph-cache-probe.", dir=here))
    except OSError as err:
        raise UsageError(f"{origin}: expected a writable folder for the cache, found '{here}', where no folder "
                         f"can be made ({err.strerror or type(err).__name__}), for the cache '{root}'") from None


def _print_tracebacks(failures: Sequence[dict[str, Any]]) -> None:
    """Print the traceback of each failure that is not bad input (a bug: exit 1) on stderr, once
    per node and call stack (chunks failing at the same place differ only in their messages)."""
    stacks: dict[tuple, list[dict[str, Any]]] = {}
    for failure in failures:
        text = failure.get("traceback") or ""
        if failure.get("bad_input") or not text:
            continue
        where = tuple(line for line in text.splitlines() if line.startswith("  File "))
        stacks.setdefault((failure.get("node"), failure.get("exception"), where), []).append(failure)
    for same in stacks.values():
        first = same[0]
        frames = f" (frames {first['frames'][0]}:{first['frames'][1]})" if first.get("frames") else ""
        also = f"; the same in {len(same) - 1} more chunk(s)" if len(same) > 1 else ""
        print(f"traceback of {first['type']} '{first['node']}'{frames}{also}:\n{first['traceback'].rstrip()}",
              file=sys.stderr)


def _run_usage() -> str:
    return ("usage: nodegraph run GRAPH.json [name=value ...] [--set NODE.PARAM=VALUE] [--frames a:b] "
            "[--chunk N] [--scheduler S] [--cache DIR | --no-cache] [--to NODE] [--force NODE] [--explain]\n"
            "       nodegraph run GRAPH.json --help   lists the graph's parameters")


def _port_text(port: Any) -> str:
    flags = ", ".join(f for f in ["optional" if port.optional else "", "list" if port.many else "",
                                  "whole" if port.type.per_frame and not port.per_frame else ""] if f)
    return f"`{port.name}`: {port.type.type_name}" + (f" ({flags})" if flags else "")


def nodes_markdown() -> str:
    """The catalogue of every registered node type as markdown (what `nodes --markdown` prints)."""
    lines = ["# Node catalogue", "",
             "Generated by `nodegraph nodes --markdown` from the registry; `tests/test_docs.py` checks "
             "that it is up to date. `nodegraph nodes TYPE` shows one type with its parameters' "
             "bounds and defaults.", "",
             "| type | v | kind | inputs | outputs | parameters | what it does |", "|---|---|---|---|---|---|---|"]
    for name, cls in registry.all_types().items():
        if name.startswith("test."):
            continue
        doc = (cls.__doc__ or "").strip().splitlines()
        params = ", ".join(f"`{p}`" for p in cls.Params.model_fields)
        cells = [f"`{name}`", str(cls.version), str(cls.kind) + ("" if not cls.writes_files else ", writes files"),
                 "<br>".join(_port_text(p) for p in cls.inputs.values()) or "",
                 "<br>".join(_port_text(p) for p in cls.outputs.values()), params, doc[0] if doc else ""]
        lines.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return "\n".join(lines) + "\n"


def _cmd_nodes(args: argparse.Namespace) -> int:
    if args.markdown:
        sys.stdout.write(nodes_markdown())
        return 0
    types = registry.all_types()
    if not args.name:
        width = max((len(n) for n in types), default=0)
        for name, cls in types.items():
            doc = (cls.__doc__ or "").strip().splitlines()
            print(f"{name:<{width}}  v{cls.version}  {cls.kind!s:<18} {doc[0] if doc else ''}")
        return 0
    try:
        cls = registry.get(args.name)
    except KeyError as err:
        raise UsageError(str(err.args[0])) from None
    print(f"{cls.type_name}  (version {cls.version}, {cls.kind}{'' if cls.cacheable else ', not cached'})")
    print((cls.__doc__ or "").strip())
    print("\ninputs:")
    for name, port in cls.inputs.items():
        flags = ", ".join(f for f in ["optional" if port.optional else "", "list" if port.many else "",
                                      "whole" if port.type.per_frame and not port.per_frame else ""] if f)
        print(f"  {name}: {port.type.type_name}{f' ({flags})' if flags else ''}  {port.doc}".rstrip())
    print("outputs:")
    for name, port in cls.outputs.items():
        print(f"  {name}: {port.type.type_name}  {port.doc}".rstrip())
    print("params:")
    for name, info in cls.Params.model_fields.items():
        default = "required" if info.is_required() else json.dumps(info.get_default(call_default_factory=True))
        bounds = " ".join(str(m) for m in info.metadata)
        kind = getattr(info.annotation, "__name__", str(info.annotation))
        print(f"  {name}: {kind} = {default} {bounds}  {info.description or ''}".rstrip())
    return 0


def _cmd_show(args: argparse.Namespace) -> int:
    graph = Graph.load(args.graph)
    print(f"{args.graph}: {len(graph.nodes)} nodes, {len(graph.edges)} edges")
    for node_id in graph.topological_order():
        spec = graph.nodes[node_id]
        cls = graph.node_class(node_id)
        extra = "".join(f", {k} {v}" for k, v in (("chunk", spec.chunk), ("device", spec.device)) if v)
        print(f"  {node_id} [{spec.type} v{spec.type_version}, {cls.kind}{extra}]")
        for port, sources in graph.upstream_lists(node_id).items():
            print(f"      {port} <- {', '.join(map(str, sources))}")
        for key, value in spec.params.items():
            print(f"      {key} = {json.dumps(value)}")
    if graph.parameters:
        print("parameters: " + ", ".join(f"{n} -> {gp.target}" for n, gp in graph.parameters.items()))
    if args.image:
        try:
            import graphviz
        except ImportError:
            print("nodegraph show --image: the graphviz Python package is not installed "
                  "(pip install graphviz, plus the 'dot' program)", file=sys.stderr)
            return 2
        dot = graphviz.Digraph(graph_attr={"rankdir": "LR"})
        for node_id, spec in graph.nodes.items():
            dot.node(node_id, f"{node_id}\n{spec.type}", shape="box")
        for src, dst in graph.edges:
            dot.edge(src.node, dst.node, label=f"{src.port}→{dst.port}")
        out = Path(args.image)
        dot.render(out.with_suffix(""), format=out.suffix.lstrip(".") or "png", cleanup=True)
        print(f"wrote {out}")
    return 0


def _cmd_upgrade(args: argparse.Namespace) -> int:
    path = Path(args.graph)
    old = path.read_text()
    graph = Graph.load(path)
    new = graph.dumps()
    if json.loads(old) == json.loads(new):
        print(f"{path}: up to date")
        return 0
    sys.stdout.writelines(difflib.unified_diff(old.splitlines(True), new.splitlines(True),
                                               str(path), f"{path} (upgraded)"))
    if args.check:
        return 1
    write_text_atomic(path, new)
    print(f"{path}: rewritten ({'; '.join(graph.migrations) or 'normalized'})")
    return 0


def _cmd_cache(args: argparse.Namespace) -> int:
    store = Cache(args.cache) if args.cache else Cache(cache_dir_from_env())
    if args.action == "info":
        info = store.info()
        temps = f", {info['temp_folders']} temporary folders" if info["temp_folders"] else ""
        print(f"{info['path']}: {info['entries']} entries, {info['bytes'] / 1e6:.1f} MB{temps}, "
              f"{info['error_records']} error records")
    elif args.action == "clear":
        if not store.root.exists():
            print(f"{store.root}: no cache here, nothing to clear")
            return 0
        store.clear()
        print(f"{store.root}: cleared")
    else:
        removed, freed = store.gc(_parse_size(args.max_size))
        print(f"{store.root}: removed {removed} entries, freed {freed / 1e6:.1f} MB")
    return 0


def _graph_files(items: Sequence[str]) -> list[str]:
    """The files to validate: each argument, or every *.json directly in a folder argument."""
    out = []
    for item in items:
        path = Path(item)
        if path.is_dir():
            found = sorted(str(p) for p in path.glob("*.json"))
            out.extend(found or [item])  # an empty folder is reported as such
        else:
            out.append(item)
    return out


def _cmd_validate(args: argparse.Namespace) -> int:
    bad = 0
    for path in _graph_files(args.graphs):
        try:
            if Path(path).is_dir():
                raise GraphError([GraphIssue("", "", "the folder holds no *.json graph file")], path)
            Graph.load(path)
            print(f"{path}: ok")
        except GraphError as err:
            print(str(err), file=sys.stderr)
            bad += 1
    return 2 if bad else 0


def _split_argv(argv: list[str]) -> list[str]:
    """Move `name=value` graph parameters given after options to just after the graph file,
    so that they are accepted anywhere on the `run` command line."""
    if not argv or argv[0] != "run":
        return argv
    takes_value = {"--set", "--frames", "--chunk", "--scheduler", "--workers", "--cache", "--to", "--force",
                   "--progress", "--device", "--report-html"}
    head, assignments, rest = [argv[0]], [], []
    graph_seen = False
    index = 1
    while index < len(argv):
        item = argv[index]
        if item in takes_value:
            rest += argv[index:index + 2]
            index += 2
            continue
        if item.startswith("-"):
            rest.append(item)
        elif not graph_seen:
            head.append(item)
            graph_seen = True
        else:
            assignments.append(item)
        index += 1
    return head + assignments + rest


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `nodegraph` command; returns the exit code.

    Exit codes: 0 ok; 2 bad graph, parameter, input data or command line (the message names
    the node, port or file); 1 a node failed, or nodegraph itself failed unexpectedly (with
    the traceback).
    """
    # OpenMP threads (torch's, numba's) that wait actively spin on their core between parallel
    # regions: on a machine with more runnable threads than cores every region then waits for
    # a descheduled spinner (stabilize.json's mode pursuit with 2 threads at load 18 on 2 cores:
    # 88.9 s wall / 30.1 s CPU, passive 10.0 s / 2.9 s). Passive unless the user chose; read
    # when torch loads, which the command has not done yet.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    parser = _parser()
    args = parser.parse_args(_split_argv(list(sys.argv[1:] if argv is None else argv)))
    try:
        if args.command == "run":
            return _cmd_run(args, parser)
        if args.command == "validate":
            return _cmd_validate(args)
        if args.command == "nodes":
            return _cmd_nodes(args)
        if args.command == "show":
            return _cmd_show(args)
        if args.command == "upgrade":
            return _cmd_upgrade(args)
        return _cmd_cache(args)
    except GraphError as err:
        print(f"nodegraph: {err}", file=sys.stderr)
        return 2
    except NodeError as err:
        print(f"nodegraph: {err}", file=sys.stderr)
        return 2 if err.bad_input else 1
    except (UsageError, NotACache) as err:
        print(f"nodegraph: {err}", file=sys.stderr)
        return 2
    except SchedulerError as err:
        print(f"nodegraph: --scheduler: {err.message}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("nodegraph: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # e.g. `nodegraph nodes | head`: the reader left, nothing is wrong
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except Exception:  # a bug in nodegraph or a node: say so, with the traceback
        print("nodegraph: unexpected error (a bug; please report it with this traceback):", file=sys.stderr)
        traceback.print_exc()
        return 1


if __name__ == "__main__":
    sys.exit(main())
