"""Landmark networks per call and a followed frame of `landmarks.TrackFaces`, CPU, 1 and 2 torch threads.

Run: nice python bench/landmark_networks.py [--repeat 30] [--frames 16] [--runs 3] [--threads 1 2]

Rows, per torch intra-op thread count (`--threads`; the landmark nodes run on one):
  per network: the median over `--repeat` calls (after 3 warm-ups) of the wall time and of the
  process CPU time (all threads: what the call costs the machine, which other work on a shared
  machine inflates less than the wall time), ms per call, for the plan (`TfliteModule.forward`,
  what the nodes run) and the op-by-op replay it was checked against (`forward_reference`):
    face mesh        MediaPipe's face mesh on one 192 x 192 crop
    iris, 2 eyes     the iris model on both eyes' 64 x 64 crops as one batch of 2
    iris, 1 eye      one crop (what the second crop of a batch of 2 adds is the difference)
    BlazeFace        short range, one 128 x 128 input (a whole frame letterboxed)
    BlazeFace full   full range, one 192 x 192 input
  followed frame: `track_faces` on a 960 x 540 video of skimage's astronaut (`--frames` frames,
  `cases.make_video`: eye distance 45-55 px, moving, zooming and rolling by up to 10 degrees),
  `--runs` runs; the median over every frame where the detector did not run of the wall and
  process CPU time between the tracker's progress calls (crop, face mesh, re-reads, iris crops and
  network, the bookkeeping), with the iris model and without it. The first frame (the detector) is left out.
The load average is printed before and after: timings on a busy machine are noisy, and with 2
threads on a machine whose cores are taken by other work OpenMP's waits dominate (at load 9 a
face-mesh call took 0.76 s of CPU; `--threads 1` skips those rows). The landmark nodes run torch on
one thread: with 2 the face mesh's points differ from one thread's in the last bits (3e-5 px).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "nodes" / "landmarks"))

from nodes.landmarks.face_tracker import track_faces  # noqa: E402
from nodes.landmarks.iris import load_iris_network  # noqa: E402
from nodes.landmarks.network import load_face_detector, load_face_mesh, load_full_range_detector  # noqa: E402


def wall_cpu_ms(fn, repeat: int) -> tuple[float, float]:
    """Medians of the wall and process CPU time of `fn()`, ms, over `repeat` runs after 3 warm-ups."""
    for _ in range(3):
        fn()
    walls, cpus = [], []
    for _ in range(repeat):
        w, c = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls) * 1e3, statistics.median(cpus) * 1e3


def followed_frame_ms(frames: np.ndarray, runs: int, *, with_iris: bool) -> tuple[float, float, int]:
    """Median wall and process CPU ms of a followed frame of `track_faces` (see the module
    docstring), and how many frames it is taken over."""
    walls, cpus = [], []
    for _ in range(runs + 1):  # the first run warms up
        stamps = [(time.perf_counter(), time.process_time())]
        out = track_faces(frames, with_iris=with_iris, progress=lambda *_: stamps.append(
            (time.perf_counter(), time.process_time())))
        if _ == 0:
            continue
        for f in range(1, len(frames)):
            if not out.detected[f] and not out.failed[f]:
                walls.append(stamps[f + 1][0] - stamps[f][0])
                cpus.append(stamps[f + 1][1] - stamps[f][1])
    return statistics.median(walls) * 1e3, statistics.median(cpus) * 1e3, len(walls)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=30, help="calls per network timing")
    parser.add_argument("--frames", type=int, default=16, help="frames of the followed video")
    parser.add_argument("--runs", type=int, default=3, help="track_faces runs per followed-frame row")
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()
    from cases import make_video

    print(f"torch {torch.__version__}, CPU ({torch.backends.cpu.get_cpu_capability()}), "
          f"{len(os.sched_getaffinity(0)) if hasattr(os, 'sched_getaffinity') else os.cpu_count()} cores usable, "
          f"load average {os.getloadavg()[0]:.2f}")
    g = torch.Generator().manual_seed(0)
    mesh, iris, detector, full = (load_face_mesh(), load_iris_network(), load_face_detector(),
                                  load_full_range_detector())
    crop, eyes = torch.rand(1, 192, 192, 3, generator=g), torch.rand(2, 64, 64, 3, generator=g)
    small, wide = torch.rand(1, 128, 128, 3, generator=g), torch.rand(1, 192, 192, 3, generator=g)
    video = make_video("astronaut", args.frames, canvas=(540, 960), eye_px=(45.0, 55.0), roll_deg=10.0,
                       sweep=(0.4, 0.5), bob=0.02)
    frames = np.ascontiguousarray(np.stack(video.frames).astype(np.float32))
    threads_before = torch.get_num_threads()
    for threads in args.threads:
        torch.set_num_threads(threads)
        print(f"\n{threads} torch thread(s)")
        print(f"{'what':28s} {'plan ms':>8s} {'cpu ms':>7s}   {'op-by-op ms':>11s} {'cpu ms':>7s}")
        with torch.no_grad():
            for name, net, x in (("face mesh", mesh.net, crop), ("iris, 2 eyes (batch 2)", iris.net, eyes),
                                 ("iris, 1 eye", iris.net, eyes[:1]), ("BlazeFace 128", detector.net, small), ("BlazeFace full 192", full.net, wide)):
                plan = wall_cpu_ms(lambda: net(x), args.repeat)
                reference = wall_cpu_ms(lambda: net.forward_reference(x), args.repeat)
                print(f"{name:28s} {plan[0]:8.2f} {plan[1]:7.2f}   {reference[0]:11.2f} {reference[1]:7.2f}")
        print(f"{'followed frame':28s} {'wall ms':>8s} {'cpu ms':>7s}   frames")
        for name, with_iris in (("with iris", True), ("without iris", False)):
            wall, cpu, count = followed_frame_ms(frames, args.runs, with_iris=with_iris)
            print(f"{name:28s} {wall:8.2f} {cpu:7.2f}   {count}")
    torch.set_num_threads(threads_before)
    print(f"\nload average {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
