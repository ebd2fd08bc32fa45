"""Temporal smoothing of fitted curves: temporal.AdaptiveSmooth against 3-frame averaging.

Run: python bench/smoothing.py [--video] [--frames 24]

1. Curves with known truth (150 frames, 5 seeds): a slow curve and a blink (0.05 -> 0.95 over 4
   frames) under white noise of 0.005 / 0.02 / 0.05; RMS error to the truth, roughness (mean
   squared second difference) and the blink's depth kept, for the raw curve, 3-frame averaging
   and adaptive smoothing; milliseconds per curve.
2. `--video`: a real photo (skimage's astronaut) made into a video by a smooth pan, zoom and roll
   (256^2, `--frames` frames), run through graphs/fit_video.json (the per-frame fit) and
   graphs/fit_video_temporal.json (the same fit, infill, adaptive smoothing; one cache, so the fit
   runs once): jitter of the projected 68 points (mean squared second difference, px^2), their
   mean distance from the per-frame fit's (% of the eye distance), the weights' and the rotation's
   roughness, the frames failed, the seconds of each graph, and the task seconds per frame of the
   fit and of each temporal stage (flow, infill, averaging, smoothing) with their ratio.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np


def curve_rows() -> list[str]:
    from nodes.temporal.adaptive import smooth_curve

    frames = 150
    t = np.arange(frames)
    slow = 0.4 + 0.2 * np.sin(t / 9.0) + 0.1 * np.sin(t / 23.0)
    blink = np.full(frames, 0.05)
    blink[70:74] = [0.5, 0.95, 0.95, 0.5]
    rows = ["| noise | curve | error raw / averaged / adaptive | roughness raw / averaged / adaptive | blink depth "
            "averaged / adaptive | ms per curve |", "|---|---|---|---|---|---|"]
    for sigma in (0.005, 0.02, 0.05):
        for name, truth in (("slow", slow), ("blink", blink)):
            stats, ms = [], []
            for seed in range(5):
                x = truth + np.random.default_rng(seed).normal(0, sigma, frames)
                avg = x.copy()
                avg[1:-1] = 0.25 * x[:-2] + 0.5 * x[1:-1] + 0.25 * x[2:]
                start = time.perf_counter()
                ada = smooth_curve(x).values
                ms.append((time.perf_counter() - start) * 1e3)
                err = [np.sqrt(np.mean((y - truth) ** 2)) for y in (x, avg, ada)]
                rough = [np.mean(np.diff(y, 2) ** 2) for y in (x, avg, ada)]
                depth = [(y[71:73].mean() - np.median(y)) / 0.9 for y in (avg, ada)]
                stats.append(err + rough + depth)
            s = np.mean(stats, 0)
            depth = f"{s[6]:.2f} / {s[7]:.2f}" if name == "blink" else "-"
            rows.append(f"| {sigma} | {name} | {s[0]:.4f} / {s[1]:.4f} / {s[2]:.4f} | {s[3]:.1e} / {s[4]:.1e} / "
                        f"{s[5]:.1e} | {depth} | {np.median(ms):.1f} |")
    return rows


def astronaut_video(folder: Path, frames: int) -> None:
    """A smooth pan, zoom and roll over skimage's astronaut, as numbered 256^2 PNGs."""
    from skimage import data
    from skimage.transform import AffineTransform, warp

    from nodes.io.image import write_image

    photo = data.astronaut().astype(np.float32) / 255.0
    t = np.arange(frames) / max(frames - 1, 1)
    for i in range(frames):
        scale = 0.8 + 0.06 * np.sin(2 * np.pi * t[i])  # photo pixels per video pixel
        angle = np.deg2rad(4.0 * np.sin(2 * np.pi * 0.8 * t[i]))
        centre = np.array([235.0 + 12 * np.sin(2 * np.pi * t[i]), 125.0 + 6 * np.cos(2 * np.pi * t[i])])
        tf = AffineTransform(scale=scale, rotation=angle)  # video (x, y) -> photo, about the video's centre
        tf = AffineTransform(scale=scale, rotation=angle, translation=centre - tf.params[:2, :2] @ [128.0, 128.0])
        frame = warp(photo, tf, output_shape=(256, 256), order=1)
        write_image(folder / f"plate.{i:04d}.png", frame.astype(np.float32), ["R", "G", "B"], "uint8")


def video_rows(frames: int) -> list[str]:
    from nodegraph import Graph, runner

    root = Path(__file__).resolve().parents[1] / "graphs"
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        astronaut_video(tmp, frames)
        results, seconds, task_seconds = {}, {}, {}
        for name in ("fit_video", "fit_video_temporal"):
            params = {"images": str(tmp / "plate.%04d.png"), "output": str(tmp / f"{name}.npz"),
                      "report": str(tmp / f"{name}_overlays")}
            if name == "fit_video_temporal":
                params["motion_report"] = str(tmp / "motion")
            start = time.perf_counter()
            result = runner.run(Graph.load(root / f"{name}.json"), parameters=params, cache=tmp / "cache",
                                scheduler="threads", workers=2)
            seconds[name] = time.perf_counter() - start
            for task in result.tasks:
                if task.get("status") == "executed":
                    task_seconds[task["node"]] = task_seconds.get(task["node"], 0.0) + float(task["seconds"])
            if result.exit_code:
                return [f"{name} failed: {result.summary()}"]
            with np.load(tmp / f"{name}.npz") as fit:
                results[name] = {k: fit[k] for k in fit.files}
        raw, smooth = results["fit_video"], results["fit_video_temporal"]
        ok = ~(raw["failed"] | smooth["failed"])
        eye = np.linalg.norm(raw["landmarks68"][:, 36:42].mean(1) - raw["landmarks68"][:, 42:48].mean(1), axis=1)

        def jitter(points):
            return float(np.mean(np.diff(points[ok], 2, axis=0) ** 2))

        def rough_rot(rot):
            from scipy.spatial.transform import Rotation

            facing = np.diag([1.0, -1.0, -1.0]) @ rot[ok].astype(np.float64)  # the fit's world faces the camera
            angles = np.unwrap(Rotation.from_matrix(facing).as_euler("YXZ"), axis=0)
            return float(np.mean(np.diff(np.degrees(angles), 2, axis=0) ** 2))

        gap = np.linalg.norm(smooth["landmarks68"] - raw["landmarks68"], axis=2).mean(1)[ok] / eye[ok]
        rows += [f"astronaut video, {frames} frames 256^2, {int(ok.sum())} solved in both",
                 "| | per-frame fit | smoothed |", "|---|---|---|",
                 f"| 68-point jitter (px^2) | {jitter(raw['landmarks68']):.3f} | {jitter(smooth['landmarks68']):.3f} |",
                 f"| weight roughness | {np.mean(np.diff(raw['weights'][ok], 2, axis=0) ** 2):.5f} | "
                 f"{np.mean(np.diff(smooth['weights'][ok], 2, axis=0) ** 2):.5f} |",
                 f"| rotation roughness (deg^2) | {rough_rot(raw['rotation']):.4f} | {rough_rot(smooth['rotation']):.4f} |",
                 f"| points from the per-frame fit's (% eye distance) | 0 | {100 * gap.mean():.2f} |",
                 f"| frames failed | {100 * raw['failed'].mean():.0f}% | {100 * smooth['failed'].mean():.0f}% |",
                 f"| graph seconds (one cache: the temporal graph reuses the fit) | {seconds['fit_video']:.1f} | "
                 f"+{seconds['fit_video_temporal']:.1f} |"]
        fit_nodes = ("detect", "marks", "first_appearance", "appearance", "first_identity", "second_identity",
                     "identity", "rigid", "expression")
        fit_s = sum(task_seconds.get(n, 0.0) for n in fit_nodes)
        stages = {n: task_seconds.get(n, 0.0) for n in ("flow", "infill", "average", "smooth")}
        rows += ["", "task seconds per frame (summed over chunks), per stage:",
                 "| fit (detection to expression) | " + " | ".join(stages) + " | temporal / fit |",
                 "|---|" + "---|" * (len(stages) + 1),
                 f"| {fit_s / frames:.3f} | " + " | ".join(f"{v / frames:.3f}" for v in stages.values())
                 + f" | {sum(stages.values()) / max(fit_s, 1e-9):.3f} |"]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--video", action="store_true", help="also the astronaut video through the graphs")
    parser.add_argument("--frames", type=int, default=24)
    args = parser.parse_args()
    print("\n".join(curve_rows()))
    if args.video:
        print()
        print("\n".join(video_rows(args.frames)))


if __name__ == "__main__":
    main()
