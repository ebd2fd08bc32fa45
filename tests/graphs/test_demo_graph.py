"""graphs/demo.json end to end on a reduced frame range (the README's first command runs it on 100
frames): stabilization beats the baselines, the bundled network removes dynamics, the fit of the
renders tracks the true head motion and adaptive smoothing steadies it, the HTML page (with the run's
per-node tasks, cache hits and seconds) loads in headless Chromium with every image decoded, and a
second run is served from the cache."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Graph, run

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
FRAMES = 40


def _params(tmp_path: Path) -> dict:
    out = tmp_path / "demo"
    return {"num_frames": FRAMES, "html": str(out / "index.html"), "report": str(out / "stabilization"),
            "dynamics_report": str(out / "dynamics"), "fit_report": str(out / "fit"),
            "motion_report": str(out / "motion")}


def _rows(table) -> dict[str, dict]:
    return {row[0]: dict(zip(table.columns, row)) for row in table.rows}


def test_demo_graph_end_to_end_and_from_the_cache(tmp_path):
    params = _params(tmp_path)
    outputs = ["report", "dynamics_error", "motion", "overlays", "html", "remove", "face", "face_truth", "flags"]
    result = run(Graph.load(GRAPHS / "demo.json"), parameters=params, scheduler="threads", cache=tmp_path / "cache",
                 outputs=outputs)
    assert result.exit_code == 0, result.summary()

    median = {k: r["median_cm"] for k, r in _rows(result.outputs["report"]["table"]).items()}
    assert set(median) == {"three_point", "procrustes", "icp", "mode_pursuit"}
    assert median["mode_pursuit"] < 0.02
    assert median["mode_pursuit"] < min(median["three_point"], median["procrustes"], median["icp"])

    # dynamics: the table, and the interior frames (the ends lack the network's 10-frame windows)
    dyn = _rows(result.outputs["dynamics_error"]["table"])
    assert set(dyn) == {"baseline", "removed"} and np.isfinite(dyn["removed"]["rms_mm"])
    inner = slice(12, FRAMES - 12)
    truth = result.outputs["face_truth"]["region"].vertices[inner]
    before = np.sqrt(((result.outputs["face"]["region"].vertices[inner] - truth) ** 2).sum(-1).mean())
    after = np.sqrt(((result.outputs["remove"]["quasistatic"].vertices[inner] - truth) ** 2).sum(-1).mean())
    assert after < 0.8 * before, (before, after)

    # the fit of the renders: tracks the truth's rotation, adaptive smoothing steadies it
    motion = _rows(result.outputs["motion"]["table"])
    assert set(motion) == {"raw", "averaged", "smoothed"}
    assert motion["smoothed"]["rough_rot_deg2"] < 0.5 * motion["raw"]["rough_rot_deg2"]
    assert motion["smoothed"]["rot_err_deg"] < 5.0
    assert result.outputs["flags"]["flags"].values[:, 0].sum() <= 2  # the renders are faces
    overlays = sorted(Path(p).name for p in result.outputs["overlays"]["files"].paths)
    assert overlays == ["fit.0000.png", "fit.0025.png"]

    page = Path(params["html"])
    assert result.outputs["html"]["files"].paths == [str(page)]
    text = page.read_text()
    for name in ("histograms.png", "dynamics.png", "fit.0025.png", "motion.png", "mode_pursuit", "smoothed",
                 "this run: per-node tasks, cache hits and seconds", "<td>performance</td>"):
        assert name in text, name
    from tests.nodes.report.test_html import CHROMIUM, check_in_browser

    if CHROMIUM is not None:  # .ci/run installs Debian's chromium
        dom = check_in_browser(page, tmp_path)
        assert "dynamics.png" in dom and "motion.png" in dom

    again = run(Graph.load(GRAPHS / "demo.json"), parameters=params, scheduler="threads", cache=tmp_path / "cache",
                outputs=["html"])
    # served from the cache; only the page is written again (it shows the run: report.Html is not cacheable)
    assert again.exit_code == 0 and again.executed() == again.executed("html") == 1, again.summary()
    assert " 0 executed, " in page.read_text()
