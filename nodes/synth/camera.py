"""A synthetic camera placed by eye and target: `synth.LookAtCamera` (renders of synthetic
performances, e.g. `graphs/demo.json`)."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from nodegraph import SEQUENCE, Camera, InputError, Node, NodeParams, Out, Param

__all__ = ["look_at", "LookAtCamera"]


def look_at(eye_cm: Sequence[float], target_cm: Sequence[float], up: Sequence[float] = (0.0, 1.0, 0.0)) -> np.ndarray:
    """The world-to-camera transform of a camera at `eye_cm` looking at `target_cm`.

    OpenCV convention: the camera looks down its +z, x to the right, y down; the world's `up`
    appears up in the image.

    Args:
        eye_cm: (3,) camera centre, world, cm.
        target_cm: (3,) point on the optical axis, world, cm.
        up: (3,) world direction shown up (not parallel to the viewing direction).
    Returns:
        (4, 4) float64 rigid transform, `x_cam = E @ x_world`.
    Raises:
        ValueError: when eye and target coincide or `up` is parallel to the viewing direction.

    Example:
        >>> look_at([0, 0, 60], [0, 0, 0])[:3].round(6).tolist()
        [[1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, -1.0, 60.0]]
    """
    eye, target, up_ = (np.asarray(v, np.float64) for v in (eye_cm, target_cm, up))
    forward = target - eye
    if np.linalg.norm(forward) < 1e-9:
        raise ValueError(f"expected a target away from the eye, found both at {eye.tolist()}")
    z = forward / np.linalg.norm(forward)
    down = -(up_ - (up_ @ z) * z)
    if np.linalg.norm(down) < 1e-9 * max(1.0, np.linalg.norm(up_)):
        raise ValueError(f"expected an up direction not parallel to the view {z.round(6).tolist()}, found "
                         f"{up_.tolist()}")
    y = down / np.linalg.norm(down)
    x = np.cross(y, z)
    e = np.eye(4)
    e[:3, :3] = np.stack([x, y, z])
    e[:3, 3] = -e[:3, :3] @ eye
    return e


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
