"""Run a shipped graph on a dask.distributed cluster with CPU workers and GPU workers, and show
which worker ran each node's tasks (docs/guide.md, "Clusters and GPUs"; tests/test_scale_out.py
runs it).

    python examples/cluster_run.py GRAPH.json [name=value ...] [--cpu-workers 2] [--gpu-workers 1]
                                   [--chunk 64] [--address tcp://head:8786]

Without `--address` it starts a cluster on this machine (`distributed.SpecCluster`: CPU workers
of one thread each, and GPU workers that offer the resource `gpu=1`, one task at a time, which
is how `dask worker --resources gpu=1` starts them on a farm). With `--address` it runs on that
cluster instead. The runner sends the tasks of nodes that declare `resources = {"gpu": 1}` (fit,
flow, dynamics) only to workers offering `gpu`; every other task goes to any worker. The worker
of each task is read from the cluster's task stream.
"""

from __future__ import annotations

import argparse
import collections
import logging
import sys
from typing import Any


def local_cluster(cpu_workers: int, gpu_workers: int) -> Any:
    """An in-process cluster: `cpu_workers` plain workers and `gpu_workers` offering `gpu=1`."""
    from distributed import Scheduler, SpecCluster, Worker

    workers: dict[str, dict] = {}
    for i in range(cpu_workers):
        workers[f"cpu-{i}"] = {"cls": Worker, "options": {"nthreads": 1, "name": f"cpu-{i}"}}
    for i in range(gpu_workers):
        workers[f"gpu-{i}"] = {"cls": Worker, "options": {"nthreads": 1, "name": f"gpu-{i}",
                                                          "resources": {"gpu": 1}}}
    scheduler = {"cls": Scheduler, "options": {"dashboard_address": None}}
    return SpecCluster(workers=workers, scheduler=scheduler, silence_logs=logging.ERROR)


def run_on_cluster(graph: str, parameters: dict[str, Any], client: Any, *, chunk: int = 64,
                   device: str = "auto") -> tuple[Any, dict[str, set[str]]]:
    """Run `graph` through `client`; return the run's result and node id -> names of the workers
    that ran its tasks."""
    from distributed import get_task_stream

    import nodegraph

    names = {address: w.get("name", address) for address, w in client.scheduler_info()["workers"].items()}
    with get_task_stream(client) as stream:
        result = nodegraph.run(graph, scheduler=client, chunk=chunk, cache=False, parameters=parameters,
                               device=device)
    where: dict[str, set[str]] = collections.defaultdict(set)
    for task in stream.data:  # keys: "NODE|CHUNK" computes, "meta|..." / "stage|..." bookkeeping
        node_id, _, rest = str(task["key"]).partition("|")
        if node_id not in ("meta", "stage") and rest:
            where[node_id].add(str(names.get(task["worker"], task["worker"])))
    return result, dict(where)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("graph")
    parser.add_argument("parameters", nargs="*", help="graph parameters, name=value")
    parser.add_argument("--cpu-workers", type=int, default=2)
    parser.add_argument("--gpu-workers", type=int, default=1)
    parser.add_argument("--chunk", type=int, default=64)
    parser.add_argument("--address", default="", help="an existing cluster's scheduler (tcp://host:port)")
    parser.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                        help="torch device of the nodes (auto: CUDA where the worker sees a GPU; cpu: "
                        "no task asks for a GPU worker)")
    args = parser.parse_args()
    from distributed import Client

    parameters = dict(p.split("=", 1) for p in args.parameters)
    if args.address:
        with Client(args.address) as client:
            result, where = run_on_cluster(args.graph, parameters, client, chunk=args.chunk, device=args.device)
    else:
        with local_cluster(args.cpu_workers, args.gpu_workers) as cluster, Client(cluster) as client:
            result, where = run_on_cluster(args.graph, parameters, client, chunk=args.chunk, device=args.device)
    for node_id in sorted(where):
        print(f"{node_id:24s} {', '.join(sorted(where[node_id]))}")
    print("ok" if result.ok else "failed")
    return 0 if result.ok else 1


if __name__ == "__main__":
    sys.exit(main())
