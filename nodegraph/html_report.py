"""A self-contained HTML page about one run: the graph drawn, per-node timings and cache
hits, failures with their error records. No scripts, no network: one file to open anywhere.

    nodegraph run GRAPH.json --report-html run.html
"""

from __future__ import annotations

import html
import time
from collections import defaultdict
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .graph import Graph
    from .runner import RunResult

__all__ = ["graph_svg", "node_rows", "node_table_html", "node_status", "run_report_html"]

_STATUS_COLOURS = {"executed": "#4c78a8", "cached": "#59a14f", "restored": "#8cd17d", "failed": "#e15759",
                   "skipped": "#bab0ac", "idle": "#ffffff"}
_BOX_W, _BOX_H, _GAP_X, _GAP_Y = 190, 46, 70, 22


def _layers(graph: "Graph") -> dict[str, int]:
    """Column of each node: the length of the longest path reaching it."""
    layer: dict[str, int] = {}
    for nid in graph.topological_order():
        ups = {src.node for src, dst in graph.edges if dst.node == nid}
        layer[nid] = 1 + max((layer[u] for u in ups), default=-1)
    return layer


def graph_svg(graph: "Graph", status: dict[str, str] | None = None) -> str:
    """The graph as an inline SVG: one box per node (coloured by `status[node]`), one arrow per
    connected node pair labelled with its ports, left to right in dependency order."""
    status = status or {}
    layer = _layers(graph)
    columns: dict[int, list[str]] = defaultdict(list)
    for nid in graph.topological_order():
        columns[layer[nid]].append(nid)
    pos = {nid: (20 + col * (_BOX_W + _GAP_X), 20 + row * (_BOX_H + _GAP_Y))
           for col, nids in columns.items() for row, nid in enumerate(nids)}
    width = 40 + (max(columns, default=0) + 1) * (_BOX_W + _GAP_X) - _GAP_X
    height = 40 + max((len(v) for v in columns.values()), default=1) * (_BOX_H + _GAP_Y) - _GAP_Y
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
             f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="11">',
             '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="7" markerHeight="7" '
             'orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" fill="#555"/></marker></defs>']
    labels: dict[tuple[str, str], list[str]] = defaultdict(list)
    for src, dst in graph.edges:
        labels[(src.node, dst.node)].append(f"{src.port}→{dst.port}")
    for (a, b), ports in labels.items():
        (xa, ya), (xb, yb) = pos[a], pos[b]
        x1, y1, x2, y2 = xa + _BOX_W, ya + _BOX_H / 2, xb, yb + _BOX_H / 2
        parts.append(f'<path d="M {x1} {y1} C {x1 + 35} {y1}, {x2 - 35} {y2}, {x2} {y2}" fill="none" '
                     f'stroke="#555" marker-end="url(#arrow)"><title>{html.escape(", ".join(ports))}</title></path>')
    for nid, (x, y) in pos.items():
        fill = _STATUS_COLOURS.get(status.get(nid, "idle"), "#ffffff")
        text_colour = "#fff" if status.get(nid) in ("executed", "failed") else "#000"
        parts.append(f'<rect x="{x}" y="{y}" width="{_BOX_W}" height="{_BOX_H}" rx="6" fill="{fill}" '
                     f'stroke="#333"/>')
        parts.append(f'<text x="{x + 8}" y="{y + 18}" fill="{text_colour}" font-weight="bold">'
                     f'{html.escape(nid)}</text>')
        parts.append(f'<text x="{x + 8}" y="{y + 34}" fill="{text_colour}">'
                     f'{html.escape(graph.nodes[nid].type)}</text>')
    parts.append("</svg>")
    return "\n".join(parts)


def node_rows(tasks: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per node, in first-seen order: tasks, executed / cached / restored / failed / skipped counts and
    seconds, from task records (`RunResult.tasks`, or a node's `run_log`)."""
    rows: dict[str, dict[str, Any]] = {}
    for task in tasks:
        row = rows.setdefault(task["node"], {"node": task["node"], "tasks": 0, "seconds": 0.0,
                                             **{s: 0 for s in ("executed", "cached", "restored", "failed", "skipped")}})
        row["tasks"] += 1
        row[task["status"]] = row.get(task["status"], 0) + 1
        row["seconds"] += float(task.get("seconds") or 0.0)
    return list(rows.values())


def node_table_html(rows: list[dict[str, Any]], types: dict[str, str]) -> str:
    """The per-node table of `node_rows` (types: node id -> type name)."""
    table = ["<table><tr><th>node</th><th>type</th><th>tasks</th><th>executed</th><th>cached</th>"
             "<th>restored</th><th>failed</th><th>skipped</th><th>seconds</th></tr>"]
    for row in rows:
        table.append(
            f"<tr><td>{html.escape(row['node'])}</td><td>{html.escape(types.get(row['node'], ''))}</td>"
            f"<td>{row['tasks']}</td><td>{row['executed']}</td><td>{row['cached']}</td><td>{row['restored']}</td>"
            f"<td>{row['failed']}</td><td>{row['skipped']}</td><td>{row['seconds']:.3f}</td></tr>")
    table.append("</table>")
    return "".join(table)


def node_status(rows: list[dict[str, Any]]) -> dict[str, str]:
    """Node id -> the status its box is coloured by (failed, skipped, executed, restored, cached)."""
    return {row["node"]: _summary_status(row) for row in rows}


def _summary_status(row: dict[str, Any]) -> str:
    for status in ("failed", "skipped", "executed", "restored", "cached"):
        if row.get(status):
            return status
    return "idle"


def run_report_html(result: "RunResult", graph: "Graph", *, title: str = "nodegraph run") -> str:
    """The HTML page of a finished run (see the module docstring)."""
    rows = node_rows(result.tasks)
    status = node_status(rows)
    table = [node_table_html(rows, {nid: spec.type for nid, spec in graph.nodes.items()})]
    failures = []
    for failure in result.failures:
        failures.append(
            f"<h3>{html.escape(str(failure.get('node')))} frames {html.escape(str(failure.get('frames')))}</h3>"
            f"<p>{html.escape(str(failure.get('message')))}</p>"
            f"<p>error record: <code>{html.escape(str(failure.get('record', '')))}</code></p>"
            f"<pre>{html.escape(str(failure.get('traceback', '')))}</pre>")
    legend = " ".join(f'<span class="chip" style="background:{c}">{s}</span>' for s, c in _STATUS_COLOURS.items()
                      if s != "idle")
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; }}
table {{ border-collapse: collapse; }} td, th {{ border: 1px solid #ccc; padding: 3px 8px; text-align: right; }}
td:first-child, td:nth-child(2), th {{ text-align: left; }}
pre {{ background: #f6f6f6; padding: 1em; overflow-x: auto; }}
.chip {{ padding: 2px 8px; border-radius: 4px; color: #fff; margin-right: 4px; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>{html.escape(result.summary().splitlines()[0])} &mdash; exit code {result.exit_code} &mdash;
written {html.escape(time.strftime("%Y-%m-%d %H:%M:%S"))}</p>
<h2>Graph</h2><p>{legend}</p>
{graph_svg(graph, status)}
<h2>Nodes</h2>
{"".join(table)}
<h2>Failures</h2>
{"".join(failures) if failures else "<p>none</p>"}
</body></html>
"""
