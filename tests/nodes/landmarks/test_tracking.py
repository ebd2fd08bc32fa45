"""Which face and following it: nodes.landmarks.tracking (pure numpy), then the node's param."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import NodeError
from nodes.landmarks import DetectFaces
from nodes.landmarks.tracking import box_iou, choose_face, follow_faces

BOXES = np.array([[300, 100, 340, 140], [10, 200, 110, 300], [150, 150, 210, 210.0]])
SCORES = np.array([0.95, 0.7, 0.8])


@pytest.mark.parametrize("choice, want", [("largest", 1), ("score", 0), ("centre", 2), (0, 1), (1, 2), (2, 0),
                                          (3, -1), ([290.0, 90, 330, 130], 0), ([0.0, 0, 5, 5], -1)])
def test_choose_face_each_choice(choice, want):
    assert choose_face(BOXES, SCORES, choice, (360, 360)) == want


def test_choose_face_reading_order_breaks_ties_top_to_bottom():
    boxes = np.array([[0, 50, 10, 60], [0, 0, 10, 10.0]])
    assert choose_face(boxes, np.ones(2), 0, (100, 100)) == 1 and choose_face(np.zeros((0, 4)), [], "largest", (9, 9)) == -1


def test_box_iou_matches_a_hand_count():
    assert box_iou(np.array([0, 0, 10, 10.0]), np.array([[5, 0, 15, 10.0], [20, 20, 30, 30]])).tolist() == \
        pytest.approx([50 / 150, 0])


def test_follow_faces_never_swaps_to_a_larger_person_and_refinds_after_a_loss():
    # A (left) starts larger; B (right) grows past A from frame 2; frame 3 loses A (cut);
    # frame 4 re-applies "largest", which is now B.
    frames = [np.array([[0, 0, 100, 100], [300, 0, 380, 80.0]]),
              np.array([[5, 0, 105, 100], [300, 0, 390, 90.0]]),
              np.array([[10, 0, 110, 100], [290, 0, 420, 130.0]]),
              np.array([[290, 0, 420, 130.0]]),
              np.array([[12, 0, 112, 100], [290, 0, 420, 130.0]]),
              np.array([[14, 0, 114, 100], [292, 0, 422, 130.0]])]
    scores = [np.full(len(f), 0.9) for f in frames]
    chosen = follow_faces(frames, scores, "largest", (480, 640))
    assert chosen.tolist() == [0, 0, 0, -1, 1, 1]
    # by index: the rightmost of two (index 1) is followed even when it is alone
    chosen = follow_faces(frames, scores, 1, (480, 640))
    assert chosen.tolist() == [1, 1, 1, 0, 1, 1]
    # a frame without detections loses the face; the next frame chooses again
    frames2 = frames[:2] + [np.zeros((0, 4))] + frames[4:]
    assert follow_faces(frames2, [np.full(len(f), 0.9) for f in frames2], "largest", (480, 640)).tolist() == \
        [0, 0, -1, 1, 1]


@pytest.mark.parametrize("value, message", [
    ("big", r"'face': expected one of \['largest', 'centre', 'score'\], an index >= 0 or a box"),
    (-1, r"'face': expected an index >= 0"),
    (True, r"'face': expected a name, an index >= 0 or a box"),
    ([1, 2], r"'face': expected a box of 4 numbers"),
    ([3, 0, 1, 5], r"'face': expected a box \[x0, y0, x1, y1\] with x1 > x0"),
    (2.5, r"'face': expected one of"),
])
def test_detect_faces_face_param_messages(value, message):
    with pytest.raises(NodeError, match=message):
        DetectFaces(face=value)


def test_detect_faces_face_param_accepts_each_form():
    assert [DetectFaces(face=v).params.face for v in ("centre", 0, 3, [1, 2, 30, 40.5])] == \
        ["centre", 0, 3, [1.0, 2.0, 30.0, 40.5]]
    with pytest.raises(NodeError, match=r"'min_score': expected a number, found True"):
        DetectFaces(min_score=True)  # the other fields keep the strict number check
