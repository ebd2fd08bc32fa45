"""Mesh sequences on disk: numbered OBJ/PLY files, NPZ, and USD (UsdGeom.Mesh).

Formats, by extension:

- numbered `face.%04d.obj` / `face.####.ply` / `face.{frame:04d}.obj`: one file per frame;
  run frame `f` is file number `first_frame + f`. PLY goes through trimesh (vertex order kept,
  per-vertex uv as `s`, `t`). OBJ has its own small reader and writer, because trimesh's OBJ
  loader either reorders and splits vertices at uv seams or collapses face-varying uv, and a
  MeshSequence needs the file's vertex order and its uv seams. Polygons are fan-triangulated.
  Vertex groups: read from `g` lines (a group's vertices are the corners of its faces) and
  written as `g` lines (a face goes in every group holding its three corners) plus one exact
  `#vg <name> <1-based indices>` comment line per group, which the reader prefers (so a group
  that is not a union of faces, or a single vertex, round-trips); PLY files carry no groups.
- `.npz`: `vertices (F, V, 3)`, `faces`, optional `uv`, `uv_faces`, `groups/<name>`, `fps`.
  A chunk reads only its rows (memory-mapped when stored uncompressed, as the saver does).
- `.usd` / `.usda` / `.usdc`: a UsdGeom.Mesh with time-sampled `points` (read and written by
  `nodes.io.usd`, see there).

Every load error names the file and the run frame.
"""

from __future__ import annotations

import os
import re
import zipfile
import zlib
from pathlib import Path

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Files, In, InputError, MeshSequence, Node, NodeParams,
                       Out, Param)

from nodegraph.files import atomic_path, files_value

from ._files import (check_frame_range, check_no_missing_files, expand_frame_pattern, find_frame_numbers, format_of,
                     frame_token, frame_where, npz_keys, npz_shape, pattern_files, read_npz_array, read_npz_rows)
from .mesh_frame import MAX_COORDINATE_CM, MeshFrame, check_frame, check_magnitude, check_mesh_file, fan_triangulate
from .usd import USD_MODULES, load_usd_mesh, save_usd_mesh, usd_mesh_frame_count

__all__ = [
    "read_obj", "write_obj", "read_ply", "write_ply",
    "mesh_frame_count", "load_mesh_sequence", "save_mesh_sequence", "LoadMeshSequence",
    "SaveMeshSequence", "SaveMeshFrames",
]

MESH_FORMATS = {".obj": "obj", ".ply": "ply", ".npz": "npz", ".usd": "usd", ".usda": "usd",
                ".usdc": "usd"}
_PER_FRAME_FORMATS = ("obj", "ply")


# -- OBJ -----------------------------------------------------------------------------------

_OBJ_V = re.compile(r"^v[ \t]+(\S+)[ \t]+(\S+)[ \t]+(\S+)", re.M)
_OBJ_VT = re.compile(r"^vt[ \t]+(\S+)[ \t]+(\S+)", re.M)


def _parse_numbers(tokens: list, dtype: type) -> np.ndarray:
    """Parse number tokens (strings, or tuples of strings) in one C pass."""
    if tokens and isinstance(tokens[0], tuple):
        tokens = [t for row in tokens for t in row]
    text = " ".join(tokens)
    values = np.array(text.split(), dtype=dtype) if dtype is np.int64 else \
        np.fromstring(text, dtype=dtype, sep=" ")
    if values.size != len(tokens):
        raise ValueError(f"expected {len(tokens)} numbers, found {values.size} parseable ones")
    return values


def _record_numbers(rows: list[str], width: int, regex: re.Pattern, text: str) -> np.ndarray:
    """(N, width) float64 from OBJ record bodies; rows with extra values (w, colours) keep
    their first `width` values (slower regex path)."""
    values = np.fromstring(" ".join(rows), dtype=np.float64, sep=" ") if rows else np.zeros(0)
    if values.size == width * len(rows):
        return values.reshape(-1, width)
    return _parse_numbers(regex.findall(text), np.float64).reshape(-1, width)


def _obj_indices(values: np.ndarray, count: int) -> np.ndarray:
    """OBJ 1-based (or negative, relative to the end) indices -> 0-based."""
    return np.where(values < 0, values + count, values - 1)


def read_obj(path: str | os.PathLike) -> MeshFrame:
    """Read an OBJ file: `v`, `vt` and `f` records (all groups/objects as one mesh).

    Vertex order is the file's. When every face corner uses the same index for `v` and `vt`
    and there are as many `vt` as `v`, uv is per vertex; otherwise it is face-varying
    (`uv_faces`). Normals and materials are ignored. Vertex groups: `#vg name i j ...` lines
    (1-based, written by `write_obj`) when present, else the corners of the faces under each
    `g name [name ...]` line (`g default` and a bare `g` are no group). Negative indices are
    taken relative to the end of the file's vertex list.

    Args:
        path: the .obj file.
    Returns:
        MeshFrame (vertices in the file's units, taken as cm).
    Raises:
        ValueError: malformed records or indices out of range.
    """
    text = Path(path).read_text(encoding="utf-8", errors="strict").replace("\t", " ")
    records: dict[str, list[str]] = {"v": [], "vt": [], "f": []}
    face_sets: list[int] = []  # per `f` record: index into group_sets
    group_sets: dict[tuple[str, ...], int] = {(): 0}
    current = 0
    exact: list[str] = []
    for line in text.splitlines():
        key, _, rest = line.partition(" ")
        if key in records:
            records[key].append(rest)
            if key == "f":
                face_sets.append(current)
        elif key == "g":
            names = tuple(sorted(set(rest.split()) - {"default"}))
            current = group_sets.setdefault(names, len(group_sets))
        elif key == "#vg":
            exact.append(rest)
    vertices = _record_numbers(records["v"], 3, _OBJ_V, text).astype(np.float32)
    uv = _record_numbers(records["vt"], 2, _OBJ_VT, text).astype(np.float32)
    lines = [line.strip() for line in records["f"]]
    nv = len(vertices)
    if not lines:
        return MeshFrame(vertices, np.zeros((0, 3), np.int32), uv if len(uv) == nv and nv else None,
                         None, _obj_groups(path, exact, group_sets, np.zeros(0, np.int64), np.zeros(0, np.int64),
                                           np.zeros(0, np.int64), nv))
    counts = np.fromiter(map(len, map(str.split, lines)), dtype=np.int64, count=len(lines))
    corners = " ".join(lines).split()
    fields = corners[0].count("/") + 1
    flat = " ".join(corners).replace("//", "/0/").replace("/", " ").split()
    if len(flat) != fields * len(corners):
        raise ValueError(f"'{path}': face corners mix formats (expected every corner like "
                         f"'{corners[0]}')")
    ints = _parse_numbers(flat, np.int64).reshape(len(corners), fields)
    tri = fan_triangulate(counts)
    v_idx = _obj_indices(ints[:, 0], nv)
    if v_idx.size and (v_idx.min() < 0 or v_idx.max() >= nv):
        raise ValueError(f"'{path}': face indices outside the {nv} vertices")
    faces = v_idx[tri].astype(np.int32)
    groups = _obj_groups(path, exact, group_sets, np.asarray(face_sets, np.int64), counts, v_idx, nv)
    if fields < 2 or not len(uv) or (ints[:, 1] == 0).any():
        return MeshFrame(vertices, faces, None, None, groups)
    t_idx = _obj_indices(ints[:, 1], len(uv))
    if t_idx.min() < 0 or t_idx.max() >= len(uv):
        raise ValueError(f"'{path}': texture indices outside the {len(uv)} uv records")
    if len(uv) == nv and np.array_equal(t_idx, v_idx):
        return MeshFrame(vertices, faces, uv, None, groups)
    return MeshFrame(vertices, faces, uv, t_idx[tri].astype(np.int32), groups)


def _obj_groups(path: str | os.PathLike, exact: list[str], group_sets: dict[tuple[str, ...], int],
                face_sets: np.ndarray, counts: np.ndarray, corner_vertices: np.ndarray,
                nv: int) -> dict[str, np.ndarray]:
    """Vertex groups of an OBJ file: the `#vg` lines, else the corners of each `g` group's faces.

    Args:
        exact: bodies of the `#vg name i j ...` lines (1-based indices).
        group_sets: group-name tuple -> id, as the `g` lines set them.
        face_sets: (P,) group-set id of each polygon.
        counts: (P,) corners of each polygon.
        corner_vertices: (sum(counts),) 0-based vertex of each corner.
        nv: vertex count (the indices are checked against it).
    Returns:
        name -> sorted unique (N,) int64 vertex indices.
    """
    groups: dict[str, np.ndarray] = {}
    owner = np.repeat(face_sets, counts) if len(face_sets) else np.zeros(0, np.int64)
    for names, gid in group_sets.items():
        if not names:
            continue
        corners = np.unique(corner_vertices[owner == gid])
        for name in names:
            groups[name] = np.union1d(groups[name], corners) if name in groups else corners
    for body in exact:
        name, _, rest = body.strip().partition(" ")
        idx = _parse_numbers(rest.split(), np.int64) - 1 if rest.strip() else np.zeros(0, np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= nv):
            raise ValueError(f"'{path}': vertex group '{name}' indexes vertices outside 1..{nv}")
        groups[name] = np.unique(idx)
    return groups


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
              uv: np.ndarray | None = None, uv_faces: np.ndarray | None = None,
              groups: dict[str, np.ndarray] | None = None) -> None:
    """Write an OBJ file (`v`, optional `vt`, `f`); float32 values round-trip exactly.

    Args:
        path: destination (written as is; use `atomic_path` for atomic writes).
        vertices: (V, 3) float, cm.
        faces: (T, 3) int.
        uv: (U, 2) or None; per vertex when `uv_faces` is None.
        uv_faces: (T, 3) int indices into `uv`, or None.
        groups: vertex groups, name -> (N,) int vertex indices: one exact `#vg` line each, and
            `g` lines before runs of faces whose three corners lie in the same groups (face
            order kept). Names must be non-empty without whitespace (OBJ separates names by it).
    Raises:
        ValueError: a group name that OBJ cannot hold.
    """
    def rows(fmt: str, values: np.ndarray) -> str:  # one C-level format call per record kind
        return (fmt * len(values)) % tuple(values.ravel().tolist())

    faces = np.asarray(faces, np.int64)
    groups = groups or {}
    for name in groups:
        if not name or len(name.split()) != 1 or name.split()[0] != name or name == "default":
            raise ValueError(f"groups: expected OBJ group names without whitespace (and not "
                             f"'default'), found {name!r}")
    if uv is not None:
        tex = faces if uv_faces is None else np.asarray(uv_faces, np.int64)
        face_rows = rows("f %d/%d %d/%d %d/%d\n", np.stack([faces, tex], axis=-1) + 1).splitlines(True)
    else:
        face_rows = rows("f %d %d %d\n", faces + 1).splitlines(True)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write("# written by nodegraph io\n")
        # float32 -> float64 is exact and %.9g round-trips any float32
        fh.write(rows("v %.9g %.9g %.9g\n", np.asarray(vertices, np.float32).astype(np.float64)))
        for name, idx in groups.items():
            fh.write(f"#vg {name}" + rows(" %d", np.asarray(idx, np.int64).ravel() + 1) + "\n")
        if uv is not None:
            fh.write(rows("vt %.9g %.9g\n", np.asarray(uv, np.float32).astype(np.float64)))
        if not groups or not len(faces):
            fh.write("".join(face_rows))
            return
        names = list(groups)
        member = np.zeros((len(names), len(vertices)), bool)
        for k, name in enumerate(names):
            member[k, np.asarray(groups[name], np.int64)] = True
        inside = member[:, faces].all(axis=2)  # (G, T): face in group
        _, sig = np.unique(inside.T, axis=0, return_inverse=True)
        sig = sig.ravel()
        starts = np.flatnonzero(np.r_[True, sig[1:] != sig[:-1]])
        for a, b in zip(starts, np.r_[starts[1:], len(faces)]):
            fh.write("g " + (" ".join(n for k, n in enumerate(names) if inside[k, a]) or "default") + "\n")
            fh.write("".join(face_rows[a:b]))


# -- PLY (trimesh) -------------------------------------------------------------------------

def read_ply(path: str | os.PathLike) -> MeshFrame:
    """Read a PLY file through trimesh, keeping vertex order; per-vertex uv when present."""
    import trimesh

    loaded = trimesh.load(os.fspath(path), file_type="ply", process=False, maintain_order=True)
    if isinstance(loaded, trimesh.Scene):
        geometry = list(loaded.geometry.values())
        if len(geometry) != 1:
            raise ValueError(f"'{path}': expected one mesh, found {len(geometry)}")
        loaded = geometry[0]
    vertices = np.asarray(loaded.vertices, dtype=np.float32)
    faces = np.asarray(getattr(loaded, "faces", np.zeros((0, 3))), dtype=np.int32).reshape(-1, 3)
    uv = getattr(getattr(loaded, "visual", None), "uv", None)
    uv = None if uv is None or len(uv) != len(vertices) else np.asarray(uv, np.float32)
    return MeshFrame(vertices, faces, uv, None)


def write_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
              uv: np.ndarray | None = None) -> None:
    """Write a binary PLY through trimesh (float32 positions, per-vertex uv as `s`, `t`)."""
    import trimesh

    visual = trimesh.visual.TextureVisuals(uv=np.asarray(uv, np.float64)) if uv is not None else None
    mesh = trimesh.Trimesh(vertices=np.asarray(vertices, np.float64), faces=np.asarray(faces),
                           visual=visual, process=False, validate=False)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False)
    with open(path, "wb") as fh:
        fh.write(data)


# -- helpers --------------------------------------------------------------------------------

def _resolve_first(path: str, first_frame: int | None) -> tuple[int | None, list[int]]:
    numbers = find_frame_numbers(path)
    if first_frame is not None:
        return first_frame, numbers
    return (numbers[0] if numbers else None), numbers


def _no_files(path: str) -> InputError:
    token = frame_token(path)
    folder = os.path.dirname(token.head) if token else os.path.dirname(path)
    return InputError("path", f"expected files matching '{path}', found none in "
                              f"'{folder or '.'}'")


# -- numbered files ------------------------------------------------------------------------

def _read_mesh_file(path: str, fmt: str, frame: int) -> MeshFrame:
    if not os.path.isfile(path):
        raise InputError("path", f"{frame_where(frame, path)}: expected the file of this frame, "
                                 "found it missing")
    try:
        return read_obj(path) if fmt == "obj" else read_ply(path)
    except (ValueError, OSError, UnicodeDecodeError, IndexError, KeyError, TypeError) as err:
        raise InputError("path", f"{frame_where(frame, path)}: expected a readable {fmt.upper()} mesh, "
                                 f"found an unreadable or truncated file ({err})") from err


def _load_numbered(path: str, fmt: str, frames: range, first_frame: int | None,
                   fps: float) -> MeshSequence:
    first, _ = _resolve_first(path, first_frame)
    if first is None:
        raise _no_files(path)
    ref_file = expand_frame_pattern(path, first)
    ref = _read_mesh_file(ref_file, fmt, 0)
    check_frame(0, ref_file, ref.vertices, None, None, ref_file)
    out = np.empty((len(frames), ref.vertices.shape[0], 3), np.float32)
    for i, f in enumerate(frames):
        file = expand_frame_pattern(path, first + f)
        data = ref if f == 0 else _read_mesh_file(file, fmt, f)
        check_frame(f, file, data.vertices, data.faces, ref, ref_file)
        out[i] = data.vertices
    return MeshSequence(vertices=out, faces=ref.faces, uv=ref.uv, uv_faces=ref.uv_faces,
                        groups=dict(ref.groups), fps=fps)


# -- NPZ ------------------------------------------------------------------------------------

def _load_npz(path: str, frames: range, fps: float) -> MeshSequence:
    try:
        keys = npz_keys(path)
        if "vertices" not in keys:
            raise InputError("path", f"file '{path}': expected an array 'vertices' (F, V, 3), "
                                     f"found keys {sorted(keys)}")
        shape, _ = npz_shape(path, "vertices")
        if len(shape) != 3 or shape[2] != 3:
            raise InputError("path", f"file '{path}': expected 'vertices' of shape (F, V, 3), "
                                     f"found {shape}")
        check_frame_range(frames, shape[0], path)
        vertices = read_npz_rows(path, "vertices", frames.start, frames.stop) if len(frames) else \
            np.zeros((0, shape[1], 3), np.float32)
        faces = read_npz_array(path, "faces") if "faces" in keys else np.zeros((0, 3), np.int32)
        uv = read_npz_array(path, "uv").astype(np.float32) if "uv" in keys else None
        uv_faces = read_npz_array(path, "uv_faces") if "uv_faces" in keys else None
        groups = {k[len("groups/"):]: read_npz_array(path, k) for k in keys if k.startswith("groups/")}
        if "fps" in keys:
            fps = float(read_npz_array(path, "fps"))
    except InputError:
        raise
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as err:
        raise InputError("path", f"file '{path}': expected a readable .npz mesh sequence, found "
                                 f"an unreadable or truncated file ({type(err).__name__}: {err})") from err
    vertices = vertices.astype(np.float32, copy=False)
    # Two reductions prove the rows finite and within MAX_COORDINATE_CM (min / max propagate
    # NaN; +-inf is beyond any bound) without (F, V, 3) temporaries; only a failure looks for
    # the first bad element.
    with np.errstate(invalid="ignore"):
        lo, hi = (float(vertices.min()), float(vertices.max())) if vertices.size else (0.0, 0.0)
    if not (-lo <= MAX_COORDINATE_CM and hi <= MAX_COORDINATE_CM):  # NaN fails both
        bad = ~np.isfinite(vertices)
        if bad.any():
            i, v = (int(x) for x in np.argwhere(bad)[0][:2])
            raise InputError("path", f"{frame_where(frames[i], path)}: expected finite vertices, found "
                                     f"NaN/inf at vertex {v}")
        check_magnitude(vertices, frames, lambda f: path)
    return MeshSequence(vertices=vertices, faces=faces, uv=uv, uv_faces=uv_faces, groups=groups,
                        fps=fps)


def _save_npz(path: str, mesh: MeshSequence, compress: bool) -> None:
    arrays: dict[str, np.ndarray] = {"vertices": np.asarray(mesh.vertices, np.float32),
                                     "faces": np.asarray(mesh.faces),
                                     "fps": np.asarray(float(mesh.fps))}
    if mesh.uv is not None:
        arrays["uv"] = np.asarray(mesh.uv, np.float32)
    if mesh.uv_faces is not None:
        arrays["uv_faces"] = np.asarray(mesh.uv_faces)
    for name, idx in mesh.groups.items():
        arrays[f"groups/{name}"] = np.asarray(idx)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        (np.savez_compressed if compress else np.savez)(fh, **arrays)


# -- public entry points -------------------------------------------------------------------

def mesh_frame_count(path: str, *, prim: str = "", first_frame: int | None = None) -> int:
    """Return how many frames `path` holds (0 when a pattern matches no file).

    For numbered files: highest number found - first number + 1 (a gap is refused while
    planning, by `LoadMeshSequence.input_files`).
    """
    fmt = format_of(path, MESH_FORMATS)
    if frame_token(path) is not None:
        first, numbers = _resolve_first(path, first_frame)
        return max(0, numbers[-1] - first + 1) if numbers and first is not None else 0
    if not os.path.isfile(path):
        return 0
    if fmt == "npz":
        try:
            return int(npz_shape(path, "vertices")[0][0])
        except (KeyError, ValueError, OSError, IndexError, zipfile.BadZipFile):
            return 0
    if fmt == "usd":
        return usd_mesh_frame_count(path, prim)
    raise InputError("path", f"'{path}': expected a numbered pattern (face.%04d.{fmt}) for "
                             f"{fmt.upper()} files, found a single file name")


def load_mesh_sequence(path: str, frames: range, *, prim: str = "", first_frame: int | None = None,
                       fps: float = 30.0) -> MeshSequence:
    """Read frames `frames` (0-based) of a mesh sequence, reading only those frames.

    Args:
        path: numbered OBJ/PLY pattern, .npz, or .usd/.usda/.usdc (see the module docstring).
        frames: run frames to read; frame f is file number first_frame + f, the f-th NPZ row
            or the f-th USD time sample.
        prim: USD Mesh prim path; "" = the first Mesh of the stage.
        first_frame: number of the file of frame 0; None = the lowest number found.
        fps: frames per second when the file stores none.
    Returns:
        MeshSequence with len(frames) frames, vertices in cm.
    Raises:
        InputError: naming the file and frame: missing or unreadable file, vertex count or
            faces differing from frame 0, non-finite vertices or ones beyond
            `MAX_COORDINATE_CM`, a stored fps not finite and > 0, face indices of missing
            vertices, unknown extension.
    """
    fmt = format_of(path, MESH_FORMATS)
    if frame_token(path) is not None:
        if fmt not in _PER_FRAME_FORMATS:
            raise InputError("path", f"'{path}': expected a single .{fmt} file, found a numbered "
                                     "pattern (numbered files are OBJ or PLY)")
        mesh = _load_numbered(path, fmt, frames, first_frame, fps)
        check_mesh_file(mesh, path, expand_frame_pattern(path, _resolve_first(path, first_frame)[0]))
        return mesh
    if fmt in ("npz", "usd"):
        if fmt == "npz" and not os.path.isfile(path):
            raise InputError("path", f"file '{path}': expected an .npz file, found it missing")
        mesh = _load_npz(path, frames, fps) if fmt == "npz" else load_usd_mesh(path, frames, prim, fps)
        check_mesh_file(mesh, path, path)
        return mesh
    raise InputError("path", f"'{path}': expected a numbered pattern (face.%04d.{fmt}) for "
                             f"{fmt.upper()} files, found a single file name")


def save_mesh_sequence(path: str, mesh: MeshSequence, frames: range, *, first_frame: int = 0,
                       prim: str = "/mesh", compress: bool = False,
                       progress=None) -> list[str]:
    """Write `mesh` (covering run frames `frames`) atomically; return the written paths.

    Args:
        path: numbered OBJ/PLY pattern (file number = first_frame + run frame), .npz or USD.
        mesh: the sequence; len(frames) == mesh.num_frames.
        frames: run frames of the sequence (USD time code = run frame).
        first_frame: file number of run frame 0 for patterns.
        prim: USD prim path of the Mesh.
        compress: NPZ only: zip-deflate the arrays (loads then stream instead of mmap).
        progress: optional callback(fraction, message).
    Raises:
        InputError: unknown extension, a single OBJ/PLY name, a numbered NPZ/USD name, or
            face-varying uv to PLY (which stores per-vertex uv only).
    """
    fmt = format_of(path, MESH_FORMATS)
    numbered = frame_token(path) is not None
    if numbered != (fmt in _PER_FRAME_FORMATS):
        expected = f"a numbered pattern such as 'face.%04d.{fmt}'" if not numbered else \
            f"a single .{fmt} file"
        raise InputError("path", f"'{path}': expected {expected} for {fmt.upper()}")
    if not numbered:
        if fmt == "npz":
            _save_npz(path, mesh, compress)
        else:
            save_usd_mesh(path, mesh, frames, prim)
        return [path]
    if fmt == "ply" and mesh.uv_faces is not None:
        raise InputError("mesh", f"'{path}': PLY stores per-vertex uv only, found face-varying uv "
                                 "(uv_faces); write OBJ, NPZ or USD instead")
    if fmt == "obj":
        bad = [n for n in mesh.groups if not n or n.split() != [n] or n == "default"]
        if bad:
            raise InputError("mesh", f"'{path}': expected vertex group names OBJ can hold (no whitespace, "
                                     f"not 'default'), found {bad}; rename the groups or write NPZ or USD")
    written = []
    for i, f in enumerate(frames):
        file = expand_frame_pattern(path, first_frame + f)
        with atomic_path(file) as tmp:
            if fmt == "obj":
                write_obj(tmp, mesh.vertices[i], mesh.faces, mesh.uv, mesh.uv_faces, mesh.groups)
            else:
                write_ply(tmp, mesh.vertices[i], mesh.faces, mesh.uv)
        written.append(file)
        if progress is not None:
            progress((i + 1) / len(frames), f"wrote {file}")
    return written


# -- nodes ----------------------------------------------------------------------------------

class LoadMeshSequence(Node):
    """Read a mesh sequence: numbered OBJ/PLY files, an .npz, or a USD Mesh."""

    type_name = "io.LoadMeshSequence"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Numbered pattern (face.%04d.obj, "
                          "face.####.ply, face.{frame:04d}.obj), .npz, or .usd/.usda/.usdc file.")
        prim: str = Param("", description="USD only: Mesh prim path; empty = the first Mesh found.")
        first_frame: int | None = Param(None, description="Numbered files: number of the file of "
                                        "frame 0; None = the lowest number found.")
        fps: float = Param(30.0, gt=0, description="Frames per second used when the file "
                           "carries none (1/s).")

    mesh = Out(MeshSequence, doc="Vertices (F, V, 3) in cm with the file's topology.")

    def frame_count(self) -> int | None:
        p = self.params
        count = mesh_frame_count(p.path, prim=p.prim, first_frame=p.first_frame)
        # frame 0 read while planning: a missing or unreadable file, a bad stored fps, faces of
        # missing vertices or a wild frame 0 are one error before anything runs
        load_mesh_sequence(p.path, range(0, 1), prim=p.prim, first_frame=p.first_frame, fps=p.fps)
        return count

    def peek_vertex_count(self) -> int | None:
        """The vertex count of the file's topology, read while planning (for consumers'
        `check_plan`, e.g. a network that fits one topology); None when unreadable (the run
        then reports why)."""
        p = self.params
        try:
            if format_of(p.path, MESH_FORMATS) == "npz" and frame_token(p.path) is None:
                return int(npz_shape(p.path, "vertices")[0][1])
            return load_mesh_sequence(p.path, range(0, 1), prim=p.prim, first_frame=p.first_frame,
                                      fps=p.fps).num_vertices
        except (InputError, OSError, ValueError, KeyError, IndexError, zipfile.BadZipFile):
            return None

    def input_files(self, frames: range | None = None) -> list[Path]:
        """All files; for a chunk of numbered files, the first file (every chunk reads its
        topology) and the chunk's own frames' files only."""
        p = self.params
        if frames is None or frame_token(p.path) is None:
            return pattern_files(p.path)
        if not hasattr(self, "_pattern_numbers"):  # one folder listing per plan
            self._pattern_numbers = _resolve_first(p.path, p.first_frame)
        first, numbers = self._pattern_numbers
        if first is None:
            return []
        check_no_missing_files(p.path, frames, first, numbers)  # a gap: one error while planning
        files = [Path(expand_frame_pattern(p.path, n)) for n in sorted({first} | {first + f for f in frames})]
        return [f for f in files if f.is_file()]

    def run(self) -> dict[str, MeshSequence]:
        p = self.params
        return {"mesh": load_mesh_sequence(p.path, self.frames, prim=p.prim,
                                           first_frame=p.first_frame, fps=p.fps)}


class SaveMeshSequence(Node):
    """Write a whole mesh sequence: .npz, USD, or numbered OBJ/PLY files (sequence kind).

    Use `io.SaveMeshFrames` to write numbered files chunk by chunk in parallel.
    """

    type_name = "io.SaveMeshSequence"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination: .npz, .usd/.usda/.usdc, or a numbered "
                          "OBJ/PLY pattern (face.%04d.obj).")
        first_frame: int = Param(0, description="Numbered files: file number of run frame 0.")
        prim: str = Param("/mesh", description="USD only: path of the Mesh prim written.")
        compress: bool = Param(False, description="NPZ only: deflate the arrays (smaller file; "
                               "chunked loads then stream instead of memory-mapping).")

        @field_validator("path")
        @classmethod
        def _writable_format(cls, value: str) -> str:  # refused at validation, not after the run
            fmt = format_of(value, MESH_FORMATS)
            numbered = frame_token(value) is not None
            if numbered != (fmt in _PER_FRAME_FORMATS):
                expected = f"a single .{fmt} file" if numbered else f"a numbered pattern such as face.%04d.{fmt}"
                raise ValueError(f"expected {expected} for {fmt.upper()}, found '{value}'")
            return value

    mesh = In(MeshSequence, doc="The sequence to write.")
    files = Out(Files, doc="Written paths and their sha256.")

    def import_first(self) -> tuple[str, ...]:
        """USD's modules when writing a .usd file (imported before the tasks: `Node.import_first`)."""
        return USD_MODULES if MESH_FORMATS.get(Path(self.params.path).suffix.lower()) == "usd" else ()

    def run(self, mesh: MeshSequence) -> dict[str, Files]:
        p = self.params
        written = save_mesh_sequence(p.path, mesh, self.frames, first_frame=p.first_frame,
                                     prim=p.prim, compress=p.compress, progress=self.progress)
        return {"files": files_value(written)}


class SaveMeshFrames(Node):
    """Write numbered OBJ/PLY files, one per frame (framewise: each chunk writes its own)."""

    type_name = "io.SaveMeshFrames"
    version = 1
    kind = FRAMEWISE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Numbered OBJ/PLY pattern (face.%04d.obj, "
                          "face.####.ply, face.{frame:04d}.obj).")
        first_frame: int = Param(0, description="File number of run frame 0.")

    mesh = In(MeshSequence, doc="The frames to write.")
    files = Out(Files, doc="Paths written by this chunk and their sha256.")

    def run(self, mesh: MeshSequence) -> dict[str, Files]:
        p = self.params
        if frame_token(p.path) is None:
            raise InputError("path", f"expected a numbered OBJ/PLY pattern such as "
                                     f"'face.%04d.obj', found '{p.path}' (use io.SaveMeshSequence "
                                     "for .npz and USD)")
        written = save_mesh_sequence(p.path, mesh, self.frames, first_frame=p.first_frame,
                                     progress=self.progress)
        return {"files": files_value(written)}
