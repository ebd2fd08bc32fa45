"""The TFLite replay's plan (`TfliteModule.forward`) against the op-by-op replay
(`forward_reference`): values, gradients (to the input and the weights), dtype moves, one plan
per input size; `iris_landmarks` on a batch with a row without a face.

Tolerances: float32 carries 2^-24 ~ 6e-8 relative per rounding; the plan reorders sums (1 x 1
convolutions as matrix products, paddings inside the convolution) in layers summing up to 1152
terms, over some 50 layers, so a worst-case bound is about 50 * sqrt(1152) * 6e-8 ~ 1e-4 of the
output's scale and a typical one 1e-6 (measured: at most 1e-6 relative on random crops); the
tests allow 2e-5. In float64 the same argument gives ~1e-13: 1e-10 allowed.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("tflite")

from nodes.landmarks.iris import IrisNetwork, iris_landmarks, load_iris_network  # noqa: E402
from nodes.landmarks.network import (BlazeFace, FullRangeBlazeFace, MediaPipeFaceMesh,  # noqa: E402
                                     load_face_detector, load_face_mesh, load_full_range_detector)

CASES = [("mesh", load_face_mesh, (1, 192, 192, 3)), ("iris", load_iris_network, (2, 64, 64, 3)),
         ("detector", load_face_detector, (1, 128, 128, 3)), ("detector level", load_face_detector, (2, 256, 320, 3)),
         ("full range", load_full_range_detector, (1, 192, 192, 3))]


@pytest.mark.parametrize("name, load, shape", CASES, ids=[c[0] for c in CASES])
def test_plan_matches_the_op_by_op_replay(name, load, shape):
    net = load().net
    x = torch.rand(*shape, generator=torch.Generator().manual_seed(3))
    with torch.no_grad():
        planned, reference = net(x), net.forward_reference(x)
    assert len(planned) == len(reference)
    for p, r in zip(planned, reference):
        assert p.shape == r.shape and p.dtype == r.dtype
        scale = float(r.abs().max())
        assert float((p - r).abs().max()) <= 2e-5 * scale, name
    assert tuple(shape[1:]) in net._plans  # resolved once for this input size


@pytest.mark.parametrize("make, shape", [(MediaPipeFaceMesh, (1, 192, 192, 3)), (IrisNetwork, (2, 64, 64, 3)),
                                         (BlazeFace, (1, 128, 128, 3))], ids=["mesh", "iris", "detector"])
def test_plan_gradients_match_the_op_by_op_replay_in_float64(make, shape):
    net = make().double().net
    assert not net._plans  # .double() starts the plans afresh
    g = torch.Generator().manual_seed(4)
    x = torch.rand(*shape, generator=g, dtype=torch.float64)
    weights = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in net.forward_reference(x)]
    grads = []
    for forward in (net.forward, net.forward_reference):
        xi = x.clone().requires_grad_(True)
        outputs = forward(xi)
        assert all(o.dtype == torch.float64 for o in outputs)
        loss = sum((o * w).sum() for o, w in zip(outputs, weights))
        grads.append(torch.autograd.grad(loss, xi)[0])
    scale = float(grads[1].abs().max())
    assert scale > 0
    assert float((grads[0] - grads[1]).abs().max()) <= 1e-10 * scale


def test_plan_gives_gradients_to_the_weights():
    net = MediaPipeFaceMesh().net
    net.requires_grad_(True)
    x = torch.rand(1, 192, 192, 3, generator=torch.Generator().manual_seed(5))
    coords, logit = net(x)
    (coords.sum() + logit.sum()).backward()
    unused = [k for k, w in net.weights.items() if w.grad is None]
    assert not unused  # every weight, the 1 x 1 and whole-input matrix products' included
    assert all(torch.isfinite(w.grad).all() for w in net.weights.values())


def test_iris_landmarks_nan_rows_and_batch():
    from tests.nodes.landmarks.cases import photo

    from nodes.landmarks.face_tracker import track_faces

    image = photo("astronaut")
    points = track_faces(image[None], with_iris=False).points[0]
    images = torch.from_numpy(np.stack([image, image, image]))
    rows = np.stack([points, np.full_like(points, np.nan), points])
    iris = iris_landmarks(images, rows, load_iris_network())
    assert np.isnan(iris[1]).all() and np.isfinite(iris[[0, 2]]).all()
    assert np.array_equal(iris[0], iris[2])
