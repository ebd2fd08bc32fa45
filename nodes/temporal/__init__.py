"""Temporal refinement of fitted parameters: parameter layout (`layout.py`), three-frame averaging
(`averaging.py`), per-frame plate/self-flow solves (`flowfit.py`), infill and smoothing sweeps
(`sweeps.py`), the nodes (`nodes.py`) and the motion report (`report.py`). (The synthetic plates
of its tests and benches are in `tests/support/synthetic.py`.)

Importing the package registers the nodes only; torch is imported when a node runs.
"""

from .nodes import AdaptiveSmooth, Average, FlowInfill, Hybrid, PlateFlow, SelfFlow
from .report import MotionReport

__all__ = ["AdaptiveSmooth", "Average", "FlowInfill", "Hybrid", "MotionReport", "PlateFlow", "SelfFlow"]
