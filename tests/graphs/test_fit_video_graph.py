"""The graph graphs/fit_video.json: valid; on skimage's astronaut the fitted model's projected
68 points land on the face; a frame without a face is flagged, not fitted."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

from .helpers import check_graph_file

pytest.importorskip("torch")
pytest.importorskip("tflite")
data = pytest.importorskip("skimage.data")

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "fit_video.json"


def test_fit_video_graph_types_ports_params_exist():
    spec = check_graph_file(GRAPH)
    assert set(spec["parameters"]) == {"images", "camera", "output", "report", "face"}


def test_fit_video_graph_on_the_astronaut_and_a_face_free_frame(tmp_path):
    from nodes.io.image import write_image
    from nodes.landmarks.correspondence import inter_ocular_distance

    face = data.astronaut()[:256, 64:320].astype(np.float32) / 255.0
    empty = data.rocket()[:256, 128:384].astype(np.float32) / 255.0
    for i, frame in enumerate([face, empty]):
        write_image(tmp_path / f"plate.{i:04d}.png", frame, ["R", "G", "B"], "uint8")
    out, report = tmp_path / "fit.npz", tmp_path / "report"
    params = {"images": str(tmp_path / "plate.%04d.png"), "output": str(out), "report": str(report)}
    graph = Graph.load(GRAPH)
    result = runner.run(graph, parameters=params, scheduler="sync", cache=False)
    assert result.exit_code == 0, result.summary()
    with np.load(out) as fit:
        assert fit["rotation"].shape == (2, 3, 3) and fit["translation"].shape == (2, 3)
        assert fit["weights"].shape == (2, len(fit["expression_names"])) and fit["identity"].shape == (40,)
        assert fit["failed"].tolist() == [False, True]
        assert np.isnan(fit["rotation"][1]).all()
        pts = fit["landmarks68"][0]
        vertices = fit["landmarks68_vertices"][0]
        assert np.isnan(fit["landmarks68"][1]).all()
        names = list(fit["expression_names"])
        looks = fit["weights"][0, [i for i, n in enumerate(names) if n.startswith("eyeLook")]]
    # she looks into the camera: the iris reads no look beyond the model's anatomy (its iris sits
    # 0.02 eye distances from a real one's place between the corners, about 0.15 of a full look;
    # identities spread it by 0.09 per sigma); a third of a look (10 deg) is a wrong answer
    assert len(looks) == 8 and np.abs(looks).max() < 1 / 3, looks
    from nodegraph import ImageSequence, run_node
    from nodes.landmarks import DetectFaces, FaceLandmarks
    from nodes.landmarks.network import detect_faces

    import torch

    det = detect_faces(torch.as_tensor(face[None]))
    x0, y0, x1, y1 = det.face_boxes[0]
    # the detector's box ends at the chin, where the fitted jaw line may sit past its edge: the chin
    # is the fit's flattest direction (issue 30): the compiled CPU render (951ea04, equal to the torch
    # one to 1e-12 in float64) moved it from 177.5 to 180.9 px against a box ending at 175.4 (side
    # 102 px). A margin of 8% of the box's side still tells a face from a fit that left it
    m = 0.08 * (x1 - x0)
    assert ((pts[:, 0] >= x0 - m) & (pts[:, 0] <= x1 + m) & (pts[:, 1] >= y0 - m) & (pts[:, 1] <= y1 + m)).all()
    seq = ImageSequence(face[None], colour_space="srgb")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    network68 = run_node(FaceLandmarks, images=seq, boxes=boxes)["landmarks68"].points[0]
    err = np.linalg.norm(pts - network68, axis=-1).mean() / inter_ocular_distance(network68)
    err_vertices = np.linalg.norm(vertices - network68, axis=-1).mean() / inter_ocular_distance(network68)
    print("astronaut mean error / IOD: read on the fitted head's render", err, "model's landmark vertices", err_vertices)
    # the points read on the render differ from the plate's by what the fit left unexplained (its
    # energy_rms, about 0.01-0.05 eye distances on real photos) plus the network's read-to-read
    # jitter (~0.01); the fixed vertices also carry their own convention's offset (brows, jaw line)
    assert err < 0.06 and err < err_vertices, (err, err_vertices)
    assert err_vertices < 0.10
    assert sorted(p.name for p in report.iterdir()) == ["fit.0000.png", "fit.0001.png"]
