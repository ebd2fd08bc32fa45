"""report.Html and the files of its `figures`: markdown rendered once as HTML (no raw `<pre>`
copy), every file named by a link relative to the page (no absolute path of the machine that
wrote it), links that still resolve when the folder is moved."""

from __future__ import annotations

import shutil
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote, urlsplit

import numpy as np

from nodegraph import Table, run_node
from nodegraph.files import files_value
from nodes.report.html import Html, markdown_html, relative_href
from nodes.report.plots import plot_head_motion
from nodes.report.stabilization import markdown_table, write_table

TABLE = Table(["method", "median_cm"], [["mode_pursuit", 0.0018], ["procrustes", 0.07]])


class _Links(HTMLParser):
    """The `href` of every `<a>` of a page."""

    def __init__(self) -> None:
        super().__init__()
        self.hrefs: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        if tag == "a":
            self.hrefs += [value for name, value in attrs if name == "href" and value is not None]


def _hrefs(text: str) -> list[str]:
    parser = _Links()
    parser.feed(text)
    return parser.hrefs


def _report(folder: Path) -> list[str]:
    """A small report folder as a report node writes it: a PNG, errors.md and errors.json."""
    motion = np.tile(np.eye(4), (10, 1, 1))
    motion[:, 0, 3] = np.linspace(0, 2, 10)
    png = plot_head_motion({"truth": motion}, folder / "head motion.png")
    return [str(png)] + [str(p) for p in write_table(folder, "errors", TABLE)]


def test_markdown_html_renders_headings_paragraphs_and_tables():
    text = "# Errors\n\nagainst the\nground truth\n\n| a | b |\n|:--|--:|\n| 1 | x<y |\n| 2 | 3 |\n\nend\n"
    assert markdown_html(text) == (
        "<h3>Errors</h3>\n<p>against the ground truth</p>\n"
        "<table><tr><th>a</th><th>b</th></tr><tr><td>1</td><td>x&lt;y</td></tr><tr><td>2</td><td>3</td></tr>"
        "</table>\n<p>end</p>")
    assert markdown_html("## C# ##") == "<h4>C#</h4>"
    assert markdown_html("a | b without a rule") == "<p>a | b without a rule</p>"
    assert markdown_html("") == ""


def test_html_page_renders_a_markdown_table_once_without_pre(tmp_path):
    files = _report(tmp_path / "report")
    page = tmp_path / "index.html"
    run_node(Html, {"path": str(page), "sections": ["stabilization"]}, figures=[files_value(files)], tables=[])
    text = page.read_text()
    assert "<pre" not in text
    assert "| method | median_cm |" not in text and "|---|" not in text
    assert text.count("<table>") == 1
    assert "<tr><th>method</th><th>median_cm</th></tr><tr><td>mode_pursuit</td><td>0.0018</td></tr>" in text
    assert markdown_table(TABLE).count("|") > 0  # the file itself stays markdown


def test_html_page_links_every_file_relative_to_the_page(tmp_path):
    site = tmp_path / "site"
    files = _report(site / "stabilization")
    outside = tmp_path / "elsewhere" / "notes.json"
    outside.parent.mkdir()
    outside.write_text("{}\n")
    page = site / "index.html"
    run_node(Html, {"path": str(page), "sections": ["stabilization", "other"], "table_titles": ["errors"]},
             figures=[files_value(files), files_value([str(outside)])], tables=[TABLE])
    text = page.read_text()
    assert str(tmp_path) not in text and str(tmp_path.resolve()) not in text
    hrefs = _hrefs(text)
    assert sorted(hrefs) == ["../elsewhere/notes.json", "stabilization/errors.json", "stabilization/errors.md",
                             "stabilization/head%20motion.png"]
    for href in hrefs:
        parts = urlsplit(href)
        assert not parts.scheme and not parts.netloc and not href.startswith("/"), href
        assert (page.parent / unquote(href)).is_file(), href
    assert '<p>also written: <a href="stabilization/errors.json">errors.json</a></p>' in text

    # the folder moved (or served): its own links still resolve
    moved = shutil.move(str(site), str(tmp_path / "moved"))
    for href in hrefs:
        if not href.startswith("../"):
            assert (Path(moved) / unquote(href)).is_file(), href


def test_html_page_links_relative_paths_given_from_the_working_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    files = _report(Path("out") / "report")
    run_node(Html, {"path": "out/pages/index.html"}, figures=[files_value(files)], tables=[])
    text = (tmp_path / "out" / "pages" / "index.html").read_text()
    assert sorted(_hrefs(text)) == ["../report/errors.json", "../report/errors.md", "../report/head%20motion.png"]
    assert relative_href("out/report/errors.md", "out/pages/index.html") == "../report/errors.md"
    assert relative_href(tmp_path / "a" / "b.md", tmp_path / "page.html") == "a/b.md"


def test_a_markdown_table_that_is_also_a_connected_table_is_shown_once(tmp_path):
    table = Table(["method", "median_cm"], [["procrustes", 0.2257], ["mode_pursuit", 0.0173]])
    (tmp_path / "report").mkdir()
    md = write_table(tmp_path / "report", "errors", table)[0]  # errors.md, as the reports write it
    other = tmp_path / "report" / "other.md"
    other.write_text("| series | value |\n|---|---|\n| raw | 1.5 |\n")
    page = tmp_path / "index.html"
    run_node(Html, {"path": str(page), "table_titles": ["stabilization errors"]},
             figures=[files_value([str(md), str(other)])], tables=[table])
    text = page.read_text()
    assert text.count("<td>procrustes</td>") == 1 and text.count("<td>mode_pursuit</td>") == 1
    assert "(this table is the section 'stabilization errors' below)" in text
    assert "<td>raw</td>" in text  # a markdown table without a connected twin is still rendered
