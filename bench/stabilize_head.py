"""`stabilize.json` on the whole head: 651 frames x 26,719 vertices, end to end and its parts.

Run: python bench/stabilize_head.py [--frames 651] [--repeat 2] [--work DIR] [--threads N]
                                    [--before REV] [--skip-command] [--skip-function]

1. `graphs/synthetic_capture.json` writes the capture and its truth (whole ICT head, the graph's
   defaults: 10 deg / 2 cm smooth head motion, 0.02 cm noise) into `--work` (a temporary folder
   unless given; an existing capture of the same frame count there is reused).
2. The shipped command, `nodegraph run graphs/stabilize.json capture=... output=... report=...
   --no-cache --progress json`, `--repeat` times: wall and CPU seconds (user + system of the
   child) and the time per phase from the run's JSON events: start-up (interpreter, imports,
   planning with the input's content hash: wall minus the run's own seconds), then each node's
   task seconds (summed over its chunks; tasks overlap on 2 cores, so these do not add up to
   the wall time). Best of the runs per row, with the machine's load average beside them.
   `--before REV` runs the same command on the code of git revision REV as well (exported
   with `git archive` into a temporary folder, run with this interpreter, interleaved with
   the current code, one unmeasured warm-up each: the numba kernels compile there once) and
   prints the table before / after.
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


def run_timed(cmd: list[str], cwd: Path = ROOT, env: dict[str, str] | None = None) -> tuple[float, float, str]:
    """(wall s, child CPU s, stderr) of one command (exit status checked)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        sys.exit(f"{' '.join(cmd)}: exit {proc.returncode}\n{proc.stderr[-2000:]}")
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), proc.stderr


def phases(wall: float, cpu: float, events: str) -> dict[str, float]:
    """Seconds per phase of one run from its JSON-lines events (see the module docstring)."""
    out: dict[str, float] = {"wall": wall, "CPU": cpu}
    run_seconds = wall
    for line in events.splitlines():
        try:
            event = json.loads(line)
        except ValueError:
            continue
        if event.get("event") == "task":
            out[f"task {event['node']}"] = out.get(f"task {event['node']}", 0.0) + float(event["seconds"])
        elif event.get("event") == "end":
            run_seconds = float(event["seconds"])
    out["start-up (imports, plan)"] = wall - run_seconds
    return out


def export_revision(rev: str, folder: Path) -> Path:
    """The tree of git revision `rev` extracted into `folder` (`git archive`; the repository
    itself is not touched)."""
    folder.mkdir(parents=True, exist_ok=True)
    archive = subprocess.run(["git", "archive", "--format=tar", rev], cwd=ROOT, capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(folder)], input=archive.stdout, check=True)
    return folder


def _file_label(label: str) -> str:
    return "".join(c if c.isalnum() else "_" for c in label)


def command_rows(trees: dict[str, Path], capture: Path, work: Path, repeat: int) -> dict[str, dict[str, float]]:
    """label -> best seconds per phase of the shipped command run from each source tree."""
    best: dict[str, dict[str, float]] = {label: {} for label in trees}
    for run in range(repeat + (1 if len(trees) > 1 else 0)):
        for label, tree in trees.items():
            env = dict(os.environ)
            if tree != ROOT:  # that tree's packages before the installed (editable) ones
                env["PYTHONPATH"] = str(tree) + os.pathsep + env.get("PYTHONPATH", "")
            cmd = [sys.executable, "-m", "nodegraph.cli", "run", str(tree / "graphs" / "stabilize.json"),
                   f"capture={capture}", f"output={work / f'stabilized_{_file_label(label)}.npz'}",
                   f"report={work / f'report_{_file_label(label)}'}", "--no-cache", "--progress", "json"]
            load_before = load()
            wall, cpu, events = run_timed(cmd, cwd=tree, env=env)
            warm_up = len(trees) > 1 and run == 0
            print(f"stabilize.json --no-cache [{label}]: {wall:.2f} s wall, {cpu:.2f} s CPU (load "
                  f"{load_before} -> {load()}){' (warm-up, not counted)' if warm_up else ''}", flush=True)
            if warm_up:
                continue
            for name, seconds in phases(wall, cpu, events).items():
                best[label][name] = min(best[label].get(name, float("inf")), seconds)
    return best


def print_phase_table(best: dict[str, dict[str, float]], frames: int, runs: int) -> None:
    labels = list(best)
    names = ["wall", "CPU", "start-up (imports, plan)"] + sorted(
        {n for row in best.values() for n in row if n.startswith("task ")})
    print(f"\nstabilize.json {frames} x 26719 --no-cache, best of {runs} run(s) per row (s):")
    print(f"{'phase':<28}" + "".join(f"{label:>14}" for label in labels))
    for name in names:
        print(f"{name:<28}" + "".join(f"{best[label].get(name, float('nan')):>14.2f}" for label in labels))


def make_capture(work: Path, frames: int) -> None:
    capture, meta = work / "capture.npz", work / "frames.txt"
    if capture.exists() and meta.exists() and meta.read_text().strip() == str(frames):
        print(f"capture: reusing {capture}")
        return
    wall, cpu, _ = run_timed([NODEGRAPH, "run", "graphs/synthetic_capture.json",
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
    parser.add_argument("--skip-function", action="store_true", help="only the command")
    parser.add_argument("--before", default="", help="git revision to time the command against (e.g. HEAD~3)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(args.work or tmp)
        work.mkdir(parents=True, exist_ok=True)
        make_capture(work, args.frames)
        capture = work / "capture.npz"
        if not args.skip_command:
            trees = {"now": ROOT}
            if args.before:
                trees = {f"before {args.before}": export_revision(args.before, Path(tmp) / "before")} | trees
            best = command_rows(trees, capture, work, args.repeat)
            print_phase_table(best, args.frames, args.repeat)
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

        if not args.skip_function:
            mode_pursuit(vertices[:40, :2000], vertex_weights=prior[:2000], device="cpu")  # kernels loaded
            mode_pursuit(vertices[:40, :2000], vertex_weights=prior[:2000], device="cpu", kernels=False)
        for kernels in () if args.skip_function else (False, True):
            load_before = load()
            wall, cpu = time.perf_counter(), time.process_time()
            res = mode_pursuit(vertices, vertex_weights=prior, device="cpu", kernels=kernels)
            wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
            print(f"mode_pursuit {'numba kernels' if kernels else 'torch ops    '} ({torch.get_num_threads()} "
                  f"torch threads): {wall:.2f} s wall, {cpu:.2f} s CPU, {res.evaluations} evaluations, "
                  f"{accuracy(res.matrices)} (load {load_before})", flush=True)
        if not args.skip_command:
            for label in trees:
                out = work / f"stabilized_{_file_label(label)}.npz"
                print(f"stabilize.json output [{label}]: {accuracy(np.load(out)['rigid'])}")


if __name__ == "__main__":
    main()
