"""Mode-pursuit stabilization against the baselines, situation by situation, with wall times.

Run: python bench/stabilize.py [--repeat 1] [--seed 0] [--frames 651] [--vertices 1185]
                               [--situations default,noise,...] [--sizes] [--compile] [--large]

Situations (synthetic performances of the ICT face region, `nodes.synth.performance`, by
default 651 frames x 1185 vertices, 10 deg / 2 cm smooth head motion, 0.01 cm noise):
  default      the defaults above
  noise        0.1 cm tracking noise (10x)
  large        head motion up to 40 deg and 10 cm per axis
  short        a 30-frame shot
  expressions  strong held expressions in about 70 % of the frames
  start        the shot starts in a strong expression
  outliers     5 % outlier vertices per frame (0.5-1.5 cm)
  noise_head   0.1 cm noise on the whole ICT head (26,719 vertices, 1487 in 'rigid'), 300 frames
Methods: `rigid.ThreePoint`, `rigid.Procrustes` on the "rigid" group and on all vertices,
robust `rigid.ICP` (all vertices, at most 1000 well-spread ones), `stabilize.ModePursuit`
(adaptive schedule, identity initialization; the node, so stabilizing every vertex is
included). Errors (`nodes.report.metrics.stabilization_errors`): per-vertex error of the
motion (noise-free mesh) after removing one global rigid offset, median / p95 (cm).

`--sizes` adds the paper's Table I sizes (63 x 2466, 96 x 2466, 651 x 1185) for mode pursuit
alone (the function, best of `--repeat`), from identity and from Procrustes, adaptive and
the paper's fixed schedule. `--compile` adds compiled rows there. `--large` adds one long,
dense case (2000 frames x 26,719 vertices, whole head) with peak memory.
CUDA rows appear when a GPU is present.
"""

from __future__ import annotations

import argparse
import resource
import time
from typing import Callable

import numpy as np
import torch

from nodegraph import run_node
from nodes.io.face_model import load_face_model
from nodes.report.metrics import stabilization_errors
from nodes.rigid.nodes import ICP, Procrustes, ReferenceFrame, ThreePoint
from nodes.stabilize.mode_pursuit import mode_pursuit
from nodes.stabilize.node import ModePursuit
from nodes.synth.performance import generate_performance

SITUATIONS: dict[str, dict] = {
    "default": {},
    "noise": {"noise_cm": 0.1},
    "large": {"rotation_deg": 40.0, "translation_cm": 10.0},
    "short": {"num_frames": 30},
    "expressions": {"held_fraction": 0.7},
    "start": {"start_expression": 1.0},
    "outliers": {"outlier_fraction": 0.05, "outlier_cm": 0.5},
    "noise_head": {"noise_cm": 0.1, "num_frames": 300},  # the whole head (26,719 vertices)
}
SIZES = [(63, 2466), (96, 2466), (651, 1185)]


def timed(fn: Callable[[], object], repeat: int) -> tuple[float, object]:
    """Best wall time of `repeat` calls (s) and the last result."""
    best, out = float("inf"), None
    for _ in range(repeat):
        start = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - start)
    return best, out


def errors(estimate: np.ndarray, perf) -> tuple[float, float]:
    s = stabilization_errors(estimate, perf.rigid.matrices, perf.stabilized.vertices).summary()
    return s["median_cm"], s["p95_cm"]


def situation_rows(name: str, perf, repeat: int, device: str) -> dict[str, tuple[float, float, float]]:
    """method -> (median cm, p95 cm, seconds) for one capture."""
    mesh = perf.capture
    reference = run_node(ReferenceFrame, {"frame": 0}, mesh=mesh)["reference"]
    methods = {
        "three_point": (ThreePoint, {}, {"reference": reference}),
        "procrustes_rigid": (Procrustes, {"group": "rigid"}, {"reference": reference}),
        "procrustes_all": (Procrustes, {"group": ""}, {"reference": reference}),
        "icp": (ICP, {"group": ""}, {"reference": reference}),
        "mode_pursuit": (ModePursuit, {"device": device}, {}),
    }
    out = {}
    for label, (node, params, extra) in methods.items():
        seconds, result = timed(lambda: run_node(node, params, mesh=mesh, **extra), repeat)
        out[label] = errors(result["rigid"].matrices, perf) + (seconds,)
    return out


def print_table(table: dict[str, dict[str, tuple[float, float, float]]]) -> None:
    methods = list(next(iter(table.values())))
    print("\nmedian / p95 vertex error (cm), wall time (s)")
    print(f"{'situation':<12} " + " ".join(f"{m:>24}" for m in methods))
    for name, rows in table.items():
        best = min(rows[m][0] for m in methods if m != "mode_pursuit")
        mark = "ok" if rows["mode_pursuit"][0] <= best else "LOSES"
        print(f"{name:<12} " + " ".join(f"{rows[m][0]:.4f}/{rows[m][1]:.4f} {rows[m][2]:6.2f}s"
                                       for m in methods) + f"  {mark}")


def bench_sizes(args: argparse.Namespace, devices: list[str]) -> None:
    print(f"\n{'size':>11}  {'method':<34} {'dev':<5} {'wall_s':>8} {'evals':>6}  median  p95 (cm)")
    for frames, vertices in SIZES:
        perf = generate_performance(load_face_model(region="face", max_vertices=vertices),
                                    num_frames=frames, seed=args.seed, noise_cm=0.01)
        mesh = perf.capture
        reference = run_node(ReferenceFrame, {"frame": 0}, mesh=mesh)["reference"]
        init = run_node(Procrustes, {"group": ""}, mesh=mesh, reference=reference)["rigid"].matrices
        for device in devices:
            for schedule in ("adaptive", "fixed"):
                for label, start in (("identity", None), ("Procrustes", init)):
                    seconds, res = timed(lambda: mode_pursuit(mesh.vertices, init=start, device=device,
                                                              schedule=schedule), args.repeat)
                    med, p95 = errors(res.matrices, perf)
                    print(f"{frames:>4}x{mesh.num_vertices:<6}  {f'{schedule} from {label}':<34} {device:<5} "
                          f"{seconds:8.3f} {res.evaluations:>6}  {med:.4f}  {p95:.4f}", flush=True)
            if args.compile:
                seconds, res = timed(lambda: mode_pursuit(mesh.vertices, device=device, compile=True),
                                     args.repeat + 1)
                med, p95 = errors(res.matrices, perf)
                print(f"{frames:>4}x{mesh.num_vertices:<6}  {'adaptive compiled (warm)':<34} {device:<5} "
                      f"{seconds:8.3f} {res.evaluations:>6}  {med:.4f}  {p95:.4f}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--frames", type=int, default=651)
    parser.add_argument("--vertices", type=int, default=1185)
    parser.add_argument("--situations", default=",".join(SITUATIONS))
    parser.add_argument("--sizes", action="store_true")
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--large", action="store_true")
    args = parser.parse_args()
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, devices {devices}")
    model = load_face_model(region="face", max_vertices=args.vertices)
    table = {}
    for name in args.situations.split(","):
        if not name:
            continue
        kw = {"num_frames": args.frames, "seed": args.seed, "noise_cm": 0.01} | SITUATIONS[name]
        perf = generate_performance(load_face_model() if name.endswith("_head") else model, **kw)
        table[name] = situation_rows(name, perf, args.repeat, devices[-1])
        rows = table[name]
        print(f"{name:<12} " + "  ".join(f"{m} {v[0]:.4f}/{v[1]:.4f} {v[2]:.2f}s" for m, v in rows.items()),
              flush=True)
    if table:
        print_table(table)
    if args.sizes:
        bench_sizes(args, devices)
    if args.large:
        perf = generate_performance(load_face_model(), num_frames=2000, seed=args.seed, noise_cm=0.01)
        seconds, out = timed(lambda: run_node(ModePursuit, {"device": devices[-1]}, mesh=perf.capture), 1)
        med, p95 = errors(out["rigid"].matrices, perf)
        print(f"\n2000x26719 whole head, stabilize.ModePursuit node: {seconds:.2f} s, median {med:.4f} "
              f"p95 {p95:.4f} cm, peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")


if __name__ == "__main__":
    main()
