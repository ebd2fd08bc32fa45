"""A frame's fit does not depend on the frames solved beside it (`batch`, chunks): the
Levenberg-Marquardt decisions are each element's own, the normal equations, the vertices, the
renders' crops and the networks are computed one frame at a time. Before, fit.Expression's
output moved by up to 0.06 between `batch` 8 and 3 on the same 8 synthetic frames."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, run_node  # noqa: E402
from nodes.fit import Expression, RigidPose  # noqa: E402
from nodes.fit.solve import PoseState, Stage, solve_stage  # noqa: E402
from nodes.geometry.lm import LMSchedule, from_jacobian, levenberg_marquardt  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from tests.support.synthetic import random_face_parameters, read_plates, render_truth_plates  # noqa: E402

from .test_compact_solve import _batch, _rosenbrock, _rosenbrock_jac  # noqa: E402

f64 = torch.float64


@pytest.mark.parametrize("compact", [False, True])
def test_each_element_solved_in_a_batch_gets_its_result_alone(compact: bool):
    # a schedule whose first steps are rejected for a far start (lambda starts tiny, grows slowly)
    # while the near ones are accepted: before, the tries ended for every element once one was
    # accepted, and the start (-1.2, 1) ended elsewhere in this batch than alone
    starts = torch.tensor([[0.999, 1.001], [-1.2, 1.0], [2.0, -1.0], [1.05, 1.1], [-3.0, -3.0]], dtype=f64)
    schedule = LMSchedule(lam0=1e-6, up=3.0, rel_tol=1e-6)

    def solve(x0: torch.Tensor):
        if not compact:
            return levenberg_marquardt(_rosenbrock, from_jacobian(_rosenbrock_jac), x0, iterations=60,
                                       schedule=schedule)
        normal = from_jacobian(_rosenbrock_jac)
        return levenberg_marquardt(lambda x, rows: _rosenbrock(x), lambda x, r, rows: normal(x, r), x0,
                                   iterations=60, schedule=schedule, compact=True)

    together = solve(starts)
    for i in range(len(starts)):
        alone = solve(starts[i:i + 1])
        assert torch.equal(alone.x[0], together.x[i]) and torch.equal(alone.cost[0], together.cost[i])
        assert torch.equal(alone.lam[0], together.lam[i])
    assert float(together.cost.min()) < 1e-8  # the near starts reached the minimum (1, 1)


def test_a_stage_solve_gives_a_frame_the_same_bits_in_any_batch():
    views, anchors, anchored, samples, state = _batch()
    model = type("Model", (), {"iris": None})()
    stage = Stage("jaw_mouth", True, True, (0, 2, 3), "all")

    def rows(t, sel):
        return type(t)(*(a[sel] for a in t))

    kw = dict(prior=1.0, edge_weight=1.0, eyelid_weight=0.2, iterations=30, photo_weight=5.0)
    every, e_every = solve_stage(stage, model, views, anchors, state, photo=samples, anchored=anchored, **kw)
    from nodes.fit.solve import frames_of
    for sel in (torch.tensor([1]), torch.tensor([0, 2])):
        part = samples._replace(**{f: getattr(samples, f)[sel] for f in ("vertices", "bary", "colour", "weight",
                                                                       "neutral", "deltas")},
                                plates=samples.plates[sel])
        got, e = solve_stage(stage, model, frames_of(views, sel), rows(anchors, sel), rows(state, sel), photo=part,
                             anchored=(anchored[0][sel], anchored[1][sel]), **kw)
        for a, b in zip(got, every):
            assert torch.equal(a, b[sel])
        assert torch.equal(e, e_every[sel])


def test_rigid_and_expression_fits_do_not_depend_on_the_batch():
    """Four synthetic plates (the bundled model at 65 cm, 0.005 noise), fit.RigidPose and
    fit.Expression with the photometric term, solved four together, three + one and one by one: the same
    bits (the renders, the network reads, the solves of a frame never see the other frames)."""
    model = load_face_model()
    cam = Camera.from_fov(192, 192, 30.0)
    truth = random_face_parameters(model, 4, seed=2, distance_cm=65.0)
    seq, boxes, marks = read_plates(render_truth_plates(model, [cam], truth, noise=0.005)[0])
    common = dict(landmarks=[marks], boxes=[boxes], cameras=[cam], images=[seq], model=model)
    out = {}
    for batch in (4, 3, 1):
        rigid = run_node(RigidPose, {"batch": batch, "rounds": 2}, frames=range(4), **common)
        expr = run_node(Expression, {"batch": batch, "rounds": 2}, frames=range(4), pose=rigid["pose"], **common)
        out[batch] = rigid["pose"].values, expr["fitted"].values
    assert np.isfinite(out[4][1]).all()
    for batch in (3, 1):
        for a, b in zip(out[4], out[batch]):
            assert np.array_equal(a, b), batch


def test_the_blur_and_the_crop_sampling_of_an_image_do_not_depend_on_its_batch_or_size():
    import torch.nn.functional as F

    from nodes.geometry.image import gaussian_kernel, sample_bilinear, sample_separable, separable_filter

    g = torch.Generator().manual_seed(0)
    images = torch.rand(5, 40, 52, 3, generator=g)
    kernel = gaussian_kernel(1.3)
    blurred = separable_filter(images, kernel)
    # reference: the same separable filter by convolution (edges replicated)
    r = len(kernel) // 2
    t = F.pad(images.permute(0, 3, 1, 2).reshape(15, 1, 40, 52), (r, r, r, r), mode="replicate")
    ref = F.conv2d(F.conv2d(t, kernel.reshape(1, 1, 1, -1)), kernel.reshape(1, 1, -1, 1)).reshape(5, 3, 40, 52)
    assert float((blurred - ref.permute(0, 2, 3, 1)).abs().max()) < 1e-6  # float32 rounding of 2 x 9 taps
    for sel in ([2], [0, 3]):
        assert torch.equal(separable_filter(images[sel], kernel), blurred[sel])
    images64 = images.double()
    xs = torch.rand(5, 30, generator=g, dtype=f64) * 56 - 2  # some samples past the edges: zeros there
    ys = torch.rand(5, 25, generator=g, dtype=f64) * 44 - 2
    crop = sample_separable(images64, xs, ys)
    grid = torch.stack(torch.broadcast_tensors(xs[:, None, :], ys[:, :, None]), -1)
    assert float((crop - sample_bilinear(images64, grid, padding="zeros")).abs().max()) < 1e-12
    wider = torch.cat([images64, torch.rand(5, 40, 9, 3, generator=g, dtype=f64)], 2)
    xs_in = torch.rand(5, 30, generator=g, dtype=f64) * 50  # within the narrower image's columns
    assert torch.equal(sample_separable(wider, xs_in, ys), sample_separable(images64, xs_in, ys))


def test_the_face_mesh_reads_a_crop_the_same_in_any_batch():
    from nodes.landmarks.network import load_face_mesh

    net = load_face_mesh("cpu")
    crops = torch.rand(3, 192, 192, 3, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        points, presence = net(crops)
        for i in range(3):
            alone = net(crops[i:i + 1])
            assert torch.equal(alone[0][0], points[i]) and torch.equal(alone[1][0], presence[i])
