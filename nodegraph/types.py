"""Port types: the values that flow on the edges of a graph.

Each type is a small dataclass around numpy arrays. A type knows
- whether it has a frame axis (`per_frame`), and which of its arrays carry it,
- how to slice a chunk of frames out of itself and concatenate chunks back,
- how to check itself (`validate`), fingerprint itself (sha256 of array bytes, never a
  pickle), and turn itself into plain arrays and back (`to_arrays` / `from_arrays`), which
  is how the cache stores it (an `.npz` loaded with `allow_pickle=False`).

Conventions: positions in cm, time in frames, angles in radians, `[F, V, 3]` order,
float32 arrays unless a field says otherwise. Rigid transforms are float64 4x4 matrices
acting on column vectors.

The core never imports torch: values are numpy; nodes convert at their boundary.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence, TypeVar

import numpy as np

__all__ = [
    "PortType", "MeshSequence", "RigidSequence", "ImageSequence", "Landmarks2D",
    "FlowSequence", "ParamSequence", "FaceModel", "TorchModel", "Camera", "CameraRig", "Table",
    "JsonValue", "Files", "port_types", "port_type_by_name", "COLOUR_SPACES", "srgb_to_linear",
    "linear_to_srgb", "CAMERA_SCHEMA", "CAMERA_RIG_SCHEMA", "CM_PER_UNIT",
]

T = TypeVar("T", bound="PortType")

_PORT_TYPES: dict[str, type["PortType"]] = {}


def port_types() -> dict[str, type["PortType"]]:
    """Return every port type by name (built-in and third-party subclasses)."""
    return dict(_PORT_TYPES)


def port_type_by_name(name: str) -> type["PortType"]:
    """Return the port type registered as `name`; raise KeyError naming the known ones."""
    try:
        return _PORT_TYPES[name]
    except KeyError:
        raise KeyError(f"unknown port type '{name}'; known: {sorted(_PORT_TYPES)}") from None


def _fail(where: str, message: str) -> None:
    raise ValueError(f"{where}: {message}")


def _check_array(where: str, name: str, value: Any, ndim: int, last: tuple[int | None, ...] = (),
                 kinds: str = "f") -> np.ndarray:
    """Check an array's rank, trailing sizes and dtype kind; return it."""
    if not isinstance(value, np.ndarray):
        _fail(where, f"'{name}' must be a numpy array, found {type(value).__name__}")
    if value.ndim != ndim:
        _fail(where, f"'{name}' must have {ndim} axes, found shape {value.shape}")
    for axis, size in enumerate(last, start=ndim - len(last)):
        if size is not None and value.shape[axis] != size:
            _fail(where, f"'{name}' must have size {size} on axis {axis}, found shape {value.shape}")
    if value.dtype.kind not in kinds:
        _fail(where, f"'{name}' must have dtype kind in '{kinds}', found {value.dtype}")
    return value


def _check_finite(where: str, name: str, value: np.ndarray) -> None:
    if value.dtype.kind != "f" or value.size == 0:
        return
    # A finite sum proves every element finite (inf and nan propagate through IEEE addition);
    # only a non-finite sum (a bad value, or huge finite values overflowing) needs the
    # element-wise test. The sum reads the array once and allocates nothing.
    with np.errstate(all="ignore"):
        total = np.add.reduce(value, axis=None)
    if np.isfinite(total):
        return
    if not np.isfinite(value).all():
        bad = np.argwhere(~np.isfinite(value))[0]
        _fail(where, f"'{name}' has a non-finite value at index {tuple(int(i) for i in bad)}")


@dataclass(eq=False)
class PortType:
    """Base of every port type.

    Subclasses are dataclasses whose fields are numpy arrays, dicts of name -> array,
    lists of strings, JSON-able values, or None (optional). `frame_fields` names the
    arrays whose axis 0 is the frame axis.
    """

    type_name: ClassVar[str] = "PortType"
    per_frame: ClassVar[bool] = False
    frame_fields: ClassVar[tuple[str, ...]] = ()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if "type_name" not in cls.__dict__:
            cls.type_name = cls.__name__
        _PORT_TYPES[cls.type_name] = cls

    # -- checks -------------------------------------------------------------------------
    def validate(self, where: str = "") -> None:
        """Raise ValueError (prefixed with `where`) when shapes or dtypes are inconsistent."""
        where = where or self.type_name
        if self.per_frame:
            counts = {name: getattr(self, name).shape[0] for name in self.frame_fields
                      if getattr(self, name) is not None}
            if len(set(counts.values())) > 1:
                _fail(where, f"frame axes disagree: {counts}")

    @property
    def num_frames(self) -> int:
        """Number of frames (axis 0 of the frame fields); only for per-frame types."""
        if not self.per_frame:
            raise TypeError(f"{self.type_name} has no frame axis")
        return int(getattr(self, self.frame_fields[0]).shape[0])

    # -- frame chunks -------------------------------------------------------------------
    def slice_frames(self: T, start: int, stop: int) -> T:
        """Return frames [start, stop) (indices relative to this value)."""
        if not self.per_frame:
            raise TypeError(f"{self.type_name} has no frame axis to slice")
        n = self.num_frames
        if not 0 <= start <= stop <= n:
            raise IndexError(f"{self.type_name}: frames {start}:{stop} outside 0:{n}")
        changes = {name: getattr(self, name)[start:stop] for name in self.frame_fields
                   if getattr(self, name) is not None}
        return dataclasses.replace(self, **changes)

    @classmethod
    def concat_frames(cls: type[T], parts: Sequence[T]) -> T:
        """Concatenate chunks along the frame axis; static fields are taken from the first."""
        if not cls.per_frame:
            raise TypeError(f"{cls.type_name} has no frame axis to concatenate")
        if not parts:
            raise ValueError(f"{cls.type_name}: nothing to concatenate")
        if len(parts) == 1:
            return parts[0]
        first = parts[0]
        for index, part in enumerate(parts[1:], start=1):
            for f in dataclasses.fields(cls):
                if f.name in cls.frame_fields:
                    continue
                a, b = getattr(first, f.name), getattr(part, f.name)
                if isinstance(a, np.ndarray) and (not isinstance(b, np.ndarray) or a.shape != b.shape):
                    raise ValueError(f"{cls.type_name}: chunk {index} has '{f.name}' of shape "
                                     f"{getattr(b, 'shape', None)}, chunk 0 has {a.shape}")
        changes = {}
        for name in cls.frame_fields:
            values = [getattr(p, name) for p in parts]
            if all(v is None for v in values):
                continue
            if any(v is None for v in values):
                raise ValueError(f"{cls.type_name}: '{name}' is missing in some chunks")
            changes[name] = np.concatenate(values, axis=0)
        return dataclasses.replace(first, **changes)

    @classmethod
    def merge_chunks(cls: type[T], parts: Sequence[T]) -> T:
        """Combine the whole values that chunks of a framewise node produced (e.g. the files
        each chunk wrote). Types that cannot be combined raise TypeError."""
        raise TypeError(f"{cls.type_name} values of different chunks cannot be combined")

    @classmethod
    def mergeable(cls) -> bool:
        """True when `merge_chunks` is defined for this type."""
        return cls.merge_chunks.__func__ is not PortType.merge_chunks.__func__

    # -- storage ------------------------------------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flatten into named arrays (no object arrays): the cache's on-disk form."""
        out: dict[str, np.ndarray] = {}
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            if isinstance(value, np.ndarray):
                if value.dtype == object:
                    raise TypeError(f"{self.type_name}.{f.name}: object arrays cannot be stored")
                out[f.name] = value
            elif isinstance(value, dict) and all(isinstance(v, np.ndarray) for v in value.values()):
                out[f"{f.name}/__dict__"] = np.array(sorted(value), dtype=str)
                for key, array in value.items():
                    out[f"{f.name}/{key}"] = array
            else:
                out[f"{f.name}/__json__"] = np.array(json.dumps(value, sort_keys=True))
        return out

    @classmethod
    def from_arrays(cls: type[T], arrays: Mapping[str, np.ndarray]) -> T:
        """Inverse of `to_arrays`."""
        kwargs: dict[str, Any] = {}
        for f in dataclasses.fields(cls):
            if f.name in arrays:
                kwargs[f.name] = np.asarray(arrays[f.name])
            elif f"{f.name}/__dict__" in arrays:
                keys = [str(k) for k in arrays[f"{f.name}/__dict__"].tolist()]
                kwargs[f.name] = {k: np.asarray(arrays[f"{f.name}/{k}"]) for k in keys}
            elif f"{f.name}/__json__" in arrays:
                kwargs[f.name] = json.loads(str(arrays[f"{f.name}/__json__"]))
        return cls(**kwargs)

    def fingerprint(self) -> str:
        """sha256 (hex) of the type name and every array's name, dtype, shape and bytes."""
        digest = hashlib.sha256(self.type_name.encode())
        for name, array in sorted(self.to_arrays().items()):
            array = np.ascontiguousarray(array)
            digest.update(f"|{name}|{array.dtype.str}|{array.shape}|".encode())
            digest.update(array.tobytes())
        return digest.hexdigest()

    def nbytes(self) -> int:
        """Total bytes of the arrays."""
        return int(sum(a.nbytes for a in self.to_arrays().values()))

    def readonly(self: T) -> T:
        """Mark every array read-only (cached values must not be mutated in place)."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, np.ndarray):
                value.flags.writeable = False
            elif isinstance(value, dict):
                for v in value.values():
                    if isinstance(v, np.ndarray):
                        v.flags.writeable = False
        return self


def _index_groups(where: str, groups: Mapping[str, np.ndarray], count: int) -> None:
    for name, idx in groups.items():
        _check_array(where, f"groups['{name}']", idx, 1, kinds="iu")
        if idx.size and (idx.min() < 0 or idx.max() >= count):
            _fail(where, f"groups['{name}'] indexes vertices outside 0..{count - 1} "
                         f"(found {int(idx.min())}..{int(idx.max())})")


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
        _check_array(where, "vertices", self.vertices, 3, (None, 3))
        _check_finite(where, "vertices", self.vertices)
        v = self.vertices.shape[1]
        _check_array(where, "faces", self.faces, 2, (3,), kinds="iu")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= v):
            _fail(where, f"'faces' index vertices outside 0..{v - 1}")
        if self.uv is not None:
            _check_array(where, "uv", self.uv, 2, (2,))
            if self.uv_faces is None and self.uv.shape[0] != v:
                _fail(where, f"per-vertex 'uv' must have {v} rows, found {self.uv.shape[0]}")
        if self.uv_faces is not None:
            _check_array(where, "uv_faces", self.uv_faces, 2, (3,), kinds="iu")
            if self.uv_faces.shape != self.faces.shape:
                _fail(where, f"'uv_faces' must match 'faces' {self.faces.shape}, found {self.uv_faces.shape}")
        _index_groups(where, self.groups, v)
        if not self.fps > 0:
            _fail(where, f"'fps' must be > 0, found {self.fps}")

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
        _check_array(where, "matrices", self.matrices, 3, (4, 4))
        _check_finite(where, "matrices", self.matrices)
        rot = self.matrices[:, :3, :3].astype(np.float64)
        err = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(initial=0.0)
        if err > 1e-3:
            _fail(where, f"'matrices' rotation blocks must be orthonormal (max |R R^T - I| = {err:.2e})")
        bottom = np.abs(self.matrices[:, 3] - np.array([0, 0, 0, 1])).max(initial=0.0)
        if bottom > 1e-6:
            _fail(where, "'matrices' bottom rows must be [0, 0, 0, 1]")


COLOUR_SPACES = ("linear", "srgb")
"""The colour spaces an `ImageSequence` declares (see `srgb_to_linear`)."""

_NON_COLOUR_CHANNELS = frozenset({"A", "ALPHA", "Z", "DEPTH"})


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values to linear light with the exact IEC 61966-2-1 curve.

    `c <= 0.04045: c / 12.92`, else `((c + 0.055) / 1.055) ** 2.4`. Negative values follow
    the linear segment; values above 1 follow the power segment (no clipping). Computed in
    float64.

    Args:
        values: (...) float, sRGB-encoded (1 = display white).
    Returns:
        (...) float32 linear values.

    Example:
        >>> [round(float(v), 6) for v in srgb_to_linear(np.array([0.0, 0.5, 1.0]))]
        [0.0, 0.214041, 1.0]
    """
    c = np.asarray(values, np.float64)
    out = np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)
    return out.astype(np.float32)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """Encode linear light as sRGB with the exact IEC 61966-2-1 curve (inverse of `srgb_to_linear`).

    `l <= 0.0031308: 12.92 l`, else `1.055 l ** (1 / 2.4) - 0.055`. Negative values follow
    the linear segment; values above 1 follow the power segment (no clipping). Computed in
    float64.

    Args:
        values: (...) float, linear light (1 = display white).
    Returns:
        (...) float32 sRGB-encoded values.

    Example:
        >>> linear_to_srgb(np.array([0.0, 0.214041, 1.0])).round(4).tolist()
        [0.0, 0.5, 1.0]
    """
    lin = np.asarray(values, np.float64)
    out = np.where(lin <= 0.0031308, lin * 12.92,
                   1.055 * np.maximum(lin, 0.0031308) ** (1.0 / 2.4) - 0.055)
    return out.astype(np.float32)


@dataclass(eq=False)
class ImageSequence(PortType):
    """Images over frames.

    Attributes:
        pixels: (F, H, W, C) float32 (8/16-bit integer files are scaled to [0, 1]).
        channels: C channel names, e.g. ["R", "G", "B", "A"].
        fps: frames per second.
        colour_space: how the colour channels encode light: "linear" (scene-linear, as EXR
            and other float files store it) or "srgb" (the sRGB transfer curve, as 8/16-bit
            PNG, JPEG, TIFF files and video store it). Alpha and depth channels (named A,
            Alpha, Z or Depth, also as the last part of a layer name such as "diffuse.A")
            are linear in both and never converted. `to_linear` / `to_srgb` convert.
    """

    pixels: np.ndarray
    channels: list[str] = field(default_factory=lambda: ["R", "G", "B"])
    fps: float = 30.0
    colour_space: str = "srgb"

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("pixels",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        _check_array(where, "pixels", self.pixels, 4)
        if len(self.channels) != self.pixels.shape[3]:
            _fail(where, f"{len(self.channels)} channel names for {self.pixels.shape[3]} channels")
        if self.colour_space not in COLOUR_SPACES:
            _fail(where, f"'colour_space' must be one of {list(COLOUR_SPACES)}, found "
                         f"{self.colour_space!r}")

    @classmethod
    def concat_frames(cls, parts: Sequence["ImageSequence"]) -> "ImageSequence":
        """Concatenate chunks; chunks of different colour spaces or channels are refused."""
        for index, part in enumerate(parts[1:], start=1):
            if part.colour_space != parts[0].colour_space:
                raise ValueError(f"{cls.type_name}: chunk {index} has colour_space "
                                 f"'{part.colour_space}', chunk 0 has '{parts[0].colour_space}'")
            if list(part.channels) != list(parts[0].channels):
                raise ValueError(f"{cls.type_name}: chunk {index} has channels {part.channels}, "
                                 f"chunk 0 has {parts[0].channels}")
        return super().concat_frames(parts)

    def colour_channels(self) -> list[int]:
        """Indices of the channels that carry colour (all but alpha and depth, see the class)."""
        return [i for i, name in enumerate(self.channels)
                if name.rsplit(".", 1)[-1].upper() not in _NON_COLOUR_CHANNELS]

    def to_colour_space(self, colour_space: str) -> "ImageSequence":
        """Return this sequence in `colour_space` ("linear" or "srgb"), converting colour
        channels with the exact sRGB curve; `self` when it is already there (nothing copied)."""
        if colour_space not in COLOUR_SPACES:
            raise ValueError(f"colour_space: expected one of {list(COLOUR_SPACES)}, found "
                             f"{colour_space!r}")
        if colour_space == self.colour_space:
            return self
        convert = srgb_to_linear if colour_space == "linear" else linear_to_srgb
        pixels = np.array(self.pixels, np.float32)
        idx = self.colour_channels()
        if idx:
            pixels[..., idx] = convert(pixels[..., idx])
        return dataclasses.replace(self, pixels=pixels, colour_space=colour_space)

    def to_linear(self) -> "ImageSequence":
        """Return the sequence with linear colour channels (decoded from sRGB when needed)."""
        return self.to_colour_space("linear")

    def to_srgb(self) -> "ImageSequence":
        """Return the sequence with sRGB-encoded colour channels (encoded when needed)."""
        return self.to_colour_space("srgb")


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
        _check_array(where, "points", self.points, 3, (None, 2))
        _check_array(where, "confidence", self.confidence, 2)
        if self.confidence.shape != self.points.shape[:2]:
            _fail(where, f"'confidence' must be {self.points.shape[:2]}, found {self.confidence.shape}")
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
        _check_array(where, "flow", self.flow, 4, (None, None, 2))
        _check_array(where, "valid", self.valid, 1, kinds="b")
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
        _check_array(where, "values", self.values, 2)
        if len(self.names) != self.values.shape[1]:
            _fail(where, f"{len(self.names)} names for {self.values.shape[1]} columns")


@dataclass(eq=False)
class FaceModel(PortType):
    """A linear face model: neutral + identity deltas + expression deltas.

    Attributes:
        neutral: (V, 3) float32, cm.
        faces: (T, 3) int.
        expression_deltas: (K, V, 3) float32, cm per unit weight.
        expression_names: K names (ARKit names for the ICT model).
        identity_deltas: (I, V, 3) float32, cm per unit weight (weights ~ N(0, 1)).
        groups: named vertex groups, name -> (N,) int vertex indices (e.g. "face",
            "rigid", "fitting").
        landmarks: (68,) int vertex index of each Multi-PIE 68-point landmark.
        uv, uv_faces: texture coordinates as in `MeshSequence`, or None.
    """

    neutral: np.ndarray
    faces: np.ndarray
    expression_deltas: np.ndarray
    expression_names: list[str]
    identity_deltas: np.ndarray
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int32))
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        _check_array(where, "neutral", self.neutral, 2, (3,))
        v = self.neutral.shape[0]
        _check_array(where, "expression_deltas", self.expression_deltas, 3, (v, 3))
        _check_array(where, "identity_deltas", self.identity_deltas, 3, (v, 3))
        if len(self.expression_names) != self.expression_deltas.shape[0]:
            _fail(where, f"{len(self.expression_names)} expression names for "
                         f"{self.expression_deltas.shape[0]} shapes")
        _index_groups(where, self.groups, v)

    def evaluate(self, expression: Any, identity: Any = None) -> Any:
        """Return vertices `neutral + identity @ identity_deltas + expression @ expression_deltas`.

        Works on numpy arrays or, differentiably, on torch tensors (the deltas are moved to
        the tensor's device and dtype).

        Args:
            expression: (F, K) weights, or (K,).
            identity: (I,) weights, or (F, I), or None for the generic neutral.
        Returns:
            (F, V, 3) vertices in cm (or (V, 3) for a 1-D `expression`), same library as
            `expression`.
        """
        k, v = self.expression_deltas.shape[:2]
        if type(expression).__module__.startswith("torch"):
            import torch

            dev, dt = expression.device, expression.dtype
            exp_d = torch.as_tensor(self.expression_deltas, device=dev, dtype=dt).reshape(k, -1)
            out = torch.as_tensor(self.neutral, device=dev, dtype=dt).reshape(-1) + expression @ exp_d
            if identity is not None:
                n = self.identity_deltas.shape[0]
                id_d = torch.as_tensor(self.identity_deltas, device=dev, dtype=dt).reshape(n, -1)
                out = out + identity.to(dev, dt) @ id_d
            return out.reshape(*out.shape[:-1], v, 3)
        expression = np.asarray(expression, dtype=np.float32)
        out = self.neutral.reshape(-1) + expression @ self.expression_deltas.reshape(k, -1)
        if identity is not None:
            n = self.identity_deltas.shape[0]
            out = out + np.asarray(identity, np.float32) @ self.identity_deltas.reshape(n, -1)
        return out.reshape(*out.shape[:-1], v, 3).astype(np.float32)


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
    _check_array(where, name, matrix, 2, (4, 4))
    _check_finite(where, name, matrix)
    rot = matrix[:3, :3].astype(np.float64)
    err = float(np.abs(rot @ rot.T - np.eye(3)).max())
    if err > _CAMERA_TOL:
        _fail(where, f"'{name}' rotation block must be orthonormal (max |R R^T - I| <= "
                     f"{_CAMERA_TOL:g}), found {err:.2e}")
    if np.linalg.det(rot) < 0:
        _fail(where, f"'{name}' rotation block must have det +1, found {np.linalg.det(rot):.3f} "
                     "(a reflection)")
    if np.abs(matrix[3] - np.array([0.0, 0.0, 0.0, 1.0])).max() > 1e-9:
        _fail(where, f"'{name}' bottom row must be [0, 0, 0, 1], found {matrix[3].tolist()}")


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
            _fail(where, f"'name' must be a non-empty string, found {self.name!r}")
        for key in ("width", "height"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
                _fail(where, f"'{key}' must be a positive integer (pixels), found {value!r}")
        for key in ("fx", "fy", "cx", "cy", "k1", "k2"):
            value = getattr(self, key)
            if not _is_number(value) or not np.isfinite(value):
                _fail(where, f"'{key}' must be a finite number, found {value!r}")
        for key in ("fx", "fy"):
            if getattr(self, key) <= 0:
                _fail(where, f"'{key}' must be > 0 (pixels), found {getattr(self, key)!r}")
        _check_rigid_matrix(where, "world_to_camera", self.world_to_camera)
        if self.world_to_camera.dtype != np.float64:
            _fail(where, f"'world_to_camera' must be float64, found {self.world_to_camera.dtype}")

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
            _fail(where, f"expected a JSON object, found {type(data).__name__}")
        if data.get("schema") != CAMERA_SCHEMA:
            _fail(where, f"'schema' must be '{CAMERA_SCHEMA}', found {data.get('schema')!r}")
        unknown = sorted(set(data) - _CAMERA_KEYS)
        if unknown:
            _fail(where, f"unknown key(s) {unknown}; expected keys among {sorted(_CAMERA_KEYS)}")
        missing = [k for k in ("width", "height", "fx", "fy", "cx", "cy") if k not in data]
        if missing:
            _fail(where, f"missing key(s) {missing}")
        units = data.get("units", "cm")
        if units not in CM_PER_UNIT:
            _fail(where, f"'units' must be one of {sorted(CM_PER_UNIT)}, found {units!r}")
        for key in ("fx", "fy", "cx", "cy", "k1", "k2"):
            if key in data and not _is_number(data[key]):
                _fail(where, f"'{key}' must be a number, found {data[key]!r}")
        extrinsics = np.eye(4)
        if "world_to_camera" in data:
            try:
                extrinsics = np.array(data["world_to_camera"], dtype=np.float64)
            except (TypeError, ValueError):
                _fail(where, f"'world_to_camera' must be a 4x4 array of numbers, found "
                             f"{str(data['world_to_camera'])[:60]}")
            if extrinsics.shape != (4, 4):
                _fail(where, f"'world_to_camera' must be 4x4, found shape {extrinsics.shape}")
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
            _fail(where, "expected at least one camera, found none")
        _check_array(where, "image_size", self.image_size, 2, (n, 2), kinds="iu")
        _check_array(where, "intrinsics", self.intrinsics, 2, (n, 4))
        _check_array(where, "distortion", self.distortion, 2, (n, 2))
        _check_array(where, "world_to_camera", self.world_to_camera, 3, (n, 4, 4))
        for key in ("image_size", "intrinsics", "distortion", "world_to_camera"):
            if getattr(self, key).shape[0] != n:
                _fail(where, f"'{key}' must have {n} rows (one per name), found shape "
                             f"{getattr(self, key).shape}")
        duplicates = sorted({name for name in self.names if self.names.count(name) > 1})
        if duplicates:
            _fail(where, f"camera names must be unique, found {duplicates} more than once")
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
            _fail(where, f"expected a JSON object, found {type(data).__name__}")
        if data.get("schema") != CAMERA_RIG_SCHEMA:
            _fail(where, f"'schema' must be '{CAMERA_RIG_SCHEMA}', found {data.get('schema')!r}")
        if sorted(data) != ["cameras", "schema"] or not isinstance(data["cameras"], list):
            _fail(where, f"expected keys 'schema' and 'cameras' (a list), found keys {sorted(data)}")
        cameras = [Camera.from_json(c, f"{where}: camera {i}") for i, c in enumerate(data["cameras"])]
        rig = cls.from_cameras(cameras) if cameras else None
        if rig is None:
            _fail(where, "'cameras' must list at least one camera, found none")
        return rig


@dataclass(eq=False)
class TorchModel(PortType):
    """A trained network as plain data: architecture name, JSON config, weights.

    The module is rebuilt by `build()` through the architecture registry of
    `nodegraph.models` (a builder `(config) -> torch.nn.Module` registered under the
    architecture name), then the weights are loaded. Stored (cache, `save`) as an npz of
    plain arrays: no pickle anywhere. The fingerprint covers architecture, config (canonical
    JSON, sorted keys), weights and normalization, independent of dict insertion order.

    Attributes:
        architecture: registered builder name (e.g. "dynamics.MLP").
        config: JSON-able builder arguments.
        state: parameter/buffer name -> array (a torch `state_dict` as numpy, dtypes kept).
        normalization: name -> array the network's user applies around it (e.g. "input_mean",
            "input_std" (D,) float32); empty when none.
    """

    architecture: str
    config: dict[str, Any]
    state: dict[str, np.ndarray]
    normalization: dict[str, np.ndarray] = field(default_factory=dict)

    def validate(self, where: str = "") -> None:
        where = where or f"{self.type_name} '{self.architecture}'"
        if not isinstance(self.architecture, str) or not self.architecture:
            _fail(where, f"'architecture' must be a non-empty string, found {self.architecture!r}")
        if not isinstance(self.config, dict):
            _fail(where, f"'config' must be a JSON object (dict), found {type(self.config).__name__}")
        try:
            json.dumps(self.config, allow_nan=False)
        except (TypeError, ValueError) as err:
            _fail(where, f"'config' must be JSON-able, found {err}")
        for group in ("state", "normalization"):
            for key, value in getattr(self, group).items():
                if not isinstance(value, np.ndarray) or value.dtype.kind not in "biuf":
                    _fail(where, f"'{group}['{key}']' must be a numeric numpy array, found "
                                 f"{getattr(value, 'dtype', type(value).__name__)}")
        for key, value in self.normalization.items():  # weights may hold inf (e.g. masks)
            _check_finite(where, f"normalization['{key}']", value)

    @classmethod
    def from_module(cls, architecture: str, config: Mapping[str, Any], module: Any,
                    normalization: Mapping[str, np.ndarray] | None = None) -> "TorchModel":
        """Capture a torch module's `state_dict` as numpy arrays (copies, dtypes preserved).

        Args:
            architecture: the registered builder name that rebuilds `module` from `config`.
            config: JSON-able builder arguments.
            module: a `torch.nn.Module` (any device).
            normalization: optional name -> array (e.g. input mean/std).
        Raises:
            TypeError: for a tensor dtype numpy cannot hold (e.g. bfloat16), naming the key.
        """
        state = {}
        for key, tensor in module.state_dict().items():
            try:
                state[key] = tensor.detach().cpu().numpy().copy()
            except TypeError as err:
                raise TypeError(f"TorchModel '{architecture}': state '{key}' has dtype "
                                f"{tensor.dtype}, which numpy cannot hold ({err}); convert the "
                                "module to float32/float16/float64 first") from err
        model = cls(architecture=architecture, config=json.loads(json.dumps(dict(config))),
                    state=state,
                    normalization={k: np.array(v) for k, v in (normalization or {}).items()})
        model.validate()
        return model

    def build(self, device: str = "cpu") -> Any:
        """Construct the module through the architecture registry and load the weights.

        Returns:
            the `torch.nn.Module` on `device`, in eval mode.
        Raises:
            KeyError: unknown architecture (the known ones are listed).
            ValueError: state keys, shapes or dtypes that do not match the module the
                config builds.
        """
        from .models import build_model

        return build_model(self, device=device)

    def save(self, path: str | Any) -> None:
        """Write the model as an npz of plain arrays (atomically, no pickle); see `load`."""
        from .models import save_model

        save_model(self, path)

    @classmethod
    def load(cls, path: str | Any) -> "TorchModel":
        """Read a model written by `save` (loaded with `allow_pickle=False`)."""
        from .models import load_model

        return load_model(path)


@dataclass(eq=False)
class Table(PortType):
    """A small table for reports.

    Attributes:
        columns: column names.
        rows: rows of JSON-able cells (numbers, strings).
    """

    columns: list[str]
    rows: list[list[Any]]

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        for index, row in enumerate(self.rows):
            if len(row) != len(self.columns):
                _fail(where, f"row {index} has {len(row)} cells for {len(self.columns)} columns")

    def column(self, name: str) -> list[Any]:
        index = self.columns.index(name)
        return [row[index] for row in self.rows]

    def format(self) -> str:
        """Render as aligned plain text."""
        def cell(x: Any) -> str:
            return f"{x:.4g}" if isinstance(x, float) else str(x)
        text = [self.columns] + [[cell(x) for x in row] for row in self.rows]
        widths = [max(len(r[i]) for r in text) for i in range(len(self.columns))]
        lines = ["  ".join(c.ljust(w) for c, w in zip(r, widths)) for r in text]
        lines.insert(1, "  ".join("-" * w for w in widths))
        return "\n".join(lines)


@dataclass(eq=False)
class JsonValue(PortType):
    """Any JSON-able value (scalars, dicts of numbers, small reports)."""

    value: Any


@dataclass(eq=False)
class Files(PortType):
    """Files a node wrote.

    Attributes:
        paths: written paths, as given (relative paths stay relative).
        sha256: hex digest of each file's bytes.
    """

    paths: list[str]
    sha256: list[str]

    @classmethod
    def merge_chunks(cls, parts: Sequence["Files"]) -> "Files":
        return cls([p for part in parts for p in part.paths], [h for part in parts for h in part.sha256])
