"""nodes.flow.fast: the compiled forward pass gives the torch flow (same model and counts) on face
renders and a translated texture, with and without skipped levels and per-warp medians; the node
uses it on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from nodegraph import ImageSequence, run_node  # noqa: E402
from nodes.flow import OpticalFlow  # noqa: E402
from nodes.flow.dense import FlowSettings, dense_flow  # noqa: E402
from nodes.flow.fast import dense_flow_numpy  # noqa: E402
from tests.support.synthetic import head_motion, make_scene, render_scene_plates  # noqa: E402


@pytest.fixture(scope="module")
def pair():
    scene = make_scene(80)
    values = head_motion(2, scene.model.expression_names, seed=3, amplitude=2.0, mouth_frames=(0, 2))
    return torch.as_tensor(render_scene_plates(scene, values).pixels).permute(0, 3, 1, 2)


@pytest.mark.parametrize("settings", [FlowSettings(), FlowSettings(skip_levels=1),
                                      FlowSettings(warps=3, median_every_warp=True, levels=3)])
def test_compiled_flow_equals_the_torch_flow(pair, settings):
    with torch.no_grad():
        ref = dense_flow(pair[:1], pair[1:], settings)[0].numpy()
    fast = dense_flow_numpy(pair[:1], pair[1:], settings)
    assert fast.shape == ref.shape == (2, 80, 80)
    assert np.abs(ref).max() > 0.5  # a real motion
    diff = np.abs(fast - ref)  # float32 sums in another order (fastmath), over 8 warps x 5 levels
    assert diff.mean() < 2e-4 and diff.max() < 2e-2, (diff.mean(), diff.max())


def test_compiled_flow_equals_the_torch_flow_with_few_finest_warps(pair):
    big = torch.nn.functional.interpolate(pair, size=(150, 170), mode="bilinear", align_corners=False)
    settings = FlowSettings(finest_warps=1)  # 150 x 170 is over FEW_WARPS_PIXELS: one warp there
    with torch.no_grad():
        ref = dense_flow(big[:1], big[1:], settings)[0].numpy()
        more = dense_flow(big[:1], big[1:], FlowSettings(finest_warps=3))[0].numpy()
    diff = np.abs(dense_flow_numpy(big[:1], big[1:], settings) - ref)
    assert diff.mean() < 2e-4 and diff.max() < 2e-2, (diff.mean(), diff.max())
    assert np.abs(more - ref).max() > 1e-2  # the finest level's warps count


def test_compiled_flow_on_odd_sizes_and_grey_images():
    rng = np.random.default_rng(0)
    base = rng.uniform(size=(1, 1, 45, 61)).astype(np.float32)
    shifted = np.roll(base, 1, axis=3)
    a, b = torch.as_tensor(base), torch.as_tensor(shifted)
    with torch.no_grad():
        ref = dense_flow(a, b)[0].numpy()
    diff = np.abs(dense_flow_numpy(a, b) - ref)
    assert diff.mean() < 2e-4 and diff.max() < 2e-2, (diff.mean(), diff.max())
    with pytest.raises(ValueError, match="one shape"):
        dense_flow_numpy(a, b[..., :60])


def test_node_on_the_cpu_uses_the_compiled_flow(pair):
    images = ImageSequence(pair.permute(0, 2, 3, 1).numpy(), colour_space="linear")
    out = run_node(OpticalFlow, {"skip_levels": 1}, images=images)["flow"]
    want = dense_flow_numpy(pair[:1], pair[1:], FlowSettings(skip_levels=1)).transpose(1, 2, 0)
    np.testing.assert_allclose(out.flow[0], want, atol=1e-6)
    assert out.valid.tolist() == [True, False]


def test_compiled_flow_is_the_same_on_any_thread_count(pair):
    numba = pytest.importorskip("numba")
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread")
    threads = numba.get_num_threads()
    big = torch.nn.functional.interpolate(pair, size=(160, 160), mode="bilinear", align_corners=False)
    try:  # row strips with recomputed halos: the strips' sweeps are the global ones, bit for bit
        numba.set_num_threads(1)
        one = dense_flow_numpy(big[:1], big[1:])
        numba.set_num_threads(2)
        two = dense_flow_numpy(big[:1], big[1:])
    finally:
        numba.set_num_threads(threads)
    assert np.abs(one).max() > 0.5
    np.testing.assert_array_equal(one, two)


def test_chebyshev_sweeps_converge_faster_than_plain_jacobi():
    """One warp's linearized equations (a smooth texture of the contrast `dense_flow` normalizes to,
    ~0.25, moved by a known half-pixel shift) solved by the compiled sweeps from zero: 20
    accelerated sweeps (acceleration 0.99, the default) land closer to the system's solution
    (20,000 plain sweeps) than 40 plain ones, and 40 accelerated ones 10x closer (measured: 0.012
    and 0.0004 px against 0.020)."""
    from nodes.flow.dense import chebyshev_weights
    from nodes.flow.fast import _gradients, _jacobi, _linearize

    rng = np.random.default_rng(1)
    h = w = 48
    noise = torch.as_tensor(rng.normal(size=(1, 1, h // 4, w // 4)).astype(np.float32))
    tex = 0.2 * torch.nn.functional.interpolate(noise, size=(h, w), mode="bicubic", align_corners=True)[0, 0].numpy()
    a1 = np.ascontiguousarray(tex)
    a2 = np.ascontiguousarray(np.roll(tex, 1, axis=1) * 0.5 + tex * 0.5)  # about 0.5 px to the right
    gx, gy = np.empty_like(a1), np.empty_like(a1)
    _gradients(a1, gx, gy)
    zero = np.zeros((h, w), np.float32)
    work = np.empty((9, h, w), np.float32)
    _linearize(a1, a2, gx, gy, zero, zero, 0.06, 0.01, work)
    coeffs = (work[4], work[5], work[6], work[7], work[8])
    scratch = np.empty((6, h, w), np.float32)

    def solve(iterations: int, acceleration: float) -> np.ndarray:
        u, v = zero.copy(), zero.copy()
        _jacobi(u, v, *coeffs, iterations, acceleration, scratch)
        return np.stack([u, v])

    exact = solve(20000, 0.0)
    assert 0.2 < exact[0].mean() < 0.8  # the shift is found
    plain = np.abs(solve(40, 0.0) - exact).mean()
    fast = np.abs(solve(20, 0.99) - exact).mean()
    assert fast < 0.75 * plain, (fast, plain)
    assert np.abs(solve(40, 0.99) - exact).mean() < 0.1 * plain
    assert chebyshev_weights(3, 0.0, 0.0) == ([1.0, 1.0, 1.0], 1.0)
    omegas, gamma = chebyshev_weights(20, 0.99)
    assert omegas[0] == 1.0 and 1.0 < omegas[-1] < 2.0 and 1.0 < gamma < 2.0
    with pytest.raises(ValueError, match="acceleration"):
        chebyshev_weights(3, 1.0)
