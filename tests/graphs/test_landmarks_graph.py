"""The graph graphs/landmarks.json: valid, and it runs end to end on images and on a video."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

from .helpers import check_graph_file

pytest.importorskip("torch")
pytest.importorskip("tflite")
data = pytest.importorskip("skimage.data")

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "landmarks.json"


def test_landmarks_graph_types_ports_params_exist():
    spec = check_graph_file(GRAPH)
    assert set(spec["parameters"]) == {"images", "output", "report", "face"}


def _plate(tmp_path: Path) -> tuple[str, np.ndarray]:
    """Three frames: the astronaut, a face-free image, the astronaut shifted; as PNGs."""
    from nodes.io.image import write_image

    face = data.astronaut()[:384, :384].astype(np.float32) / 255.0
    empty = data.rocket()[:384, 128:512].astype(np.float32) / 255.0
    frames = np.stack([face, empty, np.roll(face, (20, -30), (0, 1))])
    for i, frame in enumerate(frames):
        write_image(tmp_path / f"plate.{i:04d}.png", frame, ["R", "G", "B"], "uint8")
    return str(tmp_path / "plate.%04d.png"), frames


def test_landmarks_graph_runs_on_an_image_sequence_in_chunks(tmp_path):
    pattern, _ = _plate(tmp_path)
    out, report = tmp_path / "marks.npz", tmp_path / "report"
    result = runner.run(Graph.load(GRAPH), parameters={"images": pattern, "output": str(out), "report": str(report)},
                        scheduler="sync", cache=False, chunk=2)
    assert result.exit_code == 0, result.summary()
    with np.load(out) as saved:
        assert saved["boxes"].shape == (3, 4) and saved["landmarks68"].shape == (3, 68, 2)
        assert saved["landmarks468"].shape == (3, 468, 2) and saved["presence"].shape == (3,)
        assert saved["failed"].tolist() == [False, True, False]
        assert np.isnan(saved["landmarks68"][1]).all() and saved["presence"][1] == 0
        assert saved["presence"][[0, 2]].min() > 0.9
        # the shifted frame's points moved by the shift (20 down, 30 left)
        shift = np.nanmean(saved["landmarks68"][2] - saved["landmarks68"][0], axis=0)
        np.testing.assert_allclose(shift, [-30, 20], atol=2.0)
    assert sorted(p.name for p in report.iterdir()) == [f"overlay.{i:04d}.png" for i in range(3)]


def test_landmarks_graph_runs_on_a_video(tmp_path):
    av = pytest.importorskip("av")
    _, frames = _plate(tmp_path)
    video = tmp_path / "plate.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = 384, 384, "yuv420p"
        stream.options = {"crf": "12"}
        for frame in frames:
            vf = av.VideoFrame.from_ndarray((frame * 255).round().astype(np.uint8), format="rgb24")
            for packet in stream.encode(vf):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    out = tmp_path / "marks.npz"
    result = runner.run(Graph.load(GRAPH), parameters={"images": str(video), "output": str(out),
                                                        "report": str(tmp_path / "r")}, scheduler="sync", cache=False)
    assert result.exit_code == 0, result.summary()
    with np.load(out) as saved:
        assert saved["failed"].tolist() == [False, True, False]
