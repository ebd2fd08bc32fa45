"""The port protocol: `PortType`, the base of every value that flows on a graph's edges, and
the registry of port types by name.

A port type is a small dataclass around numpy arrays. It knows
- whether it has a frame axis (`per_frame`), and which of its arrays carry it,
- how to slice a chunk of frames out of itself and concatenate chunks back,
- how to check itself (`validate`), fingerprint itself (sha256 of array bytes, never a
  pickle), and turn itself into plain arrays and back (`to_arrays` / `from_arrays`), which
  is how the cache stores it (an `.npz` loaded with `allow_pickle=False`).

Every subclass registers itself under its `type_name` (the class name unless set): the name
that graph files, cache entries and model files store. The built-in types live in
`nodegraph.sequences`, `nodegraph.images`, `nodegraph.face_model`, `nodegraph.cameras`,
`nodegraph.models`, `nodegraph.performance` and `nodegraph.values`; importing `nodegraph`
registers them all. The check helpers below (`check_array`, `check_finite`, `fail`,
`check_index_groups`) are shared by those modules and by third-party port types.

Conventions: positions in cm, time in frames, angles in radians, `[F, V, 3]` order,
float32 arrays unless a field says otherwise. Rigid transforms are float64 4x4 matrices
acting on column vectors.

The core never imports torch: values are numpy; nodes convert at their boundary.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from typing import Any, ClassVar, Mapping, Sequence, TypeVar

import numpy as np

__all__ = ["PortType", "port_types", "port_type_by_name", "check_array", "check_finite", "fail",
           "check_index_groups"]

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


def fail(where: str, message: str) -> None:
    """Raise ValueError("WHERE: MESSAGE")."""
    raise ValueError(f"{where}: {message}")


def check_array(where: str, name: str, value: Any, ndim: int, last: tuple[int | None, ...] = (),
                kinds: str = "f") -> np.ndarray:
    """Check an array's rank, trailing sizes and dtype kind; return it.

    Args:
        where: prefix of the error message (the value's type or the node and port).
        name: the field's name, quoted in the message.
        value: the value to check.
        ndim: the number of axes expected.
        last: expected sizes of the trailing axes (None: any size).
        kinds: accepted numpy dtype kinds ("f" float, "iu" integer, "b" bool).
    Raises:
        ValueError: "WHERE: 'NAME' must ..., found ..." naming the first mismatch.
    """
    if not isinstance(value, np.ndarray):
        fail(where, f"'{name}' must be a numpy array, found {type(value).__name__}")
    if value.ndim != ndim:
        fail(where, f"'{name}' must have {ndim} axes, found shape {value.shape}")
    for axis, size in enumerate(last, start=ndim - len(last)):
        if size is not None and value.shape[axis] != size:
            fail(where, f"'{name}' must have size {size} on axis {axis}, found shape {value.shape}")
    if value.dtype.kind not in kinds:
        fail(where, f"'{name}' must have dtype kind in '{kinds}', found {value.dtype}")
    return value


def check_finite(where: str, name: str, value: np.ndarray) -> None:
    """Raise ValueError naming the first non-finite element of a float array (others pass)."""
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
        fail(where, f"'{name}' has a non-finite value at index {tuple(int(i) for i in bad)}")


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
                fail(where, f"frame axes disagree: {counts}")

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


def check_index_groups(where: str, groups: Mapping[str, np.ndarray], count: int) -> None:
    """Check named vertex groups: 1-D integer indices inside 0..count-1."""
    for name, idx in groups.items():
        check_array(where, f"groups['{name}']", idx, 1, kinds="iu")
        if idx.size and (idx.min() < 0 or idx.max() >= count):
            fail(where, f"groups['{name}'] indexes vertices outside 0..{count - 1} "
                        f"(found {int(idx.min())}..{int(idx.max())})")
