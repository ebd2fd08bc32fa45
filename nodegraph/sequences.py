"""Per-frame sequences of geometry and parameters: the port types of meshes, rigid motions,
2D landmarks, optical flow and named parameters over frames.

Each has a frame axis (`per_frame`), so the runner chunks it over frames and concatenates the
chunks back. Positions in cm, pixels with the origin top-left, rigid transforms float64 4x4
acting on column vectors.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from .ports import PortType, check_array, check_finite, check_index_groups, fail

__all__ = ["MeshSequence", "RigidSequence", "Landmarks2D", "FlowSequence", "ParamSequence"]


@dataclass(eq=False)
class MeshSequence(PortType):
    """Vertices over frames with one shared topology.

    Attributes:
        vertices: (F, V, 3) float32, cm.
        faces: (T, 3) int, vertex indices (may be (0, 3) for a point cloud).
        uv: (U, 2) float32 texture coordinates, or None. Per vertex when `uv_faces` is None
            (then U == V), else indexed per face corner by `uv_faces`.
        uv_faces: (T, 3) int indices into `uv`, or None.
        groups: named vertex groups, name -> (N,) int vertex indices.
        fps: frames per second.
    """

    vertices: np.ndarray
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    fps: float = 30.0

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("vertices",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "vertices", self.vertices, 3, (None, 3))
        check_finite(where, "vertices", self.vertices)
        v = self.vertices.shape[1]
        check_array(where, "faces", self.faces, 2, (3,), kinds="iu")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= v):
            fail(where, f"'faces' index vertices outside 0..{v - 1}")
        if self.uv is not None:
            check_array(where, "uv", self.uv, 2, (2,))
            if self.uv_faces is None and self.uv.shape[0] != v:
                fail(where, f"per-vertex 'uv' must have {v} rows, found {self.uv.shape[0]}")
        if self.uv_faces is not None:
            check_array(where, "uv_faces", self.uv_faces, 2, (3,), kinds="iu")
            if self.uv_faces.shape != self.faces.shape:
                fail(where, f"'uv_faces' must match 'faces' {self.faces.shape}, found {self.uv_faces.shape}")
        check_index_groups(where, self.groups, v)
        if not self.fps > 0:
            fail(where, f"'fps' must be > 0, found {self.fps}")

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])


@dataclass(eq=False)
class RigidSequence(PortType):
    """One rigid transform per frame.

    Attributes:
        matrices: (F, 4, 4) float64; `matrices[f]` maps points of the local frame (e.g. the
            skull) to world: `x_world = M @ [x_local, 1]`, translation in cm.
    """

    matrices: np.ndarray

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("matrices",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "matrices", self.matrices, 3, (4, 4))
        check_finite(where, "matrices", self.matrices)
        rot = self.matrices[:, :3, :3].astype(np.float64)
        err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(initial=0.0)
        if err > 1e-3:
            fail(where, f"'matrices' rotation blocks must be orthonormal (max |R R^T - I| = {err:.2e})")
        bottom = np.abs(self.matrices[:, 3] - np.array([0, 0, 0, 1])).max(initial=0.0)
        if bottom > 1e-6:
            fail(where, "'matrices' bottom rows must be [0, 0, 0, 1]")



@dataclass(eq=False)
class Landmarks2D(PortType):
    """2D landmarks over frames.

    Attributes:
        points: (F, L, 2) float32, pixels, origin top-left, x to the right.
        confidence: (F, L) float32 in [0, 1] (0 = not detected).
    """

    points: np.ndarray
    confidence: np.ndarray

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("points", "confidence")

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "points", self.points, 3, (None, 2))
        check_array(where, "confidence", self.confidence, 2)
        if self.confidence.shape != self.points.shape[:2]:
            fail(where, f"'confidence' must be {self.points.shape[:2]}, found {self.confidence.shape}")
        super().validate(where)


@dataclass(eq=False)
class FlowSequence(PortType):
    """Optical flow from each frame to the next.

    Attributes:
        flow: (F, H, W, 2) float32, pixels; `flow[f]` maps frame f to frame f + 1.
        valid: (F,) bool, False where no next frame exists or flow failed.
    """

    flow: np.ndarray
    valid: np.ndarray

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("flow", "valid")

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "flow", self.flow, 4, (None, None, 2))
        check_array(where, "valid", self.valid, 1, kinds="b")
        super().validate(where)


@dataclass(eq=False)
class ParamSequence(PortType):
    """Named scalar parameters over frames (e.g. expression weights).

    Attributes:
        values: (F, K) float32.
        names: K parameter names.
    """

    values: np.ndarray
    names: list[str] = field(default_factory=list)

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("values",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "values", self.values, 2)
        if len(self.names) != self.values.shape[1]:
            fail(where, f"{len(self.names)} names for {self.values.shape[1]} columns")
