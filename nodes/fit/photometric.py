"""Photometric term of the fit: the plate sampled at surface points of the head must show
the colour the render gives them.

After a render of the current estimate (`nodes.fit.views.render_crops`), every `stride`-th
covered pixel of each view's crop becomes a *sample*: the surface point under it (triangle +
barycentrics, like a landmark anchor) and the render's colour there. While the pose and the
shapes move, the sample's surface point moves with them and the plate's crop is read where
it projects (bilinearly, both images blurred by the same Gaussian):

    E_p = w_p * (1 / N_c) sum_i rho_i |P(pi_c(x_i(theta))) - c_i|^2 / sigma_0^2

with `P` the plate's blurred crop, `c_i` the render's blurred colour at sample i, `N_c` the
view's samples, `rho_i` a Huber weight (fixed per round from the residual at its start, so
that hair, teeth, occluders and a wrong background count little) and `sigma_0 = 0.01` linear
units. `w_p` is in the landmark energy's units (256-crop pixel^2): with `w_p = 68` a view's
photometric residual of 0.01 everywhere weighs as much as a 1 px error on each of the 68
landmarks (the nodes' default is 500, `nodes.fit.tuning.PHOTOMETRIC_WEIGHT`). The landmarks find the face from far; this term then holds the surface where the
plate shows it, which the landmarks (a network's reading, a few pixels noisy, with an
identity that is only estimated) pin less well, most of all in pitch.

Torch is imported at the top: import this module from node `run()` methods only.
"""

from __future__ import annotations

import threading
from typing import NamedTuple

import torch
from torch import Tensor

from ..geometry.image import gaussian_blur, image_to_crop, sample_bilinear
from .energy import axis_angle_to_rotmat, project_views, project_views_jacobian
from .views import FitModel, FitViews, _barycentrics, at_anchors

__all__ = ["PHOTO_UNIT", "RESIDUAL_SCALE_REFERENCE", "residual_scale_weight", "blurred_plates", "PhotoSamples",
           "photometric_samples", "photometric_residuals", "photometric_point_jacobian", "PhotoTerm"]

PHOTO_UNIT = 0.01
"""sigma_0: photometric residuals are measured in units of 0.01 (linear colour)."""

RESIDUAL_SCALE_REFERENCE = 0.05
"""A view's samples weigh `(RESIDUAL_SCALE_REFERENCE / s)^2` where its robust residual scale `s`
(1.4826 x the median |plate - render| at the round's start, linear colour) is larger: the
term counts as much as the model explains the plate (a maximum-likelihood weight, 1 / s^2).
Synthetic plates of the model itself give s = 0.013-0.049 (4 one-photo plates, default and
painted albedo), so their fits are unchanged to the bit; real photos give 0.34-0.50 with the
default albedo (skimage's astronaut, matplotlib's grace_hopper), whose residuals are the
model's mismatch (hair, brows, teeth, skin texture), not evidence of the pose: there the term,
at full weight 100 times the landmarks' energy, pulled the identity to norm 21 under a prior
of 100 and turned 1-LSB changes of the plate into 1.0 changes of expression weights (issue 30)."""


class PhotoSamples(NamedTuple):
    """Surface samples of one round (see the module docstring).

    Attributes:
        vertices: (B, C, N, 3) int64 triangle corners; bary: (B, C, N, 3) barycentrics.
        colour: (B, C, N, 3) the render's blurred colour at each sample, linear.
        weight: (B, C, N) rho_i / N_c (0 for padding and for views without a render).
        plates: (B * C, S, S, 3) the plate's crops, blurred as the render was.
        size: S, the crops' side (render pixels).
        neutral: (B, C, N, 3) the model's neutral at the samples, cm; deltas: (B, C, N, K, 3)
            its expression shapes there.
    """

    vertices: Tensor
    bary: Tensor
    colour: Tensor
    weight: Tensor
    plates: Tensor
    size: int
    neutral: Tensor
    deltas: Tensor


_BLURRED_PLATES: list[tuple[Tensor, int, float, torch.dtype, Tensor]] = []  # plates, _version, sigma, dtype, out
_BLURRED_PLATES_LOCK = threading.Lock()


def blurred_plates(plates: Tensor, sigma: float, dtype: torch.dtype) -> Tensor:
    """(N, S, S, 3) `gaussian_blur` of the (..., S, S, 3) `plates` (N crops) in `dtype`, cached for
    the last 4 plate tensors: a fit's rounds take samples from the same plates every round (the
    blur was 12 ms of each 8-frame round's 80-110 ms of sampling). A cached entry holds its
    tensor, so its storage is not reused while cached, and an in-place change (`_version`) is seen."""
    with _BLURRED_PLATES_LOCK:
        for src, version, sig, dt, out in _BLURRED_PLATES:
            if src is plates and version == plates._version and sig == sigma and dt == dtype:
                return out
    out = gaussian_blur(plates.reshape(-1, *plates.shape[-3:]).to(dtype), sigma)
    with _BLURRED_PLATES_LOCK:
        _BLURRED_PLATES.append((plates, plates._version, float(sigma), dtype, out))
        del _BLURRED_PLATES[:-4]
    return out


def residual_scale_weight(scale: Tensor) -> Tensor:
    """(N,) factor on each view's samples from its robust residual scale `scale` (N,), linear colour:
    exactly 1 up to `RESIDUAL_SCALE_REFERENCE`, then `(RESIDUAL_SCALE_REFERENCE / scale)^2`."""
    return torch.where(scale > RESIDUAL_SCALE_REFERENCE, (RESIDUAL_SCALE_REFERENCE / scale) ** 2,
                       torch.ones_like(scale))


def photometric_samples(model: FitModel, views: FitViews, image: Tensor, triangle: Tensor, pix: Tensor,
                        rendered: Tensor, *, stride: int = 4, sigma: float = 1.0, erode: int = 1,
                        huber: float = 3.0, state_points: Tensor | None = None,
                        frame_weight: Tensor | None = None) -> PhotoSamples:
    """The samples of one round, from a render of the current estimate.

    Args:
        model, views: as in `render_crops`; `views.plates` holds the plate's crops.
        image: (B * C, S, S, 3) the render's crops (linear, noise-free); triangle: (B * C, S, S)
            visible triangle (-1 none); pix: (B * C, V, 2) projected vertices, crop pixels.
        rendered: (B, C) bool, views whose render is usable (the face seen, the network found it).
        stride: every stride-th crop pixel along x and y is a sample candidate.
        sigma: Gaussian blur of render and plate, crop pixels (widens the basin; noise averages out).
        erode: covered pixels within this many pixels of the silhouette are left out (their
            blurred colour mixes in the background).
        huber: the Huber weight's threshold, in robust standard deviations (1.4826 x the
            median absolute residual of the view at the round's start).
        frame_weight: (B,) a factor on each frame's samples (None: 1). 0 leaves a frame out of
            the term: `nodes.fit.tuning.photometric_frame_weights` gives 0 to the frames whose
            plate the albedo was painted from.
    Returns:
        PhotoSamples.
    """
    if views.plates is None:
        raise ValueError("views.plates: expected the plate's crops for the photometric term, found None")
    b, c = views.boxes.shape[:2]
    n, s = triangle.shape[:2]
    dev, dt = image.device, image.dtype
    covered = (triangle >= 0).to(dt)[:, None]
    if erode > 0:  # a pixel counts when every pixel within `erode` of it is covered
        covered = -torch.nn.functional.max_pool2d(-covered, 2 * erode + 1, stride=1, padding=erode)
    grid = torch.zeros(s, s, dtype=torch.bool, device=dev)
    grid[stride // 2::stride, stride // 2::stride] = True
    keep = (covered[:, 0] > 0.5) & grid & rendered.reshape(n)[:, None, None]
    count = keep.flatten(1).sum(1)
    m = max(int(count.max().item()), 1)
    order = torch.argsort(keep.flatten(1).to(torch.int8), dim=1, descending=True, stable=True)[:, :m]  # (N, M)
    valid = torch.arange(m, device=dev)[None] < count[:, None]
    tri = triangle.flatten(1).gather(1, order).clamp_min(0)
    faces = torch.as_tensor(model.faces, device=dev)
    corner_ids = faces[tri]  # (N, M, 3)
    rows = torch.arange(n, device=dev)[:, None, None]
    corners = pix.detach()[rows, corner_ids]  # (N, M, 3, 2)
    centres = torch.stack([order % s, order // s], -1).to(dt)
    bary = _barycentrics(corners, centres)
    blurred = gaussian_blur(image.detach(), sigma)
    colour = blurred.reshape(n, s * s, 3).gather(1, order[..., None].expand(n, m, 3))
    plates = blurred_plates(views.plates, sigma, dt)  # (N, S, S, 3): the same plates every round
    # Huber weights from the residual at the start of the round (the anchors' own projection)
    resid = (sample_bilinear(plates, (bary[..., None] * corners).sum(-2)) - colour).norm(dim=-1)
    med = torch.where(valid, resid, torch.full_like(resid, float("nan"))).nanmedian(1).values.nan_to_num(1.0)
    thresh = (huber * 1.4826 * med).clamp_min(1e-3)[:, None]
    rho = torch.where(resid <= thresh, torch.ones_like(resid), thresh / resid.clamp_min(1e-9))
    weight = torch.where(valid, rho, torch.zeros_like(rho)) / count.clamp_min(1)[:, None].to(dt)
    weight = residual_scale_weight(1.4826 * med)[:, None] * weight
    if frame_weight is not None:
        weight = weight * frame_weight.to(device=dev, dtype=dt).repeat_interleave(c)[:, None]
    shape = (b, c, m)
    vertices, bary = corner_ids.reshape(*shape, 3), bary.reshape(*shape, 3)
    return PhotoSamples(vertices, bary, colour.reshape(*shape, 3), weight.reshape(shape), plates, s,
                        at_anchors(model.neutral, vertices, bary), at_anchors(model.deltas, vertices, bary))


def photometric_residuals(samples: PhotoSamples, points: Tensor, views: FitViews, weight: float) -> Tensor:
    """(B, C*N*3) residuals whose squares sum to E_p of the module docstring.

    Args:
        samples: from `photometric_samples`.
        points: (B, C, N, 2) the samples' projections at the current unknowns, image pixels.
        views: the boxes; weight: w_p.
    """
    b, c, m = samples.weight.shape
    crop = image_to_crop(points, views.boxes, samples.size).reshape(b * c, m, 2)
    seen = sample_bilinear(samples.plates, crop).reshape(b, c, m, 3)
    r = (seen - samples.colour) / PHOTO_UNIT
    return (r * (samples.weight * float(weight))[..., None].sqrt()).flatten(1)


def photometric_point_jacobian(samples: PhotoSamples, world: Tensor, views: FitViews,
                               weight: float) -> tuple[Tensor, Tensor]:
    """Residuals and their derivatives with respect to each sample's world point.

    A sample's residual depends on its own point only: its 3 x 3 Jacobian is the plate's
    bilinear gradient (`sample_bilinear(gradient=True)`) times the crop's scale times the
    projection's derivative (`project_views_jacobian`), chained by hand; a caller chains it
    with the points' derivatives in its unknowns (a matrix product per sample).

    Args:
        samples: from `photometric_samples`; world: (B, C, N, 3) the samples' world points, cm.
        views, weight: as in `photometric_residuals`.
    Returns:
        residuals (B, C, N, 3) and their Jacobian (B, C, N, 3, 3) (colour channel, x y z).
    """
    b, c, m = samples.weight.shape
    pix, d_pix = project_views_jacobian(world, views.world_to_camera, views.intrinsics, views.distortion)
    crop = image_to_crop(pix, views.boxes, samples.size)
    k = ((views.boxes[..., 2] - views.boxes[..., 0]) / samples.size)[..., None, None, None]  # crop px per px
    seen, grad = sample_bilinear(samples.plates, crop.reshape(b * c, m, 2), gradient=True)
    scale = (samples.weight * float(weight)).sqrt()[..., None] / PHOTO_UNIT  # (B, C, N, 1)
    r = (seen.reshape(b, c, m, 3) - samples.colour) * scale
    jac = grad.reshape(b, c, m, 3, 2) @ (d_pix / k)  # (B, C, N, 3, 3)
    return r, jac * scale[..., None]


class PhotoTerm:
    """A stage's photometric residuals as a function of the pose and the active weights, with
    their Jacobian chained by hand (`photometric_point_jacobian`).

    The samples' local points are `local0 + basis @ active` (model frame, cm), their world
    points `R local + t` with `R = exp([omega]) rot0`.

    Args:
        samples, views, weight: as in `photometric_residuals`.
        local0: (B, C, N, 3) the local points with the active weights at 0.
        basis: (B, C, N, 3, S) the active shapes (or any linear unknowns) at the samples.
    """

    def __init__(self, samples: PhotoSamples, views: FitViews, weight: float, local0: Tensor, basis: Tensor):
        self.samples, self.views, self.weight = samples, views, float(weight)
        self.local0, self.basis = local0, basis
        self._last_local: tuple[Tensor, int, Tensor] | None = None  # the last `_local`: active, _version, answer

    @classmethod
    def about(cls, samples: PhotoSamples, views: FitViews, weight: float, weights: Tensor, active: Tensor | list[int],
              basis: Tensor, cache: dict | None = None) -> "PhotoTerm":
        """The term about expression weights (B, K) whose `active` shapes are the unknowns: local0
        holds the samples' neutral with the other shapes at `weights`, `basis` (B, C, N, 3, S+)
        the active shapes at the samples (then any other linear unknowns, e.g. identity components).

        `cache`: a dict the caller keeps for one set of samples, views, weight and basis; the term
        is reused while the inactive weights are equal (a solve re-linearizes after every step,
        and only its active weights move)."""
        inactive = weights.clone()
        inactive[:, active] = 0.0
        if cache is not None and "inactive" in cache and torch.equal(cache["inactive"], inactive):
            return cache["term"]
        # all inactive weights 0 (the rigid fit; the expression's start): the neutral itself (the sum
        # over the K shapes was 11 ms for 8 frames of 1401 samples)
        local0 = samples.neutral if not bool(inactive.any()) else \
            samples.neutral + torch.einsum("bk,bclkd->bcld", inactive, samples.deltas)
        term = cls(samples, views, weight, local0, basis)
        if cache is not None:
            cache["inactive"], cache["term"] = inactive, term
        return term

    def _project(self, world: Tensor) -> Tensor:
        v = self.views
        return project_views(world, v.world_to_camera, v.intrinsics, v.distortion)

    def _local(self, active: Tensor) -> Tensor:
        """(B, C, N, 3) the samples' local points at (B, S) `active`. The answer for the last `active`
        tensor is kept while that tensor is unchanged (same object, no in-place change): a solve
        that passes the same tensor to the residuals and then to the Jacobian (an accepted step,
        `nodes.fit.identity`) sums the basis once (0.13 s of the identity's 2.1 s, 8 frames, was
        this sum). Keyed on the object, not its values: autodiff's wrappers are other objects."""
        if not active.shape[1]:
            return self.local0
        last = self._last_local
        if last is not None and last[0] is active and last[1] == active._version:
            return last[2]
        local = self.local0 + torch.einsum("bcnds,bs->bcnd", self.basis, active)
        self._last_local = (active, active._version, local)
        return local

    def residuals(self, omega: Tensor, rot0: Tensor, trans: Tensor, active: Tensor) -> Tensor:
        """(B, C*N*3) residuals at (B, 3) omega about (B, 3, 3) rot0, (B, 3) trans cm, (B, S) active."""
        rot = axis_angle_to_rotmat(omega) @ rot0
        world = self._local(active) @ rot[:, None].transpose(-1, -2) + trans[:, None, None, :]
        return photometric_residuals(self.samples, self._project(world), self.views, self.weight)

    def jacobian(self, rot: Tensor, trans: Tensor, active: Tensor, pose: bool = True) -> tuple[Tensor, Tensor]:
        """Residuals (B, M) and Jacobian (B, M, 6 + S) in (omega, t, active) at omega = 0; with
        `pose` False only the (B, M, S) columns of the active unknowns (a stage that holds the pose)."""
        q = self._local(active) @ rot[:, None].transpose(-1, -2)  # (B, C, N, 3) rotated, not translated
        r, jp = photometric_point_jacobian(self.samples, q + trans[:, None, None, :], self.views, self.weight)
        # d q / d omega = -[q]x, and a row a of jp times -[q]x is q x a; the shapes' columns are
        # (jp R) basis, three broadcast products instead of a 3 x 3 matrix product per sample
        # (bench/profile_fit.py, 8 frames of 1401 samples: the expression's Jacobian 26 -> 17 ms a call)
        b, s = r.shape[0], self.basis.shape[-1]
        if not pose and not s:
            return r.reshape(b, -1), jp.new_empty(b, r[0].numel(), 0)
        first = 6 if pose else 0
        dtype = torch.promote_types(jp.dtype, self.basis.dtype) if s else jp.dtype
        jac = jp.new_empty(*jp.shape[:-1], first + s, dtype=dtype)  # (B, C, N, 3, 6 + S), written in place
        if pose:
            jac[..., :3] = torch.linalg.cross(q[..., None, :].expand_as(jp), jp, dim=-1)
            jac[..., 3:6] = jp
        if s:
            _chain_basis(torch.einsum("bcnij,bjk->bcnik", jp, rot), self.basis, jac[..., first:])
        return r.reshape(b, -1), jac.reshape(b, -1, jac.shape[-1])


CHAIN_CHUNK = 256
"""`_chain_basis` works on this many samples at a time (their products stay in the CPU's cache)."""


def _chain_basis(jr: Tensor, basis: Tensor, out: Tensor) -> None:
    """`out = jr[..., 0] basis[0] + jr[..., 1] basis[1] + jr[..., 2] basis[2]` per sample: (B, C, N, 3, 3)
    `jr` (channel, local axis) and (B, C, N, 3, S) `basis` into (B, C, N, 3, S) `out`.

    The same three products and two sums, in the same order, as the broadcast expression, so the
    same bits; done `CHAIN_CHUNK` samples at a time into one reused buffer (the whole-batch
    temporaries, 9 MB each for the identity's 4 frames of 1400 samples and 67 columns, were fresh
    allocations the CPU faulted in: 7-18 ms -> 3 ms a call)."""
    n = basis.shape[2]
    step = max(min(CHAIN_CHUNK, n), 1)
    tmp = out.new_empty(*out.shape[:2], step, *out.shape[3:])
    for start in range(0, n, step):
        stop = min(start + step, n)
        j, bas, o = jr[:, :, start:stop], basis[:, :, start:stop], out[:, :, start:stop]
        t = tmp[:, :, :stop - start]
        torch.mul(j[..., 0, None], bas[..., None, 0, :], out=o)
        o += torch.mul(j[..., 1, None], bas[..., None, 1, :], out=t)
        o += torch.mul(j[..., 2, None], bas[..., None, 2, :], out=t)
