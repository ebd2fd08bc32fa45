"""Temporal smoothing of fitted curves: temporal.AdaptiveSmooth against 3-frame averaging.

Run: python bench/smoothing.py [--video] [--frames 24]

1. Curves with known truth (150 frames, 5 seeds): a slow curve and a blink (0.05 -> 0.95 over 4
   frames) under white noise of 0.005 / 0.02 / 0.05; RMS error to the truth, roughness (mean
   squared second difference) and the blink's depth kept, for the raw curve, 3-frame averaging
   and adaptive smoothing; milliseconds per curve.
2. A head performance with known truth (`known_shot_rows`: pose, a jaw snap and blinks under
   fit-like noise) through temporal.Average and temporal.AdaptiveSmooth: error to the truth,
   roughness, and the depth of the snap and the blinks kept.
3. A per-frame fit with known truth on the bundled face model (`fit_shot_rows`): each frame's
   pose and 53 weights solved by least squares from its 68 projected landmarks under white pixel
   noise (0.3 and 1 px), the weights pulled to 0 by a prior and clipped to [0, 1] (so, as on real
   video, their noise is large, correlated and pinned at 0 with spikes), a jaw snap and two blinks:
   raw, 3-frame averaged, AdaptiveSmooth curve by curve and AdaptiveSmooth with the model and
   camera (smoothing in the projected landmarks' metric, as the shipped graphs run it): errors to
   the truth, roughness, the blinks' eyelid closing and the jaw snap kept.
4. `--video`: a real photo (skimage's astronaut) made into a video by a smooth pan, zoom and roll
   (256^2, `--frames` frames) with a jaw snapping open and shut (a local warp of the chin and lower
   lip), sensor noise and JPEG, run through graphs/fit_video.json (the per-frame fit) and
   graphs/fit_video_temporal.json (the same fit, infill, adaptive smoothing; one cache, so the fit
   runs once): jitter of the projected 68 points (mean squared second difference, px^2), their
   mean distance from the per-frame fit's (% of the eye distance), the same for the fit's points
   averaged over 3 frames and averaged to the smoothed points' distance (3-frame averaging
   repeated, interpolated between repeats), the jaw's landmark snap, the weights' and the rotation's
   roughness, the frames failed, the seconds of each graph, and the task seconds per frame of the
   fit and of each temporal stage (flow, infill, averaging, smoothing) with their ratio, and
   whether issue 28's acceptance holds (jitter <= 0.6x, within 3% of the eye distance, <= 10%
   failed, temporal stage <= 1/4 of the fit's task time).
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support

from tests.support.synthetic import (LANDMARK_FIT_BLINKS, LANDMARK_FIT_FRAMES, landmark_fit_truth,  # noqa: E402
                                     per_frame_landmark_fit)


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


def known_shot_rows(seeds: int = 5, frames: int = 90) -> list[str]:
    """A head performance with known truth (`tests.support.synthetic.head_motion`, a jaw snap
    0 -> 0.7 -> 0 over frames 40-46, blinks 0.05 -> 0.95 over frames 20-23 and 65-68) under
    white noise like a per-frame fit's (rotation 0.01 rad, translation 0.15 cm, weights 0.03),
    through the nodes temporal.Average and temporal.AdaptiveSmooth: error to the truth, roughness
    and the depth of the jaw snap and the blinks kept (1 = the truth's)."""
    from nodegraph import ParamSequence, run_node
    from nodes.temporal import AdaptiveSmooth, Average
    from nodes.temporal.layout import RIGID_NAMES
    from tests.support.synthetic import head_motion

    names = ["jawOpen", "mouthSmileLeft", "eyeBlinkLeft", "eyeBlinkRight"]
    jaw, blinks = 6, [8, 9]
    stats = []
    for seed in range(seeds):
        truth = head_motion(frames, names, seed=seed, mouth_frames=(40, 46)).astype(np.float64)
        for b in blinks:
            truth[:, b] = 0.05
            truth[20:24, b] = truth[65:69, b] = [0.5, 0.95, 0.95, 0.5]
        rng = np.random.default_rng(100 + seed)
        noisy = truth + np.concatenate([rng.normal(0, 0.01, (frames, 3)), rng.normal(0, 0.15, (frames, 3)),
                                        rng.normal(0, 0.03, (frames, len(names)))], 1)
        fitted = ParamSequence(noisy.astype(np.float32), list(RIGID_NAMES) + names)
        outs = [noisy, run_node(Average, fitted=fitted)["averaged"].values.astype(np.float64),
                run_node(AdaptiveSmooth, fitted=fitted)["smoothed"].values.astype(np.float64)]

        def depth(y: np.ndarray) -> list[float]:
            snap = (y[42:45, jaw].mean() - y[35:38, jaw].mean()) / (truth[42:45, jaw].mean() - truth[35:38, jaw].mean())
            blink = np.mean([(y[s:s + 2, b].mean() - np.median(y[:, b])) / 0.9 for b in blinks for s in (21, 66)])
            return [snap, blink]

        stats.append([[np.degrees(np.abs(y[:, :3] - truth[:, :3])).mean(), np.abs(y[:, 3:6] - truth[:, 3:6]).mean(),
                       np.sqrt(np.mean((y[:, 6:] - truth[:, 6:]) ** 2)),
                       np.mean(np.diff(np.degrees(y[:, :3]), 2, axis=0) ** 2), np.mean(np.diff(y[:, 6:], 2, axis=0) ** 2)]
                      + depth(y) for y in outs])
    s = np.mean(stats, 0)
    truth_rough = np.mean(np.diff(truth[:, 6:], 2, axis=0) ** 2)
    rows = [f"known head performance, {frames} frames, {seeds} seeds (noise: rotation 0.01 rad, translation 0.15 cm, "
            f"weights 0.03; the truth's weight roughness {truth_rough:.1e}, most of it the blinks and the snap)",
            "| | rotation error (deg) | translation error (cm) | weight RMS error | rotation roughness (deg^2) | "
            "weight roughness | jaw snap depth | blink depth |", "|---|---|---|---|---|---|---|---|"]
    for label, r in zip(("raw", "3-frame averaged", "adaptive (temporal.AdaptiveSmooth)"), s):
        rows.append(f"| {label} | {r[0]:.3f} | {r[1]:.3f} | {r[2]:.4f} | {r[3]:.4f} | {r[4]:.1e} | {r[5]:.2f} | "
                    f"{r[6]:.2f} |")
    return rows


def fit_shot_rows(seeds: int = 3, noises: tuple[float, ...] = (0.3, 1.0)) -> list[str]:
    """Section 3 of the module docstring."""
    from nodegraph import Camera, ParamSequence, run_node
    from nodes.geometry.rotation import rotmat_to_axis_angle
    from nodes.io.face_model import load_face_model
    from nodes.temporal import AdaptiveSmooth, Average
    from nodes.temporal.layout import FIT_TRANSLATION_NAMES, MATRIX_NAMES, params_layout
    from nodes.temporal.nodes import _projected_landmarks_function
    from nodes.temporal.report import rigid_curves

    model = load_face_model()
    camera = Camera.from_fov(256, 256, 40.0)
    shapes = list(model.expression_names)
    names = list(MATRIX_NAMES) + list(FIT_TRANSLATION_NAMES) + shapes
    project = _projected_landmarks_function(model, camera, params_layout(names, shapes))
    jaw = 12 + shapes.index("jawOpen")

    def measures(y: np.ndarray, truth: np.ndarray) -> list[float]:
        points, true_points = project(y).reshape(len(y), 68, 2), project(truth).reshape(len(y), 68, 2)
        relative = np.einsum("fji,fjk->fik", truth[:, :9].reshape(-1, 3, 3), y[:, :9].reshape(-1, 3, 3))
        angles, _ = rigid_curves(ParamSequence(y.astype(np.float32), names))

        def lid(p: np.ndarray) -> float:
            gap = np.linalg.norm(p[:, [37, 38, 43, 44]] - p[:, [41, 40, 47, 46]], axis=2).mean(1)
            return float(np.median(gap) - np.mean([gap[b + 1:b + 3].mean() for b in LANDMARK_FIT_BLINKS]))

        def snap(v: np.ndarray) -> float:
            return float(v[42:45, jaw].mean() - v[35:38, jaw].mean())

        return [float(np.degrees(np.linalg.norm(rotmat_to_axis_angle(relative), axis=1)).mean()),
                float(np.sqrt(np.mean(np.sum((points - true_points) ** 2, 2)))),
                float(np.sqrt(np.mean((y[:, 12:] - truth[:, 12:]) ** 2))),
                float(np.mean(np.diff(angles, 2, axis=0) ** 2)),
                float(np.mean(np.sum(np.diff(points, 2, axis=0) ** 2, 2))),
                float(np.mean(np.diff(y[:, 12:], 2, axis=0) ** 2)),
                lid(points) / lid(true_points), snap(y) / snap(truth)]

    labels = ("raw", "3-frame averaged", "adaptive, curve by curve (no model)",
              "adaptive in the landmarks' metric (model + camera, as shipped)")
    rows = [f"per-frame fit with known truth on the bundled model, {LANDMARK_FIT_FRAMES} frames, {seeds} seeds (errors to "
            "the truth; blink: the eyelids' closing kept, jaw: the jawOpen snap kept, 1 = the truth's)",
            "| landmark noise (px) | | rotation error (deg) | 68-point error (px RMS) | weight RMS error | rotation "
            "roughness (deg^2) | 68-point roughness (px^2) | weight roughness | blink | jaw snap |",
            "|---|---|---|---|---|---|---|---|---|---|"]
    for noise in noises:
        stats, truth_stats = [], []
        for seed in range(seeds):
            truth = landmark_fit_truth(seed, shapes)
            fitted = per_frame_landmark_fit(truth, project, seed, noise)
            seq = ParamSequence(fitted.astype(np.float32), names)
            outs = [fitted, run_node(Average, fitted=seq)["averaged"].values,
                    run_node(AdaptiveSmooth, fitted=seq)["smoothed"].values,
                    run_node(AdaptiveSmooth, fitted=seq, model=model, camera=camera)["smoothed"].values]
            stats.append([measures(np.asarray(y, np.float64), truth) for y in outs])
            truth_stats.append(measures(truth, truth))
        t = np.mean(truth_stats, 0)
        rows.append(f"| {noise} | truth | 0 | 0 | 0 | {t[3]:.4f} | {t[4]:.3f} | {t[5]:.1e} | 1 | 1 |")
        for label, r in zip(labels, np.mean(stats, 0)):
            rows.append(f"| {noise} | {label} | {r[0]:.3f} | {r[1]:.3f} | {r[2]:.4f} | {r[3]:.4f} | {r[4]:.3f} | "
                        f"{r[5]:.1e} | {r[6]:.2f} | {r[7]:.2f} |")
    return rows


def mouth_opening(frames: int) -> np.ndarray:
    """The jaw's drop over the video, 0..1: shut, a snap open over 2 frames at a third of the
    video, held, closed again over 3 frames at two thirds."""
    t = np.arange(frames, dtype=np.float64)
    start, end = frames / 3.0, 2.0 * frames / 3.0
    return np.clip((t - start + 1) / 2.0, 0, 1) * np.clip((end - t + 2) / 3.0, 0, 1)


def astronaut_video(folder: Path, frames: int, *, jaw_px: float = 7.0, noise: float = 0.01,
                    jpeg_quality: int = 85) -> None:
    """A smooth pan, zoom and roll over skimage's astronaut, as numbered 256^2 PNGs, with a real
    change of expression: the lower lip and chin are warped down by up to `jaw_px` photo pixels
    (a Gaussian of 22 px about the chin, below the mouth at (222, 144) photo px, where the face
    mesh reads it) following `mouth_opening`; then sensor noise (`noise`, std in [0, 1] sRGB) and
    a JPEG round trip at `jpeg_quality`."""
    import io

    from PIL import Image
    from skimage import data
    from skimage.transform import AffineTransform, warp

    from nodes.io.image import write_image

    photo = data.astronaut().astype(np.float32) / 255.0
    t = np.arange(frames) / max(frames - 1, 1)
    opening = mouth_opening(frames)
    chin = np.array([222.0, 168.0])  # photo (x, y), px: below the mouth's centre
    rng = np.random.default_rng(0)
    for i in range(frames):
        scale = 0.8 + 0.06 * np.sin(2 * np.pi * t[i])  # photo pixels per video pixel
        angle = np.deg2rad(4.0 * np.sin(2 * np.pi * 0.8 * t[i]))
        centre = np.array([235.0 + 12 * np.sin(2 * np.pi * t[i]), 125.0 + 6 * np.cos(2 * np.pi * t[i])])
        tf = AffineTransform(scale=scale, rotation=angle)  # video (x, y) -> photo, about the video's centre
        tf = AffineTransform(scale=scale, rotation=angle, translation=centre - tf.params[:2, :2] @ [128.0, 128.0])

        def video_to_source(xy: np.ndarray, tf: AffineTransform = tf, drop: float = jaw_px * opening[i]) -> np.ndarray:
            photo_xy = tf(xy)  # where the moved photo's point lies; the jaw's drop pulls it from above
            bump = np.exp(-np.sum((photo_xy - chin) ** 2, axis=1) / (2 * 22.0 ** 2))
            return photo_xy - np.outer(drop * bump, [0.0, 1.0])

        frame = warp(photo, video_to_source, output_shape=(256, 256), order=1)
        frame = np.clip(frame + rng.normal(0.0, noise, frame.shape), 0.0, 1.0)
        buffer = io.BytesIO()
        Image.fromarray(np.round(frame * 255).astype(np.uint8)).save(buffer, format="JPEG", quality=jpeg_quality)
        frame = np.asarray(Image.open(buffer).convert("RGB"), dtype=np.float32) / 255.0
        write_image(folder / f"plate.{i:04d}.png", frame, ["R", "G", "B"], "uint8")


def video_rows(frames: int, keep: Path | None = None) -> list[str]:
    """The real-video rows; `keep`: a folder the two graphs' NPZ outputs are copied to."""
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
            if keep is not None:
                keep.mkdir(parents=True, exist_ok=True)
                shutil.copy(tmp / f"{name}.npz", keep / f"{name}.npz")
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
        names = [str(n).lower().replace("_", "") for n in raw["expression_names"]]
        jaw = names.index("jawopen") if "jawopen" in names else int(np.argmax(np.var(raw["weights"], 0)))
        opening = mouth_opening(frames)
        open_, shut = ok & (opening == 1.0), ok & (opening == 0.0)
        averaged = raw["landmarks68"].copy()  # 3-frame weighted averaging of the fit's own projected points
        averaged[1:-1] = 0.25 * raw["landmarks68"][:-2] + 0.5 * raw["landmarks68"][1:-1] + 0.25 * raw["landmarks68"][2:]
        average_gap = np.linalg.norm(averaged - raw["landmarks68"], axis=2).mean(1)[ok] / eye[ok]
        # averaging at the smoothed points' distance: 3-frame averaging repeated n = 0..8 times
        # (wider binomial filters), the jitter interpolated (log) between the repeats that bracket it
        repeats, points = [(0.0, jitter(raw["landmarks68"]))], raw["landmarks68"].astype(np.float64)
        for _ in range(8):
            points = np.concatenate([points[:1], 0.25 * points[:-2] + 0.5 * points[1:-1] + 0.25 * points[2:],
                                     points[-1:]])
            repeats.append((float(np.mean(np.linalg.norm(points - raw["landmarks68"], axis=2).mean(1)[ok] / eye[ok])),
                            jitter(points)))
        gaps, jitters = np.array(repeats).T
        equal_jitter = float(np.exp(np.interp(gap.mean(), gaps, np.log(jitters))))

        def point_snap(p):  # chin (8) to nose tip (33) distance, px: open minus shut
            d = np.linalg.norm(p[:, 8] - p[:, 33], axis=1)
            return float(d[open_].mean() - d[shut].mean()) if open_.any() and shut.any() else float("nan")

        def snap(w):  # the jaw weight's mean while open minus while shut
            return float(w[open_, jaw].mean() - w[shut, jaw].mean()) if open_.any() and shut.any() else float("nan")

        averaged_weights = raw["weights"].copy()
        averaged_weights[1:-1] = 0.25 * raw["weights"][:-2] + 0.5 * raw["weights"][1:-1] + 0.25 * raw["weights"][2:]
        rows += [f"astronaut video, {frames} frames 256^2, {int(ok.sum())} solved in both",
                 "| | per-frame fit | smoothed |", "|---|---|---|",
                 f"| 68-point jitter (px^2) | {jitter(raw['landmarks68']):.3f} | {jitter(smooth['landmarks68']):.3f} |",
                 f"| 68-point jitter of the fit's points averaged over 3 frames (px^2), their distance from the fit's "
                 f"(% eye distance) | {jitter(averaged):.3f}, {100 * average_gap.mean():.2f} | - |",
                 f"| 68-point jitter of the fit's points averaged to the smoothed points' distance (3-frame averaging "
                 f"repeated) | {equal_jitter:.3f} at {100 * gap.mean():.2f} | - |",
                 f"| jaw snap in the points: chin-to-nose open minus shut (px; 3-frame averaged points: "
                 f"{point_snap(averaged):.2f}) | {point_snap(raw['landmarks68']):.2f} | {point_snap(smooth['landmarks68']):.2f} |",
                 f"| weight roughness (3-frame averaged weights: "
                 f"{np.mean(np.diff(averaged_weights[ok], 2, axis=0) ** 2):.5f}) | {np.mean(np.diff(raw['weights'][ok], 2, axis=0) ** 2):.5f} | "
                 f"{np.mean(np.diff(smooth['weights'][ok], 2, axis=0) ** 2):.5f} |",
                 f"| {raw['expression_names'][jaw]} open minus shut (3-frame averaged weights: {snap(averaged_weights):.3f}) | "
                 f"{snap(raw['weights']):.3f} | {snap(smooth['weights']):.3f} |",
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
        checks = {"jitter at most 0.6x the fit's": jitter(smooth["landmarks68"]) <= 0.6 * jitter(raw["landmarks68"]),
                  "within 3% of the eye distance": 100 * gap.mean() <= 3.0,
                  "at most 10% of frames failed": smooth["failed"].mean() <= 0.1,
                  "temporal stage at most 1/4 of the fit's time": sum(stages.values()) <= 0.25 * fit_s}
        rows += ["", "issue 28's acceptance: " + "; ".join(f"{k}: {'yes' if v else 'NO'}" for k, v in checks.items())]
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--video", action="store_true", help="also the astronaut video through the graphs")
    parser.add_argument("--frames", type=int, default=24)
    parser.add_argument("--keep", type=Path, default=None, help="folder to copy the two graphs' NPZ outputs to")
    args = parser.parse_args()
    print("\n".join(curve_rows()))
    print()
    print("\n".join(known_shot_rows()))
    print()
    print("\n".join(fit_shot_rows()))
    if args.video:
        print()
        print("\n".join(video_rows(args.frames, args.keep)))


if __name__ == "__main__":
    main()
