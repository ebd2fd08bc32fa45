"""`Takes`: a list of mesh sequences (takes) of one topology, of different lengths and frame rates,
as one graph value; and `cached_take`, which reads a take's file(s) once and keeps the result
in the cache, keyed by the files' contents and the reader, so a folder of takes re-reads only
the files that changed.

A dataset (a day of capture: held expressions under several motions, dialog takes) is then a
first-class value in a graph rather than one long concatenated sequence with segment labels:
nodes iterate over `takes.take(i)` / `takes.skull(i)`. The value is whole (not chunked by
frames): a node that consumes it sees every take.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Callable, ClassVar, Sequence

import numpy as np

from .ports import PortType, check_array, check_finite, check_index_groups, fail
from .sequences import MeshSequence, RigidSequence

__all__ = ["Takes", "cached_take"]


@dataclass(eq=False)
class Takes(PortType):
    """Takes of one topology, each with its own length, frame rate and (optional) skull motion.

    Attributes:
        names: N take names (distinct; e.g. file stems).
        lengths: (N,) int64 frames of each take (>= 1).
        fps: (N,) float64 frames per second of each take.
        vertices: (sum(lengths), V, 3) float32, world space, cm: the takes one after the other.
        faces: (T, 3) int shared topology ((0, 3) for point sets).
        groups: named vertex groups, name -> (M,) int vertex indices.
        rigid: (sum(lengths), 4, 4) float64 skull-to-world transforms (identity rows where the
            take has none), or None when no take has any.
        has_rigid: (N,) bool, which takes carry `rigid`.
    """

    names: list[str]
    lengths: np.ndarray
    fps: np.ndarray
    vertices: np.ndarray
    faces: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    rigid: np.ndarray | None = None
    has_rigid: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))

    per_frame: ClassVar[bool] = False

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        n = len(self.names)
        if len(set(self.names)) != n:
            fail(where, f"take names must be distinct, found {self.names}")
        check_array(where, "lengths", self.lengths, 1, kinds="iu")
        check_array(where, "fps", self.fps, 1)
        check_array(where, "has_rigid", self.has_rigid, 1, kinds="b")
        if not (len(self.lengths) == len(self.fps) == len(self.has_rigid) == n):
            fail(where, f"expected {n} lengths, fps and has_rigid (one per take), found "
                         f"{len(self.lengths)}, {len(self.fps)}, {len(self.has_rigid)}")
        if n and self.lengths.min() < 1:
            fail(where, f"every take needs >= 1 frame, found lengths {self.lengths.tolist()}")
        if n and not (np.isfinite(self.fps).all() and self.fps.min() > 0):
            fail(where, f"'fps' must be finite and > 0, found {self.fps.tolist()}")
        check_array(where, "vertices", self.vertices, 3, (None, 3))
        check_finite(where, "vertices", self.vertices)
        if self.vertices.shape[0] != int(self.lengths.sum()):
            fail(where, f"expected {int(self.lengths.sum())} frames of vertices (sum of lengths), found "
                         f"{self.vertices.shape[0]}")
        v = self.vertices.shape[1]
        check_array(where, "faces", self.faces, 2, (3,), kinds="iu")
        if self.faces.size and (self.faces.min() < 0 or self.faces.max() >= v):
            fail(where, f"'faces' index vertices outside 0..{v - 1}")
        check_index_groups(where, self.groups, v)
        if self.rigid is not None:
            check_array(where, "rigid", self.rigid, 3, (4, 4))
            check_finite(where, "rigid", self.rigid)
            if self.rigid.shape[0] != self.vertices.shape[0]:
                fail(where, f"expected {self.vertices.shape[0]} rigid transforms, found {self.rigid.shape[0]}")
        elif self.has_rigid.any():
            fail(where, "has_rigid marks takes but 'rigid' is missing")

    @property
    def num_takes(self) -> int:
        return len(self.names)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[1])

    def _span(self, index: int) -> slice:
        starts = np.concatenate([[0], np.cumsum(self.lengths)])
        return slice(int(starts[index]), int(starts[index + 1]))

    def index(self, name: str) -> int:
        """The position of take `name` (ValueError naming the known takes when absent)."""
        if name not in self.names:
            raise ValueError(f"no take '{name}'; takes: {self.names}")
        return self.names.index(name)

    def take(self, index: int) -> MeshSequence:
        """Take `index` as a MeshSequence (its frames, the shared topology, its fps)."""
        return MeshSequence(vertices=self.vertices[self._span(index)], faces=self.faces,
                            groups=dict(self.groups), fps=float(self.fps[index]))

    def skull(self, index: int) -> RigidSequence | None:
        """Take `index`'s skull-to-world transforms, or None when it has none."""
        if not bool(self.has_rigid[index]):
            return None
        return RigidSequence(matrices=self.rigid[self._span(index)])

    @classmethod
    def from_sequences(cls, names: Sequence[str], meshes: Sequence[MeshSequence],
                       skulls: Sequence[RigidSequence | None]) -> "Takes":
        """Build from per-take values of one topology (the first take's faces and groups).

        Raises:
            ValueError: no takes, counts that disagree, or a take of another vertex count or
                faces, or a skull of another length than its take (the take named).
        """
        if not meshes or not (len(names) == len(meshes) == len(skulls)):
            raise ValueError(f"expected one name, mesh and skull (or None) per take and at least one "
                             f"take, found {len(names)}, {len(meshes)}, {len(skulls)}")
        first = meshes[0]
        for name, mesh, skull in zip(names, meshes, skulls):
            if mesh.num_vertices != first.num_vertices or not np.array_equal(mesh.faces, first.faces):
                raise ValueError(f"take '{name}': expected the topology of take '{names[0]}' "
                                 f"({first.num_vertices} vertices, {len(first.faces)} faces), found "
                                 f"{mesh.num_vertices} vertices, {len(mesh.faces)} faces")
            if skull is not None and skull.num_frames != mesh.num_frames:
                raise ValueError(f"take '{name}': expected {mesh.num_frames} rigid transforms (one per "
                                 f"frame), found {skull.num_frames}")
        has = np.array([s is not None for s in skulls], bool)
        rigid = None
        if has.any():
            rigid = np.concatenate([np.asarray(s.matrices, np.float64) if s is not None else
                                    np.broadcast_to(np.eye(4), (m.num_frames, 4, 4))
                                    for m, s in zip(meshes, skulls)])
        return cls(names=[str(n) for n in names],
                   lengths=np.array([m.num_frames for m in meshes], np.int64),
                   fps=np.array([float(m.fps) for m in meshes], np.float64),
                   vertices=np.concatenate([np.asarray(m.vertices, np.float32) for m in meshes]),
                   faces=np.asarray(first.faces), groups=dict(first.groups), rigid=rigid, has_rigid=has)


def cached_take(files_sha256: Sequence[str], reader_id: str,
                read: Callable[[], tuple[MeshSequence, RigidSequence | None]],
                cache=None) -> tuple[MeshSequence, RigidSequence | None]:
    """Read one take through the cache: a hit when the same reader read the same file contents.

    Args:
        files_sha256: content hashes of the take's file(s) (several for numbered OBJ/PLY).
        reader_id: identifies the reader and its settings (e.g. node type, version, code hash,
            parameters); another reader never gets this one's entry.
        read: reads the take (called on a miss).
        cache: a `nodegraph.cache.Cache`, or None to read without caching.
    Returns:
        (mesh, skull or None), read-only arrays on a hit.
    """
    if cache is None:
        return read()
    from .cache import CorruptEntry, make_key

    key = make_key({"type": "nodegraph.takes/file", "reader": reader_id, "files": list(files_sha256)})
    if cache.contains(key):
        try:
            values = cache.load(key)
            return values["mesh"], values.get("rigid")
        except (KeyError, CorruptEntry, OSError, ValueError):
            pass  # removed or damaged meanwhile: read again
    mesh, skull = read()
    values = {"mesh": mesh} if skull is None else {"mesh": mesh, "rigid": skull}
    try:
        cache.store(key, values, {"type": "nodegraph.takes/file", "reader": reader_id,
                                  "files": json.dumps(list(files_sha256))})
    except OSError:
        pass  # a read-only or full cache folder: the take was still read
    return mesh, skull
