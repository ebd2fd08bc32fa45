"""One self-contained HTML page of a pipeline's results: `report.Html`.

The page embeds every PNG of the connected `Files` (base64 data URIs), shows their markdown
files as text and every connected `Table` as an HTML table, one section per connection, and
draws the graph the results came from (when `graph` names its JSON file), each node coloured
by what it did in this run. Nothing is loaded from the network.

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
import time
from pathlib import Path

from nodegraph import SEQUENCE, Files, In, InputError, Node, NodeParams, Out, Param, Table
from nodegraph.files import files_value, write_text_atomic

__all__ = ["Html", "html_page"]

_SCRIPT = """<script>
window.addEventListener("load", function () {
  var images = document.querySelectorAll("img"), ok = 0;
  for (var i = 0; i < images.length; i++) { if (images[i].complete && images[i].naturalWidth > 0) ok++; }
  document.body.setAttribute("data-images", ok + "/" + images.length);
});
</script>"""


def _table_html(table: Table) -> str:
    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in table.columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_cell(v))}</td>" for v in row) + "</tr>" for row in table.rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _cell(value: object) -> str:
    return f"{value:.4g}" if isinstance(value, float) else str(value)


def _files_html(paths: list[str]) -> str:
    parts = []
    for path in paths:
        p = Path(path)
        if p.suffix.lower() == ".png":
            data = base64.b64encode(p.read_bytes()).decode("ascii")
            parts.append(f'<figure><img alt="{html.escape(p.name)}" src="data:image/png;base64,{data}">'
                         f"<figcaption>{html.escape(p.name)}</figcaption></figure>")
        elif p.suffix.lower() == ".md":
            parts.append(f"<h4>{html.escape(p.name)}</h4><pre>{html.escape(p.read_text())}</pre>")
        else:
            parts.append(f"<p>also written: <code>{html.escape(str(p))}</code></p>")
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
    version = 1
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

    figures = In(Files, many=True, optional=True, doc="Files of report nodes: PNGs embedded, .md shown.")
    tables = In(Table, many=True, optional=True, doc="Tables shown.")
    files = Out(Files, doc="The HTML file.")

    def input_files(self, frames: range | None = None) -> list[Path]:
        return [Path(self.params.graph)] if self.params.graph else []

    def run(self, figures: list[Files], tables: list[Table]) -> dict[str, Files]:
        p = self.params
        if not p.path.lower().endswith((".html", ".htm")):
            raise InputError("path", f"expected a file name ending in .html, found '{p.path}'")
        sections = []
        for i, files in enumerate(figures):
            name = p.sections[i] if i < len(p.sections) else f"figures {i + 1}"
            missing = [f for f in files.paths if not Path(f).is_file()]
            if missing:
                raise InputError("figures", f"connection {i} ('{name}'): expected written files, found missing "
                                            f"{missing[:3]}")
            sections.append((name, _files_html(list(files.paths))))
        for i, table in enumerate(tables):
            name = p.table_titles[i] if i < len(p.table_titles) else f"table {i + 1}"
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
