"""Deep-energy pose and expression fitting (paper 2, PAPERS.md §2): energies (`energy.py`),
renders read by the landmark network and their anchors (`views.py`), the staged solver
(`solve.py`), appearance (`appearance.py`) and identity (`identity.py`) estimation, and
the nodes: the node inputs as solver tensors
(`node_inputs.py`), frame selection (`frame_selection.py`), tuning constants and the
measurements behind them (`tuning.py`), the per-shot camera, appearance and identity
(`estimation_nodes.py`), the per-frame rigid and expression stages (`pose_nodes.py`), failure
flags, NPZ and overlays (`output_nodes.py`), and the fit as a `Performance` (`performance.py`).

Importing the package registers the nodes only; torch is imported when a node runs.
"""

from .estimation_nodes import EstimateAppearance, EstimateIdentity, PlateCamera
from .output_nodes import FitReport, FittedLandmarks, FlagFailures, SaveFit
from .performance import MakePerformance, PosedMesh
from .pose_nodes import Expression, RigidPose

__all__ = ["PlateCamera", "EstimateAppearance", "EstimateIdentity", "RigidPose", "Expression", "FlagFailures",
           "FittedLandmarks", "SaveFit", "FitReport", "MakePerformance", "PosedMesh"]
