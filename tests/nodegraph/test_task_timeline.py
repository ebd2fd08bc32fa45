"""Task records carry when each task began (`started`), and bench/profile_graphs.py's concurrency
table reads them: seconds with 0, 1, 2+ tasks running and the nodes that ran alone."""

from __future__ import annotations

import importlib.util
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from nodegraph import run

from .helpers import chain

BENCH = Path(__file__).resolve().parents[2] / "bench"


def test_executed_tasks_record_when_they_began():
    before = time.time()
    result = run(chain(), chunk=7, scheduler="threads", cache=False, workers=2)
    after = time.time()
    assert result.ok
    for task in result.tasks:
        assert task["status"] == "executed"
        assert before <= task["started"] <= task["started"] + task["seconds"] <= after + 1e-3


@pytest.fixture(scope="module")
def profile_graphs():
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location("profile_graphs", BENCH / "profile_graphs.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


def test_concurrency_counts_overlaps(profile_graphs):
    # a alone 0-2, a and b together 2-3, b alone 3-4, nothing 4-5, c alone 5-6; d failed (ignored)
    tasks = [{"node": "a", "status": "executed", "started": 100.0, "seconds": 3.0},
             {"node": "b", "status": "executed", "started": 102.0, "seconds": 2.0},
             {"node": "c", "status": "executed", "started": 105.0, "seconds": 1.0},
             {"node": "d", "status": "failed", "started": 100.0, "seconds": 6.0}]
    at_once, alone = profile_graphs.concurrency(SimpleNamespace(tasks=tasks), 100.0, 106.0, 2)
    assert at_once == pytest.approx([1.0, 4.0, 1.0])
    assert alone == pytest.approx({"a": 2.0, "b": 1.0, "c": 1.0})
