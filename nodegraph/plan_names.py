"""Names inside a planned run, as values with fields rather than string formats.

- `TaskName`: one task of a run, a node and the output frames of its chunk (or none, for a
  static task).
- `PortSlot`: one input of a task, a node's input port and, for a list port (`many=True`),
  which connection in edge order.

Their text (`str`) is the form the cache's records, the run log, `--explain` and the dask
keys have always used ("fit|0:64", "fit|all"; "views", "views#1"), so old caches still hit
and old records still compare; that text is only ever written, never read back for its parts.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TaskName", "PortSlot"]


@dataclass(frozen=True)
class TaskName:
    """One task of a run.

    Attributes:
        node: the node id in the graph.
        frames: the output frames [start, stop) of the task (absolute frame numbers); None for
            a static task (a node without per-frame inputs or outputs), which has no range.
    """

    node: str
    frames: tuple[int, int] | None

    def __str__(self) -> str:
        if self.frames is None:
            return f"{self.node}|all"
        return f"{self.node}|{self.frames[0]}:{self.frames[1]}"


@dataclass(frozen=True)
class PortSlot:
    """One input of a task: `port`, or the `index`-th connection (edge order) of a list port.

    Attributes:
        port: the node's input port name.
        index: the connection's position among the edges into a list port; None for a port
            that takes one connection.
    """

    port: str
    index: int | None = None

    def __str__(self) -> str:
        return self.port if self.index is None else f"{self.port}#{self.index}"
