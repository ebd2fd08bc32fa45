"""Cache keys and writers: code hashes over imported helpers, writers skipped while their files are
intact, per-chunk input files, list ports, seeds, devices, per-node chunks."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import nodegraph.tasks
from nodegraph import Graph, run
from nodegraph.cache import Cache
from nodegraph.plan_names import TaskName
from nodegraph.schedule import plan_run

from .helpers import chain


# -- 1. code hash over every imported project module ---------------------------------------

PLUGIN_NODE = '''
from nodegraph import FRAMEWISE, In, Node, NodeParams, Out, ParamSequence

class Double(Node):
    type_name = "{pkg}.Double"
    kind = FRAMEWISE

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    doubled = Out(ParamSequence)

    def run(self, values):
        from .math.helper import factor  # lazy, inside run: still part of the code hash
        return {{"doubled": ParamSequence(values.values * factor(), list(values.names))}}
'''


def _plugin(tmp_path: Path, pkg: str, factor: str) -> Path:
    root = tmp_path / "site"
    (root / pkg / "math").mkdir(parents=True, exist_ok=True)
    (root / pkg / "__init__.py").write_text("from . import node\n")
    (root / pkg / "node.py").write_text(PLUGIN_NODE.format(pkg=pkg))
    (root / pkg / "math" / "__init__.py").write_text("")
    (root / pkg / "math" / "helper.py").write_text(f"def factor():\n    return {factor}\n")
    return root


_PROBE = textwrap.dedent('''
    import json, sys
    sys.path.insert(0, sys.argv[1])
    import nodegraph.testing
    from nodegraph import Graph, run
    from nodegraph.runner import explain
    from nodegraph.plan_names import TaskName
    pkg = sys.argv[2]
    __import__(pkg)
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=10)
    g.add(pkg + ".Double", id="double")
    g.connect("ramp.values", "double.values")
    if sys.argv[4] == "explain":
        rows = explain(g, chunk=10, cache=sys.argv[3])
        print(json.dumps([r for r in rows if r["node"] == "double"]))
    else:
        result = run(g, chunk=10, scheduler="sync", cache=sys.argv[3])
        from nodegraph import registry
        print(json.dumps({"key": result.plan.tasks[TaskName("double", (0, 10))].key,
                          "value": float(result.outputs["double"]["doubled"].values[3, 0]),
                          "sources": sorted(registry.get(pkg + ".Double").code_sources())}))
''')


def _probe(root: Path, pkg: str, cache: Path, mode: str = "run"):
    proc = subprocess.run([sys.executable, "-c", _PROBE, str(root), pkg, str(cache), mode],
                          capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_editing_an_imported_helper_changes_the_key_and_explain_names_it(tmp_path, cache_dir):
    root = _plugin(tmp_path, "plugin_hash", "2.0")
    first = _probe(root, "plugin_hash", cache_dir)
    assert first["value"] == 6.0
    assert "plugin_hash/math/helper.py" in first["sources"] and "plugin_hash/node.py" in first["sources"]
    assert not any(s.startswith(("numpy", "torch")) for s in first["sources"])
    again = _probe(root, "plugin_hash", cache_dir)
    assert again["key"] == first["key"]
    (root / "plugin_hash" / "math" / "helper.py").write_text("def factor():\n    return 3.0\n")
    rows = _probe(root, "plugin_hash", cache_dir, "explain")
    assert rows and not rows[0]["hit"]
    assert rows[0]["reason"] == "code changed: plugin_hash/math/helper.py", rows
    second = _probe(root, "plugin_hash", cache_dir)
    assert second["key"] != first["key"] and second["value"] == 9.0  # never yesterday's result


def test_module_sources_are_found_without_importing(tmp_path):
    from nodegraph.codehash import module_sources

    root = _plugin(tmp_path, "plugin_static", "1.0")
    sys.path.insert(0, str(root))
    try:
        sources = module_sources("plugin_static.node")
        assert "plugin_static" not in sys.modules
    finally:
        sys.path.remove(str(root))
    assert {"plugin_static/__init__.py", "plugin_static/node.py", "plugin_static/math/__init__.py",
            "plugin_static/math/helper.py", "nodegraph/__init__.py", "nodegraph/node.py",
            "nodegraph/sequences.py"} <= set(sources)
    # `from nodegraph import Node, ParamSequence` depends on the modules defining those names,
    # not on everything nodegraph/__init__.py re-exports (the runner, the cache, ...)
    assert not {"nodegraph/runner.py", "nodegraph/cache.py", "nodegraph/graph.py"} & set(sources)


def test_builtin_node_hash_covers_its_helpers():
    from nodegraph import registry

    sources = registry.get("stabilize.ModePursuit").code_sources()
    assert "nodes/stabilize/penalty.py" in sources and "nodes/stabilize/mode_pursuit.py" in sources


def test_builtin_node_hash_covers_only_the_modules_it_uses():
    """A package passed through on the way to a submodule counts by its own source only: a
    temporal node's key does not change when the generator, a report or the runner is edited."""
    from nodegraph import registry

    for type_name in ("temporal.Hybrid", "temporal.AdaptiveSmooth", "fit.Expression", "dynamics.RemoveDynamics"):
        sources = set(registry.get(type_name).code_sources())
        area = type_name.split(".")[0]
        assert any(s.startswith(f"nodes/{area}/") for s in sources), type_name
        assert "nodes/__init__.py" in sources and "nodegraph/node.py" in sources, type_name
        unused = {s for s in sources if s.startswith(("nodes/synth/", "nodes/report/", "nodes/export/"))
                  or s in ("nodegraph/runner.py", "nodegraph/cache.py", "nodegraph/dask_run.py", "nodes/_areas.py")}
        assert not unused, (type_name, unused)


# -- 2. writers skipped while their files are intact ---------------------------------------

def _writer_graph(path: str, factor: float = 2.0) -> Graph:
    g = chain(num_frames=30, factor=factor)
    g.add("test.WriteText", id="write", path=path)
    g.connect("scale.scaled", "write.values")
    return g


def test_writer_is_skipped_when_files_are_intact_and_rewrites_exactly_a_deleted_file(tmp_path, cache_dir):
    pattern = str(tmp_path / "out" / "v{frame}.txt")
    first = run(_writer_graph(pattern), chunk=10, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert first.executed("write") == 3
    files = sorted((tmp_path / "out").glob("v*.txt"))
    assert len(files) == 30
    mtimes = {f: f.stat().st_mtime_ns for f in files}
    second = run(_writer_graph(pattern), chunk=10, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert second.executed() == 0
    assert {f: f.stat().st_mtime_ns for f in files} == mtimes
    victim = tmp_path / "out" / "v17.txt"
    text = victim.read_text()
    victim.unlink()
    third = run(_writer_graph(pattern), chunk=10, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert third.executed() == 0 and third.count("restored") == 1  # from the entry's copy
    assert victim.read_text() == text
    assert {f: f.stat().st_mtime_ns for f in files if f != victim} == {f: m for f, m in mtimes.items() if f != victim}


def test_writer_without_copies_reruns_only_the_chunk_whose_file_changed(tmp_path, cache_dir, monkeypatch):
    monkeypatch.setattr(nodegraph.tasks, "COPY_LIMIT", 0)
    pattern = str(tmp_path / "out" / "v{frame}.txt")
    run(_writer_graph(pattern), chunk=10, scheduler="sync", cache=cache_dir, outputs=["write"])
    victim = tmp_path / "out" / "v25.txt"
    good = victim.read_text()
    victim.write_text("edited by hand\n")
    result = run(_writer_graph(pattern), chunk=10, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert result.executed("write") == 1 and result.executed() == 1  # upstream loaded from the cache
    assert victim.read_text() == good


def test_touched_but_identical_file_stays_a_hit(tmp_path, cache_dir):
    path = str(tmp_path / "all{start}.txt")
    run(_writer_graph(path), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"])
    target = tmp_path / "all0.txt"
    os.utime(target, ns=(1, 1))
    assert run(_writer_graph(path), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"]).executed() == 0


def test_writer_reruns_when_its_key_changes(tmp_path, cache_dir):
    path = str(tmp_path / "all{start}.txt")
    run(_writer_graph(path), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"])
    before = (tmp_path / "all0.txt").read_text()
    result = run(_writer_graph(path, factor=3.0), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert result.executed("write") == 1 and (tmp_path / "all0.txt").read_text() != before


def test_relative_writer_path_run_from_another_folder_writes_there(tmp_path, cache_dir, monkeypatch):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    monkeypatch.chdir(tmp_path / "a")
    run(_writer_graph("out{start}.txt"), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"])
    monkeypatch.chdir(tmp_path / "b")
    result = run(_writer_graph("out{start}.txt"), chunk=100, scheduler="sync", cache=cache_dir, outputs=["write"])
    assert (tmp_path / "b" / "out0.txt").exists() and result.count("restored") + result.executed() >= 1


# -- 3. per-frame input files key per chunk ------------------------------------------------

def test_one_changed_frame_file_recomputes_only_its_chunk(tmp_path, cache_dir):
    for f in range(30):
        (tmp_path / f"in{f}.txt").write_text(f"{f}\n")
    g = Graph()
    g.add("test.ReadText", id="read", path=str(tmp_path / "in{frame}.txt"), num_frames=30)
    g.add("test.Scale", id="scale", factor=2.0)
    g.connect("read.values", "scale.values")
    first = run(g, chunk=10, scheduler="sync", cache=cache_dir)
    assert first.executed() == 6
    (tmp_path / "in14.txt").write_text("100\n")
    second = run(g, chunk=10, scheduler="sync", cache=cache_dir)
    assert second.executed("read") == 1 and second.executed("scale") == 1
    assert second.outputs["scale"]["scaled"].values[14, 0] == 200.0


def test_numbered_mesh_files_key_per_chunk(tmp_path):
    from nodegraph.types import MeshSequence
    from nodes.io.mesh import save_mesh_sequence

    verts = np.random.default_rng(0).normal(size=(12, 4, 3)).astype(np.float32)
    mesh = MeshSequence(verts, np.array([[0, 1, 2], [0, 2, 3]], np.int32))
    pattern = str(tmp_path / "face.%04d.obj")
    save_mesh_sequence(pattern, mesh, range(12))
    g = Graph()
    g.add("io.LoadMeshSequence", id="load", path=pattern)
    before = {n: t.key for n, t in plan_run(g, chunk=4).tasks.items()}
    save_mesh_sequence(pattern, MeshSequence(verts[9:10] + 1, mesh.faces), range(9, 10))
    after = {n: t.key for n, t in plan_run(g, chunk=4).tasks.items()}
    assert [n for n in before if before[n] != after[n]] == [TaskName("load", (8, 12))]


# -- 4. list ports, seeds, devices, per-node chunk -----------------------------------------

def _weighted_graph() -> Graph:
    g = Graph()
    g.add("test.Ramp", id="one", num_frames=10, start=1.0, slope=0.0)
    g.add("test.Ramp", id="ten", num_frames=10, start=10.0, slope=0.0)
    g.add("test.Weighted", id="w")
    g.connect("ten.values", "w.values")
    g.connect("one.values", "w.values")
    return g


def test_list_port_keeps_connection_order_through_json(tmp_path):
    g = _weighted_graph()
    path = tmp_path / "g.json"
    g.save(path)
    loaded = Graph.load(path)
    assert loaded == g
    assert [str(src) for src in loaded.upstream_lists("w")["values"]] == ["ten.values", "one.values"]
    out = run(loaded, scheduler="sync", cache=False)
    assert out.outputs["w"]["total"].values[0, 0] == 1 * 10 + 2 * 1
    data = json.loads(path.read_text())
    data["edges"].reverse()
    assert run(Graph.from_json(data), scheduler="sync", cache=False).outputs["w"]["total"].values[0, 0] == 21


def test_list_port_required_needs_a_connection():
    g = Graph()
    g.add("test.Weighted", id="w")
    assert any(i.port == "values" and "not connected" in i.message for i in g.validate())


_SEED_PROBE = textwrap.dedent('''
    import json, sys
    import nodegraph.testing
    from nodegraph import Graph, run
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=20)
    g.add("test.Noise", id="noise")
    g.connect("ramp.values", "noise.values")
    out = run(g, chunk=10, scheduler=sys.argv[1], cache=False)
    print(json.dumps(out.outputs["noise"]["noise"].values[:, 0].tolist()))
''')


def test_same_seed_for_the_same_key_in_two_processes():
    runs = [json.loads(subprocess.run([sys.executable, "-c", _SEED_PROBE, scheduler], capture_output=True,
                                      text=True, check=True).stdout) for scheduler in ("sync", "processes")]
    assert runs[0] == runs[1]
    assert runs[0][:10] != runs[0][10:]  # chunks have their own seeds


def test_device_default_and_pinned_per_node():
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=4)
    g.add("test.Noise", id="noise")
    g.add("test.Noise", id="pinned", device="cpu")
    g.connect("ramp.values", "noise.values")
    g.connect("ramp.values", "pinned.values")
    out = run(g, scheduler="sync", cache=False, device="cuda")
    assert out.outputs["noise"]["noise"].names == ["cuda"]
    assert out.outputs["pinned"]["noise"].names == ["cpu"]
    assert Graph.from_json(g.to_json()).nodes["pinned"].device == "cpu"


def test_per_node_chunk_from_json():
    data = chain(num_frames=40).to_json()
    data["nodes"]["scale"]["chunk"] = 8
    g = Graph.from_json(data)
    plan = plan_run(g, chunk=20)
    assert len(plan.by_node["scale"]) == 5 and len(plan.by_node["ramp"]) == 2
    base = run(chain(num_frames=40), chunk=20, scheduler="sync", cache=False)
    mixed = run(g, chunk=20, scheduler="sync", cache=False)
    np.testing.assert_array_equal(mixed.outputs["cum"]["total"].values, base.outputs["cum"]["total"].values)


@pytest.mark.slow
@pytest.mark.timeout(120)
def test_gpu_tasks_go_to_the_gpu_worker_on_a_cluster():
    from distributed import Client, LocalCluster, Worker

    # A cluster with two workers, one declaring a GPU.
    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False, dashboard_address=None) as cluster:
        async def add_gpu_worker():
            return await Worker(cluster.scheduler_address, resources={"gpu": 1}, nthreads=2)

        with Client(cluster) as client:
            gpu_worker = client.sync(add_gpu_worker)
            try:
                g = Graph()
                g.add("test.Ramp", id="ramp", num_frames=10)
                for i in range(6):  # without the resource, some would land on the other worker
                    g.add("test.Noise", id=f"noise{i}")
                    g.connect("ramp.values", f"noise{i}.values")
                out = run(g, chunk=10, scheduler=client, cache=False, device="auto")
                assert out.ok
                where = {out.outputs[f"noise{i}"]["noise"].names[0] for i in range(6)}
                assert where == {f"auto@{gpu_worker.address}"}
                cpu_only = run(g, chunk=10, scheduler=client, cache=False, device="cpu")
                assert cpu_only.ok
            finally:
                client.sync(gpu_worker.close)


def test_run_node_counts_frames_from_a_list_port():
    from nodegraph import ParamSequence, run_node
    from nodegraph.testing import Weighted

    values = [ParamSequence(np.ones((7, 1), np.float32), ["value"]) for _ in range(2)]
    out = run_node(Weighted, values=values)["total"]
    assert out.num_frames == 7 and float(out.values[0, 0]) == 3.0
