"""Write a stabilization result as one NPZ: the rigid transforms and the stabilized mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import field_validator

from nodegraph import SEQUENCE, Files, In, InputError, MeshSequence, Node, NodeParams, Out, Param
from nodegraph import RigidSequence
from nodegraph.files import check_output_suffix, write_npz_atomic

__all__ = ["save_stabilization", "SaveStabilization"]


def save_stabilization(path: str, rigid: RigidSequence, mesh: MeshSequence) -> str:
    """Write `rigid` [F,4,4] (skull-to-world, `world = rigid @ skull`) and the stabilized
    `vertices` [F,V,3] (cm), plus `faces` and `fps`, to one NPZ, atomically.

    Returns:
        The file's sha256 (hex), hashed while writing (the file is not read back).
    Raises:
        InputError: frame counts differ, or `path` does not end in .npz.
    """
    if Path(path).suffix.lower() != ".npz":
        raise InputError("path", f"expected a .npz file, found '{path}'")
    if rigid.num_frames != mesh.num_frames:
        raise InputError("rigid", f"expected {mesh.num_frames} frames (as mesh), found {rigid.num_frames}")
    # np.asarray: no copy of vertices that are float32 already (210 MB on a whole-head shot)
    return write_npz_atomic(path, {"rigid": np.asarray(rigid.matrices, np.float64),
                                   "vertices": np.asarray(mesh.vertices, np.float32),
                                   "faces": mesh.faces, "fps": np.float64(mesh.fps)})


class SaveStabilization(Node):
    """Write `rigid` (skull-to-world) and the stabilized `vertices` to one NPZ file."""

    type_name = "io.SaveStabilization"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param("out/stabilized.npz", output_file=True, description="Output .npz (keys rigid, vertices, faces, fps).")

        @field_validator("path")
        @classmethod
        def _npz(cls, value: str) -> str:
            return check_output_suffix(value, (".npz",))

    rigid = In(RigidSequence, doc="Skull-to-world transforms, world = rigid @ skull.")
    mesh = In(MeshSequence, doc="Stabilized mesh (skull frame), cm.")
    files = Out(Files, doc="The written file and its sha256.")

    def run(self, rigid: RigidSequence, mesh: MeshSequence) -> dict[str, Files]:
        sha256 = save_stabilization(self.params.path, rigid, mesh)
        return {"files": Files(paths=[self.params.path], sha256=[sha256])}
