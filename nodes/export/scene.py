"""What every animation writer needs from a performance and a face model: the head's motion in
the file's frame, and the model's shapes as ARKit-named blendshapes with their weights.

**Frames.** With a camera, the head moves in ARKit's camera frame (the camera at the origin,
x right, y up, looking down -z: the convention of USD, glTF and ARKit alike), so a fit from a
video plays in front of the file's default view; without one, in the performance's own world
(y up when it came from `io.LoadLiveLinkCSV` or a y-up capture).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
from pydantic import field_validator

from nodegraph import SEQUENCE, Camera, FaceModel, Files, In, InputError, Node, NodeParams, Out, Param, Performance
from nodegraph.files import check_output_suffix, files_value

from ..geometry.rotation import quat_sequence_continuous, rotmat_to_quat
from ..io.arkit import OPENCV_TO_ARKIT, shape_basis

__all__ = ["head_transforms", "head_quaternions", "Blendshapes", "blendshapes", "SceneWriterParams", "SceneWriter"]


def head_transforms(performance: Performance, camera: Camera | None = None) -> np.ndarray:
    """(F, 4, 4) float64 head model-to-file transforms, cm.

    Args:
        performance: its rotation and translation are model-to-world.
        camera: when given, the file's frame is the camera's in ARKit's convention:
            `diag(1, -1, -1, 1) @ world_to_camera @ M_f`.
    """
    rigid = performance.rigid()
    if camera is None:
        return rigid
    to_file = np.eye(4)
    to_file[:3, :3] = OPENCV_TO_ARKIT
    return to_file @ np.asarray(camera.world_to_camera, np.float64) @ rigid


def head_quaternions(transforms: np.ndarray) -> np.ndarray:
    """(F, 4) unit quaternions (w, x, y, z) of (F, 4, 4) `head_transforms`, sign-continuous over the
    frames (a file's curve never turns the long way between q and -q); (0, 4) for no frames."""
    if not len(transforms):
        return np.zeros((0, 4))
    return quat_sequence_continuous(rotmat_to_quat(np.asarray(transforms)[:, :3, :3]))


@dataclass
class Blendshapes:
    """A model's shapes as the file's blendshapes.

    Attributes:
        names: S blendshape names (the 52 ARKit names first, then asymmetry shapes and others).
        offsets: (S, V, 3) float32 vertex offsets, cm, model frame.
        weights: (F, S) float32 weight of each blendshape at each frame.
    """

    names: list[str]
    offsets: np.ndarray
    weights: np.ndarray


def blendshapes(performance: Performance, model: FaceModel, *, asymmetry: bool = True) -> Blendshapes:
    """The model's shapes as ARKit blendshapes and the performance's weights on them.

    `neutral + sum_s weights[:, s] offsets[s]` equals `model.evaluate(w)` for the performance's
    weights `w` (exactly with `asymmetry`; without it a left-right difference of ICT's split
    browInnerUp and cheekPuff is averaged away). See `nodes.io.arkit.shape_basis`.
    """
    names = list(model.expression_names)
    w = performance.weights_in(names).astype(np.float64)
    out_names, a, b = shape_basis(names, asymmetry=asymmetry)
    k, v = model.expression_deltas.shape[:2]
    offsets = (b @ model.expression_deltas.reshape(k, -1).astype(np.float64)).reshape(-1, v, 3)
    return Blendshapes(out_names, offsets.astype(np.float32), (w @ a.T).astype(np.float32))


class SceneWriterParams(NodeParams):
    """Parameters of the head-and-blendshape writers; a subclass sets `suffixes` (and the path's description)."""

    suffixes: ClassVar[tuple[str, ...]] = ()

    path: str = Param(..., output_file=True, description="Destination file; '' = write nothing.")
    asymmetry_shapes: bool = Param(True, description="Also write browInnerUpAsymmetry and cheekPuffAsymmetry, so "
                                   "ICT's separate left and right halves of those shapes play back exactly (off: "
                                   "the 52 ARKit shapes only, halves averaged).")

    @field_validator("path")
    @classmethod
    def _suffix(cls, value: str) -> str:
        return check_output_suffix(value, cls.suffixes, allow_empty=True)


class SceneWriter(Node):
    """What the USD and glTF writers share: ports, checks, the empty path; a subclass defines `write`."""

    kind = SEQUENCE
    writes_files = True
    Params = SceneWriterParams

    performance = In(Performance, doc="Pose and weights of the model's shapes.")
    model = In(FaceModel, doc="The fitted head (fit.EstimateIdentity's fitted_model: identity applied).")
    camera = In(Camera, optional=True, doc="The plate's camera: the head moves relative to it (y up, the camera "
                "at the origin looking down -z); absent: in the performance's world.")
    files = Out(Files, doc="The file written (none for an empty path).")

    def write(self, path: Path, model: FaceModel, performance: Performance, camera: Camera | None) -> None:
        raise NotImplementedError

    def run(self, performance: Performance, model: FaceModel, camera: Camera | None = None) -> dict[str, Files]:
        if not self.params.path:
            return {"files": files_value([])}
        try:
            performance.weights_in(model.expression_names)
        except ValueError as err:
            raise InputError("performance", str(err)) from err
        self.write(Path(self.params.path), model, performance, camera)
        self.progress(1.0, f"wrote {performance.num_frames} frames to {self.params.path}")
        return {"files": files_value([self.params.path])}
