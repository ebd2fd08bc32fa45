"""fit.Expression makes its (F, V, 3) mesh only when an edge reads it (`skips_unread_outputs`):
the fit is the same without it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")

from nodegraph import Camera, run_node  # noqa: E402
from nodegraph.node import execute  # noqa: E402
from nodes.fit import Expression, RigidPose  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from tests.support.synthetic import random_face_parameters, read_plates, render_truth_plates  # noqa: E402


def test_expression_without_its_mesh_fits_the_same():
    model = load_face_model()
    cam = Camera.from_fov(160, 160, 30.0)
    truth = random_face_parameters(model, 2, seed=4, distance_cm=65.0)
    seq, boxes, marks = read_plates(render_truth_plates(model, [cam], truth, noise=0.005)[0])
    common = dict(landmarks=[marks], boxes=[boxes], cameras=[cam], model=model)
    pose = run_node(RigidPose, {"rounds": 1}, frames=range(2), **common)["pose"]
    full = run_node(Expression, {"rounds": 1}, frames=range(2), pose=pose, **common)
    node = Expression({"rounds": 1})
    inputs = dict(common, pose=pose)
    lean = execute(node, inputs, range(2), range(2), wanted=["fitted", "energy", "failed"])
    assert "mesh" not in lean and set(full) == {"fitted", "mesh", "energy", "failed"}
    np.testing.assert_array_equal(lean["fitted"].values, full["fitted"].values)
    np.testing.assert_array_equal(lean["energy"].values, full["energy"].values)
    # the full run's mesh is the fitted head: the model at the weights, posed
    v = full["fitted"].values
    posed = model.evaluate(v[:, 12:]) @ np.swapaxes(v[:, :9].reshape(-1, 3, 3), 1, 2) + v[:, None, 9:12]
    np.testing.assert_allclose(full["mesh"].vertices, posed, atol=1e-4)  # cm, float32 rounding at ~65 cm
