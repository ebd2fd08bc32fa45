"""Mode-pursuit stabilization: wall time, energy evaluations and accuracy at the paper's sizes.

Run: python bench/stabilize.py [--repeat 3] [--seed 0] [--compile] [--large]

For each size of the paper's Table I (63 x 2466, 96 x 2466, 651 x 1185 frames x vertices) a
synthetic performance of the ICT face region is generated (`nodes.synth.performance`, 10 deg /
2 cm smooth head motion, 0.01 cm noise). Rows:
- the baselines `rigid.ThreePoint`, `rigid.Procrustes` (group "rigid") and robust `rigid.ICP`
  (all vertices, at most 1000 well-spread ones), skull frame = frame 0;
- `stabilize.ModePursuit` initialised from Procrustes, and from identity, on CPU (and CUDA
  when available): best wall time of `--repeat` runs (s), energy + gradient evaluations,
  L-BFGS iterations.
Accuracy (`nodes.report.metrics.stabilization_errors`): per-vertex error of the motion
(noise-free mesh) after removing one global rigid offset: median / mean / p95 (cm).
`--compile` adds a row with `compile=True` (first run includes the compile, then the best
warm run). `--large` adds one long, dense case (2000 frames x 26,719 vertices, whole head,
energy on 2000 sampled vertices) to show time and peak memory at scale.
"""

from __future__ import annotations

import argparse
import resource
import time
from typing import Callable

import numpy as np
import torch

from nodegraph import RigidSequence, run_node
from nodes.io.face_model import load_face_model
from nodes.report.metrics import stabilization_errors
from nodes.rigid.nodes import ICP, Procrustes, ReferenceFrame, ThreePoint
from nodes.stabilize.mode_pursuit import mode_pursuit
from nodes.stabilize.node import ModePursuit
from nodes.synth.performance import generate_performance

SIZES = [(63, 2466), (96, 2466), (651, 1185)]


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """Best wall time of `repeat` calls (s) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def row(size: str, method: str, device: str, seconds: float, evals: object, iters: object,
        estimate: np.ndarray, truth_rigid: np.ndarray, truth: np.ndarray) -> None:
    s = stabilization_errors(estimate, truth_rigid, truth).summary()
    print(f"{size:>11}  {method:<26} {device:<5} {seconds:8.3f} {str(evals):>6} {str(iters):>6}  "
          f"{s['median_cm']:.4f}  {s['mean_cm']:.4f}  {s['p95_cm']:.4f}", flush=True)


def bench_size(frames: int, vertices: int, args: argparse.Namespace, devices: list[str],
               region: str = "face", max_vertices: int = 2000) -> None:
    model = load_face_model(region=region, max_vertices=vertices if region else 0)
    perf = generate_performance(model, num_frames=frames, seed=args.seed, rotation_deg=10.0,
                                translation_cm=2.0, noise_cm=0.01)
    mesh, truth_rigid = perf.capture, perf.rigid.matrices
    truth = perf.stabilized.vertices
    size = f"{frames}x{mesh.num_vertices}"
    reference = run_node(ReferenceFrame, {"frame": 0}, mesh=mesh)["reference"]
    baselines = {"rigid.ThreePoint": (ThreePoint, {}),
                 "rigid.Procrustes": (Procrustes, {"group": "rigid"}),
                 "rigid.ICP": (ICP, {"group": ""})}
    init = None
    for name, (node, params) in baselines.items():
        seconds, out = timed(lambda: run_node(node, params, mesh=mesh, reference=reference), args.repeat)
        row(size, name, "cpu", seconds, "-", "-", out["rigid"].matrices, truth_rigid, truth)
        if name == "rigid.Procrustes":
            init = out["rigid"].matrices
    for device in devices:
        for label, start in (("ModePursuit(Procrustes)", init), ("ModePursuit(identity)", None)):
            seconds, res = timed(lambda: mode_pursuit(mesh.vertices, init=start, device=device,
                                                      max_vertices=max_vertices), args.repeat)
            row(size, label, device, seconds, res.evaluations, res.iterations, res.matrices, truth_rigid, truth)
        if args.compile:
            first = time.perf_counter()
            mode_pursuit(mesh.vertices, init=init, device=device, compile=True)
            first = time.perf_counter() - first
            seconds, res = timed(lambda: mode_pursuit(mesh.vertices, init=init, device=device, compile=True),
                                 args.repeat)
            row(size, f"ModePursuit compiled(1st {first:.1f}s)", device, seconds, res.evaluations,
                res.iterations, res.matrices, truth_rigid, truth)
    # Node path (includes stabilizing every vertex and the port checks).
    seconds, out = timed(lambda: run_node(ModePursuit, {"device": devices[0]}, mesh=mesh,
                                          init=RigidSequence(init)), 1)
    row(size, "stabilize.ModePursuit node", devices[0], seconds, "-", "-", out["rigid"].matrices,
        truth_rigid, truth)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--large", action="store_true")
    args = parser.parse_args()
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, devices {devices}")
    print(f"{'size':>11}  {'method':<26} {'dev':<5} {'wall_s':>8} {'evals':>6} {'iters':>6}  "
          f"median  mean    p95 (cm)")
    for frames, vertices in SIZES:
        bench_size(frames, vertices, args, devices)
    if args.large:
        args.repeat, args.compile = 1, False
        bench_size(2000, 0, args, devices, region="")
        print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
