"""End to end: graphs/stabilize.json through the `nodegraph` command (the demo: test_demo_graph.py)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nodes.io.face_model import load_face_model
from nodes.io.mesh import save_mesh_sequence
from nodes.report.metrics import stabilization_errors
from nodes.synth.performance import generate_performance

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


@pytest.fixture(scope="module")
def performance():
    model = load_face_model(region="face")
    return generate_performance(model, num_frames=120, seed=3, rotation_deg=12.0, translation_cm=2.5,
                                noise_cm=0.01)


def test_stabilize_graph_runs_from_the_command_line(performance, tmp_path):
    capture = tmp_path / "shot.npz"
    save_mesh_sequence(str(capture), performance.capture, range(120))
    output, report = tmp_path / "out.npz", tmp_path / "report"
    cmd = [sys.executable, "-m", "nodegraph.cli", "run", str(GRAPHS / "stabilize.json"), f"capture={capture}",
           f"output={output}", f"report={report}", "--cache", str(tmp_path / "cache"), "--progress", "json"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with np.load(output) as saved:
        rigid, vertices = saved["rigid"], saved["vertices"]
    assert rigid.shape == (120, 4, 4) and vertices.shape == performance.capture.vertices.shape
    # world = rigid @ skull, for every frame and vertex
    world = np.einsum("fij,fvj->fvi", rigid[:, :3, :3], vertices) + rigid[:, None, :3, 3]
    np.testing.assert_allclose(world, performance.capture.vertices, atol=1e-3)
    errors = stabilization_errors(rigid, performance.rigid.matrices, performance.stabilized.vertices)
    assert errors.summary()["median_cm"] < 0.02
    assert {p.name for p in report.iterdir()} == {"head_motion.png", "histograms.png"}
    events = [json.loads(line) for line in proc.stderr.splitlines() if line.startswith("{")]
    assert any(e["event"] == "task" and e["node"] == "stab" for e in events)
    # a second run with another output path re-runs only the writer and the report
    proc = subprocess.run(cmd[:-5] + [f"output={tmp_path / 'again.npz'}", "--cache", str(tmp_path / "cache"),
                                      "--progress", "none"], capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "2 executed" in proc.stdout + proc.stderr


def test_stabilize_graph_runs_a_range_that_does_not_start_at_frame_0(performance, tmp_path):
    capture = tmp_path / "shot.npz"
    save_mesh_sequence(str(capture), performance.capture, range(120))
    output = tmp_path / "part.npz"
    proc = subprocess.run([sys.executable, "-m", "nodegraph.cli", "run", str(GRAPHS / "stabilize.json"),
                           f"capture={capture}", f"output={output}", f"report={tmp_path / 'report'}",
                           "--frames", "40:70", "--no-cache", "--progress", "none"],
                          capture_output=True, text=True, cwd=tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    with np.load(output) as saved:
        rigid, vertices = saved["rigid"], saved["vertices"]
    assert rigid.shape == (30, 4, 4)
    world = np.einsum("fij,fvj->fvi", rigid[:, :3, :3], vertices) + rigid[:, None, :3, 3]
    np.testing.assert_allclose(world, performance.capture.vertices[40:70], atol=1e-3)


def test_stabilize_graph_missing_capture_exit_2(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "nodegraph.cli", "run", str(GRAPHS / "stabilize.json"),
                           f"capture={tmp_path / 'missing.npz'}", "--no-cache"], capture_output=True, text=True,
                          cwd=tmp_path)
    assert proc.returncode == 2
    assert "'load'" in proc.stderr and "'path'" in proc.stderr and "missing.npz" in proc.stderr
