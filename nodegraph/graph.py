"""The graph model, its JSON form, and validation that reports every problem at once.

Build in Python::

    g = Graph()
    load = g.add("io.LoadMeshSequence", id="load", path="shot.npz")
    stab = g.add("stabilize.ModePursuit", id="stab")
    g.connect(load["mesh"], stab["mesh"])
    g.expose("capture", load, "path", description="tracked mesh sequence")
    g.save("stabilize.json")

JSON form (`schema` "nodegraph/1")::

    {"schema": "nodegraph/1",
     "nodes": {"load": {"type": "io.LoadMeshSequence", "type_version": 1, "params": {"path": "shot.npz"}}},
     "edges": [["load.mesh", "stab.mesh"]],
     "parameters": {"capture": {"target": "load.path", "description": "..."}}}

Parameters are stored by name only (never positionally) and only those the author set;
defaults come from the node type, so files survive new parameters. Old `type_version`s are
migrated on load through the node type's `migrate`; the file itself is never rewritten
except by `nodegraph upgrade`.
"""

from __future__ import annotations

import bisect
import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Iterator, Literal, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError

from . import registry

if TYPE_CHECKING:
    import networkx as nx
from .errors import GraphError, GraphIssue
from .files import write_text_atomic
from .node import Node
from .params import format_validation_error, number_problem, path_params

__all__ = ["SCHEMA", "PortRef", "NodeRef", "NodeSpec", "GraphParameter", "Graph", "parse_value"]

SCHEMA = "nodegraph/1"


class PortRef(NamedTuple):
    """A port of a node, written "node.port" in JSON."""

    node: str
    port: str

    def __str__(self) -> str:
        return f"{self.node}.{self.port}"

    @classmethod
    def parse(cls, text: str) -> "PortRef":
        node, sep, port = str(text).rpartition(".")
        if not sep or not node or not port:
            raise ValueError(f"expected a 'node.port' reference, found {text!r}")
        return cls(node, port)


@dataclass
class NodeSpec:
    """One node of a graph as data: type name, the version its params are written for, params,
    and optionally its own chunk size and device (overriding the run's)."""

    type: str
    type_version: int
    params: dict[str, Any] = field(default_factory=dict)
    chunk: int | None = None
    device: Literal["cpu", "cuda", "auto"] | None = None


@dataclass
class GraphParameter:
    """A node parameter a user sets per run, by a graph-level name: parameter `param` of node
    `node`, written "node.param" in JSON (`target`)."""

    node: str
    param: str
    description: str = ""

    @property
    def target(self) -> str:
        return f"{self.node}.{self.param}"

    @classmethod
    def parse(cls, target: str, description: str = "") -> "GraphParameter":
        """From the JSON form "node.param" (node ids hold no dot)."""
        node, _, param = target.rpartition(".")
        return cls(node, param, description)


class NodeRef:
    """Handle returned by `Graph.add`; `ref["port"]` is a `PortRef`."""

    def __init__(self, graph: "Graph", node_id: str):
        self.graph = graph
        self.id = node_id

    def __getitem__(self, port: str) -> PortRef:
        return PortRef(self.id, port)

    def __str__(self) -> str:
        return self.id

    def __repr__(self) -> str:
        return f"NodeRef({self.id!r})"


class _NodeEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    type: str
    type_version: int = Field(1, ge=1)
    params: dict[str, Any] = {}
    chunk: int | None = Field(None, ge=1, description="frames per chunk for this node")
    device: Literal["cpu", "cuda", "auto"] | None = None


class _ParameterEntry(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    target: str
    description: str = ""


class _GraphFile(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True)
    schema_: Literal["nodegraph/1"]
    description: str = ""
    nodes: dict[str, _NodeEntry]
    edges: list[Annotated[list[str], Field(min_length=2, max_length=2)]] = []
    parameters: dict[str, str | _ParameterEntry] = {}


def parse_value(node_cls: type[Node], param: str, text: str) -> Any:
    """Turn a command-line string into a value for `node_cls.Params.<param>`.

    The string is tried as is first (so "007" stays a string for a str field), then as JSON
    (numbers, lists, booleans).
    """
    annotation = node_cls.Params.model_fields[param].annotation
    if not number_problem(annotation, text):
        try:
            TypeAdapter(annotation).validate_python(text)
            return text
        except ValidationError:
            pass
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        return text


class Graph:
    """A graph of typed nodes (see the module docstring)."""

    def __init__(self, description: str = ""):
        self.description = description
        self.nodes: dict[str, NodeSpec] = {}
        self.edges: list[tuple[PortRef, PortRef]] = []
        self.parameters: dict[str, GraphParameter] = {}
        self.migrations: list[str] = []
        self.base_dir: Path | None = None  # relative paths in a graph file resolve against its folder

    # -- building ------------------------------------------------------------------------
    def add(self, type_name: str, id: str | None = None, *, chunk: int | None = None,
            device: str | None = None, **params: Any) -> NodeRef:
        """Add a node of registered type `type_name`; raise GraphError on a bad type or param.

        `chunk` (frames per chunk) and `device` ("cpu", "cuda", "auto") override the run's for
        this node.
        """
        cls = self._node_class(type_name, id or "?")
        node_id = id or self._fresh_id(cls.type_name.rpartition(".")[2].lower())
        if node_id in self.nodes:
            raise GraphError([GraphIssue(node_id, "", "duplicate node id")])
        if "." in node_id or not node_id:
            raise GraphError([GraphIssue(node_id, "", "node ids must be non-empty and contain no '.'")])
        issues = _param_issues(node_id, cls, params)
        if issues:
            raise GraphError(issues)
        if chunk is not None and (not isinstance(chunk, int) or isinstance(chunk, bool) or chunk < 1):
            raise GraphError([GraphIssue(node_id, "chunk", f"expected an integer >= 1, found {chunk!r}")])
        if device not in (None, "cpu", "cuda", "auto"):
            raise GraphError([GraphIssue(node_id, "device", f"expected cpu, cuda or auto, found {device!r}")])
        self.nodes[node_id] = NodeSpec(type_name, cls.version, dict(params), chunk, device)  # type: ignore[arg-type]
        return NodeRef(self, node_id)

    def connect(self, src: PortRef | str, dst: PortRef | str) -> None:
        """Connect output `src` ("node.port") to input `dst`; raise GraphError if invalid."""
        edge = (PortRef.parse(str(src)), PortRef.parse(str(dst)))
        before = set(self._edge_issues())
        self.edges.append(edge)
        new = [issue for issue in self._edge_issues() if issue not in before]
        if new:
            self.edges.pop()
            raise GraphError(new)

    def set(self, node_id: str, **params: Any) -> None:
        """Set parameters of an existing node (validated)."""
        spec = self.nodes[node_id]
        merged = {**spec.params, **params}
        issues = _param_issues(node_id, self._node_class(spec.type, node_id), merged)
        if issues:
            raise GraphError(issues)
        spec.params = merged

    def expose(self, name: str, node: NodeRef | str, param: str, description: str = "") -> None:
        """Make `node.param` settable per run as graph parameter `name`."""
        self.parameters[name] = GraphParameter(str(node), param, description)

    def apply(self, values: dict[str, Any], *, strings: bool = False) -> None:
        """Set graph parameters by name (`strings=True` parses command-line text).

        Raises:
            GraphError: listing unknown names and invalid values.
        """
        issues = []
        for name, value in values.items():
            gp = self.parameters.get(name)
            if gp is None:
                issues.append(GraphIssue("", name, f"unknown graph parameter; known: {sorted(self.parameters)}"))
                continue
            spec = self.nodes[gp.node]
            cls = self._node_class(spec.type, gp.node)
            if strings:
                value = parse_value(cls, gp.param, value)
            value = _from_working_folder(cls, gp.param, value)
            merged = {**spec.params, gp.param: value}
            found = _param_issues(gp.node, cls, merged)
            if found:
                issues.extend(GraphIssue(i.node, i.port, f"{i.message} (graph parameter '{name}')") for i in found)
            else:
                spec.params = merged
        if issues:
            raise GraphError(issues)

    def set_strings(self, assignments: dict[str, str]) -> None:
        """Apply `node.param=value` command-line assignments."""
        issues = []
        for target, text in assignments.items():
            node_id, _, param = target.rpartition(".")
            if node_id not in self.nodes:
                issues.append(GraphIssue(node_id, param, f"no node '{node_id}' for --set {target}"))
                continue
            cls = self._node_class(self.nodes[node_id].type, node_id)
            if param not in cls.Params.model_fields:
                issues.append(GraphIssue(node_id, param, f"unknown parameter; known: {sorted(cls.Params.model_fields)}"))
                continue
            value = _from_working_folder(cls, param, parse_value(cls, param, text))
            merged = {**self.nodes[node_id].params, param: value}
            found = _param_issues(node_id, cls, merged)
            if found:
                issues.extend(found)
            else:
                self.nodes[node_id].params = merged
        if issues:
            raise GraphError(issues)

    # -- queries -------------------------------------------------------------------------
    def node_class(self, node_id: str) -> type[Node]:
        return registry.get(self.nodes[node_id].type)

    def instantiate(self, node_id: str) -> Node:
        """A Node instance with this graph's params for `node_id` (relative file paths written
        in a graph file resolved against the file's folder)."""
        return registry.get(self.nodes[node_id].type)(self.resolved_params(node_id), node_id=node_id)

    def resolved_params(self, node_id: str) -> dict[str, Any]:
        """`node_id`'s params with relative input/output paths joined to `base_dir`."""
        spec = self.nodes[node_id]
        params = dict(spec.params)
        if self.base_dir is None:
            return params
        for name in path_params(registry.get(spec.type)):
            if name in params:
                params[name] = _join_paths(self.base_dir, params[name])
        return params

    def upstream(self, node_id: str) -> dict[str, PortRef]:
        """Input port -> the output it is connected to (the first, for a `many` port)."""
        out: dict[str, PortRef] = {}
        for src, dst in self.edges:
            if dst.node == node_id:
                out.setdefault(dst.port, src)
        return out

    def upstream_lists(self, node_id: str) -> dict[str, list[PortRef]]:
        """Input port -> the outputs connected to it, in edge order (several for a `many` port)."""
        out: dict[str, list[PortRef]] = {}
        for src, dst in self.edges:
            if dst.node == node_id:
                out.setdefault(dst.port, []).append(src)
        return out

    def downstream(self, node_id: str) -> list[tuple[str, PortRef]]:
        """(output port, destination input) pairs leaving `node_id`."""
        return [(src.port, dst) for src, dst in self.edges if src.node == node_id]

    def to_networkx(self) -> "nx.DiGraph":
        """The node-level graph as a networkx DiGraph (for analysis and drawing)."""
        
        g = nx.DiGraph()
        g.add_nodes_from(self.nodes)
        for src, dst in self.edges:
            g.add_edge(src.node, dst.node)
        return g

    def _successors(self) -> dict[str, list[str]]:
        succ: dict[str, list[str]] = {nid: [] for nid in self.nodes}
        for src, dst in self.edges:
            if src.node in succ and dst.node in succ and dst.node not in succ[src.node]:
                succ[src.node].append(dst.node)
        return succ

    def topological_order(self) -> list[str]:
        """Node ids, each after everything it consumes; ties broken by id (deterministic).

        Raises:
            GraphError: the graph has a cycle.
        """
        succ = self._successors()
        indegree = {nid: 0 for nid in self.nodes}
        for targets in succ.values():
            for nid in targets:
                indegree[nid] += 1
        ready = sorted(nid for nid, d in indegree.items() if d == 0)
        order: list[str] = []
        while ready:
            nid = ready.pop(0)
            order.append(nid)
            for nxt in succ[nid]:
                indegree[nxt] -= 1
                if indegree[nxt] == 0:
                    bisect.insort(ready, nxt)
        if len(order) != len(self.nodes):
            cycle = self._find_cycle() or []
            raise GraphError([GraphIssue(cycle[0] if cycle else "", "", "cycle: " + " -> ".join(cycle))])
        return order

    def _find_cycle(self) -> list[str] | None:
        """A cycle as [a, b, ..., a], or None."""
        succ = self._successors()
        state: dict[str, int] = {}  # 1 = on the stack, 2 = done
        for root in sorted(self.nodes):
            if state.get(root):
                continue
            stack: list[tuple[str, Iterator[str]]] = [(root, iter(succ[root]))]
            path = [root]
            state[root] = 1
            while stack:
                nid, children = stack[-1]
                child = next(children, None)
                if child is None:
                    stack.pop()
                    path.pop()
                    state[nid] = 2
                elif state.get(child) == 1:
                    return path[path.index(child):] + [child]
                elif not state.get(child):
                    state[child] = 1
                    path.append(child)
                    stack.append((child, iter(succ[child])))
        return None

    def descendants(self, node_id: str) -> set[str]:
        succ = self._successors()
        seen: set[str] = set()
        stack = list(succ.get(node_id, []))
        while stack:
            nid = stack.pop()
            if nid not in seen:
                seen.add(nid)
                stack.extend(succ[nid])
        return seen

    def sinks(self) -> list[str]:
        succ = self._successors()
        return [n for n in self.nodes if not succ[n]]

    # -- validation ----------------------------------------------------------------------
    def validate(self) -> list[GraphIssue]:
        """Every problem of the graph (empty when valid), each naming node and port."""
        issues: list[GraphIssue] = []
        for node_id, spec in self.nodes.items():
            if not node_id or "." in node_id:
                issues.append(GraphIssue(node_id, "", "node ids must be non-empty and contain no '.'"))
            try:
                cls = registry.get(spec.type)
            except KeyError as err:
                issues.append(GraphIssue(node_id, "", str(err.args[0])))
                continue
            if spec.type_version > cls.version:
                issues.append(GraphIssue(node_id, "", f"type_version {spec.type_version} is newer than "
                                         f"installed {spec.type} version {cls.version}; upgrade nodegraph"))
            issues.extend(_param_issues(node_id, cls, spec.params))
        issues.extend(self._edge_issues())
        for node_id, spec in self.nodes.items():
            cls = self._try_class(spec.type)
            if cls is None:
                continue
            connected = {dst.port for _, dst in self.edges if dst.node == node_id}
            for name, port in cls.inputs.items():
                if not port.optional and name not in connected:
                    issues.append(GraphIssue(node_id, name, f"required input ({port.type.type_name}) "
                                             "is not connected"))
        cycle = self._find_cycle()
        if cycle:
            issues.append(GraphIssue(cycle[0], "", f"cycle: {' -> '.join(cycle)}"))
        for name, gp in self.parameters.items():
            node_id, param = gp.node, gp.param
            if node_id not in self.nodes:
                issues.append(GraphIssue(node_id, param, f"graph parameter '{name}' targets unknown node "
                                         f"'{node_id}' ('{gp.target}')"))
                continue
            cls = self._try_class(self.nodes[node_id].type)
            if cls is not None and param not in cls.Params.model_fields:
                issues.append(GraphIssue(node_id, param, f"graph parameter '{name}' targets unknown parameter "
                                         f"'{param}'; known: {sorted(cls.Params.model_fields)}"))
        return issues

    def check(self, source: str = "") -> "Graph":
        """Raise GraphError listing every problem; return self when valid."""
        issues = self.validate()
        if issues:
            raise GraphError(issues, source)
        return self

    def _edge_issues(self) -> list[GraphIssue]:
        issues = []
        seen: dict[PortRef, PortRef] = {}
        for src, dst in self.edges:
            src_cls = self._try_class(self.nodes[src.node].type) if src.node in self.nodes else None
            dst_cls = self._try_class(self.nodes[dst.node].type) if dst.node in self.nodes else None
            if src.node not in self.nodes:
                issues.append(GraphIssue(dst.node, dst.port, f"edge from unknown node '{src.node}' ('{src}')"))
            if dst.node not in self.nodes:
                issues.append(GraphIssue(dst.node, dst.port, f"edge to unknown node '{dst.node}' (from '{src}')"))
            out_port = in_port = None
            if src_cls is not None:
                out_port = src_cls.outputs.get(src.port)
                if out_port is None:
                    issues.append(GraphIssue(src.node, src.port, f"no output port '{src.port}' on {src_cls.type_name}; "
                                             f"outputs: {sorted(src_cls.outputs)}"))
            if dst_cls is not None:
                in_port = dst_cls.inputs.get(dst.port)
                if in_port is None:
                    issues.append(GraphIssue(dst.node, dst.port, f"no input port '{dst.port}' on {dst_cls.type_name}; "
                                             f"inputs: {sorted(dst_cls.inputs)}"))
            if dst in seen and dst_cls is not None and not (in_port is not None and in_port.many):
                issues.append(GraphIssue(dst.node, dst.port, f"input connected twice: from '{seen[dst]}' and '{src}'"))
            seen.setdefault(dst, src)
            if out_port is not None and in_port is not None:
                if not issubclass(out_port.type, in_port.type):
                    issues.append(GraphIssue(dst.node, dst.port, f"type mismatch: expects {in_port.type.type_name}, "
                                             f"'{src}' gives {out_port.type.type_name}"))
                elif in_port.per_frame and not out_port.per_frame:
                    issues.append(GraphIssue(dst.node, dst.port, f"expects a per-frame {in_port.type.type_name}; "
                                             f"'{src}' gives one whole value"))
        return issues

    @staticmethod
    def _try_class(type_name: str) -> type[Node] | None:
        try:
            return registry.get(type_name)
        except KeyError:
            return None

    @staticmethod
    def _node_class(type_name: str, node_id: str) -> type[Node]:
        try:
            return registry.get(type_name)
        except KeyError as err:
            raise GraphError([GraphIssue(node_id, "", str(err.args[0]))]) from None

    def _fresh_id(self, stem: str) -> str:
        index = 0
        while f"{stem}{index}" in self.nodes:
            index += 1
        return f"{stem}{index}"

    # -- JSON ----------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """The JSON-able form (see the module docstring)."""
        data: dict[str, Any] = {"schema": SCHEMA}
        if self.description:
            data["description"] = self.description
        data["nodes"] = {}
        for nid, s in self.nodes.items():
            entry: dict[str, Any] = {"type": s.type, "type_version": s.type_version, "params": s.params}
            if s.chunk is not None:
                entry["chunk"] = s.chunk
            if s.device is not None:
                entry["device"] = s.device
            data["nodes"][nid] = entry
        data["edges"] = [[str(src), str(dst)] for src, dst in self.edges]
        data["parameters"] = {
            name: ({"target": gp.target, "description": gp.description} if gp.description else gp.target)
            for name, gp in self.parameters.items()}
        return data

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=2) + "\n"

    def save(self, path: str | os.PathLike) -> None:
        """Write the JSON form atomically (temp file + rename)."""
        write_text_atomic(Path(path), self.dumps())

    @classmethod
    def from_json(cls, data: Any, source: str = "", *, migrate: bool = True) -> "Graph":
        """Build and validate a graph from its JSON form; migrate old node versions.

        Raises:
            GraphError: every problem found, each naming node id and port.
        """
        if isinstance(data, dict) and "schema" in data:
            data = {("schema_" if k == "schema" else k): v for k, v in data.items()}
        try:
            parsed = _GraphFile.model_validate(data)
        except ValidationError as err:
            issues = [GraphIssue("", where, msg) for where, msg in format_validation_error(err)]
            raise GraphError(issues, source) from None
        graph = cls(parsed.description)
        issues: list[GraphIssue] = []
        old_versions: dict[str, int] = {}
        for node_id, entry in parsed.nodes.items():
            params = dict(entry.params)
            version = entry.type_version
            node_cls = cls._try_class(entry.type)
            if migrate and node_cls is not None and version < node_cls.version:
                try:
                    params = node_cls.migrate(version, params)
                except (ValueError, KeyError, TypeError) as err:
                    issues.append(GraphIssue(node_id, "", f"cannot migrate {entry.type} from version "
                                             f"{version} to {node_cls.version}: {err}"))
                    continue
                graph.migrations.append(f"{node_id}: {entry.type} v{version} -> v{node_cls.version}")
                old_versions[node_id] = version
                version = node_cls.version
            graph.nodes[node_id] = NodeSpec(entry.type, version, params, entry.chunk, entry.device)
        for index, (src, dst) in enumerate(parsed.edges):
            try:
                edge = [PortRef.parse(src), PortRef.parse(dst)]
            except ValueError as err:
                issues.append(GraphIssue("", f"edges[{index}]", str(err)))
                continue
            for end, ref in enumerate(edge):  # ports renamed since the version the file was written for
                if ref.node in old_versions:
                    edge[end] = PortRef(ref.node, graph.node_class(ref.node).migrate_port(old_versions[ref.node], ref.port))
            graph.edges.append((edge[0], edge[1]))
        for name, value in parsed.parameters.items():
            entry = value if isinstance(value, _ParameterEntry) else _ParameterEntry(target=value)
            graph.parameters[name] = GraphParameter.parse(entry.target, entry.description)
        issues.extend(graph.validate())
        if issues:
            raise GraphError(issues, source)
        return graph

    @classmethod
    def load(cls, path: str | os.PathLike, *, migrate: bool = True) -> "Graph":
        """Read and validate a graph file."""
        path = Path(path)
        try:
            data = json.loads(path.read_bytes(), object_pairs_hook=_no_duplicate_keys,
                              parse_constant=_no_constant)
        except FileNotFoundError:
            raise GraphError([GraphIssue("", "", f"graph file not found: {path}")], str(path)) from None
        except IsADirectoryError:
            raise GraphError([GraphIssue("", "", f"expected a graph file, found a folder: {path}")], str(path)) from None
        except OSError as err:
            raise GraphError([GraphIssue("", "", f"cannot read graph file: {err}")], str(path)) from None
        except UnicodeDecodeError as err:
            raise GraphError([GraphIssue("", "", f"not UTF-8 text: {err}")], str(path)) from None
        except RecursionError:
            raise GraphError([GraphIssue("", "", "JSON nested too deeply")], str(path)) from None
        except ValueError as err:  # JSONDecodeError, duplicate keys, NaN/Infinity
            raise GraphError([GraphIssue("", "", f"not valid JSON: {err}")], str(path)) from None
        try:
            graph = cls.from_json(data, str(path), migrate=migrate)
        except RecursionError:
            raise GraphError([GraphIssue("", "", "JSON nested too deeply")], str(path)) from None
        graph.base_dir = path.resolve().parent
        return graph

    def __iter__(self) -> Iterator[str]:
        return iter(self.nodes)

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Graph) and self.to_json() == other.to_json()


def _no_duplicate_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise ValueError(f"duplicate key {key!r} in one JSON object")
        out[key] = value
    return out


def _no_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _from_working_folder(cls: type[Node], param: str, value: Any) -> Any:
    """A relative path given on the command line (or from Python) is relative to the working
    folder: make it absolute so that the graph file's folder does not apply to it."""
    return _join_paths(Path.cwd(), value) if param in path_params(cls) else value


def _join_paths(base: Path, value: Any) -> Any:
    """Relative path strings in `value` (a path or a list of paths) joined to `base`."""
    if isinstance(value, list):
        return [_join_paths(base, item) for item in value]
    if isinstance(value, str) and value and not os.path.isabs(value):
        return os.path.normpath(os.path.join(base, value))
    return value


def _param_issues(node_id: str, cls: type[Node], params: dict[str, Any]) -> list[GraphIssue]:
    try:
        cls.Params(**params)
    except ValidationError as err:
        return [GraphIssue(node_id, where, msg) for where, msg in format_validation_error(err)]
    except TypeError as err:
        return [GraphIssue(node_id, "", f"invalid parameters: {err}")]
    return []
