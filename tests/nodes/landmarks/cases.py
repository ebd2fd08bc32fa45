"""Hard detection cases with known answers, made from real photos: skimage's astronaut and camera
and matplotlib's grace_hopper (a frontal US Navy portrait, public domain; `PHOTOS`).

The detector and face mesh run once on the upright photo; their points are the reference. A
case moves the photo into a canvas by an exact similarity transform (shrink, rotate about the
face, place), optionally pastes a second, smaller copy beside it and darkens the result; the
reference points go through the same transform, so the expected landmarks are known to the
accuracy of the network's own equivariance. Errors are in % of the eye distance (between the
eye centres, means of Multi-PIE points 36-41 and 42-47).

Used by `test_hard_cases.py` and `bench/detect_faces.py`.
"""

from __future__ import annotations

from functools import lru_cache
from typing import NamedTuple, Sequence

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["PHOTOS", "HAND_ANNOTATIONS", "hand_error_percent", "Case", "VideoCase", "photo", "reference", "make_case", "video_path", "make_video", "TalkingHead", "make_talking_head", "head_pose_matrix", "hand_mask", "CASES", "eye_distance",
           "error_percent"]


class Case(NamedTuple):
    """A test image and its known face: `image` (H, W, 3) float32 sRGB in [0, 1]; `points`
    (468, 2) the reference points in it, pixels; `face_box` (4,) the reference face box; `eye`
    the eye distance, pixels; `others` (K, 4) face boxes of the other copies."""

    image: np.ndarray
    points: np.ndarray
    face_box: np.ndarray
    eye: float
    others: np.ndarray
    hand: np.ndarray = np.zeros((0, 2))
    """(K, 2) the photo's hand annotation (`HAND_ANNOTATIONS`) moved with the image, pixels; empty
    where the photo has none."""


HAND_ANNOTATIONS = {
    "camera": {36: (226.5, 146.0), 39: (240.5, 148.5), 30: (254.3, 166.5), 33: (246.5, 171.0),
               48: (229.2, 180.1), 51: (245.4, 175.1), 57: (241.0, 184.5), 8: (235.5, 194.0)},
}
"""Photo -> {Multi-PIE 68-point index: (x, y) pixels in the upright photo}, read by hand.

The camera man faces right in a near profile (his left eye is hidden behind the camera), so only
the visible points are annotated: his right eye's outer (36) and inner (39) corners, the nose tip
(30, the most forward point of the nose) and the nose's base where it meets the upper lip (33),
the visible mouth corner (48), the upper lip's top (51) and the lower lip's bottom (57) on the
profile line, and the chin's lowest point (8). Read on 8x-18x bicubic enlargements of the photo
with a one-pixel grid (pixel centres at integers): the eye corners where the dark fissure ends
(about +-1.5 px: the corners are soft at 23 px eye distance), the nose and lips on the profile
edge (+-1 px), the chin where the face meets the dark collar (+-2 px: the collar hides its
edge). The face mesh's own read of the photo (`reference`) is 19% of the eye distance from these
points on average, TrackFaces' read 11%."""


PHOTOS = ("astronaut", "camera", "grace_hopper")
"""The photos of the cases: skimage's `astronaut` and `camera`, matplotlib's `grace_hopper.jpg`
(512 x 600, shipped in matplotlib's sample data: Grace Hopper facing the camera)."""


def photo(name: str) -> np.ndarray:
    """One of `PHOTOS` as (H, W, 3) float32 in [0, 1] (grey replicated)."""
    if name == "grace_hopper":
        from matplotlib.cbook import get_sample_data
        from PIL import Image

        with Image.open(get_sample_data("grace_hopper.jpg", asfileobj=False)) as file:
            return np.asarray(file.convert("RGB"), np.float32) / 255.0
    if name not in PHOTOS:
        raise ValueError(f"photo: expected one of {PHOTOS}, found {name!r}")
    from skimage import data

    img = getattr(data, name)().astype(np.float32) / 255.0
    return np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3]


@lru_cache(maxsize=4)
def reference(name: str) -> tuple[np.ndarray, np.ndarray]:
    """(468, 2) reference points and (4,) face box of the upright photo (the current detector
    on the whole frame and the face mesh on its upright crop)."""
    from nodes.landmarks.network import detect_faces, face_landmarks, load_face_mesh

    img = torch.from_numpy(photo(name))[None]
    det = detect_faces(img)
    if not det.found[0]:
        raise RuntimeError(f"no face in the upright {name}")
    with torch.no_grad():
        points, _ = face_landmarks(img, det.boxes, load_face_mesh())
    return points[0].double().numpy(), det.face_boxes[0]


def eye_distance(points468: np.ndarray) -> float:
    """Distance between the eye centres (Multi-PIE 36-41 and 42-47), pixels."""
    from nodes.landmarks.correspondence import MEDIAPIPE_TO_68

    p = np.asarray(points468, np.float64)[MEDIAPIPE_TO_68]
    return float(np.linalg.norm(p[36:42].mean(0) - p[42:48].mean(0)))


def hand_error_percent(name: str, points68: np.ndarray, case: Case) -> float:
    """Mean distance of the hand-annotated points of `points68` (68, 2) to `case.hand`, in % of
    the case's eye distance (the reference's: one eye of a profile is hidden); NaN without an
    annotation."""
    ids = list(HAND_ANNOTATIONS.get(name, {}))
    if not ids:
        return float("nan")
    return error_percent(np.asarray(points68)[ids], case.hand, case.eye)


def error_percent(points68: np.ndarray, reference68: np.ndarray, eye: float) -> float:
    """Mean distance of 68 points to the reference, in % of the eye distance."""
    return float(np.linalg.norm(np.asarray(points68) - np.asarray(reference68), axis=-1).mean() / eye * 100)


def _warp(image: np.ndarray, matrix: np.ndarray, size: tuple[int, int], fill: float | np.ndarray,
          mask: np.ndarray | None = None) -> np.ndarray:
    """Canvas (H, W, 3) with canvas[q] = image[M^-1 q] (bilinear; `matrix` (2, 3) affine or (3, 3)
    homography maps image pixel centres to canvas pixel centres) over `fill` (a grey level or an (H, W, 3) canvas)
    outside the image or where `mask` (H, W) is 0; the image is area-averaged first when shrunk."""
    scale = float(np.sqrt(abs(np.linalg.det(matrix[:2, :2]))))
    alpha = np.ones(image.shape[:2]) if mask is None else mask
    src = torch.from_numpy(np.concatenate([image * alpha[..., None], alpha[..., None]], -1)).permute(2, 0, 1)[None].double()
    pre = np.eye(3)
    if scale < 0.9:  # shrink with an antialiased resize, then warp at about 1:1
        h, w = max(int(round(image.shape[0] * scale)), 1), max(int(round(image.shape[1] * scale)), 1)
        src = F.interpolate(src, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
        sx, sy = w / image.shape[1], h / image.shape[0]
        pre = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])  # image -> small
    full = (matrix if matrix.shape == (3, 3) else np.vstack([matrix, [0, 0, 1]])) @ np.linalg.inv(pre)  # small -> canvas
    inv = np.linalg.inv(full)
    height, width = size
    ys, xs = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    w_ = inv[2, 0] * xs + inv[2, 1] * ys + inv[2, 2]
    u = (inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2]) / w_
    v = (inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]) / w_
    h, w = src.shape[2:]
    grid = torch.from_numpy(np.stack([(u + 0.5) / w * 2 - 1, (v + 0.5) / h * 2 - 1], -1))[None]
    out = F.grid_sample(src, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
    alpha = out[0, 3:].permute(1, 2, 0).numpy()
    background = fill if isinstance(fill, np.ndarray) else np.full(alpha.shape[:2] + (3,), fill)
    return (out[0, :3].permute(1, 2, 0).numpy() + (1 - alpha) * background).astype(np.float32)


def _similarity(scale: float, angle_deg: float, centre_src: np.ndarray, centre_dst: np.ndarray) -> np.ndarray:
    """(2, 3): scale and turn by `angle_deg` (clockwise on screen) about `centre_src`, moved to `centre_dst`."""
    a = np.deg2rad(angle_deg)
    r = scale * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return np.hstack([r, (centre_dst - r @ centre_src)[:, None]])


def _apply(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ matrix[:, :2].T + matrix[:, 2]


def _box_of(matrix: np.ndarray, box: np.ndarray) -> np.ndarray:
    corners = _apply(matrix, np.array([[box[0], box[1]], [box[2], box[1]], [box[0], box[3]], [box[2], box[3]]]))
    return np.concatenate([corners.min(0), corners.max(0)])


def make_case(name: str = "astronaut", *, angle_deg: float = 0.0, eye_px: float | None = None,
              canvas: tuple[int, int] | None = None, at: tuple[float, float] = (0.5, 0.5),
              second: float = 0.0, darken: float = 1.0, fill: float = 0.35) -> Case:
    """Build a case (see the module docstring).

    Args:
        name: one of `PHOTOS`.
        angle_deg: roll of the face, degrees, clockwise on screen.
        eye_px: eye distance in the canvas, pixels; None = the photo's own.
        canvas: (H, W); None = the photo's size.
        at: where the face centre goes, as fractions of the canvas (x, y).
        second: > 0: a second copy at this fraction of the first's size, to the right of it.
        darken: the sRGB values are multiplied by this.
        fill: grey level around the photo.
    """
    img = photo(name)
    points, box = reference(name)
    eye0 = eye_distance(points)
    scale = 1.0 if eye_px is None else eye_px / eye0
    size = canvas or img.shape[:2]
    face_centre = (box[:2] + box[2:]) / 2
    dst = np.array([at[0] * (size[1] - 1), at[1] * (size[0] - 1)])
    m = _similarity(scale, angle_deg, face_centre, dst)
    out = _warp(img, m, size, fill)
    others = np.zeros((0, 4))
    if second > 0:
        width = (box[2] - box[0]) * scale
        m2 = _similarity(scale * second, angle_deg, face_centre, dst + [(0.6 + 0.9 * second) * width, 0.1 * width])
        yy, xx = np.mgrid[:img.shape[0], :img.shape[1]]
        half = 0.9 * max(box[2] - box[0], box[3] - box[1])
        patch = ((abs(xx - face_centre[0]) < half) & (abs(yy - face_centre[1]) < half)).astype(np.float64)
        out = _warp(img, m2, size, out, patch)
        others = _box_of(m2, box)[None]
    out = np.clip(out * darken, 0, 1).astype(np.float32)
    hand = np.array(list(HAND_ANNOTATIONS.get(name, {}).values()), np.float64).reshape(-1, 2)
    return Case(out, _apply(m, points), _box_of(m, box), eye0 * scale, others, _apply(m, hand))


CASES = {
    "upright": dict(),
    "roll 30": dict(angle_deg=30, canvas=(768, 768)),
    "roll 90": dict(angle_deg=90, canvas=(768, 768)),
    "roll -60": dict(angle_deg=-60, canvas=(768, 768)),
    "eye 25 px in 1080p": dict(eye_px=25, canvas=(1080, 1920), at=(0.3, 0.6)),
    "eye 25 px in 4K": dict(eye_px=25, canvas=(2160, 3840), at=(0.7, 0.35)),
    "eye 20 px in 817 x 1024": dict(eye_px=20, canvas=(1024, 817), at=(0.6, 0.4)),
    "second smaller copy": dict(eye_px=40, canvas=(720, 1280), at=(0.35, 0.5), second=0.6),
    "dark (x0.25)": dict(darken=0.25),
    "eye 25 px, roll 90, dark, second copy": dict(eye_px=25, angle_deg=90, canvas=(1080, 1920), at=(0.4, 0.5),
                                                   second=0.7, darken=0.4),
}
"""Name -> `make_case` arguments (with `name` the photo)."""


class VideoCase(NamedTuple):
    """A video with known faces: `frames` (F, H, W, 3) float32 sRGB in [0, 1]; `points` (F, 468,
    2) the reference points of the followed face, pixels (NaN on blank frames); `eye` (F,) its
    eye distance, pixels; `others` (F, 4) the face box of the pasted second copy (NaN where none)."""

    frames: np.ndarray
    points: np.ndarray
    eye: np.ndarray
    others: np.ndarray


def video_path(count: int, *, eye_px: tuple[float, float] = (45.0, 70.0), roll_deg: float = 20.0,
               sweep: tuple[float, float] = (0.3, 0.6), bob: float = 0.05) -> list[dict]:
    """`make_case` arguments of a smooth move: the face crosses the frame left to right over `sweep`
    (fractions of the width) while it bobs up and down by `bob` (a fraction of the height, 1.5
    periods), zooms from the first eye distance to the second and back (sine squared) and rolls
    by up to +-`roll_deg` degrees (one sine period), so all of them change at once."""
    t = np.linspace(0.0, 1.0, count)
    return [dict(eye_px=float(eye_px[0] + (eye_px[1] - eye_px[0]) * np.sin(np.pi * s) ** 2),
                 angle_deg=float(roll_deg * np.sin(2 * np.pi * s)),
                 at=(float(sweep[0] + (sweep[1] - sweep[0]) * s), float(0.5 + bob * np.sin(3 * np.pi * s))))
            for s in t]


def make_video(name: str = "astronaut", count: int = 30, *, canvas: tuple[int, int] = (1080, 1920),
               blank: tuple[int, ...] = (), second: float | Sequence[float] = 0.0, **path) -> VideoCase:
    """A video of `count` frames along `video_path(count, **path)`; `blank` frames are plain grey
    (an occlusion); `second` > 0 pastes a copy of that relative size beside the face (as
    `make_case`), which then moves with it (one size, or one per frame)."""
    frames, points, eyes, others = [], [], [], []
    seconds = np.broadcast_to(np.asarray(second, np.float64), (count,))
    for f, kw in enumerate(video_path(count, **path)):
        if f in blank:
            frames.append(np.full(canvas + (3,), 0.35, np.float32))
            points.append(np.full((468, 2), np.nan))
            eyes.append(np.nan)
            others.append(np.full(4, np.nan))
            continue
        c = make_case(name, canvas=canvas, second=float(seconds[f]), **kw)
        frames.append(c.image)
        points.append(c.points)
        eyes.append(c.eye)
        others.append(c.others[0] if len(c.others) else np.full(4, np.nan))
    return VideoCase(np.stack(frames), np.stack(points), np.array(eyes), np.stack(others))


class TalkingHead(NamedTuple):
    """A talking-head video with known faces (`make_talking_head`): `frames` (F, H, W, 3) float32
    sRGB in [0, 1]; `points` (F, 468, 2) the speaker's reference points, pixels (at mid-exposure);
    `eye` (F,) their eye distance, pixels; `occluded` (F,) float: the fraction of the speaker's
    face box the hand covers; `passer` (F, 4) the face box of the smaller second person."""

    frames: np.ndarray
    points: np.ndarray
    eye: np.ndarray
    occluded: np.ndarray
    passer: np.ndarray


def head_pose_matrix(centre_src: np.ndarray, face_side: float, *, scale: float, roll_deg: float, yaw_deg: float,
                     pitch_deg: float, centre_dst: np.ndarray) -> np.ndarray:
    """(3, 3) homography of a small head turn: the photo's face taken as a plane through
    `centre_src` (pixels) turned by `yaw_deg` about the vertical and `pitch_deg` about the
    horizontal axis, seen in perspective from 4 face sides away (a phone at arm's length), then
    scaled, rolled (clockwise on screen) and moved to `centre_dst` (canvas pixels)."""
    yaw, pitch, roll = np.deg2rad([yaw_deg, pitch_deg, roll_deg])
    depth = 4.0 * face_side
    to_centre = np.array([[1.0, 0, -centre_src[0]], [0, 1, -centre_src[1]], [0, 0, 1]])
    turn = (np.array([[np.cos(yaw), 0, 0], [0, 1, 0], [np.sin(yaw) / depth, 0, 1]])
            @ np.array([[1, 0, 0], [0, np.cos(pitch), 0], [0, np.sin(pitch) / depth, 1]]))
    c, s = np.cos(roll), np.sin(roll)
    place = np.array([[scale * c, -scale * s, centre_dst[0]], [scale * s, scale * c, centre_dst[1]], [0, 0, 1]])
    return place @ turn @ to_centre


def _project(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    q = points @ matrix[:2, :2].T + matrix[:2, 2]
    return q / (points @ matrix[2, :2] + matrix[2, 2])[..., None]


def hand_mask(size: tuple[int, int], centre: np.ndarray, side: float) -> np.ndarray:
    """(H, W) in [0, 1]: a hand seen from its back, palm an ellipse of `side` wide centred at
    `centre` (pixels) with four fingers and a thumb, edges softened over 2 pixels."""
    height, width = size
    ys, xs = np.mgrid[:height, :width].astype(np.float64)
    inside = np.full((height, width), -np.inf)

    def ellipse(cx: float, cy: float, rx: float, ry: float, angle: float) -> None:
        nonlocal inside
        c, s = np.cos(angle), np.sin(angle)
        dx, dy = xs - cx, ys - cy
        a, b = (c * dx + s * dy) / rx, (-s * dx + c * dy) / ry
        inside = np.maximum(inside, (1.0 - np.sqrt(a * a + b * b)) * min(rx, ry))  # ~ pixels inside

    x, y = float(centre[0]), float(centre[1])
    ellipse(x, y, 0.5 * side, 0.55 * side, 0.0)
    for k, lean in enumerate((-0.25, -0.08, 0.08, 0.25)):
        fx = x + (k - 1.5) * 0.24 * side
        ellipse(fx + 0.5 * side * np.sin(lean), y - 0.9 * side, 0.1 * side, 0.45 * side, lean)
    ellipse(x + 0.6 * side, y - 0.1 * side, 0.12 * side, 0.35 * side, -0.9)
    return np.clip(inside / 2.0 + 0.5, 0.0, 1.0)


def make_talking_head(name: str = "astronaut", count: int = 60, *, canvas: tuple[int, int] = (480, 640),
                      eye_px: float = 40.0, passer: str | None = "grace_hopper", occlusion: tuple[int, int] = (30, 36),
                      shutter: float = 0.5, samples: int = 3) -> TalkingHead:
    """A talking-head video made from a real photo, with the truth moved with the image.

    The speaker (`name`) sways, nods (pitch +-8 deg) and turns the head (yaw +-18 deg; a plane
    turned in perspective, `head_pose_matrix`), rolls +-6 deg and zooms +-12%, with a quick
    shift of a quarter of the frame width over frames 0.2-0.3 of the video; the light dims to
    0.45 and comes back (linear light, as a 2.2 power law; with a side light sweeping across); each frame is the
    mean of `samples` renders over the `shutter` (fraction of a frame), so fast motion blurs; a
    dark hand (`hand_mask`) passes over the face during `occlusion` (first frame, end), covering
    it wholly in the middle frames; `passer`, a smaller second person (0.7 of the speaker's eye
    distance), stands at the side. The truth is the photo's reference points (`reference`) moved
    by the mid-exposure pose.
    """
    img, other = photo(name), (photo(passer) if passer else None)
    points, box = reference(name)
    eye0 = eye_distance(points)
    face_side = float(max(box[2:] - box[:2]))
    lo = np.maximum(np.floor((box[:2] + box[2:]) / 2 - 0.9 * face_side), 0).astype(int)  # the head and shoulders
    hi = np.minimum(np.ceil((box[:2] + box[2:]) / 2 + 0.9 * face_side), img.shape[1::-1]).astype(int)
    img = np.ascontiguousarray(img[lo[1]:hi[1], lo[0]:hi[0]])
    points, box = points - lo, box - np.tile(lo, 2)
    centre_src = (box[:2] + box[2:]) / 2
    height, width = canvas
    patch = None
    if other is not None:
        o_points, o_box = reference(passer)
        o_scale = 0.7 * eye_px / eye_distance(o_points)
        o_centre = (o_box[:2] + o_box[2:]) / 2
        o_half = 0.9 * float(max(o_box[2:] - o_box[:2]))
        oy, ox = np.mgrid[:other.shape[0], :other.shape[1]]
        o_patch = ((abs(ox - o_centre[0]) < o_half) & (abs(oy - o_centre[1]) < o_half)).astype(np.float64)
        o_dst = np.array([0.82 * (width - 1), 0.62 * (height - 1)])
        o_matrix = _similarity(o_scale, 0.0, o_centre, o_dst)
        backdrop = _warp(other, o_matrix, canvas, 0.35, o_patch)
        passer_box = _box_of(o_matrix, o_box)
    else:
        backdrop, passer_box = np.full(canvas + (3,), 0.35, np.float32), np.full(4, np.nan)

    def pose(t: float) -> np.ndarray:  # t in frames
        s = t / max(count - 1, 1)
        jump = 0.25 * np.clip((s - 0.2) / 0.1, 0.0, 1.0)  # the quick shift
        dst = np.array([(0.32 + 0.04 * np.sin(2 * np.pi * s * 1.3) + jump) * (width - 1),
                        (0.5 + 0.03 * np.sin(2 * np.pi * s * 2.1)) * (height - 1)])
        scale = eye_px / eye0 * (1.0 + 0.12 * np.sin(2 * np.pi * s * 0.9))
        return head_pose_matrix(centre_src, face_side, scale=scale, roll_deg=6.0 * np.sin(2 * np.pi * s * 1.7),
                                yaw_deg=18.0 * np.sin(2 * np.pi * s * 1.1), pitch_deg=8.0 * np.sin(2 * np.pi * s * 2.3 + 1.0),
                                centre_dst=dst)

    xs = np.arange(width, dtype=np.float64) / max(width - 1, 1)
    frames, truth, eyes, covered = [], [], [], []
    start, end = occlusion
    image_corners = np.array([[0.0, 0], [img.shape[1], 0], [0, img.shape[0]], [img.shape[1], img.shape[0]]]) - 0.5
    for f in range(count):
        times = f + shutter * ((np.arange(samples) + 0.5) / samples - 0.5)
        reach = np.concatenate([_project(pose(t), image_corners) for t in times])  # warp only where the photo lands
        x0, y0 = np.clip(np.floor(reach.min(0)).astype(int) - 1, 0, [width, height])
        x1, y1 = np.clip(np.ceil(reach.max(0)).astype(int) + 2, 0, [width, height])
        frame = backdrop.copy()
        if x1 > x0 and y1 > y0:
            shift = np.array([[1.0, 0, -x0], [0, 1, -y0], [0, 0, 1]])
            frame[y0:y1, x0:x1] = np.mean([_warp(img, shift @ pose(t), (y1 - y0, x1 - x0),
                                                 backdrop[y0:y1, x0:x1], patch) for t in times], 0)
        m = pose(float(f))
        pts = _project(m, points)
        corners = _project(m, np.array([[box[0], box[1]], [box[2], box[1]], [box[0], box[3]], [box[2], box[3]]]))
        face_box = np.concatenate([corners.min(0), corners.max(0)])
        s = f / max(count - 1, 1)
        gain = 1.0 - 0.55 * np.sin(np.pi * np.clip((s - 0.45) / 0.4, 0.0, 1.0)) ** 2
        side_light = 0.75 + 0.5 * np.clip(xs - s + 0.5, 0.0, 1.0)  # a light sweeping across
        light = (gain * side_light) ** (1 / 2.2)  # linear-light gain as an sRGB factor (a 2.2 power law)
        frame = frame * light.astype(np.float32)[None, :, None]
        coverage = 0.0
        if start <= f < end:
            u = (f - start + 0.5) / (end - start) - 0.5  # the hand enters from the left, stays, leaves to the right
            side = float(face_box[2] - face_box[0])
            centre = (face_box[:2] + face_box[2:]) / 2 + np.array([2.4 * np.sign(u) * max(abs(u) - 0.2, 0.0), 0.25]) * side
            hand = hand_mask(canvas, centre, 1.3 * side)
            frame = frame * (1 - hand[..., None]) + hand[..., None] * np.array([0.16, 0.11, 0.09])
            x0, y0, x1, y1 = np.clip(np.round(face_box).astype(int), 0, [width, height, width, height])
            coverage = float(hand[y0:y1, x0:x1].mean()) if x1 > x0 and y1 > y0 else 0.0
        frames.append(np.clip(frame, 0, 1).astype(np.float32))
        truth.append(pts)
        eyes.append(eye_distance(pts))
        covered.append(coverage)
    return TalkingHead(np.stack(frames), np.stack(truth), np.array(eyes), np.array(covered),
                       np.broadcast_to(passer_box, (count, 4)).copy())


def degrade(image: np.ndarray, kind: str, seed: int = 0) -> np.ndarray:
    """A frame spoiled as footage is: (H, W, 3) float32 sRGB in [0, 1] -> the same shape.

    kinds: "dark" (3 stops under: linear light / 8), "blur" (Gaussian, sigma 3 px), "jpeg 6"
    (JPEG at quality 6, Pillow), "noise" (Gaussian, sigma 0.1, seeded), "grey" (Rec. 709 luma),
    "16-bit" (quantized to 16 bits: the values a 16-bit file holds).
    """
    from nodegraph.types import linear_to_srgb, srgb_to_linear

    if kind == "dark":
        return linear_to_srgb(srgb_to_linear(image) / 8.0).astype(np.float32)
    if kind == "blur":
        from scipy.ndimage import gaussian_filter

        return gaussian_filter(image, (3.0, 3.0, 0.0)).astype(np.float32)
    if kind.startswith("jpeg"):
        import io

        from PIL import Image

        buffer = io.BytesIO()
        Image.fromarray((np.clip(image, 0, 1) * 255).round().astype(np.uint8)).save(
            buffer, "JPEG", quality=int(kind.split()[1]))
        return np.asarray(Image.open(buffer), np.float32) / 255.0
    if kind == "noise":
        rng = np.random.default_rng(seed)
        return np.clip(image + rng.normal(0, 0.1, image.shape), 0, 1).astype(np.float32)
    if kind == "grey":
        return np.repeat((image @ np.array([0.2126, 0.7152, 0.0722]))[..., None], 3, -1).astype(np.float32)
    if kind == "16-bit":
        return ((np.clip(image, 0, 1) * 65535).round() / 65535).astype(np.float32)
    raise ValueError(f"kind: expected dark, blur, jpeg N, noise, grey or 16-bit, found {kind!r}")
