"""The `nodegraph` command: exit codes, --explain, --help of a graph, upgrade, cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from nodegraph.cache import Cache
from nodegraph.cli import main

from .helpers import chain, two_branches


@pytest.fixture
def graph_file(tmp_path):
    g = chain(num_frames=20)
    g.expose("factor", "scale", "factor", description="multiplier")
    path = tmp_path / "chain.json"
    g.save(path)
    return path


def test_run_ok_exit_0(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "factor=3", "--cache", str(cache_dir), "--chunk", "5",
                 "--progress", "none"]) == 0
    assert "cum.total" in capsys.readouterr().out


def test_bad_graph_parameter_exit_2(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "factor=lots", "--cache", str(cache_dir)]) == 2
    err = capsys.readouterr().err
    assert "node 'scale'" in err and "'factor'" in err


def test_invalid_graph_exit_2(tmp_path, capsys):
    path = tmp_path / "bad.json"
    data = chain().to_json()
    data["edges"].pop(0)
    path.write_text(json.dumps(data))
    assert main(["validate", str(path)]) == 2
    assert "node 'scale', 'values': required input" in capsys.readouterr().err
    assert main(["run", str(path)]) == 2


def test_failing_node_exit_1(tmp_path, cache_dir, capsys):
    path = tmp_path / "fail.json"
    two_branches(fail_frames=[4]).save(path)
    assert main(["run", str(path), "--cache", str(cache_dir), "--progress", "none"]) == 1
    out = capsys.readouterr()
    assert "FAILED test.Fail 'fail' (frames 0:30)" in out.out + out.err or "FAILED" in out.out


def test_explain_names_the_changed_parameter(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "--cache", str(cache_dir), "--chunk", "5", "--progress", "none"]) == 0
    capsys.readouterr()
    assert main(["run", str(graph_file), "factor=7", "--cache", str(cache_dir), "--chunk", "5", "--explain"]) == 0
    out = capsys.readouterr().out
    assert "param factor changed (2.0 -> 7.0)" in out
    assert "ramp|0:5" in out and "upstream 'values' changed" in out
    assert "4 hit" in out


def test_run_help_lists_graph_parameters(graph_file, capsys):
    assert main(["run", str(graph_file), "--help"]) == 0
    out = capsys.readouterr().out
    assert "factor=2.0" in out and "float" in out and "scale.factor" in out and "multiplier" in out


def test_nodes_lists_and_describes(capsys):
    assert main(["nodes"]) == 0
    assert "test.Scale" in capsys.readouterr().out
    assert main(["nodes", "test.Scale"]) == 0
    out = capsys.readouterr().out
    assert "factor: float = 1.0" in out and "values: ParamSequence" in out
    assert main(["nodes", "test.Scael"]) == 2


def test_show_prints_outline(graph_file, capsys):
    assert main(["show", str(graph_file)]) == 0
    out = capsys.readouterr().out
    assert "avg [test.MovingAverage v1, windowed(halo=3)]" in out and "values <- scale.scaled" in out


def test_upgrade_rewrites_and_shows_diff(tmp_path, capsys):
    data = chain().to_json()
    data["nodes"]["off"] = {"type": "test.Offset", "type_version": 1, "params": {"amount": 1.0}}
    data["edges"].append(["cum.total", "off.values"])
    path = tmp_path / "old.json"
    path.write_text(json.dumps(data, indent=2))
    before = path.read_text()
    assert main(["upgrade", str(path), "--check"]) == 1
    assert path.read_text() == before  # --check and loading never rewrite
    assert main(["upgrade", str(path)]) == 0
    out = capsys.readouterr().out
    assert '-        "amount": 1.0' in out and '+        "offset": 1.0' in out
    assert json.loads(path.read_text())["nodes"]["off"]["type_version"] == 2
    assert main(["upgrade", str(path)]) == 0 and "up to date" in capsys.readouterr().out


def test_cache_commands(graph_file, cache_dir, capsys):
    main(["run", str(graph_file), "--cache", str(cache_dir), "--progress", "none"])
    capsys.readouterr()
    assert main(["cache", "info", "--cache", str(cache_dir)]) == 0
    assert "entries" in capsys.readouterr().out
    assert main(["cache", "gc", "--max-size", "0", "--cache", str(cache_dir)]) == 0
    assert main(["cache", "clear", "--cache", str(cache_dir)]) == 0
    assert Cache(cache_dir).info()["entries"] == 0 and Cache(cache_dir).is_cache()


def test_console_script_json_progress(graph_file, cache_dir):
    env = {**os.environ, "NODEGRAPH_PLUGINS": "nodegraph.testing"}
    proc = subprocess.run([sys.executable, "-m", "nodegraph.cli", "run", str(graph_file), "--cache", str(cache_dir),
                           "--chunk", "10"], capture_output=True, text=True, env=env)
    assert proc.returncode == 0, proc.stderr
    events = [json.loads(line) for line in proc.stderr.splitlines() if line.startswith("{")]
    assert events[0]["event"] == "start" and events[-1]["event"] == "end"
    assert any(e["event"] == "task" and e["node"] == "avg" for e in events)


def test_force_and_to_options(graph_file, cache_dir, capsys):
    args = ["run", str(graph_file), "--cache", str(cache_dir), "--chunk", "5", "--progress", "none"]
    assert main(args) == 0
    capsys.readouterr()
    assert main(args + ["--to", "scale", "--force", "scale"]) == 0
    out = capsys.readouterr()
    assert "scale.scaled" in out.out and "cum.total" not in out.out
    assert "4 executed" in out.out + out.err
