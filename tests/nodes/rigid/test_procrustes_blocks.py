"""rigid.Procrustes fits a few frames at a time (`_FIT_BLOCK_FRAMES`): the same matrices as one
`fit_rigid` over the whole sequence in float64 (what version 2 computed), up to rounding.

Each frame's moments are its own BLAS products either way, but BLAS may sum in another order
for another memory alignment of the float64 copy: on this machine the two agreed bit for bit on
the whole-head bench capture and within 8e-14 here (rotation entries and cm, coordinates ~50
cm). The tolerance, 1e-11, is 100x that and far below any fit error (>1e-4 cm)."""

import numpy as np
import pytest

from nodegraph import run_node
from nodes.geometry.rigid import fit_rigid
from nodes.rigid import Procrustes
from nodes.rigid import nodes as rigid_nodes

from .test_nodes import _capture


@pytest.mark.parametrize("group", ["", "rigid"])
def test_procrustes_blocks_match_one_fit(group):
    frames = 3 * rigid_nodes._FIT_BLOCK_FRAMES + 1  # three whole blocks and a one-frame block
    mesh, _, _, rest = _capture(num_frames=frames, seed=3, noise_cm=0.05)
    out = run_node(Procrustes, {"group": group}, mesh=mesh, reference=rest)
    idx = np.arange(mesh.num_vertices) if group == "" else np.asarray(mesh.groups[group], np.int64)
    whole = fit_rigid(rest.vertices[0].astype(np.float64)[idx], mesh.vertices[:, idx].astype(np.float64)).matrix()
    assert out["rigid"].matrices.shape == (frames, 4, 4)
    np.testing.assert_allclose(out["rigid"].matrices, whole, rtol=0, atol=1e-11)
