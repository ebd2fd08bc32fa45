"""CUDA against CPU: timings and agreement of the render, the landmark networks and the fit.

Run: python bench/gpu.py [--repeat 5] [--frames 4] [--device cuda]

One short script (about a minute on a GPU machine, two to three on a 2-core CPU) for a machine
with an NVIDIA GPU: `nodegraph run ... --device cuda` computes the nodes below on the GPU, and
this prints what that buys and how far the GPU's results are from the CPU's. On a machine
without CUDA it says so and exits 0. `--device cpu` runs every step twice on the CPU (a check of
the script itself; the agreement is then exact or at the level of thread scheduling).

Rows (ms per frame, median of `--repeat` runs after one warm-up, CUDA synchronized):
  render 256^2 fwd / fwd+bwd   the whole ICT head, default appearance, gradients w.r.t. vertices,
                               albedo and SH; agreement: max |image difference| (linear colour)
                               and the relative difference of the vertex gradient
  detector 512^2               BlazeFace on skimage's astronaut; agreement: box corners, px
  face mesh (crop + net)       468 points on the detector's box; agreement: max point distance, px
  fit rigid + expression       fit.RigidPose + fit.Expression on `--frames` synthetic 256^2 plates
                               (mean identity, default appearance: the per-frame stages the
                               graphs chunk); agreement: rotation (deg), translation (cm), weights;
                               then each device's error against the plates' truth (median rotation,
                               depth, jawOpen), so a difference can be judged: equal errors mean the
                               two landed at different points of the same flat valley

Tolerances (a row prints `ok` or `DIFFERS`): float32 kernels sum in another order on the GPU, so
renders agree to ~1e-5 of their range and networks to ~1e-3 px (1e-4 image, 5e-3 px allowed
here). The fit is a solve in a flat valley (issue 30: a 1e-5 change in its inputs can move a
weakly observed weight by a few hundredths); its rows allow 0.5 deg, 0.5 cm and 0.05, and print
the actual differences so a larger one is seen.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _timing import median_ms

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository root: tests.support

RENDER_TOL = 1e-4      # max |image difference|, linear colour
GRAD_TOL = 1e-3        # relative difference of the vertex gradient (norm of difference / norm)
POINT_TOL_PX = 5e-3    # detector box corners and face mesh points, px
FIT_TOL = {"rotation deg": 0.5, "translation cm": 0.5, "weights": 0.05}


def _verdict(value: float, tol: float) -> str:
    return "ok" if value <= tol else "DIFFERS"


def _sync() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def bench_render(device: str, repeat: int) -> list[tuple[str, float, float, str]]:
    """(row, ms on CPU, ms on `device`, agreement text) for the render at 256^2."""
    from nodes.io.face_model import load_face_model
    from nodes.render.appearance import DEFAULT_LIGHT, default_albedo, default_sh, visible_faces
    from nodes.geometry.mesh import triangle_adjacency
    from nodes.render.renderer import render_mesh

    model = load_face_model()
    faces = visible_faces(model.faces, model.neutral.shape[0])
    adjacency = triangle_adjacency(faces)
    extrinsics = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, -1, 55.0], [0, 0, 0, 1]])
    albedo, sh = default_albedo(model), default_sh()

    def run(dev: str, grad: bool):
        v = torch.as_tensor(model.neutral, device=dev)[None].clone().requires_grad_(grad)
        a = torch.as_tensor(albedo, device=dev)[None].clone().requires_grad_(grad)
        s = torch.as_tensor(sh, device=dev)[None].clone().requires_grad_(grad)
        e = torch.as_tensor(extrinsics, dtype=torch.float32, device=dev)[None]
        k = torch.tensor([[520.0, 520.0, 127.5, 127.5]], device=dev)
        out = render_mesh(v, faces, e, k, 256, 256, albedo=a, sh=s,
                          background=torch.as_tensor(DEFAULT_LIGHT["background"], device=dev), adjacency=adjacency)
        if grad:
            (out.image * torch.linspace(0, 1, 256 * 256 * 3, device=dev).reshape(out.image.shape)).sum().backward()
            return out.image.detach(), v.grad
        return out.image, None

    rows = []
    with torch.no_grad():
        cpu_fwd = median_ms(lambda: run("cpu", False), repeat)
        dev_fwd = median_ms(lambda: run(device, False), repeat)
    cpu_both = median_ms(lambda: run("cpu", True), repeat)
    dev_both = median_ms(lambda: run(device, True), repeat)
    img_c, grad_c = run("cpu", True)
    img_d, grad_d = run(device, True)
    diff = float((img_c - img_d.cpu()).abs().max())
    rel = float((grad_c - grad_d.cpu()).norm() / grad_c.norm().clamp_min(1e-30))
    rows.append(("render 256^2 fwd", cpu_fwd, dev_fwd, f"image {diff:.1e} {_verdict(diff, RENDER_TOL)}"))
    rows.append(("render 256^2 fwd+bwd", cpu_both, dev_both,
                 f"vertex gradient {rel:.1e} relative {_verdict(rel, GRAD_TOL)}"))
    return rows


def bench_networks(device: str, repeat: int) -> list[tuple[str, float, float, str]]:
    """Detector and face mesh on skimage's astronaut."""
    from skimage.data import astronaut

    from nodes.landmarks.network import detect_faces, face_landmarks, load_face_detector, load_face_mesh

    pixels = astronaut().astype(np.float32) / 255.0
    out = {}
    times = {}
    for label, dev in (("cpu", "cpu"), ("other", device)):  # labels: `device` may be "cpu" too
        photo = torch.as_tensor(pixels, device=dev)[None]
        detector, mesh = load_face_detector(dev), load_face_mesh(dev)
        with torch.no_grad():
            det = detect_faces(photo, detector)
            times[label] = (median_ms(lambda: detect_faces(photo, detector), repeat),
                          median_ms(lambda: face_landmarks(photo, det.boxes, mesh), repeat))
            points, _ = face_landmarks(photo, det.boxes, mesh)
        out[label] = (np.asarray(det.face_boxes, np.float64), points.cpu().numpy().astype(np.float64))
    box = float(np.abs(out["cpu"][0] - out["other"][0]).max())
    pts = float(np.linalg.norm(out["cpu"][1] - out["other"][1], axis=-1).max())
    return [("detector 512^2", times["cpu"][0], times["other"][0], f"box {box:.1e} px {_verdict(box, POINT_TOL_PX)}"),
            ("face mesh (crop + net)", times["cpu"][1], times["other"][1],
             f"points {pts:.1e} px {_verdict(pts, POINT_TOL_PX)}")]


def bench_fit(device: str, frames: int) -> list[tuple[str, float, float, str]]:
    """fit.RigidPose + fit.Expression on synthetic plates, per frame, and their agreement."""
    from nodegraph import Camera, ImageSequence
    from nodegraph.node import execute
    from nodes.fit import EstimateIdentity, Expression, RigidPose
    from tests.support.synthetic import random_face_parameters, render_truth_plates
    from nodes.geometry.rotation import rotmat_to_axis_angle
    from nodes.io.face_model import load_face_model
    from nodes.landmarks import DetectFaces, FaceLandmarks

    model = load_face_model()
    cam = Camera.from_fov(256, 256, 30.0)
    truth = random_face_parameters(model, frames, seed=0, distance_cm=65.0)
    seq = ImageSequence(render_truth_plates(model, [cam], truth)[0], colour_space="linear")
    span = range(frames)

    def node_run(node_type, params, device_name, **inputs):
        return execute(node_type(params), inputs, span, span, device=device_name)

    det = node_run(DetectFaces, {}, "cpu", images=seq)
    marks = node_run(FaceLandmarks, {}, "cpu", images=seq, boxes=det["boxes"])
    views = dict(landmarks=[marks["landmarks68"]], boxes=[det["boxes"]], cameras=[cam], images=[seq])
    fitted = node_run(EstimateIdentity, {"mode": "mean"}, "cpu", model=model, **dict(views, images=[]))["fitted_model"]
    results, seconds = {}, {}
    for label, dev in (("cpu", "cpu"), ("other", device)):
        _sync()
        t = time.perf_counter()
        pose = node_run(RigidPose, {}, dev, model=fitted, **views)["pose"]
        expr = node_run(Expression, {}, dev, model=fitted, pose=pose, **views)["fitted"].values
        _sync()
        seconds[label] = (time.perf_counter() - t) / frames * 1e3
        results[label] = np.asarray(expr, np.float64)
    a, b = results["cpu"], results["other"]
    rel = np.einsum("fji,fjk->fik", a[:, :9].reshape(-1, 3, 3), b[:, :9].reshape(-1, 3, 3))
    diffs = {"rotation deg": float(np.degrees(np.linalg.norm(rotmat_to_axis_angle(rel), axis=1)).max()),
             "translation cm": float(np.abs(a[:, 9:12] - b[:, 9:12]).max()),
             "weights": float(np.abs(a[:, 12:] - b[:, 12:]).max())}
    text = ", ".join(f"{k} {v:.3g} {_verdict(v, FIT_TOL[k])}" for k, v in diffs.items())
    # Which device is closer to the truth? Equal errors mean a flat valley, not a wrong kernel.
    jaw = model.expression_names.index("jawOpen")
    for label, r in results.items():
        err = np.einsum("fji,fjk->fik", truth["rotation"].astype(np.float64), r[:, :9].reshape(-1, 3, 3))
        rot = np.degrees(np.linalg.norm(rotmat_to_axis_angle(err), axis=1))
        depth = np.abs(r[:, 11] - truth["translation"][:, 2])
        jaw_err = np.abs(r[:, 12 + jaw] - truth["weights"][:, jaw])
        name = "cpu" if label == "cpu" else device
        text += (f"; {name} vs truth: rotation median {np.median(rot):.2f} / max {rot.max():.2f} deg, depth "
                 f"{np.median(depth):.2f} cm, jawOpen {np.median(jaw_err):.3f}")
    return [(f"fit rigid + expression ({frames} frames)", seconds["cpu"], seconds["other"], text)]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--frames", type=int, default=4, help="synthetic plates of the fit rows")
    parser.add_argument("--device", default="cuda", choices=["cuda", "cpu"],
                        help="the device compared with the CPU (cpu: a check of the script)")
    args = parser.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        print(f"torch {torch.__version__}: no CUDA GPU on this machine; nothing to time "
              "(run with --device cpu to check the script)")
        return 0
    name = torch.cuda.get_device_name(0) if args.device == "cuda" else "CPU again"
    print(f"torch {torch.__version__}, CPU threads {torch.get_num_threads()}, against: {args.device} ({name})")
    rows = bench_render(args.device, args.repeat) + bench_networks(args.device, args.repeat) \
        + bench_fit(args.device, args.frames)
    print(f"{'what':38s} {'CPU ms':>9s} {args.device + ' ms':>9s} {'speed-up':>8s}  agreement")
    for what, cpu_ms, dev_ms, agreement in rows:
        print(f"{what:38s} {cpu_ms:9.1f} {dev_ms:9.1f} {cpu_ms / max(dev_ms, 1e-9):7.1f}x  {agreement}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
