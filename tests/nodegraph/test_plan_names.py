"""Task names and input slots are typed values whose text is the one caches and logs have always held."""

from __future__ import annotations

from pathlib import Path

import pytest

from nodegraph import Graph, run
from nodegraph.cache import make_key
from nodegraph.node import Node
from nodegraph.plan_names import PortSlot, TaskName
from nodegraph.runner import explain
from nodegraph.schedule import plan_run


def test_text_of_names_and_slots():
    assert str(TaskName("fit", (0, 64))) == "fit|0:64"
    assert str(TaskName("model", None)) == "model|all"
    assert str(PortSlot("views")) == "views"
    assert str(PortSlot("views", 0)) == "views#0" and str(PortSlot("views", 12)) == "views#12"
    assert TaskName("fit", (0, 64)) == TaskName("fit", (0, 64)) != TaskName("fit", (64, 128))
    assert PortSlot("views", 0) != PortSlot("views") and len({PortSlot("a", 1), PortSlot("a", 1)}) == 1


def _writers(folder: Path, connections: int = 2, fail: bool = False) -> Graph:
    """ramp -> summary (sequence writer) x connections -> join (static, a list port of Files)."""
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=20)
    g.add("test.JoinFiles", id="join", path=str(folder / "joined.txt"), fail=fail)
    for i in range(connections):
        g.add("test.WriteSummary", id=f"summary{i}", folder=str(folder / f"s{i}"))
        g.connect("ramp.values", f"summary{i}.values")
        g.connect(f"summary{i}.files", "join.parts")
    return g


def test_plan_names_tasks_and_list_port_slots(tmp_path):
    plan = plan_run(_writers(tmp_path), chunk=8)
    assert plan.by_node["ramp"] == [TaskName("ramp", (0, 8)), TaskName("ramp", (8, 16)), TaskName("ramp", (16, 20))]
    assert plan.by_node["summary1"] == [TaskName("summary1", (0, 20))]  # sequence: the whole range
    join = plan.tasks[TaskName("join", None)]  # static: no frame range
    assert join.mode == "static" and join.name == TaskName("join", None)
    assert list(join.inputs) == [PortSlot("parts", 0), PortSlot("parts", 1)]  # edge order
    assert [p.task for p in join.inputs[PortSlot("parts", 1)]] == [TaskName("summary1", (0, 20))]
    # the key description names the slots by their text, as every cache entry so far does
    assert sorted(join.description["inputs"]) == ["parts#0", "parts#1"]
    assert join.description["inputs"]["parts#1"][0][0] == plan.tasks[TaskName("summary1", (0, 20))].key


def test_key_layout_is_unchanged(monkeypatch):
    """The key of every task of a fixed graph, with the code hash held fixed: these digests were
    printed before list ports and task names became types; any change to what a key hashes
    (and so a cache miss for every existing entry) changes them."""
    monkeypatch.setattr(Node, "code_hash", classmethod(lambda cls: "code-of-" + cls.type_name))
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=20)
    g.add("test.Weighted", id="w")
    g.connect("ramp.values", "w.values")
    g.connect("ramp.values", "w.values")
    g.add("test.Total", id="total")
    g.connect("w.total", "total.values")
    plan = plan_run(g, chunk=10)
    keys = {str(name): task.key for name, task in plan.tasks.items()}
    assert all(task.key == make_key(task.description) for task in plan.tasks.values())
    assert keys == {
        "ramp|0:10": "35df91fb999ce7916d0b77f25efab24e44c4a16bdd7aae9b2c921395ca21382a",
        "ramp|10:20": "c5ce85a88224d343481a4fa1cd7b81ea39affe1ecd8343b8db18df1b2ce6c0e6",
        "w|0:10": "48811d65ce7c036ae6fc37d89a205b62cdf5c793c33d483ca88e3159b1c26b2d",
        "w|10:20": "4854a5566b97ddaca3970599baab135d5f12c48f3d7b770ea459a9427fb4b09e",
        "total|0:20": "ae4706b958ed972b9dcd9a03cea00a2712b5c5d68c80d0ce5d9206fd8f9e0e33",
    }


def test_failure_record_of_a_static_task_has_no_frames(tmp_path):
    result = run(_writers(tmp_path, fail=True), chunk=8, scheduler="sync", cache=False)
    (failure,) = result.failures
    assert failure["node"] == "join" and failure["frames"] is None
    assert set(failure["input_keys"]) == {"parts#0", "parts#1"}
    assert [t["name"] for t in result.tasks if t["node"] == "join"] == ["join|all"]


@pytest.mark.parametrize("connections", [1, 3])
def test_explain_names_the_list_port_whose_connections_changed(tmp_path, connections):
    cache = tmp_path / "cache"
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=20)
    g.add("test.Weighted", id="w")
    g.connect("ramp.values", "w.values")
    g.connect("ramp.values", "w.values")
    assert run(g, chunk=10, scheduler="sync", cache=cache).ok
    changed = Graph()
    changed.add("test.Ramp", id="ramp", num_frames=20)
    changed.add("test.Weighted", id="w")
    for _ in range(connections):
        changed.connect("ramp.values", "w.values")
    rows = [r for r in explain(changed, chunk=10, cache=cache) if r["node"] == "w"]
    assert [r["reason"] for r in rows] == ["upstream 'values' changed"] * 2


def test_writer_tags_are_written_and_read_back_in_one_place():
    import os
    import subprocess
    import sys

    from nodegraph.writer_tag import HOST, WriterTag

    tag = WriterTag.new(12)
    assert (tag.host, tag.pid, len(tag.nonce)) == (HOST, os.getpid(), 12)
    assert WriterTag.of_name(f"{'a' * 64}.{tag}") == tag == WriterTag.of_name(f".nodegraph-staging.{tag}")
    assert WriterTag.of_name(str(tag)) == tag
    assert WriterTag.of_name("notes.txt") is None and WriterTag.of_name("a.b.c") is None
    assert not tag.writer_gone()  # this process
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True).stdout)
    assert WriterTag(HOST, dead, "x").writer_gone()
    assert not WriterTag("another-host", dead, "x").writer_gone()  # cannot be checked from here
