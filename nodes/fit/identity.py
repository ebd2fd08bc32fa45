"""Identity (the model's 40 shape components) from the landmarks of one or a few frames.

Unknowns: one identity vector `a` (I,) shared by the frames, and per frame the rigid pose
and the jaw and mouth weights. Energy: the frames' landmark energies (anchored, as in
`nodes.fit.solve`), optionally their photometric energies (`nodes.fit.photometric`: with
the frames' several poses a multi-view constraint on the shape), + `lambda_id |a|^2` (the
components are N(0, 1) a priori) + the expression prior. Alternates with re-anchoring on
renders like `fit_stages`.

Solver: Levenberg-Marquardt on all the unknowns together (bundle adjustment): the normal
equations couple each frame's block (pose and shapes) to the shared identity, and the
(B P + I)-square system is solved dense (B P + I is a few hundred). L-BFGS on the same
energy stalled with the identity near the mean: its unknowns mix radians, centimetres and
unit weights, and the energy's valley along pitch against face proportions is long.

Torch at the top: import from node `run()` methods only.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..landmarks.correspondence import MEDIAPIPE_TO_68
from .energy import axis_angle_to_rotmat, landmark_weights
from .photometric import PhotoSamples, PhotoTerm
from .solve import (PoseState, _anchored, _render_anchors, _stage_jacobian, _stage_residuals, jaw_shapes,
                    mouth_shapes)
from .views import Anchors, FitModel, FitViews, at_anchors, landmark_anchors

__all__ = ["solve_identity"]


def _identity_step(model: FitModel, identity_deltas: Tensor, views: FitViews, anchors: Anchors, state: PoseState,
                   identity: Tensor, w_lm: Tensor, *, prior: float, identity_prior: float, edge_weight: float,
                   iterations: int, photo: PhotoSamples | None = None,
                   photo_weight: float = 0.0) -> tuple[PoseState, Tensor]:
    """Levenberg-Marquardt on (pose, jaw and mouth weights) per frame and the shared identity.

    Returns:
        the frames' states and the identity (I,).
    """
    neutral, deltas = _anchored(model, anchors)
    id_d = at_anchors(identity_deltas, anchors.vertices, anchors.bary)  # (B, C, L, I, 3)
    dev, dt = neutral.device, neutral.dtype
    b = state.rot.shape[0]
    shapes = torch.as_tensor(sorted(set(jaw_shapes(model.names)) | set(mouth_shapes(model.names))), device=dev)
    n_p, n_i = 6 + len(shapes), identity.shape[0]
    use_photo = photo is not None and photo_weight > 0
    if use_photo:  # the photometric unknowns per frame: the active weights, then the identity
        p_basis = torch.cat([photo.deltas[:, :, :, shapes].transpose(-1, -2),
                             at_anchors(identity_deltas, photo.vertices, photo.bary).transpose(-1, -2)], -1)

    def photo_term(weights0: Tensor) -> PhotoTerm:
        return PhotoTerm.about(photo, views, photo_weight, weights0, shapes, p_basis)

    def landmark_fn(rot0: Tensor, weights0: Tensor, ident: Tensor) -> Callable[[Tensor], Tensor]:
        shape = torch.einsum("i,bclid->bcld", ident, id_d)
        return _stage_residuals(neutral + shape, deltas, views, anchors, rot0, weights0, shapes, w_lm, prior=prior,
                                edge_weight=edge_weight, rigid_prior=None, rigid_prior_weight=0.0)

    def residuals(rot0: Tensor, weights0: Tensor, x: Tensor, ident: Tensor) -> Tensor:
        """(B, M) residuals of the frames (without the identity prior) at x (B, P), ident (I,)."""
        r = landmark_fn(rot0, weights0, ident)(x)
        if not use_photo:
            return r
        lin = torch.cat([x[:, 6:], ident.expand(b, n_i)], 1)
        return torch.cat([r, photo_term(weights0).residuals(x[:, :3], rot0, x[:, 3:6], lin)], 1)

    def jacobians(rot0: Tensor, weights0: Tensor, x: Tensor, ident: Tensor) -> tuple[Tensor, Tensor]:
        """(B, M, P) in the frames' unknowns and (B, M, I) in the identity, at omega = 0."""
        shape = torch.einsum("i,bclid->bcld", ident, id_d)
        jac = _stage_jacobian(neutral + shape, deltas, views, rot0, weights0, shapes, w_lm, x, prior=prior,
                              edge_weight=edge_weight, rigid_prior=None, rigid_prior_weight=0.0, extra=id_d)
        jx, ji = jac[:, :, :n_p], jac[:, :, n_p:]
        if not use_photo:
            return jx, ji
        lin = torch.cat([x[:, 6:], ident.expand(b, n_i)], 1)
        _, jp = photo_term(weights0).jacobian(rot0, x[:, 3:6], lin)
        return torch.cat([jx, jp[:, :, :n_p]], 1), torch.cat([ji, jp[:, :, n_p:]], 1)

    def total(r: Tensor, ident: Tensor) -> Tensor:
        return (r * r).sum() + identity_prior * (ident * ident).sum()

    rot, weights, ident = state.rot.detach(), state.weights.detach(), identity.detach().to(dt)
    x = torch.cat([torch.zeros(b, 3, dtype=dt, device=dev), state.trans.detach(), weights[:, shapes]], 1)
    n = b * n_p + n_i
    eye = torch.eye(n, dtype=dt, device=dev)
    with torch.no_grad():
        r = residuals(rot, weights, x, ident)
        cost = total(r, ident)
        lam = 1e-3
        for _ in range(iterations):
            jx, ji = jacobians(rot, weights, x, ident)  # (B, M, P), (B, M, I)
            h = torch.zeros(n, n, dtype=dt, device=dev)
            for f in range(b):  # the frames' blocks and their coupling to the identity
                s = slice(f * n_p, (f + 1) * n_p)
                h[s, s] = jx[f].T @ jx[f]
                h[s, b * n_p:] = jx[f].T @ ji[f]
                h[b * n_p:, s] = h[s, b * n_p:].T
            h[b * n_p:, b * n_p:] = torch.einsum("bmi,bmj->ij", ji, ji) + identity_prior * torch.eye(n_i, dtype=dt,
                                                                                                     device=dev)
            g = torch.cat([torch.einsum("bmp,bm->bp", jx, r).reshape(-1),
                           torch.einsum("bmi,bm->i", ji, r) + identity_prior * ident])
            diag = torch.diagonal(h).clamp_min(1e-9)
            improved = False
            for _try in range(6):
                step = -torch.linalg.solve(h + lam * torch.diag(diag) + 1e-9 * eye, g)
                x_new = x + step[:b * n_p].reshape(b, n_p)
                i_new = ident + step[b * n_p:]
                r_new = residuals(rot, weights, x_new, i_new)
                cost_new = total(r_new, i_new)
                if cost_new < cost:
                    improved = True
                    break
                lam = min(lam * 10.0, 1e8)
            if not improved:
                break
            gain = float((cost - cost_new) / cost.clamp_min(1e-12))
            lam = max(lam * 0.3, 1e-7)
            rot = axis_angle_to_rotmat(x_new[:, :3]) @ rot  # re-linearize the rotation about the new pose
            weights = weights.index_copy(1, shapes, x_new[:, 6:])
            x = torch.cat([torch.zeros(b, 3, dtype=dt, device=dev), x_new[:, 3:]], 1)
            ident, r, cost = i_new, r_new, cost_new
            if gain < 1e-4:
                break
    return PoseState(rot, x[:, 3:6], weights.clamp(0, 1)), ident


def solve_identity(model: FitModel, identity_deltas: np.ndarray, views: FitViews, state: PoseState,
                   network: torch.nn.Module, *, outer: int = 2, prior: float = 100.0, identity_prior: float = 20.0,
                   edge_weight: float = 1.0, eyelid_weight: float = 0.2, iterations: int = 15,
                   supersample: int = 2, extra_points: np.ndarray | None = None,
                   extra_weight: float = 0.25, photometric_weight: float = 0.0,
                   photometric: dict | None = None) -> tuple[np.ndarray, PoseState]:
    """Estimate the identity shared by the frames of `views` (see the module docstring).

    Args:
        model: the model with the *mean* neutral (identity 0).
        identity_deltas: (I, V, 3) cm per unit.
        views, state: the frames used and their rigid start; `views.target` holds the 68
            Multi-PIE points, then the face-mesh points `extra_points` (if any).
        identity_prior: lambda_id, 256-crop pixel^2 per unit^2, summed over the frames' energies.
        iterations: Levenberg-Marquardt iterations per round (at most).
        extra_points: (E,) face-mesh indices of the targets past the 68, or None. They count
            from the first round anchored on a render (they have no model vertex before), with
            weight `extra_weight` each.
        photometric_weight: w_p of the photometric term (`nodes.fit.photometric`, needs
            `views.plates`) in the rounds anchored on a render; photometric: its sampling arguments.
    Returns:
        identity (I,) float32 and the frames' final states.
    """
    id_t = torch.as_tensor(np.asarray(identity_deltas, np.float32), device=model.neutral.device)
    identity = torch.zeros(id_t.shape[0], device=model.neutral.device)
    b, c = views.seen.shape
    extra = np.zeros(0, np.int64) if extra_points is None else np.asarray(extra_points, np.int64)
    if views.target.shape[2] != 68 + len(extra):
        raise ValueError(f"views.target: expected {68 + len(extra)} points (68 + extra_points), found "
                         f"{views.target.shape[2]}")
    if photometric_weight > 0 and views.plates is None:
        raise ValueError("views.plates: expected the plate's crops for the photometric term, found None")
    photo_args = dict(photometric or {}) if photometric_weight > 0 else None
    indices = np.concatenate([MEDIAPIPE_TO_68, extra])
    fallback = landmark_anchors(model, b, c, len(indices))
    w68 = torch.as_tensor(landmark_weights("all", eyelid=eyelid_weight), device=model.neutral.device)
    base = model.neutral.clone()
    for r in range(outer + 1):
        samples = None
        if r == 0:
            anchors = fallback
        else:
            model.neutral = base + torch.einsum("i,ivd->vd", identity, id_t)
            anchors, _, samples = _render_anchors(model, views, state, network, fallback, supersample, indices,
                                                  photometric=photo_args)
            model.neutral = base
            if samples is not None:  # the samples' neutral without the identity (the step adds it)
                samples = samples._replace(neutral=at_anchors(base, samples.vertices, samples.bary))
        w_extra = anchors.rendered.to(w68.dtype)[..., None] * extra_weight  # (B, C, 1)
        w_lm = torch.cat([w68.expand(b, c, 68), w_extra.expand(b, c, len(extra))], -1)
        state, identity = _identity_step(model, id_t, views, anchors, state, identity, w_lm, prior=prior,
                                         identity_prior=identity_prior, edge_weight=edge_weight,
                                         iterations=iterations, photo=samples, photo_weight=photometric_weight)
    model.neutral = base
    return identity.cpu().numpy().astype(np.float32), state
