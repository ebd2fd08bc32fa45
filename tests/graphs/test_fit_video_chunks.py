"""graphs/fit_video.json writes the same fit whatever the chunks (stop 41): a frame's rigid and
expression solves, renders and network reads never see the frames solved beside it
(tests/nodes/fit/test_batch_independence.py), so a cluster may cut a shot anywhere. Before, the
solver's retries were shared by a batch and batched products rounded by batch size: the face
mesh's points of a frame moved by 6e-5 px between chunks of 2 and 64 frames, and on 8 frames
fit.Expression's weights by up to 0.06 between batches of 8 and 3."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, runner

pytest.importorskip("torch")
pytest.importorskip("tflite")

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "fit_video.json"


@pytest.mark.slow
def test_chunks_of_one_frame_give_the_fit_of_one_chunk(tmp_path):
    from nodegraph import Camera
    from nodes.io.face_model import load_face_model
    from nodes.io.image import write_image
    from tests.support.synthetic import random_face_parameters, render_truth_plates

    model = load_face_model()
    truth = random_face_parameters(model, 3, seed=4, distance_cm=65.0)
    plates = render_truth_plates(model, [Camera.from_fov(192, 192, 30.0)], truth, noise=0.005)[0]
    for i, plate in enumerate(plates):  # linear -> sRGB-encoded 8-bit files, as a camera writes them
        srgb = np.where(plate <= 0.0031308, 12.92 * plate, 1.055 * np.clip(plate, 0, 1) ** (1 / 2.4) - 0.055)
        write_image(tmp_path / f"plate.{i:04d}.png", srgb.astype(np.float32), ["R", "G", "B"], "uint8")
    fits = []
    for chunk in (1, 3):  # the fit nodes' own chunks and batches too: one frame at a time, or all three
        out = tmp_path / f"fit_{chunk}.npz"
        params = {"images": str(tmp_path / "plate.%04d.png"), "output": str(out), "report": str(tmp_path / f"r{chunk}")}
        graph = Graph.load(GRAPH)
        for name in ("rigid", "expression"):
            graph.set(name, batch=chunk)
            graph.nodes[name].chunk = chunk
        result = runner.run(graph, parameters=params, scheduler="sync", cache=False, chunk=chunk)
        assert result.exit_code == 0, result.summary()
        with np.load(out) as fit:
            fits.append({k: fit[k] for k in fit.files})
    assert not fits[0]["failed"].any()
    for name, value in fits[0].items():
        assert np.array_equal(value, fits[1][name], equal_nan=value.dtype.kind == "f"), name
