"""Read a day of capture (Zoss et al. 2020, section 5): `dynamics.LoadTakes` turns a glob or a
folder of takes into one `nodegraph.takes.Takes` value (each take its own length and frame rate):
NPZ (`vertices [F,V,3]`, `faces`, `fps`, optional `rigid [F,4,4]` skull-to-world), USD, numbered
OBJ/PLY (`take_a.0001.obj`, ... = one take). Each take is read through the run's cache, keyed by
its files' contents: adding a take to the folder re-reads only that one. The training on the
takes is in `takes.py`.
"""

from __future__ import annotations

import glob
import os
import re
import zipfile
from pathlib import Path

import numpy as np

from nodegraph import SEQUENCE, InputError, MeshSequence, Node, NodeParams, Out, Param, RigidSequence
from nodegraph.files import file_sha256
from nodegraph.takes import Takes, cached_take

from ..io.mesh import load_mesh_sequence, mesh_frame_count

__all__ = ["TAKE_SUFFIXES", "find_takes", "read_take", "LoadTakes"]

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


class LoadTakes(Node):
    """Read a day of capture: every take of a glob or folder, each its own length and frame rate."""

    type_name = "dynamics.LoadTakes"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        captures: str = Param(..., input_file=True, description="Glob (takes/take_*.npz) or folder of takes: "
                              "NPZ (vertices [F,V,3], faces, fps, optional rigid [F,4,4] skull-to-world), "
                              "USD, or numbered OBJ/PLY (take_a.0001.obj, ... = one take).")
        fps: float = Param(0.0, ge=0, description="Frames per second of takes whose files carry none "
                           "(NPZ without fps, OBJ/PLY); 0 = such a take is an error (a guessed rate "
                           "would scale every velocity the network sees).")

    takes = Out(Takes, doc="The takes, sorted by name; one topology.")

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
        try:
            return {"takes": Takes.from_sequences(names, meshes, skulls)}
        except ValueError as err:
            raise InputError("captures", str(err)) from err
