"""Mode-pursuit stabilization: the energy and its optimizer.

Method: "Mode pursuit stabilization" (seed paper 1, `shared/seeds/mode_pursuit_stabilization.txt`).
Find world-to-skull rigid transforms `r_f` so that the stabilized mesh `S_f = r_f(X_f)` of a
tracked mesh `X` (F, V, 3) keeps each vertex at its rest position `R_v` as often as possible:

    E(q) = 1 / (3 F V) * [ sum_{f, v, c} psi_pos(S_{f,v,c} - R_{v,c})
                           + lambda * sum_{f, v, c} psi_vel(dS_{f,v,c} / dt) ]        (eq. 4)

with the bounded penalty `psi_w` and the 7-tap velocity of `penalty.py` at every frame with
a full stencil and lower-order central differences at the three first and last frames
(`ends="reduced"`: without them the end control points drift when their position terms
saturate). The motion is a dual-quaternion B-spline (SDLB):
`r_f = normalize(sum_i B_i(f) q_i)` with uniform cubic weights over control dual quaternions
`q_i` (8 numbers each, optimized directly as in the paper). Optimization is a numerical
continuation: L-BFGS (strong-Wolfe line search) restarted at every stage with a fixed iteration
count, stages walking down the width schedule, with midpoint refinement interleaved (see
`make_schedule`).

Coarse to fine: the control polygon lives at the finest spacing `spacing / 2^refinements`
from the start (the initial motion is least-squares fitted there, so fast head motion in the
initialization is kept). A stage at a coarser level optimizes a correction polygon of that
level, which midpoint refinement (exact knot insertion) carries to the finest level and adds
to the control points; after each stage the control dual quaternions are normalized (this
stops weakly constrained end control points from drifting in scale). With an identity
initialization this is exactly the paper's coarse-to-fine refinement.

The rest shape R is the per-vertex median of the initially stabilized vertices, unless given;
by default it is re-estimated before every stage after the first by 3 mean-shift steps at the
stage's width (`update_rest`): this matters with an identity initialization, where the first
median is blurred by the head motion (median error 0.016 -> 0.002 cm on the synthetic
651 x 1185 benchmark) and changes nothing measurable with a good initialization.

Implementation notes (what makes it fast):
  - Coordinates are centred and scaled to unit RMS radius inside the optimizer (the energy is
    unchanged since widths scale too), so rotations and translations are equally conditioned.
  - The big tensor is kept as (F, 3, V) float32 so the per-frame transform is one `baddbmm`
    and reductions run along contiguous memory.
  - Energy and gradient with respect to the per-frame (R_f, t_f) are computed together in
    one fused pass over blocks of frames (no autograd graph over F x V x 3 tensors; blocks of
    about 2^18 coordinates stay in cache and bound the memory); autograd only runs over the
    small spline (F x 8). `torch.compile` of the block kernel is optional (`compile=True`).
  - The energy uses at most `max_vertices` vertices (default 2000), chosen by farthest-point
    sampling on the first frame (spread is rigid-invariant; deterministic); the result is
    applied to every vertex afterwards, in blocks of frames.
  - L-BFGS is our own (`lbfgs.py`, same algorithm as `torch.optim.LBFGS`): constructing a
    torch optimizer imports `torch._dynamo` (about 2 s per process).

Conventions: cm, frames; `matrices[f]` is skull-to-world (`x_world = M_f x_skull`), so
`r_f = M_f^-1`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..io.face_model import farthest_point_sampling as _farthest_point_sampling_np
from ..rigid.kabsch import apply_rigid, invert_rigid as _invert_rigid_np
from .bspline import SplineBasis, evaluate_spline, fit_control_points, frame_basis, num_control_points, refine_midpoint
from .dualquat import (dualquat_align_hemisphere, dualquat_from_rotation_translation,
                       dualquat_identity, dualquat_normalize, dualquat_to_rotmat_translation,
                       rotmat_to_quat)
from .lbfgs import lbfgs
from .penalty import REDUCED_END_COEFFS, VELOCITY_COEFFS, central_velocity, psi, psi_sum_and_grad_

__all__ = [
    "DEFAULT_POSITION_WIDTHS", "DEFAULT_VELOCITY_WIDTHS", "Stage", "make_schedule",
    "stabilization_energy", "fused_stabilization_energy", "farthest_point_sampling",
    "ModePursuitResult", "mode_pursuit", "stabilize_vertices", "invert_rigid",
]

DEFAULT_POSITION_WIDTHS: tuple[float, ...] = (0.8, 0.4, 0.2, 0.1, 0.05)
"""Position widths of the paper's continuation schedule (cm)."""
DEFAULT_VELOCITY_WIDTHS: tuple[float, ...] = (0.2, 0.1, 0.05, 0.025, 0.0125)
"""Velocity widths of the paper's continuation schedule (cm / frame)."""

ProgressFn = Callable[[float, str], None]


# --------------------------------------------------------------------------------------
# Energy
# --------------------------------------------------------------------------------------
def stabilization_energy(vertices: Tensor, rot: Tensor, trans: Tensor, rest: Tensor, *,
                         width_pos: float, width_vel: float, velocity_weight: float) -> Tensor:
    """Return the mode-pursuit energy (eq. 4), plainly, differentiable by autograd.

    This is the reference formulation (tests, small problems); `mode_pursuit` uses the fused
    `fused_stabilization_energy`, which returns the same value and gradient.

    Args:
        vertices: (F, V, 3) tracked vertices X, world frame, cm; F >= 7.
        rot: (F, 3, 3) world-to-skull rotations.
        trans: (F, 3) world-to-skull translations, cm: `S_f = rot_f X_f + trans_f`.
        rest: (V, 3) rest mesh R, skull frame, cm.
        width_pos: position width (cm).
        width_vel: velocity width (cm / frame).
        velocity_weight: lambda >= 0.
    Returns:
        () mean penalty per coordinate: `(sum psi_pos + lambda sum psi_vel) / (3 F V)`.
    """
    stab = vertices @ rot.transpose(1, 2) + trans[:, None, :]
    pos = psi(stab - rest, width_pos).sum()
    vel = psi(central_velocity(stab, dim=0, ends="reduced"), width_vel).sum()
    return (pos + velocity_weight * vel) / stab.numel()


def _block_energy(x: Tensor, rot: Tensor, trans: Tensor, rest_neg: Tensor, inner: tuple[int, int],
                  inv_w_pos: float, inv_w_vel: float, pos_scale: float, vel_scale: float,
                  vel_range: tuple[int, int]) -> tuple[Tensor, Tensor, Tensor]:
    """Energy and gradient of one block of frames (coordinates first: x is (B, 3, V)).

    Args:
        x: (B, 3, V) float32 tracked vertices of the block plus up to 3 halo frames a side.
        rot: (B, 3, 3) float32; trans: (B, 3) float32.
        rest_neg: (3, V) float32, `-rest / width_pos`.
        inner: [a, b) block frames (indices into x) owning the position terms.
        inv_w_pos, inv_w_vel: 1 / widths.
        pos_scale, vel_scale: weights of the two sums (1 / N and lambda / N).
        vel_range: [a, b) velocity centres (indices into x), each with 3 frames a side.
    Returns:
        energy () float64, grad_rot (B, 3, 3), grad_trans (B, 3).
    """
    stab = torch.baddbmm(trans[:, :, None], rot, x)                           # (B, 3, V)
    a, b = inner
    z = torch.add(rest_neg, stab[a:b], alpha=inv_w_pos)                      # (S - R) / w
    e_pos, h = psi_sum_and_grad_(z)
    grad = torch.empty_like(stab)
    torch.mul(h, 4.0 * pos_scale * inv_w_pos, out=grad[a:b])
    grad[:a].zero_()
    grad[b:].zero_()
    energy = pos_scale * e_pos
    c0, c1 = vel_range
    if c1 > c0:
        a1, a2, a3 = (coef * inv_w_vel for coef in VELOCITY_COEFFS)
        zv = torch.sub(stab[c0 + 1:c1 + 1], stab[c0 - 1:c1 - 1]).mul_(a1)
        zv.add_(stab[c0 + 2:c1 + 2], alpha=a2).sub_(stab[c0 - 2:c1 - 2], alpha=a2)
        zv.add_(stab[c0 + 3:c1 + 3], alpha=a3).sub_(stab[c0 - 3:c1 - 3], alpha=a3)
        e_vel, hv = psi_sum_and_grad_(zv)
        energy = energy + vel_scale * e_vel
        for k, coef in enumerate(VELOCITY_COEFFS, start=1):
            alpha = 4.0 * vel_scale * coef * inv_w_vel
            grad[c0 + k:c1 + k].add_(hv, alpha=alpha)
            grad[c0 - k:c1 - k].sub_(hv, alpha=alpha)
    grad_rot = torch.bmm(grad, x.transpose(1, 2))
    grad_trans = grad.sum(2)
    return energy, grad_rot, grad_trans


@dataclass
class _EnergyData:
    """The fixed data of a fused energy: vertices (F, 3, V) float32 and settings."""

    x: Tensor
    rest: Tensor
    width_pos: float
    width_vel: float
    velocity_weight: float
    block_frames: int
    kernel: Callable[..., tuple[Tensor, Tensor, Tensor]] = _block_energy


def _fused_value_and_grad(data: _EnergyData, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    x = data.x
    f, _, v = x.shape
    rot32, trans32 = rot.to(x.dtype), trans.to(x.dtype)
    inv_w_pos, inv_w_vel = 1.0 / data.width_pos, 1.0 / data.width_vel
    rest_neg = data.rest * (-inv_w_pos)
    scale = 1.0 / (3 * f * v)
    grad_rot = torch.zeros(f, 3, 3, dtype=x.dtype, device=x.device)
    grad_trans = torch.zeros(f, 3, dtype=x.dtype, device=x.device)
    total = torch.zeros((), dtype=torch.float64, device=x.device)
    for start in range(0, f, data.block_frames):
        stop = min(f, start + data.block_frames)
        lo, hi = max(0, start - 3), min(f, stop + 3)
        c0, c1 = max(start, 3), min(stop, f - 3)
        energy, g_rot, g_trans = data.kernel(
            x[lo:hi], rot32[lo:hi], trans32[lo:hi], rest_neg, (start - lo, stop - lo),
            inv_w_pos, inv_w_vel, scale, scale * data.velocity_weight,
            (c0 - lo, max(c1, c0) - lo))
        total = total + energy
        grad_rot[lo:hi] += g_rot
        grad_trans[lo:hi] += g_trans
    # Velocities of the three first and last frames (lower-order stencils on 5 frames).
    head = torch.tensor(REDUCED_END_COEFFS, dtype=x.dtype, device=x.device)          # (3, 5)
    tail = -head.flip(0, 1)                                                           # frames F-3..F-1
    for coeffs, lo in ((head, 0), (tail, f - 5)):
        xs = x[lo:lo + 5]
        stab = torch.baddbmm(trans32[lo:lo + 5, :, None], rot32[lo:lo + 5], xs)        # (5, 3, V)
        z = torch.einsum("aj,jcv->acv", coeffs * inv_w_vel, stab)
        energy, h = psi_sum_and_grad_(z)
        total = total + scale * data.velocity_weight * energy
        grad = torch.einsum("aj,acv->jcv", coeffs * (4.0 * scale * data.velocity_weight * inv_w_vel), h)
        grad_rot[lo:lo + 5] += torch.bmm(grad, xs.transpose(1, 2))
        grad_trans[lo:lo + 5] += grad.sum(2)
    return total, grad_rot.to(rot.dtype), grad_trans.to(trans.dtype)


class _FusedEnergy(torch.autograd.Function):
    """Energy whose forward also computes the gradient (L-BFGS always needs both)."""

    @staticmethod
    def forward(ctx, rot: Tensor, trans: Tensor, data: _EnergyData) -> Tensor:  # type: ignore[override]
        total, grad_rot, grad_trans = _fused_value_and_grad(data, rot.detach(), trans.detach())
        ctx.save_for_backward(grad_rot, grad_trans)
        return total.to(rot.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        grad_rot, grad_trans = ctx.saved_tensors
        return grad_out * grad_rot, grad_out * grad_trans, None


def fused_stabilization_energy(vertices: Tensor, rot: Tensor, trans: Tensor, rest: Tensor, *,
                               width_pos: float, width_vel: float, velocity_weight: float,
                               block_frames: int = 0) -> Tensor:
    """Return the same value as `stabilization_energy`, computed by the fused block kernel.

    The gradient with respect to `rot` and `trans` is computed in the forward pass (no
    autograd graph over the vertices); `vertices` and `rest` are constants.

    Args:
        vertices: (F, V, 3) tracked vertices (converted once to (F, 3, V) float32).
        rot, trans, rest, width_pos, width_vel, velocity_weight: as `stabilization_energy`.
        block_frames: frames per block (0: about 2^18 coordinates per block).
    Returns:
        () energy in `rot`'s dtype, differentiable in `rot` and `trans`.
    """
    x = vertices.detach().to(torch.float32).permute(0, 2, 1).contiguous()
    data = _EnergyData(x, rest.detach().to(torch.float32).T.contiguous(), float(width_pos),
                       float(width_vel), float(velocity_weight),
                       block_frames or _default_block(x.shape[0], x.shape[2]))
    return _FusedEnergy.apply(rot, trans, data)


def _default_block(num_frames: int, num_vertices: int) -> int:
    return max(8, min(num_frames, (1 << 18) // max(1, 3 * num_vertices)))


# --------------------------------------------------------------------------------------
# Schedule
# --------------------------------------------------------------------------------------
class Stage(NamedTuple):
    """One L-BFGS restart.

    Attributes:
        width_pos: position width (cm).
        width_vel: velocity width (cm / frame).
        refine: refine the control polygon (midpoint) before this stage.
    """

    width_pos: float
    width_vel: float
    refine: bool


def make_schedule(position_widths: Sequence[float] = DEFAULT_POSITION_WIDTHS,
                  velocity_widths: Sequence[float] = DEFAULT_VELOCITY_WIDTHS,
                  refinements: int = 2) -> list[Stage]:
    """Return the continuation schedule: the widths in order, refinements interleaved.

    The K width pairs are walked once, coarse to fine. The `refinements` refinements are
    spread evenly over the stages after the first, so that the coarse spline takes the wide
    widths (large basin) and the finest one the narrow widths; when there are more
    refinements than widths, the last width pair is repeated after each extra refinement.

    Args:
        position_widths: K widths (cm), decreasing.
        velocity_widths: K widths (cm / frame).
        refinements: number of midpoint refinements R >= 0.
    Returns:
        max(K, R + 1) stages.

    Example:
        >>> [s.refine for s in make_schedule(refinements=2)]
        [False, False, True, False, True]
    """
    if len(position_widths) != len(velocity_widths) or not position_widths:
        raise ValueError(f"velocity_widths: expected as many widths as position_widths "
                         f"({len(position_widths)}), found {len(velocity_widths)}")
    if refinements < 0:
        raise ValueError(f"refinements: expected >= 0, found {refinements}")
    widths = list(zip(position_widths, velocity_widths))
    while len(widths) < refinements + 1:
        widths.append(widths[-1])
    k = len(widths)
    # Level of stage j: floor(j * (R + 1) / K), so level 0 first and level R last.
    levels = [j * (refinements + 1) // k for j in range(k)]
    return [Stage(float(wp), float(wv), j > 0 and levels[j] > levels[j - 1])
            for j, (wp, wv) in enumerate(widths)]


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
def farthest_point_sampling(points: Tensor, count: int) -> Tensor:
    """Pick `count` well-spread points, deterministically (greedy farthest-point sampling).

    Starts at the point nearest the centroid (not at a seeded random one, so the picks do not
    depend on a seed); each next pick maximises the distance to the picks so far (ties: lowest
    index). A tensor front end of `nodes.io.face_model.farthest_point_sampling`.

    Args:
        points: (N, 3) positions.
        count: number to pick (clipped to N).
    Returns:
        (min(count, N),) int64 indices on `points.device`, sorted ascending.
    """
    n = points.shape[0]
    if count >= n:
        return torch.arange(n, device=points.device)
    pts = points.detach().to(torch.float64)
    first = int(((pts - pts.mean(0)) ** 2).sum(1).argmin())
    picks = _farthest_point_sampling_np(pts.cpu().numpy(), count, first=first)
    return torch.from_numpy(picks).to(points.device)


def invert_rigid(matrices: Tensor) -> Tensor:
    """Return the inverses of rigid 4x4 matrices `[[R, t], [0, 1]] -> [[R^T, -R^T t], [0, 1]]`.

    The tensor twin of `nodes.rigid.kabsch.invert_rigid` (mode pursuit's transforms are tensors).

    Args:
        matrices: (..., 4, 4) rigid transforms.
    Returns:
        (..., 4, 4) inverses, same dtype.
    """
    rot_t = matrices[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(matrices)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ matrices[..., :3, 3:])[..., 0]
    out[..., 3, 3] = 1.0
    return out


def stabilize_vertices(vertices: np.ndarray, matrices: np.ndarray, *, block_frames: int = 256) -> np.ndarray:
    """Return `S_f = M_f^-1 X_f`: world vertices moved into the skull frame.

    Args:
        vertices: (F, V, 3) world vertices, cm.
        matrices: (F, 4, 4) float64 skull-to-world transforms.
        block_frames: frames per block (bounds the float64 temporaries).
    Returns:
        (F, V, 3) float32 skull-frame vertices, cm.
    """
    vertices = np.asarray(vertices)
    if vertices.ndim != 3 or vertices.shape[2] != 3:
        raise ValueError(f"vertices: expected shape (F, V, 3), found {vertices.shape}")
    if matrices.shape != (vertices.shape[0], 4, 4):
        raise ValueError(f"matrices: expected shape ({vertices.shape[0]}, 4, 4), found {matrices.shape}")
    out = np.empty(vertices.shape, dtype=np.float32)
    inverse = _invert_rigid_np(matrices)
    for a in range(0, vertices.shape[0], block_frames):
        b = min(vertices.shape[0], a + block_frames)
        out[a:b] = apply_rigid(inverse[a:b], vertices[a:b])
    return out


class ModePursuitResult(NamedTuple):
    """Output of `mode_pursuit`.

    Attributes:
        matrices: (F, 4, 4) float64 skull-to-world transforms (cm), `x_world = M_f x_skull`.
        rest: (E, 3) float32 rest positions (skull frame, cm) of the energy vertices.
        vertex_ids: (E,) int64 indices (into the input vertices) of the energy vertices.
        evaluations: number of energy + gradient evaluations.
        iterations: number of L-BFGS iterations (over all stages).
        stages: one dict per stage: width_pos, width_vel, spacing (frames), control_points,
            iterations, evaluations, energy_start, energy_end, seconds.
        seconds: wall time of the optimization.
    """

    matrices: np.ndarray
    rest: np.ndarray
    vertex_ids: np.ndarray
    evaluations: int
    iterations: int
    stages: list[dict]
    seconds: float


def _resolve_device(device: str | torch.device | None) -> torch.device:
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(device)


def _spline_transforms(control: Tensor, basis: SplineBasis) -> tuple[Tensor, Tensor]:
    return dualquat_to_rotmat_translation(evaluate_spline(control, basis))


def _update_rest(x: Tensor, rot: Tensor, trans: Tensor, rest: Tensor, width: float,
                 steps: int, block_frames: int) -> Tensor:
    """Mean-shift the rest toward each coordinate's mode of the stabilized positions.

    Each step is `R <- R + sum_f k(S - R) (S - R) / sum_f k(S - R)` with the flat kernel
    weights `k = [|S - R| < width / 2]` (the region where `psi` is quadratic), i.e. one
    exact minimisation of `sum_f psi_w(S_f - R)` over R when no sample leaves the quadratic
    zone. Coordinates with no sample near the rest keep it.
    """
    for _ in range(steps):
        num = torch.zeros_like(rest)
        den = torch.zeros_like(rest)
        for a in range(0, x.shape[0], block_frames):
            b = min(x.shape[0], a + block_frames)
            d = torch.baddbmm(trans[a:b, :, None], rot[a:b], x[a:b]).sub_(rest)
            inside = (d.abs() < 0.5 * width).to(d.dtype)
            num += (d * inside).sum(0)
            den += inside.sum(0)
        rest = rest + num / den.clamp(min=1.0)
    return rest


# --------------------------------------------------------------------------------------
# Optimizer
# --------------------------------------------------------------------------------------
def mode_pursuit(vertices: np.ndarray | Tensor, *, init: np.ndarray | Tensor | None = None,
                 rest: np.ndarray | Tensor | None = None,
                 vertex_ids: np.ndarray | Sequence[int] | None = None,
                 position_widths: Sequence[float] = DEFAULT_POSITION_WIDTHS,
                 velocity_widths: Sequence[float] = DEFAULT_VELOCITY_WIDTHS,
                 velocity_weight: float = 1.0, spacing: float = 8.0, refinements: int = 2,
                 iterations: int = 24, max_vertices: int = 2000, update_rest: bool = True,
                 history_size: int = 10, device: str | torch.device | None = "auto",
                 compile: bool = False, progress: ProgressFn | None = None) -> ModePursuitResult:
    """Stabilize a tracked mesh sequence by mode pursuit (see the module docstring).

    Minimises eq. 4 over the control dual quaternions of a cubic SDLB spline of the
    world-to-skull motion, by L-BFGS restarted at each stage of `make_schedule(...)`.

    Args:
        vertices: (F, V, 3) tracked vertices, world frame, cm; F >= 7.
        init: (F, 4, 4) initial skull-to-world transforms, or None for identity; the
            initial spline is its least-squares fit (on hemisphere-aligned dual quaternions).
        rest: (V, 3) rest mesh in the skull frame (cm), or None for the per-vertex median
            of the vertices moved by `init` into the skull frame.
        vertex_ids: indices of the vertices the energy uses (e.g. a face region), or None
            for all.
        position_widths: continuation widths for positions (cm), decreasing.
        velocity_widths: continuation widths for velocities (cm / frame), same count.
        velocity_weight: lambda, weight of the velocity sum.
        spacing: control-point spacing of the initial spline (frames).
        refinements: midpoint refinements during the schedule (final spacing is
            `spacing / 2**refinements`).
        iterations: L-BFGS iterations per stage (fixed; no convergence test).
        max_vertices: at most this many energy vertices, chosen by farthest-point sampling
            (deterministic) on the first frame.
        update_rest: re-estimate the rest (3 mean-shift steps at the stage's position width)
            before every stage after the first; ignored when `rest` is given.
        history_size: L-BFGS memory.
        device: "auto" (CUDA when available), "cpu", "cuda" or a torch device.
        compile: run the block kernel through `torch.compile` (pays a one-off compile).
        progress: optional callback `(fraction, message)`.
    Returns:
        ModePursuitResult.
    Raises:
        ValueError: bad shapes, fewer than 7 frames, out-of-range `vertex_ids`, bad settings.
    """
    started = time.perf_counter()
    verts = torch.as_tensor(np.asarray(vertices) if not isinstance(vertices, Tensor) else vertices)
    if verts.ndim != 3 or verts.shape[2] != 3:
        raise ValueError(f"vertices: expected shape (F, V, 3), found {tuple(verts.shape)}")
    num_frames, num_vertices = int(verts.shape[0]), int(verts.shape[1])
    if num_frames < 7:
        raise ValueError(f"vertices: expected at least 7 frames (the velocity stencil spans 7), "
                         f"found {num_frames}")
    if num_vertices < 3:
        raise ValueError(f"vertices: expected at least 3 vertices, found {num_vertices}")
    for name, value in (("velocity_weight", velocity_weight), ("refinements", refinements),
                        ("iterations", iterations)):
        if value < 0:
            raise ValueError(f"{name}: expected >= 0, found {value}")
    if not spacing >= 1.0:
        raise ValueError(f"spacing: expected >= 1 frame, found {spacing}")
    if spacing / 2 ** refinements < 1.0:
        raise ValueError(f"refinements: the final spacing {spacing} / 2^{refinements} would be "
                         f"below 1 frame; use at most {int(math.log2(spacing))} refinements")
    if any(not w > 0 for w in list(position_widths) + list(velocity_widths)):
        raise ValueError(f"position_widths/velocity_widths: expected positive widths, found "
                         f"{list(position_widths)} / {list(velocity_widths)}")
    if max_vertices < 3:
        raise ValueError(f"max_vertices: expected >= 3, found {max_vertices}")
    schedule = make_schedule(position_widths, velocity_widths, refinements)
    dev = _resolve_device(device)

    # -- energy vertices -----------------------------------------------------------------
    if vertex_ids is None:
        ids = torch.arange(num_vertices)
    else:
        ids = torch.as_tensor(np.asarray(vertex_ids, dtype=np.int64)).reshape(-1)
        if ids.numel() < 3:
            raise ValueError(f"vertex_ids: expected at least 3 vertices, found {ids.numel()}")
        if ids.min() < 0 or ids.max() >= num_vertices:
            raise ValueError(f"vertex_ids: expected indices in 0..{num_vertices - 1}, found "
                             f"{int(ids.min())}..{int(ids.max())}")
        ids = torch.unique(ids)

    # -- initial world-to-skull transforms (float64, cm) ---------------------------------
    if init is None:
        world_to_skull = torch.eye(4, dtype=torch.float64).expand(num_frames, 4, 4).clone()
    else:
        init_t = torch.as_tensor(np.asarray(init) if not isinstance(init, Tensor) else init).to(torch.float64)
        if init_t.shape != (num_frames, 4, 4):
            raise ValueError(f"init: expected shape ({num_frames}, 4, 4), found {tuple(init_t.shape)}")
        world_to_skull = invert_rigid(init_t.cpu())

    if ids.numel() > max_vertices:
        # Spread is rigid-invariant, so the first frame (world) serves as the shape to sample.
        ids = ids[farthest_point_sampling(verts[0, ids], max_vertices)]
    x_sel = verts[:, ids].to(torch.float32)                                   # (F, E, 3)
    rot0 = world_to_skull[:, :3, :3]

    # -- normalised coordinates: x~ = (x - centre) / scale (world and skull alike) --------
    centre = x_sel.mean(dim=(0, 1), dtype=torch.float64)
    scale = float(((x_sel - centre.float()) ** 2).sum(-1).mean().sqrt().clamp(min=1e-6))
    trans0 = (rot0 @ centre + world_to_skull[:, :3, 3] - centre) / scale
    x = ((x_sel - centre.float()) / scale).to(dev, torch.float32).permute(0, 2, 1).contiguous()  # (F, 3, E)
    del x_sel
    block = _default_block(num_frames, x.shape[2])

    # -- initial spline, at the finest spacing -----------------------------------------------
    final_spacing = float(spacing) / 2 ** refinements
    basis = frame_basis(num_frames, final_spacing, device=dev)
    if init is None:
        base = dualquat_identity(basis.num_control, dtype=torch.float64, device=dev)
    else:
        dq = dualquat_from_rotation_translation(rotmat_to_quat(rot0), trans0)
        dq = dualquat_align_hemisphere(dq, dim=0).to(dev)
        base = fit_control_points(dq, basis)

    # -- rest shape -------------------------------------------------------------------------
    if rest is not None:
        rest_t = torch.as_tensor(np.asarray(rest) if not isinstance(rest, Tensor) else rest).to(torch.float64)
        if rest_t.shape != (num_vertices, 3):
            raise ValueError(f"rest: expected shape ({num_vertices}, 3), found {tuple(rest_t.shape)}")
        rest_x = ((rest_t[ids] - centre) / scale).to(dev, torch.float32).T.contiguous()  # (3, E)
    else:
        with torch.no_grad():
            rot, trans = _spline_transforms(base, basis)
            stab0 = torch.baddbmm(trans.to(x.dtype)[:, :, None], rot.to(x.dtype), x)
            rest_x = stab0.median(dim=0).values.contiguous()                               # (3, E)
            del stab0

    kernel: Callable[..., tuple[Tensor, Tensor, Tensor]] = _block_energy
    if compile:
        kernel = torch.compile(_block_energy, dynamic=True)
    counters = {"evaluations": 0}
    total_iterations = 0
    stages_out: list[dict] = []
    level = 0

    def corrected(base: Tensor, delta: Tensor, from_level: int) -> Tensor:
        """Add a correction of level `from_level`, refined to the finest level, to `base`."""
        h = float(spacing) / 2 ** from_level
        for _ in range(from_level, refinements):
            h /= 2.0
            delta = refine_midpoint(delta)[:num_control_points(num_frames, h)]
        return base + delta

    for index, stage in enumerate(schedule):
        stage_started = time.perf_counter()
        level += int(stage.refine)
        current_spacing = float(spacing) / 2 ** level
        if update_rest and rest is None and index > 0:
            with torch.no_grad():
                rot, trans = _spline_transforms(base, basis)
            rest_x = _update_rest(x, rot.to(torch.float32), trans.to(torch.float32), rest_x,
                                  stage.width_pos / scale, 3, block)
        data = _EnergyData(x, rest_x, stage.width_pos / scale, stage.width_vel / scale,
                           float(velocity_weight), block, kernel)
        shape = (num_control_points(num_frames, current_spacing), 8)
        energies: list[float] = []

        def objective(flat: Tensor) -> tuple[float, Tensor]:
            delta = flat.view(shape).requires_grad_(True)
            rot, trans = _spline_transforms(corrected(base, delta, level), basis)
            energy = _FusedEnergy.apply(rot, trans, data)
            (grad,) = torch.autograd.grad(energy, delta)
            energies.append(float(energy.detach()))
            return energies[-1], grad.reshape(-1)

        zero = torch.zeros(shape[0] * shape[1], dtype=torch.float64, device=dev)
        flat, _, stage_iters = lbfgs(objective, zero, iterations=iterations,
                                     history_size=history_size) if iterations > 0 else (zero, 0.0, 0)
        counters["evaluations"] += len(energies)
        total_iterations += stage_iters
        with torch.no_grad():
            base = dualquat_normalize(corrected(base, flat.view(shape), level))
        stages_out.append({
            "width_pos": stage.width_pos, "width_vel": stage.width_vel,
            "spacing": current_spacing, "control_points": shape[0],
            "iterations": stage_iters,
            "evaluations": len(energies),
            "energy_start": energies[0] if energies else float("nan"),
            "energy_end": energies[-1] if energies else float("nan"),
            "seconds": time.perf_counter() - stage_started,
        })
        if progress is not None:
            progress((index + 1) / len(schedule),
                     f"stage {index + 1}/{len(schedule)}: width {stage.width_pos:g} cm, spacing "
                     f"{current_spacing:g} frames, energy {stages_out[-1]['energy_end']:.6g}")
    control = base

    # -- back to cm, skull-to-world ----------------------------------------------------------
    with torch.no_grad():
        rot, trans = _spline_transforms(control, basis)
    rot, trans = rot.cpu(), trans.cpu()
    # Orthonormalise in float64 (the quaternion is normalised, this only removes rounding).
    u, _, vh = torch.linalg.svd(rot)
    rot = u @ vh
    world_to_skull = torch.zeros(num_frames, 4, 4, dtype=torch.float64)
    world_to_skull[:, :3, :3] = rot
    world_to_skull[:, :3, 3] = scale * trans + centre - rot @ centre
    world_to_skull[:, 3, 3] = 1.0
    matrices = invert_rigid(world_to_skull)
    rest_cm = (rest_x.T.double().cpu() * scale + centre).to(torch.float32)
    return ModePursuitResult(matrices.numpy(), rest_cm.numpy(), ids.numpy().astype(np.int64),
                             counters["evaluations"], total_iterations, stages_out,
                             time.perf_counter() - started)
