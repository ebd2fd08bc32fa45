"""Port types of plain values: a small `Table` for reports, any `JsonValue`, and the `Files`
a writer node wrote."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

from .ports import PortType, fail

__all__ = ["Table", "JsonValue", "Files"]


@dataclass(eq=False)
class Table(PortType):
    """A small table for reports.

    Attributes:
        columns: column names.
        rows: rows of JSON-able cells (numbers, strings).
    """

    columns: list[str]
    rows: list[list[Any]]

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        for index, row in enumerate(self.rows):
            if len(row) != len(self.columns):
                fail(where, f"row {index} has {len(row)} cells for {len(self.columns)} columns")

    def column(self, name: str) -> list[Any]:
        index = self.columns.index(name)
        return [row[index] for row in self.rows]

    def format(self) -> str:
        """Render as aligned plain text."""
        def cell(x: Any) -> str:
            return f"{x:.4g}" if isinstance(x, float) else str(x)
        text = [self.columns] + [[cell(x) for x in row] for row in self.rows]
        widths = [max(len(r[i]) for r in text) for i in range(len(self.columns))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in text]
        lines.insert(1, "  ".join("-" * w for w in widths))
        return "\n".join(lines)


@dataclass(eq=False)
class JsonValue(PortType):
    """Any JSON-able value (scalars, dicts of numbers, small reports)."""

    value: Any


@dataclass(eq=False)
class Files(PortType):
    """Files a node wrote.

    Attributes:
        paths: written paths, as given (relative paths stay relative).
        sha256: hex digest of each file's bytes.
    """

    paths: list[str]
    sha256: list[str]

    @classmethod
    def merge_chunks(cls, parts: Sequence["Files"]) -> "Files":
        return cls([p for part in parts for p in part.paths], [h for part in parts for h in part.sha256])
