"""Outputs no edge reads are not computed by a node that `skips_unread_outputs`, and the cache
never hands a later run an entry without an output it reads; `Node.import_first` modules are
imported by the runner's thread before the tasks."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import FRAMEWISE, Graph, In, Node, NodeError, NodeParams, Out, Param, ParamSequence, run
from nodegraph.schedule import plan_run
from nodegraph.node import execute

COMPUTED: list[str] = []  # the outputs the probes computed, in order


def _column(values: np.ndarray) -> ParamSequence:
    return ParamSequence(values[:, None].astype(np.float64), ["v"])


class SplitProbe(Node):
    """Doubles and squares its values; computes only the outputs read."""

    type_name = "test.SplitProbe"
    kind = FRAMEWISE
    skips_unread_outputs = True

    values = In(ParamSequence)
    double = Out(ParamSequence)
    square = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        x = values.values[:, 0]
        out = {}
        for name, value in (("double", 2.0 * x), ("square", x * x)):
            if self.wants(name):
                COMPUTED.append(name)
                out[name] = _column(value)
        return out


class LazyWithoutOptIn(Node):
    """Leaves out an output without declaring `skips_unread_outputs` (an error)."""

    type_name = "test.LazyWithoutOptIn"
    kind = FRAMEWISE

    values = In(ParamSequence)
    double = Out(ParamSequence)
    square = Out(ParamSequence)

    def run(self, values: ParamSequence) -> dict:
        return {"double": _column(2.0 * values.values[:, 0])}


def _graph(read: tuple[str, ...], probe: str = "test.SplitProbe") -> Graph:
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=6, start=1.0, slope=1.0)
    split = g.add(probe, id="split")
    g.connect(ramp["values"], split["values"])
    for port in read:
        total = g.add("test.Total", id=f"total_{port}")
        g.connect(split[port], total["values"])
    return g


def _totals(result) -> dict[str, float]:
    return {node: float(ports["total"].value) for node, ports in result.outputs.items()}


def test_unread_output_is_not_computed_and_reads_are_right(tmp_path):
    COMPUTED.clear()
    result = run(_graph(("double",)), scheduler="sync", cache=False)
    assert result.ok
    assert COMPUTED == ["double"]
    assert _totals(result) == {"total_double": 2.0 * 21.0}  # 2 x (1 + ... + 6)


def test_cache_entry_without_an_output_is_not_reused(tmp_path):
    cache = tmp_path / "cache"
    COMPUTED.clear()
    assert run(_graph(("double",)), scheduler="sync", cache=cache).ok
    assert COMPUTED == ["double"]
    COMPUTED.clear()
    both = run(_graph(("double", "square")), scheduler="sync", cache=cache)
    assert both.ok
    assert sorted(COMPUTED) == ["double", "square"]  # recomputed: the first entry lacks `square`
    assert _totals(both) == {"total_double": 42.0, "total_square": 91.0}
    COMPUTED.clear()
    again = run(_graph(("double",)), scheduler="sync", cache=cache)  # its own entry is still there
    assert again.ok and COMPUTED == [] and _totals(again) == {"total_double": 42.0}


def test_plan_keys_differ_by_the_outputs_read():
    one = plan_run(_graph(("double",)))
    two = plan_run(_graph(("double", "square")))
    task_one = next(t for t in one.tasks.values() if t.node == "split")
    task_two = next(t for t in two.tasks.values() if t.node == "split")
    assert task_one.description["outputs"] == ["double"]
    assert "outputs" not in task_two.description  # all read: the key of a node that computes all
    assert task_one.key != task_two.key


def test_a_target_returns_every_output():
    COMPUTED.clear()
    result = run(_graph(("double",)), scheduler="sync", cache=False, outputs=["split"])
    assert result.ok and sorted(COMPUTED) == ["double", "square"]
    assert set(result.outputs["split"]) == {"double", "square"}


def test_leaving_out_an_output_needs_the_opt_in():
    with pytest.raises(NodeError, match="returned ports"):
        execute(LazyWithoutOptIn(), {"values": _column(np.arange(3.0))}, range(3), range(3), wanted=["double"])


def test_wanted_output_left_out_is_an_error():
    node = SplitProbe()
    node.run = lambda values: {}  # type: ignore[method-assign]
    with pytest.raises(NodeError, match="wanted \\['double'\\]"):
        execute(node, {"values": _column(np.arange(3.0))}, range(3), range(3), wanted=["double"])


def test_unknown_wanted_output_is_an_error():
    with pytest.raises(NodeError, match="unknown output"):
        execute(SplitProbe(), {"values": _column(np.arange(3.0))}, range(3), range(3), wanted=["cube"])


def test_explain_names_the_outputs_read(tmp_path):
    from nodegraph.explain import explain

    cache = tmp_path / "cache"
    assert run(_graph(("double",)), scheduler="sync", cache=cache, outputs=["split"]).ok  # a target: all outputs
    rows = {row["node"]: row for row in explain(_graph(("double",)), cache=cache)}
    assert not rows["split"]["hit"]
    assert rows["split"]["reason"] == ("outputs read changed (all -> double: the node computes only the "
                                       "outputs an edge reads)")


class ImportFirstProbe(Node):
    """Imports `module` in run; names it in `import_first`."""

    type_name = "test.ImportFirstProbe"
    kind = FRAMEWISE

    class Params(NodeParams):
        module: str = Param("", description="module imported first")

    values = In(ParamSequence)
    seen = Out(ParamSequence)

    def import_first(self) -> tuple[str, ...]:
        return (self.params.module,)

    def run(self, values: ParamSequence) -> dict:
        import importlib
        import sys

        already = self.params.module in sys.modules  # imported before this task ran
        module = importlib.import_module(self.params.module)
        COMPUTED.append(f"{already} {module.THREAD}")
        return {"seen": values}


def test_import_first_modules_are_imported_on_the_runner_thread_before_the_tasks(tmp_path, monkeypatch):
    # a C extension whose initialisers wait for the GIL inside the loader (pxr) must not be
    # imported by a task thread while another holds the GIL (numpy's dladdr): the runner imports it
    (tmp_path / "import_first_probe_mod.py").write_text("import threading\nTHREAD = threading.current_thread().name\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=4)
    probe = g.add("test.ImportFirstProbe", id="probe", module="import_first_probe_mod")
    g.connect(ramp["values"], probe["values"])
    COMPUTED.clear()
    assert run(g, scheduler="threads", cache=False, chunk=2).ok
    assert COMPUTED == ["True MainThread"] * 2
