"""A failing node: other branches finish and are cached, failures are recorded, exit code 1."""

from __future__ import annotations

import json
from pathlib import Path

from nodegraph import run

from .helpers import two_branches


def test_failing_branch_does_not_stop_the_other(cache_dir):
    result = run(two_branches(fail_frames=[12]), chunk=5, scheduler="threads", cache=cache_dir)
    assert not result.ok and result.exit_code == 1
    assert "total_good" in result.outputs and "total_bad" not in result.outputs
    assert result.outputs["total_good"]["total"].value == 3.0 * sum(range(30))
    assert result.count("failed", "fail") == 1 and result.count("skipped", "total_bad") == 1
    assert result.executed("fail") == 5  # the other chunks of the failing node ran
    (failure,) = result.failures
    assert failure["node"] == "fail" and failure["frames"] == [10, 15]
    assert "deliberate failure at frame 12" in failure["message"] and "RuntimeError" in failure["traceback"]
    assert failure["input_keys"]["values"] and len(failure["input_keys"]["values"][0]) == 64
    record = json.loads(Path(failure["record"]).read_text())
    assert record["node"] == "fail" and record["frames"] == [10, 15] and record["exception"] == "RuntimeError"
    # the good branch was cached: a re-run computes nothing there
    again = run(two_branches(fail_frames=[12]), chunk=5, scheduler="sync", cache=cache_dir)
    assert again.executed("scale") == 0 and again.executed("total_good") == 0
    assert again.count("failed", "fail") == 1 and again.count("cached", "fail") == 5  # only the failed chunk re-ran


def test_bad_input_failure_gives_exit_code_2(cache_dir):
    g = two_branches(fail_frames=[3])
    g.set("fail", bad_input=True)
    result = run(g, chunk=5, scheduler="sync", cache=cache_dir)
    assert result.exit_code == 2
    assert "'values': frame 3 is not acceptable" in result.failures[0]["message"]


def test_error_record_is_cleared_after_success(cache_dir):
    result = run(two_branches(fail_frames=[12]), chunk=5, scheduler="sync", cache=cache_dir)
    record = Path(result.failures[0]["record"])
    assert record.exists()
    fixed = run(two_branches(fail_frames=[]), chunk=5, scheduler="sync", cache=cache_dir)
    assert fixed.ok and not record.exists()
