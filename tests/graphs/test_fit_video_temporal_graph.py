"""The graph graphs/fit_video_temporal.json: valid, with fit_video.json's parameters (and a
motion-report folder); on synthetic plates of a smooth head motion (unseen identity, unlike
lighting) it writes fit_video.json's NPZ fields, the overlays and the motion report, and the
adaptive smoothing lowers the jitter of the raw per-frame fit, pose and weights, while staying
near the truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

from .helpers import check_graph_file

pytest.importorskip("torch")
pytest.importorskip("tflite")

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "fit_video_temporal.json"
FRAMES = 8


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = np.einsum("fij,fkj->fik", a, b)
    return np.degrees(np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def test_fit_video_temporal_graph_types_ports_params_exist():
    spec = check_graph_file(GRAPH)
    plain = json.loads((GRAPH.parent / "fit_video.json").read_text())
    assert set(plain["parameters"]) <= set(spec["parameters"])
    assert set(spec["parameters"]) == {"images", "camera", "output", "report", "motion_report", "face"}


def test_fit_video_temporal_graph_on_a_smooth_synthetic_shot(tmp_path):
    from scipy.spatial.transform import Rotation

    from nodegraph import Camera
    from tests.support.synthetic import random_face_parameters, render_truth_plates
    from nodes.io.face_model import load_face_model
    from nodes.io.image import write_image

    model = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0, name="cam0")
    truth = random_face_parameters(model, FRAMES, seed=5, distance_cm=65.0)
    t = np.arange(FRAMES, dtype=np.float64)
    yaw, pitch = 12.0 * np.sin(t / 5.0), 4.0 * np.sin(t / 4.0 + 1.0)
    r_model = Rotation.from_euler("YXZ", np.stack([yaw, pitch, np.zeros(FRAMES)], 1), degrees=True).as_matrix()
    truth["rotation"] = np.diag([1.0, -1.0, -1.0])[None] @ r_model
    truth["translation"] = np.stack([0.3 * t / FRAMES, 0.2 * np.sin(t / 3.0), 65.0 + 0.0 * t], 1)
    jaw = model.expression_names.index("jawOpen")
    truth["weights"] = np.zeros((FRAMES, len(model.expression_names)), np.float32)
    truth["weights"][:, jaw] = 0.1 + 0.05 * np.sin(t / 3.0)
    plates = render_truth_plates(model, [cam], truth)[0]
    for i, frame in enumerate(plates):
        write_image(tmp_path / f"plate.{i:04d}.png", np.clip(frame, 0, 1) ** (1 / 2.2), ["R", "G", "B"], "uint8")
    out, report, motion = tmp_path / "fit.npz", tmp_path / "overlays", tmp_path / "motion"
    params = {"images": str(tmp_path / "plate.%04d.png"), "output": str(out), "report": str(report),
              "motion_report": str(motion)}
    # threads: two fit chunks run at once (the forward-mode Jacobians must not collide)
    result = runner.run(Graph.load(GRAPH), parameters=params, scheduler="threads", workers=2, cache=False,
                        outputs=["save", "report", "motion", "expression"])
    assert result.exit_code == 0, result.summary()
    with np.load(out) as fit:
        assert {"rotation", "translation", "weights", "expression_names", "identity", "failed", "energy",
                "landmarks68", "frames"} <= set(fit.files)
        assert fit["rotation"].shape == (FRAMES, 3, 3) and fit["weights"].shape[0] == FRAMES
        assert not fit["failed"].any()
        smoothed = fit["rotation"]
    rows = {row[0]: row for row in json.loads((motion / "motion.json").read_text())["rows"]}
    assert set(rows) == {"raw", "averaged", "smoothed"}
    assert rows["smoothed"][1] < rows["raw"][1], rows  # rotation roughness (deg^2) goes down
    raw_fit = result.outputs["expression"]["fitted"].values
    raw = raw_fit[:, :9].reshape(-1, 3, 3)
    err = _rotation_error_deg(smoothed, truth["rotation"])
    raw_err = _rotation_error_deg(raw, truth["rotation"])
    print("rotation error deg raw", np.round(raw_err, 2), "smoothed", np.round(err, 2), "roughness", rows)
    assert np.median(err) < np.median(raw_err) + 0.5
    with np.load(out) as fit:  # the weights a user keeps are no rougher than the raw fit's
        weights = fit["weights"].astype(np.float64)
    assert np.mean(np.diff(weights, 2, axis=0) ** 2) <= np.mean(np.diff(raw_fit[:, 12:], 2, axis=0) ** 2) + 1e-12
    assert sorted(p.name for p in report.iterdir()) == [f"fit.{i:04d}.png" for i in range(FRAMES)]
    assert (motion / "motion.png").stat().st_size > 10_000
