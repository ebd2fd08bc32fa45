"""Tests of nodes.stabilize.mode_pursuit (energy, optimizer) and the stabilize.ModePursuit node."""

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from nodegraph import MeshSequence, NodeError, RigidSequence, run_node
from nodes.stabilize import ModePursuit
from nodes.stabilize.energy import fused_stabilization_energy, stabilization_energy
from nodes.geometry.rigid import stabilize_vertices
from nodes.stabilize.mode_pursuit import mode_pursuit
from nodes.stabilize.schedule import make_schedule


# -- synthetic data --------------------------------------------------------------------------
def _smooth_curves(rng: np.random.Generator, frames: int, columns: int, peak: float) -> np.ndarray:
    """Sums of 4 random sinusoids of 0.05-0.5 Hz at 30 fps, each column peaking at `peak`."""
    t = np.arange(frames) / 30.0
    freq = rng.uniform(0.05, 0.5, (4, columns))
    phase = rng.uniform(0, 2 * np.pi, (4, columns))
    curves = (rng.uniform(0.5, 1.0, (4, columns)) * np.sin(2 * np.pi * freq * t[:, None, None] + phase)).sum(1)
    return curves * (peak / np.abs(curves).max(0))


def _synthetic_capture(frames: int = 620, vertices: int = 300, seed: int = 0, rotation_deg: float = 15.0,
                       translation_cm: float = 3.0, noise_cm: float = 0.01):
    """A head-sized point set with sparse local "expressions" and smooth rigid motion.

    Returns (world (F, V, 3) float32 with noise, truth skull-to-world (F, 4, 4), truth
    skull-frame vertices (F, V, 3) float64 without noise).
    """
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=(vertices, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    neutral = direction * np.array([7.0, 9.0, 8.0])                      # cm, an ellipsoid
    # 8 expressions: smooth bumps of up to 1 cm around random centres (local, sparse)
    centres = neutral[rng.choice(vertices, 8, replace=False)]
    dist = np.linalg.norm(neutral[None] - centres[:, None], axis=2)       # (8, V)
    deltas = np.exp(-(dist / 3.0) ** 2)[..., None] * rng.normal(size=(8, 1, 3)) * 0.6
    # activations at rest most frames: a few 15-45 frame bumps per expression
    weights = np.zeros((frames, 8))
    t = np.arange(frames)
    for k in range(8):
        for _ in range(rng.integers(1, 4)):
            start, length = rng.integers(0, frames - 20), rng.integers(15, 45)
            bump = np.sin(np.clip((t - start) / length, 0, 1) * np.pi) ** 2
            weights[:, k] = np.maximum(weights[:, k], rng.uniform(0.5, 1.0) * bump)
    skull = neutral[None] + np.einsum("fk,kvc->fvc", weights, deltas)
    angles = _smooth_curves(rng, frames, 3, np.deg2rad(rotation_deg))
    trans = _smooth_curves(rng, frames, 3, translation_cm)
    matrices = np.tile(np.eye(4), (frames, 1, 1))
    matrices[:, :3, :3] = Rotation.from_euler("xyz", angles).as_matrix()
    pivot = np.array([0.0, -9.0, -3.0])                                   # rotate about the neck
    matrices[:, :3, 3] = pivot - matrices[:, :3, :3] @ pivot + trans
    world = skull @ np.swapaxes(matrices[:, :3, :3], 1, 2) + matrices[:, None, :3, 3]
    world += rng.normal(scale=noise_cm, size=world.shape)
    return world.astype(np.float32), matrices, skull


def _kabsch_init(world: np.ndarray) -> np.ndarray:
    """Per-frame least-squares rigid fit of frame 0 onto each frame (skull frame = frame 0)."""
    ref = world[0].astype(np.float64)
    x = world.astype(np.float64)
    cr, cx = ref.mean(0), x.mean(1)
    u, _, vt = np.linalg.svd(np.einsum("vi,fvj->fij", ref - cr, x - cx[:, None]))
    d = np.sign(np.linalg.det(np.swapaxes(vt, 1, 2) @ np.swapaxes(u, 1, 2)))
    rot = np.swapaxes(vt, 1, 2) @ (np.eye(3) * np.stack([np.ones_like(d), np.ones_like(d), d], 1)[:, None]) \
        @ np.swapaxes(u, 1, 2)
    m = np.tile(np.eye(4), (len(world), 1, 1))
    m[:, :3, :3] = rot
    m[:, :3, 3] = cx - rot @ cr
    return m


def _motion_errors(estimate: np.ndarray, truth: np.ndarray, skull: np.ndarray) -> np.ndarray:
    """Per-vertex error (cm) of the estimated motion, after removing one global rigid offset.

    The truth skull-frame vertices are moved to world by the truth and back by the estimate
    (noise excluded: this measures the motion only), then aligned to the truth by one Kabsch
    fit over all frames and vertices.
    """
    relative = np.linalg.inv(estimate) @ truth
    est = skull @ np.swapaxes(relative[:, :3, :3], 1, 2) + relative[:, None, :3, 3]
    a, b = est.reshape(-1, 3), skull.reshape(-1, 3)
    ca, cb = a.mean(0), b.mean(0)
    u, _, vt = np.linalg.svd((a - ca).T @ (b - cb))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(vt.T @ u.T))])
    rot = vt.T @ d @ u.T
    return np.linalg.norm((a - ca) @ rot.T + cb - b, axis=1)


# -- energy ----------------------------------------------------------------------------------------
def _energy_inputs(frames=23, vertices=40, seed=0):
    gen = torch.Generator().manual_seed(seed)
    x = torch.randn(frames, vertices, 3, generator=gen, dtype=torch.float64) * 3.0
    rot = torch.tensor(Rotation.from_rotvec(
        np.random.default_rng(seed).normal(scale=0.05, size=(frames, 3))).as_matrix())
    trans = torch.randn(frames, 3, generator=gen, dtype=torch.float64) * 0.1
    stab = x @ rot.transpose(1, 2) + trans[:, None]
    rest = stab.median(0).values + 0.2 * torch.randn(vertices, 3, generator=gen, dtype=torch.float64)
    return x, rot, trans, rest


def test_stabilization_energy_matches_float64_loop():
    x, rot, trans, rest = _energy_inputs(frames=9, vertices=5)
    wp, wv, lam = 0.4, 0.3, 0.7

    def psi(d, w):
        u = min(abs(d) / w, 1.0)
        return 2 * u * u if u < 0.5 else 1 - 2 * (1 - u) ** 2

    coef = [3 / 4, -3 / 20, 1 / 60]
    total = 0.0
    s = [[(rot[f] @ x[f, v] + trans[f]).tolist() for v in range(5)] for f in range(9)]
    for f in range(9):
        for v in range(5):
            for c in range(3):
                total += psi(s[f][v][c] - float(rest[v, c]), wp)
                p = [s[g][v][c] for g in range(9)]
                if 3 <= f < 6:
                    vel = sum(a * (p[f + k] - p[f - k]) for k, a in enumerate(coef, 1))
                else:  # the lower-order end stencils ("reduced" ends)
                    vel = {0: p[1] - p[0], 1: (p[2] - p[0]) / 2,
                           2: (p[0] - 8 * p[1] + 8 * p[3] - p[4]) / 12,
                           6: (p[4] - 8 * p[5] + 8 * p[7] - p[8]) / 12,
                           7: (p[8] - p[6]) / 2, 8: p[8] - p[7]}[f]
                total += lam * psi(vel, wv)
    got = stabilization_energy(x, rot, trans, rest, width_pos=wp, width_vel=wv, velocity_weight=lam)
    assert float(got) == pytest.approx(total / (9 * 5 * 3), rel=1e-12)


def test_stabilization_energy_gradcheck():
    x, rot, trans, rest = _energy_inputs(frames=10, vertices=6)
    rot.requires_grad_(True)
    trans.requires_grad_(True)
    # keep residuals away from the penalty's kinks (|x| = w/2, w), where it is only C1
    assert torch.autograd.gradcheck(
        lambda r, t: stabilization_energy(x, r, t, rest, width_pos=2.0, width_vel=1.5, velocity_weight=0.5),
        (rot, trans), atol=1e-5)


@pytest.mark.parametrize("block_frames", [0, 1, 3, 5, 8, 100])
def test_fused_energy_matches_reference_value_and_gradient(block_frames):
    x, rot, trans, rest = _energy_inputs()
    kw = dict(width_pos=0.5, width_vel=0.3, velocity_weight=0.8)
    rot.requires_grad_(True)
    trans.requires_grad_(True)
    want = stabilization_energy(x, rot, trans, rest, **kw)
    g_want = torch.autograd.grad(want, (rot, trans))
    got = fused_stabilization_energy(x, rot, trans, rest, block_frames=block_frames, **kw)
    g_got = torch.autograd.grad(got, (rot, trans))
    assert float(got.detach()) == pytest.approx(float(want.detach()), rel=1e-5)
    for a, b in zip(g_got, g_want):
        np.testing.assert_allclose(a.numpy(), b.numpy(), atol=2e-5 * float(b.abs().max()))


# -- helpers ---------------------------------------------------------------------------------------
def test_make_schedule_walks_widths_and_spreads_refinements():
    stages = make_schedule(refinements=2)
    assert [s.width_pos for s in stages] == [0.8, 0.4, 0.2, 0.1, 0.05]
    assert [s.width_vel for s in stages] == [0.2, 0.1, 0.05, 0.025, 0.0125]
    assert [s.refine for s in stages] == [False, False, True, False, True]
    assert sum(s.refine for s in make_schedule(refinements=0)) == 0
    many = make_schedule([1.0, 0.5], [0.1, 0.05], refinements=3)
    assert [(s.width_pos, s.refine) for s in many] == [(1.0, False), (0.5, True), (0.5, True), (0.5, True)]
    with pytest.raises(ValueError, match="velocity_widths: expected as many widths as position_widths"):
        make_schedule([1.0, 0.5], [0.1])


# -- optimizer -------------------------------------------------------------------------------------
def test_mode_pursuit_recovers_head_motion_from_kabsch_init():
    world, truth, skull = _synthetic_capture(frames=620, vertices=300, seed=0)
    init = _kabsch_init(world)
    messages = []
    result = mode_pursuit(world, init=init, schedule="fixed", device="cpu",
                          progress=lambda f, m: messages.append((f, m)))
    err = _motion_errors(result.matrices, truth, skull)
    err_init = _motion_errors(init, truth, skull)
    assert np.median(err) < 0.02, np.median(err)
    assert np.mean(err) < 0.5 * np.mean(err_init), (np.mean(err), np.mean(err_init))
    assert result.matrices.shape == (620, 4, 4) and result.matrices.dtype == np.float64
    assert result.evaluations >= result.iterations > 0
    assert len(result.stages) == 5 and sum(s.evaluations for s in result.stages) == result.evaluations
    assert [round(f, 6) for f, _ in messages] == [0.2, 0.4, 0.6, 0.8, 1.0]


def test_mode_pursuit_identity_init_head_rest():
    world, truth, skull = _synthetic_capture(frames=600, vertices=200, seed=1, rotation_deg=3.0,
                                             translation_cm=0.5)
    result = mode_pursuit(world, device="cpu", max_vertices=150)
    assert len(result.vertex_ids) == 150
    err = _motion_errors(result.matrices, truth, skull)
    err_identity = _motion_errors(np.tile(np.eye(4), (600, 1, 1)), truth, skull)
    assert np.median(err) < 0.02 and np.median(err) < 0.1 * np.median(err_identity)


def test_mode_pursuit_with_true_rest_and_vertex_subset_keeps_skull_frame():
    # With the true rest shape given, the skull frame is fixed: no global offset to remove.
    world, truth, skull = _synthetic_capture(frames=300, vertices=200, seed=2, rotation_deg=5.0,
                                             translation_cm=1.0)
    rest = np.median(skull, axis=0)
    subset = np.arange(0, 200, 2)
    kabsch = _kabsch_init(world)
    init = kabsch @ np.linalg.inv(kabsch[0]) @ truth[0]      # the baseline, in the true skull frame
    result = mode_pursuit(world, init=init, rest=rest, vertex_ids=subset, device="cpu")
    assert set(result.vertex_ids.tolist()) <= set(subset.tolist())
    stab = stabilize_vertices(world, result.matrices)
    direct = np.linalg.norm(stab - skull, axis=2)
    assert np.median(direct) < 0.03


def test_mode_pursuit_rejects_bad_input():
    world = np.zeros((6, 10, 3), np.float32)
    with pytest.raises(ValueError, match=r"vertices: expected at least 7 frames .* found 6"):
        mode_pursuit(world, schedule="fixed")
    with pytest.raises(ValueError, match=r"vertices: expected at least 1 frames, found 0"):
        mode_pursuit(world[:0])
    with pytest.raises(ValueError, match=r"schedule: expected 'adaptive' or 'fixed', found 'paper'"):
        mode_pursuit(world, schedule="paper")
    world = np.random.default_rng(0).normal(size=(20, 10, 3)).astype(np.float32)
    with pytest.raises(ValueError, match=r"init: expected shape \(20, 4, 4\), found \(19, 4, 4\)"):
        mode_pursuit(world, init=np.tile(np.eye(4), (19, 1, 1)))
    with pytest.raises(ValueError, match=r"vertex_ids: expected indices in 0..9, found 0..12"):
        mode_pursuit(world, vertex_ids=[0, 5, 12])
    with pytest.raises(ValueError, match=r"refinements: the final spacing 4.0 / 2\^3 would be below 1 frame"):
        mode_pursuit(world, spacing=4.0, refinements=3)
    with pytest.raises(ValueError, match=r"rest: expected shape \(10, 3\), found \(9, 3\)"):
        mode_pursuit(world, rest=np.zeros((9, 3)))


# -- node ------------------------------------------------------------------------------------------
def test_node_outputs_and_accuracy_on_synthetic_performance():
    from nodes.io.face_model import load_face_model
    from nodes.synth.performance import generate_performance

    model = load_face_model(region="face", max_vertices=400)
    perf = generate_performance(model, num_frames=620, seed=3, rotation_deg=10.0, translation_cm=2.0,
                                noise_cm=0.01)
    base = _kabsch_init(perf.capture.vertices)
    out = run_node(ModePursuit, {"max_vertices": 300}, mesh=perf.capture, init=RigidSequence(base))
    assert set(out) == {"rigid", "stabilized"}
    assert out["rigid"].matrices.shape == (620, 4, 4) and out["rigid"].matrices.dtype == np.float64
    stab = out["stabilized"]
    assert stab.vertices.shape == perf.capture.vertices.shape and stab.vertices.dtype == np.float32
    assert np.array_equal(stab.faces, perf.capture.faces) and set(stab.groups) == set(perf.capture.groups)
    np.testing.assert_allclose(stab.vertices, stabilize_vertices(perf.capture.vertices, out["rigid"].matrices))
    skull = perf.stabilized.vertices.astype(np.float64)
    err = _motion_errors(out["rigid"].matrices, perf.rigid.matrices, skull)
    err_base = _motion_errors(base, perf.rigid.matrices, skull)
    assert np.median(err) < 0.02 and np.mean(err) < np.mean(err_base), (np.median(err), np.mean(err_base))


def _small_mesh(frames=12, groups=None):
    rng = np.random.default_rng(0)
    return MeshSequence(vertices=rng.normal(size=(frames, 30, 3)).astype(np.float32),
                        groups=groups or {"face": np.arange(10)})


def test_node_group_and_device_params():
    mesh = _small_mesh()
    out = run_node(ModePursuit, {"group": "face", "iterations": 2, "spacing": 4.0, "device": "cpu"}, mesh=mesh)
    assert out["stabilized"].vertices.shape == (12, 30, 3)
    node_a = ModePursuit({"device": "cpu", "compile": False})
    node_b = ModePursuit({"device": "auto", "compile": True})
    assert node_a.key_params() == node_b.key_params()
    assert ModePursuit({"iterations": 3}).key_params() != ModePursuit({"iterations": 4}).key_params()


def test_node_errors_name_port_or_param():
    mesh = _small_mesh()
    with pytest.raises(NodeError, match=r"'group': expected a vertex group 'lips' of the mesh, found groups \['face'\]"):
        run_node(ModePursuit, {"group": "lips"}, mesh=mesh)
    with pytest.raises(NodeError, match=r"'mesh': expected at least 7 frames .* found 5"):
        run_node(ModePursuit, {"schedule": "fixed"}, mesh=_small_mesh(frames=5))
    with pytest.raises(NodeError, match=r"'group': group 'tiny': expected at least 10 distinct vertices .*found 2"):
        run_node(ModePursuit, {"group": "tiny"}, mesh=_small_mesh(groups={"tiny": np.array([1, 2])}))
    rest = MeshSequence(vertices=np.zeros((2, 30, 3), np.float32))
    with pytest.raises(NodeError, match=r"'rest': expected a one-frame mesh, found 2 frames"):
        run_node(ModePursuit, {}, mesh=mesh, rest=rest)
    rest = MeshSequence(vertices=np.zeros((1, 29, 3), np.float32))
    with pytest.raises(NodeError, match=r"'rest': expected 30 vertices \(as 'mesh'\), found 29"):
        run_node(ModePursuit, {}, mesh=mesh, rest=rest)
    with pytest.raises(NodeError, match=r"velocity_widths: expected 5 widths"):
        ModePursuit({"velocity_widths": [0.1, 0.05]})
    with pytest.raises(NodeError, match=r"refinements: spacing 2.0 / 2\^2 is below 1 frame"):
        ModePursuit({"spacing": 2.0})
    with pytest.raises(NodeError, match=r"device"):
        ModePursuit({"device": "tpu"})
    if not torch.cuda.is_available():
        with pytest.raises(NodeError, match=r"'device': expected an available device, found 'cuda'"):
            run_node(ModePursuit, {"device": "cuda"}, mesh=mesh)
