"""The staged deep-energy solve of pose and expression (the paper's section 8), vectorized
over the frames of a chunk.

Each stage minimizes `nodes.fit.energy.landmark_energy` (+ the L2 prior on the active
shapes) over a subset of the unknowns with Levenberg-Marquardt per frame, starting from
the previous stage:

- rigid (`RIGID_STAGES`): translation on the non-jaw landmarks; rotation and translation on
  the non-jaw, then the jaw, then all landmarks;
- expression (`expression_stages`): jaw open only (lips weighted up), all jaw shapes, then
  all jaw and mouth shapes together with the rigid pose; the L2 prior `lambda sum w^2`;
- eyes (`eye_stage`, where the plate's iris centres are known): the eight eyeLook shapes, with
  the two iris centres as two more points (`nodes.fit.energy.iris_points`: the eyeballs turned by
  the weights, re-linearized at every step; no render offset) and their own, weaker prior.

Solver (`fit_stages`): the render landmarks `q = N(F(x_R))` are linearized about the
current estimate through *anchors* (`nodes.fit.views`): the head is rendered, the network
reads the render, and each of its points is tied to the surface point under it (triangle +
barycentrics + a residual offset). Within an outer iteration the stages move the anchored
points, whose projections change with the pose and shapes exactly as the network's points
do to first order (the network tracks the surface); the next outer iteration renders and
reads again. This is Gauss-Newton on the deep energy with the network's Jacobian replaced
by the anchors' (one render and one forward pass per outer iteration, no backward pass
through the network). `refine_backprop` is the paper's literal solver: gradient steps on
`|N(F*) - N(F(x_R))|^2` backpropagated through the network and the renderer.

Rotation is `R = exp([omega]) R0` (axis-angle `omega`, radians, about the model's origin),
translation `t` in cm; weights are kept in [0, 1] by a stiff quadratic penalty.
Torch is imported at the top: import this module from node `run()` methods only.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..geometry.image import crop_to_image
from ..geometry.lm import LMSchedule, levenberg_marquardt, normal_products
from ..geometry.rotation import rotmat_to_quat_torch
from ..landmarks.correspondence import MEDIAPIPE_TO_68
from .energy import (EDGES_68, IRIS_CORNERS_68, _skew, axis_angle_to_rotmat, eye_look_shapes, iris_points,
                     iris_relative, landmark_energy, landmark_weights, posed_anchor_points, project_views,
                     project_views_jacobian)
from .photometric import PhotoSamples, PhotoTerm, photometric_samples
from .views import (Anchors, FitModel, FitViews, anchors_from_render, at_anchors, landmark_anchors, network_points,
                    render_crops)

__all__ = ["Stage", "PoseState", "RIGID_STAGES", "expression_stages", "eye_stage", "jaw_shapes", "mouth_shapes",
           "initial_pose", "predicted_points", "solve_stage", "fit_stages", "refine_backprop", "RETRY_YAWS",
           "frames_of", "retry_from_starts"]

BOUND_PENALTY = 1e4
"""Weight of the quadratic penalty that keeps expression weights in [0, 1]."""

SOLVE_DTYPE = torch.float64
"""Precision of the Levenberg-Marquardt solves (residuals, Jacobians, normal equations). In float32
the sums over the landmarks' and photometric samples' residuals round differently with the number
of threads (torch splits a reduction across them), and a solve in a flat valley turns that
rounding into a different answer (issue 30); in float64 the rounding is 1e-9 times smaller.
Renders and the network's readings stay float32."""

STAGE_SCHEDULE = LMSchedule(lam0=1e-3, down=0.3, up=10.0, lam_min=1e-7, lam_max=1e8, tries=6, rel_tol=1e-4,
                            diag_floor=1e-9, floor=1e-9)
"""`nodes.geometry.lm`'s schedule for the stage and identity solves: lambda x 0.3 after a step that
lowers a frame's energy, x 10 and retry (6 tries) otherwise; a frame stops when a step gains less
than 1e-4 of its energy."""


def in_dtype(value: Any, dtype: torch.dtype) -> Any:
    """`value` with its floating tensors (also inside a NamedTuple or a dataclass) cast to `dtype`."""
    if isinstance(value, Tensor):
        return value.to(dtype) if value.is_floating_point() else value
    if isinstance(value, tuple):
        items = [in_dtype(v, dtype) for v in value]
        return value._make(items) if hasattr(value, "_make") else tuple(items)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return dataclasses.replace(value, **{f.name: in_dtype(getattr(value, f.name), dtype)
                                             for f in dataclasses.fields(value) if f.init})
    return value


@dataclass(frozen=True)
class Stage:
    """One stage: which unknowns move and which landmarks count.

    Attributes:
        name: for logs and histories.
        rotation, translation: the rigid pose moves.
        shapes: indices of the expression shapes that move.
        landmarks: "non_jaw", "jaw", "all" or "none" (`nodes.fit.energy.landmark_weights`).
        mouth_weight: weight of the lip points 48-67.
        jaw_weight: weight of the jaw contour points 0-16 when `landmarks` is "all".
        iris_weight: weight of each of the two iris centres (`FitViews.iris`, `FitModel.iris`;
            0 = not used, and not used where either is None).
        prior: lambda of this stage's L2 prior on the active weights; None = the solve's.
        photometric: the photometric term counts (where the solve has one).
    """

    name: str
    rotation: bool
    translation: bool
    shapes: tuple[int, ...] = ()
    landmarks: str = "all"
    mouth_weight: float = 1.0
    jaw_weight: float = 1.0
    iris_weight: float = 0.0
    prior: float | None = None
    photometric: bool = True


RIGID_STAGES = (
    Stage("translation", False, True, (), "non_jaw"),
    Stage("rigid_non_jaw", True, True, (), "non_jaw"),
    Stage("rigid_jaw", True, True, (), "jaw"),
    Stage("rigid_all", True, True, (), "all"),
)
"""The paper's rigid stages."""


def jaw_shapes(names: list[str]) -> list[int]:
    """Indices of the jaw shapes (ARKit names starting with 'jaw')."""
    return [i for i, n in enumerate(names) if n.startswith("jaw")]


def mouth_shapes(names: list[str]) -> list[int]:
    """Indices of the mouth shapes (ARKit names starting with 'mouth')."""
    return [i for i, n in enumerate(names) if n.startswith("mouth")]


def expression_stages(names: list[str]) -> tuple[Stage, ...]:
    """The paper's expression stages for a model with ARKit shape names (needs 'jawOpen')."""
    if "jawOpen" not in names:
        raise ValueError(f"expression names: expected a 'jawOpen' shape, found {names[:8]}...")
    jaw = tuple(jaw_shapes(names))
    both = tuple(sorted(set(jaw) | set(mouth_shapes(names))))
    return (Stage("jaw_open", False, False, (names.index("jawOpen"),), "all", mouth_weight=2.0),
            Stage("jaw", False, False, jaw, "all"),
            Stage("jaw_mouth", True, True, both, "all"))


def eye_stage(names: list[str], *, iris_weight: float = 1.0, prior: float = 4.0) -> Stage:
    """The eyeLook shapes from the iris centres alone, pose held; a frame whose iris was not read
    keeps its weights (`solve_stage`).

    The 68 points weigh 0 here, and the photometric term is off: the ICT eyeLook shapes also move
    the lids and the outer eye corners (up to 0.64 and 0.25 cm), and the render's eyes are empty
    sockets (the eyeballs are hidden), so both terms turned the eyes to fit the lids: on skimage's
    astronaut (looking into the camera) both eyes went a full look to one side.

    Args:
        names: the model's expression names (needs the eight eyeLook shapes).
        iris_weight: weight of each iris centre (the landmarks weigh 1).
        prior: lambda of the L2 prior on the eyeLook weights, 256-crop pixel^2 per unit weight^2.
    Raises:
        ValueError: a model without the eight eyeLook shapes.
    """
    shapes = tuple(eye_look_shapes(names))
    if len(shapes) != 8:
        raise ValueError(f"expression names: expected the eight eyeLook{{In,Out,Up,Down}}_{{L,R}} shapes, found "
                         f"{[names[i] for i in shapes]}")
    return Stage("eyes", False, False, shapes, "none", iris_weight=iris_weight, prior=prior, photometric=False)


def _with_iris(stage: Stage, model: FitModel, views: FitViews, anchors: Anchors,
               w_lm: Tensor) -> tuple[FitViews, Anchors, Tensor, bool]:
    """The stage's targets with the plate's two iris centres and the four eye corners they are
    measured from appended (L -> L + 6, as `nodes.fit.energy.iris_relative` reads them) when it uses
    them.

    The iris rows weigh `stage.iris_weight` (0 where not read), the corner rows 0 (they enter only
    through `iris_relative`); their offset is 0; the matching model points come from `_iris_rows`.
    Returns views, anchors, w_lm (as given, or (B, C, L + 6)) and whether the iris was appended.
    """
    if stage.iris_weight <= 0 or model.iris is None or views.iris is None:
        return views, anchors, w_lm, False
    w3 = w_lm if w_lm.ndim == 3 else w_lm.expand(*views.target.shape[:3])
    b, c = views.seen.shape
    found = torch.isfinite(views.iris).all(-1) & views.seen[..., None]  # (B, C, 2)
    corners = torch.as_tensor(IRIS_CORNERS_68.reshape(-1), device=views.target.device)
    target = torch.cat([views.target, torch.where(found[..., None], views.iris, 0.0).to(views.target.dtype),
                        views.target[:, :, corners]], 2)
    offset = torch.cat([anchors.offset, torch.zeros(b, c, 6, 2, dtype=anchors.offset.dtype,
                                                    device=anchors.offset.device)], 2)
    w_iris = found.to(w3.dtype) * float(stage.iris_weight)
    return (dataclasses.replace(views, target=target), anchors._replace(offset=offset),
            torch.cat([w3, w_iris, torch.zeros_like(w3[..., :4])], 2), True)


def _iris_rows(model: FitModel, weights: Tensor, c: int) -> tuple[Tensor, Tensor]:
    """The iris centres, then the eye corners' landmark vertices, as anchored points, linear in the
    weights about `weights` (B, K): neutral (B, C, 6, 3) and shapes (B, C, 6, K, 3) such that
    `neutral + sum_k w_k shape_k` is the exact turned centre (`nodes.fit.energy.iris_points`) at
    `weights`, with its derivative, and the corner vertices (linear in the weights).

    The corners are the model's own vertices, not the network's reading of the render: the iris
    centre is the model's geometry too, and the render's eyes (eyeballs hidden) are read with a
    bias that, on skimage's astronaut, turned both eyes a full look to one side."""
    point, deriv = iris_points(model.iris, model.iris_centres, model.iris_turns, weights)
    base = point - torch.einsum("bk,bekd->bed", weights, deriv)
    b = weights.shape[0]
    vert = torch.as_tensor(model.landmarks[IRIS_CORNERS_68.reshape(-1)], device=weights.device)
    c_base = model.neutral[vert].to(weights.dtype)[None].expand(b, -1, -1)  # (B, 4, 3)
    c_deriv = model.deltas[:, vert].to(weights.dtype).permute(1, 0, 2)[None].expand(b, -1, -1, -1)  # (B, 4, K, 3)
    base, deriv = torch.cat([base, c_base], 1), torch.cat([deriv, c_deriv], 1)
    return base[:, None].expand(b, c, *base.shape[1:]), deriv[:, None].expand(b, c, *deriv.shape[1:])


class PoseState(NamedTuple):
    """Per-frame unknowns: rot (B, 3, 3) model-to-world, trans (B, 3) cm, weights (B, K)."""

    rot: Tensor
    trans: Tensor
    weights: Tensor


def initial_pose(model: FitModel, views: FitViews, yaw: float = 0.0) -> PoseState:
    """The head facing the first camera that saw it, upright, at the depth of the eye distance.

    Rotation: the model's frame (y up, z out of the face) turned to face the camera
    (`R = R_cam^T diag(1, -1, -1)`); depth `z = f * IOD_model / IOD_plate` from the outer
    eye corners (36, 45); x, y by back-projecting the centroid of the non-jaw landmarks.
    With `yaw` (radians, not 0): that head turned by `yaw` about its own vertical axis
    (`R R_y(yaw)`), at the depth where a head so turned shows the plate's eye distance
    (`z |cos yaw|`, the eye corners' span foreshortened); `retry_from_starts`' other starts.
    """
    b, c = views.seen.shape
    dev, dt = model.neutral.device, model.neutral.dtype
    first = torch.argmax(views.seen.to(torch.int64), 1)  # (B,) first camera that saw the face
    e = views.world_to_camera[first]  # (B, 4, 4)
    k = views.intrinsics[first]
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=dt, device=dev))
    rot = e[:, :3, :3].transpose(1, 2) @ flip
    if yaw:
        cy, sy = float(np.cos(yaw)), float(np.sin(yaw))
        rot = rot @ torch.tensor([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]], dtype=dt, device=dev)
    target = views.target[torch.arange(b), first]  # (B, 68, 2)
    lm = model.neutral[torch.as_tensor(model.landmarks, device=dev)]
    iod_model = (lm[36] - lm[45]).norm()
    iod_px = (target[:, 36] - target[:, 45]).norm(dim=-1).clamp_min(1.0)
    z = k[:, 0] * iod_model / iod_px
    if yaw:
        z = z * abs(float(np.cos(yaw)))
    centre_px = target[:, 17:].mean(1)
    x = (centre_px[:, 0] - k[:, 2]) / k[:, 0] * z
    y = (centre_px[:, 1] - k[:, 3]) / k[:, 1] * z
    cam_point = torch.stack([x, y, z], -1)
    world_point = ((cam_point - e[:, :3, 3])[:, None] @ e[:, :3, :3])[:, 0]  # R^T (p - t)
    trans = world_point - (lm[17:].mean(0) @ rot.transpose(1, 2))
    return PoseState(rot, trans, torch.zeros(b, model.deltas.shape[0], dtype=dt, device=dev))


RETRY_YAWS = (0.0, float(np.pi), float(np.radians(35.0)), -float(np.radians(35.0)))
"""`retry_from_starts`' starts, yaw about the head's vertical axis (radians) from facing the camera:
facing it (`initial_pose`), turned away, and turned 35 deg each way (each at the depth of the
plate's eye distance foreshortened by that turn)."""


def frames_of(views: FitViews, frames: Tensor) -> FitViews:
    """The views of some frames: `frames` (N,) int64 indices into the batch."""
    pick = lambda a: None if a is None else a[frames]  # noqa: E731
    return dataclasses.replace(views, target=views.target[frames], boxes=views.boxes[frames],
                               seen=views.seen[frames], plates=pick(views.plates), iris=pick(views.iris))


def retry_from_starts(model: FitModel, views: FitViews, state: PoseState, energy: Tensor, wrong: Tensor,
                      solve: Callable[[FitViews, PoseState], tuple[PoseState, Tensor]],
                      yaws: tuple[float, ...] = RETRY_YAWS) -> tuple[PoseState, Tensor, Tensor]:
    """Re-solve the frames whose fit landed in a wrong minimum from other starts; keep the lowest energy.

    The frames in `wrong` are solved again by `solve` from `initial_pose(model, views, yaw)` for
    each of `yaws`; each frame keeps, of its first solve (`state`, `energy`) and these, the
    one with the lowest final energy. Frames not in `wrong` are not touched (the same tensors'
    values, bit for bit), and nothing runs when no frame is.

    Args:
        model, views: the model and the batch's views (B frames).
        state, energy: the first solve's result, (B,) final energies (256-crop pixel^2).
        wrong: (B,) bool, the frames to re-solve (e.g. landmarks reprojected more than
            `nodes.fit.output_nodes.MAX_REPROJECTION` eye distances from the plate's).
        solve: (views of N frames, start) -> (state, (N,) final energy), the solve that gave `state`.
        yaws: the starts' turns about the head's vertical axis, radians (`RETRY_YAWS`).
    Returns:
        the state, (B,) its energy, and (B,) int64: 0 where the first solve was kept, i where the
        start `yaws[i - 1]` won.
    """
    chosen = torch.zeros(len(energy), dtype=torch.int64, device=energy.device)
    if not bool(wrong.any()):
        return state, energy, chosen
    idx = torch.nonzero(wrong)[:, 0]
    sub = frames_of(views, idx)
    best = PoseState(state.rot[idx], state.trans[idx], state.weights[idx])
    best_e, best_i = energy[idx], chosen[idx]
    for i, yaw in enumerate(yaws, 1):
        found, e = solve(sub, initial_pose(model, sub, yaw))
        found = PoseState(*(a.to(b.dtype) for a, b in zip(found, best)))
        take = e.to(best_e.dtype) < best_e  # a NaN energy never wins
        best, best_e = _mix(take, found, best), torch.where(take, e.to(best_e.dtype), best_e)
        best_i = torch.where(take, torch.full_like(best_i, i), best_i)
    rot, trans, weights = state.rot.clone(), state.trans.clone(), state.weights.clone()
    rot[idx], trans[idx], weights[idx] = best.rot, best.trans, best.weights
    energy = energy.clone()
    energy[idx] = best_e
    chosen[idx] = best_i
    return PoseState(rot, trans, weights), energy, chosen


def _anchored(model: FitModel, anchors: Anchors) -> tuple[Tensor, Tensor]:
    """(B, C, L, 3) anchored neutral and (B, C, L, K, 3) anchored shapes."""
    return at_anchors(model.neutral, anchors.vertices, anchors.bary), at_anchors(model.deltas, anchors.vertices,
                                                                                 anchors.bary)


def predicted_points(model: FitModel, views: FitViews, anchors: Anchors, state: PoseState) -> Tensor:
    """(B, C, 68, 2) render landmarks predicted from the anchors, image pixels."""
    neutral, deltas = _anchored(model, anchors)
    pts = posed_anchor_points(neutral, deltas, state.weights, state.rot, state.trans)
    return project_views(pts, views.world_to_camera, views.intrinsics, views.distortion) + anchors.offset


def _stage_residuals(neutral: Tensor, deltas: Tensor, views: FitViews, anchors: Anchors, rot0: Tensor,
                     base_weights: Tensor, shapes: Tensor, w_lm: Tensor, *, prior: float, edge_weight: float,
                     rigid_prior: PoseState | None, rigid_prior_weight: float,
                     iris: bool = False) -> Callable[[Tensor], Tensor]:
    """A stage's energy as a sum of squares: x (B, 6 + S) -> residuals (B, M).

    x = [omega (3), t (3) cm, the S active weights]; `R = exp([omega]) rot0`. The residuals are,
    in order: data (C*L*2), edges (C*E*2, if mu > 0), prior (S), bound penalty (S), rigid
    prior (12, if any), so that `sum r^2` is `landmark_energy` + the prior + the bound
    penalty + the rigid prior of `solve_stage`. `w_lm` is (L,) or (B, C, L). With `iris`, the
    last two points are the iris centres, compared relative to their eyes' corners
    (`nodes.fit.energy.iris_relative`).
    """
    a, b = EDGES_68[:, 0], EDGES_68[:, 1]
    scale = views.scale
    w3 = w_lm if w_lm.ndim == 3 else w_lm.expand(*views.target.shape[:3])  # (B, C, L)
    sw = w3.clamp_min(0).sqrt()[..., None]
    ew = ((w3[..., a] > 0) & (w3[..., b] > 0)).to(w_lm.dtype)[..., None] * float(edge_weight) ** 0.5
    n_w = len(shapes)
    use_rigid_prior = rigid_prior is not None and rigid_prior_weight > 0

    def fn(x: Tensor) -> Tensor:
        rot = axis_angle_to_rotmat(x[:, :3]) @ rot0
        trans = x[:, 3:6]
        active = x[:, 6:]
        weights = base_weights.index_copy(1, shapes, active) if n_w else base_weights
        pts = posed_anchor_points(neutral, deltas, weights, rot, trans)
        pred = project_views(pts, views.world_to_camera, views.intrinsics, views.distortion) + anchors.offset
        r = (views.target - pred) * scale[..., None, None]  # (B, C, 68, 2)
        if iris:
            r = iris_relative(r)
        parts = [(r * sw).flatten(1)]
        if edge_weight > 0:
            parts.append(((r[:, :, b] - r[:, :, a]) * ew).flatten(1))
        if n_w:
            parts.append(active * float(prior) ** 0.5)
            parts.append(((-active).clamp_min(0) + (active - 1).clamp_min(0)) * BOUND_PENALTY ** 0.5)
        if use_rigid_prior:
            k = float(rigid_prior_weight) ** 0.5
            parts.append((trans - rigid_prior.trans) * k)
            parts.append((rot - rigid_prior.rot).flatten(1) * (k / 2 ** 0.5))
        return torch.cat(parts, 1)

    return fn


def _stage_jacobian(neutral: Tensor, deltas: Tensor, views: FitViews, rot0: Tensor, base_weights: Tensor,
                    shapes: Tensor, w_lm: Tensor, x: Tensor, *, prior: float, edge_weight: float,
                    rigid_prior: PoseState | None, rigid_prior_weight: float,
                    extra: Tensor | None = None, iris: bool = False) -> Tensor:
    """The Jacobian of `_stage_residuals`' function at x (B, 6 + S) with omega = 0, by hand.

    The landmark rows chain `project_views_jacobian` with the anchored points' derivatives:
    `-[R q]_x` in omega, the identity in t, `R d_s` in active weight s (q the anchored local
    point, d_s its shape). The bound penalty's rows follow autodiff's convention at the bounds
    (a weight exactly at 0 counts as below it).

    Args:
        neutral, deltas, views, rot0, base_weights, shapes, w_lm, prior, edge_weight,
            rigid_prior, rigid_prior_weight: as in `_stage_residuals`.
        x: the unknowns (omega = 0).
        extra: (B, C, L, X, 3) the anchored points' local derivatives in X further linear
            unknowns (the identity), or None.
        iris: as in `_stage_residuals`.
    Returns:
        (B, M, 6 + S (+ X)).
    """
    a, b = EDGES_68[:, 0], EDGES_68[:, 1]
    bsz, n_w = x.shape[0], len(shapes)
    dt, dev = x.dtype, x.device
    w3 = w_lm if w_lm.ndim == 3 else w_lm.expand(*views.target.shape[:3])  # (B, C, L)
    sw = w3.clamp_min(0).sqrt()[..., None, None]
    weights = base_weights.index_copy(1, shapes, x[:, 6:]) if n_w else base_weights
    local = neutral + torch.einsum("bk,bclkd->bcld", weights, deltas)
    rotated = local @ rot0[:, None].transpose(-1, -2)  # (B, C, L, 3)
    _, d_pix = project_views_jacobian(rotated + x[:, None, None, 3:6], views.world_to_camera, views.intrinsics,
                                      views.distortion)
    cols = [-_skew(rotated), torch.eye(3, dtype=dt, device=dev).expand(*rotated.shape, 3)]
    if n_w:
        cols.append(torch.einsum("bij,bclsj->bclis", rot0, deltas[:, :, :, shapes]))
    if extra is not None:
        cols.append(torch.einsum("bij,bclxj->bclix", rot0, extra))
    d_world = torch.cat(cols, -1)  # (B, C, L, 3, P)
    n_all = d_world.shape[-1]
    jac = -views.scale[..., None, None, None] * (d_pix @ d_world)  # (B, C, L, 2, P): r = (target - pred) scale
    if iris:
        jac = iris_relative(jac)
    parts = [(jac * sw).reshape(bsz, -1, n_all)]
    if edge_weight > 0:
        ew = ((w3[..., a] > 0) & (w3[..., b] > 0)).to(dt)[..., None, None] * float(edge_weight) ** 0.5
        parts.append(((jac[:, :, b] - jac[:, :, a]) * ew).reshape(bsz, -1, n_all))
    if n_w:
        rows = torch.zeros(bsz, n_w, n_all, dtype=dt, device=dev)
        diag = torch.arange(n_w, device=dev)
        rows[:, diag, 6 + diag] = float(prior) ** 0.5
        parts.append(rows)
        active = x[:, 6:]
        side = (active >= 1).to(dt) - (active <= 0).to(dt)
        bound = torch.zeros(bsz, n_w, n_all, dtype=dt, device=dev)
        bound[:, diag, 6 + diag] = side * BOUND_PENALTY ** 0.5
        parts.append(bound)
    if rigid_prior is not None and rigid_prior_weight > 0:
        k = float(rigid_prior_weight) ** 0.5
        rows = torch.zeros(bsz, 12, n_all, dtype=dt, device=dev)
        three = torch.arange(3, device=dev)
        rows[:, three, 3 + three] = k
        gens = _skew(torch.eye(3, dtype=dt, device=dev))  # [e_j]_x
        rows[:, 3:, :3] = torch.einsum("jik,bkl->bilj", gens, rot0).reshape(bsz, 9, 3) * (k / 2 ** 0.5)
        parts.append(rows)
    return torch.cat(parts, 1)


def solve_stage(stage: Stage, model: FitModel, views: FitViews, anchors: Anchors, state: PoseState, *,
                prior: float, edge_weight: float, eyelid_weight: float, iterations: int,
                rigid_prior: PoseState | None = None, rigid_prior_weight: float = 0.0,
                photo: PhotoSamples | None = None, photo_weight: float = 0.0,
                anchored: tuple[Tensor, Tensor] | None = None) -> tuple[PoseState, Tensor]:
    """Minimize one stage's energy over its unknowns (all frames at once; frames are independent).

    The energy is a sum of squares (`_stage_residuals`), minimized per frame by
    Levenberg-Marquardt (`nodes.geometry.lm`, `STAGE_SCHEDULE`) in float64 (`SOLVE_DTYPE`):
    Jacobian chained by hand (`_stage_jacobian`, the photometric term's `PhotoTerm.jacobian`;
    tested against forward-mode autodiff), the rotation re-linearized after every accepted step
    (`R <- exp([omega]) R`). Much cheaper than
    L-BFGS here: the unknowns are few (6 + the active shapes) and each iteration costs one
    Jacobian and one or two evaluations.

    Args:
        stage: the unknowns and landmarks.
        model, views, anchors: the linearization (see the module docstring).
        state: the start.
        prior: lambda of the L2 prior on the active weights (256-crop pixel^2 per unit weight^2).
        edge_weight: mu of the edge term.
        eyelid_weight: weight of the eyelid points.
        iterations: at most this many Levenberg-Marquardt iterations; a frame stops when a step
            lowers its energy by less than 1e-4 relative.
        rigid_prior: pose the rigid unknowns are pulled toward in expression stages, with
            `rigid_prior_weight` (per radian^2 and cm^2).
        photo: photometric samples (`nodes.fit.photometric`) of this round, or None;
            photo_weight: their w_p.
        anchored: `_anchored(model, anchors)` in `SOLVE_DTYPE` when the caller has it (the
            stages of a round share their anchors), or None to compute it here.
    Returns:
        the new state and (B,) the energy at it (data + edges + photometric + prior).
    """
    out_dt = state.rot.dtype
    neutral, deltas = anchored if anchored is not None else in_dtype(_anchored(model, anchors), SOLVE_DTYPE)
    views, anchors, state, photo, rigid_prior = in_dtype((views, anchors, state, photo, rigid_prior), SOLVE_DTYPE)
    b = state.rot.shape[0]
    use_photo = photo is not None and photo_weight > 0 and stage.photometric
    if use_photo:
        shape_list = list(stage.shapes)
        p_basis = photo.deltas[:, :, :, shape_list].transpose(-1, -2).contiguous()  # (B, C, N, 3, S), read
        # at every residual and Jacobian: contiguous once (the expression stage's residuals 9 -> 5 ms)
        # the term about the stage's start: the inactive weights do not move in a stage, so the
        # samples' local points with them (`PhotoTerm.about`) hold for every linearization
        photo_term = PhotoTerm.about(photo, views, photo_weight, state.weights, shape_list, p_basis)
    dev, dt = neutral.device, neutral.dtype
    w_np = landmark_weights(stage.landmarks, eyelid=eyelid_weight, mouth=stage.mouth_weight, jaw=stage.jaw_weight)
    w_lm = torch.as_tensor(w_np, dtype=dt, device=dev)
    views, anchors, w_lm, iris = _with_iris(stage, model, views, anchors, w_lm)
    n_cams = views.seen.shape[1]
    if stage.prior is not None:
        prior = stage.prior
    shapes = torch.as_tensor(list(stage.shapes), dtype=torch.long, device=dev)
    free = torch.as_tensor([stage.rotation] * 3 + [stage.translation] * 3 + [True] * len(stage.shapes), device=dev)
    free_idx = torch.nonzero(free)[:, 0]
    n_p = len(free_idx)
    # the free unknowns are one run of columns in every stage (t; omega, t; the shapes; all): a slice
    # of the Jacobian is a view, and a stage that holds the pose takes no photometric pose columns
    lo = int(free_idx[0]) if n_p else 0
    cols: slice | Tensor = slice(lo, lo + n_p) if n_p and bool((free_idx == lo + torch.arange(
        n_p, device=dev)).all()) else free_idx
    pose_held = isinstance(cols, slice) and lo == 6
    rot, trans, weights = state.rot.detach(), state.trans.detach(), state.weights.detach()

    def full(x_free: Tensor, x_fixed: Tensor) -> Tensor:
        return x_fixed.index_copy(1, free_idx, x_free) if n_p else x_fixed

    def unknowns(trans: Tensor, weights: Tensor) -> Tensor:  # x = [omega = 0, t, active weights]
        return torch.cat([torch.zeros(trans.shape[0], 3, dtype=dt, device=dev), trans, weights[:, shapes]], 1)

    every = torch.arange(b, device=dev)

    def frames(rows: Tensor) -> dict[str, Any]:
        """The stage's per-frame data of the frames `rows` (R,): the Levenberg-Marquardt solve runs
        on the frames still running only (`levenberg_marquardt(compact=True)`)."""
        if len(rows) == b and bool((rows == every).all()):
            return dict(views=views, anchors=anchors, neutral=neutral, deltas=deltas, w_lm=w_lm, rigid=rigid_prior,
                        term=photo_term if use_photo else None)
        sub = frames_of(views, rows)
        term = None
        if use_photo:
            pick = photo._replace(
                **{f: getattr(photo, f)[rows] for f in ("vertices", "bary", "colour", "weight", "neutral", "deltas")},
                plates=photo.plates.unflatten(0, (b, n_cams))[rows].flatten(0, 1))
            term = PhotoTerm(pick, sub, photo_weight, photo_term.local0[rows], photo_term.basis[rows])
        return dict(views=sub, anchors=Anchors(*(a[rows] for a in anchors)), neutral=neutral[rows],
                    deltas=deltas[rows], w_lm=w_lm[rows] if w_lm.ndim == 3 else w_lm,
                    rigid=None if rigid_prior is None else PoseState(*(a[rows] for a in rigid_prior)), term=term)

    def linearize(rot: Tensor, trans: Tensor, weights: Tensor,
                  d: dict[str, Any]) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], tuple[Tensor, ...]]]:
        """The residual function of the free unknowns about the current state of the frames of `d`
        (`frames`), and its Jacobian."""
        views, anchors, w_lm = d["views"], d["anchors"], d["w_lm"]
        if iris:  # the iris centres' turn, re-linearized about the current weights (as the rotation)
            rows = _iris_rows(model, weights, n_cams)
            at_n, at_d = torch.cat([d["neutral"], rows[0]], 2), torch.cat([d["deltas"], rows[1]], 2)
        else:
            at_n, at_d = d["neutral"], d["deltas"]
        fn = _stage_residuals(at_n, at_d, views, anchors, rot, weights, shapes, w_lm, prior=prior,
                              edge_weight=edge_weight, rigid_prior=d["rigid"],
                              rigid_prior_weight=rigid_prior_weight, iris=iris)
        x0 = unknowns(trans, weights)
        term = d["term"]

        def residuals(xf: Tensor) -> Tensor:
            xa = full(xf, x0)
            r = fn(xa)
            return torch.cat([r, term.residuals(xa[:, :3], rot, xa[:, 3:6], xa[:, 6:])], 1) if term else r

        def jacobian(xf: Tensor) -> tuple[Tensor, ...]:
            """The Jacobian's row blocks in the residuals' order (landmarks, then photometric), each (R, M_i, P)."""
            xa = full(xf, x0)
            jac = _stage_jacobian(at_n, at_d, views, rot, weights, shapes, w_lm, xa, prior=prior,
                                  edge_weight=edge_weight, rigid_prior=d["rigid"],
                                  rigid_prior_weight=rigid_prior_weight, iris=iris)[:, :, cols]
            if term is None:
                return (jac,)
            if pose_held:
                return jac, term.jacobian(rot, xa[:, 3:6], xa[:, 6:], pose=False)[1]
            return jac, term.jacobian(rot, xa[:, 3:6], xa[:, 6:])[1][:, :, cols]

        return residuals, jacobian

    def state_at(rot: Tensor, x: Tensor, base: Tensor) -> PoseState:
        r = axis_angle_to_rotmat(x[:, :3]) @ rot
        w = base.index_copy(1, shapes, x[:, 6:]) if len(stage.shapes) else base
        return PoseState(r, x[:, 3:6], w)

    with torch.no_grad():
        # the state of every frame; the linearization of the frames `rows` about it, made when first needed
        now: dict[str, Any] = dict(rot=rot, trans=trans, weights=weights, rows=None, part=None, lin=None)

        def linearized(rows: Tensor) -> tuple[Callable[[Tensor], Tensor], Callable[[Tensor], tuple[Tensor, ...]]]:
            if now["part"] is None or not torch.equal(now["rows"], rows):
                now["rows"], now["part"], now["lin"] = rows, frames(rows), None
            if now["lin"] is None:
                now["lin"] = linearize(now["rot"][rows], now["trans"][rows], now["weights"][rows], now["part"])
            return now["lin"]

        def relinearize(x: Tensor, accepted: Tensor, rows: Tensor) -> Tensor:
            new = state_at(now["rot"][rows], full(x, unknowns(now["trans"][rows], now["weights"][rows])), weights[rows])
            for key, value in zip(("rot", "trans", "weights"), new):
                take = accepted.reshape(-1, *[1] * (value.ndim - 1))
                now[key] = now[key].index_copy(0, rows, torch.where(take, value, now[key][rows]))
            now["lin"] = None
            return unknowns(now["trans"][rows], now["weights"][rows])[:, free_idx]

        def normal(x: Tensor, r: Tensor, rows: Tensor) -> tuple[Tensor, Tensor]:
            jtj, jtr, row = None, None, 0
            for jac in linearized(rows)[1](x):  # (R, M_i, P) row blocks: summed without concatenating
                part, part_r = normal_products(jac, r[:, row:row + jac.shape[1]])
                jtj, jtr = (part, part_r) if jtj is None else (jtj + part, jtr + part_r)
                row += jac.shape[1]
            return jtj, jtr

        x = unknowns(trans, weights)[:, free_idx]
        if n_p:
            out = levenberg_marquardt(lambda xf, rows: linearized(rows)[0](xf), normal, x, iterations=iterations,
                                      schedule=STAGE_SCHEDULE, relinearize=relinearize, compact=True)
            r = out.residuals
        else:
            r = linearized(every)[0](x)
        rot, trans, weights = now["rot"], now["trans"], now["weights"]
        if iris:  # a frame whose iris no camera read keeps its eyeLook weights (the lids alone do not move them)
            read = (w_lm[..., -6:-4] > 0).flatten(1).any(1)
            weights = torch.where(read[:, None], weights, state.weights)
        m_lm = r.shape[1] - (photo.weight[0].numel() * 3 if use_photo else 0)  # landmark residuals come first
        drop = len(stage.shapes) + (12 if rigid_prior is not None and rigid_prior_weight > 0 else 0)
        kept = torch.cat([r[:, :m_lm - drop], r[:, m_lm:]], 1)  # data + edges + prior + photometric
        e = (kept * kept).sum(1)
    return in_dtype(PoseState(rot, trans, weights.clamp(0.0, 1.0)), out_dt), e.to(out_dt)


def _render_anchors(model: FitModel, views: FitViews, state: PoseState, network: torch.nn.Module,
                    fallback: Anchors, supersample: int, indices: np.ndarray = MEDIAPIPE_TO_68,
                    photometric: dict | None = None) -> tuple[Anchors, Tensor, PhotoSamples | None]:
    """Render the current estimate, read it with the network, anchor its points.

    Args:
        indices: (L,) the face-mesh points anchored (`network_points`); `fallback` has L points.
        photometric: keyword arguments of `photometric_samples` to take samples from the render
            too, or None.
    Returns:
        anchors, (B, C, L, 2) the network's render points, image pixels, and the photometric
        samples (None without `photometric`).
    """
    size = int(network.input_size)
    with torch.no_grad():
        verts = model.vertices(state.weights, state.rot, state.trans)
        image, triangle, pix = render_crops(model, views, verts, size=size, supersample=supersample)
        points, presence = network_points(image, network, indices)
    anchors = anchors_from_render(model, views, triangle, pix, points, presence, fallback)
    samples = None
    if photometric is not None:
        with torch.no_grad():
            if model.noise > 0:  # the samples' colours come from the noise-free render
                image, _, _ = render_crops(dataclasses.replace(model, noise=0.0), views, verts, size=size,
                                           supersample=supersample)
            samples = photometric_samples(model, views, image, triangle, pix, anchors.rendered, **photometric)
    b, c = views.seen.shape
    return anchors, crop_to_image(points.reshape(b, c, len(indices), 2), views.boxes, size), samples


OUTER_STEP_CUT = 0.5
"""`fit_stages`: a round whose move raised a frame's objective (the deep energy read on a render, plus
the prior) is undone for that frame, and its later rounds move this fraction of the step before."""


def _mix(take: Tensor, a: PoseState, b: PoseState) -> PoseState:
    """Per frame, `a` where `take` (B,) else `b`."""
    return PoseState(torch.where(take[:, None, None], a.rot, b.rot), torch.where(take[:, None], a.trans, b.trans),
                     torch.where(take[:, None], a.weights, b.weights))


def _part_way(start: PoseState, end: PoseState, step: Tensor) -> PoseState:
    """The pose `step` (B,) of the way from `start` to `end`: rotation along the geodesic
    (`R = exp(step log(R_end R_start^T)) R_start`), translation and weights linearly."""
    if bool((step == 1).all()):
        return end
    q = rotmat_to_quat_torch(end.rot.to(torch.float64) @ start.rot.to(torch.float64).transpose(1, 2))  # w >= 0
    vec = q[:, 1:]
    sin = vec.norm(dim=1, keepdim=True)
    omega = torch.where(sin > 1e-12, vec / sin.clamp_min(1e-300) * 2 * torch.atan2(sin, q[:, :1]), 2 * vec)
    rel = axis_angle_to_rotmat(omega * step[:, None].to(torch.float64)).to(start.rot.dtype)
    s1 = step.to(start.trans.dtype)[:, None]
    moved = PoseState(rel @ start.rot, start.trans + s1 * (end.trans - start.trans),
                      start.weights + s1 * (end.weights - start.weights))
    return _mix(step == 1, end, moved)  # a whole step is `end` exactly, whatever the other frames' steps


def _keep_better(best: PoseState, best_e: Tensor | None, best_objective: Tensor | None, state: PoseState,
                 e: Tensor, objective: Tensor) -> tuple[PoseState, Tensor, Tensor]:
    """Per frame, `state` with its energy `e` and `objective` (B,) where the objective is below
    `best_objective` (or there is none yet), else the best so far."""
    if best_objective is None or best_e is None:
        return state, e, objective
    take = objective < best_objective
    return _mix(take, state, best), torch.where(take, e, best_e), torch.where(take, objective, best_objective)


def fit_stages(model: FitModel, views: FitViews, state: PoseState, stages: tuple[Stage, ...],
               network: torch.nn.Module, *, outer: int = 2, first_outer_on_landmarks: bool = True,
               prior: float = 100.0, edge_weight: float = 1.0, eyelid_weight: float = 0.2,
               iterations: int = 30, supersample: int = 2, rigid_prior_weight: float = 0.0,
               photometric_weight: float = 0.0, photometric: dict | None = None,
               progress: Callable[[float, str], None] | None = None) -> tuple[PoseState, Tensor, list[dict]]:
    """Run the stages `outer` times, re-rendering and re-anchoring before each round.

    With expression stages (any stage moves shapes), each render also measures the state it shows: its objective is the deep energy read on the
    render plus the prior on the weights the stages move (256-crop pixel^2). The anchors are the
    network's Jacobian only to first order, and on real photos a round could move the state to a
    higher objective and the next rounds further (skimage's astronaut: 1488 at the rigid pose, 1186
    after one round, then 1702, 1947, 1888, with six mouth weights at the bound 1.0, opposite
    shapes together). So a frame whose objective rose goes back to its best state (read again on
    a render) and its later rounds move `OUTER_STEP_CUT` of the step before (a line search on
    the outer step); the result is each frame's best state read. Rigid stages keep every round's
    move (bench/fit.py --frames 2: the line search there raised the median rotation error 1.08 ->
    1.22 deg, the network's reading noise rejecting useful rounds).

    Args:
        model, views: the model, appearance and plate landmarks.
        state: the start (e.g. `initial_pose`, or the previous node's result).
        stages: `RIGID_STAGES` or `expression_stages(...)`.
        network: the landmark network (`MediaPipeFaceMesh`).
        outer: rounds of render + anchor + stages.
        first_outer_on_landmarks: the first round uses the model's 68 landmark vertices as
            anchors instead of a render (cheap and good from a far start).
        prior, edge_weight, eyelid_weight, iterations: see `solve_stage`.
        supersample: of the renders.
        rigid_prior_weight: pull of the rigid pose toward `state`'s in expression stages.
        photometric_weight: w_p of the photometric term (`nodes.fit.photometric`) in the rounds
            anchored on a render; 0 = off. Needs `views.plates`.
        photometric: keyword arguments of `photometric_samples` (stride, sigma, ...).
    Returns:
        the best state read (rigid stages: the last), (B,) its deep energy (data + edges with all landmarks, read on its
        render, in 256-crop pixel^2), and a history of dicts (round, stage, mean energy; the
        "read" entries also the per-frame objective and step of each render, the "final" one the
        returned state's objective).
    """
    b, c = views.seen.shape
    start = state
    fallback = landmark_anchors(model, b, c)
    history: list[dict] = []
    use_photo = photometric_weight > 0
    if use_photo and views.plates is None:
        raise ValueError("views.plates: expected the plate's crops for the photometric term, found None")
    photo_args = dict(photometric or {}) if use_photo else None
    w_all = torch.as_tensor(landmark_weights("all", eyelid=eyelid_weight), dtype=views.target.dtype,
                            device=views.target.device)
    moved = sorted({s for stage in stages for s in stage.shapes})

    def deep_energy(rendered: Tensor) -> Tensor:
        return landmark_energy(rendered, views.target, views.scale, w_all, edge_weight=edge_weight)

    def with_prior(e: Tensor, at: PoseState) -> Tensor:
        return e + float(prior) * (at.weights[:, moved] ** 2).sum(1) if moved else e

    best, best_e, best_objective = state, None, None
    step = torch.ones(b, dtype=views.target.dtype, device=views.target.device)  # per frame, of a round's move
    for r in range(outer):
        samples = None
        if r == 0 and first_outer_on_landmarks:
            anchors = fallback
        else:
            anchors, rendered, samples = _render_anchors(model, views, state, network, fallback, supersample,
                                                         photometric=photo_args)
            e = deep_energy(rendered)
            objective = with_prior(e, state)
            history.append({"round": r, "stage": "read", "energy": float(e.mean()), "objective": objective.tolist(),
                            "step": step.tolist()})
            if best_objective is not None and moved:
                worse = objective > best_objective
                if bool(worse.any()):  # those frames go back to their best state, with half the step
                    step = torch.where(worse, step * OUTER_STEP_CUT, step)
                    state = _mix(worse, best, state)
                    anchors, rendered, samples = _render_anchors(model, views, state, network, fallback,
                                                                 supersample, photometric=photo_args)
                    e = deep_energy(rendered)
                    objective = with_prior(e, state)
                    history.append({"round": r, "stage": "back", "energy": float(e.mean()),
                                    "objective": objective.tolist(), "step": step.tolist()})
            if moved:
                best, best_e, best_objective = _keep_better(best, best_e, best_objective, state, e, objective)
        before = state
        # the round's stages share the anchors, the samples and the views, cast once to the solve's precision
        anchored = in_dtype(_anchored(model, anchors), SOLVE_DTYPE)
        samples64, views64, start64 = in_dtype((samples, views, start), SOLVE_DTYPE)
        for stage in stages:
            state, e = solve_stage(stage, model, views64, anchors, state, prior=prior, edge_weight=edge_weight,
                                   eyelid_weight=eyelid_weight, iterations=iterations, rigid_prior=start64,
                                   rigid_prior_weight=rigid_prior_weight, photo=samples64,
                                   photo_weight=photometric_weight, anchored=anchored)
            history.append({"round": r, "stage": stage.name, "energy": float(e.mean())})
        state = _part_way(before, state, step)
        if progress is not None:
            progress((r + 1) / (outer + 1), f"round {r + 1}/{outer}")
    _, rendered, _ = _render_anchors(model, views, state, network, fallback, supersample)
    e = deep_energy(rendered)
    history.append({"round": outer, "stage": "read", "energy": float(e.mean()),
                    "objective": with_prior(e, state).tolist(), "step": step.tolist()})
    objective = with_prior(e, state)
    if moved:
        state, e, objective = _keep_better(best, best_e, best_objective, state, e, objective)
    energy = e
    history.append({"round": outer, "stage": "final", "energy": float(energy.mean()), "objective": objective.tolist()})
    return state, energy, history


def refine_backprop(model: FitModel, views: FitViews, state: PoseState, stage: Stage, network: torch.nn.Module,
                    *, steps: int = 10, lr_rot: float = 2e-3, lr_trans: float = 0.05, lr_weights: float = 0.02,
                    prior: float = 100.0, edge_weight: float = 1.0, eyelid_weight: float = 0.2,
                    supersample: int = 2) -> tuple[PoseState, Tensor]:
    """The paper's literal solve: Adam on `|N(F*) - N(F(x_R))|^2` through network and renderer.

    Crop boxes are held constant (the plate's). Slow on a CPU (a render, a forward and a
    backward pass of both per step); used as an optional polish after `fit_stages`.

    Args:
        stage: which unknowns move and which landmarks count.
        steps: Adam steps; lr_*: step sizes (radians, cm, weight units).
    Returns:
        the best state seen and its (B,) energy.
    """
    size = int(network.input_size)
    b, c = views.seen.shape
    dt, dev = state.trans.dtype, state.trans.device
    w_lm = torch.as_tensor(landmark_weights(stage.landmarks, eyelid=eyelid_weight, mouth=stage.mouth_weight,
                                            jaw=stage.jaw_weight),
                           dtype=dt, device=dev)
    shapes = torch.as_tensor(list(stage.shapes), dtype=torch.long, device=dev)
    omega = torch.zeros(b, 3, dtype=dt, device=dev, requires_grad=True)
    trans = state.trans.clone().requires_grad_(True)
    active = state.weights[:, shapes].clone().requires_grad_(True)
    groups = [{"params": [omega], "lr": lr_rot if stage.rotation else 0.0},
              {"params": [trans], "lr": lr_trans if stage.translation else 0.0},
              {"params": [active], "lr": lr_weights}]
    opt = torch.optim.Adam(groups)
    best_e = torch.full((b,), float("inf"), dtype=dt, device=dev)
    best = state
    for _ in range(steps + 1):
        rot = axis_angle_to_rotmat(omega) @ state.rot
        weights = state.weights.index_copy(1, shapes, active.clamp(0.0, 1.0)) if len(stage.shapes) else state.weights
        verts = model.vertices(weights, rot, trans)
        image, _, _ = render_crops(model, views, verts, size=size, supersample=supersample)
        points, _ = network_points(image, network)
        pred = crop_to_image(points.reshape(b, c, 68, 2), views.boxes, size)
        e = landmark_energy(pred, views.target, views.scale, w_lm, edge_weight=edge_weight)
        e = e + prior * (active * active).sum(-1)
        with torch.no_grad():
            better = e < best_e
            best_e = torch.where(better, e, best_e)
            best = PoseState(torch.where(better[:, None, None], rot, best.rot),
                             torch.where(better[:, None], trans, best.trans),
                             torch.where(better[:, None], weights, best.weights))
        opt.zero_grad()
        e.sum().backward()
        opt.step()
    return PoseState(best.rot.detach(), best.trans.detach(), best.weights.detach()), best_e.detach()
