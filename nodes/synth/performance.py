"""Synthetic facial performances with ground truth: capture, skull motion, expressions.

The truth stabilized mesh (skull frame = model frame) of frame f is
`S_f = neutral + a @ identity_deltas + w_f @ expression_deltas`, with a random identity
`a ~ N(0, identity_scale^2)` and expression weights `w_f` from `expressions.py`. The capture
is `X_f = M_f (S_f + slide_f) + noise_f + outliers_f` in world space, with `M_f` the truth
skull-to-world transform from `head_motion.py` (rotation about a pivot near the top of the
neck, see `head_motion.default_pivot`).

Artefacts (default off) are part of the capture only, never of the truth:
- noise: i.i.d. Gaussian per coordinate, `noise_cm` standard deviation;
- sliding: forehead/scalp skin (vertices above the brows, weight ramping from 0 at the brows
  to 1 at 3 cm above) slides tangentially to the head, upward while browInnerUp /
  browOuterUp / eyeWide are strongly active and downward with browDown, up to `sliding_cm`,
  following the activation with a 0.3 s lag (the skin's slow response). This moves
  "stable" points, the effect that breaks stable-point stabilization;
- outliers: each vertex of each frame, with probability `outlier_fraction`, is offset by
  `outlier_cm` to 3 x `outlier_cm` in a random direction.

All curves are drawn from the seed for all `num_frames` frames (cheap), and per-frame
random draws use a generator seeded by (seed, stream, frame): the result for frames a:b is
exactly the slice a:b of the whole sequence.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

from pydantic import field_validator

import numpy as np

from nodegraph import (FRAMEWISE, FaceModel, In, InputError, MeshSequence, Node, NodeParams, Out,
                       Param, ParamSequence, RigidSequence)

from .expressions import expression_curves, held_expressions
from .head_motion import MOTIONS, default_pivot, head_motion_curves, poses_to_matrices

__all__ = ["SyntheticPerformance", "generate_performance", "upper_face_weights",
           "sliding_activation", "transform_points", "Performance"]

_STREAM_IDENTITY, _STREAM_EXPRESSION, _STREAM_MOTION, _STREAM_NOISE, _STREAM_OUTLIER, _STREAM_HELD = range(6)
_SLIDE_UP = ("browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
             "eyeWide_L", "eyeWide_R")
_SLIDE_DOWN = ("browDown_L", "browDown_R")
_BROW_LANDMARKS = np.arange(17, 27)


class SyntheticPerformance(NamedTuple):
    """A synthetic capture and its ground truth, for the frames requested.

    Attributes:
        capture: world-space mesh sequence (with the artefacts asked for).
        rigid: truth skull-to-world transforms, `x_world = M_f x_skull`.
        expressions: truth weights (F, K), names = the model's expression names.
        stabilized: truth skull-frame mesh sequence, noise-free, without artefacts.
    """

    capture: MeshSequence
    rigid: RigidSequence
    expressions: ParamSequence
    stabilized: MeshSequence


def upper_face_weights(neutral: np.ndarray, landmarks: np.ndarray | None = None, *,
                       ramp_cm: float = 3.0) -> np.ndarray:
    """Weight of each vertex in forehead/scalp sliding: 0 at or below the brows, 1 at `ramp_cm` above.

    The brow level is the lowest brow landmark (Multi-PIE 17-26) when the 68 landmarks are
    present, else 65 % of the bounding-box height (y up).

    Args:
        neutral: (V, 3) cm, y up.
        landmarks: (68,) vertex indices, or None / fewer than 68 (then the bbox rule).
        ramp_cm: height over which the weight rises from 0 to 1.
    Returns:
        (V,) float32 in [0, 1].
    """
    y = neutral[:, 1].astype(np.float64)
    if landmarks is not None and len(landmarks) == 68:
        level = float(y[landmarks[_BROW_LANDMARKS]].min())
    else:
        level = float(y.min() + 0.65 * (y.max() - y.min())) if len(y) else 0.0
    return np.clip((y - level) / ramp_cm, 0.0, 1.0).astype(np.float32)


def _slide_directions(neutral: np.ndarray, center: np.ndarray) -> np.ndarray:
    """Unit "up" directions in each vertex's tangent plane (normal ~ radial from `center`)."""
    normal = neutral.astype(np.float64) - center
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-9)
    up = np.array([0.0, 1.0, 0.0])
    tangent = up - (normal @ up)[:, None] * normal
    return tangent / np.maximum(np.linalg.norm(tangent, axis=1, keepdims=True), 1e-9)


def sliding_activation(weights: np.ndarray, names: list[str], fps: float, *,
                       lag_s: float = 0.3) -> np.ndarray:
    """Signed, lagged activation of skin sliding in [-1, 1] for every frame.

    `a_f = smoothstep((max up-shape weight - 0.3) / 0.5) - smoothstep((max browDown - 0.3) / 0.5)`,
    then a causal exponential filter with time constant `lag_s`.

    Args:
        weights: (F, K) expression weights of the whole sequence.
        names: K names.
        fps: frames per second.
    Returns:
        (F,) float64.
    """
    def strength(group: tuple[str, ...]) -> np.ndarray:
        cols = [i for i, n in enumerate(names) if n in group]
        if not cols:
            return np.zeros(len(weights))
        x = np.clip((weights[:, cols].max(axis=1).astype(np.float64) - 0.3) / 0.5, 0.0, 1.0)
        return x * x * (3 - 2 * x)

    raw = strength(_SLIDE_UP) - strength(_SLIDE_DOWN)
    alpha = 1.0 - np.exp(-1.0 / (lag_s * fps))
    out = np.empty_like(raw)
    state = 0.0
    for f, value in enumerate(raw):  # a first-order filter over frames (F is small)
        state += alpha * (value - state)
        out[f] = state
    return out


def transform_points(matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply per-frame 4x4 transforms, frame by frame (bit-identical whatever the frame count).

    Each frame is one (V, 3) @ (3, 3) product of the same shape, so a frame's result does not
    depend on which other frames are computed with it (a batched product could). Deliberately not
    `nodes.geometry.rigid.apply_rigid`: that one computes in float64, and its results rounded to
    float32 differ in the last bit from these float32 products for about 40 % of coordinates,
    so using it would change every synthetic capture the generator has produced.

    Args:
        matrices: (F, 4, 4) float64.
        points: (F, V, 3) float32.
    Returns:
        (F, V, 3) float32, `M_f @ [x, 1]`.
    """
    rot_t = np.swapaxes(matrices[:, :3, :3], 1, 2).astype(np.float32)  # (F, 3, 3), R^T
    trans = matrices[:, :3, 3].astype(np.float32)
    out = np.empty(points.shape, np.float32)
    for f in range(len(points)):
        np.matmul(points[f], rot_t[f], out=out[f])
        out[f] += trans[f]
    return out


def _frame_rngs(seed: int, stream: int, frames: range) -> list[np.random.Generator]:
    return [np.random.default_rng([seed, stream, f]) for f in frames]


def generate_performance(model: FaceModel, *, num_frames: int, seed: int, fps: float = 30.0,
                         identity_scale: float = 1.0, rotation_deg: float = 10.0,
                         translation_cm: float = 2.0, motion: str = "smooth",
                         max_frequency_hz: float = 0.5, pivot_cm: tuple[float, float, float] | None = None,
                         rest_fraction: float = 0.7, expression_rate_hz: float = 0.4,
                         noise_cm: float = 0.0, sliding_cm: float = 0.0,
                         outlier_fraction: float = 0.0, outlier_cm: float = 2.0,
                         held_fraction: float = 0.0, start_expression: float = 0.0,
                         frames: range | None = None) -> SyntheticPerformance:
    """Generate a synthetic capture of `model` with its ground truth (see the module docstring).

    Args:
        model: face model (cm); expression names should be ARKit names (others stay 0).
        num_frames: F, length of the whole performance.
        seed: every random choice derives from it (separate streams for identity,
            expressions, motion, noise, outliers: changing one artefact leaves the rest).
        fps: frames per second (> 0).
        identity_scale: std of the identity weights (0 = the generic neutral).
        rotation_deg: peak |angle| per axis (degrees); translation_cm: peak |t| per axis (cm).
        motion: "smooth", "nod", "turn", "walk" or "none".
        max_frequency_hz: highest frequency of smooth head motion (Hz).
        pivot_cm: rotation pivot in the skull frame (cm); None = `default_pivot(neutral)`.
        rest_fraction: every expression weight is < 0.05 on at least this fraction of frames.
        expression_rate_hz: onsets per second of single expressions.
        noise_cm: std of Gaussian tracking noise (cm).
        sliding_cm: peak forehead/scalp sliding (cm).
        outlier_fraction: probability of each vertex of each frame being an outlier.
        outlier_cm: smallest outlier offset (cm); offsets are 1-3 times this.
        held_fraction: about this fraction of frames holds strong expressions (2-4 families
            at 0.6-1.0, see `expressions.held_expressions`); 0 = none (default, unchanged).
        start_expression: strength of a strong expression (3 families) held over the first
            second and released over 0.5 s; 0 = none (default, unchanged).
        frames: absolute frames to produce (a sub-range of range(num_frames)); None = all.
    Returns:
        SyntheticPerformance for `frames`: capture (world) and stabilized (skull) meshes
        (len(frames), V, 3) float32 with the model's faces, uv and groups; rigid (F, 4, 4)
        float64; expressions (F, K) float32.
    Raises:
        ValueError: bad `frames`, `motion`, fps, or rest_fraction (named).
    """
    if frames is None:
        frames = range(num_frames)
    if frames.step != 1 or frames.start < 0 or frames.stop > num_frames or frames.start > frames.stop:
        raise ValueError(f"frames: expected a sub-range of range(0, {num_frames}) with step 1, "
                         f"found {frames}")
    if not 0.0 <= outlier_fraction <= 1.0:
        raise ValueError(f"outlier_fraction: expected in [0, 1], found {outlier_fraction}")
    if noise_cm < 0 or sliding_cm < 0 or identity_scale < 0:
        raise ValueError(f"noise_cm, sliding_cm, identity_scale: expected >= 0, found "
                         f"{noise_cm}, {sliding_cm}, {identity_scale}")
    root = np.random.SeedSequence(seed)
    streams = root.spawn(3)
    names = list(model.expression_names)
    weights_all = expression_curves(names, num_frames, seed=streams[_STREAM_EXPRESSION], fps=fps,
                                    rest_fraction=rest_fraction,
                                    expression_rate_hz=expression_rate_hz)
    if held_fraction > 0 or start_expression > 0:
        extra = held_expressions(names, num_frames, rng=np.random.default_rng([seed, _STREAM_HELD]),
                                 fps=fps, held_fraction=held_fraction, start_strength=start_expression)
        weights_all = np.clip(weights_all + extra, 0.0, 1.0).astype(np.float32)
    angles, trans = head_motion_curves(num_frames, seed=streams[_STREAM_MOTION], fps=fps,
                                       motion=motion, rotation_deg=rotation_deg,
                                       translation_cm=translation_cm,
                                       max_frequency_hz=max_frequency_hz)
    pivot = default_pivot(model.neutral) if pivot_cm is None else np.asarray(pivot_cm, np.float64)
    matrices = poses_to_matrices(angles[frames.start:frames.stop], trans[frames.start:frames.stop], pivot)
    weights = weights_all[frames.start:frames.stop]

    num_identity, v = model.identity_deltas.shape[:2]
    identity = (identity_scale * np.random.default_rng(streams[_STREAM_IDENTITY])
                .standard_normal(num_identity)).astype(np.float32)
    base = (model.neutral.reshape(-1) + identity @ model.identity_deltas.reshape(num_identity, -1))
    deltas = model.expression_deltas.reshape(len(names), -1)
    stabilized = np.empty((len(frames), v, 3), np.float32)
    scratch = np.empty(3 * v, np.float32)  # reused buffer: large per-frame temporaries are slow
    for i, w in enumerate(weights):  # per-frame GEMV: bit-identical whatever the chunk
        np.dot(w, deltas, out=scratch)
        np.add(base, scratch, out=stabilized[i].reshape(-1))

    skin = stabilized
    if sliding_cm > 0:
        activation = sliding_activation(weights_all, names, fps)[frames.start:frames.stop]
        neutral = base.reshape(v, 3)
        center = neutral.mean(axis=0).astype(np.float64)
        field = (sliding_cm * upper_face_weights(neutral, model.landmarks)[:, None]
                 * _slide_directions(neutral, center)).astype(np.float32)  # (V, 3)
        skin = stabilized + activation.astype(np.float32)[:, None, None] * field
    capture = transform_points(matrices, skin)
    if noise_cm > 0:
        noise = np.empty((v, 3), np.float32)
        for i, rng in enumerate(_frame_rngs(seed, _STREAM_NOISE, frames)):
            rng.standard_normal(dtype=np.float32, out=noise)
            noise *= np.float32(noise_cm)
            capture[i] += noise
    if outlier_fraction > 0:
        for i, rng in enumerate(_frame_rngs(seed, _STREAM_OUTLIER, frames)):
            hit = np.flatnonzero(rng.random(v) < outlier_fraction)
            direction = rng.standard_normal((len(hit), 3))
            direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-9)
            size = outlier_cm * rng.uniform(1.0, 3.0, (len(hit), 1))
            capture[i, hit] += (size * direction).astype(np.float32)

    def mesh(vertices: np.ndarray) -> MeshSequence:
        return MeshSequence(vertices=vertices, faces=model.faces, uv=model.uv,
                            uv_faces=model.uv_faces, groups=dict(model.groups), fps=float(fps))

    return SyntheticPerformance(
        capture=mesh(capture),
        rigid=RigidSequence(matrices=matrices),
        expressions=ParamSequence(values=weights, names=names),
        stabilized=mesh(stabilized),
    )


class Performance(Node):
    """Synthesize a facial performance of a face model with truth skull motion and expressions."""

    type_name = "synth.Performance"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        num_frames: int = Param(300, description="length of the performance (frames)", ge=1)
        seed: int = Param(0, description="seed of every random choice", ge=0)
        fps: float = Param(30.0, description="frame rate (frames per second)", gt=0)
        identity_scale: float = Param(1.0, description="std of the random identity weights "
                                                       "(0 = generic neutral)", ge=0)
        rotation_deg: float = Param(10.0, description="peak head rotation per axis (degrees)", ge=0)
        translation_cm: float = Param(2.0, description="peak head translation per axis (cm)", ge=0)
        motion: Literal["smooth", "nod", "turn", "walk", "none"] = Param(
            "smooth", description=f"head motion, one of {list(MOTIONS)}")
        max_frequency_hz: float = Param(0.5, description="highest frequency of smooth head "
                                                         "motion (Hz)", gt=0)
        pivot_cm: list[float] = Param([], description="rotation pivot (x, y, z) in the skull "
                                                      "frame (cm); [] = near the top of the neck")

        @field_validator("pivot_cm")
        @classmethod
        def _three_or_none(cls, value: list[float]) -> list[float]:
            if len(value) not in (0, 3):
                raise ValueError(f"expected [] or 3 numbers (x, y, z, cm), found {value}")
            return value
        rest_fraction: float = Param(0.7, description="each expression weight is < 0.05 on at "
                                                      "least this fraction of frames", ge=0, le=1)
        expression_rate_hz: float = Param(0.4, description="single-expression onsets per second "
                                                           "(1/s)", ge=0)
        noise_cm: float = Param(0.0, description="Gaussian tracking noise std (cm)", ge=0)
        sliding_cm: float = Param(0.0, description="peak forehead/scalp skin sliding with "
                                                   "raised/lowered brows (cm)", ge=0)
        outlier_fraction: float = Param(0.0, description="probability of a vertex being an "
                                                         "outlier in a frame", ge=0, le=1)
        outlier_cm: float = Param(2.0, description="smallest outlier offset (cm; up to 3x)", ge=0)
        held_fraction: float = Param(0.0, description="about this fraction of frames holds strong "
                                                      "expressions (0 = none)", ge=0, le=1)
        start_expression: float = Param(0.0, description="strength of a strong expression held "
                                                         "over the first second (0 = none)", ge=0, le=1)

    model = In(FaceModel, doc="face model (ARKit expression names)")
    capture = Out(MeshSequence, doc="world-space capture, with artefacts (cm)")
    rigid = Out(RigidSequence, doc="truth skull-to-world transforms")
    expressions = Out(ParamSequence, doc="truth expression weights")
    stabilized = Out(MeshSequence, doc="truth skull-frame mesh, without artefacts (cm)")

    def frame_count(self) -> int:
        return self.params.num_frames

    def run(self, model: FaceModel) -> dict:
        p = self.params
        if p.motion not in MOTIONS:
            raise InputError("motion", f"expected one of {list(MOTIONS)}, found '{p.motion}'")
        if p.pivot_cm and len(p.pivot_cm) != 3:
            raise InputError("pivot_cm", f"expected [] or 3 numbers (cm), found {p.pivot_cm}")
        if self.frames.start < 0 or self.frames.stop > p.num_frames:
            raise InputError("num_frames", f"frames {self.frames.start}:{self.frames.stop} asked "
                                           f"for a performance of {p.num_frames} frames")
        result = generate_performance(
            model, num_frames=p.num_frames, seed=p.seed, fps=p.fps,
            identity_scale=p.identity_scale, rotation_deg=p.rotation_deg,
            translation_cm=p.translation_cm, motion=p.motion, max_frequency_hz=p.max_frequency_hz,
            pivot_cm=tuple(p.pivot_cm) if p.pivot_cm else None, rest_fraction=p.rest_fraction,
            expression_rate_hz=p.expression_rate_hz, noise_cm=p.noise_cm,
            sliding_cm=p.sliding_cm, outlier_fraction=p.outlier_fraction,
            outlier_cm=p.outlier_cm, held_fraction=p.held_fraction,
            start_expression=p.start_expression, frames=self.frames)
        return result._asdict()
