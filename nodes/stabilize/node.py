"""The `stabilize.ModePursuit` node: mode-pursuit head stabilization of a tracked mesh sequence.

A thin adapter over `nodes.stabilize.mode_pursuit.mode_pursuit` (the method, its energy and
its optimizer are documented there).
"""

from __future__ import annotations

import dataclasses
from typing import Literal

import numpy as np
from pydantic import model_validator

from nodegraph import SEQUENCE, In, InputError, MeshSequence, Node, NodeParams, Out, Param, RigidSequence

from ..geometry.rigid import rigid_fit_problem, stabilize_vertices
from .schedule import DEFAULT_POSITION_WIDTHS, DEFAULT_VELOCITY_WIDTHS

__all__ = ["ModePursuit", "ModePursuitParams", "MIN_ENERGY_VERTICES"]

MIN_ENERGY_VERTICES = 10
"""Fewest vertices a robust rigid fit is trusted on: with 3 or 4 the robust penalty can take one
moving vertex for the head's motion (rotations off by up to 178 degrees were seen); 10 gave 0.17."""


class ModePursuitParams(NodeParams):
    """Parameters of `stabilize.ModePursuit` (default: the adaptive schedule; "fixed" = the paper's)."""

    schedule: Literal["adaptive", "fixed"] = Param(
        "adaptive", description="'adaptive': robust per-frame alignment to the rest's mode, widths "
        "from the estimated noise (final = max(noise_multiple x noise, min_width_cm)), spline "
        "spacing from the shot length, then a per-frame polish; the width lists, spacing and "
        "refinements below are not used. 'fixed': the paper's schedule with those settings.")
    noise_multiple: float = Param(5.0, gt=0, description="Adaptive: final width in estimated "
                                                         "noise std (unitless).")
    min_width_cm: float = Param(0.02, gt=0, description="Adaptive: smallest width (cm).")
    polish_iterations: int = Param(3, ge=0, description="Adaptive: IRLS steps of the final "
                                                        "per-frame robust alignment to the rest "
                                                        "(0 = none).")
    still_refinement: bool = Param(True, description="Adaptive: last, re-align every frame on the "
                                   "vertices still up to the noise over the whole shot and around that frame (up to 31 "
                                   "frames averaged; 3 rounds). Frame by frame, "
                                   "expression motion under the final width (5 noise std: 0.5 cm at "
                                   "0.1 cm noise) looks like rest and biases the pose; over a few "
                                   "frames it does not. On by default: it removes that bias and "
                                   "changes little where there is none.")
    prior_group: str = Param("rigid", description="Adaptive: vertex group of (nearly) rigid "
                             "vertices weighted prior_weight in the robust alignments; used only "
                             "when the mesh has it (\"\" = none).")
    prior_weight: float = Param(2.0, ge=0, description="Adaptive: weight of prior_group vertices "
                                                       "(others 1; unitless).")
    position_widths: list[float] = Param(list(DEFAULT_POSITION_WIDTHS),
                                         description="Fixed schedule: continuation widths of the position penalty, "
                                                     "coarse to fine (cm).", min_length=1)
    velocity_widths: list[float] = Param(list(DEFAULT_VELOCITY_WIDTHS),
                                         description="Fixed schedule: continuation widths of the velocity penalty, "
                                                     "one per position width (cm/frame).", min_length=1)
    velocity_weight: float = Param(1.0, ge=0, description="Weight lambda of the velocity term "
                                                          "(unitless).")
    spacing: float = Param(8.0, ge=1, description="Fixed schedule: control-point spacing of the initial (coarsest) "
                                                  "dual-quaternion spline (frames).")
    refinements: int = Param(2, ge=0, le=8, description="Fixed schedule: midpoint refinements of the spline during "
                                                        "the schedule; the final spacing is "
                                                        "spacing / 2^refinements (frames).")
    iterations: int = Param(12, ge=0, description="L-BFGS iterations per stage (fixed count; the "
                                                  "paper used 24 with its fixed schedule).")
    group: str = Param("", description="Vertex group of the mesh that enters the energy (e.g. the "
                                       "face region); \"\" = all vertices.")
    max_vertices: int = Param(2000, ge=MIN_ENERGY_VERTICES, description="At most this many energy vertices "
                              "(farthest-point sampling, deterministic); at least 10, since a robust fit "
                              "to fewer takes a moving vertex for the head's motion.")
    update_rest: bool = Param(True, description="Re-estimate the rest shape (mean shift) before "
                                                "each stage; ignored when 'rest' is connected.")
    device: str = Param("auto", affects_output=False, pattern="^(auto|cpu|cuda(:[0-9]+)?)$",
                        description="Torch device: auto (CUDA when available), cpu or cuda.")
    compile: bool = Param(False, affects_output=False,
                          description="torch.compile the energy kernel (one-off compile cost).")

    @model_validator(mode="after")
    def _check_widths(self) -> "ModePursuitParams":
        if len(self.velocity_widths) != len(self.position_widths):
            raise ValueError(f"velocity_widths: expected {len(self.position_widths)} widths (one per "
                             f"position width), found {len(self.velocity_widths)}")
        bad = [w for w in self.position_widths + self.velocity_widths if not w > 0]
        if bad:
            raise ValueError(f"position_widths/velocity_widths: expected widths > 0, found {bad}")
        if self.spacing / 2 ** self.refinements < 1.0:
            raise ValueError(f"refinements: spacing {self.spacing} / 2^{self.refinements} is below "
                             f"1 frame; use spacing >= {2 ** self.refinements} or fewer refinements")
        return self


class ModePursuit(Node):
    """Stabilize a tracked face by mode pursuit over a dual-quaternion spline of head motion.

    Finds the skull-to-world motion whose removal brings each vertex back to its rest position
    as often as possible (bounded penalty on positions and velocities, continuation over widths,
    spline, L-BFGS). Outputs the motion and the stabilized mesh (all vertices). The default
    adaptive schedule needs no per-shot settings: it aligns every frame robustly to the rest's
    mode (any head motion, any initialization), estimates the noise, ends the widths at a
    multiple of it, adapts the spline spacing to the shot length and polishes each frame; the
    chosen schedule is reported in the progress messages.
    """

    type_name = "stabilize.ModePursuit"
    version = 4
    kind = SEQUENCE
    # Imported in the runner's preload thread while the capture is read: torch, the solver, and
    # the numba kernels of robust_kernels.py loaded from numba's cache (preload_kernels.py).
    preload = ("torch", "nodes.stabilize.mode_pursuit", "nodes.stabilize.preload_kernels")
    skips_unread_outputs = True
    Params = ModePursuitParams

    @classmethod
    def migrate(cls, from_version: int, params: dict) -> dict:
        """Graphs written for v1 (the paper's fixed schedule, 24 iterations) keep their results."""
        params = dict(params)
        if from_version < 2:
            params.setdefault("schedule", "fixed")
            params.setdefault("iterations", 24)
        return params

    mesh = In(MeshSequence, doc="Tracked mesh sequence, world frame, vertices in correspondence, cm.")
    init = In(RigidSequence, optional=True,
              doc="Initial skull-to-world motion (e.g. rigid.Procrustes); identity when unconnected.")
    rest = In(MeshSequence, optional=True, per_frame=False,
              doc="One-frame rest mesh in the skull frame; default: per-vertex median of the "
                  "initially stabilized mesh.")
    rigid = Out(RigidSequence, doc="Skull-to-world transforms M_f (x_world = M_f @ x_skull).")
    stabilized = Out(MeshSequence, doc="Stabilized mesh M_f^-1 mesh_f (skull frame, all vertices), cm.")

    def run(self, mesh: MeshSequence, init: RigidSequence | None = None,
            rest: MeshSequence | None = None) -> dict:
        p = self.params
        if p.schedule == "fixed" and mesh.num_frames < 7:
            raise InputError("mesh", f"expected at least 7 frames (the velocity filter spans 7), "
                                     f"found {mesh.num_frames}")
        if p.group and p.group not in mesh.groups:
            raise InputError("group", f"expected a vertex group '{p.group}' of the mesh, found "
                                      f"groups {sorted(mesh.groups)}")
        ids = np.asarray(mesh.groups[p.group], np.int64) if p.group else None
        problem = rigid_fit_problem(mesh.vertices[0] if ids is None else mesh.vertices[0, np.unique(ids)],
                                    least=MIN_ENERGY_VERTICES)
        if problem:
            raise InputError("group" if ids is not None else "mesh",
                             (f"group '{p.group}': " if ids is not None else "") + problem)
        rest_vertices = None
        if rest is not None:
            if rest.num_frames != 1:
                raise InputError("rest", f"expected a one-frame mesh, found {rest.num_frames} frames")
            if rest.num_vertices != mesh.num_vertices:
                raise InputError("rest", f"expected {mesh.num_vertices} vertices (as 'mesh'), "
                                         f"found {rest.num_vertices}")
            rest_vertices = rest.vertices[0]
        prior = None
        if p.schedule == "adaptive" and p.prior_group and p.prior_group in mesh.groups and p.prior_weight != 1.0:
            prior = np.ones(mesh.num_vertices, np.float32)
            prior[np.asarray(mesh.groups[p.prior_group], np.int64)] = p.prior_weight
        import torch

        from .mode_pursuit import mode_pursuit

        if p.device.startswith("cuda") and not torch.cuda.is_available():
            raise InputError("device", f"expected an available device, found '{p.device}' but CUDA "
                                       f"is not available (use 'auto' or 'cpu')")
        result = mode_pursuit(
            mesh.vertices, init=None if init is None else init.matrices, rest=rest_vertices,
            vertex_ids=ids, vertex_weights=prior, schedule=p.schedule,
            position_widths=p.position_widths, velocity_widths=p.velocity_widths,
            velocity_weight=p.velocity_weight, spacing=p.spacing, refinements=p.refinements,
            iterations=p.iterations, max_vertices=p.max_vertices, update_rest=p.update_rest,
            noise_multiple=p.noise_multiple, min_width=p.min_width_cm,
            polish_iterations=p.polish_iterations, still_refinement=p.still_refinement,
            device=p.device, compile=p.compile, progress=self.progress)
        out: dict = {"rigid": RigidSequence(np.ascontiguousarray(result.matrices, np.float64))}
        if self.wants("stabilized"):  # not computed when no edge reads it (skips_unread_outputs)
            out["stabilized"] = dataclasses.replace(mesh, vertices=stabilize_vertices(mesh.vertices, result.matrices))
        return out
