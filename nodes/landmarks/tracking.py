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

Boxes are (x0, y0, x1, y1) pixels, origin top-left, x right, y down. Pure numpy (no torch).
"""

from __future__ import annotations

from typing import Sequence, Union

import numpy as np

__all__ = ["FACE_CHOICES", "FaceChoice", "box_iou", "choose_face", "follow_faces"]

FACE_CHOICES = ("largest", "centre", "score")
"""The named choices of `choose_face`."""

FaceChoice = Union[str, int, Sequence[float]]


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
