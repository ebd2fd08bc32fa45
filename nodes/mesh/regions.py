"""Work on one part of a mesh: `mesh.SelectRegion` cuts a vertex group out of a mesh sequence
(the topology `io.LoadFaceModel(region=...)` gives the model), `mesh.ReplaceRegion` writes a
processed region back into the whole mesh.

Typical use: a network trained on the face region (dynamics) cleans the face of a whole-head
capture, and the whole head goes on to a renderer that needs eyes, teeth and the back of the
head.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from nodegraph import FRAMEWISE, In, InputError, MeshSequence, Node, NodeParams, Out, Param

__all__ = ["region_vertices", "restrict_faces", "remap_indices", "SelectRegion", "ReplaceRegion"]


def region_vertices(mesh: MeshSequence, group: str, port: str = "mesh") -> np.ndarray:
    """The sorted, unique vertex indices of `group` in `mesh` (the region's vertex order).

    Raises:
        InputError: on `port` when the mesh has no such group (the known ones listed).
    """
    if group not in mesh.groups:
        raise InputError(port, f"expected a mesh with a vertex group '{group}', found groups "
                               f"{sorted(mesh.groups) or 'none'}")
    keep = np.unique(np.asarray(mesh.groups[group], np.int64))
    if keep.size == 0:
        raise InputError(port, f"expected a non-empty vertex group '{group}', found it empty")
    return keep


def restrict_faces(faces: np.ndarray, keep: np.ndarray, num_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Faces whose three corners are all kept, re-indexed to the kept vertices.

    Args:
        faces: (T, 3) int vertex indices.
        keep: (N,) sorted unique kept vertex indices.
        num_vertices: V, the vertex count `faces` index.
    Returns:
        (faces (T', 3) int32 into 0..N-1, inside (T,) bool: the faces kept,
        old_to_new (V,) int64: new index of each old vertex, -1 where dropped).
    """
    old_to_new = np.full(num_vertices, -1, np.int64)
    old_to_new[keep] = np.arange(len(keep))
    if not faces.size:
        return np.zeros((0, 3), np.int32), np.zeros(len(faces), bool), old_to_new
    inside = (old_to_new[faces] >= 0).all(axis=1)
    return old_to_new[faces[inside]].astype(np.int32), inside, old_to_new


def remap_indices(old_to_new: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """Map old vertex indices to new ones (`restrict_faces`' old_to_new), dropping those not kept
    (order preserved); int32."""
    mapped = old_to_new[indices]
    return mapped[mapped >= 0].astype(np.int32)


def select_region(mesh: MeshSequence, keep: np.ndarray) -> MeshSequence:
    """The sub-mesh of vertices `keep`: faces, uv and groups restricted and re-indexed."""
    faces, inside, old_to_new = restrict_faces(mesh.faces, keep, mesh.num_vertices)
    uv, uv_faces = mesh.uv, mesh.uv_faces
    if uv is not None and uv_faces is None:
        uv = uv[keep]
    elif uv_faces is not None:
        uv_faces = uv_faces[inside]
    groups = {name: remap_indices(old_to_new, np.asarray(idx, np.int64)) for name, idx in mesh.groups.items()}
    return dataclasses.replace(mesh, vertices=np.ascontiguousarray(mesh.vertices[:, keep]), faces=faces, uv=uv,
                               uv_faces=uv_faces, groups=groups)


class SelectRegion(Node):
    """Cut a vertex group out of a mesh sequence (the vertex order of `io.LoadFaceModel(region=...)`)."""

    type_name = "mesh.SelectRegion"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        group: str = Param("face", description="Vertex group of the mesh to keep (its vertices in ascending "
                           "index order; faces kept where all three corners are kept).")

    mesh = In(MeshSequence, doc="The whole mesh sequence, with its vertex groups.")
    region = Out(MeshSequence, doc="The group's vertices, faces, uv and re-indexed groups.")

    def run(self, mesh: MeshSequence) -> dict[str, MeshSequence]:
        return {"region": select_region(mesh, region_vertices(mesh, self.params.group))}


class ReplaceRegion(Node):
    """Write a processed region (from `mesh.SelectRegion`) back into the whole mesh sequence."""

    type_name = "mesh.ReplaceRegion"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        group: str = Param("face", description="Vertex group of `mesh` that `region` holds, in ascending index "
                           "order.")

    mesh = In(MeshSequence, doc="The whole mesh sequence (the vertices outside the group are kept).")
    region = In(MeshSequence, doc="The group's new vertices, same frames.")
    replaced = Out(MeshSequence, doc="`mesh` with the group's vertices taken from `region`.")

    def run(self, mesh: MeshSequence, region: MeshSequence) -> dict[str, MeshSequence]:
        keep = region_vertices(mesh, self.params.group)
        if region.num_vertices != len(keep):
            raise InputError("region", f"expected {len(keep)} vertices (group '{self.params.group}' of the mesh), "
                                       f"found {region.num_vertices}")
        if region.num_frames != mesh.num_frames:
            raise InputError("region", f"expected {mesh.num_frames} frames (as the mesh), found {region.num_frames}")
        vertices = mesh.vertices.copy()
        vertices[:, keep] = region.vertices
        return {"replaced": dataclasses.replace(mesh, vertices=vertices)}
