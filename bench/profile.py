"""Where the time goes: task time per node of the demo and of the video graph, and import times.

Run: python bench/profile.py [--demo-frames 40] [--video-frames 12] [--skip-demo] [--skip-video]

Prints, for `graphs/demo.json` (a performance of `--demo-frames` frames, the default 100) and for
`graphs/fit_video_temporal.json` on a video made from skimage's astronaut (`--video-frames`
frames of 256^2: the photo panned, zoomed and rolled, bench/smoothing.py's video), one table per
graph: each node's task time (summed over its chunks: the work; with 2 workers the wall time is
less), its share of all task time, its chunk count and the time per frame it covers, largest
first; then the run's wall time. Before both, the import time of the packages a run loads
(each in a fresh interpreter). Every run is uncached (`cache=False`) with the `threads`
scheduler and 2 workers, as `nodegraph run` does by default.
"""

from __future__ import annotations

import argparse
import collections
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from smoothing import astronaut_video

ROOT = Path(__file__).resolve().parents[1]
DEMO_OUTPUTS = {"html": "index.html", "report": "stabilization", "dynamics_report": "dynamics",
                "fit_report": "fit", "motion_report": "motion"}


def import_seconds(module: str) -> float:
    """Wall seconds of `import module` in a fresh interpreter (the least of three)."""
    best = float("inf")
    for _ in range(3):
        out = subprocess.run([sys.executable, "-c", f"import time; t = time.perf_counter(); import {module}; "
                              "print(time.perf_counter() - t)"], capture_output=True, text=True, cwd=ROOT)
        best = min(best, float(out.stdout.strip().splitlines()[-1]))
    return best


def node_table(result) -> list[tuple[str, float, int]]:
    """(node, summed task seconds, chunks) per node, largest first."""
    seconds: dict[str, float] = collections.defaultdict(float)
    chunks: dict[str, int] = collections.defaultdict(int)
    for task in result.tasks:
        if task.get("status") == "executed":
            seconds[task["node"]] += float(task.get("seconds") or 0.0)
            chunks[task["node"]] += 1
    return sorted(((n, s, chunks[n]) for n, s in seconds.items()), key=lambda row: -row[1])


def print_table(title: str, result, frames: int, wall: float) -> None:
    rows = node_table(result)
    total = sum(s for _, s, _ in rows)
    print(f"\n{title}: {frames} frames, wall {wall:.1f} s, task time {total:.1f} s "
          f"({'ok' if result.ok else 'FAILED'})")
    print(f"  {'node':26s} {'task s':>8s} {'share':>6s} {'chunks':>6s} {'s/frame':>8s}")
    for node, s, n in rows:
        if s >= 0.05:
            print(f"  {node:26s} {s:8.2f} {100 * s / total:5.1f}% {n:6d} {s / frames:8.3f}")
    for task in result.tasks:
        error = task.get("error") or {}
        if task.get("status") == "failed" and isinstance(error, dict) and error.get("message"):
            print(f"  failed: {error['message']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--demo-frames", type=int, default=100)
    parser.add_argument("--video-frames", type=int, default=12)
    parser.add_argument("--skip-demo", action="store_true")
    parser.add_argument("--skip-video", action="store_true")
    args = parser.parse_args()

    print("import time (fresh interpreter, least of 3):")
    for module in ("numpy", "torch", "dask", "distributed", "nodegraph", "nodes.fit", "nodes.landmarks"):
        print(f"  import {module:10s} {import_seconds(module):6.2f} s")

    from nodegraph import runner

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        if not args.skip_demo:
            t = time.perf_counter()
            result = runner.run(ROOT / "graphs" / "demo.json", cache=False, workers=2,
                                parameters={"num_frames": args.demo_frames,
                                            **{k: str(out / "demo" / v) for k, v in DEMO_OUTPUTS.items()}})
            print_table("graphs/demo.json", result, args.demo_frames, time.perf_counter() - t)
        if not args.skip_video:
            astronaut_video(out, args.video_frames)
            pattern = str(out / "plate.%04d.png")
            t = time.perf_counter()
            result = runner.run(ROOT / "graphs" / "fit_video_temporal.json", cache=False, workers=2,
                                parameters={"images": pattern, "output": str(out / "fit.npz"),
                                            "report": str(out / "fit"), "motion_report": str(out / "motion")})
            print_table("graphs/fit_video_temporal.json (astronaut video)", result, args.video_frames,
                        time.perf_counter() - t)


if __name__ == "__main__":
    main()
