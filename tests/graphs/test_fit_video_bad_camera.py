"""fit_video.json with a malformed camera file is refused while planning, before the plate is read
and its face followed (it was refused only after landmarks.TrackFaces had run: 13-143 s)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, NodeError, runner

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "fit_video.json"


def test_a_malformed_camera_file_is_refused_while_planning(tmp_path, monkeypatch):
    from nodes.io.image import write_image
    from nodes.landmarks.nodes import TrackFaces

    write_image(tmp_path / "plate.0000.png", np.full((64, 64, 3), 0.5, np.float32), ["R", "G", "B"], "uint8")
    camera = tmp_path / "camera.json"
    camera.write_text('{"fx": 500.0}')
    ran = []
    monkeypatch.setattr(TrackFaces, "run", lambda self, **kw: ran.append(1))
    params = {"images": str(tmp_path / "plate.%04d.png"), "camera": str(camera),
              "output": str(tmp_path / "fit.npz"), "report": str(tmp_path / "report")}
    with pytest.raises(NodeError, match=r"fit\.PlateCamera 'camera': 'path': file .*camera\.json.*intrinsic matrix"):
        runner.run(Graph.load(GRAPH), parameters=params, scheduler="sync", cache=False)
    assert not ran and not (tmp_path / "fit.npz").exists() and not (tmp_path / "report").exists()
