"""Framework overhead: per-task cost of a trivial framewise node, and cached re-run vs cold run.

Run: python bench/framework_overhead.py [--scheduler threads]

1. A trivial framewise node (`test.Scale`) over 10,000 frames at chunk sizes 10, 100, 1000:
   wall time per task, without cache (pure scheduling) and with a cold cache (plus writes).
2. A 5-node chain (Ramp -> Scale x4): cold run, then the last node's parameter changed; the
   ratio (re-run / cold run) shows how little is recomputed.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import nodegraph.testing  # noqa: F401  (registers test.* nodes)
from nodegraph import Graph, run


def trivial(num_frames: int) -> Graph:
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=num_frames)
    scale = g.add("test.Scale", id="scale", factor=2.0)
    g.connect(ramp["values"], scale["values"])
    return g


def chain5(num_frames: int, last_factor: float) -> Graph:
    g = Graph()
    prev = g.add("test.Ramp", id="n0", num_frames=num_frames)["values"]
    for i in range(1, 5):
        node = g.add("test.Scale", id=f"n{i}", factor=last_factor if i == 4 else 1.0 + i)
        g.connect(prev, node["values"])
        prev = node["scaled"]
    return g


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scheduler", default="threads")
    parser.add_argument("--frames", type=int, default=10_000)
    args = parser.parse_args()

    print(f"trivial framewise node (2 nodes: source + scale), {args.frames} frames, scheduler={args.scheduler}")
    print(f"{'chunk':>6} {'tasks':>6} {'no cache s':>11} {'ms/task':>8} {'cold cache s':>13} {'ms/task':>8}")
    for chunk in (10, 100, 1000):
        g = trivial(args.frames)
        t0 = time.perf_counter()
        result = run(g, chunk=chunk, scheduler=args.scheduler, cache=False)
        nocache = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            run(g, chunk=chunk, scheduler=args.scheduler, cache=tmp)
            cold = time.perf_counter() - t0
        tasks = len(result.tasks)
        print(f"{chunk:>6} {tasks:>6} {nocache:>11.3f} {1e3 * nocache / tasks:>8.3f} {cold:>13.3f} "
              f"{1e3 * cold / tasks:>8.3f}")

    print(f"\n5-node chain, {args.frames} frames, chunk 100: change the last node's parameter")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        cold = run(chain5(args.frames, 5.0), chunk=100, scheduler=args.scheduler, cache=tmp)
        cold_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        warm = run(chain5(args.frames, 6.0), chunk=100, scheduler=args.scheduler, cache=tmp)
        warm_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        hit = run(chain5(args.frames, 6.0), chunk=100, scheduler=args.scheduler, cache=tmp)
        hit_s = time.perf_counter() - t0
    print(f"cold run: {cold_s:.3f} s ({cold.executed()} tasks executed)")
    print(f"last param changed: {warm_s:.3f} s ({warm.executed()} executed, {warm.count('cached')} loaded); "
          f"ratio {warm_s / cold_s:.3f}")
    print(f"nothing changed: {hit_s:.3f} s ({hit.executed()} executed); ratio {hit_s / cold_s:.3f}")


if __name__ == "__main__":
    main()
