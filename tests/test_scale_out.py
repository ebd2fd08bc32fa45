"""examples/cluster_run.py, the scale-out recipe of docs/guide.md: a graph run on a dask.distributed
cluster of CPU workers and a GPU worker (one offering the resource gpu=1) gives the local run's
result, and the tasks of nodes declaring `resources = {"gpu": 1}` run only on the GPU worker."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _example():
    spec = importlib.util.spec_from_file_location("cluster_run", ROOT / "examples" / "cluster_run.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_graph_on_a_cluster_with_a_gpu_worker_matches_the_local_run(tmp_path):
    distributed = pytest.importorskip("distributed")
    from nodegraph import registry, runner
    from nodes.export.livelink import live_link_rows, live_link_text
    from nodes.io.arkit import head_rotation
    from nodes.io.image import read_image

    frames = 12
    rng = np.random.default_rng(0)
    take = tmp_path / "take.csv"
    take.write_text(live_link_text(live_link_rows(rng.uniform(0, 0.6, (frames, 52)),
                                                  head_rotation(rng.normal(0, 0.1, (frames, 3))), 30.0)))
    graph = ROOT / "graphs" / "livelink_to_render.json"
    local = runner.run(graph, scheduler="sync", cache=False, chunk=4,
                       parameters={"csv": str(take), "fps": 30.0, "images": str(tmp_path / "local.%04d.png")})
    assert local.ok

    example = _example()
    with example.local_cluster(cpu_workers=2, gpu_workers=1) as cluster, distributed.Client(cluster) as client:
        result, where = example.run_on_cluster(str(graph), {"csv": str(take), "fps": 30.0,
                                                            "images": str(tmp_path / "cluster.%04d.png")},
                                               client, chunk=4)
    assert result.ok
    spec = json.loads(graph.read_text())["nodes"]
    gpu_nodes = {n for n, s in spec.items() if registry.get(s["type"]).resources.get("gpu")}
    assert gpu_nodes == {"render"}
    assert where["render"] == {"gpu-0"}, where  # its 3 chunks, all on the GPU worker
    assert set(where) == set(spec)
    for f in range(frames):  # the same pictures (one 8-bit level for float sums split otherwise)
        a, b = (np.rint(read_image(tmp_path / f"{run}.{f:04d}.png")[0] * 255).astype(np.int16)
                for run in ("local", "cluster"))  # read_image scales 8-bit to [0, 1]
        assert a.max() > 0 and np.abs(a - b).max() <= 1, f
