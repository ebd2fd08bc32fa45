"""Refuse, before anything runs, output paths that would destroy the run's inputs or cannot be written.

Every output path parameter (`Param(..., output_file=True)`) of the nodes a run needs is
checked against every input path parameter (`input_file=True`) and every file the nodes'
`input_files()` list. A path is one of:

- a **pattern**: it holds a frame token (`%04d`, `%d`, `####`, `{frame}`, `{frame:04d}`, or
  any other `{name}` a writer fills in, such as `{start}`), standing for many files;
- a **folder**: an existing folder, a parameter whose name says so (`folder`, `..._dir`), or
  an output path without an extension (report folders);
- a **file**: anything else.

Refused (exit 2, one message naming both nodes, both parameters and the path): an output file
that is an input file; an output file an input pattern would read; an output pattern that
could produce an input file, or that shares an input pattern's folder, prefix and extension;
an output folder that is, or contains, an input file, folder or an input pattern's folder;
an output inside an input folder or inside the run's cache folder; two outputs of the run at
one path (or patterns that can name the same files, or one output's file path another's
folder). Also refused: an output whose nearest existing parent is a regular file, or whose
folder cannot be created or written (`os.access` on the nearest existing ancestor, then a
hidden folder made and removed there, as the run's staging will: root passes `os.access`
everywhere, yet cannot write in /proc, /sys or a read-only mount), a file output that is a
folder and a folder output that is a file. An empty output path ('' = write nothing) is skipped.
"""

from __future__ import annotations

import os
import re
import tempfile
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Iterable

from .errors import GraphError, GraphIssue
from .node import Node
from .params import field_flag

if TYPE_CHECKING:
    from .schedule import Plan

__all__ = ["PathParam", "classify", "check_output_paths", "output_path_issues"]

_TOKEN = re.compile(r"%0?\d*d|#+|\{frame(?::0?\d+d)?\}|\{[A-Za-z_][A-Za-z0-9_]*(?::[^{}]*)?\}")
_FRAME = re.compile(r"%0?\d*d|#+|\{frame(?::0?\d+d)?\}")


@dataclass(frozen=True)
class PathParam:
    """One path a node reads or writes.

    Attributes:
        node: node id.
        param: parameter name (or "input_files()" for a file listed only by that method).
        value: the path (absolute when the graph resolved it).
        kind: "file", "pattern" or "folder".
    """

    node: str
    param: str
    value: str
    kind: str

    @cached_property
    def real(self) -> str:
        return os.path.realpath(self.value)

    @cached_property
    def folder(self) -> str:
        """The folder the path's files are in (the folder itself for a folder; for a pattern,
        the folder before its first token)."""
        if self.kind == "folder":
            return self.real
        if self.kind == "pattern":
            real = self.real
            return os.path.dirname(real[:_TOKEN.search(real).start()])  # type: ignore[union-attr]
        return os.path.dirname(self.real)

    def name_parts(self) -> tuple[str, str, bool]:
        """For a pattern: (absolute text before its first token, text after its last token,
        whether the tokens are all in the file name)."""
        real = self.real
        matches = list(_TOKEN.finditer(real))
        return real[:matches[0].start()], real[matches[-1].end():], os.sep not in real[matches[0].start():]

    def regex(self) -> re.Pattern[str]:
        """For a pattern: matches the absolute paths of the files it stands for."""
        real, parts, last = self.real, [], 0
        for match in _TOKEN.finditer(real):
            parts.append(re.escape(real[last:match.start()]))
            parts.append(r"-?\d+" if _FRAME.fullmatch(match.group(0)) else r"[^/]*")
            last = match.end()
        parts.append(re.escape(real[last:]))
        return re.compile("".join(parts) + r"\Z")


def classify(value: str, param: str, output: bool) -> str:
    """"pattern", "folder" or "file" for a path value (see the module docstring)."""
    if _TOKEN.search(value):
        return "pattern"
    if os.path.isdir(value):
        return "folder"
    if output and (param == "folder" or param.endswith(("_folder", "_dir")) or not Path(value).suffix):
        return "folder"
    return "file"


def _values(node: Node, flag: str) -> list[tuple[str, str]]:
    """(parameter, path) of `node`'s non-empty path values declared with `flag`."""
    out = []
    for name in node.Params.model_fields:
        if not field_flag(node.Params, name, flag, False):
            continue
        value = getattr(node.params, name)
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if isinstance(item, str) and item:
                out.append((name, item))
    return out


def _inputs(node_id: str, node: Node) -> list[PathParam]:
    paths = [PathParam(node_id, name, value, classify(value, name, False)) for name, value in _values(node, "input_file")]
    declared = {os.path.realpath(p.value) for p in paths if p.kind == "file"}
    try:
        listed = node.input_files()
    except Exception:  # noqa: BLE001 - planning has already reported unreadable inputs
        listed = []
    params = [name for name, _ in _values(node, "input_file")]
    for path in listed:
        if os.path.realpath(path) in declared:
            continue
        param = params[0] if len(set(params)) == 1 else "input_files()"
        paths.append(PathParam(node_id, param, os.fspath(path), "file"))
    return paths


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def _patterns_overlap(a: PathParam, b: PathParam) -> bool:
    head_a, tail_a, name_a = a.name_parts()
    head_b, tail_b, name_b = b.name_parts()
    if name_a and name_b and a.folder != b.folder:
        return False  # tokens in the file names: the folders must be the same
    return (head_a.startswith(head_b) or head_b.startswith(head_a)) and \
        (tail_a.endswith(tail_b) or tail_b.endswith(tail_a))


def _clash(out: PathParam, inp: PathParam) -> str:
    """How writing `out` would destroy `inp` ("" when it would not)."""
    who = f"of node '{inp.node}' parameter '{inp.param}'"
    if out.kind != "folder" and inp.kind != "folder" and out.real == inp.real:
        return f"would overwrite the input {'file' if inp.kind == 'file' else 'pattern'} '{inp.value}' {who}"
    if out.kind == "file":
        if inp.kind == "file" and out.real == inp.real:
            return f"would overwrite the input file '{inp.value}' {who}"
        if inp.kind == "pattern" and inp.regex().match(out.real):
            return f"would overwrite a file of the input pattern '{inp.value}' {who}"
        if inp.kind == "folder" and _inside(out.real, inp.real):
            return f"would write into the input folder '{inp.value}' {who}"
    elif out.kind == "pattern":
        if inp.kind == "file" and out.regex().match(inp.real):
            return f"could overwrite the input file '{inp.value}' {who}"
        if inp.kind == "pattern" and _patterns_overlap(out, inp):
            return f"could overwrite files of the input pattern '{inp.value}' {who} (same folder, prefix and extension)"
        if inp.kind == "folder" and _inside(out.folder, inp.real):
            return f"would write into the input folder '{inp.value}' {who}"
    else:
        if inp.kind == "file" and _inside(inp.real, out.real):
            return f"is (or contains) the folder of the input file '{inp.value}' {who}"
        if inp.kind == "pattern" and _inside(inp.folder, out.real):
            return f"is (or contains) the folder that the input pattern '{inp.value}' {who} reads"
        if inp.kind == "folder" and (_inside(inp.real, out.real) or _inside(out.real, inp.real)):
            return f"overlaps the input folder '{inp.value}' {who}"
    return ""


def _writable(out: PathParam) -> str:
    """Why `out` cannot be written ("" when it can, as far as permissions tell)."""
    if out.kind == "file" and os.path.isdir(out.value):
        return "expected a file path, found a folder"
    if out.kind == "folder" and os.path.lexists(out.value) and not os.path.isdir(out.value):
        return "expected a folder, found a file"
    folder = out.folder
    here = Path(folder)
    while not os.path.lexists(here) and here.parent != here:
        here = here.parent
    if not here.is_dir():
        return f"cannot create the folder '{folder}': '{here}' is a file, not a folder"
    if not os.access(here, os.W_OK | os.X_OK):
        if str(here) == folder:
            return f"cannot write in the folder '{folder}' (permission denied)"
        return f"cannot create the folder '{folder}': '{here}' is not writable"
    try:  # what the staging does first (staging.STAGE_PREFIX folder beside the destination)
        probe = Path(tempfile.mkdtemp(prefix=".nodegraph-staging.probe.", dir=here))
    except OSError as err:
        reason = err.strerror or type(err).__name__
        if str(here) == folder:
            return f"cannot write in the folder '{folder}' ({reason})"
        return f"cannot create the folder '{folder}': '{here}' does not accept new folders ({reason})"
    probe.rmdir()
    return ""


def output_path_issues(nodes: dict[str, Node], cache_root: str | os.PathLike | None = None) -> list[GraphIssue]:
    """Every problem of the output paths of `nodes` (id -> instance), as graph issues; with
    `cache_root`, also an output inside the run's cache folder (`nodegraph cache gc` or `clear`
    would delete it with the cache's entries)."""
    outputs = [PathParam(nid, name, value, classify(value, name, True))
               for nid, node in nodes.items() for name, value in _values(node, "output_file")]
    if not outputs:
        return []
    inputs = [p for nid, node in nodes.items() for p in _inputs(nid, node)]
    issues = []
    for out in outputs:
        problem = _writable(out)
        if problem:
            issues.append(GraphIssue(out.node, out.param, f"output '{out.value}': {problem}"))
            continue
        if cache_root is not None and _inside(out.real, os.path.realpath(cache_root)):
            issues.append(GraphIssue(out.node, out.param, f"output '{out.value}' is inside the cache folder "
                                     f"'{cache_root}', whose cleaning (nodegraph cache gc / clear) would delete "
                                     "it; choose another output path"))
            continue
        for inp in inputs:
            clash = _clash(out, inp)
            if clash:
                issues.append(GraphIssue(out.node, out.param, f"output '{out.value}' {clash}; choose another "
                                                              "output path"))
                break
    for later, out in enumerate(outputs):
        for other in outputs[:later]:
            clash = _output_clash(out, other)
            if clash:
                issues.append(GraphIssue(out.node, out.param, f"output '{out.value}' {clash}; choose another "
                                                              "output path"))
                break
    return issues


def _output_clash(out: PathParam, other: PathParam) -> str:
    """How two outputs of one run would write over each other ("" when they would not): the
    same path, patterns that can name the same files, or one's file path the other's folder.
    (A file written into another output's folder is fine: writers write their own files.)"""
    who = f"of node '{other.node}' parameter '{other.param}'"
    if out.real == other.real:
        return f"is also the output '{other.value}' {who}"
    if out.kind == "pattern" and other.kind == "pattern" and _patterns_overlap(out, other):
        return f"could write the same files as the output pattern '{other.value}' {who}"
    if other.kind == "file" and _inside(out.real, other.real):
        return f"would be inside the output file '{other.value}' {who}"
    if out.kind == "file" and _inside(other.real, out.real):
        return f"would be the file the output '{other.value}' {who} needs as a folder"
    return ""


def _needed_nodes(plan: Plan) -> list[str]:
    """The plan's targets and every node upstream of them, in topological order."""
    graph = plan.graph
    seen: dict[str, None] = {}
    stack = list(plan.targets)
    while stack:
        nid = stack.pop()
        if nid in seen:
            continue
        seen[nid] = None
        for sources in graph.upstream_lists(nid).values():
            stack.extend(src.node for src in sources)
    return [nid for nid in graph.topological_order() if nid in seen]


def check_output_paths(plan: Plan, nodes: Iterable[str] | None = None,
                       cache_root: str | os.PathLike | None = None) -> None:
    """Raise GraphError (exit 2) listing every output path problem of `nodes` (default: the
    plan's targets and everything upstream of them), before anything runs; `cache_root`: the
    run's cache folder, which no output may be inside."""
    ids = list(nodes) if nodes is not None else _needed_nodes(plan)
    issues = output_path_issues({nid: plan.nodes[nid] for nid in ids}, cache_root)
    if issues:
        raise GraphError(issues)
