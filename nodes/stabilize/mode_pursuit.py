"""Mode-pursuit stabilization: the optimizer (the energy is in `energy.py`, the schedule in
`schedule.py`).

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
`schedule.make_schedule`).

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
    one fused pass over blocks of frames (`energy.fused_energy`: no autograd graph over
    F x V x 3 tensors; blocks of about 2^18 coordinates stay in cache and bound the memory);
    autograd only runs over the small spline (F x 8). `torch.compile` of the block kernel is optional (`compile=True`).
  - The energy uses at most `max_vertices` vertices (default 2000), chosen by farthest-point
    sampling on the first frame (spread is rigid-invariant; deterministic); the result is
    applied to every vertex afterwards, in blocks of frames.
  - L-BFGS is our own (`lbfgs.py`, same algorithm as `torch.optim.LBFGS`): constructing a
    torch optimizer imports `torch._dynamo` (about 2 s per process).
  - On the CPU the robust per-frame alignments (every IRLS step: distances, lower quartile,
    weights and Kabsch moments), the stillness test and the still refinement's gather are numba
    kernels, one pass over the points each (`robust_kernels.py`; `kernels=False` runs the
    torch ops): on the whole head (651 x 26,719) mode pursuit's CPU time went from 5.8 to
    about 2.3 s at one thread, the same median error.

Last, every frame is re-aligned on the vertices still over the whole shot and around that
frame (`still_refinement`): frame by frame, expression motion smaller than the final width
looks like noise; averaged over a few frames it does not.

Conventions: cm, frames; `matrices[f]` is skull-to-world (`x_world = M_f x_skull`), so
`r_f = M_f^-1`.
"""

from __future__ import annotations

import math
import time
from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch
from torch import Tensor

from ..geometry.bspline import (SplineBasis, evaluate_spline, fit_control_points, frame_basis,
                                num_control_points, refine_midpoint)
from ..geometry.dualquat import (dualquat_align_hemisphere, dualquat_from_rotation_translation,
                                 dualquat_identity, dualquat_normalize, dualquat_to_rotmat_translation,
                                 rotmat_to_quat)
from ..geometry.rigid import invert_rigid_torch
from ..geometry.sampling import farthest_point_sampling_torch
from .energy import EnergyData, block_energy, default_block_frames, fused_energy
from .lbfgs import lbfgs
from .robust import (apply_transforms, frame_blocks, locally_still, lower_median, noise_level, residual_scale,
                     rest_mode, robust_align, still_vertices)
from .schedule import DEFAULT_POSITION_WIDTHS, DEFAULT_VELOCITY_WIDTHS, Stage, StageLog, make_schedule

__all__ = ["ModePursuitResult", "AdaptivePlan", "adaptive_plan", "mode_pursuit"]

ProgressFn = Callable[[float, str], None]


# --------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------
class ModePursuitResult(NamedTuple):
    """Output of `mode_pursuit`.

    Attributes:
        matrices: (F, 4, 4) float64 skull-to-world transforms (cm), `x_world = M_f x_skull`.
        rest: (E, 3) float32 rest positions (skull frame, cm) of the energy vertices.
        vertex_ids: (E,) int64 indices (into the input vertices) of the energy vertices.
        evaluations: number of energy + gradient evaluations.
        iterations: number of L-BFGS iterations (over all stages).
        stages: one `StageLog` per stage of the schedule.
        seconds: wall time of the optimization.
        plan: how the adaptive schedule was chosen (None for `schedule="fixed"`).
    """

    matrices: np.ndarray
    rest: np.ndarray
    vertex_ids: np.ndarray
    evaluations: int
    iterations: int
    stages: list[StageLog]
    seconds: float
    plan: "AdaptivePlan | None" = None


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


def _still_refinement(verts: Tensor, candidates: Tensor, centre: Tensor, scale: float, rot: Tensor,
                      trans: Tensor, prior: Tensor | None, *, sigma: float, width: float, window: int,
                      iterations: int, rounds: int = 3, max_points: int = 1 << 23,
                      kernels: bool = True) -> tuple[Tensor, Tensor]:
    """Re-align every frame on the vertices that stay still over the whole shot and around it.

    The bounded penalty cannot tell noise from expression motion smaller than its width (about
    5 noise std): at 0.1 cm noise, millimetres of expression motion count as rest and pull the
    frames. Here every candidate vertex (not only the energy's sample; a strided subset when
    F x V exceeds `max_points`) is stabilized by the current transforms, and the vertices still
    up to the noise over the whole shot are found (`robust.still_vertices`). That test averages
    over the shot, so an expression held in a minority of the frames passes it while it moves
    its vertices by a millimetre in those frames (whole head, 300 frames at 0.1 cm noise, seed 0:
    mouthPress_R over frames 224-275 moved 3,000 of the 16,000 still vertices by more than
    0.5 mm and carried the p95 error, 0.0143 cm against 0.0128 for Procrustes on 'rigid').
    So each of `rounds` rounds also asks, frame by frame, which of them are at their rest
    around that frame (`robust.locally_still`, the residual averaged over 2 `window` + 1
    frames), takes each vertex's rest as its mean over the frames where it is, and aligns each
    frame on its locally still vertices (`robust.robust_align` at the final width, per-frame
    weights). Each round starts from the previous round's transforms: the first removes most of
    the pull, which lets the next one see the moving vertices better (same case, p95: 0.0129
    and 0.0084 cm after 1 and 2 rounds averaging 15 frames, 0.0066 after 3 rounds averaging 31
    as shipped; 3 rounds with the whole-shot weights alone stay at 0.0143). Nothing changes when fewer than max(10, V / 10)
    vertices are still.

    Args:
        verts: (F, V, 3) input vertices, cm. candidates: (N,) vertex indices to consider.
        centre, scale: the optimizer's normalisation (x~ = (x - centre) / scale).
        rot, trans: (F, 3, 3), (F, 3) current world-to-skull transforms (normalised units).
        prior: (V,) vertex weights or None. sigma, width: noise std and final width (normalised).
        window: frames averaged by the stillness test; the per-frame test averages
            2 min(window, F / 10) + 1. iterations: IRLS steps per round.
        rounds: per-frame stillness test, rest and alignment, repeated from the new transforms.
        kernels: numba kernels on the CPU (see `mode_pursuit`).
    Returns:
        rot, trans (float64), refined or unchanged.
    """
    num_frames = verts.shape[0]
    step = max(1, math.ceil(num_frames * candidates.numel() / max_points))
    ids = candidates[::step]
    dev = rot.device
    if kernels and verts.device.type == "cpu":  # one pass (the torch ops below make five)
        from .robust_kernels import gather_normalized

        x = torch.empty(num_frames, 3, ids.numel(), dtype=torch.float32)
        source, out = verts.contiguous().numpy(), x.numpy()
        index, origin = ids.contiguous().numpy(), centre.double().contiguous().numpy()
        frame_blocks(lambda lo, hi: gather_normalized(source[lo:hi], index, origin, float(scale), out[lo:hi]),
                     num_frames)
        x = x.to(dev)
    else:
        x = ((verts[:, ids].to(torch.float64) - centre) / scale).to(dev, torch.float32).permute(0, 2, 1).contiguous()
    stab = apply_transforms(x, rot, trans)
    still = still_vertices(stab, sigma, window=window, centre=lower_median(stab, dim=0), kernels=kernels)
    if int(still.sum()) < max(10, ids.numel() // 10):
        return rot, trans
    x = x[:, :, still].contiguous()
    stab = stab[:, :, still]
    prior_still = None if prior is None else prior[ids][still.cpu()].to(dev)
    # Rounds: which vertices are still around each frame, their rest (mean over the frames
    # where they are), every frame aligned to it; then again from the new transforms.
    half_window = min(window, num_frames // 10)
    rest = stab.mean(dim=0)
    for round_index in range(rounds):
        local = locally_still(stab - rest, sigma, half_window=half_window, kernels=kernels).to(dev)
        rest = torch.einsum("fcv,fv->cv", stab, local) / local.sum(0).clamp(min=1.0)
        weights = local if prior_still is None else local * prior_still
        aligned = robust_align(x, rest, rot, trans, width, iterations=max(iterations, 1), vertex_weights=weights,
                               kernels=kernels)
        rot, trans = aligned.rot, aligned.trans
        if round_index < rounds - 1:
            stab = apply_transforms(x, rot, trans)
    return rot, trans


# --------------------------------------------------------------------------------------
# Adaptive schedule
# --------------------------------------------------------------------------------------
class AdaptivePlan(NamedTuple):
    """How the adaptive schedule was chosen (cm, frames), reported in progress and results.

    Attributes:
        noise_cm: estimated tracking-noise std (cm), from second differences over frames of
            the robustly aligned vertices (`robust.noise_level`).
        init_width_cm: width of the last robust per-frame alignment round (cm).
        position_widths: spline-stage position widths (cm): `noise_multiple * noise_cm`, not
            below `min_width`.
        velocity_widths: spline-stage velocity widths (cm / frame), a quarter of the position
            widths (the paper's ratio).
        spacing: control-point spacing of the spline (frames), `clip((F - 1) / 4, 1, 4)`.
        velocity_weight: lambda used (the given one; 0 when the shot is too short for the
            7-tap stencil, F < 7).
        spline: whether spline stages ran (False for F < 7: per-frame alignment only).
    """

    noise_cm: float
    init_width_cm: float
    position_widths: tuple[float, ...]
    velocity_widths: tuple[float, ...]
    spacing: float
    velocity_weight: float
    spline: bool


def adaptive_plan(noise_cm: float, init_width_cm: float, num_frames: int, *,
                  noise_multiple: float = 5.0, min_width: float = 0.02,
                  velocity_weight: float = 1.0) -> AdaptivePlan:
    """Choose the spline stages from the data: widths from the noise, spacing from the length.

    The width is `w_end = max(noise_multiple * noise_cm, min_width)`: below a few noise std
    the bounded penalty saturates on noise and the energy goes flat. There is one spline stage
    at `w_end`: the robust per-frame alignment before it already walked its own widths down to
    about `init_width_cm` (about 5 noise std) and brought every frame near the mode, so the
    paper's coarse widths are not needed (on the bench situations a `[2 w_end, w_end]`
    schedule was no more accurate and twice as slow).
    The spacing is `clip((F - 1) / 4, 1, 4)` frames, so a short shot keeps at least about 7
    control points; shots under 7 frames get no spline stage (the velocity stencil needs 7).

    Args:
        noise_cm: estimated noise std (cm).
        init_width_cm: width reached by the robust per-frame alignment (cm).
        num_frames: F.
        noise_multiple: w_end in noise std.
        min_width: smallest final width (cm).
        velocity_weight: lambda.
    Returns:
        AdaptivePlan.

    Example:
        >>> adaptive_plan(0.01, 0.05, 651).position_widths
        (0.05,)
    """
    w_end = max(noise_multiple * noise_cm, min_width)
    widths = (w_end,)
    spline = num_frames >= 7
    return AdaptivePlan(float(noise_cm), float(init_width_cm), widths, tuple(w / 4.0 for w in widths),
                        float(min(4.0, max(1.0, (num_frames - 1) / 4.0))),
                        float(velocity_weight) if spline else 0.0, spline)


# --------------------------------------------------------------------------------------
# Optimizer
# --------------------------------------------------------------------------------------
def _spline_stages(x: Tensor, base: Tensor, basis: SplineBasis, rest_x: Tensor, schedule: list[Stage],
                   *, scale: float, spacing: float, refinements: int, velocity_weight: float,
                   iterations: int, history_size: int, update_rest: bool, block: int,
                   kernel: Callable[..., tuple[Tensor, Tensor, Tensor]],
                   progress: Callable[[int, StageLog], None] | None) -> tuple[Tensor, Tensor, list[StageLog]]:
    """Run the L-BFGS stages of `schedule` on the spline; return (control, rest, stage logs)."""
    num_frames = x.shape[0]
    stages_out: list[StageLog] = []
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
        if update_rest and index > 0:
            with torch.no_grad():
                rot, trans = _spline_transforms(base, basis)
            rest_x = _update_rest(x, rot.to(torch.float32), trans.to(torch.float32), rest_x,
                                  stage.width_pos / scale, 3, block)
        data = EnergyData(x, rest_x, stage.width_pos / scale, stage.width_vel / scale,
                          float(velocity_weight), block, kernel)
        shape = (num_control_points(num_frames, current_spacing), 8)
        energies: list[float] = []

        def objective(flat: Tensor) -> tuple[float, Tensor]:
            delta = flat.view(shape).requires_grad_(True)
            rot, trans = _spline_transforms(corrected(base, delta, level), basis)
            energy = fused_energy(rot, trans, data)
            (grad,) = torch.autograd.grad(energy, delta)
            energies.append(float(energy.detach()))
            return energies[-1], grad.reshape(-1)

        zero = torch.zeros(shape[0] * shape[1], dtype=torch.float64, device=x.device)
        flat, _, stage_iters = lbfgs(objective, zero, iterations=iterations,
                                     history_size=history_size) if iterations > 0 else (zero, 0.0, 0)
        with torch.no_grad():
            base = dualquat_normalize(corrected(base, flat.view(shape), level))
        stages_out.append(StageLog(
            width_pos=stage.width_pos, width_vel=stage.width_vel,
            spacing=current_spacing, control_points=shape[0],
            iterations=stage_iters,
            evaluations=len(energies),
            energy_start=energies[0] if energies else float("nan"),
            energy_end=energies[-1] if energies else float("nan"),
            seconds=time.perf_counter() - stage_started,
        ))
        if progress is not None:
            progress(index, stages_out[-1])
    return base, rest_x, stages_out


def _robust_initialization(x: Tensor, rot: Tensor, trans: Tensor, rest_x: Tensor | None,
                           vertex_weights: Tensor | None, *, rounds: int, min_width: float,
                           kernels: bool = True) -> tuple[Tensor, Tensor, Tensor, float]:
    """Robust per-frame alignment to a rest estimate, alternating with the rest's mode.

    Round k: width `w_k = max(3 median_{f,v} |S_fv - R_v|, min_width)`, two IRLS steps of
    `robust.robust_align` at `w_k`, then (unless the rest is given) the rest moves to the
    per-vertex mode at radius `w_k / 2` (`robust.rest_mode`; a full candidate search in
    round 2, once the frames are roughly aligned, mean shift from the previous rest otherwise). Round 0 starts from the
    median of the initially stabilized vertices, so the first widths are wide (nearly least
    squares) when the initialization is poor (identity under large head motion); the widths
    then shrink to about 5 noise std. Units are those of `x`.

    Returns:
        rot (F, 3, 3) float64, trans (F, 3) float64, rest (3, E), last width.
    """
    fixed_rest = rest_x is not None
    if rest_x is None:
        rest_x = lower_median(apply_transforms(x, rot, trans), dim=0).contiguous()
    width = float("inf")
    for r in range(rounds):
        dist = apply_transforms(x, rot, trans).sub_(rest_x).square_().sum(1).sqrt_()
        width = max(3.0 * residual_scale(dist), min_width)
        del dist
        aligned = robust_align(x, rest_x, rot, trans, width, iterations=2, vertex_weights=vertex_weights,
                               kernels=kernels)
        rot, trans = aligned.rot, aligned.trans
        if not fixed_rest:
            stab = apply_transforms(x, rot, trans)
            search = r == min(2, rounds - 1)
            rest_x = rest_mode(stab, 0.5 * width, start=None if search else rest_x).contiguous()
            del stab
    return rot, trans, rest_x, width


def mode_pursuit(vertices: np.ndarray | Tensor, *, init: np.ndarray | Tensor | None = None,
                 rest: np.ndarray | Tensor | None = None,
                 vertex_ids: np.ndarray | Sequence[int] | None = None,
                 vertex_weights: np.ndarray | Sequence[float] | None = None,
                 schedule: str = "adaptive",
                 position_widths: Sequence[float] = DEFAULT_POSITION_WIDTHS,
                 velocity_widths: Sequence[float] = DEFAULT_VELOCITY_WIDTHS,
                 velocity_weight: float = 1.0, spacing: float = 8.0, refinements: int = 2,
                 iterations: int | None = None, max_vertices: int = 2000, update_rest: bool = True,
                 noise_multiple: float = 5.0, min_width: float = 0.02, init_rounds: int = 6,
                 polish_iterations: int = 3, still_refinement: bool = True, still_window: int = 15,
                 history_size: int = 10, device: str | torch.device | None = "auto",
                 compile: bool = False, kernels: bool = True,
                 progress: ProgressFn | None = None) -> ModePursuitResult:
    """Stabilize a tracked mesh sequence by mode pursuit (see the module docstring).

    Minimises eq. 4 over the control dual quaternions of a cubic SDLB spline of the
    world-to-skull motion, by L-BFGS restarted at each stage of the schedule.

    Args:
        vertices: (F, V, 3) tracked vertices, world frame, cm; F >= 7 for `schedule="fixed"`,
            F >= 1 for "adaptive" (under 7 frames: robust per-frame alignment only).
        init: (F, 4, 4) initial skull-to-world transforms, or None for identity. "fixed": the
            initial spline is its least-squares fit (on hemisphere-aligned dual quaternions);
            "adaptive": only the start of the robust per-frame alignment (the result does
            not depend on it beyond rounding, for any reasonable start).
        rest: (V, 3) rest mesh in the skull frame (cm), or None to estimate it ("fixed": the
            per-vertex median of the vertices moved by `init`; "adaptive": the per-vertex
            mode, see `robust.rest_mode`).
        vertex_ids: indices of the vertices the energy uses (e.g. a face region), or None
            for all.
        vertex_weights: (V,) prior weight of each vertex >= 0 ("adaptive" only: robust
            alignment and polish), e.g. 2 on a rigid region and 1 elsewhere; None = 1.
        schedule: "adaptive" (default; see `adaptive_plan` and the module docstring) or
            "fixed" (the paper's method: the given widths, spacing, refinements).
        position_widths: "fixed": continuation widths for positions (cm), decreasing.
        velocity_widths: "fixed": continuation widths for velocities (cm / frame), same count.
        velocity_weight: lambda, weight of the velocity sum.
        spacing: "fixed": control-point spacing of the initial spline (frames).
        refinements: "fixed": midpoint refinements during the schedule (final spacing is
            `spacing / 2**refinements`).
        iterations: L-BFGS iterations per stage (fixed; no convergence test); None = 12 for
            "adaptive" (its stages start near the optimum), 24 for "fixed" (the paper's count).
        max_vertices: at most this many energy vertices, chosen by farthest-point sampling
            (deterministic) on the first frame.
        update_rest: re-estimate the rest (3 mean-shift steps at the stage's position width)
            before every stage after the first; ignored when `rest` is given.
        noise_multiple: "adaptive": final width in estimated noise std.
        min_width: "adaptive": smallest width of any stage (cm).
        init_rounds: "adaptive": rounds of robust per-frame alignment and rest estimation.
        polish_iterations: "adaptive": IRLS steps of the final per-frame robust alignment to
            the rest at the final width (0 = none).
        still_refinement: "adaptive": after the polish, re-align every frame on the vertices
            (all of `vertex_ids`, not only the energy's sample) that stay still up to the
            estimated noise over the whole shot (`robust.still_vertices`) and around each frame
            (`robust.locally_still`, see `_still_refinement`). At 0.1 cm noise the
            final width (0.5 cm) lets millimetres of expression motion count as rest; this
            step removes that bias (whole ICT head, 150 frames: median 0.0045 -> 0.0013 cm,
            Procrustes on the 'rigid' group 0.0053). Needs F >= 30.
        still_window: frames averaged by the stillness test (noise averages out, expressions
            do not); at most F / 10, so the shot holds at least 10 windows.
        history_size: L-BFGS memory.
        device: "auto" (CUDA when available), "cpu", "cuda" or a torch device.
        compile: run the block kernel through `torch.compile` (pays a one-off compile).
        kernels: on the CPU, the robust alignments, the stillness test and the still
            refinement's gather run as numba kernels (`robust_kernels.py`: one pass over the
            points per step, float64 sums); False: as torch ops (results agree to ~1e-6 cm).
        progress: optional callback `(fraction, message)`.
    Returns:
        ModePursuitResult.
    Raises:
        ValueError: bad shapes, too few frames, out-of-range `vertex_ids`, bad settings.
    """
    started = time.perf_counter()
    verts = torch.as_tensor(np.asarray(vertices) if not isinstance(vertices, Tensor) else vertices)
    if verts.ndim != 3 or verts.shape[2] != 3:
        raise ValueError(f"vertices: expected shape (F, V, 3), found {tuple(verts.shape)}")
    num_frames, num_vertices = int(verts.shape[0]), int(verts.shape[1])
    if schedule not in ("adaptive", "fixed"):
        raise ValueError(f"schedule: expected 'adaptive' or 'fixed', found {schedule!r}")
    adaptive = schedule == "adaptive"
    if num_frames < (1 if adaptive else 7):
        raise ValueError(f"vertices: expected at least {1 if adaptive else 7} frames"
                         f"{'' if adaptive else ' (the velocity stencil spans 7)'}, found {num_frames}")
    if num_vertices < 3:
        raise ValueError(f"vertices: expected at least 3 vertices, found {num_vertices}")
    if iterations is None:
        iterations = 12 if adaptive else 24
    for name, value in (("velocity_weight", velocity_weight), ("refinements", refinements),
                        ("iterations", iterations), ("init_rounds", init_rounds),
                        ("polish_iterations", polish_iterations)):
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
    if not (noise_multiple > 0 and min_width > 0):
        raise ValueError(f"noise_multiple, min_width: expected > 0, found {noise_multiple}, {min_width}")
    if max_vertices < 3:
        raise ValueError(f"max_vertices: expected >= 3, found {max_vertices}")
    fixed_schedule = make_schedule(position_widths, velocity_widths, refinements)
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
    prior = None
    if vertex_weights is not None:
        prior = torch.as_tensor(np.asarray(vertex_weights, dtype=np.float32)).reshape(-1)
        if prior.numel() != num_vertices or not bool(torch.isfinite(prior).all()) or bool((prior < 0).any()):
            raise ValueError(f"vertex_weights: expected {num_vertices} finite weights >= 0, found "
                             f"{prior.numel()} (min {float(prior.min()) if prior.numel() else 'n/a'})")

    # -- initial world-to-skull transforms (float64, cm) ---------------------------------
    if init is None:
        world_to_skull = torch.eye(4, dtype=torch.float64).expand(num_frames, 4, 4).clone()
    else:
        init_t = torch.as_tensor(np.asarray(init) if not isinstance(init, Tensor) else init).to(torch.float64)
        if init_t.shape != (num_frames, 4, 4):
            raise ValueError(f"init: expected shape ({num_frames}, 4, 4), found {tuple(init_t.shape)}")
        world_to_skull = invert_rigid_torch(init_t.cpu())

    candidates = ids
    if ids.numel() > max_vertices:
        # Spread is rigid-invariant, so the first frame (world) serves as the shape to sample.
        ids = ids[farthest_point_sampling_torch(verts[0, ids], max_vertices)]
    x_sel = verts[:, ids].to(torch.float32)                                   # (F, E, 3)
    rot0 = world_to_skull[:, :3, :3]

    # -- normalised coordinates: x~ = (x - centre) / scale (world and skull alike) --------
    centre = x_sel.mean(dim=(0, 1), dtype=torch.float64)
    scale = float(((x_sel - centre.float()) ** 2).sum(-1).mean().sqrt().clamp(min=1e-6))
    trans0 = (rot0 @ centre + world_to_skull[:, :3, 3] - centre) / scale
    x = ((x_sel - centre.float()) / scale).to(dev, torch.float32).permute(0, 2, 1).contiguous()  # (F, 3, E)
    del x_sel
    block = default_block_frames(num_frames, x.shape[2])

    rest_x: Tensor | None = None
    if rest is not None:
        rest_t = torch.as_tensor(np.asarray(rest) if not isinstance(rest, Tensor) else rest).to(torch.float64)
        if rest_t.shape != (num_vertices, 3):
            raise ValueError(f"rest: expected shape ({num_vertices}, 3), found {tuple(rest_t.shape)}")
        rest_x = ((rest_t[ids] - centre) / scale).to(dev, torch.float32).T.contiguous()  # (3, E)

    kernel: Callable[..., tuple[Tensor, Tensor, Tensor]] = block_energy
    if compile:
        kernel = torch.compile(block_energy, dynamic=True)

    plan: AdaptivePlan | None = None
    if adaptive:
        weights_e = None if prior is None else prior[ids].to(dev)
        rot_a, trans_a, rest_x, init_width = _robust_initialization(
            x, rot0.to(dev), trans0.to(dev), rest_x, weights_e, rounds=max(init_rounds, 1),
            min_width=min_width / scale, kernels=kernels)
        noise = noise_level(apply_transforms(x, rot_a, trans_a)) * scale
        plan = adaptive_plan(noise, init_width * scale, num_frames, noise_multiple=noise_multiple,
                             min_width=min_width, velocity_weight=velocity_weight)
        stages = make_schedule(plan.position_widths, plan.velocity_widths, 0) if plan.spline else []
        total_steps = len(stages) + 2
        if progress is not None:
            progress(1.0 / total_steps,
                     f"robust per-frame alignment: width {plan.init_width_cm:.3g} cm; noise "
                     f"{plan.noise_cm:.3g} cm -> widths {', '.join(f'{w:.3g}' for w in plan.position_widths)} "
                     f"cm (final = max({noise_multiple:g} x noise, {min_width:g})), spacing "
                     f"{plan.spacing:g} frames" + ("" if plan.spline else "; under 7 frames: no spline stage"))
        final_width = plan.position_widths[-1]
        spline_spacing, spline_refinements = plan.spacing, 0
        lam = plan.velocity_weight
        fit_rot, fit_trans = rot_a, trans_a
        stage_update_rest = update_rest and rest is None
    else:
        stages = fixed_schedule
        total_steps = len(stages)
        spline_spacing, spline_refinements, lam = float(spacing), refinements, velocity_weight
        fit_rot, fit_trans = rot0, trans0
        stage_update_rest = update_rest and rest is None

    def report(index: int, log: StageLog) -> None:
        if progress is not None:
            done = index + 1 + (1 if adaptive else 0)
            progress(done / total_steps,
                     f"stage {index + 1}/{len(stages)}: width {log.width_pos:g} cm, spacing "
                     f"{log.spacing:g} frames, energy {log.energy_end:.6g}")

    stages_out: list[StageLog] = []
    evaluations = iterations_done = 0
    if stages:
        # -- initial spline, at the finest spacing -------------------------------------------
        final_spacing = float(spline_spacing) / 2 ** spline_refinements
        basis = frame_basis(num_frames, final_spacing, device=dev)
        if not adaptive and init is None:
            base = dualquat_identity(basis.num_control, dtype=torch.float64, device=dev)
        else:
            dq = dualquat_from_rotation_translation(rotmat_to_quat(fit_rot.double().cpu()),
                                                    fit_trans.double().cpu())
            dq = dualquat_align_hemisphere(dq, dim=0).to(dev)
            base = fit_control_points(dq, basis)
        if rest_x is None:
            with torch.no_grad():
                rot, trans = _spline_transforms(base, basis)
                stab0 = torch.baddbmm(trans.to(x.dtype)[:, :, None], rot.to(x.dtype), x)
                rest_x = lower_median(stab0, dim=0).contiguous()                         # (3, E)
                del stab0
        control, rest_x, stages_out = _spline_stages(
            x, base, basis, rest_x, stages, scale=scale, spacing=spline_spacing,
            refinements=spline_refinements, velocity_weight=lam, iterations=iterations,
            history_size=history_size, update_rest=stage_update_rest, block=block, kernel=kernel,
            progress=report)
        evaluations = sum(s.evaluations for s in stages_out)
        iterations_done = sum(s.iterations for s in stages_out)
        with torch.no_grad():
            rot, trans = _spline_transforms(control, basis)
    else:
        rot, trans = fit_rot, fit_trans
    assert rest_x is not None
    if adaptive and polish_iterations > 0:
        # -- polish: per-frame robust alignment to the mode at the final width ------------------
        aligned = robust_align(x, rest_x, rot.to(dev), trans.to(dev), final_width / scale,
                               iterations=polish_iterations, vertex_weights=weights_e, kernels=kernels)
        rot, trans = aligned.rot, aligned.trans
        # at least 10 windows over the shot, so the stillness statistic is not noise itself
        window = min(still_window, num_frames // 10)
        if still_refinement and plan is not None and plan.noise_cm > 0 and window >= 3:
            rot, trans = _still_refinement(verts, candidates, centre, scale, rot, trans, prior,
                                           sigma=plan.noise_cm / scale, width=final_width / scale,
                                           window=window, iterations=polish_iterations, kernels=kernels)
        if progress is not None:
            progress(1.0, f"polished every frame: robust alignment to the rest at {final_width:.3g} cm")

    # -- back to cm, skull-to-world ----------------------------------------------------------
    rot, trans = rot.double().cpu(), trans.double().cpu()
    # Orthonormalise in float64 (the quaternion is normalised, this only removes rounding).
    u, _, vh = torch.linalg.svd(rot)
    rot = u @ vh
    world_to_skull = torch.zeros(num_frames, 4, 4, dtype=torch.float64)
    world_to_skull[:, :3, :3] = rot
    world_to_skull[:, :3, 3] = scale * trans + centre - rot @ centre
    world_to_skull[:, 3, 3] = 1.0
    matrices = invert_rigid_torch(world_to_skull)
    rest_cm = (rest_x.T.double().cpu() * scale + centre).to(torch.float32)
    return ModePursuitResult(matrices.numpy(), rest_cm.numpy(), ids.numpy().astype(np.int64),
                             evaluations, iterations_done, stages_out,
                             time.perf_counter() - started, plan)
