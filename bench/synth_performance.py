"""Synthetic performance generation: model loading, full-head generation, chunks, report plots.

Run: python bench/synth_performance.py [--frames 600] [--repeat 3]

Prints the best of `--repeat` wall times (s) for:
1. `load_face_model()` (whole ICT head) and with `region="face"`, `max_vertices=2000`;
2. `generate_performance` on the whole head (26,719 vertices): clean, and with noise,
   sliding and outliers; and the same split into chunks of 64 frames (the framewise node's
   cost under the scheduler);
3. `CaptureReport` plots (head motion + histograms) for the face region.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from typing import Callable

from nodegraph import run_node
from nodes.io.face_model import load_face_model
from nodes.report.plots import CaptureReport
from nodes.synth.performance import generate_performance


def best(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=600)
    parser.add_argument("--repeat", type=int, default=3)
    args = parser.parse_args()
    f, r = args.frames, args.repeat

    print(f"load_face_model() whole head:            {best(load_face_model, r):7.3f} s")
    print(f"load_face_model(region='face'):          {best(lambda: load_face_model(region='face'), r):7.3f} s")
    print(f"load_face_model(max_vertices=2000):      {best(lambda: load_face_model(max_vertices=2000), r):7.3f} s")
    model = load_face_model()
    v = model.neutral.shape[0]
    clean = best(lambda: generate_performance(model, num_frames=f, seed=0), r)
    print(f"generate_performance {f} x {v}, clean:     {clean:7.3f} s  ({f / clean:.0f} frames/s)")
    art = dict(noise_cm=0.05, sliding_cm=0.3, outlier_fraction=0.001)
    dirty = best(lambda: generate_performance(model, num_frames=f, seed=0, **art), r)
    print(f"generate_performance {f} x {v}, artefacts: {dirty:7.3f} s  ({f / dirty:.0f} frames/s)")

    def chunked() -> None:
        for a in range(0, f, 64):
            generate_performance(model, num_frames=f, seed=0, frames=range(a, min(a + 64, f)), **art)

    print(f"same in chunks of 64 frames:               {best(chunked, r):7.3f} s")
    face = load_face_model(region="face")
    perf = generate_performance(face, num_frames=f, seed=0, noise_cm=0.02)
    with tempfile.TemporaryDirectory() as folder:
        report = best(lambda: run_node(CaptureReport, {"folder": folder}, capture=perf.capture,
                                       rigid=perf.rigid), 1)
    print(f"CaptureReport {f} x {face.neutral.shape[0]} (2 PNGs):     {report:7.3f} s")


if __name__ == "__main__":
    main()
