"""An example plugin for nodegraph: `example.ScaleMesh` scales a mesh sequence about a point.

Install it next to nodegraph (`pip install -e examples/nodegraph_example`) and the node type is
available to every graph file and to `nodegraph nodes`, through the `nodegraph.nodes` entry
point declared in this package's pyproject.toml.
"""

from __future__ import annotations

import numpy as np

from nodegraph import FRAMEWISE, In, InputError, MeshSequence, Node, NodeParams, Out, Param

__all__ = ["scale_about", "ScaleMesh"]


def scale_about(vertices: np.ndarray, factor: float, centre: np.ndarray) -> np.ndarray:
    """Scale points about `centre`.

    Args:
        vertices: (F, V, 3) float32, cm.
        factor: scale factor (unitless), > 0.
        centre: (3,) cm.
    Returns:
        (F, V, 3) float32, cm: `centre + factor * (vertices - centre)`.
    """
    return (centre + np.float32(factor) * (vertices - centre)).astype(np.float32)


class ScaleMesh(Node):
    """Scale every vertex about a point (framewise)."""

    type_name = "example.ScaleMesh"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        factor: float = Param(1.0, gt=0, description="Scale factor (unitless).")
        centre_cm: list[float] = Param([0.0, 0.0, 0.0], min_length=3, max_length=3,
                                       description="Point kept fixed (x, y, z), cm.")

    mesh = In(MeshSequence, doc="Mesh sequence to scale, cm.")
    scaled = Out(MeshSequence, doc="The scaled mesh sequence, cm.")

    def run(self, mesh: MeshSequence) -> dict[str, MeshSequence]:
        if mesh.num_vertices < 1:
            raise InputError("mesh", "expected at least one vertex, found none")
        centre = np.asarray(self.params.centre_cm, np.float32)
        return {"scaled": MeshSequence(scale_about(mesh.vertices, self.params.factor, centre), mesh.faces,
                                       mesh.uv, mesh.uv_faces, dict(mesh.groups), mesh.fps)}
