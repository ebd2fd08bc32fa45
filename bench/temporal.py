"""Optical flow and temporal refinement: accuracy and time.

Run: nice python bench/temporal.py [--size 256] [--pairs 4] [--threads 2] [--frames 9]

1. Flow on pairs of renders of the bundled head under known motion (two amplitudes) (`tests.support.synthetic`,
   textured skin, grey background; the truth is the geometric render flow): mean end-point
   error over the face (px) and ms per pair, ours (the differentiable torch `dense_flow` and
   its compiled forward pass `dense_flow_numpy`, which `flow.OpticalFlow` runs on the CPU)
   against OpenCV DIS (medium and fast presets, on 8-bit sRGB luminance, when `cv2` is
   installed); the defaults of both also on one thread.
2. Infill: a shot with 5 consecutive frames marked failed during a fast jaw opening; mean
   absolute error of rotation (rad), translation (cm) and jawOpen over the run, for linear
   interpolation of the neighbours and `temporal.FlowInfill` with geometric and optical plate
   flow.
3. Smoothing: the same shot with per-frame fitting noise (0.01 rad, 0.15 cm); jitter (mean
   squared second difference of the 6 rigid parameters) and mean absolute error to the truth,
   for the raw values, averaging, self flow, plate flow and hybrid (optical plate flow).
4. `--video FRAMES`: the real-video case (`bench/smoothing.py --video`, run from here too).
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from _timing import median_ms

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support


@contextlib.contextmanager
def one_thread(cv2) -> Iterator[None]:
    """numba's and OpenCV's thread counts set to 1 inside the block."""
    import numba

    threads, cv_threads = numba.get_num_threads(), (cv2.getNumThreads() if cv2 is not None else 0)
    numba.set_num_threads(1)
    if cv2 is not None:
        cv2.setNumThreads(1)
    try:
        yield
    finally:
        numba.set_num_threads(threads)
        if cv2 is not None:
            cv2.setNumThreads(cv_threads)


def flow_rows(size: int, pairs: int) -> list[tuple[str, float, float]]:
    from nodes.flow.dense import FlowSettings, dense_flow, endpoint_error
    from nodes.flow.fast import dense_flow_numpy
    from nodes.flow.geometric import render_flow
    from tests.support.synthetic import head_motion, make_scene, render_scene_plates, scene_vertices

    scene = make_scene(size)
    cam = scene.camera
    e = torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None]
    k = torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]])
    try:
        import cv2
    except ImportError:
        cv2 = None
    results: dict[str, list[tuple[float, float]]] = {}
    for pair in range(2 * pairs):
        seed, amplitude = pair % pairs, 1.0 + pair // pairs  # amplitude 2: ~6 px mean motion at 256^2
        values = head_motion(2, scene.model.expression_names, seed=10 + seed, amplitude=amplitude, mouth_frames=(0, 2))
        plates = render_scene_plates(scene, values)
        verts = scene_vertices(scene, values)
        truth, mask = render_flow(verts[:1], verts[1:], torch.as_tensor(scene.faces), e, k, cam.height, cam.width)
        img = torch.as_tensor(plates.pixels).permute(0, 3, 1, 2)
        with torch.no_grad():
            flow = dense_flow(img[:1], img[1:])
            ms = median_ms(lambda: dense_flow(img[:1], img[1:]))
        tag = f", motion x{amplitude:.0f}"
        results.setdefault("ours, torch (differentiable)" + tag, []).append((endpoint_error(flow, truth, mask).item(), ms))
        for name, settings in (("ours, compiled (flow.OpticalFlow defaults)", FlowSettings()),
                               ("ours, compiled, plain Jacobi (v2: 12/40 iterations, 8 warps)",
                                FlowSettings(acceleration=0.0, finest_iterations=12, iterations=40, warps=8)),
                               ("ours, compiled, warps=8", FlowSettings(warps=8)),
                               ("ours, compiled, finest_warps=8", FlowSettings(finest_warps=8)),
                               ("ours, compiled, fast (skip 1, 7 warps, median/warp, alpha .07)",
                                FlowSettings(skip_levels=1, warps=7, median_every_warp=True, alpha=0.07))):
            fast = torch.as_tensor(dense_flow_numpy(img[:1], img[1:], settings))[None]
            epe = endpoint_error(fast, truth, mask).item()
            ms = median_ms(lambda: dense_flow_numpy(img[:1], img[1:], settings))
            results.setdefault(name + tag, []).append((epe, ms))
            if settings == FlowSettings():  # one thread each, ours and DIS: the cost without threading
                with one_thread(cv2):
                    ms = median_ms(lambda: dense_flow_numpy(img[:1], img[1:], settings))
                results.setdefault(name + ", 1 thread" + tag, []).append((epe, ms))
        results.setdefault("|true motion|" + tag, []).append((truth.norm(dim=1)[mask].mean().item(), 0.0))
        if cv2 is None:
            continue
        grey = (np.clip(plates.pixels, 0, 1) ** (1 / 2.2)) @ np.array([0.2126, 0.7152, 0.0722])
        u8 = [(g * 255).astype(np.uint8) for g in grey]
        for name, preset in (("DIS medium", cv2.DISOPTICAL_FLOW_PRESET_MEDIUM),
                             ("DIS fast", cv2.DISOPTICAL_FLOW_PRESET_FAST)):
            dis = cv2.DISOpticalFlow_create(preset)
            d = dis.calc(u8[0], u8[1], None)
            ms = median_ms(lambda: dis.calc(u8[0], u8[1], None))
            epe = endpoint_error(torch.as_tensor(d).permute(2, 0, 1)[None], truth, mask).item()
            results.setdefault(name + tag, []).append((epe, ms))
            if preset == cv2.DISOPTICAL_FLOW_PRESET_MEDIUM:
                with one_thread(cv2):
                    ms = median_ms(lambda: dis.calc(u8[0], u8[1], None))
                results.setdefault(name + ", 1 thread" + tag, []).append((epe, ms))
    return sorted([(name, float(np.mean([r[0] for r in rows])), float(np.median([r[1] for r in rows])))
                   for name, rows in results.items()], key=lambda row: row[0].rpartition(",")[2])


def temporal_rows(frames: int) -> tuple[list, list]:
    from nodegraph import FlowSequence, ParamSequence, run_node
    from nodes.flow import OpticalFlow
    from nodes.flow.geometric import render_flow
    from nodes.temporal import Average, FlowInfill, Hybrid, PlateFlow, SelfFlow
    from nodes.temporal.layout import RIGID_NAMES
    from tests.support.synthetic import head_motion, make_scene, render_scene_plates, scene_vertices

    size = 64
    scene = make_scene(size)
    names = scene.model.expression_names
    truth = head_motion(frames, names, seed=2, mouth_frames=(1, frames - 1))
    verts = scene_vertices(scene, truth)
    cam = scene.camera
    e = torch.as_tensor(cam.world_to_camera, dtype=torch.float32).expand(frames - 1, 4, 4)
    k = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy]).expand(frames - 1, 4)
    flow, _ = render_flow(verts[:-1], verts[1:], torch.as_tensor(scene.faces), e, k, size, size)
    exact = np.zeros((frames, size, size, 2), np.float32)
    exact[:-1] = flow.permute(0, 2, 3, 1).numpy()
    flows = {"geometric": FlowSequence(exact, np.r_[np.ones(frames - 1, bool), False]),
             "optical": run_node(OpticalFlow, images=render_scene_plates(scene, truth))["flow"]}

    def seq(values):
        return ParamSequence(np.asarray(values, np.float32), list(RIGID_NAMES) + list(names))

    jaw = 6 + names.index("jawOpen")
    a, b = 2, 7
    failed = np.zeros(frames, bool)
    failed[a:b] = True
    gapped = truth.copy()
    gapped[failed] = 0.0
    t = np.linspace(0, 1, b - a + 2)[1:-1, None]
    interp = (1 - t) * truth[a - 1] + t * truth[b]

    def run_err(v):
        d = np.abs(v[a:b] - truth[a:b])
        return d[:, :3].mean(), d[:, 3:6].mean(), d[:, jaw].mean()

    infill = [("linear interpolation",) + run_err(np.r_[truth[:a], interp, truth[b:]]) + (0.0,)]
    for kind, plate in flows.items():
        t0 = time.perf_counter()
        out = run_node(FlowInfill, {"iterations": 6, "stride": 2}, fitted=seq(gapped),
                       failed=ParamSequence(failed[:, None].astype(np.float32), ["failed"]), plate_flow=plate,
                       model=scene.model, camera=scene.camera)["infilled"].values
        infill.append((f"FlowInfill, {kind} plate flow",) + run_err(out) + (time.perf_counter() - t0,))
    # the render flow matched to the optical plate flow: exact surface motion or the same optical flow
    from nodegraph import JsonValue
    from nodes.render.appearance import appearance_json

    app = JsonValue(appearance_json(scene.albedo, scene.sh, tuple(scene.background), None))
    t0 = time.perf_counter()
    out = run_node(FlowInfill, {"iterations": 6, "stride": 2, "render_flow": "optical", "optical_steps": 6},
                   fitted=seq(gapped), failed=ParamSequence(failed[:, None].astype(np.float32), ["failed"]),
                   plate_flow=flows["optical"], model=scene.model, camera=scene.camera,
                   appearance=app)["infilled"].values
    infill.append(("FlowInfill, optical plate + optical render flow",) + run_err(out) + (time.perf_counter() - t0,))

    rng = np.random.default_rng(0)
    noisy = truth.copy()
    noisy[:, :3] += rng.normal(0, 0.01, (frames, 3))
    noisy[:, 3:6] += rng.normal(0, 0.15, (frames, 3))

    def jitter(v):
        return float((np.diff(v[:, :6], 2, axis=0) ** 2).mean())

    def err(v):
        return float(np.abs(v[1:-1, :6] - truth[1:-1, :6]).mean())

    common = dict(plate_flow=flows["optical"], model=scene.model, camera=scene.camera)
    smooth = [("raw (noisy fit)", jitter(noisy), err(noisy), 0.0)]
    t0 = time.perf_counter()
    avg = run_node(Average, fitted=seq(noisy))["averaged"].values
    smooth.append(("averaging", jitter(avg), err(avg), time.perf_counter() - t0))
    for name, node in (("self flow", SelfFlow), ("plate flow", PlateFlow), ("hybrid", Hybrid)):
        t0 = time.perf_counter()
        out = run_node(node, {"sweeps": 2, "iterations": 4, "stride": 2}, fitted=seq(noisy), **common)["smoothed"].values
        smooth.append((name, jitter(out), err(out), time.perf_counter() - t0))
    return infill, smooth


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--pairs", type=int, default=4)
    parser.add_argument("--frames", type=int, default=9)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--video", type=int, default=0, metavar="FRAMES",
                        help="also the real-video case: bench/smoothing.py's astronaut video of FRAMES frames "
                        "through fit_video.json and fit_video_temporal.json (roughness of pose, weights and "
                        "landmarks, failed frames, seconds per frame of each temporal stage beside the fit's)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    import numba

    numba.set_num_threads(min(args.threads, numba.config.NUMBA_NUM_THREADS))
    print(f"torch {torch.__version__}, {args.threads} threads; flow on {args.pairs} face-render pairs at "
          f"{args.size}^2")
    print(f"{'flow':66s} {'EPE px':>8s} {'ms/pair':>8s}")
    rows = flow_rows(args.size, args.pairs)
    for name, epe, ms in rows:
        print(f"{name:66s} {epe:8.3f} {ms:8.1f}")
    table = {name: (epe, ms) for name, epe, ms in rows}
    for tag in sorted({name.rpartition(",")[2] for name in table if "motion" in name}):
        ours, dis = table.get("ours, compiled (flow.OpticalFlow defaults)," + tag), table.get("DIS medium," + tag)
        if ours and dis:
            print(f"flow.OpticalFlow defaults against DIS medium,{tag}: {ours[0] / dis[0]:.2f}x its EPE in "
                  f"{ours[1] / dis[1]:.2f}x its time")
    infill, smooth = temporal_rows(args.frames)
    print(f"\n{'infill of 5 failed frames':48s} {'rot rad':>8s} {'trans cm':>8s} {'jawOpen':>8s} {'s':>6s}")
    for name, r, t, j, s in infill:
        print(f"{name:48s} {r:8.4f} {t:8.3f} {j:8.4f} {s:6.1f}")
    print(f"\n{'smoothing (optical plate flow)':34s} {'jitter':>9s} {'error':>8s} {'s':>6s}")
    for name, jit, e, s in smooth:
        print(f"{name:34s} {jit:9.5f} {e:8.4f} {s:6.1f}")
    if args.video:
        from smoothing import video_rows

        print()
        print("\n".join(video_rows(args.video)))


if __name__ == "__main__":
    main()
