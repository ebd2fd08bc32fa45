"""Per-frame flags: the one reading of a flags `ParamSequence` as a boolean mask, and its writing.

Nodes pass per-frame yes/no facts (a frame failed, a face was not found) as a `ParamSequence`
with one float column per flag, 1.0 for yes and 0.0 for no, so that flags travel, chunk and
cache like any other per-frame values. Code reads them only through `flags_to_mask`, which
fixes what a value means:

- the column named `failed` (or the name asked for) is read, else the first column;
- a value above 0.5 is set (flags are written as exactly 0.0 and 1.0; 0.5 splits them);
- a value that is not finite (NaN) is set too: a flag nobody could compute does not vouch for
  its frame, so a frame with an unknown failure flag counts as failed.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .sequences import ParamSequence

__all__ = ["FAILED", "flags_to_mask", "mask_to_flags"]

FAILED = "failed"
"""Name of the column of a flags sequence that marks failed frames."""


def flags_to_mask(flags: ParamSequence | None, frames: int, *, name: str = FAILED,
                  where: str = "failed") -> np.ndarray:
    """Read one flag of a flags sequence as a boolean mask (see the module's rules).

    Args:
        flags: (F, C) flags, or None (no frame flagged).
        frames: F, the number of frames the mask must cover.
        name: the column to read when present (else the first column is read).
        where: the input port named in errors.
    Returns:
        (F,) bool, True where the flag is set (value > 0.5, or not finite).
    Raises:
        InputError: a sequence without columns, or of another frame count.

    Example:
        >>> flags_to_mask(ParamSequence(np.array([[0.0], [1.0], [np.nan]], np.float32), ["failed"]), 3).tolist()
        [False, True, True]
    """
    if flags is None:
        return np.zeros(frames, bool)
    values = np.asarray(flags.values)
    if values.ndim != 2 or values.shape[1] < 1:
        raise InputError(where, f"expected (F, 1) flags with a '{name}' column, found shape {values.shape}")
    if len(values) != frames:
        raise InputError(where, f"expected flags for {frames} frames, found {len(values)}")
    column = values[:, flags.names.index(name) if name in flags.names else 0]
    return ~np.isfinite(column) | (column > 0.5)


def mask_to_flags(mask: np.ndarray, name: str = FAILED) -> ParamSequence:
    """Write a boolean mask as a one-column flags sequence.

    Args:
        mask: (F,) bool (or anything `astype(bool)` reads), True where the flag is set.
        name: the column's name.
    Returns:
        ParamSequence (F, 1) float32, 1.0 where set, 0.0 elsewhere, column `name`.
    """
    mask = np.asarray(mask, bool).reshape(-1)
    return ParamSequence(mask.astype(np.float32)[:, None], [name])
