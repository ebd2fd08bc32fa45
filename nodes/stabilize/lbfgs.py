"""L-BFGS with a strong-Wolfe line search, for a fixed iteration count (mode pursuit's optimizer).

Same algorithm as `torch.optim.LBFGS` (two-loop recursion, cubic-interpolation line search as
in minFunc), written out because constructing a torch optimizer imports `torch._dynamo`
(about 2 s per process). The objective returns its value and gradient together.
"""

from __future__ import annotations

import math
from typing import Callable

from torch import Tensor

__all__ = ["ObjectiveFn", "lbfgs"]

ObjectiveFn = Callable[[Tensor], tuple[float, Tensor]]


def _cubic_minimum(x1: float, f1: float, g1: float, x2: float, f2: float, g2: float,
                   lo: float, hi: float) -> float:
    """Minimiser of the cubic through (x1, f1, g1), (x2, f2, g2), clipped to [lo, hi]."""
    d1 = g1 + g2 - 3.0 * (f1 - f2) / (x1 - x2)
    disc = d1 * d1 - g1 * g2
    if disc < 0 or not math.isfinite(disc):
        return 0.5 * (lo + hi)
    d2 = math.sqrt(disc)
    if x1 <= x2:
        den = g2 - g1 + 2.0 * d2
        t = x2 - (x2 - x1) * ((g2 + d2 - d1) / den) if den != 0 else 0.5 * (lo + hi)
    else:
        den = g1 - g2 + 2.0 * d2
        t = x1 - (x1 - x2) * ((g1 + d2 - d1) / den) if den != 0 else 0.5 * (lo + hi)
    return min(max(t, lo), hi) if math.isfinite(t) else 0.5 * (lo + hi)


def _strong_wolfe(fun: ObjectiveFn, x: Tensor, step: float, d: Tensor, f: float, g: Tensor,
                  gtd: float, *, c1: float = 1e-4, c2: float = 0.9, max_evals: int = 25
                  ) -> tuple[float, Tensor, float]:
    """Line search for a step satisfying the strong Wolfe conditions (bracket, then zoom).

    Cubic interpolation as in minFunc (M. Schmidt) and `torch.optim.LBFGS`. Returns the best
    point seen: (f, g, step); `step` may be 0 when nothing decreased the objective.
    """
    d_max = float(d.abs().max())
    best = (f, g, 0.0)
    t_prev, f_prev, g_prev, gtd_prev = 0.0, f, g, gtd
    t = step
    f_new, g_new = fun(x + t * d)
    gtd_new = float(g_new @ d)
    evals = 1
    bracket: list[tuple[float, float, Tensor, float]] | None = None
    while True:
        if f_new < best[0]:
            best = (f_new, g_new, t)
        if f_new > f + c1 * t * gtd or (evals > 1 and f_new >= f_prev):
            bracket = [(t_prev, f_prev, g_prev, gtd_prev), (t, f_new, g_new, gtd_new)]
            break
        if abs(gtd_new) <= -c2 * gtd:
            return f_new, g_new, t
        if gtd_new >= 0:
            bracket = [(t_prev, f_prev, g_prev, gtd_prev), (t, f_new, g_new, gtd_new)]
            break
        if evals >= max_evals:
            return best
        t_next = _cubic_minimum(t_prev, f_prev, gtd_prev, t, f_new, gtd_new,
                                t + 0.01 * (t - t_prev), 10.0 * t)
        t_prev, f_prev, g_prev, gtd_prev = t, f_new, g_new, gtd_new
        t = t_next
        f_new, g_new = fun(x + t * d)
        gtd_new = float(g_new @ d)
        evals += 1
    # Zoom: bracket[low] has the lower objective.
    insufficient = False
    while evals < max_evals:
        low, high = (0, 1) if bracket[0][1] <= bracket[1][1] else (1, 0)
        (a, fa, _, ga), (b, fb, _, gb) = bracket
        if abs(b - a) * d_max < 1e-12:
            break
        t = _cubic_minimum(a, fa, ga, b, fb, gb, min(a, b), max(a, b))
        width = max(a, b) - min(a, b)
        eps = 0.1 * width
        if min(max(a, b) - t, t - min(a, b)) < eps:
            if insufficient or t >= max(a, b) or t <= min(a, b):
                t = max(a, b) - eps if abs(t - max(a, b)) < abs(t - min(a, b)) else min(a, b) + eps
                insufficient = False
            else:
                insufficient = True
        else:
            insufficient = False
        f_new, g_new = fun(x + t * d)
        gtd_new = float(g_new @ d)
        evals += 1
        if f_new < best[0]:
            best = (f_new, g_new, t)
        if f_new > f + c1 * t * gtd or f_new >= bracket[low][1]:
            bracket[high] = (t, f_new, g_new, gtd_new)
        else:
            if abs(gtd_new) <= -c2 * gtd:
                return f_new, g_new, t
            if gtd_new * (bracket[high][0] - bracket[low][0]) >= 0:
                bracket[high] = bracket[low]
            bracket[low] = (t, f_new, g_new, gtd_new)
    return best


def lbfgs(fun: ObjectiveFn, x0: Tensor, *, iterations: int, history_size: int = 10
          ) -> tuple[Tensor, float, int]:
    """Minimise `fun` by L-BFGS with a strong-Wolfe line search, for a fixed iteration count.

    Two-loop recursion (Nocedal and Wright, "Numerical Optimization", algorithm 7.4), first
    step `min(1, 1 / |g|_1)` along -g (as `torch.optim.LBFGS`), then unit initial steps. Stops
    early only when the direction is not a descent direction or the line search finds no
    decrease (converged to working precision).

    Args:
        fun: x -> (value, gradient), x and gradient (N,) float64.
        x0: (N,) starting point.
        iterations: number of iterations (each one line search).
        history_size: number of (s, y) pairs kept.
    Returns:
        (x, f(x), iterations done).
    """
    x = x0.clone()
    f, g = fun(x)
    s_hist: list[Tensor] = []
    y_hist: list[Tensor] = []
    rho_hist: list[float] = []
    gamma = 1.0
    done = 0
    for it in range(iterations):
        if not s_hist:
            d = -g
            step = min(1.0, 1.0 / max(float(g.abs().sum()), 1e-300))
        else:
            q = -g
            alphas = []
            for s, y, rho in zip(reversed(s_hist), reversed(y_hist), reversed(rho_hist)):
                alpha = rho * float(s @ q)
                q = q - alpha * y
                alphas.append(alpha)
            d = q * gamma
            for (s, y, rho), alpha in zip(zip(s_hist, y_hist, rho_hist), reversed(alphas)):
                beta = rho * float(y @ d)
                d = d + (alpha - beta) * s
            step = 1.0
        gtd = float(g @ d)
        if not gtd < 0:
            break
        f_new, g_new, t = _strong_wolfe(fun, x, step, d, f, g, gtd)
        done = it + 1
        if t == 0.0:
            break
        s, y = t * d, g_new - g
        ys = float(y @ s)
        if ys > 1e-10:
            if len(s_hist) == history_size:
                s_hist.pop(0), y_hist.pop(0), rho_hist.pop(0)
            s_hist.append(s)
            y_hist.append(y)
            rho_hist.append(1.0 / ys)
            gamma = ys / float(y @ y)
        x = x + s
        f, g = f_new, g_new
    return x, f, done
