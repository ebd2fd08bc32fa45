"""`stabilize.json` on the whole head: 651 frames x 26,719 vertices, end to end and its parts.

Run: python bench/stabilize_head.py [--frames 651] [--repeat 2] [--work DIR] [--threads N]

1. `graphs/synthetic_capture.json` writes the capture and its truth (whole ICT head, the graph's
   defaults: 10 deg / 2 cm smooth head motion, 0.02 cm noise) into `--work` (a temporary folder
   unless given; an existing capture of the same frame count there is reused).
2. The shipped command, `nodegraph run graphs/stabilize.json capture=... output=... report=...
   --no-cache`, `--repeat` times: wall and CPU seconds (user + system of the child), best and
   all, with the machine's load average beside them.
3. In process, `mode_pursuit` (the node's method; the stabilized mesh excluded) on the same
   capture, the torch and numba versions of the robust alignment side by side
   (`kernels=False` is the torch ops): wall and CPU seconds, energy evaluations.
4. Accuracy of the command's output: median / p95 vertex error (cm) against the truth
   (`nodes.report.metrics.stabilization_errors`: the head motion left in the stabilized mesh).

Timings on a shared machine are noisy: compare CPU seconds, and wall seconds only at a low load.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


NODEGRAPH = str(Path(sys.executable).with_name("nodegraph"))


def load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def run_timed(cmd: list[str]) -> tuple[float, float]:
    """(wall s, child CPU s) of one command (exit status checked)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def make_capture(work: Path, frames: int) -> None:
    capture, meta = work / "capture.npz", work / "frames.txt"
    if capture.exists() and meta.exists() and meta.read_text().strip() == str(frames):
        print(f"capture: reusing {capture}")
        return
    wall, cpu = run_timed([NODEGRAPH, "run", "graphs/synthetic_capture.json",
                           f"num_frames={frames}", f"capture={capture}", f"truth={work / 'truth.npz'}",
                           f"truth_rigid={work / 'truth_rigid.json'}", f"expressions={work / 'expr.json'}",
                           f"report={work / 'capture_report'}", "--no-cache"])
    meta.write_text(str(frames))
    print(f"capture: synthetic_capture.json, {frames} frames, whole head ({wall:.1f} s)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=651)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--work", default="", help="folder for the capture and outputs (default: temporary)")
    parser.add_argument("--threads", type=int, default=0, help="torch threads in process (0 = default)")
    parser.add_argument("--skip-command", action="store_true", help="only the in-process mode pursuit")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        make_capture(work, args.frames)
        capture, output = work / "capture.npz", work / "stabilized.npz"
        if not args.skip_command:
            cmd = [NODEGRAPH, "run", "graphs/stabilize.json", f"capture={capture}",
                   f"output={output}", f"report={work / 'report'}", "--no-cache"]
            runs = []
            for _ in range(args.repeat):
                load_before = load()
                wall, cpu = run_timed(cmd)
                runs.append((wall, cpu))
                print(f"stabilize.json --no-cache: {wall:.2f} s wall, {cpu:.2f} s CPU (load {load_before} "
                      f"-> {load()})", flush=True)
            print(f"stabilize.json {args.frames} x 26719, --no-cache: best {min(r[0] for r in runs):.2f} s wall, "
                  f"best {min(r[1] for r in runs):.2f} s CPU over {len(runs)} runs")

        import torch

        from nodes.report.metrics import stabilization_errors
        from nodes.stabilize.mode_pursuit import mode_pursuit

        if args.threads:
            torch.set_num_threads(args.threads)
        data = np.load(capture)
        vertices = data["vertices"]
        prior = np.ones(vertices.shape[1], np.float32)
        prior[data["groups/rigid"]] = 2.0  # the node's default prior_group / prior_weight
        truth = np.load(work / "truth.npz")["vertices"]
        truth_rigid = np.asarray(json.loads((work / "truth_rigid.json").read_text())["matrices"], np.float64)

        def accuracy(matrices: np.ndarray) -> str:
            s = stabilization_errors(matrices, truth_rigid, truth).summary()
            return f"median {s['median_cm']:.5f} cm, p95 {s['p95_cm']:.5f} cm"

        mode_pursuit(vertices[:40, :2000], vertex_weights=prior[:2000], device="cpu")  # kernels loaded
        mode_pursuit(vertices[:40, :2000], vertex_weights=prior[:2000], device="cpu", kernels=False)
        for kernels in (False, True):
            load_before = load()
            wall, cpu = time.perf_counter(), time.process_time()
            res = mode_pursuit(vertices, vertex_weights=prior, device="cpu", kernels=kernels)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            print(f"mode_pursuit {'numba kernels' if kernels else 'torch ops    '} ({torch.get_num_threads()} "
                  f"torch threads): {wall:.2f} s wall, {cpu:.2f} s CPU, {res.evaluations} evaluations, "
                  f"{accuracy(res.matrices)} (load {load_before})", flush=True)
        if not args.skip_command:
            print(f"stabilize.json output: {accuracy(np.load(output)['rigid'])}")


if __name__ == "__main__":
    main()
