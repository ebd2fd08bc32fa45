"""Sweeps over frames of the plate-flow solve: flow infill of failed frames, and smoothing.

- `infill`: each run of failed frames [a, b] no longer than `max_gap` is solved from its good
  neighbours: forward from frame a - 1 (each frame from the one before, prev term only, started
  at the previous frame's values), then backward from frame b + 1 (both neighbours); repeated
  `sweeps` times (later passes use both neighbours both ways). A run at the start of the shot
  is solved backward first. Runs longer than `max_gap`, or that reach the edge of the frames
  received without that edge being the shot's, stay failed, so that the result of every frame
  depends only on frames within `max_gap` of it (the node's halo): chunk-invariant.
- `smooth`: `sweeps` Jacobi sweeps (every frame from its neighbours' previous values; radius
  1 per sweep) or red-black Gauss-Seidel sweeps (frames of even absolute index, then odd,
  each from the newest values; radius 2 per sweep) of the per-frame energy of
  `nodes.temporal.flowfit` (plate flow, self flow, prior).

One frame per `solve_frames` call, so a frame's result never depends on the batch it is in.
Torch at module level: import from node `run()` methods only.
"""

from __future__ import annotations

from typing import Callable, Literal

import numpy as np
import torch
from torch import Tensor

from .flowfit import FlowModel, Terms, frame_energies, solve_frames
from .opticalfit import RenderScene, optical_energies, solve_frame_optical

__all__ = ["failed_runs", "infill", "smooth"]


def failed_runs(failed: np.ndarray) -> list[tuple[int, int]]:
    """[(a, b)] inclusive runs of True in a (F,) bool array.

    Example:
        >>> failed_runs(np.array([0, 1, 1, 0, 1], bool))
        [(1, 2), (4, 4)]
    """
    f = np.r_[False, np.asarray(failed, bool), False]
    d = np.diff(f.astype(np.int8))
    return [(int(a), int(b) - 1) for a, b in zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1))]


class _Problem:
    def __init__(self, model: FlowModel, x: Tensor, flows: Tensor, pair_valid: np.ndarray, usable: np.ndarray,
                 iterations: int, plate_weight: float = 1.0, self_weight: float = 0.0,
                 prior: Tensor | None = None, prior_weight: float = 0.0):
        self.model, self.x, self.flows = model, x, flows
        self.pair_valid, self.usable = np.asarray(pair_valid, bool), np.asarray(usable, bool)
        self.iterations = iterations
        self.plate_weight, self.self_weight = plate_weight, self_weight
        self.prior, self.prior_weight = prior, prior_weight

    def _terms(self, i: int, x: Tensor, use_prev: bool, use_next: bool) -> Terms | None:
        f = len(x)
        prev_on = use_prev and i > 0 and self.usable[i - 1] and self.pair_valid[i - 1]
        next_on = use_next and i + 1 < f and self.usable[i + 1] and self.pair_valid[i]
        if not (prev_on or next_on):
            return None
        ip, inx = max(i - 1, 0), min(i + 1, f - 1)
        flat = self.flows
        return Terms(x[ip:ip + 1], x[inx:inx + 1], torch.tensor([prev_on]), torch.tensor([next_on]),
                     flat[ip:ip + 1], flat[i:i + 1], self.plate_weight, self.self_weight,
                     None if self.prior is None else self.prior[i:i + 1], self.prior_weight)

    def _solve(self, x0: Tensor, terms: Terms) -> Tensor:
        """(1, 6 + K) start -> (1, 6 + K) solved parameters of one frame."""
        return solve_frames(self.model, x0, terms, iterations=self.iterations)

    def _energy(self, x: Tensor, terms: Terms) -> float:
        """E_i of one frame at (1, 6 + K) parameters."""
        return float(frame_energies(self.model, x, terms)[0])

    def solve(self, i: int, x: Tensor, *, use_prev: bool = True, use_next: bool = True,
              start: Tensor | None = None) -> Tensor:
        terms = self._terms(i, x, use_prev, use_next)
        if terms is None:
            return x[i]
        return self._solve((x[i] if start is None else start)[None], terms)[0]

    def mismatch(self, i: int, x: Tensor, *, use_prev: bool = True, use_next: bool = True) -> float:
        """Mean squared plate-flow mismatch of frame i per flow pair it has (pixels^2); NaN if none."""
        terms = self._terms(i, x, use_prev, use_next)
        if terms is None:
            return float("nan")
        return self._energy(x[i:i + 1], terms) / (int(terms.prev_on[0]) + int(terms.next_on[0]))


class _OpticalProblem(_Problem):
    """`_Problem` with the optical render flow (`nodes.temporal.opticalfit`)."""

    def __init__(self, scene: RenderScene, steps: int, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.scene, self.steps = scene, steps

    def _solve(self, x0: Tensor, terms: Terms) -> Tensor:
        return solve_frame_optical(self.scene, self.model, x0, terms, iterations=self.steps)

    def _energy(self, x: Tensor, terms: Terms) -> float:
        return float(optical_energies(self.scene, self.model, x, terms)[0])


def infill(model: FlowModel, x: Tensor, flows: Tensor, pair_valid: np.ndarray, failed: np.ndarray, *,
           max_gap: int, sweeps: int = 1, iterations: int = 8, at_start: bool = True, at_end: bool = True,
           reject_ratio: float = 6.0, floor_px2: float = 0.25, optical: RenderScene | None = None,
           optical_steps: int = 6,
           progress: Callable[[float, str], None] | None = None) -> tuple[Tensor, np.ndarray, np.ndarray]:
    """Solve the failed frames from their neighbours by plate flow (module docstring).

    A solved frame whose mean squared plate-flow mismatch (`_Problem.mismatch`, both pairs)
    is above `reject_ratio` times that of the run's good neighbours (pairs (a - 2, a - 1) and
    (b + 1, b + 2); at least `floor_px2`) stays failed: the plate itself does not follow the
    face there (no face in the frame, an occluder, a cut).

    Args:
        model: FlowModel (its free unknowns are solved).
        x: (F, 6 + K) float64 parameters (failed frames: any finite values).
        flows: (F, H, W, 2) float64 plate flow, frame f -> f + 1, pixels.
        pair_valid: (F,) bool, flows[f] is valid.
        failed: (F,) bool.
        max_gap: longest run solved, frames.
        sweeps: forward + backward passes.
        iterations: LM iterations per frame solve.
        at_start, at_end: frame 0 / F - 1 is the shot's first / last frame (not a chunk edge).
        reject_ratio, floor_px2: the acceptance test above.
        optical: None for the geometric render flow; a RenderScene for the optical one
            (`nodes.temporal.opticalfit`, `optical_steps` LM iterations per frame solve).
        progress: called with (fraction, message).
    Returns:
        (F, 6 + K) parameters, (F,) bool frames still failed and (F,) the mismatch of each
        solved frame, pixels^2 (NaN where not solved).
    """
    x = x.clone()
    failed = np.asarray(failed, bool).copy()
    f = len(x)
    mismatches = np.full(f, np.nan)
    runs = failed_runs(failed)
    todo = []
    for a, b in runs:
        if b - a + 1 > max_gap or (a == 0 and not at_start) or (b == f - 1 and not at_end) or (a == 0 and b == f - 1):
            continue
        todo.append((a, b))
    for n, (a, b) in enumerate(todo):
        usable = ~failed
        prob = _Problem(model, x, flows, pair_valid, usable, iterations) if optical is None else \
            _OpticalProblem(optical, optical_steps, model, x, flows, pair_valid, usable, iterations)
        forward_first = a > 0
        for sweep in range(sweeps):
            order = [("fwd", range(a, b + 1)), ("bwd", range(b, a - 1, -1))]
            if not forward_first:
                order = order[::-1]
            for p, (direction, frames) in enumerate(order):
                first = sweep == 0 and p == 0
                for i in frames:
                    if first and direction == "fwd":
                        x[i] = prob.solve(i, x, use_next=False, start=x[i - 1])
                    elif first:
                        x[i] = prob.solve(i, x, use_prev=False, start=x[i + 1])
                    else:
                        x[i] = prob.solve(i, x)
                    usable[i] = True
                    prob.usable = usable
                if (a == 0 or b == f - 1) and not first:
                    continue
        # Accept a solved frame only if its plate flow is explained about as well as at the run's
        # good neighbours (a frame with no face, or a cut, cannot be: its flow is noise).
        ref = [prob.mismatch(a - 1, x, use_next=False) if a >= 2 else float("nan"),
               prob.mismatch(b + 1, x, use_prev=False) if b + 2 < f else float("nan")]
        ref = [r for r in ref if np.isfinite(r)]
        limit = reject_ratio * max(float(np.median(ref)) if ref else 0.0, floor_px2)
        for i in range(a, b + 1):
            mismatch = prob.mismatch(i, x)
            mismatches[i] = mismatch
            failed[i] = not mismatch <= limit
        if progress is not None:
            kept = int(failed[a:b + 1].sum())
            progress((n + 1) / len(todo), f"infilled frames {a}-{b}" + (f" ({kept} left failed: flow mismatch "
                                                                        f"above {limit:.2f} px^2)" if kept else ""))
    return x, failed, mismatches


def smooth(model: FlowModel, x: Tensor, flows: Tensor, pair_valid: np.ndarray, usable: np.ndarray, *,
           sweeps: int, scheme: Literal["jacobi", "red_black"] = "jacobi", parity: int = 0, iterations: int = 6,
           plate_weight: float = 1.0, self_weight: float = 0.0, prior_weight: float = 0.0,
           prior: Tensor | None = None,
           progress: Callable[[float, str], None] | None = None) -> Tensor:
    """Sweeps of the per-frame plate-flow / self-flow solve (module docstring).

    Args:
        model, x, flows, pair_valid: as for `infill`.
        usable: (F,) bool frames solved and used as neighbours (the others are kept).
        sweeps: sweep count; scheme: "jacobi" or "red_black".
        parity: absolute index of frame 0 modulo 2 (red-black colours by absolute frame).
        iterations: LM iterations per frame solve.
        plate_weight, self_weight, prior_weight: the energy's weights (`nodes.temporal.flowfit`).
        prior: (F, 6 + K) values of the prior (None: the start values x).
    Returns:
        (F, 6 + K) float64.
    """
    x = x.clone()
    prob = _Problem(model, x, flows, pair_valid, usable, iterations, plate_weight, self_weight,
                    x.clone() if prior is None else prior, prior_weight)
    frames = np.flatnonzero(np.asarray(usable, bool))
    total = max(sweeps * len(frames), 1)
    done = 0
    for _ in range(sweeps):
        if scheme == "jacobi":
            old = x.clone()
            for i in frames:
                x[i] = prob.solve(int(i), old)
                done += 1
        else:
            for colour in (0, 1):
                for i in frames[(frames + parity) % 2 == colour]:
                    x[i] = prob.solve(int(i), x)
                    done += 1
        if progress is not None:
            progress(done / total, f"smoothed {done}/{total} frame solves")
    return x
