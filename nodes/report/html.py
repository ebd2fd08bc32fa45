"""One self-contained HTML page of a pipeline's results: `report.Html`.

The page embeds every PNG of the connected `Files` (base64 data URIs), renders their markdown
files as HTML (`markdown_html`: headings, paragraphs, pipe tables), links their other files,
and shows every connected `Table` as an HTML table (a markdown table with the same columns
is not shown a second time), one section per connection, and draws the
graph the results came from (when `graph` names its JSON file), each node coloured by what it
did in this run. Nothing is loaded from the network. Every file is named by a link relative to
the page's folder (`relative_href`), so the folder can be moved or served as it is.

Per-node timings and cache hits: the node `uses_run_log`, so the runner hands it the records
of every task upstream of it in the current run (executed or served from the cache, seconds),
and the page tabulates them. Its output depends on the run, so it is not cacheable: it is
written again by every run (in a fraction of a second; a second run of a graph shows its
upstream nodes as cached). `nodegraph run GRAPH --report-html FILE` writes the same table for
every node of any graph, with failures and their error records; `run_page` links that page.

A short inline script marks, after loading, how many images decoded (`data-images` on
`<body>`: "decoded/total"), so that a headless browser test can check the page.
"""

from __future__ import annotations

import base64
import html
import os
import re
import time
from pathlib import Path
from typing import Mapping
from urllib.parse import quote

from pydantic import field_validator

from nodegraph import SEQUENCE, Files, In, InputError, Node, NodeParams, Out, Param, Table
from nodegraph.files import check_output_suffix, files_value, write_text_atomic

__all__ = ["Html", "html_page", "markdown_html", "relative_href"]

_SCRIPT = """<script>
window.addEventListener("load", function () {
  var images = document.querySelectorAll("img"), ok = 0;
  for (var i = 0; i < images.length; i++) { if (images[i].complete && images[i].naturalWidth > 0) ok++; }
  document.body.setAttribute("data-images", ok + "/" + images.length);
});
</script>"""


def _grid_html(columns: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(v)}</td>" for v in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _table_html(table: Table) -> str:
    return _grid_html([str(c) for c in table.columns], [[_cell(v) for v in row] for row in table.rows])


def _cell(value: object) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def relative_href(path: str | os.PathLike, page: str | os.PathLike) -> str:
    """The URL of `path` relative to the folder of the HTML file `page` (posix separators, percent-quoted).

    Example:
        >>> relative_href("/out/demo/stabilization/errors.json", "/out/demo/index.html")
        'stabilization/errors.json'
    """
    rel = os.path.relpath(os.path.abspath(path), os.path.dirname(os.path.abspath(page)))
    return quote(Path(rel).as_posix())


def _link(path: Path, page: str) -> str:
    return f'<a href="{html.escape(relative_href(path, page))}">{html.escape(path.name)}</a>'


_TABLE_RULE = re.compile(r"^\|?\s*:?-+:?\s*(\|\s*:?-+:?\s*)*\|?$")


def _row_cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def markdown_html(text: str, shown: Mapping[tuple[str, ...], str] | None = None) -> str:
    """Render the markdown that reports write as HTML: `#` headings, pipe tables, paragraphs.

    A table is a row of cells, a rule (`|---|---|`) and its rows; other lines join into
    paragraphs split by blank lines. All text is escaped (no inline markup, no raw HTML).
    A table whose header row is a key of `shown` (the columns of a `Table` the page shows
    itself) is replaced by a line naming that section, so that the page shows it once.

    Example:
        >>> markdown_html("| a | b |\\n|---|---|\\n| 1 | 2 |\\n")
        '<table><tr><th>a</th><th>b</th></tr><tr><td>1</td><td>2</td></tr></table>'
    """
    lines = text.splitlines()
    parts: list[str] = []
    paragraph: list[str] = []

    def flush() -> None:
        if paragraph:
            parts.append(f"<p>{html.escape(' '.join(paragraph))}</p>")
            paragraph.clear()

    i = 0
    while i < len(lines):
        line = lines[i].strip()
        i += 1
        heading = re.match(r"^(#{1,6})\s+(.*?)(?:\s+#+)?$", line)
        if heading:
            flush()
            level = min(len(heading.group(1)) + 2, 6)  # below the page's own h1 / h2
            parts.append(f"<h{level}>{html.escape(heading.group(2))}</h{level}>")
        elif "|" in line and i < len(lines) and _TABLE_RULE.match(lines[i].strip()):
            flush()
            rows = []
            i += 1  # the rule
            while i < len(lines) and "|" in lines[i]:
                rows.append(_row_cells(lines[i]))
                i += 1
            header = _row_cells(line)
            if shown and tuple(header) in shown:
                parts.append(f"<p>(this table is the section '{html.escape(shown[tuple(header)])}' below)</p>")
            else:
                parts.append(_grid_html(header, rows))
        elif line:
            paragraph.append(line)
        else:
            flush()
    flush()
    return "\n".join(parts)


def _files_html(paths: list[str], page: str, shown: Mapping[tuple[str, ...], str] | None = None) -> str:
    parts = []
    for path in paths:
        p = Path(path)
        if p.suffix.lower() == ".png":
            data = base64.b64encode(p.read_bytes()).decode("ascii")
            parts.append(f'<figure><img alt="{html.escape(p.name)}" src="data:image/png;base64,{data}">'
                         f"<figcaption>{_link(p, page)}</figcaption></figure>")
        elif p.suffix.lower() == ".md":
            parts.append(f"<h4>{_link(p, page)}</h4>\n{markdown_html(p.read_text(), shown)}")
        else:
            parts.append(f"<p>also written: {_link(p, page)}</p>")
    return "\n".join(parts)


def _run_html(run_log: list[dict], types: dict[str, str]) -> str:
    from nodegraph.html_report import node_rows, node_table_html

    rows = node_rows(run_log)
    done = sum(r["executed"] for r in rows)
    cached = sum(r["cached"] + r["restored"] for r in rows)
    seconds = sum(r["seconds"] for r in rows)
    return (f"<p>{len(run_log)} tasks upstream of this page: {done} executed, {cached} served from the cache; "
            f"{seconds:.1f} s of task time (tasks run in parallel: more than the wall time).</p>"
            + node_table_html(rows, types))


def html_page(title: str, sections: list[tuple[str, str]], graph_svg: str = "", run_page: str = "") -> str:
    """The page: a title, the graph (an inline SVG, may be empty), then (heading, HTML) sections."""
    link = (f'<p>Per-node timings and cache hits of the run: <a href="{html.escape(run_page)}">'
            f"{html.escape(run_page)}</a></p>") if run_page else ""
    body = "\n".join(f"<section><h2>{html.escape(name)}</h2>\n{content}\n</section>" for name, content in sections)
    graph = (f'<section><h2>Graph</h2>\n<div class="graph">{graph_svg}</div>\n</section>') if graph_svg else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
body {{ font-family: sans-serif; margin: 2em; color: #222; max-width: 1300px; }}
table {{ border-collapse: collapse; margin: 0.5em 0; }} td, th {{ border: 1px solid #ccc; padding: 3px 8px; }}
figure {{ display: inline-block; margin: 0.5em; }} img {{ max-width: 100%; border: 1px solid #ddd; }}
pre {{ background: #f6f6f6; padding: 1em; overflow-x: auto; }}
.graph {{ overflow-x: auto; border: 1px solid #eee; }}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>written {html.escape(time.strftime("%Y-%m-%d %H:%M:%S"))}</p>
{link}
{graph}
{body}
{_SCRIPT}
</body></html>
"""


class Html(Node):
    """A self-contained HTML page of the results: figures, tables and the graph drawn."""

    type_name = "report.Html"
    version = 3  # v2: markdown rendered (was raw text), files linked relative to the page (were absolute);
    # v3: a markdown table that is also a connected Table is shown once (the Table's section)
    kind = SEQUENCE
    writes_files = True
    cacheable = False  # it shows the run (uses_run_log): written again by every run
    uses_run_log = True

    class Params(NodeParams):
        path: str = Param("report.html", output_file=True, description="The HTML file to write.")
        title: str = Param("nodegraph results", description="Page title.")
        sections: list[str] = Param([], description="Heading of each `figures` connection, in order; missing "
                                    "ones are 'figures 1', 'figures 2', ...")
        table_titles: list[str] = Param([], description="Heading of each `tables` connection, in order.")
        graph: str = Param("", input_file=True, description="Graph JSON file to draw ('' = none); relative paths "
                           "in a graph file resolve against its folder.")
        run_page: str = Param("", description="Link to the run page (`nodegraph run --report-html`), '' = none.")

        @field_validator("path")
        @classmethod
        def _suffix(cls, value: str) -> str:  # refused at validation, not after the whole pipeline ran
            return check_output_suffix(value, (".html", ".htm"))

    figures = In(Files, many=True, optional=True,
                 doc="Files of report nodes: PNGs embedded, .md rendered, every file linked.")
    tables = In(Table, many=True, optional=True, doc="Tables shown.")
    files = Out(Files, doc="The HTML file.")

    def input_files(self, frames: range | None = None) -> list[Path]:
        return [Path(self.params.graph)] if self.params.graph else []

    def run(self, figures: list[Files], tables: list[Table]) -> dict[str, Files]:
        p = self.params
        if not p.path.lower().endswith((".html", ".htm")):
            raise InputError("path", f"expected a file name ending in .html, found '{p.path}'")
        sections = []
        titles = [p.table_titles[i] if i < len(p.table_titles) else f"table {i + 1}" for i in range(len(tables))]
        shown = {tuple(str(c) for c in table.columns): title for table, title in zip(tables, titles)}
        for i, files in enumerate(figures):
            name = p.sections[i] if i < len(p.sections) else f"figures {i + 1}"
            missing = [f for f in files.paths if not Path(f).is_file()]
            if missing:
                raise InputError("figures", f"connection {i} ('{name}'): expected written files, found missing "
                                            f"{missing[:3]}")
            sections.append((name, _files_html(list(files.paths), p.path, shown)))
        for table, name in zip(tables, titles):
            sections.append((name, _table_html(table)))
        svg = ""
        types: dict[str, str] = {}
        if p.graph:
            from nodegraph import Graph
            from nodegraph.html_report import graph_svg, node_rows, node_status

            try:
                graph = Graph.load(p.graph)
            except Exception as err:  # noqa: BLE001 - named, with the file, below
                raise InputError("graph", f"expected a readable graph JSON file, '{p.graph}' gave "
                                          f"{type(err).__name__}: {err}") from err
            types = {nid: spec.type for nid, spec in graph.nodes.items()}
            svg = graph_svg(graph, node_status(node_rows(self.run_log)) if self.run_log else None)
        if self.run_log:
            sections.append(("this run: per-node tasks, cache hits and seconds", _run_html(self.run_log, types)))
        write_text_atomic(p.path, html_page(p.title, sections, svg, p.run_page))
        return {"files": files_value([p.path])}
