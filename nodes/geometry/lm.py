"""Batched damped least squares (Levenberg-Marquardt) with one damping schedule.

Minimizes, independently for each batch element b, the sum of squares
`C_b(x_b) = |r_b(x_b)|^2` of residuals r_b (M,) in unknowns x_b (P,). Pure torch, batched
over a leading dimension B, in the manner of kornia/roma: the caller supplies the residuals
and their normal equations (or a Jacobian, through `from_jacobian`); bounds, priors and
penalties are residuals of the caller's (a prior `sqrt(lambda) (x - x0)`, a bound's
quadratic penalty), or a projection in `retract`.

The schedule (Marquardt 1963, with Nielsen's accept/reject bookkeeping; one for every fitter):
- step: `(J^T J + lambda_b diag(J^T J) + floor I) dx = -J^T r`, with diag(J^T J) clamped to
  at least `diag_floor` (an unobserved unknown still gets a damped, finite step) and `floor`
  a Tikhonov term that keeps a flat valley's system regular;
- gain: the actual relative decrease `(C(x) - C(x + dx)) / C(x)`; a step is *accepted* for an
  element when it lowers its cost, and then `lambda_b <- max(lambda_b down, lambda_min)`,
  else *rejected*, `lambda_b <- min(lambda_b up, lambda_max)`, and retried (the Jacobian
  kept) up to `tries` times in one iteration until that element's step is accepted;
- stopping: an element stops when an accepted step lowers its cost by less than `rel_tol`
  relative, or (with `stop_when_stuck`) when an iteration's `tries` tries did not lower it;
  the solve stops after `iterations` iterations or when every element has stopped.

Every decision is the element's own, so an element's result does not depend on the elements
solved beside it (a fit's frame on the frames of its batch). Until stop 41 the tries stopped
for every element once any element's step was accepted, and the solve when none was.

Each iteration costs one linearization and one to `tries` residual evaluations.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import torch
from torch import Tensor

__all__ = ["LMSchedule", "LMResult", "damped_step", "from_jacobian", "levenberg_marquardt", "normal_products"]


@dataclass(frozen=True)
class LMSchedule:
    """The damping schedule's constants (see the module docstring).

    Attributes:
        lam0: initial lambda (relative to diag(J^T J)).
        down, up: lambda's factor after an accepted and after a rejected step.
        lam_min, lam_max: lambda's bounds.
        tries: rejected steps retried within one iteration (Jacobian kept).
        rel_tol: an element stops when an accepted step gains less than this (relative cost).
        diag_floor: lower bound of diag(J^T J) in the damping.
        floor: Tikhonov term added to the normal matrix (unit: the cost's per unit x^2).
        stop_when_stuck: end the solve when an iteration improved no element.
    """

    lam0: float = 1e-3
    down: float = 0.3
    up: float = 10.0
    lam_min: float = 1e-7
    lam_max: float = 1e8
    tries: int = 6
    rel_tol: float = 1e-4
    diag_floor: float = 1e-9
    floor: float = 1e-9
    stop_when_stuck: bool = True


class LMResult(NamedTuple):
    """x: (B, P) the solution; residuals: (B, M) at x; cost: (B,) |r|^2 at x; lam: (B,) the final
    damping; iterations: how many linearizations ran."""

    x: Tensor
    residuals: Tensor
    cost: Tensor
    lam: Tensor
    iterations: int


def damped_step(jtj: Tensor, jtr: Tensor, lam: Tensor, *, diag_floor: float = 1e-9, floor: float = 1e-9) -> Tensor:
    """The Levenberg-Marquardt step of B damped normal equations.

    Args:
        jtj: (B, P, P) J^T J; jtr: (B, P) J^T r; lam: (B,) damping relative to diag(J^T J).
        diag_floor: lower clamp of diag(J^T J); floor: added to the diagonal (Tikhonov).
    Returns:
        (B, P) dx solving (J^T J + lam diag(J^T J) + floor I) dx = -J^T r.
    """
    p = jtj.shape[-1]
    eye = torch.eye(p, dtype=jtj.dtype, device=jtj.device)
    diag = torch.diagonal(jtj, dim1=-2, dim2=-1).clamp_min(diag_floor)
    a = jtj + (lam[:, None] * diag)[:, :, None] * eye
    if floor:
        a = a + floor * eye
    return -torch.linalg.solve(a, jtr[..., None])[..., 0]


def normal_products(jac: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """`(J^T J, J^T r)` ((B, P, P), (B, P)) of (B, M, P) Jacobians and (B, M) residuals, one
    problem at a time: a batched product takes another kernel for a batch of one than for
    several (J^T J of one (500, 9) Jacobian differed by 4e-14 between the two), so a problem's
    steps, and the frames a compacted solve (`compact=True`) keeps running, would depend on the
    problems solved beside it."""
    jt = jac.transpose(1, 2)
    return (torch.stack([a @ b for a, b in zip(jt, jac)]),
            torch.stack([a @ b for a, b in zip(jt, r[..., None])])[..., 0])


def from_jacobian(jacobian: Callable[[Tensor], Tensor]) -> Callable[[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """Normal equations `(J^T J, J^T r)` ((B, P, P), (B, P)) from a Jacobian callback x (B, P) -> (B, M, P)."""

    def normal(x: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
        return normal_products(jacobian(x), r)

    return normal


def levenberg_marquardt(residuals: Callable[[Tensor], Tensor],
                        normal: Callable[[Tensor, Tensor], tuple[Tensor, Tensor]], x0: Tensor, *,
                        iterations: int, schedule: LMSchedule = LMSchedule(),
                        retract: Callable[[Tensor, Tensor], Tensor] | None = None,
                        relinearize: Callable[[Tensor, Tensor], Tensor] | None = None,
                        compact: bool = False) -> LMResult:
    """Minimize |r_b(x_b)|^2 per batch element by Levenberg-Marquardt (module docstring).

    Args:
        residuals: x (B, P) -> (B, M) residuals (any float dtype; float64 recommended where the
            valley is flat: the normal equations square the condition number).
        normal: (x (B, P), r (B, M)) -> (J^T J (B, P, P), J^T r (B, P)) at x; `from_jacobian`
            builds it from a Jacobian callback. Where linearizing changes the residual function
            itself (a mask or an anchoring taken at x, held for the iteration's trial steps) it
            returns (J^T J, J^T r, r') with r' (B, M) the residuals at x under the new
            linearization, which replace r (and the cost the trial steps must beat).
        x0: (B, P) start.
        iterations: at most this many linearizations.
        schedule: the damping schedule's constants.
        retract: (x, dx) -> x' applying a step (default x + dx); e.g. a projection onto bounds.
        relinearize: (x, accepted (B,) bool) -> x, called after each iteration with an accepted
            step: the caller moves its linearization point (e.g. folds a rotation increment into
            its base rotation and zeroes it in x) and returns the equivalent x; the residuals
            at the returned x must equal those at the given x.
        compact: evaluate only the elements still running. The callbacks then take one more
            argument, `rows` (R,) int64, the batch indices of the elements they get (x and r
            hold those R rows): `residuals(x, rows)`, `normal(x, r, rows)` (two outputs only),
            `relinearize(x, accepted, rows)`. A batch whose elements stop at different
            iterations costs what its running elements do (the fit's stages: 0.68 of the
            frame-iterations); each element's result is the same as without it where the
            callbacks compute each element from its own row only.
    Returns:
        LMResult (x, residuals, cost, lam, iterations).
    """
    if compact:
        return _levenberg_marquardt_compact(residuals, normal, x0, iterations=iterations, schedule=schedule,
                                            retract=retract, relinearize=relinearize)
    s = schedule
    x = x0
    b = x.shape[0]
    r = residuals(x)
    cost = (r * r).sum(1)
    lam = torch.full((b,), s.lam0, dtype=x.dtype, device=x.device)
    running = torch.ones(b, dtype=torch.bool, device=x.device)
    done = 0
    for _ in range(iterations):
        done += 1
        linear = normal(x, r)
        jtj, jtr = linear[0], linear[1]
        if len(linear) == 3:
            r = linear[2]
            cost = (r * r).sum(1)
        better = torch.zeros_like(running)
        x_new, r_new, cost_new = x, r, cost
        for _try in range(s.tries):  # each element retries until its own step is accepted
            trying = running & ~better
            step = damped_step(jtj, jtr, lam, diag_floor=s.diag_floor, floor=s.floor)
            x_try = x + step if retract is None else retract(x, step)
            r_try = residuals(x_try)
            cost_try = (r_try * r_try).sum(1)
            ok = (cost_try < cost) & trying
            lam = torch.where(ok, (lam * s.down).clamp_min(s.lam_min),
                              torch.where(trying, (lam * s.up).clamp_max(s.lam_max), lam))
            r_new, r_try = _pad_to(r_new, r_try)
            x_new = torch.where(ok[:, None], x_try, x_new)
            r_new = torch.where(ok[:, None], r_try, r_new)
            cost_new = torch.where(ok, cost_try, cost_new)
            better = better | ok
            if not bool((running & ~better).any()):
                break
        gain = (cost - cost_new) / cost.clamp_min(1e-12)
        running = running & ~(better & (gain < s.rel_tol))
        if s.stop_when_stuck:
            running = running & better
        x = torch.where(better[:, None], x_new, x)
        r_new, r = _pad_to(r_new, r)
        r = torch.where(better[:, None], r_new, r)
        cost = torch.where(better, cost_new, cost)
        if relinearize is not None and bool(better.any()):
            x = relinearize(x, better)
        if not bool(running.any()):
            break
    return LMResult(x, r, cost, lam, done)


def _pad_to(*parts: Tensor) -> tuple[Tensor, ...]:
    """(B_i, M_i) residuals padded with zeros to the widest: the residual count may follow x (a
    coverage), and zeros leave every cost unchanged."""
    m = max(v.shape[1] for v in parts)
    return tuple(torch.nn.functional.pad(v, (0, m - v.shape[1])) if v.shape[1] < m else v for v in parts)


def _levenberg_marquardt_compact(residuals: Callable[..., Tensor], normal: Callable[..., tuple[Tensor, Tensor]],
                                 x0: Tensor, *, iterations: int, schedule: LMSchedule,
                                 retract: Callable[[Tensor, Tensor], Tensor] | None,
                                 relinearize: Callable[..., Tensor] | None) -> LMResult:
    """`levenberg_marquardt(compact=True)`: the same iterations, each on the running elements' rows only."""
    s = schedule
    b = x0.shape[0]
    every = torch.arange(b, device=x0.device)
    x = x0.clone()
    r = residuals(x, every)
    cost = (r * r).sum(1)
    lam = torch.full((b,), s.lam0, dtype=x.dtype, device=x.device)
    running = torch.ones(b, dtype=torch.bool, device=x.device)
    done = 0
    for _ in range(iterations):
        done += 1
        rows = every if bool(running.all()) else torch.nonzero(running)[:, 0]
        x_run, r_run, cost_run, lam_run = x[rows], r[rows], cost[rows], lam[rows]
        linear = normal(x_run, r_run, rows)
        if len(linear) != 2:
            raise ValueError(f"normal: expected (J^T J, J^T r) with compact=True, found {len(linear)} outputs")
        jtj, jtr = linear
        n = len(rows)
        better = torch.zeros(n, dtype=torch.bool, device=x.device)
        x_new, r_new, cost_new = x_run, r_run, cost_run
        trying = torch.arange(n, device=x.device)  # positions in `rows` whose step is not yet accepted
        for _try in range(s.tries):  # each element retries until its own step is accepted
            step = damped_step(jtj[trying], jtr[trying], lam_run[trying], diag_floor=s.diag_floor, floor=s.floor)
            x_try = x_run[trying] + step if retract is None else retract(x_run[trying], step)
            r_try = residuals(x_try, rows[trying])
            cost_try = (r_try * r_try).sum(1)
            ok = cost_try < cost_run[trying]
            lam_run = lam_run.index_copy(0, trying, torch.where(ok, (lam_run[trying] * s.down).clamp_min(s.lam_min),
                                                                (lam_run[trying] * s.up).clamp_max(s.lam_max)))
            if bool(ok.any()):
                took = trying[ok]
                r_new, r_try = _pad_to(r_new, r_try)
                x_new = x_new.index_copy(0, took, x_try[ok])
                r_new = r_new.index_copy(0, took, r_try[ok])
                cost_new = cost_new.index_copy(0, took, cost_try[ok])
                better = better.index_fill(0, took, True)
                trying = trying[~ok]
            if not len(trying):
                break
        lam = lam.index_copy(0, rows, lam_run)
        gain = (cost_run - cost_new) / cost_run.clamp_min(1e-12)
        still = ~(better & (gain < s.rel_tol))
        if s.stop_when_stuck:
            still = still & better
        running = running.index_copy(0, rows, still)
        if not bool(better.any()):
            if not bool(running.any()):
                break
            continue
        x_run = torch.where(better[:, None], x_new, x_run)
        r_new, r, r_run = _pad_to(r_new, r, r_run)
        r = r.index_copy(0, rows, torch.where(better[:, None], r_new, r_run))
        cost = cost.index_copy(0, rows, torch.where(better, cost_new, cost_run))
        if relinearize is not None:
            x_run = relinearize(x_run, better, rows)
        x = x.index_copy(0, rows, x_run)
        if not bool(running.any()):
            break
    return LMResult(x, r, cost, lam, done)
