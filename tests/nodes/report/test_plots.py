"""Tests of nodes/report/plots.py: PNGs written atomically, spread helper, CaptureReport node."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodegraph import Files, NodeError, RigidSequence, run_node
from nodes.io.face_model import load_face_model
from nodes.report.plots import (CaptureReport, plot_head_motion, plot_position_histograms, position_spread,
                                rigid_to_euler_translation)
from nodes.geometry.rigid import invert_rigid, stabilize_vertices
from nodes.synth.performance import generate_performance

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


@pytest.fixture(scope="module")
def perf():
    model = load_face_model(region="face", max_vertices=200)
    return generate_performance(model, num_frames=120, seed=11, noise_cm=0.01, rest_fraction=0.8)


def _is_png(path: Path) -> bool:
    return path.stat().st_size > 1000 and path.read_bytes()[:8] == PNG_MAGIC


def test_rigid_to_euler_translation_matches_scipy():
    rng = np.random.default_rng(0)
    angles = rng.uniform(-0.5, 0.5, (7, 3))
    m = np.tile(np.eye(4), (7, 1, 1))
    m[:, :3, :3] = Rotation.from_euler("xyz", angles).as_matrix()
    m[:, :3, 3] = rng.normal(0, 3, (7, 3))
    got_angles, got_trans = rigid_to_euler_translation(m)
    np.testing.assert_allclose(got_angles, np.rad2deg(angles), atol=1e-9)
    np.testing.assert_array_equal(got_trans, m[:, :3, 3])
    with pytest.raises(ValueError, match=r"matrices: expected shape \(F, 4, 4\), found \(7, 3, 3\)"):
        rigid_to_euler_translation(m[:, :3, :3])


def test_invert_rigid_and_stabilize_vertices_round_trip(perf):
    m = perf.rigid.matrices
    np.testing.assert_allclose(invert_rigid(m), np.linalg.inv(m), atol=1e-12)
    world = perf.capture.vertices
    skull = stabilize_vertices(world, m)
    # noise 0.01 cm is all that separates the capture brought back from the truth
    np.testing.assert_allclose(skull, perf.stabilized.vertices, atol=0.08)
    assert abs(float((skull - perf.stabilized.vertices).std()) - 0.01) < 0.001


def test_position_spread_skull_sharper_than_world(perf):
    skull = stabilize_vertices(perf.capture.vertices, perf.rigid.matrices)
    spread = position_spread(perf.capture.vertices, {"truth": perf.stabilized.vertices, "est": skull},
                             vertices=[0, 50, 199])
    assert spread.world.shape == (3, 3) and set(spread.skull) == {"truth", "est"}
    assert spread.skull["truth"].mean() < 0.2 * spread.world.mean()
    # independent reference: median absolute deviation by a float64 loop, vertex 50, coordinate y
    series = perf.capture.vertices[:, 50, 1].astype(np.float64)
    median = sorted(series)[59:61]
    median = 0.5 * (median[0] + median[1])
    deviations = sorted(abs(x - median) for x in series)
    np.testing.assert_allclose(spread.world[1, 1], 0.5 * (deviations[59] + deviations[60]), rtol=1e-6)


def test_position_spread_errors(perf):
    world = perf.capture.vertices
    with pytest.raises(ValueError, match=r"skull\['skull'\]: expected shape \(120, 200, 3\)"):
        position_spread(world, world[:, :10])
    with pytest.raises(ValueError, match=r"vertices: expected indices in 0..199, found 0..200"):
        position_spread(world, world, vertices=[0, 200])
    with pytest.raises(ValueError, match=r"world: expected shape \(F, V, 3\)"):
        position_spread(world[0], world)


def test_plot_head_motion_writes_png_atomically(perf, tmp_path):
    path = plot_head_motion({"truth": perf.rigid.matrices, "other": perf.rigid.matrices[::-1]},
                            tmp_path / "sub" / "motion.png", fps=30.0)
    assert path == tmp_path / "sub" / "motion.png" and _is_png(path)
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["motion.png"]  # no temp left
    with pytest.raises(ValueError, match=r"curves\['bad'\]: matrices: expected shape"):
        plot_head_motion({"bad": np.zeros((3, 3, 3))}, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_plot_position_histograms_writes_png(perf, tmp_path):
    path = plot_position_histograms(perf.capture.vertices, perf.stabilized.vertices,
                                    tmp_path / "hist.png", vertices=[3, 7])
    assert _is_png(path)


def test_capture_report_node_writes_files_with_sha256(perf, tmp_path):
    folder = tmp_path / "report"
    out = run_node(CaptureReport, {"folder": str(folder)}, capture=perf.capture, rigid=perf.rigid)
    files = out["files"]
    assert isinstance(files, Files)
    assert [Path(p).name for p in files.paths] == ["head_motion.png", "histograms.png"]
    for path, digest in zip(files.paths, files.sha256):
        assert _is_png(Path(path))
        assert hashlib.sha256(Path(path).read_bytes()).hexdigest() == digest
    assert CaptureReport.writes_files and CaptureReport.cacheable


def test_capture_report_node_errors(perf, tmp_path):
    short = RigidSequence(matrices=perf.rigid.matrices[:10])
    with pytest.raises(NodeError, match=r"report.CaptureReport.*'rigid'.*120 frames.*found 10"):
        run_node(CaptureReport, {"folder": str(tmp_path)}, capture=perf.capture, rigid=short)
    with pytest.raises(NodeError, match=r"report.CaptureReport.*'vertices'.*0..199"):
        run_node(CaptureReport, {"folder": str(tmp_path), "vertices": [5, 999]},
                 capture=perf.capture, rigid=perf.rigid)
