"""One mesh as read from a file, and the checks and polygon helpers its readers share.

Shared by the mesh-sequence readers of `nodes.io.mesh` (OBJ, PLY, NPZ) and `nodes.io.usd`.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from nodegraph import InputError, MeshSequence

from ._files import frame_where

__all__ = ["MeshFrame", "MAX_COORDINATE_CM", "MAX_FPS", "fan_triangulate", "check_frame", "check_magnitude",
           "check_mesh_file"]

MAX_COORDINATE_CM = 1e6
"""Largest vertex coordinate a reader accepts, in cm (10 km). Beyond it float32 steps are 0.06 cm
or coarser, as coarse as the motion a capture measures, and squared distances overflow float32
near 1e19: a coordinate that large is a unit or export error, never a face."""

MAX_FPS = 1e4
"""Largest frame rate a file may store (as `nodegraph.performance` accepts): beyond it a take's
velocities (the dynamics descriptors) and time steps are a unit error, not a capture."""


class MeshFrame(NamedTuple):
    """One mesh as read from a file.

    Attributes:
        vertices: (V, 3) float32, cm.
        faces: (T, 3) int32 vertex indices.
        uv: (U, 2) float32 or None.
        uv_faces: (T, 3) int32 indices into `uv`, or None (then uv is per vertex).
        groups: named vertex groups, name -> (N,) int64 vertex indices (empty when the file has none).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None
    groups: dict[str, np.ndarray] = {}


def fan_triangulate(counts: np.ndarray) -> np.ndarray:
    """Fan-triangulate polygons given their corner counts.

    Args:
        counts: (N,) int, corners of each polygon (>= 3), corners stored one polygon after
            the other.
    Returns:
        (T, 3) int64 indices of corners (into the flat corner list), T = sum(counts - 2);
        polygon (c0, c1, ..., cn) gives (c0, c1, c2), (c0, c2, c3), ...
    Raises:
        ValueError: when a polygon has fewer than 3 corners.

    Example:
        >>> fan_triangulate(np.array([3, 4])).tolist()
        [[0, 1, 2], [3, 4, 5], [3, 5, 6]]
    """
    counts = np.asarray(counts, dtype=np.int64)
    if counts.size and counts.min() < 3:
        bad = int(np.argmax(counts < 3))
        raise ValueError(f"counts: expected >= 3 corners per polygon, found {int(counts[bad])} "
                         f"at polygon {bad}")
    starts = np.cumsum(counts) - counts
    tris = counts - 2
    owner = np.repeat(np.arange(counts.size), tris)
    k = np.arange(int(tris.sum())) - np.repeat(np.cumsum(tris) - tris, tris)
    base = starts[owner]
    return np.stack([base, base + k + 1, base + k + 2], axis=1)


def check_frame(frame: int, file: str, vertices: np.ndarray, faces: np.ndarray | None,
                ref: MeshFrame | None, ref_file: str) -> None:
    """Raise InputError (param "path") when a frame's vertices are not finite or its topology differs.

    Args:
        frame: run frame, named in the error.
        file: the frame's file, named in the error.
        vertices: (V, 3) the frame's vertices.
        faces: (T, 3) its faces, or None to skip the topology check.
        ref: frame 0 to compare with, or None (frame 0 itself).
        ref_file: frame 0's file, named in the error.
    """
    if ref is not None:
        if vertices.shape[0] != ref.vertices.shape[0]:
            raise InputError("path", f"{frame_where(frame, file)}: expected {ref.vertices.shape[0]} "
                                     f"vertices as in frame 0 ('{ref_file}'), found {vertices.shape[0]}")
        if faces is not None and not np.array_equal(faces, ref.faces):
            detail = (f"{len(faces)} faces vs {len(ref.faces)}" if faces.shape != ref.faces.shape else
                      f"first different face {int(np.argmax((faces != ref.faces).any(axis=1)))}")
            raise InputError("path", f"{frame_where(frame, file)}: expected the faces of frame 0 "
                                     f"('{ref_file}'), found different topology ({detail})")
    bad = ~np.isfinite(vertices)
    if bad.any():
        vertex = int(np.argwhere(bad)[0][0])
        raise InputError("path", f"{frame_where(frame, file)}: expected finite vertices, found "
                                 f"NaN/inf at vertex {vertex}")
    check_magnitude(vertices[None], range(frame, frame + 1), lambda f: file)


def check_magnitude(vertices: np.ndarray, frames: range, file_of) -> None:
    """Raise InputError (param "path") naming the first vertex beyond `MAX_COORDINATE_CM`.

    Args:
        vertices: (F, V, 3) finite coordinates, cm, of run frames `frames`.
        frames: the run frames of the rows (len F).
        file_of: run frame -> the file to name in the error.
    """
    big = np.abs(vertices) > MAX_COORDINATE_CM
    if big.any():
        i, v, axis = (int(x) for x in np.argwhere(big)[0])
        frame = frames[i]
        raise InputError("path", f"{frame_where(frame, file_of(frame))}: expected vertex coordinates "
                                 f"within +-{MAX_COORDINATE_CM:g} cm, found {float(vertices[i, v, axis]):g} "
                                 f"at vertex {v} (a unit or export error?)")


def check_mesh_file(mesh: MeshSequence, path: str, topology_file: str) -> None:
    """Raise InputError (param "path") naming the file when a read mesh is unusable.

    Checks what the file itself stores beyond its vertices: the frame rate (finite, in (0, MAX_FPS]), the
    faces ((T, 3) integer indices of existing vertices), uv and vertex groups.

    Args:
        mesh: the sequence as read.
        path: the file (or pattern) it was read from, named for the frame rate.
        topology_file: the file its faces, uv and groups came from (frame 0's for patterns).
    """
    fps = float(mesh.fps)
    if not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise InputError("path", f"file '{path}': expected the frame rate it stores ('fps') finite "
                                 f"and in (0, {MAX_FPS:g}], found {fps:g}")
    faces = np.asarray(mesh.faces)
    count = mesh.vertices.shape[1]
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.dtype.kind not in "iu":
        raise InputError("path", f"file '{topology_file}': expected 'faces' (T, 3) integer vertex "
                                 f"indices, found shape {faces.shape} {faces.dtype}")
    bad = (faces < 0) | (faces >= count)
    if bad.any():
        t, corner = (int(x) for x in np.argwhere(bad)[0])
        raise InputError("path", f"file '{topology_file}': expected face vertex indices in "
                                 f"0..{count - 1} ({count} vertices), found {int(faces[t, corner])} in "
                                 f"face {t} ({int(bad.any(axis=1).sum())} such faces)")
    try:
        mesh.validate(f"file '{topology_file}'")
    except ValueError as err:
        raise InputError("path", str(err)) from err
