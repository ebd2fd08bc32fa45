"""Where the time goes: task time per node and per stage of the demo and of the video graph,
the critical path, and import times.

Run: python bench/profile_graphs.py [--demo-frames 100] [--video-frames 12] [--video-size 512]
     [--workers 2] [--skip-demo] [--skip-video] [--skip-imports]

Prints, for `graphs/demo.json` (a performance of `--demo-frames` frames, the default 100) and for
`graphs/fit_video_temporal.json` on a talking-head video made from skimage's astronaut
(`--video-frames` frames, bench/smoothing.py's video: the photo panned, zoomed and rolled, the
jaw opened and shut, sensor noise and JPEG; made at 256^2 and resized to `--video-size`), two
tables per graph:

- per node: its task time (summed over its chunks: the work; with 2 workers the wall time is
  less), its share of all task time, its chunk count, the time per frame it covers, and its
  seconds on the run's critical path (the longest chain of dependent tasks, by their measured
  seconds: what bounds the wall time however many workers run);
- per stage (the nodes grouped by what they do: capture, stabilize, dynamics, render,
  landmarks, identity + appearance, rigid, expression, flags, flow, temporal, reports and
  writers): the same columns, the stage's task seconds per frame and its critical-path seconds;

then the run's wall time, its critical path, and the rest (wall minus critical path: waiting
for a free worker, scheduling, the workers' first imports inside tasks); then how many tasks ran
at once over the wall (0, 1, 2+ with 2 workers: the seconds with one task running are seconds a
worker sat idle) and the nodes that ran alone longest (a serial chain: where a faster node, or one
that uses both cores, shortens the wall). Before both, the
import time of the packages a run loads (each in a fresh interpreter, the least of three).
Every run is uncached (`cache=False`) with the `threads` scheduler and `--workers` workers
(2, as `nodegraph run` does by default). Timings depend on the machine's load: print `uptime`
beside them. bench/profile_graphs_results.md holds a printed run.
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from smoothing import astronaut_video

ROOT = Path(__file__).resolve().parents[1]
DEMO_OUTPUTS = {"html": "index.html", "report": "stabilization", "dynamics_report": "dynamics",
                "fit_report": "fit", "motion_report": "motion"}
IMPORTS = ("numpy", "torch", "numba", "dask", "distributed", "matplotlib.pyplot", "nodegraph", "nodes.fit",
           "nodes.landmarks", "nodes.render", "nodes.temporal", "nodes.flow")

# stage of a node, by its type (first match); the fit's own stages by type name
STAGES = (
    ("identity + appearance", ("fit.EstimateIdentity", "fit.EstimateAppearance")),
    ("rigid", ("fit.RigidPose",)),
    ("expression", ("fit.Expression",)),
    ("flags", ("fit.FlagFailures",)),
    ("reports + writers", ("report.", "fit.FitReport", "fit.SaveFit", "temporal.MotionReport", "export.",
                           "landmarks.SaveLandmarks", "landmarks.LandmarkOverlays", "io.Save")),
    ("capture", ("synth.", "io.", "mesh.")),
    ("stabilize", ("rigid.", "stabilize.")),
    ("dynamics", ("dynamics.",)),
    ("render", ("render.",)),
    ("landmarks", ("landmarks.",)),
    ("camera", ("fit.PlateCamera",)),
    ("flow", ("flow.",)),
    ("temporal", ("temporal.",)),
)


def stage_of(node_type: str) -> str:
    for stage, prefixes in STAGES:
        if any(node_type == p or (p.endswith(".") and node_type.startswith(p)) for p in prefixes):
            return stage
    return "other"


def import_seconds(module: str) -> float:
    """Wall seconds of `import module` in a fresh interpreter (the least of three)."""
    best = float("inf")
    for _ in range(3):
        out = subprocess.run([sys.executable, "-c", f"import time; t = time.perf_counter(); import {module}; "
                              "print(time.perf_counter() - t)"], capture_output=True, text=True, cwd=ROOT)
        best = min(best, float(out.stdout.strip().splitlines()[-1]))
    return best


def critical_path(result) -> tuple[float, dict[str, float]]:
    """The longest chain of dependent tasks by their measured seconds: its length and each
    node's seconds on it."""
    seconds = {t["name"]: float(t.get("seconds") or 0.0) for t in result.tasks}
    plan = result.plan
    finish: dict[str, float] = {}
    came_from: dict[str, str | None] = {}

    def visit(name) -> float:  # memoized longest finish time (the plan is a DAG)
        key = str(name)
        if key not in finish:
            deps = [d for d in plan.tasks[name].deps if d in plan.tasks]
            best, prev = 0.0, None
            for dep in deps:
                f = visit(dep)
                if f > best:
                    best, prev = f, str(dep)
            finish[key] = best + seconds.get(key, 0.0)
            came_from[key] = prev
        return finish[key]

    sys.setrecursionlimit(max(sys.getrecursionlimit(), 10 * len(plan.tasks) + 100))
    for name in plan.tasks:
        visit(name)
    if not finish:
        return 0.0, {}
    end = max(finish, key=finish.get)
    node_of = {str(n): p.node for n, p in plan.tasks.items()}
    on_path: dict[str, float] = collections.defaultdict(float)
    key: str | None = end
    while key is not None:
        on_path[node_of[key]] += seconds.get(key, 0.0)
        key = came_from[key]
    return finish[end], dict(on_path)


def tables(result) -> tuple[list[tuple], list[tuple], float, float]:
    """Rows per node and per stage: (name, task s, chunks, frames covered, critical-path s),
    largest task time first; and the total task time and the critical path."""
    types = {p.node: p.node_type for p in result.plan.tasks.values()}
    seconds: dict[str, float] = collections.defaultdict(float)
    chunks: dict[str, int] = collections.defaultdict(int)
    frames: dict[str, int] = collections.defaultdict(int)
    for task in result.tasks:
        if task.get("status") == "executed":
            seconds[task["node"]] += float(task.get("seconds") or 0.0)
            chunks[task["node"]] += 1
            a, b = task.get("frames") or (0, 0)
            frames[task["node"]] += b - a
    path, on_path = critical_path(result)
    nodes = sorted(((n, s, chunks[n], frames[n], on_path.get(n, 0.0), types.get(n, "?")) for n, s in seconds.items()),
                   key=lambda row: -row[1])
    by_stage: dict[str, list[float]] = collections.defaultdict(lambda: [0.0, 0, 0, 0.0])
    for n, s, c, f, p, t in nodes:
        row = by_stage[stage_of(t)]
        row[0] += s
        row[1] += c
        row[2] = max(row[2], f)
        row[3] += p
    stages = sorted(((k, *v) for k, v in by_stage.items()), key=lambda row: -row[1])
    return nodes, stages, sum(s for _, s, *_ in nodes), path


def print_tables(title: str, result, frames: int, wall: float) -> None:
    nodes, stages, total, path = tables(result)
    print(f"\n{title}: {frames} frames, {'ok' if result.ok else 'FAILED'}, {len(result.tasks)} tasks; "
          f"wall {wall:.1f} s ({wall / frames:.3f} s a frame), task time {total:.1f} s, critical path {path:.1f} s, "
          f"wall - critical path {wall - path:.1f} s (waiting for a worker, scheduling, first imports)")
    print(f"  {'node':22s} {'type':26s} {'task s':>8s} {'share':>6s} {'chunks':>6s} {'s/frame':>8s} {'path s':>7s}")
    for node, s, n, f, p, t in nodes:
        if s >= 0.05:
            print(f"  {node:22s} {t:26s} {s:8.2f} {100 * s / total:5.1f}% {n:6d} {s / max(f, 1):8.3f} {p:7.2f}")
    print(f"  per stage:")
    print(f"  {'stage':49s} {'task s':>8s} {'share':>6s} {'chunks':>6s} {'s/frame':>8s} {'path s':>7s}")
    for stage, s, n, f, p in stages:
        print(f"  {stage:49s} {s:8.2f} {100 * s / total:5.1f}% {n:6d} {s / frames:8.3f} {p:7.2f}")
    for task in result.tasks:
        error = task.get("error") or {}
        if task.get("status") == "failed" and isinstance(error, dict) and error.get("message"):
            print(f"  failed: {error['message']}")


def concurrency(result, began: float, ended: float, workers: int) -> tuple[list[float], dict[str, float]]:
    """How many tasks ran at once over the run: seconds of the wall (`began` to `ended`,
    time.time()) with 0, 1, ..., `workers` or more tasks running, and per node the seconds it ran
    alone (the only task running: the other workers idle)."""
    events = []
    for task in result.tasks:
        start = float(task.get("started") or 0.0)
        if task.get("status") == "executed" and start > 0:
            events.append((start, float(task.get("seconds") or 0.0), task["node"]))
    cuts = sorted({began, ended, *(s for s, _, _ in events), *(s + d for s, d, _ in events)})
    cuts = [c for c in cuts if began <= c <= ended]
    at_once = [0.0] * (workers + 1)
    alone: dict[str, float] = collections.defaultdict(float)
    for a, b in zip(cuts[:-1], cuts[1:]):
        mid = 0.5 * (a + b)
        running = [node for s, d, node in events if s <= mid < s + d]
        at_once[min(len(running), workers)] += b - a
        if len(running) == 1:
            alone[running[0]] += b - a
    return at_once, dict(alone)


def print_concurrency(result, began: float, ended: float, workers: int) -> None:
    at_once, alone = concurrency(result, began, ended, workers)
    wall = max(ended - began, 1e-9)
    parts = ", ".join(f"{n}{'+' if n == workers else ''} {s:.1f} s ({100 * s / wall:.0f}%)" for n, s in enumerate(at_once))
    print(f"  tasks running at once over the wall: {parts}")
    top = sorted(alone.items(), key=lambda kv: -kv[1])[:8]
    if top and workers > 1:
        print("  ran alone (the other workers idle): " + ", ".join(f"{n} {s:.1f} s" for n, s in top))


def resize_video(folder: Path, frames: int, size: int) -> None:
    """The 256^2 plates resized to `size`^2 in place (bicubic), as a higher-resolution camera."""
    from PIL import Image

    if size == 256:
        return
    for i in range(frames):
        path = folder / f"plate.{i:04d}.png"
        Image.open(path).convert("RGB").resize((size, size), Image.BICUBIC).save(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo-frames", type=int, default=100)
    parser.add_argument("--video-frames", type=int, default=12)
    parser.add_argument("--video-size", type=int, default=512, help="plate side, pixels (made at 256, resized)")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--scheduler", default="threads", help="threads | processes | sync")
    parser.add_argument("--skip-demo", action="store_true")
    parser.add_argument("--skip-video", action="store_true")
    parser.add_argument("--skip-imports", action="store_true")
    parser.add_argument("--keep", type=Path, default=None, help="write the runs' outputs here (else a temporary "
                        "folder): demo/ (stabilization/errors.md, motion/motion.md, ...) and video/")
    args = parser.parse_args()

    print(f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs; scheduler {args.scheduler}, "
          f"{args.workers} workers")
    if not args.skip_imports:
        print("import time (fresh interpreter, least of 3):")
        for module in IMPORTS:
            print(f"  import {module:18s} {import_seconds(module):6.2f} s")

    from nodegraph import runner

    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep or Path(tmp)
        if not args.skip_demo:
            t, began = time.perf_counter(), time.time()
            result = runner.run(ROOT / "graphs" / "demo.json", cache=False, workers=args.workers,
                                scheduler=args.scheduler,
                                parameters={"num_frames": args.demo_frames,
                                            **{k: str(out / "demo" / v) for k, v in DEMO_OUTPUTS.items()}})
            print_tables("graphs/demo.json", result, args.demo_frames, time.perf_counter() - t)
            print_concurrency(result, began, time.time(), args.workers)
        if not args.skip_video:
            video = out / "video"
            video.mkdir(parents=True, exist_ok=True)
            astronaut_video(video, args.video_frames)
            resize_video(video, args.video_frames, args.video_size)
            pattern = str(video / "plate.%04d.png")
            t, began = time.perf_counter(), time.time()
            result = runner.run(ROOT / "graphs" / "fit_video_temporal.json", cache=False, workers=args.workers,
                                scheduler=args.scheduler,
                                parameters={"images": pattern, "output": str(video / "fit.npz"),
                                            "report": str(video / "fit"), "motion_report": str(video / "motion")})
            print_tables(f"graphs/fit_video_temporal.json (astronaut video, {args.video_size}^2)", result,
                         args.video_frames, time.perf_counter() - t)
            print_concurrency(result, began, time.time(), args.workers)
        print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
