"""Nodes that `uses_run_log` (report.Html) get the records of every task upstream of them in the
current run, with any in-process or process scheduler; nothing downstream or beside them."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import SEQUENCE, Graph, In, JsonValue, Node, NodeParams, Out, ParamSequence, run


class RunLogProbe(Node):
    """Returns the run log it was handed: (node, status) pairs, sorted."""

    type_name = "test.RunLogProbe"
    kind = SEQUENCE
    cacheable = False
    uses_run_log = True

    class Params(NodeParams):
        pass

    values = In(ParamSequence)
    log = Out(JsonValue)

    def run(self, values: ParamSequence) -> dict:
        return {"log": JsonValue(sorted([r["node"], r["status"], r["frames"]] for r in self.run_log))}


def _graph() -> Graph:
    g = Graph()
    g.add("test.Ramp", "ramp", num_frames=20)
    g.add("test.Scale", "scale", factor=2.0)
    g.add("test.Scale", "beside", factor=3.0)  # not upstream of the probe
    g.add("test.RunLogProbe", "probe")
    g.connect("ramp.values", "scale.values")
    g.connect("ramp.values", "beside.values")
    g.connect("scale.scaled", "probe.values")
    return g


@pytest.mark.parametrize("scheduler", ["sync", "threads", "processes"])
def test_probe_sees_its_upstream_tasks_then_their_cache_hits(scheduler, tmp_path):
    first = run(_graph(), scheduler=scheduler, chunk=10, cache=tmp_path / "cache", outputs=["probe", "beside"])
    assert first.exit_code == 0, first.summary()
    want = [["ramp", "executed", [0, 10]], ["ramp", "executed", [10, 20]],
            ["scale", "executed", [0, 10]], ["scale", "executed", [10, 20]]]
    assert first.outputs["probe"]["log"].value == want
    again = run(_graph(), scheduler=scheduler, chunk=10, cache=tmp_path / "cache", outputs=["probe", "beside"])
    # scale is read from the cache, so its inputs are not needed: the ramp is not part of this run
    assert again.outputs["probe"]["log"].value == [["scale", "cached", [0, 10]], ["scale", "cached", [10, 20]]]
    assert again.executed() == again.executed("probe") == 1  # not cacheable: it always runs


def test_a_node_outside_a_run_has_an_empty_log():
    from nodegraph import run_node
    from nodegraph.testing import Ramp

    values = run_node(Ramp, {"num_frames": 3})["values"]
    assert run_node(RunLogProbe, values=values)["log"].value == []
    assert np.isfinite(values.values).all()
