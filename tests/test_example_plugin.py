"""The example plugin in examples/nodegraph_example is found through its entry point and runs."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "nodegraph_example"


def test_example_plugin_registers_through_its_entry_point(tmp_path):
    meta = tomllib.loads((EXAMPLE / "pyproject.toml").read_text())
    entry = meta["project"]["entry-points"]["nodegraph.nodes"]
    # What `pip install` would leave: the package on the path and a dist-info with its entry points.
    site = tmp_path / "site"
    dist = site / "nodegraph_example-0.1.0.dist-info"
    dist.mkdir(parents=True)
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: nodegraph-example\nVersion: 0.1.0\n")
    (dist / "entry_points.txt").write_text(
        "[nodegraph.nodes]\n" + "".join(f"{name} = {target}\n" for name, target in entry.items()))
    probe = textwrap.dedent('''
        import json, sys
        import numpy as np
        from nodegraph import Graph, MeshSequence, registry, run_node
        cls = registry.get("example.ScaleMesh")
        mesh = MeshSequence(np.ones((2, 3, 3), np.float32), np.array([[0, 1, 2]], np.int32))
        out = run_node(cls, {"factor": 2.0, "centre_cm": [1.0, 0.0, 0.0]}, mesh=mesh)["scaled"]
        g = Graph()
        g.add("example.ScaleMesh", id="scale", factor=3.0)
        print(json.dumps({"module": cls.__module__, "first": out.vertices[0, 0].tolist(),
                          "listed": "example.ScaleMesh" in registry.all_types()}))
    ''')
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), str(EXAMPLE / "src"),
                                                        os.environ.get("PYTHONPATH", "")])}
    env.pop("NODEGRAPH_PLUGINS", None)
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, check=True)
    got = json.loads(done.stdout.strip().splitlines()[-1])
    assert got == {"module": "nodegraph_example", "first": [1.0, 2.0, 2.0], "listed": True}
