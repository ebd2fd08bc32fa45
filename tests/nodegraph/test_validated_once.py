"""A port value a node produced and checked is not checked again as its readers' input
(`nodegraph.node._VALIDATED`); values built elsewhere are checked as inputs every time."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import MeshSequence, NodeError, run_node
from nodes.rigid.nodes import ReferenceFrame


def _mesh(frames: int = 3) -> MeshSequence:
    rng = np.random.default_rng(0)
    return MeshSequence(vertices=rng.normal(size=(frames, 12, 3)).astype(np.float32),
                        faces=np.array([[0, 1, 2]], np.int32))


def test_a_produced_value_is_validated_once(monkeypatch):
    calls = []
    original = MeshSequence.validate

    def counting(self, where=""):
        calls.append(id(self))
        return original(self, where)

    monkeypatch.setattr(MeshSequence, "validate", counting)
    mesh = _mesh()
    reference = run_node(ReferenceFrame, {}, mesh=mesh)["reference"]
    assert calls.count(id(mesh)) == 1 and calls.count(id(reference)) == 1  # input, output
    run_node(ReferenceFrame, {}, mesh=reference)
    assert calls.count(id(reference)) == 1  # produced and checked: not again as an input
    run_node(ReferenceFrame, {}, mesh=mesh)
    assert calls.count(id(mesh)) == 2  # built here: checked as an input each time


def test_a_bad_value_built_elsewhere_is_still_refused():
    mesh = _mesh()
    run_node(ReferenceFrame, {}, mesh=mesh)
    mesh.vertices[1, 4, 0] = np.nan
    with pytest.raises(NodeError, match="non-finite"):
        run_node(ReferenceFrame, {}, mesh=mesh)
