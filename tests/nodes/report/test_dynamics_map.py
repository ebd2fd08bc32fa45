"""report.DynamicsMap: offsets drawn where they are (flat colours on the front view), one shared
scale, the frame with the largest true offsets picked, mismatched inputs named."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph.errors import NodeError
from nodegraph import MeshSequence, RigidSequence, run_node
from nodes.report.dynamics_map import DynamicsMap, render_scalar_front


def _grid(n: int = 12) -> tuple[np.ndarray, np.ndarray]:
    """An n x n vertex grid in the z = 0 plane, 10 cm wide, facing +z."""
    x, y = np.meshgrid(np.linspace(-5, 5, n), np.linspace(-5, 5, n))
    verts = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], 1).astype(np.float32)
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + n], 1), np.stack([a + 1, a + n + 1, a + n], 1)]).astype(np.int32)
    return verts, faces


def test_values_land_on_their_side_of_the_mesh():
    verts, faces = _grid()
    values = (verts[:, 0] > 0).astype(np.float64)  # right half (+x) hot
    image = render_scalar_front(verts, faces, values, vmax=1.0, size=96)
    assert image.shape == (96, 96, 3)
    row = image[48]
    left, right = row[25:40].mean(), row[56:71].mean()
    assert right > left + 0.5  # magma: 0 black, 1 light yellow; +x is on the image's right
    assert np.allclose(image[2, 2], 1.0)  # white background


def test_node_picks_the_frame_of_the_largest_true_offsets(tmp_path):
    verts, faces = _grid()
    frames = 4
    truth = np.repeat(verts[None], frames, 0)
    bump = np.zeros((frames, len(verts), 3), np.float32)
    bump[2, :, 2] = 0.3  # frame 2 has the largest offsets
    bump[1, :, 2] = 0.1
    capture = MeshSequence(truth + bump, faces)
    result = MeshSequence(truth + 0.5 * bump, faces)
    out = run_node(DynamicsMap, {"folder": str(tmp_path), "size": 96}, capture=capture, result=result,
                   skull=RigidSequence(np.tile(np.eye(4), (frames, 1, 1))), truth=MeshSequence(truth, faces))
    path = tmp_path / "dynamics.png"
    assert out["files"].paths == [str(path)] and path.stat().st_size > 5000
    import matplotlib.image

    assert matplotlib.image.imread(path).shape[1] > 3 * 96  # three panels and a colour bar


def test_mismatched_inputs_are_named(tmp_path):
    verts, faces = _grid()
    capture = MeshSequence(np.repeat(verts[None], 3, 0), faces)
    skull = RigidSequence(np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(NodeError, match="'result'"):
        run_node(DynamicsMap, {"folder": str(tmp_path)}, capture=capture, result=MeshSequence(verts[None, :5]),
                 skull=skull)
    with pytest.raises(NodeError, match="'skull'"):
        run_node(DynamicsMap, {"folder": str(tmp_path)}, capture=capture, result=capture,
                 skull=RigidSequence(np.tile(np.eye(4), (2, 1, 1))))
