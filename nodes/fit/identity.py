"""Identity (the model's 40 shape components) from the landmarks of one or a few frames.

Unknowns: one identity vector `a` (I,) shared by the frames, and per frame the rigid pose
and the jaw and mouth weights. Energy: the frames' landmark energies (anchored, as in
`nodes.fit.solve`), optionally their photometric energies (`nodes.fit.photometric`: with
the frames' several poses a multi-view constraint on the shape), + `lambda_id |a|^2` (the
components are N(0, 1) a priori) + the expression prior. Alternates with re-anchoring on
renders like `fit_stages`.

Solver: Levenberg-Marquardt (`nodes.geometry.lm`, the stages' schedule `STAGE_SCHEDULE`) in
float64 on all the unknowns together (bundle adjustment): the normal equations couple each
frame's block (pose and shapes) to the shared identity, and the (B P + I)-square system is
solved dense (B P + I is a few hundred). L-BFGS on the same
energy stalled with the identity near the mean: its unknowns mix radians, centimetres and
unit weights, and the energy's valley along pitch against face proportions is long.

Torch at the top: import from node `run()` methods only.
"""

from __future__ import annotations

from typing import Callable

import numpy as np
import torch
from torch import Tensor

from ..geometry.lm import levenberg_marquardt
from ..landmarks.correspondence import MEDIAPIPE_TO_68
from .energy import axis_angle_to_rotmat, landmark_weights
from .photometric import PhotoSamples, PhotoTerm
from .solve import (SOLVE_DTYPE, STAGE_SCHEDULE, PoseState, _anchored, _render_anchors, _stage_jacobian,
                    _stage_residuals, in_dtype, jaw_shapes, mouth_shapes)
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
    out_dt = state.rot.dtype
    neutral, deltas = in_dtype(_anchored(model, anchors), SOLVE_DTYPE)
    id_d = at_anchors(identity_deltas, anchors.vertices, anchors.bary).to(SOLVE_DTYPE)  # (B, C, L, I, 3)
    views, anchors, state, identity, w_lm, photo = in_dtype((views, anchors, state, identity, w_lm, photo),
                                                            SOLVE_DTYPE)
    dev, dt = neutral.device, neutral.dtype
    b = state.rot.shape[0]
    shapes = torch.as_tensor(sorted(set(jaw_shapes(model.names)) | set(mouth_shapes(model.names))), device=dev)
    n_p, n_i = 6 + len(shapes), identity.shape[0]
    use_photo = photo is not None and photo_weight > 0
    if use_photo:  # the photometric unknowns per frame: the active weights, then the identity
        p_basis = torch.cat([photo.deltas[:, :, :, shapes].transpose(-1, -2),
                             at_anchors(identity_deltas, photo.vertices, photo.bary).to(SOLVE_DTYPE)
                             .transpose(-1, -2)], -1)

    photo_cache: dict = {}  # the term about the current inactive weights (`PhotoTerm.about`)

    def photo_term(weights0: Tensor) -> PhotoTerm:
        return PhotoTerm.about(photo, views, photo_weight, weights0, shapes, p_basis, cache=photo_cache)

    shaped: dict = {}  # the anchors' neutral with the last identity (residuals, then the Jacobian at it)

    def neutral_at(ident: Tensor) -> Tensor:
        """(B, C, L, 3) the anchors' neutral plus identity (I,)'s shape, cm."""
        if "ident" not in shaped or not torch.equal(shaped["ident"], ident):
            shaped["ident"], shaped["neutral"] = ident.clone(), neutral + torch.einsum("i,bclid->bcld", ident, id_d)
        return shaped["neutral"]

    def landmark_fn(rot0: Tensor, weights0: Tensor, ident: Tensor) -> Callable[[Tensor], Tensor]:
        return _stage_residuals(neutral_at(ident), deltas, views, anchors, rot0, weights0, shapes, w_lm, prior=prior,
                                edge_weight=edge_weight, rigid_prior=None, rigid_prior_weight=0.0)

    held: dict = {}

    def linear_unknowns(x: Tensor, ident: Tensor) -> Tensor:
        """(B, S + I) the photometric term's linear unknowns: the active weights, then the identity;
        the same tensor while its values are (`PhotoTerm` then sums its basis once for the residuals
        at a step and the Jacobian after it)."""
        lin = torch.cat([x[:, 6:], ident.expand(b, n_i)], 1)
        if "lin" not in held or not torch.equal(held["lin"], lin):
            held["lin"] = lin
        return held["lin"]

    def residuals(rot0: Tensor, weights0: Tensor, x: Tensor, ident: Tensor) -> Tensor:
        """(B, M) residuals of the frames (without the identity prior) at x (B, P), ident (I,)."""
        r = landmark_fn(rot0, weights0, ident)(x)
        if not use_photo:
            return r
        lin = linear_unknowns(x, ident)
        return torch.cat([r, photo_term(weights0).residuals(x[:, :3], rot0, x[:, 3:6], lin)], 1)

    def jacobians(rot0: Tensor, weights0: Tensor, x: Tensor, ident: Tensor) -> tuple[Tensor, Tensor]:
        """(B, M, P) in the frames' unknowns and (B, M, I) in the identity, at omega = 0."""
        jac = _stage_jacobian(neutral_at(ident), deltas, views, rot0, weights0, shapes, w_lm, x, prior=prior,
                              edge_weight=edge_weight, rigid_prior=None, rigid_prior_weight=0.0, extra=id_d)
        jx, ji = jac[:, :, :n_p], jac[:, :, n_p:]
        if not use_photo:
            return jx, ji
        lin = linear_unknowns(x, ident)
        _, jp = photo_term(weights0).jacobian(rot0, x[:, 3:6], lin)
        return torch.cat([jx, jp[:, :, :n_p]], 1), torch.cat([ji, jp[:, :, n_p:]], 1)

    rot, weights, ident = state.rot.detach(), state.weights.detach(), identity.detach().to(dt)
    x = torch.cat([torch.zeros(b, 3, dtype=dt, device=dev), state.trans.detach(), weights[:, shapes]], 1)
    now = {"rot": rot, "weights": weights}
    root_prior = float(identity_prior) ** 0.5

    def split(z: Tensor) -> tuple[Tensor, Tensor]:
        """(1, B P + I) -> the frames' unknowns (B, P) and the identity (I,)."""
        return z[0, :b * n_p].reshape(b, n_p), z[0, b * n_p:]

    def all_residuals(z: Tensor) -> Tensor:
        """(1, B P + I) -> (1, B M + I): the frames' residuals, then the identity prior's."""
        xf, i = split(z)
        return torch.cat([residuals(now["rot"], now["weights"], xf, i).reshape(-1), root_prior * i])[None]

    def normal(z: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
        xf, i = split(z)
        rf = r[0, :-n_i].reshape(b, -1)
        jx, ji = jacobians(now["rot"], now["weights"], xf, i)  # (B, M, P), (B, M, I)
        h = torch.zeros(n, n, dtype=dt, device=dev)
        h[:b * n_p, :b * n_p] = torch.block_diag(*(jx.transpose(1, 2) @ jx))  # the frames' blocks
        coupling = (jx.transpose(1, 2) @ ji).reshape(b * n_p, n_i)  # each frame's coupling to the identity
        h[:b * n_p, b * n_p:] = coupling
        h[b * n_p:, :b * n_p] = coupling.T
        h[b * n_p:, b * n_p:] = torch.einsum("bmi,bmj->ij", ji, ji) + identity_prior * torch.eye(n_i, dtype=dt,
                                                                                                 device=dev)
        g = torch.cat([torch.einsum("bmp,bm->bp", jx, rf).reshape(-1),
                       torch.einsum("bmi,bm->i", ji, rf) + identity_prior * i])
        return h[None], g[None]

    def relinearize(z: Tensor, accepted: Tensor) -> Tensor:  # the rotation about the new pose
        xf, i = split(z)
        now["rot"] = axis_angle_to_rotmat(xf[:, :3]) @ now["rot"]
        now["weights"] = now["weights"].index_copy(1, shapes, xf[:, 6:])
        xf = torch.cat([torch.zeros(b, 3, dtype=dt, device=dev), xf[:, 3:]], 1)
        return torch.cat([xf.reshape(-1), i])[None]

    n = b * n_p + n_i
    with torch.no_grad():
        out = levenberg_marquardt(all_residuals, normal, torch.cat([x.reshape(-1), ident])[None],
                                  iterations=iterations, schedule=STAGE_SCHEDULE, relinearize=relinearize)
    x, ident = split(out.x)
    return in_dtype((PoseState(now["rot"], x[:, 3:6], now["weights"].clamp(0, 1)), ident), out_dt)


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
