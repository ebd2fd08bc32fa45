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

__all__ = ["PHOTOS", "Case", "VideoCase", "photo", "reference", "make_case", "video_path", "make_video", "CASES", "eye_distance",
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


def error_percent(points68: np.ndarray, reference68: np.ndarray, eye: float) -> float:
    """Mean distance of 68 points to the reference, in % of the eye distance."""
    return float(np.linalg.norm(np.asarray(points68) - np.asarray(reference68), axis=-1).mean() / eye * 100)


def _warp(image: np.ndarray, matrix: np.ndarray, size: tuple[int, int], fill: float | np.ndarray,
          mask: np.ndarray | None = None) -> np.ndarray:
    """Canvas (H, W, 3) with canvas[q] = image[M^-1 q] (bilinear; `matrix` (2, 3) maps image
    pixel centres to canvas pixel centres) over `fill` (a grey level or an (H, W, 3) canvas)
    outside the image or where `mask` (H, W) is 0; the image is area-averaged first when shrunk."""
    scale = float(np.sqrt(abs(np.linalg.det(matrix[:, :2]))))
    alpha = np.ones(image.shape[:2]) if mask is None else mask
    src = torch.from_numpy(np.concatenate([image * alpha[..., None], alpha[..., None]], -1)).permute(2, 0, 1)[None].double()
    pre = np.eye(3)
    if scale < 0.9:  # shrink with an antialiased resize, then warp at about 1:1
        h, w = max(int(round(image.shape[0] * scale)), 1), max(int(round(image.shape[1] * scale)), 1)
        src = F.interpolate(src, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
        sx, sy = w / image.shape[1], h / image.shape[0]
        pre = np.array([[sx, 0, 0.5 * sx - 0.5], [0, sy, 0.5 * sy - 0.5], [0, 0, 1]])  # image -> small
    full = np.vstack([matrix, [0, 0, 1]]) @ np.linalg.inv(pre)  # small -> canvas
    inv = np.linalg.inv(full)
    height, width = size
    ys, xs = np.meshgrid(np.arange(height, dtype=np.float64), np.arange(width, dtype=np.float64), indexing="ij")
    u = inv[0, 0] * xs + inv[0, 1] * ys + inv[0, 2]
    v = inv[1, 0] * xs + inv[1, 1] * ys + inv[1, 2]
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
    return Case(out, _apply(m, points), _box_of(m, box), eye0 * scale, others)


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
