"""Small node types for tests, examples and benchmarks of the framework itself.

They work on `ParamSequence` values (one float column) so results are easy to check:
`test.Ramp` produces `value[f] = start + slope * f` for absolute frame f, `test.Scale`
multiplies (framewise), `test.MovingAverage` averages over a window (windowed), `test.CumSum`
sums over the whole sequence (sequence), `test.Fail` raises on chosen frames, and
`test.Sum` adds two sequences, `test.Weighted` weights a list port by position, `test.Noise`
draws from the task's seed, `test.WriteText` / `test.ReadText` write and read numbered text
files, `test.ReadLines` reads one text file, `test.WriteSummary` writes a folder and
`test.JoinFiles` reads the files of upstream writers and writes them joined into one. Import
this module to register them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import InputError
from .node import FRAMEWISE, SEQUENCE, In, Node, Out, windowed
from .params import NodeParams, Param
from .types import Files, JsonValue, ParamSequence

__all__ = ["Ramp", "Scale", "MovingAverage", "CumSum", "Fail", "Sum", "Total", "Offset", "Weighted", "Noise",
           "WriteText", "ReadText", "ReadLines", "WriteSummary", "JoinFiles"]


def _column(values: np.ndarray) -> ParamSequence:
    return ParamSequence(values.astype(np.float32).reshape(-1, 1), ["value"])


class Ramp(Node):
    """A source: value[f] = start + slope * f over `num_frames` frames."""

    type_name = "test.Ramp"
    kind = FRAMEWISE

    class Params(NodeParams):
        num_frames: int = Param(100, ge=1, description="Frames produced.")
        start: float = Param(0.0, description="Value at frame 0.")
        slope: float = Param(1.0, description="Increase per frame.")

    values = Out(ParamSequence)

    def frame_count(self) -> int:
        return self.params.num_frames

    def run(self) -> dict:
        if self.frames.stop > self.params.num_frames:
            raise InputError("num_frames", f"frames {self.frames.start}:{self.frames.stop} requested, "
                             f"only {self.params.num_frames} exist")
        f = np.arange(self.frames.start, self.frames.stop, dtype=np.float64)
        return {"values": _column(self.params.start + self.params.slope * f)}


class Scale(Node):
    """Multiply by a factor (framewise)."""

    type_name = "test.Scale"
    kind = FRAMEWISE

    class Params(NodeParams):
        factor: float = Param(1.0, description="Multiplier.")
        label: str = Param("", affects_output=False, description="Ignored by the computation.")

    values = In(ParamSequence)
    scaled = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        return {"scaled": ParamSequence(values.values * np.float32(self.params.factor), list(values.names))}


class MovingAverage(Node):
    """Centered moving average over 2*halo+1 frames, edge frames repeated (windowed)."""

    type_name = "test.MovingAverage"
    kind = windowed(3)

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    averaged = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        h = self.kind.halo
        x = values.values
        # Edge frames are repeated. Inside the run, the padding only touches halo frames,
        # which the runner trims; at the run's ends it is the same whatever the chunking.
        padded = np.concatenate([np.repeat(x[:1], h, 0), x, np.repeat(x[-1:], h, 0)], axis=0)
        out = np.zeros_like(x)
        for shift in range(2 * h + 1):
            out += padded[shift:shift + len(x)]
        return {"averaged": ParamSequence(out / np.float32(2 * h + 1), list(values.names))}


class CumSum(Node):
    """Cumulative sum over the whole sequence (sequence)."""

    type_name = "test.CumSum"
    kind = SEQUENCE

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    total = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        return {"total": ParamSequence(np.cumsum(values.values, axis=0, dtype=np.float32), list(values.names))}


class Fail(Node):
    """Pass values through, but raise on the frames listed (to test failure handling)."""

    type_name = "test.Fail"
    kind = FRAMEWISE

    class Params(NodeParams):
        frames: list[int] = Param([0], description="Absolute frames that raise.")
        bad_input: bool = Param(False, description="Raise InputError instead of RuntimeError.")
        message: str = Param("", description="Raise with this message in every failing chunk ('' = name the "
                             "frame).")

    values = In(ParamSequence)
    passed = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        hit = [f for f in self.params.frames if f in self.frames]
        if hit and self.params.bad_input:
            raise InputError("values", self.params.message or f"frame {hit[0]} is not acceptable")
        if hit:
            raise RuntimeError(self.params.message or f"deliberate failure at frame {hit[0]}")
        return {"passed": values}


class Sum(Node):
    """Add two sequences (framewise)."""

    type_name = "test.Sum"
    kind = FRAMEWISE

    class Params(NodeParams):
        pass

    a = In(ParamSequence)
    b = In(ParamSequence, optional=True)
    total = Out(ParamSequence)

    def run(self, a: ParamSequence, b: ParamSequence | None) -> dict:
        values = a.values if b is None else a.values + b.values
        return {"total": ParamSequence(values, list(a.names))}


class Total(Node):
    """The sum of all values, as one JSON number (sequence, whole-value output)."""

    type_name = "test.Total"
    kind = SEQUENCE

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    total = Out(JsonValue)

    def run(self, values: ParamSequence) -> dict:
        return {"total": JsonValue(float(values.values.astype(np.float64).sum()))}


class Offset(Node):
    """Add a constant (framewise). Version 2 renamed the parameter `amount` to `offset`."""

    type_name = "test.Offset"
    version = 2
    kind = FRAMEWISE

    class Params(NodeParams):
        offset: float = Param(0.0, description="Added to every value.")

    values = In(ParamSequence)
    shifted = Out(ParamSequence)

    @classmethod
    def migrate(cls, from_version: int, params: dict) -> dict:
        params = dict(params)
        if from_version == 1 and "amount" in params:
            params["offset"] = params.pop("amount")
        return params

    def run(self, values: ParamSequence) -> dict:
        return {"shifted": ParamSequence(values.values + np.float32(self.params.offset), list(values.names))}


class Weighted(Node):
    """A list port: sum_i (i + 1) * values_i, so that the order of connections shows (framewise)."""

    type_name = "test.Weighted"
    kind = FRAMEWISE

    class Params(NodeParams):
        pass

    values = In(ParamSequence, many=True)
    total = Out(ParamSequence)

    def run(self, values: list[ParamSequence]) -> dict:
        out = sum(np.float32(i + 1) * v.values for i, v in enumerate(values))
        return {"total": ParamSequence(np.asarray(out, np.float32), list(values[0].names))}


class Noise(Node):
    """Random values from the task's seed (framewise), named after the device the node got."""

    type_name = "test.Noise"
    kind = FRAMEWISE
    resources = {"gpu": 1}

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    noise = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        rng = np.random.default_rng(self.seed)
        where = self._device if self._device != "auto" else "auto"
        try:
            from distributed import get_worker

            where += "@" + get_worker().address
        except (ImportError, ValueError):
            pass
        return {"noise": ParamSequence(rng.standard_normal(values.values.shape).astype(np.float32), [where])}


class WriteText(Node):
    """Write each frame's value to numbered text files, or all to one file (a writer node)."""

    type_name = "test.WriteText"
    kind = FRAMEWISE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="File, or pattern with {frame} for one per frame.")
        fail_frames: list[int] = Param([], description="Raise after writing a chunk holding one of these "
                                       "absolute frames (to test partial writes).")

    values = In(ParamSequence)
    files = Out(Files)

    def run(self, values: ParamSequence) -> dict:
        from .files import file_sha256, write_text_atomic

        rows = values.values[:, 0]
        if "{frame}" in self.params.path:
            paths = [self.params.path.format(frame=f) for f in self.frames]
            for path, value in zip(paths, rows):
                write_text_atomic(path, f"{value!r}\n")
        else:
            paths = [self.params.path.format(start=self.frames.start)]
            write_text_atomic(paths[0], "".join(f"{v!r}\n" for v in rows))
        hit = [f for f in self.params.fail_frames if f in self.frames]
        if hit:
            raise RuntimeError(f"deliberate failure after writing frame {hit[0]}")
        return {"files": Files(paths, [file_sha256(p, memo=False) for p in paths])}


class ReadText(Node):
    """A framewise source reading one number per frame from numbered text files ({frame})."""

    type_name = "test.ReadText"
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Pattern with {frame}.")
        num_frames: int = Param(..., ge=1, description="Frames to read.")

    values = Out(ParamSequence)

    def frame_count(self) -> int:
        return self.params.num_frames

    def input_files(self, frames: range | None = None) -> list[Path]:
        frames = range(self.params.num_frames) if frames is None else frames
        return [Path(self.params.path.format(frame=f)) for f in frames]

    def run(self) -> dict:
        rows = [float(Path(self.params.path.format(frame=f)).read_text()) for f in self.frames]
        return {"values": _column(np.asarray(rows))}


class ReadLines(Node):
    """A framewise source reading one number per line of one text file."""

    type_name = "test.ReadLines"
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Text file, one number per line.")

    values = Out(ParamSequence)

    def frame_count(self) -> int:
        return len(Path(self.params.path).read_text().split())

    def run(self) -> dict:
        rows = [float(v) for v in Path(self.params.path).read_text().split()]
        return {"values": _column(np.asarray(rows[self.frames.start:self.frames.stop]))}


class WriteSummary(Node):
    """Write `summary.txt` (count and sum of the values) into a folder (a writer; '' = write nothing)."""

    type_name = "test.WriteSummary"
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        folder: str = Param(..., output_file=True, description="Output folder (created); '' = write nothing.")

    values = In(ParamSequence)
    files = Out(Files)

    def run(self, values: ParamSequence) -> dict:
        from .files import files_value, write_text_atomic

        if not self.params.folder:
            return {"files": Files([], [])}
        path = Path(self.params.folder) / "summary.txt"
        write_text_atomic(path, f"{len(values.values)} {float(values.values.sum())!r}\n")
        return {"files": files_value([path])}


class JoinFiles(Node):
    """Read the files of upstream writers and write them joined into one file (a writer that
    reads what other writers wrote in the same run)."""

    type_name = "test.JoinFiles"
    kind = SEQUENCE
    writes_files = True
    cacheable = False

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination file.")
        fail: bool = Param(False, description="Raise after writing (to test that published files are undone).")

    parts = In(Files, many=True)
    files = Out(Files)

    def run(self, parts: list[Files]) -> dict:
        from .files import files_value, write_text_atomic

        text = "".join(Path(path).read_text() for files in parts for path in files.paths)
        write_text_atomic(self.params.path, text)
        if self.params.fail:
            raise RuntimeError("deliberate failure after joining")
        return {"files": files_value([self.params.path])}
