"""Face detection cost per frame at 1080p (whole frame vs image pyramid) and the hard cases.

Run: nice python bench/detect_faces.py [--repeat 3] [--threads 2] [--batch 1] [--no-cases]

Timings (best of `--repeat` runs after one warm-up, ms per frame: the least disturbed by other
work on a shared machine) on a 1920 x 1080 frame
holding the astronaut with an eye distance of 25 px:
  whole frame          `landmarks.DetectFaces` before the pyramid (`min_face_px=0`: the frame
                       letterboxed to 128 x 128; misses this face)
  pyramid min_face N   the whole frame plus the finer levels for faces of box side >= N px
                       (`min_face_px`, default 40: an eye distance of about 19 px)
  mesh, roll passes K  crop + face mesh with the crop turned by the detector's roll and then
                       K more passes by the points' own eye line (`FaceLandmarks.roll_passes`)
Then, unless `--no-cases`, every case of `tests/nodes/landmarks/cases.py` at 4 placements:
detection rate (chosen face within one eye distance of the truth) and the mean 68-point error
in % of the eye distance (eye centres), on the astronaut and the camera man (grey).
CUDA rows appear when a GPU is present.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "nodes" / "landmarks"))
from _timing import best_ms  # noqa: E402  (bench/ is on the path: the script runs from it)


SHIFTS = [(0.0, 0.0), (0.013, 0.007), (-0.011, 0.017), (0.021, -0.013)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=1, help="frames per detector call")
    parser.add_argument("--no-cases", action="store_true", help="timings only")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    from cases import CASES, error_percent, make_case

    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68
    from nodes.landmarks.network import (detect_faces, load_face_detector, load_face_mesh, pyramid_scales,
                                         upright_face_landmarks)

    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    print(f"torch {torch.__version__}, {args.threads} threads, devices: {devices}")
    case = make_case("astronaut", **CASES["eye 25 px in 1080p"])
    rows = []
    for device in devices:
        frames = torch.from_numpy(np.repeat(case.image[None], args.batch, 0)).to(device)
        detector, mesh = load_face_detector(device), load_face_mesh(device)
        for min_face in (0.0, 80.0, 40.0, 30.0):
            label = "whole frame" if min_face == 0 else f"pyramid min_face {min_face:.0f}"
            det = detect_faces(frames, detector, min_face_px=min_face)
            ms = best_ms(lambda: detect_faces(frames, detector, min_face_px=min_face), args.repeat) / args.batch
            levels = len(pyramid_scales(1080, 1920, min_face))
            rows.append((label, device, ms, f"{levels} finer levels, found: {bool(det.found[0])}"))
        det = detect_faces(frames, detector, min_face_px=40.0)
        for passes in (0, 3):
            with torch.no_grad():
                ms = best_ms(lambda: upright_face_landmarks(frames, det.boxes, mesh, det.rolls, passes),
                               args.repeat) / args.batch
            rows.append((f"mesh, roll passes {passes}", device, ms, ""))
    print(f"\n| what | device | ms/frame | note |\n|---|---|---|---|")
    for name, device, ms, note in rows:
        print(f"| {name} | {device} | {ms:.0f} | {note} |")
    if args.no_cases:
        return
    mesh = load_face_mesh()
    print("\n| photo | case | found | error % eye distance (per placement) |\n|---|---|---|---|")
    for photo in ("astronaut", "camera"):
        for name, params in CASES.items():
            found, errors = 0, []
            for dx, dy in SHIFTS:
                kw = dict(params)
                at = kw.pop("at", (0.5, 0.5))
                c = make_case(photo, **kw, at=(at[0] + dx, at[1] + dy))
                img = torch.from_numpy(c.image)[None]
                det = detect_faces(img, min_face_px=40.0)
                centre = (det.face_boxes[0, :2] + det.face_boxes[0, 2:]) / 2
                if not det.found[0] or np.linalg.norm(centre - (c.face_box[:2] + c.face_box[2:]) / 2) > c.eye:
                    continue
                found += 1
                with torch.no_grad():
                    points, _, _ = upright_face_landmarks(img, det.boxes, mesh, det.rolls, 3)
                errors.append(error_percent(points[0].numpy()[MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye))
            text = " ".join(f"{e:.1f}" for e in errors) or "-"
            print(f"| {photo} | {name} | {found}/{len(SHIFTS)} | {text} |", flush=True)


if __name__ == "__main__":
    main()
