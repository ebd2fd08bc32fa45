"""Graph builders shared by the framework tests."""

from __future__ import annotations

from nodegraph import Graph


def chain(num_frames: int = 40, factor: float = 2.0) -> Graph:
    """ramp -> scale (framewise) -> avg (windowed, halo 3) -> cum (sequence)."""
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=num_frames, slope=0.5)
    scale = g.add("test.Scale", id="scale", factor=factor)
    avg = g.add("test.MovingAverage", id="avg")
    cum = g.add("test.CumSum", id="cum")
    g.connect(ramp["values"], scale["values"])
    g.connect(scale["scaled"], avg["values"])
    g.connect(avg["averaged"], cum["values"])
    return g


def two_branches(fail_frames: list[int]) -> Graph:
    """ramp -> fail -> total_bad ; ramp -> scale -> total_good."""
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=30)
    fail = g.add("test.Fail", id="fail", frames=fail_frames)
    bad = g.add("test.Total", id="total_bad")
    scale = g.add("test.Scale", id="scale", factor=3.0)
    good = g.add("test.Total", id="total_good")
    g.connect(ramp["values"], fail["values"])
    g.connect(fail["passed"], bad["values"])
    g.connect(ramp["values"], scale["values"])
    g.connect(scale["scaled"], good["values"])
    return g
