"""Synthetic captures with secondary dynamics (skin jiggle) and their true quasistatic motion.

The skin of a face model rides on the skull. In the skull frame each vertex i is displaced by
`u_i(t)` from its quasistatic position `S_i(t)` (neutral + identity + expression, as in
`performance.py`) by a damped second-order system driven by the inertial (fictitious)
acceleration of the skull-attached point at its rest position `r_i`:

    u_i'' + 2 zeta_i w_i u_i' + w_i^2 kappa_i(t) u_i = -a_i(t),
    a_i(t) = R(t)^T d^2/dt^2 [R(t) r_i + o(t)] = (R^T R'') r_i + R^T o''

(linear, angular and centripetal acceleration of the skull at the vertex, in the skull frame;
Coriolis on `u` neglected). `w_i = 2 pi f_i` varies smoothly over the face: loose where
`looseness_i` is high (cheeks, lips, jowls: about 7.5 Hz) and stiff on the forehead and nose
(about 22 Hz), `f_i = f_stiff^(1 - L_i) f_loose^L_i`; damping ratio `zeta_i = 0.45 - 0.15 L_i`.
Expressions modulate stiffness: stretched skin is stiffer,
`kappa_i(t) = clip(1 + stretch_stiffening * stretch_i(t), 0.5, 3)` with `stretch_i` the
mean relative length change of the edges at vertex i against the neutral, smoothed with a
Gaussian of 0.8 cm (the skin's response is spatially smooth). The looseness field is a sum of Gaussian blobs with centres in the ICT head's
frame (cm, y up, z out of the face); other heads get a plausible but uncalibrated field.

The capture is `X_i(t) = T(t) (S_i(t) + u_i(t))` (+ optional Gaussian noise), the truth
quasistatic sequence is `Y_i(t) = T(t) S_i(t)`, both in world space; `T` is the skull-to-world
`RigidSequence`.

A performance is a list of segments: every (expression, motion program) pair, expressions
outer, each `segment_frames` long, simulated independently (vectorized over segments and
vertices; a time loop over sub-steps) after a pre-roll of `preroll_s` seconds of the same
motion that lets the start-up transient decay. Motion programs (time t in seconds, vertical
translation y in cm, pitch/roll in degrees; all scaled by `amplitude_scale`):
- still: sway of 0.1 cm and 0.3 degree below 0.4 Hz;
- walk: step rate 1.7-2.1 Hz, a 2 cm bob with soft heel-strike cusps, 1 cm lateral sway,
  1.5 degree pitch and roll;
- run: step rate 2.6-3.0 Hz, 3.5 cm bob with sharper impacts, 2.5 degree pitch;
- jump: hops every 0.6-0.75 s, ballistic flight (free fall) and a sinusoidal landing squat;
- oscillate@F: the vibrating platform, a vertical 0.25 cm sinusoid at F Hz (6-11 Hz in the
  paper) with a 0.25 degree pitch at the same frequency.
Expressions: "neutral", held ones (`HELD_EXPRESSIONS`: weights of ARKit shapes held for the
whole segment), and "speech" (jaw and lip syllables at 3-6 Hz).
"""

from __future__ import annotations

from typing import Iterator, NamedTuple, Sequence

import numpy as np
from pydantic import field_validator

from nodegraph import (SEQUENCE, FaceModel, In, InputError, MeshSequence, Node, NodeParams, Out,
                       Param, ParamSequence, RigidSequence)

from ..geometry.mesh import vertex_neighbours
from .expressions import envelope
from .head_motion import default_pivot, poses_to_matrices
from .performance import transform_points

__all__ = [
    "MOTION_PROGRAMS", "HELD_EXPRESSIONS", "parse_program", "skull_motion", "looseness_field",
    "smoothing_matrix", "edge_stretch", "expression_weights", "DynamicCapture",
    "simulate_dynamics", "DynamicPerformance",
]

MOTION_PROGRAMS = ("still", "walk", "run", "jump", "oscillate")
"""Kinds of skull motion; "oscillate" takes a frequency: "oscillate@8.5" (Hz)."""

HELD_EXPRESSIONS: dict[str, dict[str, float]] = {
    "neutral": {},
    "smile": {"mouthSmile_L": 0.8, "mouthSmile_R": 0.8, "cheekSquint_L": 0.4, "cheekSquint_R": 0.4},
    "jaw_open": {"jawOpen": 0.7, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},
    "pucker": {"mouthPucker": 0.9, "mouthFunnel": 0.3},
    "brow_raise": {"browInnerUp_L": 0.9, "browInnerUp_R": 0.9, "browOuterUp_L": 0.9,
                   "browOuterUp_R": 0.9, "eyeWide_L": 0.3, "eyeWide_R": 0.3},
    "frown": {"browDown_L": 0.8, "browDown_R": 0.8, "mouthFrown_L": 0.7, "mouthFrown_R": 0.7},
    "sneer": {"noseSneer_L": 0.8, "noseSneer_R": 0.8, "mouthUpperUp_L": 0.5, "mouthUpperUp_R": 0.5},
    "relaxed_lips": {"jawOpen": 0.15, "mouthLowerDown_L": 0.2, "mouthLowerDown_R": 0.2},
    "stretch": {"mouthStretch_L": 0.8, "mouthStretch_R": 0.8, "jawOpen": 0.2},
}
"""Held expressions by name: ARKit shape -> weight (missing shapes stay 0)."""

_F_STIFF_HZ, _F_LOOSE_HZ = 22.0, 7.5
_GRAVITY = 981.0  # cm/s^2
# (centre (cm, ICT head frame), sigma (cm), weight): positive = loose, negative = stiff
_BLOBS = (
    ((-4.8, -1.5, 8.0), 2.5, 1.0), ((4.8, -1.5, 8.0), 2.5, 1.0),   # cheeks
    ((0.0, -3.4, 11.0), 2.5, 0.8),                                  # lips
    ((-4.0, -5.5, 8.0), 2.5, 0.7), ((4.0, -5.5, 8.0), 2.5, 0.7),   # jowls
    ((0.0, -7.0, 10.0), 2.5, 0.4),                                  # chin
    ((0.0, 1.5, 12.0), 2.5, -1.0),                                  # nose
    ((0.0, 8.0, 9.0), 4.0, -1.0),                                   # forehead
)


def parse_program(program: str) -> tuple[str, float]:
    """Split "oscillate@8.5" into ("oscillate", 8.5); other kinds get frequency 0.

    Raises:
        ValueError: unknown kind, or a frequency that is missing, not a number or <= 0.
    """
    kind, _, freq = program.partition("@")
    if kind not in MOTION_PROGRAMS:
        raise ValueError(f"motion program '{program}': expected one of {list(MOTION_PROGRAMS)} "
                         "(oscillate as 'oscillate@HZ')")
    if kind == "oscillate":
        try:
            value = float(freq)
        except ValueError:
            raise ValueError(f"motion program '{program}': expected 'oscillate@HZ' with a "
                             "frequency in Hz, e.g. 'oscillate@8'") from None
        if not np.isfinite(value) or value <= 0:
            raise ValueError(f"motion program '{program}': expected a frequency > 0 Hz, found {value}")
        return kind, value
    if freq:
        raise ValueError(f"motion program '{program}': only 'oscillate' takes a frequency")
    return kind, 0.0


def _soft_abs(x: np.ndarray, eps: float) -> np.ndarray:
    return np.sqrt(x * x + eps * eps) - eps


def skull_motion(program: str, times: np.ndarray, rng: np.random.Generator, *,
                 amplitude_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Skull pose curves of a motion program at arbitrary times.

    Args:
        program: a motion program (see the module docstring), e.g. "walk", "oscillate@9".
        times: (T,) seconds (may be negative: the pre-roll).
        rng: draws the program's random parameters (step rate, phases); the same draws for
            the same generator state whatever `times` is.
        amplitude_scale: multiplies every translation and angle.
    Returns:
        angles (T, 3) radians (extrinsic XYZ, x = pitch, z = roll), translations (T, 3) cm.
    """
    kind, freq = parse_program(program)
    t = np.asarray(times, np.float64)
    ang = np.zeros((len(t), 3))
    trans = np.zeros((len(t), 3))
    phase = rng.uniform(0.0, 2 * np.pi, 4)
    deg = np.pi / 180.0
    if kind == "still":
        f = rng.uniform(0.1, 0.4, 3)
        trans[:, 0] = 0.1 * np.sin(2 * np.pi * f[0] * t + phase[0])
        trans[:, 1] = 0.1 * np.sin(2 * np.pi * f[1] * t + phase[1])
        ang[:, 0] = 0.3 * deg * np.sin(2 * np.pi * f[2] * t + phase[2])
    elif kind in ("walk", "run"):
        step = rng.uniform(1.7, 2.1) if kind == "walk" else rng.uniform(2.6, 3.0)
        bob, eps, pitch = (2.0, 0.15, 1.5) if kind == "walk" else (3.5, 0.12, 2.5)
        s = np.sin(np.pi * step * t + phase[0])  # |s| has a cusp at every foot strike
        trans[:, 1] = bob * (_soft_abs(s, eps) - 0.5)
        trans[:, 0] = 1.0 * np.sin(np.pi * step * t + phase[0] + phase[1])
        ang[:, 0] = pitch * deg * np.sin(2 * np.pi * step * t + phase[2])
        ang[:, 2] = 1.5 * deg * np.sin(np.pi * step * t + phase[0] + phase[1])
    elif kind == "jump":
        period = rng.uniform(0.6, 0.75)
        flight, contact = 0.6 * period, 0.4 * period
        v0 = _GRAVITY * flight / 2.0  # take-off speed, cm/s
        depth = v0 * contact / np.pi  # squat depth matching the landing speed
        tau = np.mod(t + phase[0] / (2 * np.pi) * period, period)
        in_flight = tau < flight
        trans[:, 1] = np.where(in_flight, v0 * tau - 0.5 * _GRAVITY * tau ** 2,
                               -depth * np.sin(np.pi * (tau - flight) / contact))
        mean = (_GRAVITY * flight ** 3 / 12.0 - 2.0 * depth * contact / np.pi) / period
        trans[:, 1] = 0.5 * (trans[:, 1] - mean)  # half a real hop: about 1.2 g at landing
        ang[:, 0] = 1.5 * deg * np.sin(2 * np.pi * (t / period) + phase[1])
    else:  # oscillate
        trans[:, 1] = 0.25 * np.sin(2 * np.pi * freq * t + phase[0])
        ang[:, 0] = 0.25 * deg * np.sin(2 * np.pi * freq * t + phase[0] + 0.5 * phase[1])
    return ang * amplitude_scale, trans * amplitude_scale


def looseness_field(rest: np.ndarray) -> np.ndarray:
    """Looseness L in [0, 1] per vertex: 1 on cheeks and lips, 0 on forehead and nose.

    `L = clip(0.2 + sum_b w_b exp(-|r - c_b|^2 / (2 sigma_b^2)), 0, 1)` over the blobs of the
    module (ICT head frame, cm).

    Args:
        rest: (V, 3) rest positions, cm, skull frame.
    Returns:
        (V,) float64.
    """
    rest = np.asarray(rest, np.float64)
    field = np.full(len(rest), 0.2)
    for centre, sigma, weight in _BLOBS:
        d2 = ((rest - np.asarray(centre)) ** 2).sum(axis=1)
        field += weight * np.exp(-d2 / (2 * sigma * sigma))
    return np.clip(field, 0.0, 1.0)


def smoothing_matrix(rest: np.ndarray, *, sigma_cm: float = 0.8):
    """Row-normalized Gaussian smoothing over positions (scipy.sparse csr, (V, V)).

    Weights `exp(-d^2 / (2 sigma^2))` for vertices within 2.5 sigma of each other and 2 for the
    vertex itself (the self pair and the added identity of the first version).
    """
    from scipy import sparse
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, np.float64)
    pairs = cKDTree(rest).query_pairs(2.5 * sigma_cm, output_type="ndarray")  # i < j; 3x faster than
    weights = np.exp(-((rest[pairs[:, 0]] - rest[pairs[:, 1]]) ** 2).sum(1) / (2 * sigma_cm ** 2))  # distances
    v = len(rest)
    diagonal = np.arange(v)
    matrix = sparse.csr_matrix((np.concatenate([weights, weights, np.full(v, 2.0)]),
                                (np.concatenate([pairs[:, 0], pairs[:, 1], diagonal]),
                                 np.concatenate([pairs[:, 1], pairs[:, 0], diagonal]))), shape=(v, v))
    return sparse.diags(1.0 / np.asarray(matrix.sum(axis=1)).ravel()) @ matrix


def edge_stretch(shapes: np.ndarray, rest: np.ndarray, edges: np.ndarray, smoothing=None) -> np.ndarray:
    """Per-vertex mean relative edge-length change against `rest`, optionally smoothed.

    Args:
        shapes: (..., V, 3) positions, cm.
        rest: (V, 3) rest positions, cm.
        edges: (E, 2) int edges.
        smoothing: optional (V, V) sparse matrix applied to the per-vertex values
            (`smoothing_matrix`).
    Returns:
        (..., V) float64: 0 unstretched, 0.1 for edges 10 % longer.
    """
    from scipy import sparse

    v = rest.shape[0]
    i, j = edges[:, 0], edges[:, 1]
    e = len(edges)
    length0 = np.linalg.norm(rest[i] - rest[j], axis=-1)
    diff = shapes[..., i, :] - shapes[..., j, :]
    rel = np.sqrt((diff * diff).sum(-1)) / np.maximum(length0, 1e-9) - 1.0  # (..., E)
    incidence = sparse.csr_matrix((np.ones(2 * e), (np.concatenate([i, j]), np.tile(np.arange(e), 2))),
                                  shape=(v, e))
    degree = np.maximum(np.asarray(incidence.sum(axis=1)).ravel(), 1.0)
    per_vertex = (incidence @ rel.reshape(-1, e).T) / degree[:, None]  # (V, B)
    if smoothing is not None:
        per_vertex = smoothing @ per_vertex
    return per_vertex.T.reshape(rel.shape[:-1] + (v,))


def _speech_weights(names: Sequence[str], num_frames: int, fps: float,
                    rng: np.random.Generator) -> np.ndarray:
    """Continuous speech: jaw pulses at 3-6 syllables/s with closures, funnels and puckers."""
    index = {n: i for i, n in enumerate(names)}
    out = np.zeros((num_frames, len(names)))
    t = np.arange(num_frames) / fps
    rate = rng.uniform(3.0, 6.0)
    syllable = np.floor(t * rate).astype(np.int64)
    phase = t * rate - syllable
    count = int(syllable.max(initial=0)) + 1
    amp = rng.uniform(0.15, 0.6, count)[syllable]
    lips = rng.random(count)[syllable]
    pulse = np.sin(np.pi * phase) ** 2
    closure = np.cos(np.pi * phase) ** 2
    burst = envelope(t, -1.0, 0.5, t[-1] + 1.0 if num_frames else 0.0, 0.5)
    curves = {
        "jawOpen": amp * pulse,
        "mouthClose": np.where(lips < 0.3, 0.5, 0.0) * closure,
        "mouthFunnel": np.where((lips >= 0.3) & (lips < 0.45), 0.5, 0.0) * pulse,
        "mouthPucker": np.where((lips >= 0.45) & (lips < 0.6), 0.5, 0.0) * pulse,
        "mouthLowerDown_L": 0.5 * amp * pulse, "mouthLowerDown_R": 0.5 * amp * pulse,
    }
    for name, curve in curves.items():
        if name in index:
            out[:, index[name]] = burst * curve
    return np.clip(out, 0.0, 1.0)


def expression_weights(expression: str, names: Sequence[str], num_frames: int, fps: float,
                       rng: np.random.Generator) -> np.ndarray:
    """Weights (F, K) of a held expression, or of "speech" (time-varying).

    Raises:
        ValueError: unknown expression (the known ones are listed).
    """
    if expression == "speech":
        return _speech_weights(names, num_frames, fps, rng).astype(np.float32)
    if expression not in HELD_EXPRESSIONS:
        raise ValueError(f"expression '{expression}': expected 'speech' or one of "
                         f"{sorted(HELD_EXPRESSIONS)}")
    held = np.zeros(len(names), np.float32)
    for name, weight in HELD_EXPRESSIONS[expression].items():
        if name in names:
            held[list(names).index(name)] = weight
    return np.repeat(held[None], num_frames, axis=0)


def _kappa(shapes: np.ndarray, rest: np.ndarray, edges: np.ndarray, gain: float, smoothing) -> np.ndarray:
    """Stiffness factor `clip(1 + gain * stretch, 0.5, 3)` (float32, shape of shapes[..., 0])."""
    return np.clip(1.0 + gain * edge_stretch(shapes, rest, edges, smoothing), 0.5, 3.0).astype(np.float32)


def _moving_kappas(shapes: np.ndarray, rest: np.ndarray, edges: np.ndarray, gain: float, smoothing,
                   starts: Sequence[int], block: int, columns: int = 256) -> Iterator[tuple[int, np.ndarray]]:
    """`_kappa` of `shapes` (S, T, V, 3) for the blocks of `block` frames from `starts`, yielded
    in order as (first frame, (S, n, V) float32), equal bit for bit to `_kappa` of each block.

    The edge stretch is computed per block (its (S, n, E, 3) edge vectors are the memory peak),
    but the Gaussian smoothing of several blocks is one product of at least `columns` columns:
    a product's cost is mostly its exp and distance per vertex pair, not the columns (the
    demo's 190 frames: 2.2 s of CPU in one product against 4.2 s in three of 64 columns). The
    columns of a product do not mix, so each comes out as it would alone."""
    per_group = 1 if smoothing is None else max(1, columns // max(1, len(shapes) * block))
    for g in range(0, len(starts), per_group):
        firsts = list(starts[g:g + per_group])
        raw = [edge_stretch(shapes[:, f0:f0 + block], rest, edges, None) for f0 in firsts]  # (S, n, V) each
        if smoothing is not None:
            v = rest.shape[0]
            flat = np.concatenate([r.reshape(-1, v) for r in raw]).T  # (V, columns): blocks side by side
            smoothed = (smoothing @ flat).T
            sizes = np.cumsum([0] + [r.shape[0] * r.shape[1] for r in raw])
            raw = [smoothed[a:b].reshape(r.shape) for a, b, r in zip(sizes[:-1], sizes[1:], raw)]
        for f0, stretch in zip(firsts, raw):
            yield f0, np.clip(1.0 + gain * stretch, 0.5, 3.0).astype(np.float32)


def _coupling_matrix(rest: np.ndarray, edges: np.ndarray, scale: float):
    """Membrane operator `scale (4 / deg_i) sum_j (u_j - u_i) / max(d_ij, 0.25 cm)^2` as a
    (V, V) csr float32 matrix (`scale` = c^2 h: one sub-step's velocity change)."""
    from scipy import sparse

    i, j = edges[:, 0], edges[:, 1]
    v = len(rest)
    d = np.maximum(np.linalg.norm(rest[i] - rest[j], axis=1), 0.25)
    w = 1.0 / d ** 2
    adj = sparse.csr_matrix((np.r_[w, w], (np.r_[i, j], np.r_[j, i])), shape=(v, v))
    degree = np.asarray((adj > 0).sum(axis=1)).ravel().astype(np.float64)
    lap = sparse.diags(4.0 / np.maximum(degree, 1.0)) @ (adj - sparse.diags(np.asarray(adj.sum(axis=1)).ravel()))
    return (scale * lap).astype(np.float32).tocsr()


class DynamicCapture(NamedTuple):
    """A capture with secondary dynamics and its truth.

    Attributes:
        capture: world-space dynamic capture (F, V, 3), cm.
        quasistatic: world-space truth without dynamics (F, V, 3), cm.
        skull: skull-to-world transforms (F, 4, 4).
        segments: (F, 1) segment index of each frame (name "segment").
        neutral: one-frame skull-frame neutral of the identity (1, V, 3), cm.
        offsets: (F, V, 3) float32 truth dynamic offsets u in the skull frame, cm.
        stabilized: the capture without noise in the true skull frame (F, V, 3), cm: what a
            perfect stabilization gives (dynamics kept).
    """

    capture: MeshSequence
    quasistatic: MeshSequence
    skull: RigidSequence
    segments: ParamSequence
    neutral: MeshSequence
    offsets: np.ndarray
    stabilized: MeshSequence


def simulate_dynamics(model: FaceModel, *, motions: Sequence[str], expressions: Sequence[str],
                      segment_frames: int, fps: float, seed: int, identity_scale: float = 1.0,
                      amplitude_scale: float = 1.0, stiffness_scale: float = 1.0,
                      damping_scale: float = 1.0, stretch_stiffening: float = 4.0,
                      preroll_s: float = 0.75, substeps: int = 4, coupling_cm_s: float = 100.0,
                      noise_cm: float = 0.0) -> DynamicCapture:
    """Simulate a dynamic capture of `model` (see the module docstring).

    Args:
        model: face model (cm, ARKit expression names).
        motions: motion programs, e.g. ["walk", "oscillate@8"].
        expressions: expression names ("neutral", held ones, "speech"); segments are
            every (expression, motion) pair, expressions outer.
        segment_frames: frames per segment.
        fps: capture frame rate (frames per second).
        seed: identity, motion parameters, speech and noise derive from it.
        identity_scale: std of the identity weights (0 = the generic neutral).
        amplitude_scale: scales every skull motion.
        stiffness_scale: multiplies every natural frequency (1 = 7.5 Hz loose, 22 Hz stiff).
        damping_scale: multiplies every damping ratio.
        stretch_stiffening: stiffness gain per unit of edge stretch.
        preroll_s: seconds simulated before each segment and dropped.
        substeps: integration sub-steps per frame (semi-implicit Euler); raised when needed
            for stability (fastest mode times the sub-step below 1.5).
        coupling_cm_s: wave speed c of the membrane coupling between neighbours (cm/s),
            `u_i'' += c^2 (4 / deg_i) sum_j (u_j - u_i) / max(d_ij, 0.25 cm)^2`; 0 = none.
        noise_cm: std of Gaussian tracking noise on the capture (cm).
    Returns:
        DynamicCapture with F = len(expressions) * len(motions) * segment_frames frames.
    Raises:
        ValueError: unknown motion or expression, or non-positive sizes (named).
    """
    if segment_frames < 1 or fps <= 0 or substeps < 1:
        raise ValueError(f"segment_frames, fps, substeps: expected >= 1, > 0, >= 1, found "
                         f"{segment_frames}, {fps}, {substeps}")
    if not motions or not expressions:
        raise ValueError("motions, expressions: expected at least one of each, found "
                         f"{list(motions)}, {list(expressions)}")
    for program in motions:
        parse_program(program)
    from scipy import sparse

    from .skin_kernels import GaussianSmoothing, integrate

    names = list(model.expression_names)
    root = np.random.SeedSequence(seed)
    id_stream = root.spawn(1)[0]
    num_identity, v = model.identity_deltas.shape[:2]
    identity = (identity_scale * np.random.default_rng(id_stream).standard_normal(num_identity)
                ).astype(np.float32)
    base = (model.neutral.reshape(-1) + identity @ model.identity_deltas.reshape(num_identity, -1)
            ).reshape(v, 3).astype(np.float32)
    rest = base.astype(np.float64)
    pivot = default_pivot(model.neutral)
    edges = vertex_neighbours(rest, model.faces)
    smooth = GaussianSmoothing(rest) if stretch_stiffening > 0 else None  # smoothing_matrix's product
    loose = looseness_field(rest)
    omega = 2 * np.pi * stiffness_scale * _F_STIFF_HZ ** (1 - loose) * _F_LOOSE_HZ ** loose
    zeta = damping_scale * (0.45 - 0.15 * loose)
    damp, stiff = 2 * zeta * omega, omega ** 2  # (V,)
    deltas = model.expression_deltas.reshape(len(names), -1)

    fastest = np.sqrt(3.0 * stiff.max() + coupling_cm_s ** 2 * 4.0 * 2.0 / 0.25 ** 2)
    substeps = max(substeps, int(np.ceil(fastest / (1.5 * fps))))
    pairs = [(e, m) for e in expressions for m in motions]
    nseg, pre = len(pairs), int(round(preroll_s * fps))
    total = pre + segment_frames
    h = 1.0 / (fps * substeps)
    fine_t = (np.arange(-1, total * substeps + 1) - pre * substeps) * h  # one extra each side
    frame_t = (np.arange(total) - pre) / fps
    shapes = np.empty((nseg, total, v, 3), np.float32)
    mats_frame = np.empty((nseg, total, 4, 4))
    accel_a = np.empty((nseg, len(fine_t) - 2, 3, 3))
    accel_b = np.empty((nseg, len(fine_t) - 2, 3))
    for s, (expression, program) in enumerate(pairs):
        motion_rng = np.random.default_rng([seed, 11, motions.index(program), expressions.index(expression)])
        state = motion_rng.bit_generator.state
        ang, trans = skull_motion(program, fine_t, motion_rng, amplitude_scale=amplitude_scale)
        mats = poses_to_matrices(ang, trans, pivot)
        rot, org = mats[:, :3, :3], mats[:, :3, 3]
        rot_dd = (rot[2:] - 2 * rot[1:-1] + rot[:-2]) / (h * h)
        org_dd = (org[2:] - 2 * org[1:-1] + org[:-2]) / (h * h)
        rt = np.swapaxes(rot[1:-1], 1, 2)
        accel_a[s] = rt @ rot_dd
        accel_b[s] = np.einsum("tij,tj->ti", rt, org_dd)
        motion_rng.bit_generator.state = state  # same draws: frames are on the fine grid
        ang_f, trans_f = skull_motion(program, frame_t, motion_rng, amplitude_scale=amplitude_scale)
        mats_frame[s] = poses_to_matrices(ang_f, trans_f, pivot)
        expr_rng = np.random.default_rng([seed, 13, expressions.index(expression)])
        weights = expression_weights(expression, names, total, fps, expr_rng)
        shapes[s] = (base.reshape(1, -1) + weights @ deltas).reshape(total, v, 3)

    u = np.zeros((nseg, v, 3), np.float32)
    du = np.zeros((nseg, v, 3), np.float32)
    offsets = np.empty((nseg, segment_frames, v, 3), np.float32)
    coupling = _coupling_matrix(rest, edges, coupling_cm_s ** 2 * h) if coupling_cm_s > 0 else None
    rest_h = np.concatenate([rest, np.ones((v, 1))], axis=1).astype(np.float32)  # (V, 4)
    affine = (h * np.concatenate([accel_a, accel_b[..., None]], axis=-1)).astype(np.float32)
    damp_h = (h * damp).astype(np.float32)[None, :, None]
    stiff_h = (h * stiff).astype(np.float32)
    held = [s for s, (expression, _) in enumerate(pairs) if expression != "speech"]
    moving = [s for s, (expression, _) in enumerate(pairs) if expression == "speech"]
    if coupling is None:
        coupling = sparse.csr_matrix((v, v), dtype=np.float32)
    coupling.sort_indices()
    held_kappa = (_kappa(shapes[held, 0], rest, edges, stretch_stiffening, smooth)[:, None] * stiff_h
                  if held else None)  # held expressions: one stiffness modulation for the whole segment
    starts = range(0, total, 64)  # time-varying expressions: modulation in blocks of frames
    kappas = (_moving_kappas(shapes[moving], rest, edges, stretch_stiffening, smooth, starts, 64)
              if moving else None)
    for f0 in starts:
        n = min(64, total - f0)
        block = np.empty((nseg, n, v), np.float32)
        if held:
            block[held] = held_kappa
        if kappas is not None:
            first, kappa = next(kappas)
            assert first == f0 and kappa.shape[1] == n
            block[moving] = kappa * stiff_h
        integrate(u, du, rest_h, affine, damp_h.reshape(v), block, coupling.indptr.astype(np.int64),
                  coupling.indices.astype(np.int64), coupling.data.astype(np.float32), substeps, h, f0, pre,
                  offsets)
    mats = np.ascontiguousarray(mats_frame[:, pre:].reshape(-1, 4, 4))
    quasi_local = shapes[:, pre:].reshape(-1, v, 3)
    capture = transform_points(mats, quasi_local + offsets.reshape(-1, v, 3))
    quasi = transform_points(mats, quasi_local)
    if noise_cm > 0:
        noise_rng = np.random.default_rng([seed, 17])
        capture += (noise_cm * noise_rng.standard_normal(capture.shape)).astype(np.float32)

    def mesh(vertices: np.ndarray) -> MeshSequence:
        return MeshSequence(vertices=vertices, faces=model.faces, uv=model.uv,
                            uv_faces=model.uv_faces, groups=dict(model.groups), fps=float(fps))

    segment_ids = np.repeat(np.arange(nseg, dtype=np.float32), segment_frames)[:, None]
    return DynamicCapture(capture=mesh(capture), quasistatic=mesh(quasi),
                          skull=RigidSequence(matrices=mats),
                          segments=ParamSequence(values=segment_ids, names=["segment"]),
                          neutral=mesh(base[None].copy()),
                          offsets=offsets.reshape(-1, v, 3),
                          stabilized=mesh(quasi_local + offsets.reshape(-1, v, 3)))


class DynamicPerformance(Node):
    """Synthesize captures with secondary dynamics (skin jiggle) and their true quasistatic motion."""

    type_name = "synth.DynamicPerformance"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        motions: list[str] = Param(["still", "walk", "run", "jump", "oscillate@6", "oscillate@8",
                                    "oscillate@10"],
                                   description="motion programs: still, walk, run, jump, "
                                               "oscillate@HZ (vertical vibration at HZ)")
        expressions: list[str] = Param(["neutral", "smile", "jaw_open", "speech"],
                                       description="'speech' or held expressions: "
                                                   f"{sorted(HELD_EXPRESSIONS)}")
        segment_frames: int = Param(192, ge=1, description="frames per (expression, motion) segment")
        fps: float = Param(120.0, gt=0, description="capture frame rate (frames per second)")
        seed: int = Param(0, ge=0, description="seed of identity, motion parameters, speech, noise")
        identity_scale: float = Param(1.0, ge=0, description="std of the identity weights")
        amplitude_scale: float = Param(1.0, ge=0, description="scales every skull motion")
        stiffness_scale: float = Param(1.0, gt=0, description="scales natural frequencies "
                                                              "(1: 7.5 Hz loose, 22 Hz stiff)")
        damping_scale: float = Param(1.0, gt=0, description="scales damping ratios (0.3 loose, 0.45 stiff)")
        stretch_stiffening: float = Param(4.0, ge=0, description="stiffness gain per unit edge stretch")
        preroll_s: float = Param(0.75, ge=0, description="seconds simulated before each segment (dropped)")
        substeps: int = Param(4, ge=1, description="integration sub-steps per frame")
        coupling_cm_s: float = Param(100.0, ge=0, description="wave speed of the skin's membrane "
                                                             "coupling between neighbours (cm/s)")
        noise_cm: float = Param(0.0, ge=0, description="Gaussian tracking noise std (cm)")

        @field_validator("motions")
        @classmethod
        def _programs(cls, value: list[str]) -> list[str]:
            if not value:
                raise ValueError("expected at least one motion program")
            for program in value:
                parse_program(program)
            if len(set(value)) != len(value):
                raise ValueError(f"expected distinct motion programs, found {value}")
            return value

        @field_validator("expressions")
        @classmethod
        def _expressions(cls, value: list[str]) -> list[str]:
            if not value:
                raise ValueError("expected at least one expression")
            bad = [e for e in value if e != "speech" and e not in HELD_EXPRESSIONS]
            if bad:
                raise ValueError(f"unknown expression(s) {bad}; expected 'speech' or one of "
                                 f"{sorted(HELD_EXPRESSIONS)}")
            if len(set(value)) != len(value):
                raise ValueError(f"expected distinct expressions, found {value}")
            return value

    model = In(FaceModel, doc="face model (cm, ARKit expression names)")
    capture = Out(MeshSequence, doc="world-space capture with secondary dynamics (cm)")
    quasistatic = Out(MeshSequence, doc="world-space truth without dynamics (cm)")
    skull = Out(RigidSequence, doc="skull-to-world transforms")
    segments = Out(ParamSequence, doc="segment index of each frame ('segment')")
    neutral = Out(MeshSequence, per_frame=False, doc="skull-frame neutral of the identity (1 frame)")
    stabilized = Out(MeshSequence, doc="the capture without noise in the true skull frame (cm): what a perfect "
                                       "stabilization gives")

    def frame_count(self) -> int:
        p = self.params
        return len(p.motions) * len(p.expressions) * p.segment_frames

    def peek_capture_timing(self, frames: range) -> tuple[float, np.ndarray]:
        """The capture's frame rate and the segment label of each of the run's `frames`, known
        from the parameters (for a trainer's `check_frames` while planning)."""
        p = self.params
        return float(p.fps), (np.arange(frames.start, frames.stop) // p.segment_frames).astype(np.float32)

    def run(self, model: FaceModel) -> dict:
        p = self.params
        total = self.frame_count()
        if not 0 <= self.frames.start <= self.frames.stop <= total:
            raise InputError("segment_frames", f"expected frames within 0:{total} (the simulated performance), "
                                               f"found frames {self.frames.start}:{self.frames.stop}")
        result = simulate_dynamics(
            model, motions=p.motions, expressions=p.expressions, segment_frames=p.segment_frames,
            fps=p.fps, seed=p.seed, identity_scale=p.identity_scale,
            amplitude_scale=p.amplitude_scale, stiffness_scale=p.stiffness_scale,
            damping_scale=p.damping_scale, stretch_stiffening=p.stretch_stiffening,
            preroll_s=p.preroll_s, substeps=p.substeps, coupling_cm_s=p.coupling_cm_s,
            noise_cm=p.noise_cm)
        out = result._asdict()
        out.pop("offsets")
        if self.frames != range(total):  # the whole performance is simulated (it is one dynamical
            # system from its first frame), then the run's frames are cut out of it
            out = {name: value.slice_frames(self.frames.start, self.frames.stop)
                   if name != "neutral" and getattr(value, "per_frame", False) else value
                   for name, value in out.items()}
        return out
