"""Read Live Link Face CSV takes (`io.LoadLiveLinkCSV`): ARKit curves and head angles -> `Performance`.

The conventions (columns, timecodes, angles) are in `nodes.io.arkit`. Columns are found by
name, case-insensitively, so a take of the app (`BlendshapeCount`), of `export.LiveLinkCSV`,
or of another tool that writes some of the columns all read.
"""

from __future__ import annotations

import csv
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nodegraph import FRAMEWISE, FaceModel, In, InputError, Node, NodeParams, Out, Param, Performance

from .arkit import (ANGLE_UNIT_RAD, LIVE_LINK_ANGLES, LIVE_LINK_SHAPES, from_arkit_weights, head_rotation,
                    parse_timecode)

__all__ = ["LiveLinkTake", "read_live_link_csv", "infer_fps", "LoadLiveLinkCSV"]

_STANDARD_RATES = (24, 25, 30, 48, 50, 60, 100, 120)


@dataclass
class LiveLinkTake:
    """The columns of a Live Link Face CSV.

    Attributes:
        seconds: (F,) time of each row from its timecode, seconds (NaN without a Timecode column).
        frames_in_second: (F,) the timecode's frame field with its fraction (`FF.mmm`).
        arkit: (F, 52) weights in `ARKIT_NAMES` order (0 where a column is absent).
        angles: (F, 9) the angle columns in `LIVE_LINK_ANGLES` order, radians (0 where absent).
        found: names of the shape columns present.
    """

    seconds: np.ndarray
    frames_in_second: np.ndarray
    arkit: np.ndarray
    angles: np.ndarray
    found: list[str]


MAX_CURVE_VALUE = 100.0
"""Largest |value| of a shape column read (ARKit weights are 0..1; beyond 100 is not a take)."""
MAX_ANGLE_VALUE = 1e4
"""Largest |value| of an angle column read, in the file's unit (quarter turns: far beyond any head turn)."""


def read_live_link_csv(path: str | os.PathLike) -> LiveLinkTake:
    """Parse a Live Link Face CSV.

    Raises:
        ValueError: naming the file and, for a bad cell, its row and column; also when no
            ARKit shape column is present.
    """
    path = Path(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as handle:
            rows = list(csv.reader(handle))
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: cannot read it as a text CSV ({err})") from None
    rows = [r for r in rows if any(cell.strip() for cell in r)]
    if not rows:
        raise ValueError(f"{path}: expected a header row and frames, found an empty file")
    header = [h.strip().lower() for h in rows[0]]
    column = {name: i for i, name in reversed(list(enumerate(header)))}
    shapes = [column.get(n.lower(), -1) for n in LIVE_LINK_SHAPES]
    if all(i < 0 for i in shapes):
        raise ValueError(f"{path}: expected Live Link Face columns (EyeBlinkLeft, ..., JawOpen, ...), found the "
                         f"header {rows[0][:6]}{' ...' if len(rows[0]) > 6 else ''}")
    angles = [column.get(n.lower(), -1) for n in LIVE_LINK_ANGLES]
    body = rows[1:]
    f = len(body)
    arkit = np.zeros((f, len(LIVE_LINK_SHAPES)))
    angle = np.zeros((f, len(LIVE_LINK_ANGLES)))
    for target, indices in ((arkit, shapes), (angle, angles)):
        for j, i in enumerate(indices):
            if i < 0:
                continue
            for r, row in enumerate(body):
                try:
                    target[r, j] = float(row[i])
                except (IndexError, ValueError):
                    cell = row[i] if i < len(row) else "(missing)"
                    raise ValueError(f"{path}: row {r + 2}, column '{rows[0][i]}': expected a number, "
                                     f"found {cell!r}") from None
    if not np.isfinite(arkit).all() or not np.isfinite(angle).all():
        r = int(np.flatnonzero(~np.isfinite(np.concatenate([arkit, angle], 1)).all(1))[0])
        raise ValueError(f"{path}: row {r + 2} has a non-finite value")
    for values, indices, bound in ((arkit, shapes, MAX_CURVE_VALUE), (angle, angles, MAX_ANGLE_VALUE)):
        far = np.abs(values) > bound
        if far.any():
            r, j = (int(x) for x in np.argwhere(far)[0])
            raise ValueError(f"{path}: row {r + 2}, column '{rows[0][indices[j]]}': expected a value within "
                             f"+-{bound:g}, found {values[r, j]:g}")
    seconds = np.full(f, np.nan)
    frames_in_second = np.full(f, np.nan)
    if "timecode" in column:
        i = column["timecode"]
        for r, row in enumerate(body):
            try:
                h, m, s, ff = parse_timecode(row[i] if i < len(row) else "")
            except ValueError as err:
                raise ValueError(f"{path}: row {r + 2}, column 'Timecode': {err}") from None
            seconds[r] = h * 3600 + m * 60 + s
            frames_in_second[r] = ff
    return LiveLinkTake(seconds, frames_in_second, arkit, angle * ANGLE_UNIT_RAD,
                        [n for n, i in zip(LIVE_LINK_SHAPES, shapes) if i >= 0])


def infer_fps(take: LiveLinkTake) -> float:
    """The take's frame rate from its timecodes.

    The timecode rate is the smallest standard rate (24, 25, 30, 48, 50, 60, 100, 120) above every
    frame field; the frame rate is one over the median step between rows (so a 60 fps take under
    a 30 fps timecode, with `.500` rows, is 60).

    Raises:
        ValueError: when the take has no timecodes, fewer than two rows, or timecodes that never
            pass a second (the timecode rate is then unknown): give `fps` instead.
    """
    if len(take.seconds) < 2 or not np.isfinite(take.seconds).all():
        raise ValueError("cannot infer the frame rate: the take has no Timecode column or fewer than 2 rows; "
                         "give fps=")
    if len(np.unique(take.seconds)) < 2:
        raise ValueError("cannot infer the frame rate: the timecodes never pass a second, so the timecode rate "
                         "is unknown; give fps=")
    top = float(np.floor(take.frames_in_second.max()))
    rate = next((r for r in _STANDARD_RATES if r > top), top + 1)
    t = take.seconds + take.frames_in_second / rate
    steps = np.diff(t)
    steps = steps[steps > 0]
    if not steps.size:
        raise ValueError("cannot infer the frame rate: the timecodes do not increase; give fps=")
    return float(1.0 / np.median(steps))


class LoadLiveLinkCSV(Node):
    """Read a Live Link Face CSV take as a performance of the face model's shapes."""

    type_name = "io.LoadLiveLinkCSV"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Live Link Face CSV (the app's takes or "
                          "export.LiveLinkCSV's).")
        fps: float = Param(0.0, ge=0, le=10000, description="Frames per second; 0 = from the timecodes (an "
                           "app take at 60 fps under a 30 fps timecode reads as 60).")
        distance_cm: float = Param(60.0, gt=0, le=10000, description="Distance of the head from the camera, "
                                   "cm: the CSV has no translation, so the head sits at (0, 0, -distance) "
                                   "in ARKit's camera frame (y up, the camera looking down -z), 60 cm being "
                                   "about where a phone is held.")

    model = In(FaceModel, optional=True, doc="Face model whose shape names the weights take (the ICT head: "
               "each half of browInnerUp and cheekPuff takes ARKit's value); absent: the 52 ARKit names.")
    performance = Out(Performance, doc="Head rotation from the angles (ARKit's camera frame), translation "
                      "(0, 0, -distance_cm), weights; identity empty.")

    def input_files(self) -> list[Path]:
        return [Path(self.params.path)] if os.path.isfile(self.params.path) else []

    def _take(self) -> LiveLinkTake:
        try:
            return read_live_link_csv(self.params.path)
        except ValueError as err:
            raise InputError("path", str(err)) from err

    def frame_count(self) -> int | None:
        return len(self._take().arkit)

    def run(self, model: FaceModel | None = None) -> dict[str, Performance]:
        from .arkit import ARKIT_NAMES

        take = self._take()
        fps = self.params.fps
        if fps <= 0:
            try:
                fps = infer_fps(take)
            except ValueError as err:
                raise InputError("fps", f"{self.params.path}: {err}") from err
        rows = np.arange(self.frames.start, self.frames.stop)
        if rows.size and rows[-1] >= len(take.arkit):
            raise InputError("path", f"{self.params.path}: expected at least {rows[-1] + 1} frames, found "
                                     f"{len(take.arkit)}")
        arkit = take.arkit[rows]
        if model is None:
            names, weights = list(ARKIT_NAMES), arkit.astype(np.float32)
        else:
            names = list(model.expression_names)
            weights, _ = from_arkit_weights(arkit, names)
        rotation = head_rotation(take.angles[rows, :3]).astype(np.float32)
        translation = np.tile(np.array([0.0, 0.0, -self.params.distance_cm], np.float32), (len(rows), 1))
        return {"performance": Performance(rotation, translation, weights, names, np.zeros(len(rows), bool),
                                           np.zeros(0, np.float32), float(fps))}
