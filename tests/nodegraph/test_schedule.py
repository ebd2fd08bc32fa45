"""Planning and chunking: results equal whatever the chunk size; halos; chunk grid."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import run
from nodegraph.plan_names import PortSlot, TaskName
from nodegraph.schedule import chunk_bounds, parse_frames, plan_run

from .helpers import chain


def _reference(num_frames: int = 40, factor: float = 2.0) -> dict[str, np.ndarray]:
    """Independent float32 computation of the chain."""
    x = (0.5 * np.arange(num_frames)).astype(np.float32) * np.float32(factor)
    padded = np.concatenate([np.repeat(x[:1], 3), x, np.repeat(x[-1:], 3)])
    avg = np.zeros_like(x)
    for shift in range(7):
        avg += padded[shift:shift + num_frames]
    avg /= np.float32(7)
    return {"scale": x, "avg": avg, "cum": np.cumsum(avg, dtype=np.float32)}


def test_chunk_bounds_follow_absolute_grid():
    assert chunk_bounds(range(0, 10), 4) == [(0, 4), (4, 8), (8, 10)]
    assert chunk_bounds(range(5, 13), 4) == [(5, 8), (8, 12), (12, 13)]
    assert chunk_bounds(range(0, 3), 10) == [(0, 3)]


def test_parse_frames():
    assert parse_frames("3:9") == range(3, 9) and parse_frames("12") == range(0, 12)
    with pytest.raises(ValueError, match="--frames"):
        parse_frames("9:3")


@pytest.mark.parametrize("chunk", [1, 7, 40])
def test_chunked_equals_unchunked_framewise_and_windowed(chunk):
    ref = _reference()
    result = run(chain(), chunk=chunk, scheduler="sync", cache=False, outputs=["scale", "avg", "cum"])
    assert result.ok
    for node, port in [("scale", "scaled"), ("avg", "averaged"), ("cum", "total")]:
        got = result.outputs[node][port].values.ravel()
        np.testing.assert_array_equal(got, ref[node], err_msg=f"{node} at chunk {chunk}")


def test_windowed_tasks_get_halo_and_trim():
    plan = plan_run(chain(), chunk=10)
    task = plan.tasks[TaskName("avg", (10, 20))]
    assert task.frames == (7, 23) and task.out_frames == (10, 20)
    assert plan.tasks[TaskName("avg", (0, 10))].frames == (0, 13)
    assert plan.tasks[TaskName("avg", (30, 40))].frames == (27, 40)
    assert [p.task for p in task.inputs[PortSlot("values")]] == [TaskName("scale", (s, s + 10)) for s in (0, 10, 20)]


def test_sub_range_of_frames():
    result = run(chain(), frames=range(10, 30), chunk=8, scheduler="sync", cache=False, outputs=["scale"])
    np.testing.assert_array_equal(result.outputs["scale"]["scaled"].values.ravel(),
                                  (0.5 * np.arange(10, 30)).astype(np.float32) * 2)
