"""Head stabilization by mode pursuit over dual-quaternion splines (seed paper 1)."""

from .bspline import (SplineBasis, basis_matrix, bspline_basis, evaluate_spline, fit_control_points,
                      frame_basis, num_control_points, refine_midpoint, uniform_knots)
from .dualquat import (dualquat_align_hemisphere, dualquat_blend, dualquat_conjugate,
                       dualquat_from_matrix, dualquat_from_rotation_translation, dualquat_identity,
                       dualquat_multiply, dualquat_normalize, dualquat_to_matrix,
                       dualquat_to_rotation_translation, dualquat_to_rotmat_translation,
                       dualquat_transform_points, quat_conjugate, quat_multiply, quat_to_rotmat,
                       rotmat_to_quat)
from .energy import fused_stabilization_energy, stabilization_energy
from .lbfgs import lbfgs
from .mode_pursuit import (ModePursuitResult, farthest_point_sampling, invert_rigid, mode_pursuit,
                           stabilize_vertices)
from .schedule import DEFAULT_POSITION_WIDTHS, DEFAULT_VELOCITY_WIDTHS, Stage, StageLog, make_schedule
from .node import ModePursuit, ModePursuitParams  # importing registers stabilize.ModePursuit
from .penalty import (VELOCITY_COEFFS, central_velocity, central_velocity_adjoint, psi, psi_derivative,
                      psi_sum_and_grad_)

__all__ = [
    "SplineBasis", "basis_matrix", "bspline_basis", "evaluate_spline", "fit_control_points",
    "frame_basis", "num_control_points", "refine_midpoint", "uniform_knots",
    "dualquat_align_hemisphere", "dualquat_blend", "dualquat_conjugate", "dualquat_from_matrix",
    "dualquat_from_rotation_translation", "dualquat_identity", "dualquat_multiply",
    "dualquat_normalize", "dualquat_to_matrix", "dualquat_to_rotation_translation",
    "dualquat_to_rotmat_translation", "dualquat_transform_points", "quat_conjugate",
    "quat_multiply", "quat_to_rotmat", "rotmat_to_quat",
    "DEFAULT_POSITION_WIDTHS", "DEFAULT_VELOCITY_WIDTHS", "ModePursuitResult", "Stage", "StageLog",
    "farthest_point_sampling", "fused_stabilization_energy", "invert_rigid", "lbfgs",
    "make_schedule", "mode_pursuit", "stabilization_energy", "stabilize_vertices",
    "ModePursuit", "ModePursuitParams",
    "VELOCITY_COEFFS", "central_velocity", "central_velocity_adjoint", "psi", "psi_derivative",
    "psi_sum_and_grad_",
]
