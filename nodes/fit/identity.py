"""Identity (the model's 40 shape components) from the landmarks of one or a few frames.

Unknowns: one identity vector `a` (I,) shared by the frames, and per frame the rigid pose
and the jaw and mouth weights. Energy: the frames' landmark energies (anchored, as in
`nodes.fit.solve`) + `lambda_id |a|^2` (the components are N(0, 1) a priori) + the expression
prior. Alternates with re-anchoring on renders like `fit_stages`. Torch at the top: import
from node `run()` methods only.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..landmarks.correspondence import MEDIAPIPE_TO_68
from .energy import axis_angle_to_rotmat, landmark_energy, landmark_weights, project_views
from .solve import PoseState, _anchored, _render_anchors, jaw_shapes, mouth_shapes
from .views import Anchors, FitModel, FitViews, landmark_anchors

__all__ = ["solve_identity"]


def _identity_step(model: FitModel, identity_deltas: Tensor, views: FitViews, anchors: Anchors, state: PoseState,
                   identity: Tensor, w_lm: Tensor, *, prior: float, identity_prior: float, edge_weight: float,
                   iterations: int) -> tuple[PoseState, Tensor]:
    neutral, deltas = _anchored(model, anchors)
    bary = anchors.bary[..., None]
    id_d = (identity_deltas[:, anchors.vertices] * bary[None]).sum(-2).permute(1, 2, 3, 0, 4)  # (B, C, L, I, 3)
    b = state.rot.shape[0]
    shapes = torch.as_tensor(sorted(set(jaw_shapes(model.names)) | set(mouth_shapes(model.names))),
                             device=neutral.device)
    omega = torch.zeros(b, 3, requires_grad=True)
    trans = state.trans.clone().requires_grad_(True)
    active = state.weights[:, shapes].clone().requires_grad_(True)
    ident = identity.clone().requires_grad_(True)

    def evaluate() -> tuple[Tensor, PoseState]:
        rot = axis_angle_to_rotmat(omega) @ state.rot
        weights = state.weights.index_copy(1, shapes, active)
        local = neutral + torch.einsum("bk,bclkd->bcld", weights, deltas) + torch.einsum("i,bclid->bcld", ident, id_d)
        pts = local @ rot[:, None].transpose(-1, -2) + trans[:, None, None]
        pred = project_views(pts, views.world_to_camera, views.intrinsics, views.distortion) + anchors.offset
        e = landmark_energy(pred, views.target, views.scale, w_lm, edge_weight=edge_weight)
        e = e + prior * (active ** 2).sum(-1) + 1e4 * ((-active).clamp_min(0) ** 2 + (active - 1).clamp_min(0) ** 2).sum(-1)
        return e.sum() + identity_prior * (ident ** 2).sum(), PoseState(rot, trans, weights)

    opt = torch.optim.LBFGS([omega, trans, active, ident], max_iter=iterations, history_size=20,
                            line_search_fn="strong_wolfe")

    def closure() -> Tensor:
        opt.zero_grad()
        total = evaluate()[0]
        total.backward()
        return total

    opt.step(closure)
    with torch.no_grad():
        _, new = evaluate()
    return PoseState(new.rot.detach(), new.trans.detach(), new.weights.detach().clamp(0, 1)), ident.detach()


def solve_identity(model: FitModel, identity_deltas: np.ndarray, views: FitViews, state: PoseState,
                   network: torch.nn.Module, *, outer: int = 2, prior: float = 100.0, identity_prior: float = 20.0,
                   edge_weight: float = 1.0, eyelid_weight: float = 0.2, iterations: int = 40,
                   supersample: int = 2, extra_points: np.ndarray | None = None,
                   extra_weight: float = 0.25) -> tuple[np.ndarray, PoseState]:
    """Estimate the identity shared by the frames of `views` (see the module docstring).

    Args:
        model: the model with the *mean* neutral (identity 0).
        identity_deltas: (I, V, 3) cm per unit.
        views, state: the frames used and their rigid start; `views.target` holds the 68
            Multi-PIE points, then the face-mesh points `extra_points` (if any).
        identity_prior: lambda_id, 256-crop pixel^2 per unit^2, summed over the frames' energies.
        extra_points: (E,) face-mesh indices of the targets past the 68, or None. They count
            from the first round anchored on a render (they have no model vertex before), with
            weight `extra_weight` each.
    Returns:
        identity (I,) float32 and the frames' final states.
    """
    id_t = torch.as_tensor(np.asarray(identity_deltas, np.float32), device=model.neutral.device)
    identity = torch.zeros(id_t.shape[0])
    b, c = views.seen.shape
    extra = np.zeros(0, np.int64) if extra_points is None else np.asarray(extra_points, np.int64)
    if views.target.shape[2] != 68 + len(extra):
        raise ValueError(f"views.target: expected {68 + len(extra)} points (68 + extra_points), found "
                         f"{views.target.shape[2]}")
    indices = np.concatenate([MEDIAPIPE_TO_68, extra])
    fallback = landmark_anchors(model, b, c, len(indices))
    w68 = torch.as_tensor(landmark_weights("all", eyelid=eyelid_weight), device=model.neutral.device)
    base = model.neutral.clone()
    for r in range(outer + 1):
        model.neutral = base + torch.einsum("i,ivd->vd", identity, id_t)
        anchors = fallback if r == 0 else _render_anchors(model, views, state, network, fallback, supersample,
                                                          indices)[0]
        model.neutral = base
        w_extra = anchors.rendered.to(w68.dtype)[..., None] * extra_weight  # (B, C, 1)
        w_lm = torch.cat([w68.expand(b, c, 68), w_extra.expand(b, c, len(extra))], -1)
        state, identity = _identity_step(model, id_t, views, anchors, state, identity, w_lm, prior=prior,
                                         identity_prior=identity_prior, edge_weight=edge_weight,
                                         iterations=iterations)
    model.neutral = base
    return identity.numpy().astype(np.float32), state
