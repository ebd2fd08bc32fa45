"""report.Html: a self-contained page (images embedded, no network) with the graph drawn; opened in
headless Chromium (Debian's `chromium`; `.ci/run` installs it): no console errors, every image
decodes, a screenshot is saved."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Files, Table, run_node
from nodegraph.files import files_value
from nodes.report.html import Html

GRAPHS = Path(__file__).resolve().parents[3] / "graphs"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--enable-logging=stderr", "--v=0", "--virtual-time-budget=5000"]


def browse(page: Path, profile: Path, *extra: str) -> subprocess.CompletedProcess:
    """Run headless Chromium on a local page (fresh profile, no network helpers)."""
    return subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", *extra, page.as_uri()],
                          capture_output=True, text=True, timeout=120)


def check_in_browser(page: Path, tmp: Path) -> str:
    """Assert the page loads without console errors and every image decodes; save a screenshot
    next to it; return the DOM after load."""
    dom = browse(page, tmp / "profile-dom", "--dump-dom")
    assert dom.returncode == 0, dom.stderr[-2000:]
    console = [line for line in dom.stderr.splitlines() if "CONSOLE" in line or "Uncaught" in line]
    errors = [line for line in console if re.search(r"error|Uncaught", line, re.IGNORECASE)]
    assert not errors, errors
    found = re.search(r'data-images="(\d+)/(\d+)"', dom.stdout)
    assert found, "the page's load script did not run"
    decoded, total = int(found.group(1)), int(found.group(2))
    assert total > 0 and decoded == total, f"{decoded} of {total} images decoded"
    shot = page.with_suffix(".png")
    done = browse(page, tmp / "profile-shot", f"--screenshot={shot}", "--window-size=1280,2400")
    assert done.returncode == 0 and shot.is_file() and shot.stat().st_size > 10_000, done.stderr[-2000:]
    return dom.stdout


def _figures(tmp: Path) -> Files:
    from nodes.report.plots import plot_head_motion

    motion = np.tile(np.eye(4), (20, 1, 1))
    motion[:, 0, 3] = np.linspace(0, 2, 20)
    png = plot_head_motion({"truth": motion}, tmp / "head_motion.png")
    (tmp / "errors.md").write_text("| a | b |\n|---|---|\n| 1 | 2 |\n")
    return files_value([str(png), str(tmp / "errors.md")])


def test_html_page_embeds_figures_tables_and_the_graph(tmp_path):
    out = tmp_path / "report.html"
    table = Table(["method", "median cm"], [["mode pursuit", 0.0018], ["procrustes", 0.07]])
    run_node(Html, {"path": str(out), "title": "demo", "sections": ["stabilization"], "table_titles": ["errors"],
                    "graph": str(GRAPHS / "stabilize.json"), "run_page": "run.html"},
             figures=[_figures(tmp_path)], tables=[table])
    text = out.read_text()
    assert "data:image/png;base64," in text and "<svg" in text and "mode pursuit" in text
    assert "http://" not in text.replace('xmlns="http://www.w3.org/2000/svg"', "") and "https://" not in text
    assert '<a href="run.html">' in text
    with pytest.raises(Exception, match="path"):
        run_node(Html, {"path": str(tmp_path / "report.txt")}, figures=[], tables=[])
    with pytest.raises(Exception, match="figures"):
        run_node(Html, {"path": str(out)}, figures=[Files([str(tmp_path / "missing.png")], ["0" * 64])], tables=[])


@pytest.mark.skipif(CHROMIUM is None, reason="Debian's chromium is not installed (.ci/run installs it)")
def test_html_page_opens_in_headless_chromium(tmp_path):
    out = tmp_path / "report.html"
    run_node(Html, {"path": str(out), "graph": str(GRAPHS / "stabilize.json")}, figures=[_figures(tmp_path)],
             tables=[])
    dom = check_in_browser(out, tmp_path)
    assert "head_motion.png" in dom
