"""Follow one face through a video by its own landmarks, detecting only when it is lost.

MediaPipe's Face Landmarker front end: after a detection, each frame's face-mesh crop comes
from the previous frames' 468 points (`nodes.landmarks.tracking.landmark_crop`: their extent in
the face's axes, times 1.5, turned by their eye line), moved on by the face's motion over the
last two frames (`predict_crop`, constant velocity: a crop that lags a moving face drifts off
it, and the face mesh reads a face 0.2 crop sides off-centre confidently wrong). So the crop
moves, zooms and rolls with the face for one face-mesh read per frame. When the crop of this
frame's points differs from the crop read by more than `reread` (`crop_movement`), the frame is
read again in the new crop (twice at most). The detector (BlazeFace over the image pyramid,
`nodes.landmarks.network.detect_all_faces`) runs only on a frame where nothing is followed (the
first frames, after a loss) or where the face mesh's presence in the crop drops below
`min_presence` (an occlusion, a cut, a face turned away).

Which face: the `face` choice (`nodes.landmarks.tracking.choose_face`) on the first frame that
finds one. While a followed face is lost, only a detection where it was last seen
(`refind_face`) continues it, for `refind_frames` frames; after that the choice is made afresh.
No confident wrong face: a detection is taken only when the face mesh confirms it (presence at
least `min_presence` after the roll passes of `upright_face_landmarks`) and reads it the same
again in the crop of its own points (`read_disagreement` at most `max_disagreement`), and a face
re-found where it was last seen keeps its size within `REFIND_MAX_ZOOM` (a face half behind a
hand is read squeezed into its visible half); otherwise the next detection in the order of the choice is tried, and the frame fails with a reason
(`nodes.landmarks.tracking.FAILURE_REASONS`) when none is left.

A confirmed detection's points are the mean of the face mesh's reads in several crop framings
around the confirming read (`FRAMINGS`): one read moves with its crop's framing, most on a near
profile.

Second looks (`LOOKS`): where nothing is confirmed, detection and confirmation run again on the
frame turned a quarter each way (`quarter_turns`; the short-range detector misses small faces
rolled 90 deg), then on the frame sharpened (`enhance`; `sharpen`, an unsharp mask of
`SHARPEN_SIGMA_PX` and `SHARPEN_AMOUNT`; a find there needs presence `SHARPENED_MIN_PRESENCE`), upright
and turned; a face found sharpened is followed
in sharpened frames until it is lost. On `bench/detect_faces.py --only-check` they read the
astronaut at a 25 px eye distance blurred by 3 px (1080p and 4K: sharpened), rolled 90 deg with
noise (turned) and at a 25 px eye distance rolled 90 deg, dark, beside a smaller copy (turned),
where the detector found nothing or the reads disagreed. After the short-range looks of the plain
frame and again after those of the sharpened one, BlazeFace full range runs on the whole frame
(`full_range`, `nodes.landmarks.network.detect_full_range`, scores from
`FULL_RANGE_LOOK_MIN_SCORE`): on the same check it read the astronaut darkened (x0.25) and
noised (5.7%; failed before), changed no other frame's error (two failures' reason went from no
face found to presence too low) and read no face on the 18 face-free photos. It is a look, not a
pyramid level: one call costs about three short-range whole-frame calls and it finds no face under
a box of about 100 px in 1080p. A contrast stretch, tried too, read wrong faces 2.7 to 4.6 eye distances away on dark and small blurred frames and is not used. No
face was read on 18 face-free skimage photos, plain, dark, blurred or noisy (0 of 72 frames).

Why the acceptance check's 30 failed frames fail (issue 26, measured at TrackFaces 7) and the
second looks tried there and not used. The face mesh's presence, not the detector, is what fails
first: read in the crop of the reference points themselves, the astronaut darkened (x0.25) and JPEG
6 gives presence 0.00 (the read itself 11% off), the 20 px astronaut blurred 0.00 (10%), the
combined case (25 px, roll 90, dark, a second copy) with JPEG 6 0.27 and with noise 0.20,
grace_hopper's combined case with JPEG 6 0.01. Denoising the frame (Gaussian 1 or 2 px, median 3 x
3), a contrast stretch of the crop (1st-99th luma percentile) and both leave that presence at most
0.20 on the astronaut's dark and grace_hopper's combined JPEG 6 frames; they raise the astronaut's
combined case with JPEG 6 to 0.83 (Gaussian 1 px; 0.18 at 2 px) and with noise to 0.91-0.99, but on
those two the detections' boxes, plain or denoised, at the detector's roll plus 0, 90, 180 or 270
deg, give reads 88-810% off, and a denoised full-range look read the dark background 7.6 eye
distances from both faces at presence 0.71 with its re-read agreeing (0.09): a confident wrong
face. The 20 px astronaut blurred reads at presence 0.75 sharpened in the reference's crop (7%
off), under the sharpened looks' 0.9. The camera man (25 failed: JPEG 6 in all 10 cases, blurred in
8, noisy in 6, the dark case darkened again) is a near profile at a 23 px eye distance: on his
upright and roll-30 blurred frames the detections' boxes are off his face and the reads in them
26-338% from his hand annotation; with the frame's crop contrast-stretched and sharpened the
full-range box reads at presence 0.95, 22% off. Agreement between framings shifted 0.1 of the crop
side and scaled 1.25 / 1.8 (the largest `read_disagreement` from their mean) does not separate
faces from texture: 0.15-0.35 for the reads within 20% on these frames, 0.17 and up on the
face-free frames' detections. TrackFaces on the frames denoised first (Gaussian 2 px) reads the
astronaut's noisy combined case 10.2% off (presence 0.66) and 2 of the camera man's 6 failed noisy
frames 13.6 and 17.2% off, the rest still failed: no frame gains a read within 10%
(`tests/nodes/landmarks/test_failed_frames.py`). So these frames stay failed with a reason
(`bench/detect_faces.py --only-check`).

Frames are (F, H, W, 3) float32 RGB in [0, 1], sRGB-encoded; pixels as in
`nodes.landmarks.network`. This module imports torch at the top: import it from node `run()`
methods only.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np
import torch

from .correspondence import MEDIAPIPE_TO_68
from .iris import iris_landmarks, load_iris_network
from .network import (PYRAMID_MIN_SCORE, detect_all_faces, detect_full_range, eye_roll, face_landmarks,
                      load_face_detector, load_face_mesh, load_full_range_detector, points_roll, square_box,
                      upright_face_landmarks)
from .tracking import FAILURE_REASONS, FaceChoice, choose_face, landmark_crop, refind_face

__all__ = ["FAILURE_REASONS", "TrackedFaces", "track_faces", "crop_movement", "predict_crop", "read_disagreement",
           "sharpen", "SHARPEN_SIGMA_PX", "SHARPEN_AMOUNT", "SHARPENED_MIN_PRESENCE", "LOOKS", "unturn_faces",
           "FULL_RANGE_LOOK_MIN_SCORE", "REFIND_MAX_ZOOM", "FRAMINGS",
           "framed_crops"]



class TrackedFaces(NamedTuple):
    """The followed face in each of F frames: `boxes` (F, 4) the square crop the points were read
    in (x0 y0 x1 y1, pixels, before its turn; NaN where failed), `rolls` (F,) that crop's turn,
    radians clockwise on screen (NaN where failed), `points` (F, 468, 2) face-mesh points, pixels
    (NaN where failed), `presence` (F,) the face mesh's presence in [0, 1] (0 where no face was
    read), `failed` (F,) bool; a frame failed only for its read (reason 2, presence under the bar,
    or 4, two reads disagree: a face the detector found that the face mesh cannot read, such as a
    profile past ~60 deg of yaw) keeps the box, roll, points and presence of its best read
    (`weak_reads`), `reasons` (F,) int64 index into `FAILURE_REASONS`, `detected` (F,)
    bool: the detector ran on the frame, `iris` (F, 2, 5, 2) iris points, pixels
    (`nodes.landmarks.iris.iris_landmarks`; NaN where failed), `rereads` (F,) int64: face-mesh
    reads after the first in a followed frame."""

    boxes: np.ndarray
    rolls: np.ndarray
    points: np.ndarray
    presence: np.ndarray
    failed: np.ndarray
    reasons: np.ndarray
    detected: np.ndarray
    iris: np.ndarray
    rereads: np.ndarray


SHARPEN_SIGMA_PX = 3.0
"""Width of the unsharp mask of the second detection pass, frame pixels (`sharpen`)."""
SHARPEN_AMOUNT = 6.0
"""Strength of that unsharp mask: the frame plus this times its difference from its blur. On the
frames of `bench/detect_faces.py --only-check`, (sigma, amount) = (3, 6) read grace_hopper at a 20
px eye distance blurred by 3 px at 8.2% (11.2% with (3, 3)) and at a 25 px eye distance rolled 90
deg, dark and blurred beside a smaller copy at 9.1% (17.3%); (3, 3) read 3 astronaut frames within
7% where (2, 1.5) read one. A stronger mask also raises the face mesh's presence on texture (the
dark rocket: 0.61 at amount 3, 0.67 at 6, read as a face) and on a wrong box (the astronaut's
combined case blurred: 293% off), hence `SHARPENED_MIN_PRESENCE`."""
SHARPENED_MIN_PRESENCE = 0.9
"""Least face-mesh presence that confirms a face found in the sharpened frame (both reads; the
plain frame's looks need `min_presence`). On the acceptance check's blurred frames the faces read
within 10% in the sharpened frame had presence 1.00; at amount 6 with the bar at 0.5, skimage's
rocket darkened 3 stops was read as a face (presence 0.67) and the astronaut's combined case
blurred 293% off. With the bar: 135 of 210 check frames within 10% with the network's read as every
reference (133 with TrackFaces 3; 171 with the camera man scored against his hand annotation), none
confidently wrong, no face on the 72 face-free frames (`bench/detect_faces.py --only-check --faceless`)."""


def sharpen(image: torch.Tensor, sigma_px: float = SHARPEN_SIGMA_PX, amount: float = SHARPEN_AMOUNT) -> torch.Tensor:
    """Unsharp mask: `image + amount (image - blur(image))`, clipped to [0, 1].

    Args:
        image: (B, H, W, 3) float RGB in [0, 1].
        sigma_px: the Gaussian blur's standard deviation, pixels (edges replicated, 4 sigma wide).
        amount: how much of the detail (image minus blur) is added.
    Returns:
        (B, H, W, 3), same dtype and device.
    """
    from ..geometry.image import gaussian_kernel, separable_filter

    kernel = gaussian_kernel(sigma_px, dtype=image.dtype, device=image.device, truncate=4.0)
    return (image + amount * (image - separable_filter(image, kernel))).clamp(0.0, 1.0)


LOOKS = ((False, 0, False), (False, 1, False), (False, 3, False), (False, 0, True),
         (True, 0, False), (True, 1, False), (True, 3, False), (True, 0, True))
"""The detection passes of a frame where no face is confirmed, in order: (sharpened, quarter turns
counter-clockwise, full range: BlazeFace full range on the whole frame, `detect_full_range`, in
place of the short-range pyramid). BlazeFace short range misses a face rolled 90 deg when it is
small (the astronaut at a 25 px eye distance in 1080p rolled 90 deg: nothing found upright, score
0.90 in the frame turned a quarter back). A face found in a turned frame is taken only when its
points' roll lies within 45 deg of the turn (each look covers its own quadrant of rolls)."""


def unturn_faces(faces, turn: int, size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boxes (N, 4), keypoints (N, 6, 2) and scores (N,) of `faces` found in a frame turned by
    `turn` quarter turns counter-clockwise (`torch.rot90` / `np.rot90`), in the unturned frame's
    pixels (`size`: its (H, W)).

    Example:
        >>> from nodes.landmarks.network import Faces
        >>> f = Faces(np.array([[1.0, 2.0, 3.0, 5.0]]), np.zeros((1, 6, 2)), np.array([0.9]))
        >>> unturn_faces(f, 1, (10, 20))[0][0].tolist()  # the turned frame is 20 x 10
        [14.0, 1.0, 17.0, 3.0]
    """
    height, width = size
    boxes, keypoints = np.asarray(faces.boxes, np.float64), np.asarray(faces.keypoints, np.float64)
    if turn % 4 == 0 or not len(boxes):
        return boxes.reshape(-1, 4), keypoints.reshape(-1, 6, 2), np.asarray(faces.scores).reshape(-1)

    def back(p: np.ndarray) -> np.ndarray:  # (..., 2) turned-frame pixels -> frame pixels
        x, y = p[..., 0], p[..., 1]
        if turn % 4 == 1:  # turned[i, j] = frame[j, W - 1 - i]
            return np.stack([width - 1 - y, x], -1)
        if turn % 4 == 3:  # turned[i, j] = frame[H - 1 - j, i]
            return np.stack([y, height - 1 - x], -1)
        return np.stack([width - 1 - x, height - 1 - y], -1)

    corners = back(boxes.reshape(-1, 2, 2))
    return (np.concatenate([corners.min(1), corners.max(1)], -1), back(keypoints),
            np.asarray(faces.scores).reshape(-1))


FULL_RANGE_LOOK_MIN_SCORE = 0.4
"""Least score of a full-range detection in the full-range look (below MediaPipe's 0.5: on the
acceptance check's frames the astronaut darkened and noised scored 0.41; a detection is taken
only when the face mesh confirms it, as every look's)."""

REFIND_MAX_ZOOM = 1.4
"""Most factor between the size of a re-found face (its points' crop) and its size when it was
last seen (`track_faces`' `refind_max_zoom`). On the talking-head video of
`cases.make_talking_head` (a hand passing over the face) the face half behind the hand was read
at presence 0.98 squeezed into its visible half, 51% of the eye distance off; the refind
detection's read there was 0.56 of the size last seen (flagged, reason 5), the next frame's
0.90 (taken: 1.7% off; 1.9% with `FRAMINGS`). A face does not change size by 1.4 in the frames a hand or a turn hides it."""

FRAMINGS = tuple((scale, along, across) for scale in (1.3, 1.5, 1.7)
                 for along, across in ((0.0, 0.0), (0.0, -0.05), (0.05, 0.0), (-0.05, 0.0), (0.0, 0.05)))
"""Crop framings read where a detection is confirmed: (side over the points' extent, shift
along and across the face's axes in crop sides); the confirmed face's points are the mean of
these reads (the confirming read stands for (1.5, 0, 0)). The face mesh's read moves with the
crop's framing by several % of the eye distance (on the camera man's near profile by 10% between
these framings, on the frontal astronaut and grace_hopper by 2.7%); the mean of the 15 reads is
closer to the truth. `bench/detect_faces.py --only-check` (210 frames): the camera man against
his hand annotation (`cases.HAND_ANNOTATIONS`) 5 -> 36 of 70 frames within 10% of the eye distance,
median 13.0 -> 9.9% (upright 12.4 -> 9.8%, roll 90 13.6 -> 9.6%); against the network's single
read as reference (which favours one read) the astronaut and grace_hopper 135 of 140 within 10%
either way, median 2.6 -> 2.2% (blur 6.6 -> 7.0%, noise 4.3 -> 4.6%, JPEG 6 8.1 -> 7.8%); the same
frames fail, none confidently wrong. It runs on detection frames only (14 more face-mesh reads);
a followed frame reads once."""


def framed_crops(points: np.ndarray, roll: float, framings: Sequence[tuple[float, float, float]],
                 crop_scale: float = 1.5) -> list[np.ndarray | None]:
    """The crop boxes (4,) of `framings` around a face's points (468, 2) turned by `roll`
    (radians), before their turn; None for the framing the points were read in ((crop_scale, 0, 0))."""
    c, s = np.cos(roll), np.sin(roll)
    boxes: list[np.ndarray | None] = []
    for scale, along, across in framings:
        if (scale, along, across) == (crop_scale, 0.0, 0.0):
            boxes.append(None)
            continue
        box = landmark_crop(points, roll, scale)
        shift = np.array([c * along - s * across, s * along + c * across]) * (box[2] - box[0])
        boxes.append(box + np.concatenate([shift, shift]))
    return boxes


ROLL_TRIES = (0.0, np.pi / 4, -np.pi / 4)
"""Turns added to the detector's roll, tried in order until the face mesh finds the face: its eye
keypoints read a 90 deg roll as about 40 deg, too far for a blurred or compressed face."""


def read_disagreement(first: np.ndarray, second: np.ndarray) -> float:
    """Mean distance between two reads of a face's 68 Multi-PIE points, over the second read's
    eye distance (`first`, `second`: (468, 2) face-mesh points, pixels)."""
    a, b = first[MEDIAPIPE_TO_68], second[MEDIAPIPE_TO_68]
    eye = np.linalg.norm(b[36:42].mean(0) - b[42:48].mean(0))
    return float(np.linalg.norm(a - b, axis=-1).mean() / max(eye, 1e-9))


def crop_movement(box: np.ndarray, roll: float, new_box: np.ndarray, new_roll: float) -> float:
    """How far a crop moved: the largest of the centre's shift in sides of `box`, |log| of the
    side ratio and the roll's change in radians (wrapped to [-pi, pi])."""
    side, new_side = box[2] - box[0], new_box[2] - new_box[0]
    shift = np.linalg.norm((new_box[:2] + new_box[2:]) / 2 - (box[:2] + box[2:]) / 2) / side
    turn = abs((new_roll - roll + np.pi) % (2 * np.pi) - np.pi)
    return float(max(shift, abs(np.log(new_side / side)), turn))


def predict_crop(before: tuple[np.ndarray, float], latest: tuple[np.ndarray, float],
                 velocity: float = 1.0) -> tuple[np.ndarray, float]:
    """The next frame's crop, moved on from `latest` by `velocity` times the step from `before`.

    Args:
        before, latest: (box (4,) square x0 y0 x1 y1 pixels, roll radians) of two consecutive frames.
        velocity: 0 = `latest` as is, 1 = constant velocity (centre, log side and roll).
    Returns:
        (box (4,), roll).

    Example:
        >>> box, roll = predict_crop((np.array([0, 0, 10, 10.]), 0.0), (np.array([2, 0, 12, 10.]), 0.1))
        >>> box.tolist(), round(roll, 3)
        ([4.0, 0.0, 14.0, 10.0], 0.2)
    """
    (b0, r0), (b1, r1) = before, latest
    c0, c1 = (b0[:2] + b0[2:]) / 2, (b1[:2] + b1[2:]) / 2
    s0, s1 = b0[2] - b0[0], b1[2] - b1[0]
    centre = c1 + velocity * (c1 - c0)
    half = s1 * (s1 / s0) ** velocity / 2
    turn = (r1 - r0 + np.pi) % (2 * np.pi) - np.pi
    return np.concatenate([centre - half, centre + half]), float(r1 + velocity * turn)


def track_faces(frames: np.ndarray, *, device: str = "cpu", face: FaceChoice = "largest", min_score: float = 0.5,
                iou: float = 0.3, min_face_px: float = 40.0, pyramid_min_score: float = PYRAMID_MIN_SCORE,
                box_scale: float = 1.5, crop_scale: float = 1.5, min_presence: float = 0.5,
                refind_frames: int = 30, reread: float = 0.05, max_rereads: int = 2,
                velocity: float = 1.0, max_candidates: int = 3,
                max_disagreement: float = 0.15, roll_passes: int = 3, with_iris: bool = True,
                enhance: bool = True, quarter_turns: bool = True, full_range: bool = True,
                sharpen_amount: float = SHARPEN_AMOUNT, sharpened_min_presence: float = SHARPENED_MIN_PRESENCE,
                refind_max_zoom: float = REFIND_MAX_ZOOM, framings: Sequence[tuple[float, float, float]] = FRAMINGS,
                weak_reads: bool = True, progress: Callable[[float, str], None] | None = None) -> TrackedFaces:
    """Follow the chosen face through `frames` (see the module docstring).

    Args:
        frames: (F, H, W, 3) float32 RGB in [0, 1], sRGB-encoded (numpy; each frame is read in place).
        device: torch device of the networks.
        face: which face (`choose_face`).
        min_score, iou, min_face_px, pyramid_min_score: the detector's (`detect_all_faces`).
        box_scale: crop side over the detector box's longer side (MediaPipe: 1.5).
        crop_scale: crop side over the landmarks' extent (MediaPipe: 1.5).
        min_presence: least face-mesh presence that keeps following (MediaPipe: 0.5).
        refind_frames: frames during which a lost face is looked for only where it was last seen.
        reread: crop movement (`crop_movement`) above which a frame is read again in the new crop.
        max_rereads: most re-reads per frame.
        velocity: how far the crop is moved on by the last frames' motion (`predict_crop`).
        max_candidates: detections tried, in the order of the choice, until the face mesh confirms one.
        max_disagreement: most `read_disagreement` between a detection's read and a second read in
            the crop of its points; above it the face mesh is not sure of the face (reason 4).
        roll_passes: face-mesh passes that re-turn a detection's crop (`upright_face_landmarks`).
        with_iris: run the iris network (`iris` stays NaN without).
        enhance: where nothing is confirmed, detect again in the frame sharpened (`sharpen`) and
            follow a face found there in sharpened frames.
        quarter_turns: where nothing is confirmed, detect again in the frame turned a quarter
            each way (`LOOKS`), the points read in the frame as it is.
        full_range: where nothing is confirmed, detect again with BlazeFace full range on the
            whole frame (`detect_full_range`; plain, then sharpened with `enhance`).
        sharpen_amount: the unsharp mask's amount of the sharpened looks (`sharpen`).
        sharpened_min_presence: least presence confirming a face found in the sharpened frame
            (at least `min_presence`).
        framings: (crop scale, shift along, shift across the face) of the extra reads whose mean
            with the confirming read is a detected face's points (`FRAMINGS`; empty: one read).
        refind_max_zoom: a face re-found where it was last seen (`refind_face`) is taken only when
            the size of its points' crop is within this factor of its size then (reason 5).
        weak_reads: a frame that fails only for its read (reason 2: the face mesh's presence
            stays under the bar; 4: two reads disagree) keeps its best read's box, roll, points and
            presence (the detection's first read of highest presence), still failed: where
            the network cannot see the far side of a turned head (renders of the bundled head at
            70 / 80 / 90 deg of yaw: presence 0.005 / 0.004 / 0.001, the profile line read 7 / 12
            / 20% of the nose-bridge-to-chin length off) a user sees where the face is.
        progress: called with (fraction done, message).
    Returns:
        TrackedFaces.
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise ValueError(f"frames: expected shape (F, H, W, 3), found {frames.shape}")
    count, height, width = frames.shape[:3]
    detector, mesh = load_face_detector(device), load_face_mesh(device)
    iris_net = load_iris_network(device) if with_iris else None
    wide = load_full_range_detector(device) if full_range else None
    out = TrackedFaces(np.full((count, 4), np.nan), np.full(count, np.nan), np.full((count, 468, 2), np.nan),
                       np.zeros(count), np.ones(count, bool), np.zeros(count, np.int64), np.zeros(count, bool),
                       np.full((count, 2, 5, 2), np.nan), np.zeros(count, np.int64))
    crop, crop_roll = None, 0.0  # the next frame's crop (None: detect)
    latest, before = None, None  # the landmark crops (box, roll) of the last two frames read (None: none)
    last_box, lost_for = None, 0  # the followed face's detector-sized box when last seen
    weak: list[tuple[torch.Tensor, float, np.ndarray, float]] = []  # this frame's best read not taken

    def read(image: torch.Tensor, box: np.ndarray, roll: float) -> tuple[np.ndarray, float]:
        points, presence = face_landmarks(image, box[None], mesh, np.array([roll]))
        return points[0].double().cpu().numpy(), float(presence[0])

    def detect(image: torch.Tensor, f: int, refind: bool, turn: int = 0, wide_look: bool = False,
               least_presence: float = min_presence) -> tuple[tuple[np.ndarray, float, np.ndarray, float] | None, int]:
        """Detect (in the frame turned `turn` quarter turns; with the full-range detector when
        `wide_look`), choose and confirm (presence at least `least_presence`) a face in one frame:
        ((points, presence, crop, roll) or None, reason)."""
        turned = torch.rot90(image, turn, dims=(1, 2)) if turn else image
        if wide_look:
            faces = detect_full_range(turned, wide, min_score=FULL_RANGE_LOOK_MIN_SCORE, iou=iou)[0]
        else:
            faces = detect_all_faces(turned, detector, min_score=min_score, iou=iou, min_face_px=min_face_px,
                                     pyramid_min_score=pyramid_min_score)[0]
        boxes, keypoints, scores = unturn_faces(faces, turn, (height, width))
        reason = 3 if refind and len(boxes) else 1
        for _ in range(max_candidates):  # a detection the face mesh rejects: the next one chosen
            pick = refind_face(boxes, last_box) if refind else choose_face(boxes, scores, face, (height, width))
            if pick < 0:
                break
            box = square_box(boxes[pick], box_scale)
            first_roll = float(eye_roll(keypoints[pick]))
            for extra in ROLL_TRIES:  # the detector's roll can be far off (a 90 deg roll reads ~40)
                pts, pres, turned = upright_face_landmarks(image, box[None], mesh,
                                                           np.array([first_roll + extra]), roll_passes)
                if float(pres[0]) >= least_presence:
                    break
            out.presence[f] = max(float(pres[0]), out.presence[f])
            if not weak or float(pres[0]) > weak[0][1]:  # kept if the frame fails for this read (reason 2 or 4)
                weak[:] = [(pts[0], float(pres[0]), box, first_roll + extra)]  # converted if used
            if float(pres[0]) >= least_presence:  # read again in the crop of its own points: agree?
                first = pts[0].double().cpu().numpy()
                roll = float(points_roll(first))
                again_crop = landmark_crop(first, roll, crop_scale)
                again, again_presence = read(image, again_crop, roll)
                # a face found in the turned frame is upright there: its points' roll within 45 deg
                # of the turn (the sharpened, turned blurred camera man read 29 deg at turn 90: 123% off)
                off_turn = abs((roll - turn * np.pi / 2 + np.pi) % (2 * np.pi) - np.pi)
                if (again_presence >= least_presence and read_disagreement(first, again) <= max_disagreement
                        and (turn == 0 or off_turn <= np.pi / 4)):
                    # a re-found face keeps its size: a face half behind a hand is read squeezed into
                    # its visible half (the talking-head video: presence 0.98, 51% off, 0.6 of the size)
                    zoom = (again_crop[2] - again_crop[0]) / box_scale / (last_box[2] - last_box[0]) if refind else 1.0
                    if max(zoom, 1.0 / zoom) <= refind_max_zoom:
                        reads = [again] + [read(image, box, roll)[0] for box in framed_crops(again, roll, framings, crop_scale)
                                           if box is not None]
                        return (np.mean(reads, 0), again_presence, again_crop, roll), 0
                    reason = 5
                else:
                    reason = 4
            else:
                reason = 2
            if not isinstance(face, str) and not refind:  # an index or a box names one detection
                break
            keep = np.arange(len(boxes)) != pick
            boxes, scores, keypoints = boxes[keep], scores[keep], keypoints[keep]
        return None, reason

    sharpened = False  # the followed face was found in the sharpened frame: follow it there
    with torch.no_grad():
        for f in range(count):
            plain = torch.as_tensor(frames[f:f + 1], device=device)
            image = sharpen(plain, amount=sharpen_amount) if sharpened else plain
            points = None
            if crop is not None:  # follow: read in the crop predicted from the previous frames' points
                if before is not None:
                    crop, crop_roll = predict_crop(before, (crop, crop_roll), velocity)
                points, presence = read(image, crop, crop_roll)
                for _ in range(max_rereads):  # the face moved in the crop: read it again centred
                    if presence < min_presence:
                        break
                    roll = float(points_roll(points))
                    new_crop = landmark_crop(points, roll, crop_scale)
                    if crop_movement(crop, crop_roll, new_crop, roll) <= reread:
                        break
                    crop, crop_roll = new_crop, roll
                    points, presence = read(image, crop, crop_roll)
                    out.rereads[f] += 1
                if presence < min_presence:
                    points, latest = None, None
            if points is None:  # detect: in the frame, then (nothing confirmed) in the frame sharpened
                out.detected[f] = True
                refind = last_box is not None and lost_for < refind_frames
                sharpened, found, reason = False, None, 1
                weak.clear()
                for look in LOOKS:  # the frame, turned a quarter each way, sharpened: until one is confirmed
                    if (look[0] and not enhance) or (look[1] and not quarter_turns) or (look[2] and not full_range):
                        continue
                    image = sharpen(plain, amount=sharpen_amount) if look[0] else plain
                    found, look_reason = detect(image, f, refind, look[1], look[2],
                                                max(min_presence, sharpened_min_presence) if look[0] else min_presence)
                    if found is not None:
                        sharpened = look[0]
                        break
                    reason = max(reason, look_reason)  # the most informative: a face seen but not read
                if found is None:
                    out.reasons[f] = reason
                    if weak_reads and reason in (2, 4) and weak:
                        points, out.presence[f], out.boxes[f], out.rolls[f] = weak[0]
                        out.points[f] = points.double().cpu().numpy()
                    crop, latest, before, lost_for = None, None, None, lost_for + 1
                    if last_box is not None and lost_for >= refind_frames:
                        last_box = None  # give up on the lost face: the choice is made afresh
                    if progress is not None:
                        progress((f + 1) / count, "following the face")
                    continue
                points, presence, crop, crop_roll = found
            out.boxes[f], out.rolls[f], out.points[f], out.presence[f] = crop, crop_roll, points, presence
            out.failed[f] = False
            if iris_net is not None:
                out.iris[f] = iris_landmarks(image, points[None], iris_net)[0]
            roll = float(points_roll(points))
            before, latest = latest, (landmark_crop(points, roll, crop_scale), roll)
            crop, crop_roll = latest
            side = (crop[2] - crop[0]) / box_scale
            centre = (crop[:2] + crop[2:]) / 2
            last_box, lost_for = np.concatenate([centre - side / 2, centre + side / 2]), 0
            if progress is not None:
                progress((f + 1) / count, "following the face")
    return out
