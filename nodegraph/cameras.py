"""Calibrated cameras: the `Camera` and `CameraRig` port types (OpenCV's convention, cm) and
their JSON form (reading validates; file formats beyond our JSON are read by `nodes.io.camera`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from .ports import PortType, check_array, check_finite, fail

__all__ = ["Camera", "CameraRig", "CAMERA_SCHEMA", "CAMERA_RIG_SCHEMA", "CM_PER_UNIT"]


CAMERA_SCHEMA = "nodegraph.camera/1"
"""`schema` value of a camera in our JSON form (see `Camera`)."""

CAMERA_RIG_SCHEMA = "nodegraph.camera_rig/1"
"""`schema` value of a camera rig in our JSON form (see `CameraRig`)."""

CM_PER_UNIT = {"mm": 0.1, "cm": 1.0, "m": 100.0}
"""Length units a camera file may state for its translation -> centimetres per unit."""

_CAMERA_TOL = 1e-5  # max |R R^T - I| of a world-to-camera rotation
_CAMERA_KEYS = {"schema", "name", "width", "height", "fx", "fy", "cx", "cy", "k1", "k2",
                "world_to_camera", "units"}


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def _check_rigid_matrix(where: str, name: str, matrix: np.ndarray) -> None:
    """Check a float (4, 4) rigid transform: finite, orthonormal rotation with det +1, bottom [0, 0, 0, 1]."""
    check_array(where, name, matrix, 2, (4, 4))
    check_finite(where, name, matrix)
    rot = matrix[:3, :3].astype(np.float64)
    err = float(np.abs(rot @ rot.T - np.eye(3)).max())
    if err > _CAMERA_TOL:
        fail(where, f"'{name}' rotation block must be orthonormal (max |R R^T - I| <= "
                    f"{_CAMERA_TOL:g}), found {err:.2e}")
    if np.linalg.det(rot) < 0:
        fail(where, f"'{name}' rotation block must have det +1, found {np.linalg.det(rot):.3f} "
                    "(a reflection)")
    if np.abs(matrix[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        fail(where, f"'{name}' bottom row must be [0, 0, 0, 1], found {matrix[3].tolist()}")


MAX_FOCAL_IMAGE_SIZES = 1000.0
"""Largest focal length a Camera accepts, in multiples of its larger image side (a field of view
of 0.057 deg): beyond it a focal length is a unit error (mm or m read as pixels), not a lens."""


@dataclass(eq=False)
class Camera(PortType):
    """A calibrated pinhole camera with radial distortion (a static value, no frame axis).

    Convention (OpenCV's): the camera looks down +z, x to the right, y down; pixel origin
    at the top-left, x to the right, y down, pixel centres at integer coordinates (pixel
    (0, 0) covers [-0.5, 0.5]^2). A world point `X` (cm) projects as::

        [x, y, z, 1] = world_to_camera @ [X, 1]          # camera frame, cm
        a, b = x / z, y / z;  r2 = a^2 + b^2;  d = 1 + k1 r2 + k2 r2^2
        u = fx d a + cx,  v = fy d b + cy                # pixels

    JSON form (written by `to_json`, read by `from_json`)::

        {"schema": "nodegraph.camera/1", "name": "cam0", "width": 1920, "height": 1080,
         "fx": 1500.0, "fy": 1500.0, "cx": 959.5, "cy": 539.5, "k1": 0.0, "k2": 0.0,
         "world_to_camera": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]],
         "units": "cm"}

    `units` ("cm", "mm" or "m", default "cm") is the unit of the translation column in the
    file; values are converted to cm on reading, and always written in cm. `k1`, `k2` and
    `world_to_camera` may be left out (0, 0 and the identity: the camera frame is the world
    frame). Unknown keys are errors.

    Attributes:
        fx, fy: focal lengths, pixels, > 0.
        cx, cy: principal point, pixels.
        width, height: image size, pixels, > 0.
        world_to_camera: (4, 4) float64 rigid transform, `x_cam = E @ x_world`, cm.
        k1, k2: radial distortion coefficients (OpenCV's k1, k2; unitless).
        name: camera name (unique within a `CameraRig`).
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    world_to_camera: np.ndarray = field(default_factory=lambda: np.eye(4))
    k1: float = 0.0
    k2: float = 0.0
    name: str = "camera"

    def __post_init__(self) -> None:
        for key in ("fx", "fy", "cx", "cy", "k1", "k2"):  # numpy scalars -> float (JSON-able)
            value = getattr(self, key)
            if _is_number(value):
                setattr(self, key, float(value))
        for key in ("width", "height"):
            value = getattr(self, key)
            if isinstance(value, np.integer):
                setattr(self, key, int(value))
        if not isinstance(self.world_to_camera, np.ndarray) or self.world_to_camera.dtype.kind in "iuf":
            try:
                self.world_to_camera = np.asarray(self.world_to_camera, np.float64)
            except (TypeError, ValueError):
                pass  # left as given; validate() names the problem

    def validate(self, where: str = "") -> None:
        where = where or f"{self.type_name} '{self.name}'"
        if not isinstance(self.name, str) or not self.name:
            fail(where, f"'name' must be a non-empty string, found {self.name!r}")
        for key in ("width", "height"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                fail(where, f"'{key}' must be a positive integer (pixels), found {value!r}")
        for key in ("fx", "fy", "cx", "cy", "k1", "k2"):
            value = getattr(self, key)
            if not _is_number(value) or not np.isfinite(value):
                fail(where, f"'{key}' must be a finite number, found {value!r}")
        for key in ("fx", "fy"):
            if getattr(self, key) <= 0:
                fail(where, f"'{key}' must be > 0 (pixels), found {getattr(self, key)!r}")
            # a field of view under 0.06 deg (an 800 mm lens on a 36 mm-wide 4K sensor is 22x)
            if getattr(self, key) > MAX_FOCAL_IMAGE_SIZES * max(self.width, self.height):
                fail(where, f"'{key}' must be at most {MAX_FOCAL_IMAGE_SIZES:g} x the image size "
                            f"({max(self.width, self.height)} px), found {getattr(self, key)!r}")
        _check_rigid_matrix(where, "world_to_camera", self.world_to_camera)
        if self.world_to_camera.dtype != np.float64:
            fail(where, f"'world_to_camera' must be float64, found {self.world_to_camera.dtype}")

    # -- helpers ------------------------------------------------------------------------
    def intrinsic_matrix(self) -> np.ndarray:
        """Return K, (3, 3) float64, pixels: `[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def camera_to_world(self) -> np.ndarray:
        """Return the inverse of `world_to_camera`, (4, 4) float64: `x_world = M @ x_cam`, cm."""
        rot, trans = self.world_to_camera[:3, :3], self.world_to_camera[:3, 3]
        out = np.eye(4)
        out[:3, :3] = rot.T
        out[:3, 3] = -rot.T @ trans
        return out

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float, name: str = "camera") -> "Camera":
        """Return a distortion-free pinhole at the world origin looking down +z.

        Args:
            width, height: image size, pixels.
            fov_deg: horizontal field of view across the full width, degrees, in (0, 180).
            name: camera name.
        Returns:
            Camera with fx = fy = (width / 2) / tan(fov / 2), principal point at the image
            centre ((width - 1) / 2, (height - 1) / 2), identity `world_to_camera`.
        Raises:
            ValueError: for a field of view outside (0, 180) or a bad size.

        Example:
            >>> Camera.from_fov(640, 480, 90.0).intrinsic_matrix()[0].round(3).tolist()
            [320.0, 0.0, 319.5]
        """
        if not 0 < fov_deg < 180:
            raise ValueError(f"fov_deg: expected a field of view in (0, 180) degrees, found {fov_deg}")
        focal = (width / 2.0) / float(np.tan(np.radians(fov_deg) / 2.0))
        camera = cls(fx=focal, fy=focal, cx=(width - 1) / 2.0, cy=(height - 1) / 2.0,
                     width=width, height=height, name=name)
        camera.validate()
        return camera

    # -- JSON ---------------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        """Return our JSON form (see the class docstring); numbers round-trip exactly."""
        return {"schema": CAMERA_SCHEMA, "name": self.name, "width": self.width,
                "height": self.height, "fx": self.fx, "fy": self.fy, "cx": self.cx,
                "cy": self.cy, "k1": self.k1, "k2": self.k2,
                "world_to_camera": np.asarray(self.world_to_camera, np.float64).tolist(),
                "units": "cm"}

    @classmethod
    def from_json(cls, data: Any, where: str = "camera") -> "Camera":
        """Read our JSON form (see the class docstring), validated.

        Args:
            data: the parsed JSON object.
            where: prefix of error messages (e.g. the file name).
        Raises:
            ValueError: "WHERE: 'KEY' ..." for a missing, unknown or bad key.
        """
        if not isinstance(data, dict):
            fail(where, f"expected a JSON object, found {type(data).__name__}")
        if data.get("schema") != CAMERA_SCHEMA:
            fail(where, f"'schema' must be '{CAMERA_SCHEMA}', found {data.get('schema')!r}")
        unknown = sorted(set(data) - _CAMERA_KEYS)
        if unknown:
            fail(where, f"unknown key(s) {unknown}; expected keys among {sorted(_CAMERA_KEYS)}")
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
        if missing:
            fail(where, f"missing key(s) {missing}")
        units = data.get("units", "cm")
        if units not in CM_PER_UNIT:
            fail(where, f"'units' must be one of {sorted(CM_PER_UNIT)}, found {units!r}")
        for key in ("fx", "fy", "cx", "cy", "k1", "k2"):
            if key in data and not _is_number(data[key]):
                fail(where, f"'{key}' must be a number, found {data[key]!r}")
        extrinsics = np.eye(4)
        if "world_to_camera" in data:
            try:
                extrinsics = np.array(data["world_to_camera"], dtype=np.float64)
            except (TypeError, ValueError):
                fail(where, f"'world_to_camera' must be a 4x4 array of numbers, found "
                            f"{str(data['world_to_camera'])[:60]}")
            if extrinsics.shape != (4, 4):
                fail(where, f"'world_to_camera' must be 4x4, found shape {extrinsics.shape}")
            extrinsics[:3, 3] *= CM_PER_UNIT[units]
        camera = cls(fx=data["fx"], fy=data["fy"], cx=data["cx"], cy=data["cy"],
                     width=data["width"], height=data["height"], world_to_camera=extrinsics,
                     k1=data.get("k1", 0.0), k2=data.get("k2", 0.0),
                     name=data.get("name", "camera"))
        camera.validate(where)
        return camera


@dataclass(eq=False)
class CameraRig(PortType):
    """Several named calibrated cameras, stored as arrays with a leading camera axis N.

    `rig.cameras()` / `rig.camera(name_or_index)` give `Camera` values;
    `CameraRig.from_cameras([...])` builds a rig. JSON form::

        {"schema": "nodegraph.camera_rig/1", "cameras": [CAMERA, ...]}

    where each CAMERA is a camera in `Camera`'s JSON form (a file loader may also accept
    paths of camera files there, see `nodes.io.camera`).

    Attributes:
        names: N unique camera names.
        image_size: (N, 2) int64 (width, height), pixels.
        intrinsics: (N, 4) float64 (fx, fy, cx, cy), pixels.
        distortion: (N, 2) float64 (k1, k2).
        world_to_camera: (N, 4, 4) float64, `x_cam = E[n] @ x_world`, cm.
    """

    names: list[str]
    image_size: np.ndarray
    intrinsics: np.ndarray
    distortion: np.ndarray
    world_to_camera: np.ndarray

    @classmethod
    def from_cameras(cls, cameras: Sequence[Camera]) -> "CameraRig":
        """Stack cameras (in order) into a rig; names must be unique."""
        cameras = list(cameras)
        rig = cls(
            names=[c.name for c in cameras],
            image_size=np.array([[c.width, c.height] for c in cameras], np.int64).reshape(-1, 2),
            intrinsics=np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras],
                                np.float64).reshape(-1, 4),
            distortion=np.array([[c.k1, c.k2] for c in cameras], np.float64).reshape(-1, 2),
            world_to_camera=np.array([c.world_to_camera for c in cameras],
                                     np.float64).reshape(-1, 4, 4),
        )
        rig.validate()
        return rig

    @property
    def num_cameras(self) -> int:
        return len(self.names)

    def camera(self, key: int | str) -> Camera:
        """Return camera `key` (an index or a name) as a `Camera`.

        Raises:
            KeyError: unknown name (the known ones are listed). IndexError: bad index.
        """
        if isinstance(key, str):
            if key not in self.names:
                raise KeyError(f"CameraRig: unknown camera '{key}'; known: {self.names}")
            index = self.names.index(key)
        else:
            index = int(key)
            if not -len(self.names) <= index < len(self.names):
                raise IndexError(f"CameraRig: camera {index} outside 0..{len(self.names) - 1}")
        (width, height), (fx, fy, cx, cy) = self.image_size[index], self.intrinsics[index]
        return Camera(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=int(width),
                      height=int(height), world_to_camera=np.array(self.world_to_camera[index]),
                      k1=float(self.distortion[index, 0]), k2=float(self.distortion[index, 1]),
                      name=self.names[index])

    def cameras(self) -> list[Camera]:
        """Return every camera, in rig order."""
        return [self.camera(i) for i in range(len(self.names))]

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        n = len(self.names)
        if n == 0:
            fail(where, "expected at least one camera, found none")
        check_array(where, "image_size", self.image_size, 2, (n, 2), kinds="iu")
        check_array(where, "intrinsics", self.intrinsics, 2, (n, 4))
        check_array(where, "distortion", self.distortion, 2, (n, 2))
        check_array(where, "world_to_camera", self.world_to_camera, 3, (n, 4, 4))
        for key in ("image_size", "intrinsics", "distortion", "world_to_camera"):
            if getattr(self, key).shape[0] != n:
                fail(where, f"'{key}' must have {n} rows (one per name), found shape "
                            f"{getattr(self, key).shape}")
        duplicates = sorted({name for name in self.names if self.names.count(name) > 1})
        if duplicates:
            fail(where, f"camera names must be unique, found {duplicates} more than once")
        for index, name in enumerate(self.names):
            self.camera(index).validate(f"{where}: camera {index} '{name}'")

    def to_json(self) -> dict[str, Any]:
        """Return our JSON form (see the class docstring)."""
        return {"schema": CAMERA_RIG_SCHEMA, "cameras": [c.to_json() for c in self.cameras()]}

    @classmethod
    def from_json(cls, data: Any, where: str = "camera rig") -> "CameraRig":
        """Read our JSON form with every camera inline, validated.

        Raises:
            ValueError: "WHERE: camera I: ..." naming the bad camera and key.
        """
        if not isinstance(data, dict):
            fail(where, f"expected a JSON object, found {type(data).__name__}")
        if data.get("schema") != CAMERA_RIG_SCHEMA:
            fail(where, f"'schema' must be '{CAMERA_RIG_SCHEMA}', found {data.get('schema')!r}")
        if sorted(data) != ["cameras", "schema"] or not isinstance(data["cameras"], list):
            fail(where, f"expected keys 'schema' and 'cameras' (a list), found keys {sorted(data)}")
        cameras = [Camera.from_json(c, f"{where}: camera {i}") for i, c in enumerate(data["cameras"])]
        rig = cls.from_cameras(cameras) if cameras else None
        if rig is None:
            fail(where, "'cameras' must list at least one camera, found none")
        return rig
