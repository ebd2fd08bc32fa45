"""Rigid stabilization baselines: weighted Kabsch/Procrustes, three-point, robust ICP.

Importing the package registers the nodes; robust ICP itself (`icp.py`, scipy) is imported
when `rigid.ICP` runs, and the rigid-transform math is in `nodes.geometry.rigid`.
"""

from .nodes import (ICP, Procrustes, ReferenceFrame, ThreePoint, spread_triple, three_point_frames,
                    triangle_quality)

__all__ = [
    "triangle_quality", "three_point_frames", "spread_triple",
    "ReferenceFrame", "ThreePoint", "Procrustes", "ICP",
]
