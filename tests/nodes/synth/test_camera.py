"""synth.LookAtCamera: the target projects to the principal point, up is up, errors are named."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph.errors import NodeError
from nodegraph import run_node
from nodes.geometry.camera import project_points
from nodes.synth.camera import LookAtCamera, look_at


def _pixels(camera, points):
    return project_points(np.asarray(points, np.float64), camera.world_to_camera,
                          [camera.fx, camera.fy, camera.cx, camera.cy], None)


def test_target_at_the_centre_and_up_is_up():
    camera = run_node(LookAtCamera, {"eye_cm": [10.0, 5.0, 60.0], "target_cm": [1.0, -2.0, 3.0], "width": 320,
                                     "height": 240})["camera"]
    e = camera.world_to_camera
    np.testing.assert_allclose(e[:3, :3] @ e[:3, :3].T, np.eye(3), atol=1e-12)
    assert np.linalg.det(e[:3, :3]) > 0
    uv = _pixels(camera, [[1.0, -2.0, 3.0], [1.0, 0.0, 3.0]])
    np.testing.assert_allclose(uv[0], [camera.cx, camera.cy], atol=1e-9)
    assert uv[1, 1] < uv[0, 1]  # a point above the target is higher in the image (smaller y)
    centre = camera.camera_to_world()[:3, 3]
    np.testing.assert_allclose(centre, [10.0, 5.0, 60.0], atol=1e-9)


def test_front_view_of_the_face_keeps_x_to_the_right():
    e = look_at([0.0, 0.0, 60.0], [0.0, 0.0, 0.0])
    np.testing.assert_allclose(e[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_bad_placements_are_named():
    with pytest.raises(NodeError, match="eye_cm"):
        run_node(LookAtCamera, {"eye_cm": [0.0, 0.0, 5.0], "target_cm": [0.0, 0.0, 5.0]})
    with pytest.raises(NodeError, match="'up'"):
        run_node(LookAtCamera, {"eye_cm": [0.0, 10.0, 0.0], "target_cm": [0.0, 0.0, 0.0]})
