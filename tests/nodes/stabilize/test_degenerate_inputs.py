"""Degenerate captures get a clear error, never a wrong stabilization: too few vertices for a robust
fit, vertices on a line (rotation about it unobserved), an energy of fewer than 10 vertices (issue 30)."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import MeshSequence, NodeError, run_node
from nodes.geometry.rigid import rigid_fit_problem
from nodes.rigid.nodes import ICP, Procrustes
from nodes.stabilize import ModePursuit


def _capture(points: np.ndarray, frames: int = 12) -> MeshSequence:
    rng = np.random.default_rng(0)
    shift = rng.normal(0, 0.5, (frames, 1, 3))
    return MeshSequence((points[None] + shift).astype(np.float32))


def test_rigid_fit_problem_names_what_is_wrong():
    rng = np.random.default_rng(1)
    assert rigid_fit_problem(rng.normal(size=(20, 3))) == ""
    assert "at least 3 distinct" in rigid_fit_problem(np.zeros((5, 3)))
    line = np.outer(np.linspace(0, 10, 30), [1.0, 2.0, 0.5])
    assert "on a line" in rigid_fit_problem(line)
    assert rigid_fit_problem(np.concatenate([line, [[0, 0, 1.0]]])) == ""  # one point off the line: fine
    assert "at least 10" in rigid_fit_problem(rng.normal(size=(4, 3)), least=10)


@pytest.mark.parametrize("count", [3, 4, 9])
def test_mode_pursuit_refuses_a_capture_of_too_few_vertices(count):
    points = np.random.default_rng(2).normal(0, 5, (count, 3))
    with pytest.raises(NodeError, match=f"'mesh'.*at least 10 distinct vertices.*found {count}"):
        run_node(ModePursuit, mesh=_capture(points))


def test_mode_pursuit_refuses_collinear_vertices_and_a_tiny_energy():
    line = np.outer(np.linspace(-5, 5, 40), [0.0, 1.0, 0.0])
    with pytest.raises(NodeError, match="on a line"):
        run_node(ModePursuit, mesh=_capture(line))
    with pytest.raises(Exception, match="max_vertices"):
        ModePursuit.Params(max_vertices=3)


def test_rigid_fits_refuse_collinear_groups():
    line = np.outer(np.linspace(-5, 5, 20), [1.0, 0.0, 0.0])
    mesh = _capture(line, 3)
    ref = MeshSequence(line[None].astype(np.float32))
    for node in (Procrustes, ICP):
        with pytest.raises(NodeError, match="on a line"):
            run_node(node, {"group": ""}, mesh=mesh, reference=ref)
