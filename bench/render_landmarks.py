"""Renderer and landmark-network timings, and landmark agreement on renders of the bundled head.

Run: nice python bench/render_landmarks.py [--repeat 5] [--threads 2] [--batch 1]

Rows (median of `--repeat` runs after one warm-up, ms per frame; for the renders also the
process CPU time, all threads, which a busy shared machine inflates less than the wall time):
  render fwd / fwd+bwd   the whole ICT head (48,836 drawn triangles of 52,220: eye shells
                         and lashes hidden) at 256^2 and 512^2, default appearance, antialiased,
                         gradients w.r.t. vertices, albedo and SH (fwd+bwd = forward plus backward)
  detector               BlazeFace on a 512 x 512 photograph (letterbox, 128^2, decode, NMS)
  face mesh fwd / +bwd   crop to 192^2 + MediaPipe face mesh, and with the gradient to the image
Then the agreement on renders at five poses (yaw/pitch/jaw): the mean distance of the
network's 68 points to the projected model landmarks, in inter-ocular distances, and the
nose-tip offset of the two schemes (face-mesh 4 vs model landmark 30).
CUDA rows appear when a GPU is present.

OpenMP threads wait passively (OMP_WAIT_POLICY=PASSIVE unless set), as under the `nodegraph`
command (`nodegraph.cli.main`): with torch's default active wait, its second OpenMP thread spins
after every parallel op (the bench's clone and sum, autograd's adds, the networks' layers) on
the core the renderer's second half (`nodes.render.halves`) or another process needs. At 8db5e8d,
`--threads 2 --repeat 9` at load 1.7-2.4 on 2 cores, OMP_WAIT_POLICY=ACTIVE against passive:
render 256^2 fwd+bwd 84.2 against 28.6 ms (wall), 512^2 152.0 / 78.9, detector 285 / 16.6.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # read when torch loads, below

import numpy as np  # noqa: E402
import torch  # noqa: E402
from _timing import median_ms  # noqa: E402


def wall_and_cpu_ms(fn, repeat: int) -> tuple[float, float]:
    """Medians of the wall time and of the process CPU time (all threads) of `fn()`, ms, over
    `repeat` runs after one warm-up (CUDA synchronized)."""
    fn()
    walls, cpus = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        if torch.cuda.is_available():
            torch.cuda.synchronize()
        walls.append((time.perf_counter() - t0) * 1e3)
        cpus.append((time.process_time() - c0) * 1e3)
    return statistics.median(walls), statistics.median(cpus)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=1, help="frames rendered per call")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from scipy.spatial.transform import Rotation
    from skimage.data import astronaut

    from nodes.geometry.camera import project_points
    from nodes.io.face_model import load_face_model
    from nodes.landmarks.correspondence import inter_ocular_distance, mediapipe_to_68
    from nodes.landmarks.network import (detect_faces, face_landmarks, load_face_detector,
                                         load_face_mesh, srgb_encode)
    from nodes.render.appearance import DEFAULT_LIGHT, default_albedo, default_sh, visible_faces
    from nodes.geometry.mesh import triangle_adjacency
    from nodes.render.renderer import render_mesh

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {args.threads} threads, devices: {devices}"
          + ("" if len(devices) > 1 else " (no CUDA GPU on this machine)"))
    model = load_face_model()
    albedo, sh = default_albedo(model), default_sh()
    faces = visible_faces(model.faces, model.neutral.shape[0])
    adjacency = triangle_adjacency(faces)
    extrinsics = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, -1, 55.0], [0, 0, 0, 1]])
    rows = []
    for device in devices:
        for size in (256, 512):
            b = args.batch
            e = torch.as_tensor(extrinsics, dtype=torch.float32, device=device).expand(b, 4, 4)
            k = torch.tensor([[520.0 * size / 256, 520.0 * size / 256, (size - 1) / 2, (size - 1) / 2]],
                             device=device).expand(b, 4)
            verts0 = torch.as_tensor(model.neutral, device=device)[None].expand(b, -1, -1).contiguous()
            alb0 = torch.as_tensor(albedo, device=device)[None]
            sh0 = torch.as_tensor(sh, device=device)[None]
            bg = torch.as_tensor(DEFAULT_LIGHT["background"], device=device)

            def forward(grad: bool = False):
                v, a, s = (t.clone().requires_grad_(grad) for t in (verts0, alb0, sh0))
                out = render_mesh(v, faces, e, k, size, size, albedo=a, sh=s, background=bg, adjacency=adjacency)
                if grad:
                    out.image.sum().backward()
                return out

            with torch.no_grad():
                fwd, fwd_cpu = wall_and_cpu_ms(forward, args.repeat)
            both, both_cpu = wall_and_cpu_ms(lambda: forward(True), args.repeat)
            rows.append((f"render {size}^2 fwd", device, fwd / b, fwd_cpu / b))
            rows.append((f"render {size}^2 fwd+bwd", device, both / b, both_cpu / b))

        photo = torch.as_tensor(astronaut().astype(np.float32) / 255.0, device=device)[None]
        detector, mesh = load_face_detector(device), load_face_mesh(device)
        det = detect_faces(photo, detector)
        rows.append(("detector 512^2 photo", device, median_ms(lambda: detect_faces(photo, detector), args.repeat),
                     None))
        with torch.no_grad():
            rows.append(("face mesh fwd (crop+net)", device,
                         median_ms(lambda: face_landmarks(photo, det.boxes, mesh), args.repeat), None))

        def mesh_backward():
            x = photo.clone().requires_grad_()
            points, _ = face_landmarks(x, det.boxes, mesh)
            points.sum().backward()

        rows.append(("face mesh fwd+bwd", device, median_ms(mesh_backward, args.repeat), None))
    print(f"{'what':28s} {'device':6s} {'ms/frame':>9s} {'cpu ms':>7s}")
    for name, device, ms, cpu in rows:
        print(f"{name:28s} {device:6s} {ms:9.1f} " + ("" if cpu is None else f"{cpu:7.1f}"))

    # agreement on renders of the head
    jaw = model.expression_names.index("jawOpen")
    poses = [(0.0, 0.0, 0.0), (20.0, -5.0, 0.2), (-25.0, 5.0, 0.3), (10.0, 8.0, 0.6), (-10.0, -8.0, 0.0),
             (30.0, 0.0, 0.0), (-30.0, 0.0, 0.5)]
    mesh = load_face_mesh()
    errors, noses = [], []
    print(f"\n{'yaw':>5s} {'pitch':>5s} {'jaw':>4s} {'score':>5s} {'pres':>5s} {'mean/IOD':>8s} {'no-jaw':>7s}")
    for yaw, pitch, opening in poses:
        w = np.zeros(len(model.expression_names), np.float32)
        w[jaw] = opening
        rot = Rotation.from_euler("yx", [yaw, pitch], degrees=True).as_matrix()
        verts = (model.evaluate(w) @ rot.T).astype(np.float32)
        out = render_mesh(torch.as_tensor(verts)[None], faces, torch.as_tensor(extrinsics, dtype=torch.float32)[None],
                          torch.tensor([[520.0, 520.0, 127.5, 127.5]]), 256, 256, albedo=torch.as_tensor(albedo)[None],
                          sh=torch.as_tensor(sh)[None], background=torch.as_tensor(DEFAULT_LIGHT["background"]),
                          supersample=2, adjacency=adjacency)
        img = srgb_encode(out.image.clamp(0, 1))
        det = detect_faces(img)
        if not det.found[0]:
            print(f"{yaw:5.0f} {pitch:5.0f} {opening:4.1f}  no face")
            continue
        with torch.no_grad():
            points, presence = face_landmarks(img, det.boxes, mesh)
        p68 = mediapipe_to_68(points[0]).numpy()
        truth = project_points(verts[model.landmarks].astype(np.float64), extrinsics, [520.0, 520.0, 127.5, 127.5])
        iod = inter_ocular_distance(truth)
        err = np.linalg.norm(p68 - truth, axis=1) / iod
        errors.append(err)
        noses.append((p68[30] - truth[30]) / iod)
        print(f"{yaw:5.0f} {pitch:5.0f} {opening:4.1f} {det.scores[0]:5.2f} {presence.item():5.2f} "
              f"{err.mean():8.3f} {err[17:].mean():7.3f}")
    errors, noses = np.array(errors), np.array(noses)
    print(f"mean over poses: {errors.mean():.3f} IOD (jaw 0-16: {errors[:, :17].mean():.3f}, others: "
          f"{errors[:, 17:].mean():.3f}); nose tip offset (network - model) {noses.mean(0).round(4).tolist()} "
          f"IOD (x right, y down), |offset| {np.linalg.norm(noses, axis=1).mean():.3f}")


if __name__ == "__main__":
    main()
