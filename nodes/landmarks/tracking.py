"""Which face: choose one detection per frame and follow that person from frame to frame.

A choice (`FaceChoice`) is one of:
- "largest": the detection with the largest box area (the default of `landmarks.DetectFaces`);
- "centre": the detection whose box centre is nearest the image centre;
- "score": the detector's most confident detection;
- an index i >= 0: the i-th detection in reading order, left to right by box centre x (ties
  broken top to bottom by box centre y); a frame with i or fewer detections has no face;
- a box [x0, y0, x1, y1] in pixels: the detection overlapping it most (IoU); none when no
  detection overlaps it at all.

Following (`follow_faces`): the choice is applied on the first frame where it finds a face;
each later frame takes the detection whose box overlaps the previous frame's chosen box most
(IoU), so the person stays the same even when another becomes larger, more central or more
confident. When no detection overlaps the previous box by at least `min_iou` (an occlusion,
a cut, a missed detection) the frame has no face and the choice is applied afresh from the
next frame on (the person is re-found).

Following by landmarks (`nodes.landmarks.face_tracker`, `landmarks.TrackFaces`) uses
`landmark_crop` (a face's crop from its points), `refind_face` (the detection where a lost face
was last seen) and `FAILURE_REASONS`; `eye_gaze` is a per-eye gaze measure from the iris points.

Boxes are (x0, y0, x1, y1) pixels, origin top-left, x right, y down. Pure numpy (no torch).
"""

from __future__ import annotations

from typing import Sequence, Union

import numpy as np

__all__ = ["FACE_CHOICES", "FAILURE_REASONS", "FaceChoice", "box_iou", "choose_face", "follow_faces",
           "refind_face", "landmark_crop", "EYE_CORNERS", "eye_gaze"]

FACE_CHOICES = ("largest", "centre", "score")
"""The named choices of `choose_face`."""

FaceChoice = Union[str, int, Sequence[float]]

EYE_CORNERS = np.array([[33, 133], [362, 263]], np.int64)
"""(2, 2) face-mesh indices of each eye's corners, ordered along the image's x axis of a frontal
face (eye 0, the subject's right: outer then inner corner; eye 1: inner then outer)."""

FAILURE_REASONS = ("", "no face found", "face presence below min_presence",
                   "the followed face is lost; other faces are in view",
                   "two reads of the face disagree (the face mesh is unsure of it)",
                   "the re-found face's size jumped from when it was last seen (partly hidden?)")
"""Why a frame failed, by code (`nodes.landmarks.face_tracker.track_faces`; 0: it did not)."""


def box_iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Intersection over union of one box with each of `boxes`.

    Args:
        box: (4,) x0 y0 x1 y1; boxes: (N, 4).
    Returns:
        (N,) in [0, 1] (0 for empty boxes).
    """
    box = np.asarray(box, np.float64)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    lo = np.maximum(box[:2], boxes[:, :2])
    hi = np.minimum(box[2:], boxes[:, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), -1)
    area = np.prod(np.clip(box[2:] - box[:2], 0, None))
    areas = np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 0, None), -1)
    return inter / np.maximum(area + areas - inter, 1e-12)


def _check_choice(choice: FaceChoice) -> None:
    if isinstance(choice, str):
        if choice not in FACE_CHOICES:
            raise ValueError(f"choice: expected one of {list(FACE_CHOICES)}, an index >= 0 or a box "
                             f"[x0, y0, x1, y1], found {choice!r}")
    elif isinstance(choice, (bool, np.bool_)):
        raise ValueError(f"choice: expected a name, an index >= 0 or a box, found {choice!r}")
    elif isinstance(choice, (int, np.integer)):
        if choice < 0:
            raise ValueError(f"choice: expected an index >= 0, found {choice}")
    elif len(choice) != 4 or not (choice[2] > choice[0] and choice[3] > choice[1]):
        raise ValueError(f"choice: expected a box [x0, y0, x1, y1] with x1 > x0 and y1 > y0, found {list(choice)}")


def choose_face(boxes: np.ndarray, scores: np.ndarray, choice: FaceChoice,
                image_size: tuple[int, int]) -> int:
    """Index of the detection `choice` picks (see the module docstring), or -1 for none.

    Args:
        boxes: (N, 4) face boxes, pixels; scores: (N,) detector scores.
        choice: "largest", "centre", "score", an index >= 0 or a box [x0, y0, x1, y1] (pixels).
        image_size: (H, W) pixels, for "centre".
    Returns:
        an index into `boxes`, or -1.
    Raises:
        ValueError: an unknown name, a negative index or a malformed box.

    Example:
        >>> b = np.array([[0, 0, 10, 10], [50, 0, 80, 30.]])
        >>> choose_face(b, np.array([0.9, 0.6]), "largest", (100, 100)), choose_face(b, np.array([0.9, 0.6]), 0, (100, 100))
        (1, 0)
    """
    _check_choice(choice)
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    if not len(boxes):
        return -1
    centres = (boxes[:, :2] + boxes[:, 2:]) / 2
    if isinstance(choice, str):
        if choice == "largest":
            return int(np.argmax(np.prod(boxes[:, 2:] - boxes[:, :2], -1)))
        if choice == "score":
            return int(np.argmax(scores))
        height, width = image_size
        middle = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
        return int(np.argmin(np.linalg.norm(centres - middle, axis=-1)))
    if isinstance(choice, (int, np.integer)):
        order = np.lexsort((centres[:, 1], centres[:, 0]))  # x first, then y
        return int(order[choice]) if choice < len(order) else -1
    overlap = box_iou(np.asarray(choice, np.float64), boxes)
    return int(np.argmax(overlap)) if overlap.max() > 0 else -1


def follow_faces(boxes: Sequence[np.ndarray], scores: Sequence[np.ndarray], choice: FaceChoice,
                 image_size: tuple[int, int], *, min_iou: float = 0.3) -> np.ndarray:
    """Choose a face on the first frame where `choice` finds one, then follow that person.

    Args:
        boxes: per frame, (N_f, 4) face boxes, pixels (N_f may be 0).
        scores: per frame, (N_f,) detector scores.
        choice: as `choose_face`.
        image_size: (H, W) pixels.
        min_iou: the least overlap with the previous frame's box that continues the track.
    Returns:
        (F,) int64: the chosen detection of each frame, -1 where none (not found, or lost:
        the next frame applies `choice` again).
    """
    _check_choice(choice)
    out = np.full(len(boxes), -1, np.int64)
    previous = None
    for f, (frame_boxes, frame_scores) in enumerate(zip(boxes, scores)):
        frame_boxes = np.asarray(frame_boxes, np.float64).reshape(-1, 4)
        if previous is None:
            out[f] = choose_face(frame_boxes, frame_scores, choice, image_size)
        elif len(frame_boxes):
            overlap = box_iou(previous, frame_boxes)
            best = int(np.argmax(overlap))
            out[f] = best if overlap[best] >= min_iou else -1
        previous = frame_boxes[out[f]] if out[f] >= 0 else None
    return out


def refind_face(boxes: np.ndarray, last_box: np.ndarray, *, max_shift: float = 1.0, max_zoom: float = 2.0) -> int:
    """The detection that is the face last seen in `last_box` (after an occlusion), or -1.

    A detection qualifies when its box centre lies within `max_shift` sides (of `last_box`) of
    the last box's centre and its side differs by at most a factor `max_zoom`; of those, the
    nearest is taken.

    Args:
        boxes: (N, 4) face boxes of this frame, pixels.
        last_box: (4,) the followed face's box when it was last seen, pixels.
    Returns:
        an index into `boxes`, or -1.

    Example:
        >>> refind_face(np.array([[300, 0, 400, 100], [20, 5, 120, 105.]]), np.array([0, 0, 100, 100.]))
        1
    """
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    last = np.asarray(last_box, np.float64)
    if not len(boxes):
        return -1
    side = np.sqrt(np.prod(np.clip(boxes[:, 2:] - boxes[:, :2], 1e-12, None), -1))
    last_side = float(np.sqrt(np.prod(np.clip(last[2:] - last[:2], 1e-12, None))))
    shift = np.linalg.norm((boxes[:, :2] + boxes[:, 2:]) / 2 - (last[:2] + last[2:]) / 2, axis=-1) / last_side
    ok = (shift <= max_shift) & (side <= max_zoom * last_side) & (side >= last_side / max_zoom)
    return int(np.argmin(np.where(ok, shift, np.inf))) if ok.any() else -1


def landmark_crop(points: np.ndarray, roll: float, scale: float = 1.5) -> np.ndarray:
    """The square crop box of a face from its landmarks (MediaPipe's tracking crop).

    The points' extent is measured in the face's own axes (turned by `roll`); the crop is
    centred on that extent's centre, of side `scale` times its longer side (MediaPipe's
    `FaceLandmarkLandmarksToRoi`: 1.5).

    Args:
        points: (N, 2) landmarks, pixels (all finite).
        roll: the face's roll, radians, clockwise on screen (e.g. the eye line's angle).
        scale: crop side over the extent's longer side.
    Returns:
        (4,) x0 y0 x1 y1, pixels: the crop before it is turned by `roll` about its centre.

    Example:
        >>> landmark_crop(np.array([[0, 0], [10, 0], [10, 20], [0, 20.]]), 0.0).tolist()
        [-10.0, -5.0, 20.0, 25.0]
    """
    p = np.asarray(points, np.float64)
    c, s = np.cos(roll), np.sin(roll)
    along = p @ np.array([c, s])  # coordinates in the face's axes
    across = p @ np.array([-s, c])
    lo, hi = np.array([along.min(), across.min()]), np.array([along.max(), across.max()])
    mid = (lo + hi) / 2
    centre = np.array([c * mid[0] - s * mid[1], s * mid[0] + c * mid[1]])
    half = scale * float((hi - lo).max()) / 2
    return np.concatenate([centre - half, centre + half])


def eye_gaze(points468: np.ndarray, iris: np.ndarray) -> np.ndarray:
    """Where each iris sits between its eye's corners: a per-eye gaze measure.

    The iris centre's offset from the midpoint of the eye's corners (`EYE_CORNERS`), in corner
    distances, in the eye's own frame: x along the corner line (towards the image's right in a
    frontal face: the subject looking to their left gives x > 0 in both eyes), y across it
    (down). About 0 looking ahead; 0.5 would put the iris centre on a corner. Unlike an angle
    it needs no eyeball model; it does not change when the head moves in the image plane
    (shift, roll, zoom), and mirroring the image swaps the eyes and negates x.

    Args:
        points468: (..., 468, 2) face-mesh points, pixels.
        iris: (..., 2, 5, 2) `iris_landmarks`, pixels.
    Returns:
        (..., 2, 2) per eye (0 right, 1 left): x, y; NaN where the inputs are.
    """
    p = np.asarray(points468, np.float64)
    a, b = p[..., EYE_CORNERS[:, 0], :], p[..., EYE_CORNERS[:, 1], :]  # (..., 2, 2)
    axis = b - a
    length2 = np.maximum((axis ** 2).sum(-1, keepdims=True), 1e-12)
    d = np.asarray(iris, np.float64)[..., 0, :] - (a + b) / 2
    along = (d * axis).sum(-1, keepdims=True) / length2
    across = (d[..., 1:] * axis[..., :1] - d[..., :1] * axis[..., 1:]) / length2
    return np.concatenate([along, across], -1)
