"""Face detection cost per frame at 1080p (whole frame vs image pyramid) and the hard cases.

Run: nice python bench/detect_faces.py [--repeat 3] [--threads 2] [--batch 1] [--no-cases] [--no-video]
     [--no-spoiled] [--no-check] [--only-check] [--photos astronaut camera grace_hopper] [--faceless]

Timings (best of `--repeat` runs after one warm-up, ms per frame: the least disturbed by other
work on a shared machine) on a 1920 x 1080 frame
holding the astronaut with an eye distance of 25 px:
  whole frame          `landmarks.DetectFaces` before the pyramid (`min_face_px=0`: the frame
                       letterboxed to 128 x 128; misses this face)
  pyramid min_face N   the whole frame plus the finer levels for faces of box side >= N px
                       (`min_face_px`, default 40: an eye distance of about 19 px)
  full range, whole    BlazeFace full range on the frame letterboxed to 192 x 192
  frame                (`detect_full_range`: TrackFaces' full-range look); "found" = a box
                       centred within one eye distance of the face's, but on this 55 px face
                       its box is about 100 px: it finds boxes from about 100 px in 1080p
  mesh, roll passes K  crop + face mesh with the crop turned by the detector's roll and then
                       K more passes by the points' own eye line (`FaceLandmarks.roll_passes`)
Then, unless `--no-cases`, every case of `tests/nodes/landmarks/cases.py` at 4 placements:
detection rate (chosen face within one eye distance of the truth) and the mean 68-point error
in % of the eye distance (eye centres), on the astronaut and the camera man (grey).
CUDA rows appear when a GPU is present.

Then, unless `--no-video`, two 1920 x 1080 videos of the astronaut (`cases.make_video`: moved,
zoomed and rolled at once, the reference points moved with the image), "slow" (40 frames: eye
distance 45-55 px, roll +-10 deg, 190 px across, a 22 px bob) and "fast" (30 frames: 45-70 px,
+-20 deg, 580 px across, a 54 px bob), each read two ways:
  track               `landmarks.TrackFaces` (`face_tracker.track_faces`): the detector on the
                      first frame, then each crop from the previous frames' points
  detect every frame  `landmarks.DetectFaces` + `FaceLandmarks` (pyramid min_face 40, roll passes 3)
with ms per frame (best of `--repeat` runs of the whole video, after one warm-up; and the CPU time
of one run on one thread, which other work on a shared machine moves little), the frames
where the detector ran, extra face-mesh reads, failed frames (presence below 0.5), the mean and
the largest 68-point error and the jitter: the mean frame-to-frame change of the 68 points'
error (the truth moves smoothly, so this is what shakes on screen), both in % of the eye
distance; failed frames are left out of both.

Then, unless `--no-spoiled`, `landmarks.TrackFaces` on spoiled frames (`cases.degrade`: 3 stops
dark, blurred, JPEG quality 6, noisy, grey, 16-bit) of three cases at the 4 placements: per
case the 68-point error in % of the eye distance, or F and the failure reason's code
(`nodes.landmarks.tracking.FAILURE_REASONS`).

Then, unless `--no-check` (`--only-check`: this table alone), the issue-26 acceptance check as one
count: `landmarks.TrackFaces` (with its defaults, as `landmarks.json` runs it) on every case of
`cases.CASES` (rolled, shrunk into 1080p / 4K / 817 x 1024 frames, dark, a second smaller copy,
combined) crossed with every spoiling of `cases.degrade` and none, on each photo, one placement
each (the placement and the noise seed cycle through `SHIFTS` by case). A frame counts as within
10% when it is not failed and its 68-point error is under 10% of the eye distance; a failed frame
counts against the rate; "confident wrong" is a frame not flagged failed whose error is over 50%
of the eye distance (a wrong face or a scatter). Printed per case, per spoiling and in all: the
frames within 10%, the median error (failed frames as infinite), failed frames and confident wrong
ones (first, per case, each spoiling's error or F and the failure reason's code,
`nodes.landmarks.tracking.FAILURE_REASONS`). The target (issue 26): at least 90% within 10%, median under 6%, no confident wrong face.
The photos (`--photos`, default all of `cases.PHOTOS`): skimage's astronaut and camera man and
matplotlib's grace_hopper (a frontal portrait). A photo with a hand annotation
(`cases.HAND_ANNOTATIONS`) is scored against it: the camera man, a near profile with a 23 px eye
distance, by 8 visible points a human read (eye corners, nose tip and base, mouth corner, lips,
chin; mean distance over those points, in % of the reference's eye distance). Every other photo's
reference is the detector and face mesh's read of the clean upright photo (`cases.reference`),
not a human annotation (on the frontal photos that read is within a few % of the face). The
headline rows (per case, spoiling, photo, all) use these scores; the last rows repeat the old
scoring for comparison, with the network's read as every photo's reference: on the camera man
that read sits 19% of the eye distance from his hand annotation, so nothing there can score
within 10% of it except by repeating its framing.

With `--talking-head` (alone): `landmarks.TrackFaces` on `cases.make_talking_head` (60 frames,
480 x 640: head turns, nod, roll, zoom, a quick dart with motion blur, dimming light, a dark hand
over the face in frames 30-35, grace_hopper beside her): failed frames, by the hand's coverage,
and the error of the frames read.

Then, with `--faceless`, `landmarks.TrackFaces` on `FACELESS` (18 skimage photos without a face),
each plain, dark, blurred and noisy: the frames where a face was read must stay 0.
"""

from __future__ import annotations

import argparse
import sys
import time
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
    parser.add_argument("--no-cases", action="store_true", help="no hard cases")
    parser.add_argument("--no-video", action="store_true", help="no video tracking")
    parser.add_argument("--no-spoiled", action="store_true", help="no spoiled frames")
    parser.add_argument("--no-check", action="store_true", help="no acceptance check (cases x spoilings)")
    parser.add_argument("--only-check", action="store_true", help="only the acceptance check")
    parser.add_argument("--photos", nargs="+", default=None, help="photos of the acceptance check (cases.PHOTOS)")
    parser.add_argument("--faceless", action="store_true", help="also TrackFaces on face-free photos")
    parser.add_argument("--talking-head", action="store_true", help="only TrackFaces on the talking-head video")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    if args.talking_head:
        talking_head_rows()
        return
    if args.only_check:
        check_rows(args.photos)
        if args.faceless:
            faceless_rows()
        return

    from cases import CASES, error_percent, make_case

    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68
    from nodes.landmarks.network import (detect_faces, detect_full_range, load_face_detector, load_face_mesh,
                                         load_full_range_detector, pyramid_scales, upright_face_landmarks)

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
        wide = load_full_range_detector(device)
        faces = detect_full_range(frames, wide)
        ms = best_ms(lambda: detect_full_range(frames, wide), args.repeat) / args.batch
        hit = [bool(np.all(np.abs((b[:2] + b[2:]) / 2 - (case.face_box[:2] + case.face_box[2:]) / 2) < case.eye))
               for b in faces[0].boxes]
        rows.append(("full range, whole frame", device, ms, f"found: {any(hit)}"))
        det = detect_faces(frames, detector, min_face_px=40.0)
        for passes in (0, 3):
            with torch.no_grad():
                ms = best_ms(lambda: upright_face_landmarks(frames, det.boxes, mesh, det.rolls, passes),
                               args.repeat) / args.batch
            rows.append((f"mesh, roll passes {passes}", device, ms, ""))
    print(f"\n| what | device | ms/frame | note |\n|---|---|---|---|")
    for name, device, ms, note in rows:
        print(f"| {name} | {device} | {ms:.0f} | {note} |")
    if not args.no_video:
        video_rows(args.repeat)
    if not args.no_spoiled:
        spoiled_rows()
    if not args.no_check:
        check_rows(args.photos)
    if args.faceless:
        faceless_rows()
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


VIDEOS = {"slow": dict(count=40, eye_px=(45.0, 55.0), roll_deg=10.0, sweep=(0.4, 0.5), bob=0.02),
          "fast": dict(count=30, eye_px=(45.0, 70.0), roll_deg=20.0, sweep=(0.3, 0.6), bob=0.05)}
"""`cases.make_video` arguments of the two bench videos."""


def video_stats(points: np.ndarray, truth: np.ndarray, eye: np.ndarray, ok: np.ndarray) -> tuple[float, float, float]:
    """Mean and largest 68-point error and the jitter (mean frame-to-frame change of the error),
    % of the eye distance, over the frames `ok` (F,) bool (jitter: pairs of consecutive ok frames)."""
    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68

    error = points[:, MEDIAPIPE_TO_68] - truth[:, MEDIAPIPE_TO_68]
    per_frame = np.linalg.norm(error, axis=-1).mean(-1) / eye * 100
    pairs = ok[1:] & ok[:-1]
    jitter = np.linalg.norm(np.diff(error, axis=0), axis=-1).mean(-1)[pairs] / eye[1:][pairs] * 100
    return float(per_frame[ok].mean()), float(per_frame[ok].max()), float(jitter.mean())


def video_rows(repeat: int) -> None:
    """Print tracking against detecting every frame on the bench videos (see the module docstring)."""
    from cases import make_video

    from nodes.landmarks.face_tracker import track_faces
    from nodes.landmarks.network import detect_faces, load_face_detector, load_face_mesh, upright_face_landmarks

    detector, mesh = load_face_detector(), load_face_mesh()

    def every_frame(frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points, presence = np.full((len(frames), 468, 2), np.nan), np.zeros(len(frames))
        for f in range(len(frames)):
            image = torch.from_numpy(frames[f:f + 1])
            det = detect_faces(image, detector, min_face_px=40.0)
            if det.found[0]:
                with torch.no_grad():
                    pts, pres, _ = upright_face_landmarks(image, det.boxes, mesh, det.rolls, 3)
                points[f], presence[f] = pts[0].double().numpy(), float(pres[0])
        return points, presence

    def cpu_ms(fn) -> float:  # CPU time of one run on one thread: little moved by other work on the machine
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        start = time.thread_time()
        fn()
        torch.set_num_threads(threads)
        return (time.thread_time() - start) * 1e3

    def frame_cpu_ms(iris: bool) -> tuple[float, float]:  # one thread: median per followed frame, per detection
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        stamps = [time.thread_time()]
        out = track_faces(frames, with_iris=iris, progress=lambda *_: stamps.append(time.thread_time()))
        torch.set_num_threads(threads)
        costs = np.diff(stamps) * 1e3
        return float(np.median(costs[~out.detected])), float(costs[out.detected].mean())

    print("\n| video | how | ms/frame | 1-thread CPU ms/frame (followed frame, median; detection frame) | "
          "detector runs | extra mesh reads | failed | error % (mean, max) | jitter % |\n"
          "|---|---|---|---|---|---|---|---|---|")
    for name, kw in VIDEOS.items():
        video = make_video("astronaut", **kw)
        frames = video.frames
        for how in ("track", "track, no iris", "detect every frame"):
            if how.startswith("track"):
                iris = how == "track"
                ms = best_ms(lambda: track_faces(frames, with_iris=iris), repeat) / len(frames)
                cpu = cpu_ms(lambda: track_faces(frames, with_iris=iris)) / len(frames)
                cpu = f"{cpu:.1f} ({'; '.join(f'{v:.1f}' for v in frame_cpu_ms(iris))})"
                out = track_faces(frames, with_iris=iris)
                points, ok = out.points, ~out.failed
                note = (int(out.detected.sum()), int(out.rereads.sum()))
            else:
                ms = best_ms(lambda: every_frame(frames), max(1, repeat - 1)) / len(frames)
                cpu = f"{cpu_ms(lambda: every_frame(frames)) / len(frames):.1f}"
                points, presence = every_frame(frames)
                ok = presence >= 0.5
                note = (len(frames), "-")
            mean, worst, jitter = video_stats(points, video.points, video.eye, ok)
            print(f"| {name} ({len(frames)} frames) | {how} | {ms:.1f} | {cpu} | {note[0]} | {note[1]} | {int((~ok).sum())} | "
                  f"{mean:.2f}, {worst:.1f} | {jitter:.2f} |", flush=True)


def spoiled_rows() -> None:
    """Print `landmarks.TrackFaces` on spoiled frames (see the module docstring)."""
    from cases import CASES, degrade, error_percent, make_case

    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68
    from nodes.landmarks.face_tracker import track_faces

    print("\n| photo | case | spoiled | error % eye distance, or F + reason (per placement) |\n|---|---|---|---|")
    for photo in ("astronaut", "camera"):
        for base in ("upright", "roll 90", "eye 25 px in 1080p"):
            for kind in ("dark", "blur", "jpeg 6", "noise", "grey", "16-bit"):
                cells = []
                for i, (dx, dy) in enumerate(SHIFTS):
                    kw = dict(CASES[base])
                    at = kw.pop("at", (0.5, 0.5))
                    c = make_case(photo, **kw, at=(at[0] + dx, at[1] + dy))
                    out = track_faces(degrade(c.image, kind, seed=i)[None], with_iris=False)
                    cells.append(f"F{out.reasons[0]}" if out.failed[0] else
                                 f"{error_percent(out.points[0][MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye):.1f}")
                print(f"| {photo} | {base} | {kind} | {' '.join(cells)} |", flush=True)


SPOILINGS = ("none", "dark", "blur", "jpeg 6", "noise", "grey", "16-bit")
"""The spoilings of the acceptance check: none and every kind of `cases.degrade`."""


def check_rows(photos: list[str] | None = None) -> None:
    """Print the issue-26 acceptance check on `photos` (None: `cases.PHOTOS`; see the module docstring)."""
    from cases import CASES, HAND_ANNOTATIONS, PHOTOS, degrade, error_percent, hand_error_percent, make_case

    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68
    from nodes.landmarks.face_tracker import track_faces

    photos = list(PHOTOS if photos is None else photos)
    records = []  # (photo, case, spoiling, error % or inf where failed, failure reason or -1, hand error %)
    for photo in photos:
        for c_index, (base, params) in enumerate(CASES.items()):
            kw = dict(params)
            at = kw.pop("at", (0.5, 0.5))
            dx, dy = SHIFTS[c_index % len(SHIFTS)]
            c = make_case(photo, **kw, at=(at[0] + dx, at[1] + dy))
            for s_index, kind in enumerate(SPOILINGS):
                image = c.image if kind == "none" else degrade(c.image, kind, seed=c_index + s_index)
                out = track_faces(image[None], with_iris=False)
                error = (np.inf if out.failed[0] else
                         error_percent(out.points[0][MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye))
                hand = np.inf if out.failed[0] else hand_error_percent(photo, out.points[0][MEDIAPIPE_TO_68], c)
                records.append((photo, base, kind, error, int(out.reasons[0]) if out.failed[0] else -1, hand))
            print(f"  {photo} / {base} ({', '.join(SPOILINGS)}): " + " ".join(
                f"F{r[4]}" if np.isinf(r[3]) else f"{r[3]:.1f}" for r in records[-len(SPOILINGS):])
                + ("" if photo not in HAND_ANNOTATIONS else "; against the hand annotation: " + " ".join(
                    f"F{r[4]}" if np.isinf(r[5]) else f"{r[5]:.1f}" for r in records[-len(SPOILINGS):])), flush=True)

    def row(label: str, chosen: list, column: int = 3) -> str:
        errors = np.array([r[column] for r in chosen])
        within = int((errors < 10).sum())
        failed = int(np.isinf(errors).sum())
        wrong = int(((errors > 50) & np.isfinite(errors)).sum())
        median = np.median(errors)
        return (f"| {label} | {len(errors)} | {within} ({100 * within / len(errors):.0f}%) | "
                f"{'F' if np.isinf(median) else f'{median:.1f}'} | {failed} | {wrong} |")

    # the headline score: against the human's points where a photo has them (the hand annotation),
    # else against the network's read of the clean upright photo
    scored = [r + ((r[5] if r[0] in HAND_ANNOTATIONS else r[3]),) for r in records]
    header = "| {} | frames | within 10% | median % | failed | confident wrong (> 50%) |\n|---|---|---|---|---|---|"
    print("\nScored against the hand annotation where the photo has one (" + ", ".join(
        f"{p}: {len(HAND_ANNOTATIONS[p])} points" for p in photos if p in HAND_ANNOTATIONS)
        + "), else against the network's read of the clean upright photo.")
    print("\n" + header.format("case (every photo and spoiling)"))
    for base in CASES:
        print(row(base, [r for r in scored if r[1] == base], 6))
    print("\n" + header.format("spoiling (every photo and case)"))
    for kind in SPOILINGS:
        print(row(kind, [r for r in scored if r[2] == kind], 6))
    print("\n" + header.format("photo"))
    for photo in photos:
        print(row(photo + (" (hand annotation)" if photo in HAND_ANNOTATIONS else ""),
                  [r for r in scored if r[0] == photo], 6))
    print(row("all", scored, 6))
    if set(photos) & set(HAND_ANNOTATIONS):
        if set(photos) - set(HAND_ANNOTATIONS):  # (a table of only hand-annotated photos has no such row)
            print(row("all but the hand-annotated photos", [r for r in scored if r[0] not in HAND_ANNOTATIONS], 6))
        print("\n" + header.format("for comparison: the network's read of the clean photo as every reference"))
        for photo in photos:
            if photo in HAND_ANNOTATIONS:
                print(row(f"{photo} against the network's read", [r for r in scored if r[0] == photo], 3))
        print(row("all", scored, 3))


def talking_head_rows() -> None:
    """Print `landmarks.TrackFaces` on `cases.make_talking_head` (60 frames, 480 x 640; see the
    module docstring): failed frames, by how much of the face the hand covers, and the error."""
    from cases import make_talking_head

    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68
    from nodes.landmarks.face_tracker import track_faces

    video = make_talking_head("astronaut", count=60)
    out = track_faces(video.frames, with_iris=False)
    error = np.linalg.norm(out.points[:, MEDIAPIPE_TO_68] - video.points[:, MEDIAPIPE_TO_68], axis=-1).mean(-1) / video.eye * 100
    ok, hidden = ~out.failed, video.occluded >= 0.5
    after = int(np.argmax(ok & (np.arange(len(ok)) > np.nonzero(hidden)[0].max())))
    print(f"\ntalking head ({len(ok)} frames, 480 x 640, eye distance {video.eye.min():.0f}-{video.eye.max():.0f} px): "
          f"failed {int(out.failed.sum())} ({100 * out.failed.mean():.0f}%; frames {np.nonzero(out.failed)[0].tolist()}, "
          f"reasons {out.reasons[out.failed].tolist()}), of them where the hand covers under half the face box "
          f"{int((out.failed & ~hidden).sum())}; hand coverage of the failed frames "
          f"{' '.join(f'{c:.2f}' for c in video.occluded[out.failed])}; error of the read frames: median "
          f"{np.median(error[ok]):.1f}%, largest {error[ok].max():.1f}%, over 10%: {int((error[ok] > 10).sum())}; "
          f"detector ran on frames {np.nonzero(out.detected)[0].tolist()}; first frame read after the hand: {after} "
          f"({error[after]:.1f}%)")


FACELESS = ("coffee", "brick", "rocket", "chelsea", "coins", "text", "grass", "gravel", "moon", "page", "horse",
            "hubble_deep_field", "immunohistochemistry", "retina", "logo", "clock", "cell", "colorwheel")
"""skimage photos without a face (`--faceless`)."""


def faceless_rows() -> None:
    """Print how many face-free frames `landmarks.TrackFaces` reads a face in (must be 0)."""
    from cases import degrade
    from skimage import data

    from nodes.landmarks.face_tracker import track_faces

    read, total = [], 0
    for name in FACELESS:
        img = np.asarray(getattr(data, name)())
        img = img.astype(np.float32) / (1.0 if img.dtype == bool else 255.0)
        img = np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3]
        for kind in ("none", "dark", "blur", "noise"):
            image = img if kind == "none" else degrade(np.ascontiguousarray(img), kind, seed=total)
            total += 1
            if not track_faces(np.ascontiguousarray(image)[None], with_iris=False).failed[0]:
                read.append(f"{name} / {kind}")
    print(f"\nface-free photos ({len(FACELESS)} x plain, dark, blur, noise): a face read in "
          f"{len(read)} of {total} frames{': ' + ', '.join(read) if read else ''}")


if __name__ == "__main__":
    main()
