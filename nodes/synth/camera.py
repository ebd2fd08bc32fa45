"""A synthetic camera placed by eye and target: `synth.LookAtCamera` (renders of synthetic
performances, e.g. `graphs/demo.json`)."""

from __future__ import annotations

import numpy as np

from nodegraph import SEQUENCE, Camera, InputError, Node, NodeParams, Out, Param

from ..geometry.camera import look_at

__all__ = ["look_at", "LookAtCamera"]  # look_at lives in nodes.geometry.camera


class LookAtCamera(Node):
    """A distortion-free pinhole camera at a point, looking at another (synthetic renders)."""

    type_name = "synth.LookAtCamera"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        width: int = Param(256, ge=8, le=16384, description="Image width, pixels.")
        height: int = Param(256, ge=8, le=16384, description="Image height, pixels.")
        fov_deg: float = Param(40.0, gt=1, lt=170, description="Horizontal field of view, degrees.")
        eye_cm: list[float] = Param([0.0, 0.0, 70.0], min_length=3, max_length=3,
                                    description="Camera centre, world, cm (default: 70 cm in front of the ICT "
                                    "head's origin, which faces +z).")
        target_cm: list[float] = Param([0.0, 0.0, 5.0], min_length=3, max_length=3,
                                       description="Point the camera looks at, world, cm.")
        up: list[float] = Param([0.0, 1.0, 0.0], min_length=3, max_length=3, description="World direction shown "
                                "up in the image.")
        name: str = Param("camera", description="Camera name.")

    camera = Out(Camera, doc="The camera (OpenCV convention, cm).")

    def run(self) -> dict[str, Camera]:
        p = self.params
        try:
            extrinsics = look_at(p.eye_cm, p.target_cm, p.up)
        except ValueError as err:
            raise InputError("eye_cm" if "eye" in str(err) else "up", str(err)) from err
        base = Camera.from_fov(p.width, p.height, p.fov_deg, name=p.name)
        return {"camera": Camera(fx=base.fx, fy=base.fy, cx=base.cx, cy=base.cy, width=p.width, height=p.height,
                                 world_to_camera=extrinsics, name=p.name)}
