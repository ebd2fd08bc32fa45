"""Rigid-stabilization baselines: three-point, Procrustes on a rigid region, robust ICP.

Every baseline estimates, per frame f, the skull-to-world transform `M_f` with the skull frame
taken as that of a one-frame reference mesh: `M_f @ reference ~ mesh_f`. Outputs:
`rigid` (RigidSequence, `x_world = M_f @ x_skull`) and `stabilized` (`M_f^-1 mesh_f` for all
vertices, topology, groups, uv and fps carried over). The baselines are framewise: each frame
is solved alone, so any chunk of frames gives the same result. `rigid.ReferenceFrame` picks
the reference frame out of a sequence once, so that every chunk sees the same reference.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from pydantic import field_validator

import numpy as np

from nodegraph import (FRAMEWISE, SEQUENCE, In, Index, InputError, MeshSequence, Node, NodeParams, Out,
                       Param, RigidSequence)

from ..geometry.rigid import fit_rigid, invert_rigid, rigid_fit_problem, rigid_matrix, stabilize_vertices
from ..geometry.sampling import farthest_point_sampling

__all__ = [
    "triangle_quality", "three_point_frames", "spread_triple",
    "ReferenceFrame", "ThreePoint", "Procrustes", "ICP",
]


# -- pure functions ----------------------------------------------------------------------
def triangle_quality(points: np.ndarray) -> np.ndarray:
    """Return `|(b - a) x (c - a)| / max_edge^2` of point triples (scale-free spread measure).

    Twice the area over the squared longest edge: 0.866 for an equilateral triangle, 0 for
    collinear or coincident points.

    Args:
        points: (..., 3, 3) float, cm: the three points (rows a, b, c).
    Returns:
        (...) float64 in [0, 0.866].
    """
    p = np.asarray(points, np.float64)
    if p.ndim < 2 or p.shape[-2:] != (3, 3):
        raise ValueError(f"points: expected shape (..., 3, 3), found {p.shape}")
    a, b, c = p[..., 0, :], p[..., 1, :], p[..., 2, :]
    area2 = np.linalg.norm(np.cross(b - a, c - a), axis=-1)
    longest = (np.stack([b - a, c - a, c - b], -2) ** 2).sum(-1).max(-1)
    return np.divide(area2, longest, out=np.zeros_like(area2), where=longest > 0)


def three_point_frames(points: np.ndarray, *, min_quality: float = 1e-3) -> np.ndarray:
    """Return the orthonormal frames spanned by point triples, as local-to-world matrices.

    For a triple (a, b, c): origin = centroid (a + b + c) / 3, `e1 = (b - a) / |b - a|`,
    `e3 = (b - a) x (c - a)` normalized, `e2 = e3 x e1`; the matrix is `[[e1 e2 e3, o], [0, 1]]`.
    The rigid motion between two poses of the same triple is `F_2 @ inv(F_1)`.

    Args:
        points: (..., 3, 3) float, cm: the three points (rows a, b, c).
        min_quality: smallest accepted `triangle_quality` (0.866 for an equilateral
            triangle, 0 when collinear or coincident).
    Returns:
        (..., 4, 4) float64.
    Raises:
        ValueError: naming the first batch index whose triple is degenerate.

    Example:
        >>> np.round(three_point_frames(np.array([[0., 0, 0], [3, 0, 0], [0, 3, 0]]))[:3, 3], 6)
        array([1., 1., 0.])
    """
    quality = triangle_quality(points)
    p = np.asarray(points, np.float64)
    a, b, c = p[..., 0, :], p[..., 1, :], p[..., 2, :]
    ab = b - a
    normal = np.cross(ab, c - a)
    area2 = np.linalg.norm(normal, axis=-1)
    ok = quality >= min_quality
    if not ok.all():
        index = np.unravel_index(int(np.argmin(ok)), ok.shape)
        raise ValueError(f"points: expected three well-spread points, found a degenerate "
                         f"(collinear or coincident) triple at batch index "
                         f"{tuple(int(i) for i in index)} with quality "
                         f"{float(quality[index]):.2e} < {min_quality:g}")
    e1 = ab / np.linalg.norm(ab, axis=-1, keepdims=True)
    e3 = normal / area2[..., None]
    e2 = np.cross(e3, e1)
    return rigid_matrix(np.stack([e1, e2, e3], -1), p.mean(-2))


def spread_triple(points: np.ndarray) -> tuple[int, int, int]:
    """Choose three well-spread points deterministically (indices into `points`).

    a = farthest from the centroid, b = farthest from a, c = farthest from the line ab
    (first index on ties).

    Args:
        points: (N, 3) float, cm, N >= 3.
    Returns:
        (a, b, c) indices into the rows of `points`.
    """
    p = np.asarray(points, np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 3:
        raise ValueError(f"points: expected shape (N, 3) with N >= 3, found {p.shape}")
    a = int(np.argmax(((p - p.mean(0)) ** 2).sum(1)))
    b = int(np.argmax(((p - p[a]) ** 2).sum(1)))
    direction = p[b] - p[a]
    direction = direction / max(float(np.linalg.norm(direction)), 1e-300)
    offset = p - p[a]
    off_line = offset - (offset @ direction)[:, None] * direction
    c = int(np.argmax((off_line ** 2).sum(1)))
    return a, b, c


# -- shared node helpers -------------------------------------------------------------------
def _group(mesh: MeshSequence, name: str, param: str = "group") -> np.ndarray:
    """Vertex indices of group `name` of `mesh` ("" = all vertices)."""
    if not name:
        return np.arange(mesh.num_vertices)
    if name not in mesh.groups:
        raise InputError(param, f"expected a vertex group '{name}' in the mesh, found groups "
                                f"{sorted(mesh.groups)}")
    idx = np.asarray(mesh.groups[name], np.int64)
    if idx.size < 3:
        raise InputError(param, f"expected at least 3 vertices in group '{name}', found {idx.size}")
    return idx


def _check_fit_points(mesh: MeshSequence, idx: np.ndarray, param: str = "group") -> None:
    """Refuse vertices that cannot carry a rigid fit (fewer than 3 distinct, or on a line), in frame 0."""
    problem = rigid_fit_problem(mesh.vertices[0, idx] if mesh.num_frames else np.zeros((0, 3)))
    if problem:
        raise InputError(param if len(idx) < mesh.num_vertices else "mesh", problem)


def _check_reference(reference: MeshSequence, mesh: MeshSequence) -> np.ndarray:
    """Return the reference's (V, 3) float64 vertices after checking it fits `mesh`."""
    if reference.num_frames != 1:
        raise InputError("reference", f"expected a one-frame mesh (e.g. from "
                                      f"rigid.ReferenceFrame), found {reference.num_frames} frames")
    if reference.num_vertices != mesh.num_vertices:
        raise InputError("reference", f"expected {mesh.num_vertices} vertices (as 'mesh'), found "
                                      f"{reference.num_vertices}")
    return reference.vertices[0].astype(np.float64)


def _outputs(node: Node, mesh: MeshSequence, matrices: np.ndarray) -> dict:
    """Build the `rigid` and `stabilized` outputs from skull-to-world matrices (F, 4, 4); the
    stabilized mesh only when an edge reads it (`Node.skips_unread_outputs`).

    The stabilized mesh is multiplied in float32 (`stabilize_vertices`: a few ulp, ~1e-6 cm at
    head scale, from the float64 product; no (F, V, 3) float64 temporaries): v2 of the nodes."""
    out: dict = {"rigid": RigidSequence(np.ascontiguousarray(matrices, np.float64))}
    if node.wants("stabilized"):
        stabilized = stabilize_vertices(mesh.vertices, np.asarray(matrices, np.float64))
        out["stabilized"] = dataclasses.replace(mesh, vertices=stabilized)
    return out


_FIT_BLOCK_FRAMES = 4  # frames per fit_rigid call of Procrustes (see Procrustes.run)
_MIN_QUALITY = 1e-3  # smallest accepted triangle_quality of a three-point triple
_MESH_DOC = "Captured world-space mesh sequence (vertices in correspondence), cm."
_REF_DOC = "One-frame reference mesh defining the skull frame (from rigid.ReferenceFrame)."
_RIGID_DOC = "Skull-to-world transforms M_f (x_world = M_f @ x_skull), M_f @ reference ~ mesh_f."
_STAB_DOC = "Stabilized mesh M_f^-1 mesh_f (skull frame), cm."


# -- nodes ---------------------------------------------------------------------------------
class ReferenceFrame(Node):
    """Pick one frame of a mesh sequence as the (unchunked) reference of the skull frame."""

    type_name = "rigid.ReferenceFrame"
    version = 2
    kind = SEQUENCE

    class Params(NodeParams):
        frame: int | None = Param(None, ge=0, description="Absolute index of the reference frame (frames); "
                                  "None = the run's first frame, so a run of any frames a:b has its "
                                  "reference. A set frame must lie in the run's frames.")

    mesh = In(MeshSequence, doc="Mesh sequence to pick the frame from.")
    reference = Out(MeshSequence, per_frame=False, doc="The picked frame (1 frame).")

    def run(self, mesh: MeshSequence) -> dict:
        frame = self.frames.start if self.params.frame is None else self.params.frame
        if frame not in self.frames:
            raise InputError("frame", f"expected a frame in {self.frames.start}.."
                                      f"{self.frames.stop - 1} (the run's frames; or null for the "
                                      f"run's first frame), found {frame}")
        index = frame - self.frames.start
        one = mesh.slice_frames(index, index + 1)
        return {"reference": dataclasses.replace(one, vertices=one.vertices.copy())}


class ThreePoint(Node):
    """Classic three-point stabilization: the rigid motion of the frame three points span.

    `M_f = F(p_f) @ inv(F(p_ref))` with `F` the orthonormal frame of a point triple (origin at
    its centroid, see `three_point_frames`). Exact for rigid motion of the three points;
    noise on them goes straight into the rotation, with a lever arm of the triangle's size.
    """

    type_name = "rigid.ThreePoint"
    version = 2  # v2: stabilized multiplied in float32 (see _outputs)
    kind = FRAMEWISE
    skips_unread_outputs = True  # the stabilized mesh only when read (see _outputs)

    class Params(NodeParams):
        vertices: list[Index] = Param([], description="Three distinct vertex indices; empty = three "
                                                      "well-spread vertices of the 'rigid' group "
                                                      "(chosen on the reference).")

        @field_validator("vertices")
        @classmethod
        def _three_distinct(cls, value: list[int]) -> list[int]:
            if value and (len(value) != 3 or len(set(value)) != 3):
                raise ValueError(f"expected three distinct vertex indices (or [] to choose), found {value}")
            return value

    mesh = In(MeshSequence, doc=_MESH_DOC)
    reference = In(MeshSequence, per_frame=False, doc=_REF_DOC)
    rigid = Out(RigidSequence, doc=_RIGID_DOC)
    stabilized = Out(MeshSequence, doc=_STAB_DOC)

    def _triple(self, mesh: MeshSequence, ref: np.ndarray) -> np.ndarray:
        chosen = list(self.params.vertices)
        v = mesh.num_vertices
        if not chosen:
            if "rigid" not in mesh.groups:
                raise InputError("vertices", f"is empty, so three vertices of the mesh's 'rigid' "
                                             f"group are used, but the mesh has groups "
                                             f"{sorted(mesh.groups)}; set 'vertices' or add "
                                             f"the group")
            group = np.asarray(mesh.groups["rigid"], np.int64)
            if group.size < 3:
                raise InputError("vertices", f"expected at least 3 vertices in the 'rigid' group, "
                                             f"found {group.size}")
            return group[list(spread_triple(ref[group]))]
        if len(chosen) != 3 or len(set(chosen)) != 3:
            raise InputError("vertices", f"expected three distinct vertex indices, found {chosen}")
        if min(chosen) < 0 or max(chosen) >= v:
            raise InputError("vertices", f"expected indices in 0..{v - 1}, found {chosen}")
        return np.asarray(chosen, np.int64)

    def run(self, mesh: MeshSequence, reference: MeshSequence) -> dict:
        ref = _check_reference(reference, mesh)
        idx = self._triple(mesh, ref)
        try:
            ref_frame = three_point_frames(ref[idx], min_quality=_MIN_QUALITY)
        except ValueError as err:
            raise InputError("vertices",
                             f"vertices {idx.tolist()} on the reference: {err}") from err
        triples = mesh.vertices[:, idx].astype(np.float64)
        quality = triangle_quality(triples)
        bad = np.flatnonzero(~(quality >= _MIN_QUALITY))
        if bad.size:
            raise InputError("mesh", f"expected vertices {idx.tolist()} to span a triangle in "
                                     f"every frame, found them degenerate (quality "
                                     f"{quality[bad[0]]:.2e} < {_MIN_QUALITY:g}) at frame "
                                     f"{self.frames.start + int(bad[0])}")
        frames = three_point_frames(triples, min_quality=_MIN_QUALITY)
        return _outputs(self, mesh, frames @ invert_rigid(ref_frame))


class Procrustes(Node):
    """Least-squares rigid fit (Kabsch) of the reference's region to each frame's region.

    Minimises `sum_{i in group} |R ref_i + t - mesh_fi|^2` per frame (uniform weights). There
    is no `with_scale` option: the best rotation does not depend on a scale and the best rigid
    translation for it moves the centroids together, so a scale could not change a rigid
    output (see `nodes.geometry.rigid.fit_rigid` for similarity fits).
    """

    type_name = "rigid.Procrustes"
    version = 2  # v2: stabilized multiplied in float32 (see _outputs)
    kind = FRAMEWISE
    skips_unread_outputs = True  # the stabilized mesh only when read (see _outputs)

    class Params(NodeParams):
        group: str = Param("rigid", description="Vertex group fitted; \"\" = all vertices.")

    mesh = In(MeshSequence, doc=_MESH_DOC)
    reference = In(MeshSequence, per_frame=False, doc=_REF_DOC)
    rigid = Out(RigidSequence, doc=_RIGID_DOC)
    stabilized = Out(MeshSequence, doc=_STAB_DOC)

    def run(self, mesh: MeshSequence, reference: MeshSequence) -> dict:
        ref = _check_reference(reference, mesh)
        idx = _group(mesh, self.params.group)
        _check_fit_points(reference, idx)
        src = ref[idx]
        # Fitted a few frames at a time: each block's float64 copy of the points stays small
        # and is reused from the allocator's cache, where one (F, N, 3) float64 copy of a
        # 64-frame whole-head chunk (41 MB) cost 3-4x the fit in fresh pages. Each frame's
        # fit is its own batch element: the same result, but for BLAS rounding that may follow
        # the copy's memory alignment (bit-identical on the bench capture, 1e-13 in tests).
        matrices = np.empty((mesh.num_frames, 4, 4), np.float64)
        for a in range(0, mesh.num_frames, _FIT_BLOCK_FRAMES):
            b = min(mesh.num_frames, a + _FIT_BLOCK_FRAMES)
            points = mesh.vertices[a:b] if self.params.group == "" else mesh.vertices[a:b, idx]  # no gather for all
            matrices[a:b] = fit_rigid(src, points.astype(np.float64)).matrix()
        return _outputs(self, mesh, matrices)


class ICP(Node):
    """Robust point-to-plane ICP of each frame's region onto the reference surface.

    No correspondences are used: each frame's `group` vertices are matched to their nearest
    reference vertices (`target_group`, a k-d tree built once per chunk) and the point-to-plane
    distances along the reference's area-weighted vertex normals are minimised under a robust
    loss (IRLS, see `nodes.rigid.icp.robust_icp`), starting from the translation that moves the
    frame's region centroid onto the reference's. When the reference has no faces (a point
    cloud) there are no normals and the distance is point-to-point instead.
    """

    type_name = "rigid.ICP"
    version = 2  # v2: stabilized multiplied in float32 (see _outputs)
    kind = FRAMEWISE
    skips_unread_outputs = True  # the stabilized mesh only when read (see _outputs)

    class Params(NodeParams):
        group: str = Param("rigid", description="Vertex group of each frame that is aligned; "
                                                "\"\" = all vertices.")
        target_group: str = Param("", description="Reference vertex group aligned to; \"\" = the "
                                                  "whole reference surface.")
        iterations: int = Param(40, ge=0, description="Maximum ICP iterations per frame.")
        robust_scale_cm: float = Param(0.1, gt=0, description="Robust loss scale (cm): residuals "
                                                              "well above it are down-weighted.")
        loss: Literal["geman_mcclure", "huber", "l2"] = Param(
            "geman_mcclure", description="Robust loss of the residuals.")
        tolerance_cm: float = Param(1e-5, ge=0, description="Stop a frame when an iteration moves "
                                                            "no point more than this (cm).")
        max_points: int = Param(1000, ge=0, description="> 0: align at most this many well-spread "
                                "vertices of `group` (farthest-point sampling on the reference, "
                                "deterministic); 0 = all of them.")
        workers: int = Param(1, affects_output=False, description="Threads for nearest-neighbour "
                                                                  "queries (-1 = all cores).")

    mesh = In(MeshSequence, doc=_MESH_DOC)
    reference = In(MeshSequence, per_frame=False, doc=_REF_DOC)
    rigid = Out(RigidSequence, doc=_RIGID_DOC)
    stabilized = Out(MeshSequence, doc=_STAB_DOC)

    def run(self, mesh: MeshSequence, reference: MeshSequence) -> dict:
        from scipy.spatial import cKDTree

        from ..geometry.mesh import vertex_normals
        from .icp import robust_icp

        p = self.params
        ref = _check_reference(reference, mesh)
        idx = _group(mesh, p.group)
        _check_fit_points(reference, idx)
        if p.max_points and len(idx) > p.max_points:
            idx = idx[farthest_point_sampling(ref[idx], p.max_points)]
        target_idx = _group(reference, p.target_group, "target_group")
        points = mesh.vertices[:, idx].astype(np.float64)
        target = ref[target_idx]
        normals = None
        if reference.faces.size:
            normals = vertex_normals(ref, reference.faces)[target_idx]
        shift = ref[idx].mean(0) - points.mean(1)
        init = rigid_matrix(np.broadcast_to(np.eye(3), (len(points), 3, 3)), shift)
        result = robust_icp(points, target, normals, init, iterations=p.iterations,
                            robust_scale_cm=p.robust_scale_cm, loss=p.loss,
                            tolerance_cm=p.tolerance_cm, tree=cKDTree(target),
                            workers=p.workers, progress=self.progress)
        return _outputs(self, mesh, invert_rigid(result.matrices))
