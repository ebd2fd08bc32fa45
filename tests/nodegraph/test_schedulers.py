"""The same graph gives equal results on every dask scheduler, a local cluster included."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import run

from .helpers import chain


@pytest.fixture(scope="module")
def reference():
    return run(chain(), chunk=40, scheduler="sync", cache=False).outputs["cum"]["total"].values


@pytest.mark.parametrize("scheduler", ["sync", "threads", "processes"])
def test_local_schedulers_agree(scheduler, reference, cache_dir):
    result = run(chain(), chunk=7, scheduler=scheduler, cache=cache_dir, workers=2)
    assert result.ok
    np.testing.assert_array_equal(result.outputs["cum"]["total"].values, reference)


def test_distributed_local_cluster_agrees(reference, cache_dir):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        result = run(chain(), chunk=7, scheduler=cluster.scheduler_address, cache=cache_dir)
    assert result.ok and result.executed() == 19
    np.testing.assert_array_equal(result.outputs["cum"]["total"].values, reference)
