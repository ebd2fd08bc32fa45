"""Errors of the framework: each names where (node id, port), what was expected and what was found."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["NodegraphError", "GraphIssue", "GraphError", "InputError", "NodeError", "SchedulerError"]


class NodegraphError(Exception):
    """Base of every error the framework raises on purpose."""


@dataclass(frozen=True)
class GraphIssue:
    """One problem found while validating a graph.

    Attributes:
        node: node id the problem is at ("" for graph-wide problems).
        port: port or parameter name ("" when none applies).
        message: what was expected and what was found.
    """

    node: str
    port: str
    message: str

    def __str__(self) -> str:
        where = f"node '{self.node}'" if self.node else "graph"
        if self.port:
            where += f", '{self.port}'"
        return f"{where}: {self.message}"


class GraphError(NodegraphError):
    """A graph failed validation; `issues` lists every problem found, not only the first."""

    def __init__(self, issues: list[GraphIssue], source: str = ""):
        self.issues = list(issues)
        self.source = source
        head = f"invalid graph{f' {source}' if source else ''}: {len(self.issues)} problem(s)"
        super().__init__(head + "".join(f"\n  - {issue}" for issue in self.issues))


class InputError(ValueError):
    """Raised by a node's `run` (or a pure function) when an input value is unusable.

    The framework adds the node id and type; the node names the port.

    Args:
        port: input port or parameter name.
        message: what was expected and what was found.
    """

    def __init__(self, port: str, message: str):
        self.port = port
        self.message = message
        super().__init__(f"'{port}': {message}")


class NodeError(NodegraphError):
    """A node failed while running a chunk of frames.

    Attributes:
        node: node id.
        node_type: registered type name.
        port: offending port when the cause is a bad input or output, else "".
        frames: (start, stop) of the chunk, or None for whole-value nodes.
        bad_input: True when the cause is bad input data (exit code 2), False for a crash (exit 1).
    """

    def __init__(self, node: str, node_type: str, message: str, *, port: str = "",
                 frames: tuple[int, int] | None = None, bad_input: bool = False):
        self.node = node
        self.node_type = node_type
        self.port = port
        self.frames = frames
        self.bad_input = bad_input
        self.message = message
        where = f"{node_type} '{node}'"
        if frames is not None:
            where += f" (frames {frames[0]}:{frames[1]})"
        if port:
            where += f": '{port}'"
        super().__init__(f"{where}: {message}")


class SchedulerError(NodegraphError):
    """The scheduler asked for is not one nodegraph knows, or cannot be reached (exit 2).

    Attributes:
        scheduler: the scheduler as given ("nosuch", "tcp://farm:8786").
        message: what was expected and what was found.
    """

    def __init__(self, scheduler: str, message: str):
        self.scheduler = scheduler
        self.message = message
        super().__init__(f"scheduler {scheduler!r}: {message}")
