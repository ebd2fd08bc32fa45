"""Rigid transforms and parameter curves over frames, as JSON or NPZ files.

Rigid sequences (`RigidSequence`, float64 (F, 4, 4), skull-to-world: `x_world = M[f] @ x_skull`):

- JSON: `{"convention": "skull_to_world", "matrices": [[[4 x 4]], ...]}`;
- NPZ: `matrices` (or `rigid`) (F, 4, 4).

Parameter sequences (`ParamSequence`, float32 (F, K) with K names):

- JSON: `{"names": [...], "values": [[K values], ...]}`;
- NPZ: `values` (F, K) and `names` (K,) strings.

JSON numbers are written with Python's shortest round-trip repr, so saved values load back
exactly. NPZ chunks read only their rows; JSON files are parsed whole and sliced.
"""

from __future__ import annotations

import json
import os
import zipfile
import zlib
from pathlib import Path
from typing import Any, Callable

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Files, In, InputError, Node, NodeParams, Out, Param,
                       ParamSequence, RigidSequence)
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic

from ._files import (check_frame_range, format_of, frame_where, npz_keys, npz_shape, read_npz_array,
                     read_npz_rows)
from .mesh_frame import MAX_COORDINATE_CM

__all__ = [
    "CONVENTION", "load_rigid_sequence", "save_rigid_sequence", "load_param_sequence",
    "save_param_sequence", "sequence_frame_count", "LoadRigidSequence", "SaveRigidSequence",
    "LoadParamSequence", "SaveParamSequence",
]

CONVENTION = "skull_to_world"
"""The only matrix convention written and accepted: `x_world = M[f] @ [x_skull, 1]`."""

SEQUENCE_FORMATS = {".json": "json", ".npz": "npz"}
_RIGID_KEYS = ("matrices", "rigid")
_ORTHO_TOL = 1e-3


def _unreadable(path: str, what: str, err: Exception) -> InputError:
    return InputError("path", f"file '{path}': expected a readable {what}, found an unreadable or "
                              f"truncated file ({type(err).__name__}: {err})")


def _read_json(path: str, what: str) -> dict[str, Any]:
    if not os.path.isfile(path):
        raise InputError("path", f"file '{path}': expected a {what}, found it missing")
    try:
        with open(path, encoding="utf-8") as fh:
            data = json.load(fh)
    except (OSError, ValueError) as err:
        raise _unreadable(path, what, err) from err
    if not isinstance(data, dict):
        raise InputError("path", f"file '{path}': expected a JSON object, found {type(data).__name__}")
    return data


def _json_rows(data: dict[str, Any], key: str, path: str) -> list:
    rows = data[key]
    if not isinstance(rows, list):
        raise InputError("path", f"file '{path}': expected '{key}' to be a list over frames, found "
                                 f"{type(rows).__name__}")
    return rows


def _frame_array(rows: list, frames: range, path: str, key: str, tail: tuple[int, ...],
                 dtype: type) -> np.ndarray:
    """Rows `frames` of a JSON list of per-frame values -> array (len(frames), *tail).

    Errors name the first bad frame.
    """
    rows = rows[frames.start:frames.stop]
    for frame, row in zip(frames, rows):
        try:
            value = np.asarray(row, dtype=np.float64)
        except (ValueError, TypeError) as err:
            raise InputError("path", f"{frame_where(frame, path)}: expected '{key}' numbers of shape "
                                     f"{tail}, found {str(row)[:60]}") from err
        if value.shape != tail:
            raise InputError("path", f"{frame_where(frame, path)}: expected '{key}' of shape {tail}, "
                                     f"found {value.shape}")
    return np.asarray(rows, dtype=np.float64).reshape(len(rows), *tail).astype(dtype)


def _check_finite(values: np.ndarray, frames: range, path: str) -> None:
    bad = ~np.isfinite(values.reshape(len(values), -1)).all(axis=1)
    if bad.any():
        raise InputError("path", f"{frame_where(frames[int(np.argmax(bad))], path)}: expected finite "
                                 "values, found NaN/inf")


def _npz_member(path: str, keys: tuple[str, ...], what: str) -> str:
    if not os.path.isfile(path):
        raise InputError("path", f"file '{path}': expected a {what}, found it missing")
    try:
        present = npz_keys(path)
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        raise _unreadable(path, what, err) from err
    for key in keys:
        if key in present:
            return key
    raise InputError("path", f"file '{path}': expected an array {' or '.join(map(repr, keys))}, "
                             f"found keys {sorted(present)}")


def _npz_rows(path: str, key: str, frames: range, tail: tuple[int, ...], what: str) -> np.ndarray:
    try:
        shape, _ = npz_shape(path, key)
        if tuple(shape[1:]) != tail or len(shape) != len(tail) + 1:
            raise InputError("path", f"file '{path}': expected '{key}' of shape (F, "
                                     f"{', '.join(map(str, tail))}), found {tuple(shape)}")
        check_frame_range(frames, shape[0], path)
        return read_npz_rows(path, key, frames.start, frames.stop) if len(frames) else \
            np.zeros((0, *tail))
    except InputError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        raise _unreadable(path, what, err) from err


def _write_json(path: str, data: dict[str, Any]) -> None:
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        json.dump(data, fh, allow_nan=False)
        fh.write("\n")




# -- rigid ----------------------------------------------------------------------------------

def _check_rigid(matrices: np.ndarray, frames: range, path: str) -> None:
    _check_finite(matrices, frames, path)
    rot = matrices[:, :3, :3]
    ortho = np.abs(rot @ np.swapaxes(rot, 1, 2) - np.eye(3)).max(axis=(1, 2), initial=0.0)
    bottom = np.abs(matrices[:, 3] - np.array([0.0, 0.0, 0.0, 1.0])).max(axis=1, initial=0.0)
    bad = (ortho > _ORTHO_TOL) | (bottom > 1e-6) | (np.linalg.det(rot) < 0)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError("path", f"{frame_where(frames[i], path)}: expected a rigid matrix (rotation "
                                 f"block orthonormal with det +1, bottom row [0, 0, 0, 1]), found "
                                 f"max |R R^T - I| = {ortho[i]:.2e}, det R = "
                                 f"{np.linalg.det(rot[i]):.3f}, bottom row {matrices[i, 3].tolist()}")
    far = np.abs(matrices[:, :3, 3]).max(axis=1, initial=0.0) > MAX_COORDINATE_CM
    if far.any():
        i = int(np.argmax(far))
        raise InputError("path", f"{frame_where(frames[i], path)}: expected a translation within "
                                 f"+-{MAX_COORDINATE_CM:g} cm, found {matrices[i, :3, 3].tolist()} "
                                 "(a unit or export error?)")


def load_rigid_sequence(path: str, frames: range | None = None) -> RigidSequence:
    """Read skull-to-world matrices from JSON or NPZ.

    Args:
        path: .json or .npz file (see the module docstring).
        frames: frames to read (0-based); None = all.
    Returns:
        RigidSequence with float64 (len(frames), 4, 4) matrices.
    Raises:
        InputError: naming file (and frame): missing/unreadable file, missing key, another
            convention, wrong shape, non-finite or non-rigid matrix.
    """
    fmt = format_of(path, SEQUENCE_FORMATS)
    what = "rigid sequence"
    if fmt == "json":
        data = _read_json(path, what)
        convention = data.get("convention", CONVENTION)
        if convention != CONVENTION:
            raise InputError("path", f"file '{path}': expected convention '{CONVENTION}', found "
                                     f"'{convention}' (invert the matrices to convert)")
        if "matrices" not in data:
            raise InputError("path", f"file '{path}': expected a key 'matrices', found keys "
                                     f"{sorted(data)}")
        rows = _json_rows(data, "matrices", path)
        frames = range(len(rows)) if frames is None else frames
        check_frame_range(frames, len(rows), path)
        matrices = _frame_array(rows, frames, path, "matrices", (4, 4), np.float64)
    else:
        key = _npz_member(path, _RIGID_KEYS, what)
        if frames is None:
            frames = range(sequence_frame_count(path, key))
        matrices = _npz_rows(path, key, frames, (4, 4), what).astype(np.float64)
    _check_rigid(matrices, frames, path)
    return RigidSequence(matrices=matrices)


def save_rigid_sequence(path: str, rigid: RigidSequence) -> None:
    """Write skull-to-world matrices as JSON or NPZ (`matrices`), atomically."""
    fmt = format_of(path, SEQUENCE_FORMATS)
    matrices = np.asarray(rigid.matrices, np.float64)
    if fmt == "json":
        _write_json(path, {"convention": CONVENTION, "matrices": matrices.tolist()})
    else:
        write_npz_atomic(path, {"matrices": matrices})


# -- params ---------------------------------------------------------------------------------

def _names(names: Any, count: int, path: str) -> list[str]:
    if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
        raise InputError("path", f"file '{path}': expected 'names' to be a list of strings, found "
                                 f"{str(names)[:60]}")
    if count >= 0 and len(names) != count:
        raise InputError("path", f"file '{path}': expected {count} names (one per column of "
                                 f"'values'), found {len(names)}")
    return names


def load_param_sequence(path: str, frames: range | None = None) -> ParamSequence:
    """Read named parameter curves from JSON or NPZ.

    Args:
        path: .json or .npz file (see the module docstring).
        frames: frames to read (0-based); None = all.
    Returns:
        ParamSequence with float32 (len(frames), K) values and K names.
    Raises:
        InputError: naming file (and frame): missing/unreadable file, missing key, rows of
            different lengths, names not matching the columns, non-finite values.
    """
    fmt = format_of(path, SEQUENCE_FORMATS)
    what = "parameter sequence"
    if fmt == "json":
        data = _read_json(path, what)
        missing = [k for k in ("names", "values") if k not in data]
        if missing:
            raise InputError("path", f"file '{path}': expected keys 'names' and 'values', found "
                                     f"keys {sorted(data)}")
        rows = _json_rows(data, "values", path)
        frames = range(len(rows)) if frames is None else frames
        check_frame_range(frames, len(rows), path)
        first_row = rows[0] if rows else []
        names = _names(data["names"], len(first_row) if isinstance(first_row, list) else -1, path)
        values = _frame_array(rows, frames, path, "values", (len(names),), np.float32)
    else:
        _npz_member(path, ("values",), what)
        try:
            names = [str(n) for n in read_npz_array(path, "names").tolist()]
            shape, _ = npz_shape(path, "values")
        except KeyError as err:
            raise InputError("path", f"file '{path}': expected arrays 'values' and 'names', found "
                                     f"keys {sorted(npz_keys(path))}") from err
        except (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as err:
            raise _unreadable(path, what, err) from err
        if len(shape) == 2:
            names = _names(names, shape[1], path)
        frames = range(shape[0]) if frames is None else frames
        values = _npz_rows(path, "values", frames, (len(names),), what).astype(np.float32)
    _check_finite(values, frames, path)
    return ParamSequence(values=values, names=list(names))


def save_param_sequence(path: str, params: ParamSequence) -> None:
    """Write named parameter curves as JSON or NPZ (`values`, `names`), atomically."""
    fmt = format_of(path, SEQUENCE_FORMATS)
    values = np.asarray(params.values, np.float32)
    if fmt == "json":
        _write_json(path, {"names": list(params.names),
                           "values": values.astype(np.float64).tolist()})
    else:
        write_npz_atomic(path, {"values": values, "names": np.asarray(list(params.names), dtype=str)})


def sequence_frame_count(path: str, npz_key: str | None = None) -> int:
    """Frames in a rigid or parameter sequence file (0 when missing or unreadable)."""
    fmt = format_of(path, SEQUENCE_FORMATS)
    if not os.path.isfile(path):
        return 0
    try:
        if fmt == "json":
            with open(path, encoding="utf-8") as fh:
                data = json.load(fh)
            rows = data.get("matrices", data.get("values")) if isinstance(data, dict) else None
            return len(rows) if isinstance(rows, list) else 0
        keys = npz_keys(path)
        key = npz_key or next((k for k in (*_RIGID_KEYS, "values") if k in keys), None)
        return int(npz_shape(path, key)[0][0]) if key else 0
    except (OSError, ValueError, KeyError, IndexError, zipfile.BadZipFile):
        return 0


# -- nodes ----------------------------------------------------------------------------------

class _LoadParams(NodeParams):
    path: str = Param(..., input_file=True, description="A .json or .npz file.")


class _SaveParams(NodeParams):
    path: str = Param(..., output_file=True, description="Destination .json or .npz file.")

    @field_validator("path")
    @classmethod
    def _json_or_npz(cls, value: str) -> str:
        return check_output_suffix(value, tuple(SEQUENCE_FORMATS))


class _SequenceLoader(Node):
    """What the rigid and parameter loaders share: one input file, its frame count, chunked reads.

    A subclass sets `load` (path, frames -> sequence) and declares its output port and `run`.
    """

    kind = FRAMEWISE
    Params = _LoadParams
    load: Callable[[str, range | None], Any]

    def frame_count(self) -> int | None:
        count = sequence_frame_count(self.params.path)
        if count == 0:  # missing or unreadable: reading frame 0 raises the error naming the file
            self.load(self.params.path, range(0, 1))
        return count

    def input_files(self) -> list[Path]:
        return [Path(self.params.path)] if os.path.isfile(self.params.path) else []


class _SequenceSaver(Node):
    """What the rigid and parameter savers share: one output file, written whole."""

    kind = SEQUENCE
    writes_files = True
    Params = _SaveParams

    files = Out(Files, doc="The written file and its sha256.")


class LoadRigidSequence(_SequenceLoader):
    """Read skull-to-world rigid transforms (JSON or NPZ)."""

    type_name = "io.LoadRigidSequence"
    version = 1
    load = staticmethod(load_rigid_sequence)

    rigid = Out(RigidSequence, doc="Skull-to-world matrices (F, 4, 4) float64, cm.")

    def run(self) -> dict[str, RigidSequence]:
        return {"rigid": self.load(self.params.path, self.frames)}


class SaveRigidSequence(_SequenceSaver):
    """Write skull-to-world rigid transforms as JSON or NPZ."""

    type_name = "io.SaveRigidSequence"
    version = 1

    rigid = In(RigidSequence, doc="Skull-to-world matrices to write.")

    def run(self, rigid: RigidSequence) -> dict[str, Files]:
        save_rigid_sequence(self.params.path, rigid)
        return {"files": files_value([self.params.path])}


class LoadParamSequence(_SequenceLoader):
    """Read named parameter curves (JSON or NPZ)."""

    type_name = "io.LoadParamSequence"
    version = 2
    port_renames = {1: {"params": "sequence"}}  # v1's port name shadowed Node.params
    load = staticmethod(load_param_sequence)

    sequence = Out(ParamSequence, doc="Values (F, K) float32 with K names.")

    def run(self) -> dict[str, ParamSequence]:
        return {"sequence": self.load(self.params.path, self.frames)}


class SaveParamSequence(_SequenceSaver):
    """Write named parameter curves as JSON or NPZ."""

    type_name = "io.SaveParamSequence"
    version = 2
    port_renames = {1: {"params": "sequence"}}  # v1's port name shadowed Node.params

    sequence = In(ParamSequence, doc="Parameter curves to write.")

    def run(self, sequence: ParamSequence) -> dict[str, Files]:
        save_param_sequence(self.params.path, sequence)
        return {"files": files_value([self.params.path])}
