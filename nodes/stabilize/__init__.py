"""Head stabilization by mode pursuit over dual-quaternion splines (seed paper 1).

Importing the package registers `stabilize.ModePursuit` and nothing heavier: the method lives
in the submodules (`mode_pursuit`, `energy`, `schedule`, `penalty`, `lbfgs`; dual quaternions
and B-splines in `nodes.geometry`), which import torch and are loaded when the node runs.
"""

from .node import ModePursuit, ModePursuitParams  # importing registers stabilize.ModePursuit

__all__ = ["ModePursuit", "ModePursuitParams"]
