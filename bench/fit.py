"""Bench of the deep-energy fit (nodes/fit): seconds per frame of detection + landmarks,
appearance, rigid and expression stages, and the synthetic accuracy table.

Usage: nice python bench/fit.py [--frames 50] [--size 256] [--seed 0] [--rounds 4] [--iterations 10]
                                [--workers 2]
Runs on the CPU (this machine has no GPU). fit.RigidPose and fit.Expression solve on one torch
thread (`torch_threads = 1`) in batches of 8 frames, so their rows are one core's seconds per frame;
with `--workers N` (default 2) they run again as the runner runs them, chunks of 8 frames on N threads
side by side, and the wall seconds per frame of that run are printed too ("N workers": what a graph gets
on N cores; the results are the same, tests/nodes/fit/test_batch_independence.py).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from nodegraph import Camera, ImageSequence, run_node
from nodes.fit import EstimateAppearance, EstimateIdentity, Expression, RigidPose
from nodes.io.face_model import load_face_model
from nodes.landmarks import DetectFaces, FaceLandmarks

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    r = np.einsum("fij,fkj->fik", a, b)
    return np.degrees(np.arccos(np.clip((np.trace(r, axis1=1, axis2=2) - 1) / 2, -1, 1)))


def chunked_seconds(node: type, params: dict, frames: int, workers: int, chunk: int = 8, **inputs: object) -> float:
    """Wall seconds per frame of `node` on chunks of `chunk` frames run on `workers` threads side by
    side (as the runner's threads scheduler runs a framewise node): per-frame inputs (list ports too)
    are sliced to each chunk."""
    from nodegraph import PortType

    def part(value: object, a: int, b: int) -> object:
        if isinstance(value, list):
            return [part(v, a, b) for v in value]
        return value.slice_frames(a, b) if isinstance(value, PortType) and value.per_frame else value

    def one(a: int) -> None:
        b = min(frames, a + chunk)
        run_node(node, params, frames=range(a, b), **{k: part(v, a, b) for k, v in inputs.items()})

    t = time.perf_counter()
    with ThreadPoolExecutor(workers) as pool:
        list(pool.map(one, range(0, frames, chunk)))
    return (time.perf_counter() - t) / frames


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--frames", type=int, default=50)
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=4)
    ap.add_argument("--iterations", type=int, default=None, help="fit.RigidPose / fit.Expression iterations "
                    "(Levenberg-Marquardt iterations per stage, at most; the nodes' default 10)")
    ap.add_argument("--noise", type=float, default=0.005, help="plate noise (standard deviation, linear)")
    ap.add_argument("--identity", default="estimate", choices=["estimate", "mean", "truth"],
                    help="truth: the plates' own identity, read from a file (the fit without identity error)")
    ap.add_argument("--albedo-prior", type=float, default=None, help="fit.EstimateAppearance prior_weight")
    ap.add_argument("--identity-prior", type=float, default=None, help="fit.EstimateIdentity identity_prior")
    ap.add_argument("--appearance-frames", type=int, default=None, help="fit.EstimateAppearance frames_used")
    ap.add_argument("--albedo", default=None, choices=["auto", "painted", "relative", "default"],
                    help="fit.EstimateAppearance albedo")
    ap.add_argument("--render-noise", type=float, default=None, help="fit.EstimateAppearance noise (-1 estimate)")
    ap.add_argument("--identity-frames", type=int, default=4, help="fit.EstimateIdentity frames_used (as the "
                    "graphs: 4)")
    ap.add_argument("--mesh-weight", type=float, default=None, help="fit.EstimateIdentity mesh_weight")
    ap.add_argument("--identity-iterations", type=int, default=None, help="fit.EstimateIdentity iterations")
    ap.add_argument("--identity-rounds", type=int, default=None, help="fit.EstimateIdentity rounds")
    ap.add_argument("--photometric", type=float, default=None, help="fit.RigidPose / fit.Expression "
                    "photometric_weight (0 = landmarks only)")
    ap.add_argument("--identity-photometric", type=float, default=None, help="fit.EstimateIdentity "
                    "photometric_weight (0 = landmarks only)")
    ap.add_argument("--identity-passes", type=int, default=2, help="appearance + identity passes after the "
                    "first identity (as the graphs: 2)")
    ap.add_argument("--identity-points", type=int, default=468, choices=[68, 468],
                    help="landmarks the identity is estimated from (as graphs/fit_video.json: 468, the 68 then 400 more face-mesh points)")
    ap.add_argument("--iris", action="store_true", help="the iris centres into fit.Expression (eyeLook weights)")
    ap.add_argument("--workers", type=int, default=2, help="also time fit.RigidPose and fit.Expression as chunks "
                    "of 8 frames on this many threads side by side (0: skip)")
    args = ap.parse_args()
    model = load_face_model()
    cam = Camera.from_fov(args.size, args.size, 30.0)
    truth = random_face_parameters(model, args.frames, seed=args.seed, distance_cm=65.0)
    plates = render_truth_plates(model, [cam], truth, noise=args.noise)[0]
    seq = ImageSequence(plates, colour_space="linear")
    f = args.frames
    times = {}
    t = time.perf_counter()
    det = run_node(DetectFaces, images=seq)
    lm_out = run_node(FaceLandmarks, images=seq, boxes=det["boxes"])
    marks = lm_out["landmarks68"]
    id_marks = lm_out["landmarks468"] if args.identity_points == 468 else marks
    times["detection + landmarks"] = (time.perf_counter() - t) / f
    views = dict(landmarks=[marks], boxes=[det["boxes"]], cameras=[cam])
    id_views = dict(views, landmarks=[id_marks])
    # as graphs/fit_video.json: identity with the default appearance, then twice the appearance
    # of that identity and the identity again with that appearance
    ident_params = {"mode": args.identity, "frames_used": args.identity_frames}
    if args.identity_prior is not None:
        ident_params["identity_prior"] = args.identity_prior
    if args.mesh_weight is not None:
        ident_params["mesh_weight"] = args.mesh_weight
    if args.identity_iterations is not None:
        ident_params["iterations"] = args.identity_iterations
    if args.identity_rounds is not None:
        ident_params["rounds"] = args.identity_rounds
    if args.identity == "truth":
        tmp = tempfile.mkdtemp()
        np.savez(f"{tmp}/identity.npz", identity=truth["identity"])
        ident_params = {"mode": "file", "path": f"{tmp}/identity.npz"}
    t = time.perf_counter()
    first = run_node(EstimateIdentity, ident_params, frames=range(f), model=model, **id_views)
    app_params = {} if args.albedo_prior is None else {"prior_weight": args.albedo_prior}
    if args.render_noise is not None:
        app_params["noise"] = args.render_noise
    if args.albedo is not None:
        app_params["albedo"] = args.albedo
    if args.appearance_frames is not None:
        app_params["frames_used"] = args.appearance_frames
    app = run_node(EstimateAppearance, app_params, images=seq, landmarks=marks, boxes=det["boxes"], camera=cam,
                   model=first["fitted_model"])
    common = dict(views, appearance=app["appearance"])
    if args.identity_photometric is not None:
        ident_params["photometric_weight"] = args.identity_photometric
    ident = run_node(EstimateIdentity, ident_params, frames=range(f), model=model,
                     **dict(common, landmarks=[id_marks], images=[seq]))
    for _ in range(args.identity_passes - 1):  # appearance of the new identity, then the identity again
        app = run_node(EstimateAppearance, app_params, images=seq, landmarks=marks, boxes=det["boxes"], camera=cam,
                       model=ident["fitted_model"])
        common = dict(views, appearance=app["appearance"])
        ident = run_node(EstimateIdentity, ident_params, frames=range(f), model=model,
                         **dict(common, landmarks=[id_marks], images=[seq]))
    times["identity + appearance (once, per shot)"] = time.perf_counter() - t
    fitted = ident["fitted_model"]
    t, c = time.perf_counter(), time.process_time()
    fit_params = {"rounds": args.rounds}
    if args.iterations is not None:
        fit_params["iterations"] = args.iterations
    if args.photometric is not None:
        fit_params["photometric_weight"] = args.photometric
    common = dict(common, images=[seq])
    rigid = run_node(RigidPose, fit_params, frames=range(f), model=fitted, **common)
    times["rigid"] = (time.perf_counter() - t) / f
    cpu = {"rigid": (time.process_time() - c) / f}
    t, c = time.perf_counter(), time.process_time()
    if args.iris:
        common = dict(common, iris=[lm_out["iris"]])
    expr = run_node(Expression, fit_params, frames=range(f), model=fitted, pose=rigid["pose"], **common)
    times["expression"] = (time.perf_counter() - t) / f
    cpu["expression"] = (time.process_time() - c) / f
    if args.workers > 0:
        w = args.workers
        times[f"rigid, {w} workers"] = chunked_seconds(RigidPose, fit_params, f, w, model=fitted, **common)
        times[f"expression, {w} workers"] = chunked_seconds(Expression, fit_params, f, w, model=fitted,
                                                            pose=rigid["pose"], **common)
        times[f"rigid + expression, {w} workers"] = times[f"rigid, {w} workers"] + times[f"expression, {w} workers"]
    print(f"CPU (no GPU), {f} frames of {args.size}x{args.size}:")
    for k, v in times.items():
        print(f"  {k:34s} {v:7.3f} s" + ("" if "once" in k else " / frame")
              + (f" (process CPU {cpu[k]:.3f} s / frame)" if k in cpu else ""))
    v = expr["fitted"].values
    ok = expr["failed"].values[:, 0] == 0
    j = model.expression_names.index("jawOpen")
    rot = rotation_error_deg(v[ok, :9].reshape(-1, 3, 3), truth["rotation"][ok])
    dt = np.abs(v[ok, 9:12] - truth["translation"][ok])
    jaw = np.abs(v[ok, 12 + j] - truth["weights"][ok, j])
    est = np.asarray(ident["identity"].value["identity"])
    print(f"identity: norm {np.linalg.norm(est):.2f} (truth {np.linalg.norm(truth['identity']):.2f}), "
          f"error norm {np.linalg.norm(est - truth['identity']):.2f}")
    from scipy.spatial.transform import Rotation

    off = Rotation.from_matrix(np.einsum("fji,fjk->fik", truth["rotation"][ok], v[ok, :9].reshape(-1, 3, 3))).as_rotvec()
    off = np.degrees(off)  # model-frame error of each frame
    spread = np.linalg.norm(off - np.median(off, 0), axis=1)
    print(f"model-frame rotation error: median vector {np.round(np.median(off, 0), 2)} deg, "
          f"median distance from it {np.median(spread):.2f} deg")
    print(f"accuracy ({ok.sum()} fitted frames, identity={args.identity}): median / 90th percentile")
    for name, e in (("rotation deg", rot), ("x cm", dt[:, 0]), ("y cm", dt[:, 1]), ("depth cm", dt[:, 2]),
                    ("jawOpen", jaw)):
        print(f"  {name:14s} {np.median(e):6.3f} / {np.percentile(e, 90):6.3f}")
    from nodes.fit.energy import eye_look_shapes
    from nodes.fit.output_nodes import projected_landmarks68
    from nodes.geometry.camera import project_points
    from nodes.landmarks.correspondence import inter_ocular_distance

    eyes = eye_look_shapes(list(model.expression_names))
    eye_err = np.abs(v[ok][:, [12 + i for i in eyes]] - truth["weights"][ok][:, eyes])
    print(f"  {'eyeLook (8)':14s} {np.median(eye_err):6.3f} / {np.percentile(eye_err, 90):6.3f}"
          f"  (truth's largest {np.abs(truth['weights'][:, eyes]).max():.3f})")
    true_local = model.evaluate(truth["weights"], truth["identity"])[:, model.landmarks]
    true68 = project_points(true_local @ np.swapaxes(truth["rotation"], 1, 2) + truth["translation"][:, None],
                            cam.world_to_camera, np.array([cam.fx, cam.fy, cam.cx, cam.cy]))[ok]
    fit68 = projected_landmarks68(v, fitted, cam).pixels[ok]
    net68 = marks.points[ok]
    iod = np.array([inter_ocular_distance(p) for p in true68])
    for name, a, b in (("fit - network", fit68, net68), ("fit - truth", fit68, true68),
                       ("network - truth", net68, true68)):
        e = np.linalg.norm(a - b, axis=-1).mean(1) / iod * 100
        print(f"  68 points {name:16s} {np.median(e):6.2f} / {np.percentile(e, 90):6.2f} % of the eye distance")


if __name__ == "__main__":
    main()
