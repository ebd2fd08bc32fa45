"""Read a day of capture (Zoss et al. 2020, section 5): `dynamics.LoadTakes` turns a glob or a
folder of takes into one `nodegraph.takes.Takes` value (each take its own length and frame rate):
NPZ (`vertices [F,V,3]`, `faces`, `fps`, optional `rigid [F,4,4]` skull-to-world), USD, numbered
OBJ/PLY (`take_a.0001.obj`, ... = one take). Each take is read through the run's cache, keyed by
its files' contents: adding a take to the folder re-reads only that one. LoadTakes is the run's
frame source (its frame count is the longest take's): `--frames a:b` keeps frames a:b of every
take. `dynamics.LoadNeutral` reads the subject's one-frame neutral as a whole value, so it takes
no part in the run's frames. The training on the takes is in `takes.py`.
"""

from __future__ import annotations

import glob
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from nodegraph import (SEQUENCE, InputError, MeshSequence, Node, NodeParams, Out, Param, ParamSequence,
                       RigidSequence)
from nodegraph.files import file_sha256
from nodegraph.takes import Takes, cached_take

from ..io._files import npz_shape, pattern_files
from ..io.mesh import load_mesh_sequence, mesh_frame_count
from ..io.mesh_frame import MAX_FPS

__all__ = ["TAKE_SUFFIXES", "find_takes", "read_take", "stored_fps", "slice_takes", "LoadTakes", "LoadNeutral"]

MIN_TAKE_FRAMES = 2  # a take needs a velocity: fewer frames in the run's range leave it out

TAKE_SUFFIXES = (".npz", ".usd", ".usda", ".usdc", ".obj", ".ply")
_NUMBERED = re.compile(r"^(?P<head>.*?)(?P<number>\d+)\.(?P<ext>obj|ply)$", re.IGNORECASE)


def find_takes(spec: str) -> list[tuple[str, str, list[Path]]]:
    """The takes a glob or folder names: (name, path for `io.load_mesh_sequence`, files).

    A folder stands for every take file in it. NPZ and USD files are one take each (name: the
    file stem); numbered OBJ/PLY files with the same name before the number are one take
    (`take_a.0001.obj`, `take_a.0002.obj` -> 'take_a', read as `take_a.%04d.obj`).

    Raises:
        InputError: ("captures") nothing found, a file of another kind in a glob, an OBJ/PLY
            without a frame number, or two takes of one name.
    """
    if os.path.isdir(spec):
        files = sorted(p for p in Path(spec).iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES)
    else:
        files = sorted(Path(p) for p in glob.glob(spec) if os.path.isfile(p))
        other = [str(p) for p in files if p.suffix.lower() not in TAKE_SUFFIXES]
        if other:
            raise InputError("captures", f"expected take files ({', '.join(TAKE_SUFFIXES)}), found "
                                         f"{other[:3]} matching '{spec}'")
    if not files:
        raise InputError("captures", f"expected take files matching '{spec}' (a glob such as "
                                     f"'takes/take_*.npz', or a folder), found none")
    takes: dict[str, tuple[str, list[Path]]] = {}
    numbered: dict[tuple[str, str, int, str], list[Path]] = {}
    for path in files:
        if path.suffix.lower() in (".obj", ".ply"):
            match = _NUMBERED.match(path.name)
            if not match:
                raise InputError("captures", f"expected numbered OBJ/PLY files (one per frame, e.g. "
                                             f"'take_a.0001.obj'), found '{path}'")
            key = (str(path.parent), match["head"], len(match["number"]), match["ext"])
            numbered.setdefault(key, []).append(path)
            continue
        name = path.stem
        if name in takes:
            raise InputError("captures", f"expected one take per name, found '{takes[name][1][0]}' and '{path}'")
        takes[name] = (str(path), [path])
    for (folder, head, width, ext), paths in numbered.items():
        name = head.rstrip("._- ") or Path(folder).name
        if name in takes:
            raise InputError("captures", f"expected one take per name, found two named '{name}' "
                                         f"('{takes[name][1][0]}' and '{paths[0]}')")
        takes[name] = (os.path.join(folder, f"{head}%0{width}d.{ext}"), paths)
    return [(name, path, files) for name, (path, files) in sorted(takes.items())]


def read_take(name: str, path: str, fps: float) -> tuple[MeshSequence, RigidSequence | None]:
    """Read one take (all its frames) and, for NPZ, its `rigid` skull-to-world transforms.

    Args:
        name: the take's name (for messages).
        path: an NPZ/USD file or a numbered OBJ/PLY pattern.
        fps: frames per second for files without one (NPZ without `fps`, OBJ/PLY); 0 = such a
            file is an error.
    Raises:
        InputError: ("captures") unreadable, fewer than 2 frames, no frame rate, or a `rigid`
            array that is not (F, 4, 4) finite.
    """
    where = f"take '{name}' ('{path}')"
    count = mesh_frame_count(path)
    try:
        mesh = load_mesh_sequence(path, range(count) if count else range(0, 1), fps=fps or 30.0)
    except InputError as err:
        raise InputError("captures", f"{where}: {err.message}") from err
    if mesh.num_frames < 2:
        raise InputError("captures", f"{where}: expected at least 2 frames, found {mesh.num_frames}")
    rigid = None
    if path.lower().endswith(".npz"):
        try:
            with np.load(path, allow_pickle=False) as data:
                has_fps = "fps" in data.files
                if "rigid" in data.files:
                    rigid = np.asarray(data["rigid"], np.float64)
        except (OSError, ValueError, zipfile.BadZipFile) as err:
            raise InputError("captures", f"{where}: expected a readable NPZ, found {err}") from err
        if rigid is not None and (rigid.shape != (mesh.num_frames, 4, 4) or not np.isfinite(rigid).all()):
            raise InputError("captures", f"{where}: expected 'rigid' of shape ({mesh.num_frames}, 4, 4), "
                                         f"finite, found shape {rigid.shape}")
    else:
        has_fps = path.lower().endswith((".usd", ".usda", ".usdc"))
    if not has_fps and not fps > 0:
        raise InputError("fps", f"{where}: expected a frame rate in the file ('fps') or the fps "
                                f"parameter, found neither")
    return mesh, (RigidSequence(matrices=rigid) if rigid is not None else None)


def _check_stored_fps(name: str, path: str) -> None:
    """InputError ("captures") when an NPZ take stores a frame rate that is not finite and in
    (0, MAX_FPS] (only the small 'fps' member is read)."""
    try:
        with np.load(path, allow_pickle=False) as data:
            if "fps" not in data.files:
                return
            stored = np.asarray(data["fps"], np.float64)
    except (OSError, ValueError, zipfile.BadZipFile):
        return  # unreadable: the read reports it
    fps = float(stored.reshape(-1)[0]) if stored.size == 1 else float("nan")
    if not (np.isfinite(fps) and 0 < fps <= MAX_FPS):
        raise InputError("captures", f"take '{name}' ('{path}'): expected the frame rate it stores ('fps') finite "
                                     f"and in (0, {MAX_FPS:g}], found {stored.tolist()}")


def stored_fps(path: str) -> float | None:
    """The frame rate an NPZ take stores ('fps', only that member read), or None when it stores
    none, is unreadable or is not an NPZ."""
    if not path.lower().endswith(".npz"):
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if "fps" not in data.files:
                return None
            stored = np.asarray(data["fps"], np.float64)
    except (OSError, ValueError, zipfile.BadZipFile):
        return None
    return float(stored.reshape(-1)[0]) if stored.size == 1 else None


def slice_takes(names: list[str], meshes: list[MeshSequence], skulls: list[RigidSequence | None],
                frames: range) -> tuple[list[int], np.ndarray]:
    """Which takes keep at least `MIN_TAKE_FRAMES` of the run's `frames`, and the coverage.

    Args:
        names: N take names (for messages).
        meshes: N takes, each its own length.
        skulls: N skull motions (None where a take has none).
        frames: the run's absolute frames (`--frames a:b`; default 0 to the longest take).
    Returns:
        (kept take indices, coverage (len(frames), N) float32: 1 where take n has the run's
        frame f, else 0).
    Raises:
        InputError: ("captures") no take keeps `MIN_TAKE_FRAMES` frames of the range.
    """
    lengths = np.array([m.num_frames for m in meshes], np.int64)
    run = np.arange(frames.start, frames.stop)
    coverage = (run[:, None] < lengths[None, :]).astype(np.float32)
    kept = [i for i, n in enumerate(lengths) if min(frames.stop, int(n)) - frames.start >= MIN_TAKE_FRAMES]
    if not kept:
        raise InputError("captures", f"--frames {frames.start}:{frames.stop}: expected takes with at least "
                                     f"{MIN_TAKE_FRAMES} frames in the range, found take lengths "
                                     f"{dict(zip(names, lengths.tolist()))}")
    return kept, coverage


class LoadTakes(Node):
    """Read a day of capture: every take of a glob or folder, each its own length and frame rate.

    The run's frames are the takes' frames: the frame count is the longest take's, and a run of
    frames a:b keeps frames a:b of every take (a take with fewer than 2 of them is left out,
    shown by a zero column of `coverage`)."""

    type_name = "dynamics.LoadTakes"
    version = 2  # v2: the run's frame source; --frames a:b keeps frames a:b of every take
    kind = SEQUENCE

    class Params(NodeParams):
        captures: str = Param(..., input_file=True, description="Glob (takes/take_*.npz) or folder of takes: "
                              "NPZ (vertices [F,V,3], faces, fps, optional rigid [F,4,4] skull-to-world), "
                              "USD, or numbered OBJ/PLY (take_a.0001.obj, ... = one take).")
        fps: float = Param(0.0, ge=0, description="Frames per second of takes whose files carry none "
                           "(NPZ without fps, OBJ/PLY); 0 = such a take is an error (a guessed rate "
                           "would scale every velocity the network sees).")

    takes = Out(Takes, doc="The takes, sorted by name; one topology; frames a:b of each for a run of a:b.")
    coverage = Out(ParamSequence, doc="Per run frame and take found (columns named by take): 1 where the "
                                      "take has that frame, 0 where it is shorter (a take with fewer than "
                                      "2 frames in the run is left out of `takes`).")

    def frame_count(self) -> int | None:
        """The longest take's frame count, read from the files' headers while planning; a take
        whose header gives none is read, so that its error is one refusal before anything runs,
        and so is an NPZ take whose stored frame rate is not finite and in (0, MAX_FPS]."""
        counts = []
        for name, path, _ in find_takes(self.params.captures):
            count = mesh_frame_count(path)
            if not count:
                count = read_take(name, path, self.params.fps)[0].num_frames  # raises why
            counts.append(int(count))
            if path.lower().endswith(".npz"):
                _check_stored_fps(name, path)
        return max(counts)

    def peek_takes(self, frames: range) -> list[tuple[str, int, float | None]] | None:
        """(name, frames in the run, frame rate or None when the header does not say) of each take
        a run of `frames` keeps (at least `MIN_TAKE_FRAMES` of them), from the files' headers
        while planning (for consumers' `check_frames`); None when a take's length is unknown
        there (the run reports it)."""
        try:
            found = find_takes(self.params.captures)
        except InputError:
            return None
        takes = []
        for name, path, _ in found:
            count = mesh_frame_count(path)
            if not count:
                return None
            inside = min(frames.stop, int(count)) - frames.start
            if inside >= MIN_TAKE_FRAMES:
                fps = stored_fps(path) if path.lower().endswith(".npz") else None
                if fps is None and not path.lower().endswith((".usd", ".usda", ".usdc")) and self.params.fps > 0:
                    fps = float(self.params.fps)  # what read_take gives a file without a rate
                takes.append((name, inside, fps if fps is not None and 0 < fps <= MAX_FPS else None))
        return takes

    def peek_vertex_counts(self) -> dict[str, int]:
        """Take name -> vertex count, from the headers of the NPZ takes (read while planning, for
        consumers' `check_plan`); takes of other formats, and unreadable ones, are left out (the
        run reports them)."""
        counts = {}
        try:
            found = find_takes(self.params.captures)
        except InputError:
            return {}
        for name, path, _ in found:
            if path.lower().endswith(".npz"):
                try:
                    shape = npz_shape(path, "vertices")[0]
                except (KeyError, ValueError, OSError, zipfile.BadZipFile):
                    continue
                if len(shape) == 3:
                    counts[name] = int(shape[1])
        return counts

    def input_files(self, frames: range | None = None) -> list[Path]:
        try:
            return [f for _, _, files in find_takes(self.params.captures) for f in files]
        except InputError:
            return []  # run() reports it

    def key_params(self) -> dict:
        key = super().key_params()
        try:  # the names are part of the value; the files' contents are keyed by input_files
            key["take_names"] = [name for name, _, _ in find_takes(self.params.captures)]
        except InputError:
            key["take_names"] = []
        return key

    def run(self) -> dict:
        p = self.params
        found = find_takes(p.captures)
        from nodegraph.cache import Cache

        cache = Cache(self.cache_root) if self.cache_root else None
        reader = f"{self.type_name}/{self.version}/{self.code_hash()}/fps={p.fps!r}"
        names, meshes, skulls = [], [], []
        for i, (name, path, files) in enumerate(found):
            mesh, skull = cached_take([file_sha256(f) for f in files], reader,
                                      lambda: read_take(name, path, p.fps), cache)
            names.append(name)
            meshes.append(mesh)
            skulls.append(skull)
            self.progress((i + 1) / len(found), f"take {name}: {mesh.num_frames} frames at {mesh.fps:g} fps"
                          f"{'' if skull is not None else ', no rigid'}")
        kept, coverage = slice_takes(names, meshes, skulls, self.frames)
        start = self.frames.start
        cut = [(names[i], meshes[i].slice_frames(start, min(self.frames.stop, meshes[i].num_frames)),
                None if skulls[i] is None else
                skulls[i].slice_frames(start, min(self.frames.stop, skulls[i].num_frames))) for i in kept]
        try:
            takes = Takes.from_sequences([c[0] for c in cut], [c[1] for c in cut], [c[2] for c in cut])
        except ValueError as err:
            raise InputError("captures", str(err)) from err
        return {"takes": takes, "coverage": ParamSequence(values=coverage, names=names)}


_PLANNED_NEUTRALS: dict[tuple, MeshSequence] = {}  # file state -> the neutral read while planning


class LoadNeutral(Node):
    """Read the subject's neutral: one frame of a mesh file, as a whole value (not framed by the run)."""

    type_name = "dynamics.LoadNeutral"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="The neutral mesh: .npz, .usd/.usda/.usdc, or a "
                          "numbered OBJ/PLY pattern (face.%04d.obj).")
        frame: int | None = Param(None, ge=0, description="Frame of the file that is the neutral; none = "
                                  "the file must hold exactly one frame (so that a take given by mistake "
                                  "is refused, not read as a neutral).")
        prim: str = Param("", description="USD only: Mesh prim path; empty = the first Mesh found.")

    mesh = Out(MeshSequence, per_frame=False, doc="The neutral (1 frame, cm).")

    def check_plan(self, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: the file is read (one frame), so a missing or unreadable neutral,
        or one of several frames without `frame`, is one refusal. The mesh read is kept for run()
        in this process (keyed by the files' paths, sizes and modification times), so the file
        is read once a run."""
        mesh = self._read()
        self._planned_vertices = mesh.num_vertices
        if len(_PLANNED_NEUTRALS) >= 8:  # plans whose run never came (cache hits, refusals)
            _PLANNED_NEUTRALS.clear()
        _PLANNED_NEUTRALS[self._file_state()] = mesh

    def input_files(self, frames: range | None = None) -> list[Path]:
        """The neutral's file, or every file of a numbered OBJ/PLY pattern (their contents key the cache)."""
        return pattern_files(self.params.path)

    def _file_state(self) -> tuple:
        """What identifies the read: parameters, and each file's path, size and modification time."""
        p = self.params
        stats = []
        for path in pattern_files(p.path):
            try:
                stat = path.stat()
            except OSError:
                return (p.path, p.frame, p.prim, None)
            stats.append((str(path.resolve()), stat.st_size, stat.st_mtime_ns))
        return (p.path, p.frame, p.prim, tuple(stats))

    def peek_vertex_count(self) -> int | None:
        """The neutral's vertex count, read while planning (None when unreadable)."""
        if getattr(self, "_planned_vertices", None) is None:
            try:
                self._planned_vertices = self._read().num_vertices
            except (InputError, OSError, ValueError):
                return None
        return self._planned_vertices

    def _read(self) -> MeshSequence:
        p = self.params
        count = mesh_frame_count(p.path, prim=p.prim)
        if not count:  # missing or unreadable: the reader says why
            load_mesh_sequence(p.path, range(0, 1), prim=p.prim)
        if p.frame is None and count != 1:
            raise InputError("path", f"file '{p.path}': expected one frame (the neutral; or set 'frame' to "
                                     f"pick one), found {count} frames")
        frame = p.frame or 0
        if frame >= count:
            raise InputError("frame", f"file '{p.path}': expected a frame in 0..{count - 1}, found {frame}")
        return load_mesh_sequence(p.path, range(frame, frame + 1), prim=p.prim)

    def run(self) -> dict:
        planned = _PLANNED_NEUTRALS.pop(self._file_state(), None)  # read while planning (same files)
        return {"mesh": planned if planned is not None else self._read()}
