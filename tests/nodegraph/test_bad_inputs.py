"""Bad input tried as a new user would: each refused with exit 2 naming what was wrong."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import nodegraph.cli
from nodegraph import Graph, Node, NodeParams, Out, ParamSequence, run
from nodegraph.cache import MARKER, Cache, NotACache
from nodegraph.cli import main
from nodegraph.errors import GraphError
from nodegraph.plan_names import TaskName
from nodegraph.schedule import plan_run

from .helpers import chain


@pytest.fixture
def graph_file(tmp_path) -> Path:
    g = chain(num_frames=20)
    g.expose("factor", "scale", "factor")
    path = tmp_path / "chain.json"
    g.save(path)
    return path


# -- item 6 ------------------------------------------------------------------------------

@pytest.mark.parametrize("port", ["params", "kind", "version", "run", "seed", "device", "frames"])
def test_port_names_shadowing_node_attributes_are_refused(port):
    with pytest.raises(TypeError, match=f"port name.*{port}.*shadow"):
        type("Bad", (Node,), {"Params": NodeParams, port: Out(ParamSequence)})


def test_unexpected_exception_in_the_cli_is_exit_1_with_traceback(monkeypatch, capsys):
    def broken(args):
        raise RuntimeError("boom")

    monkeypatch.setattr(nodegraph.cli, "_cmd_nodes", broken)
    assert main(["nodes"]) == 1
    err = capsys.readouterr().err
    assert "unexpected error" in err and "Traceback" in err and "RuntimeError: boom" in err


# -- cache folder safety ----------------------------------------------------------------

def test_cache_clear_and_gc_refuse_a_folder_without_the_marker(tmp_path, capsys):
    precious = tmp_path / "work"
    (precious / "sub").mkdir(parents=True)
    (precious / "sub" / "thesis.tex").write_text("years of work")
    for action in (["clear"], ["gc", "--max-size", "0"]):
        assert main(["cache", *action, "--cache", str(precious)]) == 2
        assert "not a nodegraph cache" in capsys.readouterr().err
    assert (precious / "sub" / "thesis.tex").read_text() == "years of work"
    with pytest.raises(NotACache):
        Cache(precious).clear()


def test_cache_clear_deletes_only_cache_entries(tmp_path, cache_dir):
    run(chain(), chunk=10, scheduler="sync", cache=cache_dir)
    (cache_dir / "notes.txt").write_text("mine")
    Cache(cache_dir).clear()
    assert (cache_dir / "notes.txt").read_text() == "mine" and (cache_dir / MARKER).exists()
    assert Cache(cache_dir).info()["entries"] == 0


def test_temp_folders_of_dead_writers_are_counted_and_collected(cache_dir):
    run(chain(), chunk=10, scheduler="sync", cache=cache_dir)
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(proc.stdout)
    from nodegraph.writer_tag import HOST

    dead = cache_dir / "tmp" / f"{'a' * 64}.{HOST}.{dead_pid}.{'b' * 32}"
    dead.mkdir(parents=True)
    (dead / "values.npz").write_bytes(b"x" * 1000)
    alive = cache_dir / "tmp" / f"{'c' * 64}.{HOST}.{os.getpid()}.{'d' * 32}"
    alive.mkdir()
    info = Cache(cache_dir).info()
    assert info["temp_folders"] == 2 and info["temp_bytes"] >= 1000
    Cache(cache_dir).gc(10 << 30)
    assert not dead.exists() and alive.exists()


@pytest.mark.parametrize("manifest", ["[]", "{}", '{"files": [], "ports": {}}', '"text"', '{"files": {"a": 1}, "ports": {}}'])
def test_manifest_of_the_wrong_shape_counts_as_corrupt(cache_dir, manifest):
    first = run(chain(), chunk=10, scheduler="sync", cache=cache_dir)
    key = plan_run(chain(), chunk=10).tasks[TaskName("cum", (0, 40))].key
    (Cache(cache_dir).entry_dir(key) / "manifest.json").write_text(manifest)
    second = run(chain(), chunk=10, scheduler="sync", cache=cache_dir)
    assert second.executed("cum") == 1 and second.ok
    assert (second.outputs["cum"]["total"].values == first.outputs["cum"]["total"].values).all()


def test_explain_reports_a_byte_flipped_entry_as_a_miss(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "--cache", str(cache_dir), "--chunk", "10", "--progress", "none"]) == 0
    key = plan_run(Graph.load(graph_file), chunk=10).tasks[TaskName("cum", (0, 20))].key
    npz = Cache(cache_dir).entry_dir(key) / "total.npz"
    data = bytearray(npz.read_bytes())
    data[len(data) // 2] ^= 0xFF
    npz.write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["run", str(graph_file), "--cache", str(cache_dir), "--chunk", "10", "--explain"]) == 0
    out = capsys.readouterr().out
    assert "cum|0:20" in out and "MISS" in out.split("cum|0:20")[1].splitlines()[0]


# -- command line ----------------------------------------------------------------------

def test_graph_parameters_are_accepted_after_options(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "--cache", str(cache_dir), "--chunk", "5", "factor=4",
                 "--progress", "none"]) == 0
    captured = capsys.readouterr()
    assert "executed" in captured.err and "FAILED" not in captured.out


def test_failure_summary_goes_to_stderr_like_success(tmp_path, cache_dir, capsys):
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=10)
    g.add("test.Fail", id="fail", frames=[3])
    g.connect("ramp.values", "fail.values")
    path = tmp_path / "fail.json"
    g.save(path)
    assert main(["run", str(path), "--cache", str(cache_dir), "--progress", "none"]) == 1
    captured = capsys.readouterr()
    assert "FAILED" in captured.err and "FAILED" not in captured.out


def test_json_progress_routes_warnings_into_events(tmp_path, cache_dir):
    plugin = tmp_path / "warn_plugin.py"
    plugin.write_text(
        "import warnings\n"
        "from nodegraph import FRAMEWISE, In, Node, NodeParams, Out, ParamSequence\n"
        "class Warn(Node):\n"
        "    type_name = 'warn.Warn'\n"
        "    kind = FRAMEWISE\n"
        "    class Params(NodeParams):\n"
        "        pass\n"
        "    values = In(ParamSequence)\n"
        "    same = Out(ParamSequence)\n"
        "    def run(self, values):\n"
        "        warnings.warn('a library complains', UserWarning)\n"
        "        return {'same': values}\n")
    g = {"schema": "nodegraph/1", "nodes": {"ramp": {"type": "test.Ramp", "params": {"num_frames": 10}},
                                            "warn": {"type": "warn.Warn"}},
         "edges": [["ramp.values", "warn.values"]]}
    path = tmp_path / "g.json"
    path.write_text(json.dumps(g))
    env = {**os.environ, "NODEGRAPH_PLUGINS": "nodegraph.testing,warn_plugin",
           "PYTHONPATH": f"{tmp_path}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    for scheduler in ("threads", "processes"):
        proc = subprocess.run([sys.executable, "-m", "nodegraph.cli", "run", str(path), "--cache", str(cache_dir),
                               "--no-cache", "--scheduler", scheduler, "--chunk", "5"],
                              capture_output=True, text=True, env=env)
        assert proc.returncode == 0, proc.stderr
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        events = [json.loads(line) for line in lines[:-1]]  # the last line is the summary
        assert any(e["event"] == "warning" and "complains" in e["message"] for e in events), scheduler


def test_validate_checks_every_file_and_folders(tmp_path, graph_file, capsys):
    bad_bytes = tmp_path / "garbage.json"
    bad_bytes.write_bytes(b"\xff\xfe\x00garbage")
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    assert main(["validate", str(bad_bytes), str(deep), str(graph_file)]) == 2
    captured = capsys.readouterr()
    assert "garbage.json" in captured.err and "deep.json" in captured.err and f"{graph_file}: ok" in captured.out
    assert main(["validate", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert f"{graph_file}: ok" in captured.out and "garbage.json" in captured.err
    assert main(["validate", "graphs/"]) == 0


@pytest.mark.parametrize("mutate, text", [
    (lambda d: d["nodes"]["scale"]["params"].update(factor=float("inf")), "not a JSON number"),
    (lambda d: d["nodes"]["ramp"]["params"].update(num_frames=True), "expected an integer"),
    (lambda d: d["nodes"]["ramp"]["params"].update(num_frames=2.5), "expected an integer"),
    (lambda d: d["nodes"]["ramp"].update(type_version=0), "greater than or equal to 1"),
    (lambda d: d["nodes"].update({"a.b": {"type": "test.Ramp"}}), "contain no '.'"),
    (lambda d: d["nodes"]["scale"].update(chunk=0), "greater than or equal to 1"),
    (lambda d: d["nodes"]["scale"].update(device="tpu"), "device"),
])
def test_bad_values_are_refused_at_validation(tmp_path, graph_file, mutate, text, capsys):
    data = json.loads(graph_file.read_text())
    mutate(data)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))  # inf is written as Infinity, which JSON does not have
    assert main(["validate", str(path)]) == 2
    assert text in capsys.readouterr().err


def test_non_finite_params_refused_naming_node_and_param():
    g = chain()
    with pytest.raises(GraphError, match="node 'scale', 'factor'.*finite"):
        g.set("scale", factor=float("nan"))


def test_duplicate_json_keys_are_refused(tmp_path, capsys):
    path = tmp_path / "dup.json"
    path.write_text('{"schema": "nodegraph/1", "nodes": {"a": {"type": "test.Ramp"}, "a": {"type": "test.Ramp"}}}')
    assert main(["validate", str(path)]) == 2
    assert "duplicate key 'a'" in capsys.readouterr().err


def test_enumerations_and_list_lengths_are_checked_at_validation():
    g = Graph()
    with pytest.raises(GraphError, match="'motion'"):
        g.add("synth.Performance", id="perf", motion="wobble")
    with pytest.raises(GraphError, match="'pivot_cm'.*3 numbers"):
        g.add("synth.Performance", id="perf", pivot_cm=[1.0, 2.0])
    with pytest.raises(GraphError, match="'vertices'.*three distinct"):
        g.add("rigid.ThreePoint", id="tp", vertices=[1, 2])
    with pytest.raises(GraphError, match="'vertices.2'.*greater than or equal to 0"):
        g.add("rigid.ThreePoint", id="tp", vertices=[1, 2, -3])


# -- paths -----------------------------------------------------------------------------

def test_relative_paths_in_a_graph_file_resolve_against_its_folder(tmp_path, cache_dir, monkeypatch):
    folder = tmp_path / "project" / "graphs"
    folder.mkdir(parents=True)
    for f in range(5):
        (folder / f"in{f}.txt").write_text(f"{f}\n")
    g = Graph()
    g.add("test.ReadText", id="read", path="in{frame}.txt", num_frames=5)
    g.add("test.WriteText", id="write", path="../out/all{start}.txt")
    g.connect("read.values", "write.values")
    g.expose("output", "write", "path")
    g.save(folder / "g.json")
    monkeypatch.chdir(tmp_path)
    assert main(["run", str(folder / "g.json"), "--cache", str(cache_dir), "--progress", "none"]) == 0
    assert (tmp_path / "project" / "out" / "all0.txt").exists()
    # a path given on the command line stays relative to the working folder
    assert main(["run", str(folder / "g.json"), "output=here{start}.txt", "--cache", str(cache_dir),
                 "--progress", "none"]) == 0
    assert (tmp_path / "here0.txt").exists()
    assert json.loads((folder / "g.json").read_text())["nodes"]["read"]["params"]["path"] == "in{frame}.txt"


def test_old_report_graph_with_estimate_ports_migrates(tmp_path):
    data = json.loads(Path("graphs/stabilize.json").read_text())
    data["nodes"]["report"]["type_version"] = 1
    numbers = iter(range(1, 5))
    data["edges"] = [[a, f"report.estimate_{next(numbers)}" if b == "report.estimates" else b] for a, b in data["edges"]]
    old = [b for _, b in data["edges"] if "estimate_" in b]
    assert len(old) == 2
    g = Graph.from_json(data)
    assert [str(s) for s in g.upstream_lists("report")["estimates"]] == ["init.rigid", "stab.rigid"]
    assert g.migrations


def test_report_html_shows_graph_timings_and_failures(tmp_path, cache_dir, capsys):
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=10)
    g.add("test.Fail", id="fail", frames=[3])
    g.add("test.Scale", id="scale")
    g.connect("ramp.values", "fail.values")
    g.connect("ramp.values", "scale.values")
    path = tmp_path / "g.json"
    g.save(path)
    page = tmp_path / "run.html"
    assert main(["run", str(path), "--cache", str(cache_dir), "--progress", "none", "--report-html", str(page)]) == 1
    text = page.read_text()
    assert "<svg" in text and "deliberate failure at frame 3" in text and "Traceback" in text
    assert ">scale<" in text and ">ramp<" in text and "http" not in text.replace('xmlns="http://www.w3.org/2000/svg"', "")
