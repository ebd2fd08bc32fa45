"""Per-frame parameter solves that match render flow to plate flow (PAPERS.md §2, temporal part).

Energy of frame i with its neighbours' parameters held (the paper's plate flow, against both
neighbours; `nodes.flow.geometric` gives the render flow G)::

    E_i(p_i) = m_(i-1) mean_(x in cover(p_(i-1))) |F*_(i-1)(x) - G(p_(i-1), p_i)(x)|^2     (prev)
             + m_i     mean_(x in cover(p_i))     |F*_i(x)     - G(p_i, p_(i+1))(x)|^2     (next)
             + s       mean_x |G(p_(i-1), p_i)(x) - G(p_i, p_(i+1))(x)|^2                  (self flow)
             + lambda  sum_j ((p_ij - p0_ij) / scale_j)^2                                   (prior)

`F*_f` is the plate flow from frame f to f + 1 (pixels), `m` says whether the term exists
(the neighbour is there and not failed). Unknowns: rotation (axis-angle, rad), translation
(cm) and optionally some expression weights; the prior scales are 0.01 rad, 0.1 cm and 0.1.

Solver: Levenberg-Marquardt (`nodes.geometry.lm`: one try per iteration, lambda x 0.3 on an
accepted step and x 10 on a rejected one, weights projected onto [0, 1]) with a fixed
iteration count, per frame (frames never share a
line search or a damping factor; the nodes solve one frame per call, so a frame's result
does not depend on which frames are solved with it: chunk-invariance of the windowed
nodes). The Jacobian is by
central differences in float64 (`_jacobian_fd`, one batched evaluation); the
coverage (which triangle is under which pixel) is rasterized again at every iteration.

Torch at module level: import from node `run()` methods only.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..geometry.lm import LMSchedule, levenberg_marquardt
from ..geometry.lm import LMSchedule, levenberg_marquardt
from ..geometry.rotation import axis_angle_to_rotmat_torch as axis_angle_to_rotmat
from ..flow.geometric import Coverage, coverage, surface_flow

__all__ = ["FlowModel", "Terms", "solve_frames", "frame_energies", "PRIOR_SCALES", "FLOW_SCHEDULE"]

PRIOR_SCALES = (0.01, 0.1, 0.1)
"""Units of the prior: rotation 0.01 rad, translation 0.1 cm, weights 0.1."""


@dataclass
class FlowModel:
    """Face model, camera and the unknowns, as float64 tensors for the solves.

    Attributes:
        neutral: (V, 3) cm; deltas: (K, V, 3) cm per unit weight; faces: (T, 3) int64.
        world_to_camera: (4, 4); intrinsics: (4,) fx fy cx cy; height, width: pixels.
        free: (P,) int64 indices into the parameter vector [rot(3), trans(3), weights(K)]
            that the solves move.
        stride: residual pixel stride.
    """

    neutral: Tensor
    deltas: Tensor
    faces: Tensor
    world_to_camera: Tensor
    intrinsics: Tensor
    height: int
    width: int
    free: Tensor
    stride: int = 1

    @classmethod
    def build(cls, neutral: np.ndarray, deltas: np.ndarray, faces: np.ndarray, world_to_camera: np.ndarray,
              intrinsics: list[float], height: int, width: int, shapes: list[int], *, stride: int = 1,
              device: str = "cpu") -> "FlowModel":
        """Build from numpy; `shapes` are the expression indices that move with the pose."""
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float64, device=device)  # noqa: E731
        free = torch.as_tensor(np.r_[np.arange(6), 6 + np.asarray(shapes, np.int64)], dtype=torch.long,
                               device=device)
        return cls(t(neutral), t(deltas), torch.as_tensor(np.asarray(faces, np.int64), device=device),
                   t(world_to_camera), t(intrinsics), int(height), int(width), free, int(stride))

    def cam(self, b: int) -> tuple[Tensor, Tensor]:
        return self.world_to_camera.expand(b, 4, 4), self.intrinsics.expand(b, 4)

    def vertices(self, x: Tensor) -> Tensor:
        """(B, 6 + K) parameters -> (B, V, 3) world vertices, cm."""
        k, v = self.deltas.shape[:2]
        local = (self.neutral.reshape(-1) + x[:, 6:] @ self.deltas.reshape(k, -1)).reshape(-1, v, 3)
        return local @ axis_angle_to_rotmat(x[:, :3]).transpose(1, 2) + x[:, None, 3:6]

    def cover(self, x: Tensor) -> Coverage:
        e, k = self.cam(x.shape[0])
        return coverage(self.vertices(x), self.faces, e, k, self.height, self.width, stride=self.stride)

    def corners(self, x: Tensor, cover: Coverage) -> Tensor:
        """(B, 6 + K) parameters -> (B, N, 3, 3) posed corners of the covered pixels' triangles."""
        ids = self.faces[cover.triangle]  # (B, N, 3)
        local = self.neutral[ids] + torch.einsum("bk,kbnjd->bnjd", x[:, 6:], self.deltas[:, ids])
        rot = axis_angle_to_rotmat(x[:, :3])
        return torch.einsum("bij,bnkj->bnki", rot, local) + x[:, None, None, 3:6]

    def prepare(self, x: Tensor, cover: Coverage) -> "_Posable":
        """Precompute what `corners` needs when only the free unknowns change (from x)."""
        ids = self.faces[cover.triangle]
        shapes = self.free[6:] - 6
        fixed = torch.ones(self.deltas.shape[0], dtype=torch.bool, device=x.device)
        fixed[shapes] = False
        w_fixed = torch.where(fixed, x[:, 6:], torch.zeros_like(x[:, 6:]))
        d = self.deltas[:, ids] if self.deltas.shape[0] else None  # (K, B, N, 3, 3)
        base = self.neutral[ids]
        if d is not None:
            base = base + torch.einsum("bk,kbnjd->bnjd", w_fixed, d)
        return _Posable(base, d[shapes] if d is not None else base.new_zeros((0,) + base.shape))


@dataclass
class _Posable:
    """Corners of covered pixels as a function of the free unknowns z = [rot, trans, free weights]."""

    base: Tensor   # (B, N, 3, 3) local corners with the fixed weights
    free: Tensor   # (Kf, B, N, 3, 3) the free shapes at the corners

    def corners(self, z: Tensor) -> Tensor:
        """(B * n, P) unknowns (n sets per frame, frame-major) -> (B * n, N, 3, 3) world corners, cm."""
        b = self.base.shape[0]
        zz = z.reshape(b, -1, z.shape[-1])
        local = self.base[:, None]
        if len(self.free):
            local = local + torch.einsum("bsk,kbnjd->bsnjd", zz[..., 6:], self.free)
        rot = axis_angle_to_rotmat(zz[..., :3])
        out = torch.einsum("bsij,bsnkj->bsnki", rot, local.expand(b, zz.shape[1], *self.base.shape[1:])) + \
            zz[:, :, None, None, 3:6]
        return out.reshape(-1, *self.base.shape[1:])


@dataclass
class Terms:
    """What each solved frame's energy contains (module docstring); B frames.

    Attributes:
        prev_x: (B, 6 + K) parameters of frame i - 1 (anything where `prev_on` is False).
        next_x: (B, 6 + K) parameters of frame i + 1.
        prev_on, next_on: (B,) bool, the prev / next plate-flow terms exist.
        prev_flow: (B, H, W, 2) plate flow F*_(i-1), pixels; next_flow: (B, H, W, 2) F*_i.
        plate_weight: weight of the plate-flow terms (0 for pure self flow).
        self_weight: s, weight of the self-flow term (needs both neighbours).
        prior_x: (B, 6 + K) the initial values; prior_weight: lambda (0 = none).
    """

    prev_x: Tensor
    next_x: Tensor
    prev_on: Tensor
    next_on: Tensor
    prev_flow: Tensor
    next_flow: Tensor
    plate_weight: float = 1.0
    self_weight: float = 0.0
    prior_x: Tensor | None = None
    prior_weight: float = 0.0


def _sample(flow: Tensor, cover: Coverage) -> Tensor:
    b = flow.shape[0]
    return flow.reshape(b, -1, 2).gather(1, cover.pixel[..., None].expand(-1, -1, 2))


def _scatter(values: Tensor, cover: Coverage) -> tuple[Tensor, Tensor]:
    b = values.shape[0]
    hw = cover.height * cover.width
    idx = cover.pixel[..., None].expand(-1, -1, 2)
    img = values.new_zeros(b, hw, 2).scatter(1, idx, torch.where(cover.valid[..., None], values, 0.0))
    mask = torch.zeros(b, hw, dtype=values.dtype, device=values.device).scatter(1, cover.pixel,
                                                                                cover.valid.to(values.dtype))
    return img, mask


def _prior_scale(model: FlowModel) -> Tensor:
    p = model.free
    r, t, w = PRIOR_SCALES
    scale = torch.full(p.shape, w, dtype=torch.float64, device=p.device)
    scale[p < 6] = t
    scale[p < 3] = r
    return scale


def _residuals(model: FlowModel, z: Tensor, terms: Terms, cov_prev: Coverage, cov_self: Coverage,
               c_prev: Tensor, c_next_target: Tensor, pose_prev: "_Posable", pose_self: "_Posable") -> Tensor:
    """(B, P) unknowns -> (B, M) weighted residuals (squared sum = E_i)."""
    x = z
    b = x.shape[0]
    e, k = model.cam(b)
    out = []
    g_prev = g_next = None
    if terms.plate_weight > 0 or terms.self_weight > 0:
        g_prev = surface_flow(c_prev, pose_prev.corners(z), model.faces, cov_prev, e, k)  # frame i-1 pixels
        g_next = surface_flow(pose_self.corners(z), c_next_target, model.faces, cov_self, e, k)  # frame i
    if terms.plate_weight > 0:
        for g, cov, target, on in ((g_prev, cov_prev, terms.prev_flow, terms.prev_on),
                                   (g_next, cov_self, terms.next_flow, terms.next_on)):
            w = cov.valid.to(x.dtype) * on.to(x.dtype)[:, None]
            n = cov.valid.sum(1).clamp_min(1).to(x.dtype)
            scale = (w * (terms.plate_weight / n)[:, None]).sqrt()[..., None]
            out.append(((_sample(target, cov) - g) * scale).reshape(b, -1))
    if terms.self_weight > 0:
        a, ma = _scatter(g_prev, cov_prev)
        c, mc = _scatter(g_next, cov_self)
        both = ma * mc * (terms.prev_on & terms.next_on).to(x.dtype)[:, None]
        n = both.sum(1).clamp_min(1)
        out.append(((a - c) * (both * (terms.self_weight / n)[:, None]).sqrt()[..., None]).reshape(b, -1))
    if terms.prior_weight > 0 and terms.prior_x is not None:
        p0 = terms.prior_x.index_select(1, model.free)
        out.append((z - p0) / _prior_scale(model) * terms.prior_weight ** 0.5)
    return torch.cat(out, 1)


def _rep(value, n: int, dim: int = 0):
    """Repeat every tensor of a Coverage / _Posable / Terms / tensor n times along its batch axis."""
    if isinstance(value, Tensor):
        return value.repeat_interleave(n, dim)
    if isinstance(value, Coverage):
        return Coverage(*(_rep(v, n) for v in value[:3]), value.height, value.width)
    if isinstance(value, _Posable):
        return value  # its corners() takes n unknown sets per frame
    if isinstance(value, Terms):
        return Terms(*(_rep(getattr(value, k), n) for k in ("prev_x", "next_x", "prev_on", "next_on", "prev_flow",
                                                              "next_flow")),
                     value.plate_weight, value.self_weight,
                     None if value.prior_x is None else _rep(value.prior_x, n), value.prior_weight)
    return value


def _jacobian_fd(f, z: Tensor, caches: tuple, terms: Terms, model: FlowModel, h: float = 1e-6) -> Tensor:
    """(B, M, P) Jacobian of the residuals by central differences (float64, one batched call).

    Why not forward-mode AD: `torch.func.jvp` under `vmap` runs the projection through
    decomposed primitives at ~10x the cost of the plain forward; the residuals are smooth
    (rational in the unknowns) and float64 central differences with h = 1e-6 are accurate to
    about 1e-9 relative.
    """
    b, p = z.shape
    n = 2 * p
    eye = torch.eye(p, dtype=z.dtype, device=z.device)
    zz = (z[:, None, :] + h * torch.cat([eye, -eye])[None]).reshape(b * n, p)
    rep = [_rep(c, n) for c in caches]
    r = _residuals(model, zz, _rep(terms, n), *rep).reshape(b, 2, p, -1)
    return ((r[:, 0] - r[:, 1]) / (2 * h)).transpose(1, 2)


FLOW_SCHEDULE = LMSchedule(lam0=1e-3, down=0.3, up=10.0, lam_min=0.0, lam_max=float("inf"), tries=1, rel_tol=0.0,
                            diag_floor=1e-12, floor=0.0, stop_when_stuck=False)
"""`nodes.geometry.lm`'s schedule for the plate-flow solves: lambda x 0.3 after a step that lowers
the frame's energy, x 10 otherwise, one trial step per iteration and no stopping rule (a fixed
count of iterations: each costs a rasterization and 2P + 1 batched residual evaluations, and a
node's `iterations` parameter says how many), no bounds on lambda, no Tikhonov floor."""


def solve_frames(model: FlowModel, x0: Tensor, terms: Terms, *, iterations: int = 8,
                 damping: float = 1e-3) -> Tensor:
    """Minimize E_i for B frames independently (module docstring) by Levenberg-Marquardt.

    `nodes.geometry.lm` with `FLOW_SCHEDULE`; the weights are projected onto [0, 1] after
    every step (the solver's `retract`). The residuals are re-defined at each linearization
    point x: the frame's own coverage (which triangle is under which pixel) is rasterized at x,
    and a trial step x' is evaluated with the coverage at x' (so the residual count changes).

    Args:
        model: the FlowModel (its `free` unknowns move).
        x0: (B, 6 + K) float64 start (and the values of the fixed parameters).
        terms: the energy's terms.
        iterations: LM iterations (fixed).
        damping: initial Marquardt damping, relative to diag(J^T J).
    Returns:
        (B, 6 + K) float64 solved parameters; weights clamped to [0, 1].
    """
    free = model.free
    cov_prev = model.cover(terms.prev_x)
    c_prev = model.corners(terms.prev_x, cov_prev)
    is_weight = free >= 6

    def full(z: Tensor) -> Tensor:
        return x0.index_copy(1, free, z)

    def setup(z: Tensor) -> tuple[Coverage, Tensor, _Posable, _Posable]:
        """Coverage of the frame's own render at z and what the residuals need at z."""
        xc = full(z)
        cov_self = model.cover(xc)
        return cov_self, model.corners(terms.next_x, cov_self), model.prepare(xc, cov_prev), \
            model.prepare(xc, cov_self)

    seen: dict[str, tuple[Tensor, tuple]] = {}  # the last trial point's set-up, reused when it is accepted

    def state_at(z: Tensor) -> tuple:
        if "trial" in seen and torch.equal(seen["trial"][0], z):
            return seen["trial"][1]
        if "at" in seen and torch.equal(seen["at"][0], z):
            return seen["at"][1]
        return setup(z)

    def residuals(z: Tensor) -> Tensor:
        state = state_at(z)
        seen["trial"] = (z, state)
        return _residuals(model, z, terms, cov_prev, state[0], c_prev, *state[1:])

    def normal(z: Tensor, _r: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        state = state_at(z)
        seen["at"] = (z, state)
        caches = (cov_prev, state[0], c_prev, *state[1:])
        r = _residuals(model, z, terms, *caches)
        jac = _jacobian_fd(None, z, caches, terms, model)
        jt = jac.transpose(1, 2)
        return jt @ jac, (jt @ r[..., None])[..., 0], r

    def retract(z: Tensor, step: Tensor) -> Tensor:
        z_new = z + step
        return torch.where(is_weight, z_new.clamp(0.0, 1.0), z_new)

    schedule = dataclasses.replace(FLOW_SCHEDULE, lam0=damping)
    out = levenberg_marquardt(residuals, normal, x0.index_select(1, free), iterations=iterations,
                              schedule=schedule, retract=retract)
    return full(out.x)


def frame_energies(model: FlowModel, x: Tensor, terms: Terms) -> Tensor:
    """E_i of B frames at parameters `x` (module docstring), no solve.

    Args:
        model: the FlowModel.
        x: (B, 6 + K) float64 parameters of the frames.
        terms: their energy's terms (as for `solve_frames`).
    Returns:
        (B,) float64 energies; the plate-flow terms are mean squared flow differences, pixels^2.
    """
    cov_prev = model.cover(terms.prev_x)
    cov_self = model.cover(x)
    r = _residuals(model, x.index_select(1, model.free), terms, cov_prev, cov_self,
                   model.corners(terms.prev_x, cov_prev), model.corners(terms.next_x, cov_self),
                   model.prepare(x, cov_prev), model.prepare(x, cov_self))
    return (r * r).sum(1)
