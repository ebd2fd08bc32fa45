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
    "FlowSequence", "ParamSequence", "FaceModel", "TorchModel", "Table", "JsonValue",
    "Files", "port_types", "port_type_by_name",
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
    if value.dtype.kind == "f" and not np.isfinite(value).all():
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


@dataclass(eq=False)
class ImageSequence(PortType):
    """Images over frames.

    Attributes:
        pixels: (F, H, W, C) float32, linear or display values as loaded (8/16-bit integer
            files are scaled to [0, 1]).
        channels: C channel names, e.g. ["R", "G", "B", "A"].
        fps: frames per second.
    """

    pixels: np.ndarray
    channels: list[str] = field(default_factory=lambda: ["R", "G", "B"])
    fps: float = 30.0

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("pixels",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        _check_array(where, "pixels", self.pixels, 4)
        if len(self.channels) != self.pixels.shape[3]:
            _fail(where, f"{len(self.channels)} channel names for {self.pixels.shape[3]} channels")


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


@dataclass(eq=False)
class TorchModel(PortType):
    """A trained network as plain data: architecture name, JSON config, weights.

    Attributes:
        architecture: name the producing module knows how to build (e.g. "dynamics.MLP").
        config: JSON-able constructor arguments.
        state: parameter name -> array (a torch `state_dict` as numpy).
    """

    architecture: str
    config: dict[str, Any]
    state: dict[str, np.ndarray]


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
