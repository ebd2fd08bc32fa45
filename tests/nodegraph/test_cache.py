"""The persistent cache: what re-runs after a change, integrity, concurrency, stable keys."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from nodegraph import run
from nodegraph.cache import Cache, make_key
from nodegraph.plan_names import TaskName
from nodegraph.schedule import plan_run

from .helpers import chain

CHUNK = 10  # 40 frames -> 4 chunks


def _executed(result) -> dict[str, int]:
    return {node: result.executed(node) for node in ["ramp", "scale", "avg", "cum"]}


def test_second_run_is_all_cached(cache_dir):
    first = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert _executed(first) == {"ramp": 4, "scale": 4, "avg": 4, "cum": 1}
    second = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert second.executed() == 0 and second.count("cached") == 1  # only the target is loaded
    np.testing.assert_array_equal(second.outputs["cum"]["total"].values, first.outputs["cum"]["total"].values)


def test_changing_last_node_reruns_only_it(cache_dir):
    def graph(factor: float):
        g = chain()
        g.add("test.Scale", id="last", factor=factor)
        g.connect("cum.total", "last.values")
        return g

    run(graph(1.0), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    result = run(graph(5.0), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert result.executed() == result.executed("last") == 4
    assert result.count("cached") == 1  # cum's output, loaded once


def test_changing_first_node_reruns_all(cache_dir):
    run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    g = chain()
    g.set("ramp", slope=0.25)
    result = run(g, chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert _executed(result) == {"ramp": 4, "scale": 4, "avg": 4, "cum": 1}


def test_output_neutral_param_keeps_cache(cache_dir):
    run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    g = chain()
    g.set("scale", label="renamed")
    assert run(g, chunk=CHUNK, scheduler="sync", cache=cache_dir).executed() == 0


def test_widening_frame_range_runs_only_new_chunks(cache_dir):
    g = chain(num_frames=60)
    outputs = ["scale"]
    run(g, frames=range(0, 30), chunk=CHUNK, scheduler="sync", cache=cache_dir, outputs=outputs)
    result = run(g, frames=range(0, 50), chunk=CHUNK, scheduler="sync", cache=cache_dir, outputs=outputs)
    assert result.executed("ramp") == 2 and result.executed("scale") == 2
    assert result.count("cached") == 3


def test_truncated_entry_is_recomputed(cache_dir):
    first = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    key = plan_run(chain(), chunk=CHUNK).tasks[TaskName("cum", (0, 40))].key
    npz = Cache(cache_dir).entry_dir(key) / "total.npz"
    npz.write_bytes(npz.read_bytes()[:40])
    second = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert second.executed("cum") == 1
    np.testing.assert_array_equal(second.outputs["cum"]["total"].values, first.outputs["cum"]["total"].values)


def test_corrupted_bytes_are_detected_not_returned(cache_dir):
    first = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    key = plan_run(chain(), chunk=CHUNK).tasks[TaskName("cum", (0, 40))].key
    npz = Cache(cache_dir).entry_dir(key) / "total.npz"
    data = bytearray(npz.read_bytes())
    data[-30] ^= 0xFF  # same size, different content
    npz.write_bytes(bytes(data))
    second = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    assert second.executed("cum") == 1
    np.testing.assert_array_equal(second.outputs["cum"]["total"].values, first.outputs["cum"]["total"].values)


def test_half_written_entry_is_invisible(cache_dir):
    store = Cache(cache_dir)
    key = plan_run(chain(), chunk=CHUNK).tasks[TaskName("cum", (0, 40))].key
    folder = store.entry_dir(key)
    folder.mkdir(parents=True)
    (folder / "total.npz").write_bytes(b"partial")  # a crash before the manifest
    assert not store.contains(key)
    assert run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir).executed("cum") == 1


def _run_script(cache_dir: Path, tag: str) -> str:
    return (
        "import sys, json; import nodegraph.testing\n"
        "sys.path.insert(0, %r)\n"
        "from tests.nodegraph.helpers import chain\n"
        "from nodegraph import run\n"
        "r = run(chain(), chunk=5, scheduler='threads', cache=%r)\n"
        "print(json.dumps({'ok': r.ok, 'sum': float(r.outputs['cum']['total'].values.sum())}))\n"
        % (str(Path(__file__).parents[2]), str(cache_dir))
    )


def test_two_processes_run_the_same_graph_at_once(cache_dir):
    procs = [subprocess.Popen([sys.executable, "-c", _run_script(cache_dir, str(i))], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for i in range(2)]
    outs = [p.communicate(timeout=120) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err
    results = [json.loads(out.strip().splitlines()[-1]) for out, _ in outs]
    assert results[0] == results[1] and results[0]["ok"]
    assert not list((cache_dir / "tmp").glob("*.*")) or all("trash" not in p.name for p in (cache_dir / "tmp").iterdir())
    again = run(chain(), chunk=5, scheduler="sync", cache=cache_dir)
    assert again.executed() == 0


def test_key_is_the_same_in_a_fresh_interpreter():
    keys = {str(name): t.key for name, t in plan_run(chain(), chunk=CHUNK).tasks.items()}
    script = ("import json, sys; sys.path.insert(0, %r); import nodegraph.testing\n"
              "from tests.nodegraph.helpers import chain\nfrom nodegraph.schedule import plan_run\n"
              "print(json.dumps({str(n): t.key for n, t in plan_run(chain(), chunk=%d).tasks.items()}))"
              % (str(Path(__file__).parents[2]), CHUNK))
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True,
                         cwd="/", env={**os.environ, "PYTHONHASHSEED": "123"})
    assert json.loads(out.stdout) == keys


def test_make_key_is_canonical():
    assert make_key({"a": 1, "b": [1, 2]}) == make_key({"b": [1, 2], "a": 1})
    assert make_key({"a": 1}) != make_key({"a": 2})


def test_cache_gc_and_info(cache_dir):
    run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    store = Cache(cache_dir)
    info = store.info()
    assert info["entries"] == 13 and info["bytes"] > 0
    removed, _ = store.gc(0)
    assert removed == 13 and store.info()["entries"] == 0


def test_force_recomputes_node_and_descendants(cache_dir):
    run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir)
    result = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir, force=["avg"])
    assert _executed(result) == {"ramp": 0, "scale": 0, "avg": 4, "cum": 1}


def test_outputs_stop_early(cache_dir):
    result = run(chain(), chunk=CHUNK, scheduler="sync", cache=cache_dir, outputs=["scale"])
    assert set(result.outputs) == {"scale"} and result.executed("avg") == 0 and result.executed("cum") == 0


def test_tty_progress_bars_do_not_change_results(cache_dir, capsys):
    quiet = run(chain(), chunk=CHUNK, scheduler="threads", cache=False)
    shown = run(chain(), chunk=CHUNK, scheduler="threads", cache=False, progress="tty")
    np.testing.assert_array_equal(quiet.outputs["cum"]["total"].values, shown.outputs["cum"]["total"].values)
    assert "avg" in capsys.readouterr().err
