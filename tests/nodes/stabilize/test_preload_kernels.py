"""`nodes.stabilize.preload_kernels` (in `stabilize.ModePursuit.preload`) loads each numba kernel
with the argument types the node's run passes: after the preload, a run adds no specialisation
(one signature per kernel), so no kernel is loaded or compiled again on the run's critical path.
A fresh interpreter, as in `nodegraph run`: other tests may have called the kernels already."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from nodes.stabilize.node import ModePursuit

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = r"""
import json
import numpy as np
from scipy.spatial.transform import Rotation

import nodes.stabilize.preload_kernels
from nodes.stabilize import robust_kernels as k

names = ("irls_moments", "window_mean_square", "local_window_still", "gather_normalized")
before = {n: len(getattr(k, n).signatures) for n in names}

from nodegraph import MeshSequence, run_node
from nodes.stabilize.node import ModePursuit

rng = np.random.default_rng(0)
rest = rng.normal(0, 8, (400, 3))
frames = 60
rot = Rotation.from_rotvec(np.deg2rad(5) * np.sin(np.arange(frames) / 9)[:, None] * [[0.3, 1, 0.2]])
world = np.stack([r.apply(rest) for r in rot]) + rng.normal(0, 0.01, (frames, 400, 3))
mesh = MeshSequence(world.astype(np.float32), np.zeros((0, 3), np.int32), fps=30.0)
run_node(ModePursuit, {}, mesh=mesh)
after = {n: len(getattr(k, n).signatures) for n in names}
print(json.dumps({"before": before, "after": after}))
"""


def test_preload_names_the_kernel_module():
    assert "nodes.stabilize.preload_kernels" in ModePursuit.preload


def test_preloaded_kernels_are_the_ones_a_run_calls():
    proc = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    counts = json.loads(proc.stdout.strip().splitlines()[-1])
    assert counts["before"] == {"irls_moments": 1, "window_mean_square": 1, "local_window_still": 1,
                                "gather_normalized": 1}
    assert counts["after"] == counts["before"]
