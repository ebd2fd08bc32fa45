"""The mode-pursuit energy (eq. 4) and its fused value-and-gradient kernel.

    E = 1 / (3 F V) * [ sum_{f, v, c} psi_pos(S_{f,v,c} - R_{v,c})
                        + lambda * sum_{f, v, c} psi_vel(dS_{f,v,c} / dt) ],   S_f = rot_f X_f + trans_f

with the bounded penalty `psi_w` and the 7-tap velocity of `penalty.py` (lower-order central
differences at the three first and last frames, `ends="reduced"`).
`stabilization_energy` is the plain autograd formulation (the reference);
`fused_stabilization_energy` returns the same value and computes the gradient with respect
to the per-frame (rot_f, trans_f) in the forward pass, over blocks of frames kept as
(B, 3, V) float32 (one `baddbmm` per block, reductions along contiguous memory, blocks of
about 2^18 coordinates stay in cache and bound the memory). `mode_pursuit.py` drives it
through `EnergyData` and `fused_energy`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .penalty import REDUCED_END_COEFFS, VELOCITY_COEFFS, central_velocity, psi, psi_sum_and_grad_

__all__ = ["stabilization_energy", "fused_stabilization_energy", "EnergyData", "fused_energy",
           "block_energy", "default_block_frames"]


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


def block_energy(x: Tensor, rot: Tensor, trans: Tensor, rest_neg: Tensor, inner: tuple[int, int],
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
class EnergyData:
    """The fixed data of a fused energy: vertices (F, 3, V) float32 and settings.

    Attributes:
        x: (F, 3, V) float32 tracked vertices, coordinates first.
        rest: (3, V) float32 rest positions.
        width_pos: position width; width_vel: velocity width (units of `x`, per frame).
        velocity_weight: lambda >= 0.
        block_frames: frames per block of the fused kernel.
        kernel: the block kernel (`block_energy`, or its `torch.compile`d version).
    """

    x: Tensor
    rest: Tensor
    width_pos: float
    width_vel: float
    velocity_weight: float
    block_frames: int
    kernel: Callable[..., tuple[Tensor, Tensor, Tensor]] = block_energy


def _fused_value_and_grad(data: EnergyData, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Energy () float64 and its gradients (F, 3, 3), (F, 3) in rot's / trans's dtypes."""
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
    def forward(ctx, rot: Tensor, trans: Tensor, data: EnergyData) -> Tensor:  # type: ignore[override]
        total, grad_rot, grad_trans = _fused_value_and_grad(data, rot.detach(), trans.detach())
        ctx.save_for_backward(grad_rot, grad_trans)
        return total.to(rot.dtype)

    @staticmethod
    def backward(ctx, grad_out: Tensor):  # type: ignore[override]
        grad_rot, grad_trans = ctx.saved_tensors
        return grad_out * grad_rot, grad_out * grad_trans, None


def fused_energy(rot: Tensor, trans: Tensor, data: EnergyData) -> Tensor:
    """Return the fused energy of `data` at (rot, trans), differentiable in both.

    Args:
        rot: (F, 3, 3) world-to-skull rotations (any float dtype; computed in float32).
        trans: (F, 3) world-to-skull translations, units of `data.x`.
        data: the vertices, rest and widths.
    Returns:
        () energy in `rot`'s dtype.
    """
    return _FusedEnergy.apply(rot, trans, data)


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
    data = EnergyData(x, rest.detach().to(torch.float32).T.contiguous(), float(width_pos),
                      float(width_vel), float(velocity_weight),
                      block_frames or default_block_frames(x.shape[0], x.shape[2]))
    return _FusedEnergy.apply(rot, trans, data)


def default_block_frames(num_frames: int, num_vertices: int) -> int:
    """Frames per block of the fused kernel: about 2^18 coordinates, at least 8 frames."""
    return max(8, min(num_frames, (1 << 18) // max(1, 3 * num_vertices)))
