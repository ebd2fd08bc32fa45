"""Small node types for tests, examples and benchmarks of the framework itself.

They work on `ParamSequence` values (one float column) so results are easy to check:
`test.Ramp` produces `value[f] = start + slope * f` for absolute frame f, `test.Scale`
multiplies (framewise), `test.MovingAverage` averages over a window (windowed), `test.CumSum`
sums over the whole sequence (sequence), `test.Fail` raises on chosen frames, and
`test.Sum` adds two sequences. Import this module to register them.
"""

from __future__ import annotations

import numpy as np

from .errors import InputError
from .node import FRAMEWISE, SEQUENCE, In, Node, NodeParams, Out, Param, windowed
from .types import JsonValue, ParamSequence

__all__ = ["Ramp", "Scale", "MovingAverage", "CumSum", "Fail", "Sum", "Total", "Offset"]


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

    values = In(ParamSequence)
    passed = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        hit = [f for f in self.params.frames if f in self.frames]
        if hit and self.params.bad_input:
            raise InputError("values", f"frame {hit[0]} is not acceptable")
        if hit:
            raise RuntimeError(f"deliberate failure at frame {hit[0]}")
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
