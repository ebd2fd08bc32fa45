"""Load a linear face model (the bundled ICT-FaceKit head by default) as a `FaceModel`.

The bundled file is `nodes/data/ict_face_model.npz` (see `nodes/data/ICT-FaceKit-README.md`,
MIT license in `ICT-FaceKit-LICENSE.txt`): a 26,719-vertex head in cm, y up, z forward
(out of the face), with 53 ARKit-named expression shapes and 40 identity components.

A model can be restricted to one vertex group (`region`, e.g. "face") and/or reduced to a
well-spread subset of at most `max_vertices` vertices (farthest-point sampling, which turns
the model into a point set without faces). Both keep vertex order and re-index groups and
landmarks, dropping entries that fall outside.
"""

from __future__ import annotations

import importlib.resources
import zipfile
from pathlib import Path
from typing import Mapping

import numpy as np
from pydantic import field_validator

from nodegraph import SEQUENCE, FaceModel, InputError, Node, NodeParams, Out, Param

from ..geometry.sampling import farthest_point_sampling

__all__ = [
    "BUNDLED_MODEL", "bundled_model_path", "load_face_model", "restrict_face_model",
    "triangulate_polygons", "LoadFaceModel",
]

BUNDLED_MODEL = "ict_face_model.npz"
"""File name of the bundled ICT-FaceKit model inside the `nodes/data` package folder."""

_REQUIRED = ("neutral", "polygons", "expression_names", "expression_deltas", "identity_deltas")
_OPTIONAL = ("polygon_uv", "uv", "group_names", "group_ranges", "rigid_vertices",
             "fitting_vertices", "landmarks68")


def bundled_model_path() -> Path:
    """Return the path of the bundled ICT-FaceKit model file (wherever the package is)."""
    return Path(str(importlib.resources.files("nodes") / "data" / BUNDLED_MODEL))


def triangulate_polygons(polygons: np.ndarray) -> np.ndarray:
    """Split quads (and -1-padded triangles) into triangles 0-1-2, 0-2-3, in polygon order.

    Args:
        polygons: (P, 4) int; a row whose last index is -1 is a triangle.
    Returns:
        (T, 3) int32 triangles, T = P + number of quads; quad p gives two consecutive rows.

    Example:
        >>> triangulate_polygons(np.array([[0, 1, 2, 3], [4, 5, 6, -1]])).tolist()
        [[0, 1, 2], [0, 2, 3], [4, 5, 6]]
    """
    polygons = np.asarray(polygons)
    if polygons.ndim != 2 or polygons.shape[1] != 4:
        raise ValueError(f"polygons: expected shape (P, 4), found {polygons.shape}")
    pairs = np.stack([polygons[:, [0, 1, 2]], polygons[:, [0, 2, 3]]], axis=1)  # (P, 2, 3)
    keep = np.stack([np.ones(len(polygons), bool), polygons[:, 3] >= 0], axis=1)  # (P, 2)
    return pairs[keep].astype(np.int32)


def restrict_face_model(model: FaceModel, keep: np.ndarray, *, keep_faces: bool = True) -> FaceModel:
    """Return the model restricted to vertices `keep` (in their original order).

    Faces are kept only where all three corners are kept (re-indexed), with their uv faces;
    groups and landmarks are re-indexed and lose the vertices not kept.

    Args:
        model: the full model.
        keep: (N,) int vertex indices (sorted ascending, unique).
        keep_faces: False drops every face (a point set), and the uv with them.
    Returns:
        A new FaceModel with N vertices; vertex i is the old vertex keep[i].
    """
    from ..mesh.regions import remap_indices, restrict_faces

    keep = np.asarray(keep, dtype=np.int64)
    faces, inside, old_to_new = restrict_faces(model.faces, keep, model.neutral.shape[0])
    uv, uv_faces = None, None
    if not keep_faces:
        faces = np.zeros((0, 3), np.int32)
    elif model.uv is not None and model.uv_faces is not None:
        uv, uv_faces = model.uv, model.uv_faces[inside]
    groups = {name: remap_indices(old_to_new, idx) for name, idx in model.groups.items()}
    return FaceModel(
        neutral=np.ascontiguousarray(model.neutral[keep]),
        faces=faces,
        expression_deltas=np.ascontiguousarray(model.expression_deltas[:, keep]),
        expression_names=list(model.expression_names),
        identity_deltas=np.ascontiguousarray(model.identity_deltas[:, keep]),
        groups=groups,
        landmarks=remap_indices(old_to_new, model.landmarks),
        uv=uv,
        uv_faces=uv_faces,
    )


def _read_arrays(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise FileNotFoundError(f"path: face model file '{path}' does not exist")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as err:
        raise ValueError(f"path: '{path}' is not a readable .npz face model "
                         f"({type(err).__name__}: {err})") from err
    missing = [name for name in _REQUIRED if name not in arrays]
    if missing:
        raise ValueError(f"path: '{path}' lacks the array(s) {missing}; a face model needs "
                         f"{list(_REQUIRED)} (found {sorted(arrays)})")
    return arrays


def _groups_from(arrays: Mapping[str, np.ndarray], v: int) -> dict[str, np.ndarray]:
    groups: dict[str, np.ndarray] = {}
    if "group_names" in arrays and "group_ranges" in arrays:
        names, ranges = arrays["group_names"], arrays["group_ranges"]
        if ranges.shape != (len(names), 2):
            raise ValueError(f"group_ranges: expected shape ({len(names)}, 2) for "
                             f"{len(names)} group_names, found {ranges.shape}")
        for name, (first, last) in zip(names.tolist(), ranges.tolist()):
            groups[str(name)] = np.arange(first, last + 1, dtype=np.int32)  # inclusive range
    for key, name in (("rigid_vertices", "rigid"), ("fitting_vertices", "fitting")):
        if key in arrays:
            groups[name] = arrays[key].astype(np.int32)
    for name, idx in groups.items():
        if idx.size and (idx.min() < 0 or idx.max() >= v):
            raise ValueError(f"groups['{name}']: indices must be in 0..{v - 1}, "
                             f"found {int(idx.min())}..{int(idx.max())}")
    return groups


def load_face_model(path: str | None = None, *, region: str = "", max_vertices: int = 0) -> FaceModel:
    """Load a face model `.npz` (ICT-FaceKit layout) as a float32 `FaceModel`.

    Faces are the polygons split 0-1-2, 0-2-3 (the file's `triangles` order) and uv faces the
    same split of `polygon_uv`. Groups: the file's `group_names` / inclusive `group_ranges`
    (face, narrow_face, head_neck, ...) plus "rigid" (`rigid_vertices`) and "fitting"
    (`fitting_vertices`); landmarks: `landmarks68`. Deltas are converted float16 -> float32.

    Args:
        path: .npz file; None or "" for the bundled ICT-FaceKit model.
        region: "" for the whole head, or a group name: the model is restricted to that
            group's vertices (faces kept where all corners are kept, re-indexed; groups and
            landmarks re-indexed, dropping what falls outside).
        max_vertices: > 0 keeps at most that many well-spread vertices (farthest-point
            sampling on the neutral, seed 0, after `region`). The result is then a point set:
            faces and uv are dropped; groups and landmarks are re-indexed as for `region`.
    Returns:
        FaceModel in cm: neutral (V, 3), expression_deltas (53, V, 3), identity_deltas
        (40, V, 3) for ICT, all float32.
    Raises:
        FileNotFoundError: `path` does not exist.
        ValueError: the file lacks arrays (named), or `region` is unknown (the known ones
            are listed), or `max_vertices` < 0.
    """
    file = Path(path) if path else bundled_model_path()
    if max_vertices < 0:
        raise ValueError(f"max_vertices: expected >= 0 (0 = all), found {max_vertices}")
    arrays = _read_arrays(file)
    neutral = arrays["neutral"].astype(np.float32)
    if neutral.ndim != 2 or neutral.shape[1] != 3:
        raise ValueError(f"neutral: expected shape (V, 3), found {neutral.shape} in '{file}'")
    v = neutral.shape[0]
    faces = triangulate_polygons(arrays["polygons"])
    uv, uv_faces = None, None
    if "uv" in arrays and "polygon_uv" in arrays:
        uv = arrays["uv"].astype(np.float32)
        uv_faces = triangulate_polygons(arrays["polygon_uv"])
    model = FaceModel(
        neutral=neutral,
        faces=faces,
        expression_deltas=arrays["expression_deltas"].astype(np.float32),
        expression_names=[str(n) for n in arrays["expression_names"].tolist()],
        identity_deltas=arrays["identity_deltas"].astype(np.float32),
        groups=_groups_from(arrays, v),
        landmarks=arrays["landmarks68"].astype(np.int32) if "landmarks68" in arrays
        else np.zeros((0,), np.int32),
        uv=uv,
        uv_faces=uv_faces,
    )
    model.validate(f"face model '{file.name}'")
    if region:
        if region not in model.groups:
            raise ValueError(f"region: unknown group '{region}'; known: {sorted(model.groups)}")
        model = restrict_face_model(model, np.sort(np.unique(model.groups[region])))
    if max_vertices and max_vertices < model.neutral.shape[0]:
        keep = farthest_point_sampling(model.neutral, max_vertices, seed=0)
        model = restrict_face_model(model, keep, keep_faces=False)
    return model


MIN_SAMPLED_VERTICES = 10
"""Fewest vertices `LoadFaceModel(max_vertices=...)` may keep: stabilize.ModePursuit's own floor
for `max_vertices`; 3 or 4 points give rigid fits off by tens of degrees under capture noise."""


class LoadFaceModel(Node):
    """Load a linear face model (bundled ICT-FaceKit head by default), optionally one region."""

    type_name = "io.LoadFaceModel"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param("", description="face model .npz (ICT-FaceKit layout); '' = the bundled "
                                           "ICT-FaceKit model", input_file=True)
        region: str = Param("", description="vertex group to keep ('' = whole head), e.g. 'face', "
                                             "'narrow_face', 'head_neck', 'rigid', 'fitting'")
        max_vertices: int = Param(0, description="> 0: keep at most this many well-spread vertices "
                                                 "(farthest-point sampling; faces dropped); 0 or at least "
                                                 f"{MIN_SAMPLED_VERTICES}", ge=0)

        @field_validator("max_vertices")
        @classmethod
        def _enough(cls, value: int) -> int:  # refused at validation, before any fit or training
            if 0 < value < MIN_SAMPLED_VERTICES:
                raise ValueError(f"expected 0 (every vertex) or at least {MIN_SAMPLED_VERTICES} vertices, "
                                 f"found {value}: fewer are no face (rigid fits, the stabilizer and the "
                                 "dynamics networks need well-spread points)")
            return value

    model = Out(FaceModel, doc="neutral, expression and identity deltas (cm), faces, groups, landmarks")

    def input_files(self) -> list[Path]:
        """The model file; the bundled one when `path` is '' (hashed by content, not location)."""
        if not self.params.path:
            return [bundled_model_path()]
        return super().input_files()

    def run(self) -> dict[str, FaceModel]:
        try:
            model = load_face_model(self.params.path or None, region=self.params.region,
                                    max_vertices=self.params.max_vertices)
        except FileNotFoundError as err:
            raise InputError("path", f"expected an existing .npz face model, found no file "
                                     f"'{self.params.path}'") from err
        except ValueError as err:
            name, _, message = str(err).partition(": ")
            port = name if name in ("region", "max_vertices") else "path"
            raise InputError(port, message if port == name else str(err)) from err
        return {"model": model}
