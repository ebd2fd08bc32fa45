"""Framework overhead: per-task cost of a trivial framewise node, and cached re-run vs cold run.

Run: python bench/framework_overhead.py [--scheduler threads]

1. A trivial framewise node (`test.Scale`) over 10,000 frames at chunk sizes 10, 100, 1000:
   wall time per task, without cache (pure scheduling) and with a cold cache (plus writes).
2. A 5-node chain (Ramp -> Scale x4): cold run, then the last node's parameter changed; the
   ratio (re-run / cold run) shows how little is recomputed.
3. `graphs/synthetic_capture.json` at 651 frames, the whole `nodegraph run` command (process
   start included): cold, unchanged re-run, re-run after the last node's (the report's)
   parameter changed, and after one written file was deleted.
4. Input-file hashing of a 1 GB file: first sight (streamed sha256), second sight in a new
   process (remembered in the cache by path, size and mtime).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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
    parser.add_argument("--capture-frames", type=int, default=651)
    parser.add_argument("--hash-gb", type=float, default=1.0)
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

    if args.frames >= 1000:
        synthetic_capture(args.capture_frames)
        input_hash(args.hash_gb)


def _cli(*argv: str) -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "nodegraph.cli", "run", *argv, "--progress", "none"], check=True,
                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def synthetic_capture(num_frames: int) -> None:
    graph = str(Path(__file__).resolve().parents[1] / "graphs" / "synthetic_capture.json")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        argv = [graph, f"num_frames={num_frames}", f"capture={out}/capture.npz", f"truth={out}/truth.npz",
                f"truth_rigid={out}/rigid.json", f"expressions={out}/expressions.json", f"report={out}/report",
                "--cache", f"{out}/cache"]
        cold = _cli(*argv)
        same = _cli(*argv)
        mtime = (out / "capture.npz").stat().st_mtime_ns
        changed = _cli(*argv, "--set", "report.vertices=[10,200,3000,9000]")
        (out / "report" / "histograms.png").unlink()
        deleted_report = _cli(*argv, "--set", "report.vertices=[10,200,3000,9000]")
        (out / "truth.npz").unlink()
        deleted_big = _cli(*argv, "--set", "report.vertices=[10,200,3000,9000]")
        untouched = (out / "capture.npz").stat().st_mtime_ns == mtime
    print(f"\ngraphs/synthetic_capture.json, {num_frames} frames, whole command (process start included)")
    print(f"cold: {cold:.2f} s")
    print(f"unchanged re-run: {same:.2f} s, ratio {same / cold:.3f} (capture.npz mtime untouched: {untouched})")
    print(f"last node's parameter changed: {changed:.2f} s, ratio {changed / cold:.3f}")
    print(f"report PNG deleted (restored from the cache): {deleted_report:.2f} s, ratio {deleted_report / cold:.3f}")
    print(f"210 MB truth NPZ deleted (saver re-runs on cached input): {deleted_big:.2f} s, "
          f"ratio {deleted_big / cold:.3f}")


def input_hash(gigabytes: float) -> None:
    from nodegraph.cache import Cache

    probe = ("import sys, time; from nodegraph.cache import Cache; t = time.perf_counter(); "
             "Cache(sys.argv[1]).file_hash(sys.argv[2]); print(time.perf_counter() - t)")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.bin"
        block = os.urandom(1 << 20)
        with open(path, "wb") as fh:
            for _ in range(int(gigabytes * 1024)):
                fh.write(block)
        runs = [float(subprocess.run([sys.executable, "-c", probe, f"{tmp}/cache", str(path)], check=True,
                                     capture_output=True, text=True).stdout) for _ in range(2)]
        assert Cache(f"{tmp}/cache").file_hash(path)
    print(f"\ninput hash of a {gigabytes:g} GB file: first sight {runs[0]:.2f} s, "
          f"second sight (new process) {1e3 * runs[1]:.2f} ms")


if __name__ == "__main__":
    main()
