"""The runner's fast paths keep results exact: shared joins of the same chunks, cache writes
in a background thread (hashed while written), module preloading, the finite-sum check."""

from __future__ import annotations

import hashlib
import json
import sys
import textwrap

import numpy as np
import pytest

from nodegraph import Graph, MeshSequence, ParamSequence, run
from nodegraph.cache import Cache
from nodegraph.plan_names import TaskName
from nodegraph.tasks import TaskResult, _CombinedInputs


def _fan_out(num_frames: int = 40) -> Graph:
    """ramp (framewise chunks) -> cum and total: two whole-sequence readers of the same chunks."""
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=num_frames, slope=0.5)
    cum = g.add("test.CumSum", id="cum")
    total = g.add("test.Total", id="total")
    g.connect(ramp["values"], cum["values"])
    g.connect(ramp["values"], total["values"])
    return g


@pytest.mark.parametrize("scheduler", ["sync", "threads"])
def test_whole_sequence_readers_share_one_join_of_the_same_chunks(scheduler, monkeypatch):
    joins = []
    original = ParamSequence.concat_frames.__func__

    def counting(cls, parts):
        joins.append(len(parts))
        return original(cls, parts)

    monkeypatch.setattr(ParamSequence, "concat_frames", classmethod(counting))
    result = run(_fan_out(), chunk=8, scheduler=scheduler, cache=False)
    ramp = 0.5 * np.arange(40, dtype=np.float64)
    np.testing.assert_allclose(result.outputs["cum"]["total"].values[:, 0], np.cumsum(ramp), rtol=1e-6)
    assert result.outputs["total"]["total"].value == pytest.approx(ramp.sum())
    # one join of the 5 chunks for both readers (the cum output is one piece: no join)
    assert joins.count(5) == 1, joins


def _result(name: str, values: np.ndarray) -> TaskResult:
    return TaskResult(TaskName(name, (0, len(values))), name, (0, len(values)), "executed",
                      {"v": ParamSequence(values, ["a"])})


def test_a_shared_join_is_valid_only_for_the_very_same_upstream_results():
    combined = _CombinedInputs()
    combined.active = True
    a, b = _result("a", np.zeros((3, 1), np.float32)), _result("b", np.ones((2, 1), np.float32))
    pieces = [(0, "v", -1, -1), (1, "v", -1, -1)]
    first = combined.get([a, b], pieces, True)
    assert combined.get([a, b], pieces, True) is first
    np.testing.assert_array_equal(first.values[:, 0], [0, 0, 0, 1, 1])
    # other frame ranges of the same results: another value
    sliced = combined.get([a, b], [(0, "v", 1, 3), (1, "v", 0, 1)], True)
    np.testing.assert_array_equal(sliced.values[:, 0], [0, 0, 1])
    # new results (even equal ones) never see the old join
    c = _result("a", np.full((3, 1), 7, np.float32))
    other = combined.get([c, b], pieces, True)
    assert other is not first
    np.testing.assert_array_equal(other.values[:, 0], [7, 7, 7, 1, 1])
    combined.clear()
    assert combined.get([a, b], pieces, True) is not first


def test_entries_written_in_the_background_are_complete_when_run_returns(cache_dir):
    result = run(_fan_out(), chunk=8, scheduler="threads", cache=cache_dir)
    assert result.executed() == 7
    store = Cache(cache_dir)
    manifests = sorted(store.root.glob("objects/*/*/manifest.json"))
    assert len(manifests) == 7
    for path in manifests:
        manifest = json.loads(path.read_text())
        for name, info in manifest["files"].items():
            data = (path.parent / name).read_bytes()
            assert len(data) == info["size"]
            assert hashlib.sha256(data).hexdigest() == info["sha256"]  # hashed while written
    again = run(_fan_out(), chunk=8, scheduler="threads", cache=cache_dir)
    assert again.executed() == 0
    assert again.outputs["total"]["total"].value == pytest.approx(result.outputs["total"]["total"].value)


PRELOADED = '''
from nodegraph import SEQUENCE, In, JsonValue, Node, NodeParams, Out, ParamSequence

class Preloading(Node):
    type_name = "test.PreloadProbe"
    kind = SEQUENCE
    preload = ("preload_probe_heavy", "preload_probe_missing_module")

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    total = Out(JsonValue)

    def run(self, values):
        import preload_probe_heavy
        return {"total": JsonValue(float(values.values.sum()) * preload_probe_heavy.FACTOR)}
'''


def test_preloaded_modules_are_imported_and_a_missing_one_is_harmless(tmp_path, monkeypatch):
    (tmp_path / "preload_probe.py").write_text(textwrap.dedent(PRELOADED))
    (tmp_path / "preload_probe_heavy.py").write_text("FACTOR = 3.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("preload_probe", "preload_probe_heavy"):
        sys.modules.pop(name, None)
    __import__("preload_probe")
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=4, slope=1.0)
    probe = g.add("test.PreloadProbe", id="probe")
    g.connect(ramp["values"], probe["values"])
    result = run(g, scheduler="threads", cache=False)
    assert result.outputs["probe"]["total"].value == pytest.approx(3.0 * (0 + 1 + 2 + 3))
    assert "preload_probe_heavy" in sys.modules


def test_finite_check_by_sum_still_finds_every_bad_value():
    faces = np.array([[0, 1, 2]])
    MeshSequence(np.full((4, 3, 3), 3e38, np.float32), faces).validate()  # finite; the sum overflows: full check
    for bad in (np.nan, np.inf, -np.inf):
        vertices = np.zeros((6, 3, 3), np.float32)
        vertices[4, 1, 2] = bad
        with pytest.raises(ValueError, match=r"non-finite value at index \(4, 1, 2\)"):
            MeshSequence(vertices, faces).validate()


def test_a_run_waits_for_a_preload_still_importing(tmp_path, monkeypatch):
    # a run that fails within seconds returned, and the command exited, while the preload thread
    # was importing (exit -6, "terminate called without an active exception"): run() waits for it
    from nodegraph import runner, tasks

    marker = tmp_path / "imported"
    (tmp_path / "slow_module_for_preload.py").write_text(
        f"import time\ntime.sleep(1.0)\nopen({str(marker)!r}, 'w').write('done')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    real_run = runner._run

    def run_with_a_slow_preload(*args, **kwargs):
        tasks.preload(["slow_module_for_preload"])
        return real_run(*args, **kwargs)

    monkeypatch.setattr(runner, "_run", run_with_a_slow_preload)
    run(_fan_out(8), chunk=8, scheduler="sync", cache=False)
    assert marker.read_text() == "done"
