"""Mode pursuit at 0.1 cm tracking noise against rigid Procrustes on the rigid group (issue 30).

At 0.1 cm noise the bounded penalty's final width is 0.5 cm (5 noise std), so expression
motion of a few millimetres counts as rest frame by frame and pulls the frames; Procrustes on
the skull-fixed vertices has no such bias. Mode pursuit's last step re-aligns every frame on
the vertices that stay still over the whole shot (`robust.still_vertices`).

Arithmetic of the tolerance: a least-squares alignment on N vertices of per-coordinate noise
sigma has a pose error that falls as sigma / sqrt(N). The whole ICT head has 1487 vertices in
its 'rigid' group; the skull, neck, teeth and eyes give well over 4x that many still
vertices, so an unbiased alignment on them has at most half Procrustes' error. The test asks
for 0.8x (room for the rest estimate and for the still test's misses), and for the noise-free
truth to be recovered within the error of a perfect least-squares alignment at this noise.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from nodegraph import run_node
from nodes.io.face_model import load_face_model
from nodes.report.metrics import stabilization_errors
from nodes.rigid import Procrustes, ReferenceFrame
from nodes.stabilize.mode_pursuit import mode_pursuit
from nodes.stabilize.robust import still_vertices
from nodes.synth.performance import generate_performance


@pytest.fixture(scope="module")
def noisy_head():
    return generate_performance(load_face_model(region=""), num_frames=150, seed=0, noise_cm=0.1)


def _median(perf, matrices: np.ndarray) -> float:
    return stabilization_errors(matrices, perf.rigid.matrices, perf.stabilized.vertices).summary()["median_cm"]


def _procrustes_rigid(perf) -> np.ndarray:
    reference = run_node(ReferenceFrame, {"frame": 0}, mesh=perf.capture)["reference"]
    return run_node(Procrustes, {"group": "rigid"}, mesh=perf.capture, reference=reference)["rigid"].matrices


def test_mode_pursuit_beats_procrustes_on_the_rigid_group_at_0_1_cm_noise(noisy_head):
    perf = noisy_head
    result = mode_pursuit(perf.capture.vertices)
    ours, theirs = _median(perf, result.matrices), _median(perf, _procrustes_rigid(perf))
    without = _median(perf, mode_pursuit(perf.capture.vertices, still_refinement=False).matrices)
    print(f"median cm: mode pursuit {ours:.5f}, without the still refinement {without:.5f}, "
          f"Procrustes on 'rigid' {theirs:.5f}")
    assert 0.08 < result.plan.noise_cm < 0.12  # estimated from 2nd differences of 12 M coordinates
    assert ours <= 0.8 * theirs, (ours, theirs)
    assert ours < without


@pytest.mark.parametrize("noise_cm", [0.01, 0.03])
def test_mode_pursuit_beats_procrustes_on_the_rigid_group_at_lower_noise(noise_cm: float):
    """The same bound (module docstring: the still vertices outnumber 'rigid' 4x, so half the
    error, 0.8x asked) at the capture noise of the other situations (0.01 cm) and between.
    Measured (seed 0, 150 frames): 0.00014 / 0.00057 cm at 0.01, 0.00040 / 0.00161 at 0.03,
    0.00130 / 0.00532 at 0.1 (ratio 0.24-0.25 at each level)."""
    perf = generate_performance(load_face_model(region=""), num_frames=150, seed=0, noise_cm=noise_cm)
    result = mode_pursuit(perf.capture.vertices)
    ours, theirs = _median(perf, result.matrices), _median(perf, _procrustes_rigid(perf))
    print(f"{noise_cm} cm noise, median cm: mode pursuit {ours:.5f}, Procrustes on 'rigid' {theirs:.5f}")
    assert 0.8 * noise_cm < result.plan.noise_cm < 1.2 * noise_cm
    assert ours <= 0.8 * theirs, (ours, theirs)


def test_still_vertices_keep_noise_and_drop_smooth_motion():
    gen = torch.Generator().manual_seed(0)
    frames, sigma = 300, 0.1
    residual = torch.randn(frames, 3, 400, generator=gen, dtype=torch.float64) * sigma
    t = torch.arange(frames, dtype=torch.float64)
    # vertices 200..399 move smoothly by 0.2 cm (2 noise std, inside a 0.5 cm penalty width)
    residual[:, 0, 200:] += 0.2 * torch.sin(2 * torch.pi * t / 90.0)[:, None]
    still = still_vertices(residual, sigma)
    # noise alone: the statistic has mean 3 sigma^2 / k and a relative std of about
    # sqrt(2 / (3 F / k)) = 0.18, so the 2x threshold is 5.5 std away: all 200 stay
    assert bool(still[:200].all())
    # the moving ones add 0.2^2 / 2 (a sine's mean square, barely reduced by a 15-frame
    # average of a 90-frame period) = 0.02 >> 3 sigma^2 / 15 = 0.002: all are dropped
    assert not bool(still[200:].any())
    with pytest.raises(ValueError, match="sigma"):
        still_vertices(residual, 0.0)


def test_an_expression_held_in_a_quarter_of_the_shot_does_not_bias_its_frames():
    """The whole head at 0.1 cm noise, 200 frames in which mouthPress_R is held at up to 1.0
    for about 50 (frames 100..299 of seed 0's 300-frame performance). The whole-shot stillness
    test keeps vertices that this expression moves by 0.5-1 mm in those frames only (it
    moves 3,000 of them, 'rigid' vertices included, by more than 0.5 mm); before the per-frame
    stillness test (`robust.locally_still`) they biased those frames, and mode pursuit lost to
    Procrustes on 'rigid' at p95 (0.0135 against 0.0132 cm; with it: 0.0081).

    Tolerance: as in the module docstring, the still vertices outnumber 'rigid' 4x or more,
    so an unbiased alignment has half Procrustes' noise error; 0.8x is asked of the median and
    of the p95 (Procrustes' p95 here also carries the expression's pull on 'rigid')."""
    frames = range(100, 300)
    perf = generate_performance(load_face_model(region=""), num_frames=300, seed=0, noise_cm=0.1, frames=frames)
    result = mode_pursuit(perf.capture.vertices)
    truth = perf.rigid.matrices
    ours = stabilization_errors(result.matrices, truth, perf.stabilized.vertices).summary()
    theirs = stabilization_errors(_procrustes_rigid(perf), truth, perf.stabilized.vertices).summary()
    print(f"median / p95 cm: mode pursuit {ours['median_cm']:.5f} / {ours['p95_cm']:.5f}, Procrustes on "
          f"'rigid' {theirs['median_cm']:.5f} / {theirs['p95_cm']:.5f}")
    assert ours["median_cm"] <= 0.8 * theirs["median_cm"], (ours, theirs)
    assert ours["p95_cm"] <= 0.8 * theirs["p95_cm"], (ours, theirs)
