"""The continuation schedule of mode pursuit: widths coarse to fine, refinements interleaved.

`make_schedule` turns the width lists and the refinement count into typed `Stage` records
(one L-BFGS restart each); `mode_pursuit` logs each stage it ran as a `StageLog`.
Pure Python (no torch): the node module imports the defaults at start-up.
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

__all__ = ["DEFAULT_POSITION_WIDTHS", "DEFAULT_VELOCITY_WIDTHS", "Stage", "StageLog", "make_schedule"]

DEFAULT_POSITION_WIDTHS: tuple[float, ...] = (0.8, 0.4, 0.2, 0.1, 0.05)
"""Position widths of the paper's continuation schedule (cm)."""
DEFAULT_VELOCITY_WIDTHS: tuple[float, ...] = (0.2, 0.1, 0.05, 0.025, 0.0125)
"""Velocity widths of the paper's continuation schedule (cm / frame)."""


class Stage(NamedTuple):
    """One L-BFGS restart.

    Attributes:
        width_pos: position width (cm).
        width_vel: velocity width (cm / frame).
        refine: refine the control polygon (midpoint) before this stage.
    """

    width_pos: float
    width_vel: float
    refine: bool


def make_schedule(position_widths: Sequence[float] = DEFAULT_POSITION_WIDTHS,
                  velocity_widths: Sequence[float] = DEFAULT_VELOCITY_WIDTHS,
                  refinements: int = 2) -> list[Stage]:
    """Return the continuation schedule: the widths in order, refinements interleaved.

    The K width pairs are walked once, coarse to fine. The `refinements` refinements are
    spread evenly over the stages after the first, so that the coarse spline takes the wide
    widths (large basin) and the finest one the narrow widths; when there are more
    refinements than widths, the last width pair is repeated after each extra refinement.

    Args:
        position_widths: K widths (cm), decreasing.
        velocity_widths: K widths (cm / frame).
        refinements: number of midpoint refinements R >= 0.
    Returns:
        max(K, R + 1) stages.

    Example:
        >>> [s.refine for s in make_schedule(refinements=2)]
        [False, False, True, False, True]
    """
    if len(position_widths) != len(velocity_widths) or not position_widths:
        raise ValueError(f"velocity_widths: expected as many widths as position_widths "
                         f"({len(position_widths)}), found {len(velocity_widths)}")
    if refinements < 0:
        raise ValueError(f"refinements: expected >= 0, found {refinements}")
    widths = list(zip(position_widths, velocity_widths))
    while len(widths) < refinements + 1:
        widths.append(widths[-1])
    k = len(widths)
    # Level of stage j: floor(j * (R + 1) / K), so level 0 first and level R last.
    levels = [j * (refinements + 1) // k for j in range(k)]
    return [Stage(float(wp), float(wv), j > 0 and levels[j] > levels[j - 1])
            for j, (wp, wv) in enumerate(widths)]


class StageLog(NamedTuple):
    """What one stage of `mode_pursuit` did.

    Attributes:
        width_pos: position width (cm).
        width_vel: velocity width (cm / frame).
        spacing: control-point spacing of the stage's correction polygon (frames).
        control_points: number of control dual quaternions optimized.
        iterations: L-BFGS iterations.
        evaluations: energy + gradient evaluations.
        energy_start: energy at the first evaluation (nan when there was none).
        energy_end: energy at the last evaluation (nan when there was none).
        seconds: wall time of the stage.
    """

    width_pos: float
    width_vel: float
    spacing: float
    control_points: int
    iterations: int
    evaluations: int
    energy_start: float
    energy_end: float
    seconds: float
