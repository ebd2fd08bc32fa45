"""Write a performance as a Live Link Face CSV (`export.LiveLinkCSV`): the take layout of the
Live Link Face app, which Unreal's importer and the MetaHuman tools read.

Columns, timecodes and angle conventions: `nodes.io.arkit`; the reader is `io.LoadLiveLinkCSV`.
"""

from __future__ import annotations

import numpy as np
from pydantic import field_validator

from nodegraph import SEQUENCE, Camera, Files, In, InputError, Node, NodeParams, Out, Param, Performance
from nodegraph.files import check_output_suffix, files_value, write_text_atomic

from ..io.arkit import (ANGLE_UNIT_RAD, ARKIT_NAMES, BLEND_SHAPE_COUNT, LIVE_LINK_HEADER, arkit_name, eye_angles,
                        format_timecode, head_angles, parse_timecode, to_arkit_weights)
from .scene import head_transforms

__all__ = ["live_link_rows", "live_link_text", "LiveLinkCSV"]


def live_link_rows(arkit: np.ndarray, head: np.ndarray, fps: float, start: str = "00:00:00:00",
                   decimals: int = 6, first_frame: int = 0) -> list[list[str]]:
    """The CSV's data rows.

    Args:
        arkit: (F, 52) ARKit weights in `ARKIT_NAMES` order (clipped to [0, 1] here).
        head: (F, 3, 3) face rotations in ARKit's camera frame.
        fps: the shot's frame rate (timecodes).
        start: timecode of the shot's frame 0.
        decimals: digits after the point of every value.
        first_frame: the shot's frame of the first row (a run of frames a:b starts at a).
    Returns:
        F rows of 63 cells.
    """
    weights = np.clip(np.asarray(arkit, np.float64), 0.0, 1.0)
    angles = np.concatenate([head_angles(head), eye_angles(weights)], axis=1) / ANGLE_UNIT_RAD
    cells = np.char.mod(f"%.{decimals}f", np.concatenate([weights, angles], axis=1))
    cells[cells == "-" + "0." + "0" * decimals] = "0." + "0" * decimals  # -0.0 and -1e-9 alike: no "-0.000000"
    return [[format_timecode(first_frame + i, fps, start), str(BLEND_SHAPE_COUNT), *row]
            for i, row in enumerate(cells.tolist())]


def live_link_text(rows: list[list[str]]) -> str:
    """The whole file: the header and the rows, comma-separated, `\\n` line ends."""
    return "\n".join(",".join(r) for r in [list(LIVE_LINK_HEADER), *rows]) + "\n"


class LiveLinkCSV(Node):
    """Write the performance as a Live Link Face CSV take (52 ARKit curves, head and eye angles)."""

    type_name = "export.LiveLinkCSV"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination .csv; '' = write nothing.")
        start_timecode: str = Param("00:00:00:00", description="Timecode of the shot's frame 0, HH:MM:SS:FF at "
                                    "the shot's frame rate (rounded to whole frames a second); a run of "
                                    "--frames a:b starts at frame a's timecode.")
        decimals: int = Param(6, ge=3, le=9, description="Digits after the point (6: weights to 1e-6, below "
                              "any visible difference).")

        @field_validator("path")
        @classmethod
        def _csv(cls, value: str) -> str:
            return check_output_suffix(value, (".csv",), allow_empty=True)

        @field_validator("start_timecode")
        @classmethod
        def _timecode(cls, value: str) -> str:
            parse_timecode(value)
            return value

    performance = In(Performance, doc="The performance (weights by the model's names: ICT or ARKit).")
    camera = In(Camera, optional=True, doc="The plate's camera: head angles relative to it (as the app "
                "records them); absent: relative to the performance's world, taken as y up and facing +z.")
    files = Out(Files, doc="The CSV written (none for an empty path).")

    def run(self, performance: Performance, camera: Camera | None = None) -> dict[str, Files]:
        if not self.params.path:
            return {"files": files_value([])}
        if not any(arkit_name(n) in ARKIT_NAMES for n in performance.expression_names):
            raise InputError("performance", f"expected ARKit or ICT shape names, found "
                                            f"{performance.expression_names[:4]}")
        arkit = to_arkit_weights(performance.weights, performance.expression_names)
        head = head_transforms(performance, camera)[:, :3, :3]
        rows = live_link_rows(arkit, head, performance.fps, self.params.start_timecode, self.params.decimals,
                              first_frame=self.frames.start)
        write_text_atomic(self.params.path, live_link_text(rows))
        self.progress(1.0, f"wrote {len(rows)} frames to {self.params.path}")
        return {"files": files_value([self.params.path])}
