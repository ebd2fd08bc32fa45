"""The optical variant of the plate-flow solve: the render flow is the same optical flow
(`nodes.flow.dense`) run on renders of the fit, not the exact screen motion of the surface.

Energy of frame i (neighbours' parameters held; m as in `nodes.temporal.flowfit`)::

    E_i(p_i) = m_(i-1) mean_(x: alpha(p_(i-1)) > 1/2) |F*_(i-1)(x) - D(R(p_(i-1)), R(p_i))(x)|^2
             + m_i     mean_(x: alpha(p_i) > 1/2)     |F*_i(x)     - D(R(p_i), R(p_(i+1)))(x)|^2

`R(p)` is the render (albedo and SH of the appearance), `D` the dense flow with the plates'
settings. The paper's argument for it: the flow method's own errors on the plates are partly
repeated on the renders and cancel. Its costs: the render must look like the plate (a
textured albedo, e.g. `fit.EstimateAppearance`'s; the default albedo has no texture to flow
on) and each residual evaluation is a render and two flows. Solved by Levenberg-Marquardt
(`nodes.geometry.lm`, one try per iteration, as `nodes.temporal.flowfit`) with a
finite-difference Jacobian (`solve_frame_optical`), one frame per call (chunk-invariant like
the geometric solve).

Torch at module level: import from node `run()` methods only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..flow.dense import FlowSettings, dense_flow
from ..geometry.lm import LMSchedule, levenberg_marquardt
from .flowfit import PRIOR_SCALES, FlowModel, Terms

__all__ = ["RenderScene", "optical_energies", "solve_frame_optical"]


@dataclass
class RenderScene:
    """What the renders of `optical_energies` need (float32 tensors on the solve's device).

    Attributes:
        faces: (T, 3) int64 triangles drawn; adjacency: `geometry.mesh.triangle_adjacency(faces)`.
        albedo: (1, V, 3) linear; sh: (1, 9, 3); background: (3,) linear.
        settings: the dense flow's settings (those of the plate flow).
    """

    faces: Tensor
    adjacency: Tensor
    albedo: Tensor
    sh: Tensor
    background: Tensor
    settings: FlowSettings

    @classmethod
    def build(cls, faces: np.ndarray, albedo: np.ndarray, sh: np.ndarray, background: np.ndarray,
              settings: FlowSettings, device: str = "cpu") -> "RenderScene":
        from ..geometry.mesh import triangle_adjacency

        f = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32, device=device)  # noqa: E731
        faces = np.asarray(faces, np.int64)
        return cls(torch.as_tensor(faces, device=device), torch.as_tensor(triangle_adjacency(faces), device=device),
                   f(albedo)[None], f(sh)[None], f(background), settings)

    def render(self, model: FlowModel, x: Tensor) -> tuple[Tensor, Tensor]:
        """(B, 6 + K) parameters -> images (B, 3, H, W) linear and alpha (B, H, W)."""
        from ..render.renderer import render_mesh

        b = x.shape[0]
        e, k = model.cam(b)
        out = render_mesh(model.vertices(x).float(), self.faces, e.float(), k.float(), model.height, model.width,
                          albedo=self.albedo, sh=self.sh, background=self.background, adjacency=self.adjacency)
        return out.image.permute(0, 3, 1, 2), out.alpha


def _flows(first: Tensor, second: Tensor, settings: FlowSettings) -> Tensor:
    """dense_flow of N pairs without gradients: compiled on the CPU (as flow.OpticalFlow's plates)."""
    if first.device.type != "cpu":
        return dense_flow(first, second, settings)
    from ..flow.fast import dense_flow_numpy

    return torch.stack([torch.as_tensor(dense_flow_numpy(first[i:i + 1], second[i:i + 1], settings))
                        for i in range(first.shape[0])])


def optical_energies(scene: RenderScene, model: FlowModel, x: Tensor, terms: Terms) -> Tensor:
    """E_i (module docstring) of one frame at parameters x (1, 6 + K), pixels^2 (no gradient)."""
    with torch.no_grad():
        self_mask = scene.render(model, x)[1][0] > 0.5
        r = _residuals(scene, model, x, terms, neighbour_renders(scene, model, terms), self_mask)
    return (r * r).sum(1)


def neighbour_renders(scene: RenderScene, model: FlowModel, terms: Terms) -> tuple:
    with torch.no_grad():
        prev = scene.render(model, terms.prev_x)
        nxt = scene.render(model, terms.next_x)[0]
    return prev, nxt


def _residuals(scene: RenderScene, model: FlowModel, xs: Tensor, terms: Terms, rendered: tuple,
               self_mask: Tensor) -> Tensor:
    """(N, 6 + K) parameter sets of one frame -> (N, M) weighted residuals (squared sum = E_i), in
    one batched render and (up to) two batched flows; masks held (the neighbour's, and `self_mask`)."""
    (prev_img, prev_alpha), next_img = rendered
    n = xs.shape[0]
    img, _ = scene.render(model, xs)
    parts = []
    for on, first, second, mask, plate in (
            (terms.prev_on, prev_img.expand(n, -1, -1, -1), img, prev_alpha[0] > 0.5, terms.prev_flow[0]),
            (terms.next_on, img, next_img.expand(n, -1, -1, -1), self_mask, terms.next_flow[0])):
        if not bool(on[0]):
            continue
        flow = _flows(first, second, scene.settings).permute(0, 2, 3, 1).double()  # (N, H, W, 2)
        weight = (terms.plate_weight / mask.sum().clamp_min(1)) ** 0.5
        parts.append(((plate[None] - flow)[:, mask] * weight).reshape(n, -1))
    return torch.cat(parts, 1)


def solve_frame_optical(scene: RenderScene, model: FlowModel, x0: Tensor, terms: Terms, *,
                        iterations: int = 6, step: float = 0.5, damping: float = 1e-3) -> Tensor:
    """Minimize the optical E_i of one frame (module docstring) by Levenberg-Marquardt.

    The Jacobian is by central differences of `step` prior units (0.01 rad, 0.1 cm, 0.1 weight):
    the optical flow is continuous in the images but not smooth at the scale of float noise, and
    its autograd gradient through the warps is unreliable far from the solution (measured: 1e4x
    the finite difference). The 2P + 1 parameter sets of an iteration are rendered and flowed
    as one batch.

    Args:
        x0: (1, 6 + K) float64 start (and the fixed parameters' values).
        iterations: LM iterations.
    Returns:
        (1, 6 + K) float64 parameters; weights clamped to [0, 1].
    """
    free = model.free
    p = len(free)
    scale = torch.full((p,), PRIOR_SCALES[2], dtype=torch.float64, device=x0.device)
    scale[free < 6] = PRIOR_SCALES[1]
    scale[free < 3] = PRIOR_SCALES[0]
    is_weight = free >= 6
    rendered = neighbour_renders(scene, model, terms)
    eye = torch.eye(p, dtype=torch.float64, device=x0.device)
    schedule = LMSchedule(lam0=damping, lam_min=0.0, lam_max=float("inf"), tries=1, rel_tol=0.0, diag_floor=1e-12,
                          floor=0.0, stop_when_stuck=False)
    held: dict = {}

    def full(z: Tensor) -> Tensor:
        return x0.index_copy(1, free, z)

    def residuals(z: Tensor) -> Tensor:  # the mask held from the iteration's start
        if "mask" not in held:
            held["mask"] = scene.render(model, full(z))[1][0] > 0.5
        return _residuals(scene, model, full(z), terms, rendered, held["mask"])

    def normal(z: Tensor, r: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """J by central differences, and the residuals at z under z's own mask (they replace r)."""
        held["mask"] = scene.render(model, full(z))[1][0] > 0.5
        zs = torch.cat([z, z[0] + step * scale * torch.cat([eye, -eye])])  # (2P + 1, P)
        rr = _residuals(scene, model, x0.expand(len(zs), -1).index_copy(1, free, zs), terms, rendered, held["mask"])
        jac = ((rr[1:p + 1] - rr[p + 1:]) / (2 * step * scale[:, None])).T  # (M, P)
        return (jac.T @ jac)[None], (jac.T @ rr[0])[None], rr[:1]

    def retract(z: Tensor, dz: Tensor) -> Tensor:
        return torch.where(is_weight, (z + dz).clamp(0.0, 1.0), z + dz)

    with torch.no_grad():
        out = levenberg_marquardt(residuals, normal, x0.index_select(1, free), iterations=iterations,
                                  schedule=schedule, retract=retract)
    return full(out.x)
