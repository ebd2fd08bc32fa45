"""Rigid stabilization baselines: weighted Kabsch/Procrustes, three-point, robust ICP."""

from . import nodes  # noqa: F401  (registers rigid.ReferenceFrame, ThreePoint, Procrustes, ICP)
from .icp import IcpResult, robust_icp, robust_weights, vertex_normals
from .nodes import (ICP, Procrustes, ReferenceFrame, ThreePoint, spread_triple, three_point_frames,
                    triangle_quality)

__all__ = [
    "IcpResult", "robust_icp", "robust_weights", "vertex_normals",
    "triangle_quality", "three_point_frames", "spread_triple",
    "ReferenceFrame", "ThreePoint", "Procrustes", "ICP",
]
