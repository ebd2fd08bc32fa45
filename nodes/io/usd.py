"""USD mesh sequences: one UsdGeom.Mesh with time-sampled points (`.usd`, `.usda`, `.usdc`).

Used by `nodes.io.mesh` (load_mesh_sequence / save_mesh_sequence pick it by extension).

- Frame `f` is the f-th time sample of `points`; the saver writes time code = run frame.
- Topology: `faceVertexCounts` / `faceVertexIndices`, polygons fan-triangulated on reading.
- uv: primvar `st`, faceVarying and indexed when the mesh has `uv_faces`, vertex otherwise.
- Vertex groups: GeomSubsets of element type `point` (family `vertexGroups`); a name that is
  not a valid prim name is kept in the subset's custom data.
- Stage metadata: `timeCodesPerSecond` = fps, `metersPerUnit` = 0.01 (cm), up axis y.

Points are read in world space (the prim's local-to-world transform is applied) and scaled to
cm. `pxr` is imported inside the functions (it is slow to import and only USD needs it).
"""

from __future__ import annotations

import os

import numpy as np

from nodegraph import InputError, MeshSequence

from nodegraph.files import atomic_path

from ._files import check_frame_range
from .mesh_frame import MeshFrame, check_frame, fan_triangulate

__all__ = ["usd_mesh_frame_count", "load_usd_mesh", "save_usd_mesh", "USD_MODULES"]

_GROUP_FAMILY = "vertexGroups"
_GROUP_NAME_KEY = "nodegraph:groupName"


def _usd_error(err: Exception) -> str:
    lines = [line.strip() for line in str(err).strip().splitlines() if line.strip()]
    return lines[-1] if lines else type(err).__name__


def _open_usd_mesh(path: str, prim: str):
    from pxr import Tf, Usd, UsdGeom

    if not os.path.isfile(path):
        raise InputError("path", f"file '{path}': expected a USD file, found it missing")
    try:
        stage = Usd.Stage.Open(path)
    except Tf.ErrorException as err:
        raise InputError("path", f"file '{path}': expected a readable USD stage, found an unreadable "
                                 f"or truncated file ({_usd_error(err)})") from err
    if prim:
        found = stage.GetPrimAtPath(prim) if prim.startswith("/") else None
        if not found or not found.IsA(UsdGeom.Mesh):
            raise InputError("prim", f"file '{path}': expected a UsdGeom.Mesh at '{prim}', found "
                                     f"{found.GetTypeName() or 'an untyped prim' if found else 'none'}")
    else:
        found = next((p for p in stage.Traverse() if p.IsA(UsdGeom.Mesh)), None)
        if found is None:
            raise InputError("path", f"file '{path}': expected a UsdGeom.Mesh prim, found none")
    return stage, UsdGeom.Mesh(found)


def _usd_times(mesh) -> list[float]:
    from pxr import Usd

    times = list(mesh.GetPointsAttr().GetTimeSamples())
    return times if times else [Usd.TimeCode.Default()]


def _usd_topology(mesh, time) -> tuple[np.ndarray, np.ndarray]:
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    indices = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if counts.sum() != indices.size:
        raise ValueError(f"faceVertexCounts sum to {int(counts.sum())}, faceVertexIndices has "
                         f"{indices.size}")
    corners = fan_triangulate(counts)
    return indices[corners].astype(np.int32), corners


def _usd_points(mesh, time, scale: float) -> np.ndarray:
    from pxr import UsdGeom

    points = np.asarray(mesh.GetPointsAttr().Get(time), dtype=np.float64).reshape(-1, 3)
    xf = np.asarray(UsdGeom.Xformable(mesh.GetPrim()).ComputeLocalToWorldTransform(time))
    if not np.array_equal(xf, np.eye(4)):
        points = points @ xf[:3, :3] + xf[3, :3]  # USD matrices act on row vectors
    return (points * scale).astype(np.float32)


def _usd_uv(mesh, corners: np.ndarray, nv: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    from pxr import UsdGeom

    primvar = UsdGeom.PrimvarsAPI(mesh.GetPrim()).GetPrimvar("st")
    if not primvar or not primvar.HasValue():
        return None, None
    values = np.asarray(primvar.Get(), dtype=np.float32).reshape(-1, 2)
    interp = primvar.GetInterpolation()
    if interp in (UsdGeom.Tokens.vertex, UsdGeom.Tokens.varying):
        flat = np.asarray(primvar.ComputeFlattened(), dtype=np.float32).reshape(-1, 2)
        if len(flat) != nv:
            raise ValueError(f"primvar 'st' ({interp}) has {len(flat)} values for {nv} points")
        return flat, None
    if interp == UsdGeom.Tokens.faceVarying:
        indices = primvar.GetIndices() if primvar.IsIndexed() else None
        corner_uv = np.asarray(indices, np.int64) if indices is not None else np.arange(len(values))
        return values, corner_uv[corners].astype(np.int32)
    return None, None  # constant/uniform uv cannot be expressed by a MeshSequence


def _usd_groups(mesh) -> dict[str, np.ndarray]:
    from pxr import UsdGeom

    groups = {}
    for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh):
        if subset.GetElementTypeAttr().Get() != UsdGeom.Tokens.point:
            continue
        prim = subset.GetPrim()
        name = prim.GetCustomDataByKey(_GROUP_NAME_KEY) or prim.GetName()
        groups[str(name)] = np.asarray(subset.GetIndicesAttr().Get() or [], dtype=np.int64)
    return groups


def usd_mesh_frame_count(path: str, prim: str = "") -> int:
    """Return the number of time samples of the Mesh's points (1 when it has none)."""
    _, mesh = _open_usd_mesh(path, prim)
    return len(_usd_times(mesh))


def load_usd_mesh(path: str, frames: range, prim: str = "", fps: float = 30.0) -> MeshSequence:
    """Read time samples `frames` of a USD Mesh (see the module docstring), in world space, cm.

    Args:
        path: .usd / .usda / .usdc file.
        frames: run frames to read (frame f = the f-th time sample of `points`).
        prim: Mesh prim path; "" = the first Mesh of the stage.
        fps: frames per second when the stage has no `timeCodesPerSecond`.
    Raises:
        InputError: naming the file (and frame): missing or unreadable file, no Mesh at `prim`,
            frames out of range, a broken topology, non-finite points, topology changing over time.
    """
    from pxr import UsdGeom

    stage, mesh = _open_usd_mesh(path, prim)
    times = _usd_times(mesh)
    check_frame_range(frames, len(times), path)
    scale = UsdGeom.GetStageMetersPerUnit(stage) / 0.01
    if stage.HasAuthoredMetadata("timeCodesPerSecond"):
        fps = float(stage.GetTimeCodesPerSecond())
    where = f"file '{path}', prim '{mesh.GetPath()}'"
    try:
        faces, corners = _usd_topology(mesh, times[0])
        ref = MeshFrame(_usd_points(mesh, times[0], scale), faces)
        varying = (mesh.GetFaceVertexIndicesAttr().GetNumTimeSamples() > 1
                   or mesh.GetFaceVertexCountsAttr().GetNumTimeSamples() > 1)
        uv, uv_faces = _usd_uv(mesh, corners, len(ref.vertices))
    except (ValueError, TypeError) as err:
        raise InputError("path", f"frame 0 ({where}): expected a valid mesh, found {err}") from err
    out = np.empty((len(frames), len(ref.vertices), 3), np.float32)
    for i, f in enumerate(frames):
        vertices = ref.vertices if f == 0 else _usd_points(mesh, times[f], scale)
        try:
            frame_faces = _usd_topology(mesh, times[f])[0] if varying and f else None
        except ValueError as err:
            raise InputError("path", f"frame {f} ({where}): expected a valid mesh, found {err}") from err
        check_frame(f, path, vertices, frame_faces, ref if f else None, path)
        out[i] = vertices
    return MeshSequence(vertices=out, faces=faces, uv=uv, uv_faces=uv_faces,
                        groups=_usd_groups(mesh), fps=fps)


USD_MODULES = ("pxr.Sdf", "pxr.Tf", "pxr.Usd", "pxr.UsdGeom", "pxr.Vt")
"""What `save_usd_mesh` imports (`Node.import_first` of io.SaveMeshSequence for a .usd path)."""


def save_usd_mesh(path: str, mesh: MeshSequence, times: range, prim: str = "/mesh") -> None:
    """Write `mesh` as a USD Mesh at `prim`, frame i at time code `times[i]`, atomically.

    Raises:
        InputError: (param "prim") when `prim` is not an absolute prim path.
    """
    from pxr import Sdf, Tf, Usd, UsdGeom, Vt

    if not (Sdf.Path.IsValidPathString(prim) and Sdf.Path(prim).IsAbsolutePath()
            and Sdf.Path(prim).IsPrimPath()):
        raise InputError("prim", f"expected an absolute prim path such as '/mesh', found '{prim}'")
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    stage.SetTimeCodesPerSecond(float(mesh.fps))
    stage.SetFramesPerSecond(float(mesh.fps))
    if len(times):
        stage.SetStartTimeCode(times[0])
        stage.SetEndTimeCode(times[-1])
    geom = UsdGeom.Mesh.Define(stage, prim)
    stage.SetDefaultPrim(stage.GetPrimAtPath(Sdf.Path(prim).GetPrefixes()[0]))
    faces = np.asarray(mesh.faces, np.int32)
    geom.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1)))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    points, extent = geom.CreatePointsAttr(), geom.CreateExtentAttr()
    vertices = np.asarray(mesh.vertices, np.float32)
    for i, t in enumerate(times):
        points.Set(Vt.Vec3fArray.FromNumpy(vertices[i]), t)
        if vertices.shape[1]:
            box = np.stack([vertices[i].min(axis=0), vertices[i].max(axis=0)])
            extent.Set(Vt.Vec3fArray.FromNumpy(box), t)
    if mesh.uv is not None:
        interp = UsdGeom.Tokens.vertex if mesh.uv_faces is None else UsdGeom.Tokens.faceVarying
        primvar = UsdGeom.PrimvarsAPI(geom.GetPrim()).CreatePrimvar(
            "st", Sdf.ValueTypeNames.TexCoord2fArray, interp)
        primvar.Set(Vt.Vec2fArray.FromNumpy(np.asarray(mesh.uv, np.float32)))
        if mesh.uv_faces is not None:
            primvar.SetIndices(Vt.IntArray.FromNumpy(np.asarray(mesh.uv_faces, np.int32).reshape(-1)))
    used: set[str] = set()
    for name, idx in mesh.groups.items():
        child = Tf.MakeValidIdentifier(name)
        while child in used:
            child += "_"
        used.add(child)
        subset = UsdGeom.Subset.Define(stage, geom.GetPath().AppendChild(child))
        subset.CreateElementTypeAttr(UsdGeom.Tokens.point)
        subset.CreateFamilyNameAttr(_GROUP_FAMILY)
        subset.CreateIndicesAttr(Vt.IntArray.FromNumpy(np.asarray(idx, np.int32)))
        if child != name:
            subset.GetPrim().SetCustomDataByKey(_GROUP_NAME_KEY, name)
    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(os.fspath(tmp)):
            raise OSError(f"could not write USD file '{path}'")
