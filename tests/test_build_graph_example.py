"""examples/build_graph.py, the README's programmatic way of building a graph: it runs as a script,
writes its files, and the graph it saves loads, validates and takes its exposed parameter."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from nodegraph import Graph

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "build_graph.py"


def test_build_graph_example_runs_and_saves_a_valid_graph(tmp_path):
    from nodes.export.livelink import live_link_rows, live_link_text
    from nodes.io.arkit import head_rotation

    take = tmp_path / "take.csv"
    arkit = np.random.default_rng(0).uniform(0, 1, (40, 52))
    take.write_text(live_link_text(live_link_rows(arkit, head_rotation(np.zeros((40, 3))), 30.0)))
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(EXAMPLE), str(take), str(out)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (out / "take.glb").stat().st_size > 0 and (out / "take.usdc").stat().st_size > 0
    graph = Graph.load(out / "take_to_gltf.json")
    assert graph.validate() == [] and set(graph.parameters) == {"take"}
    graph.apply({"take": str(take)})
