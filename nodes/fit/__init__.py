"""Deep-energy pose and expression fitting (paper 2, PAPERS.md §2): energies (`energy.py`),
renders read by the landmark network and their anchors (`views.py`), the staged solver
(`solve.py`), appearance (`appearance.py`) and identity (`identity.py`) estimation,
synthetic plates (`synthetic.py`), the nodes (`nodes.py`), and the fit as a `Performance`
(`performance.py`).

Importing the package registers the nodes only; torch is imported when a node runs.
"""

from .nodes import (EstimateAppearance, EstimateIdentity, Expression, FitReport, FlagFailures, PlateCamera,
                    RigidPose, SaveFit)
from .performance import MakePerformance, PosedMesh

__all__ = ["PlateCamera", "EstimateAppearance", "EstimateIdentity", "RigidPose", "Expression", "FlagFailures",
           "SaveFit", "FitReport", "MakePerformance", "PosedMesh"]
