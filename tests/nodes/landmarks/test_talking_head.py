"""A talking-head video made from a real photo (`cases.make_talking_head`): the astronaut sways,
nods, turns her head (yaw +-18 deg, a perspective warp), rolls, zooms, darts a quarter of the
frame across (motion blur: each frame the mean of 3 renders over half a frame), the light dims to
0.45 with a side light sweeping across, a dark hand passes over her face (frames 20-25, wholly
covering it in 22-23) and grace_hopper stands beside her, smaller. `landmarks.TrackFaces` must
read every frame where the hand covers under half of her face (issue 26: under 5% failed frames
on talking-head videos), flag the frames it hides, never read a half-hidden face confidently
wrong, and re-find her, not grace_hopper, after the hand.

Measured (40 frames, 480 x 640, one thread, TrackFaces 6): failed frames 20-25 (the hand covering
0.69-0.92 of the face box; 25: 0.52, reason 5, the re-found face's size jumped); 1.6-3.7% of the
eye distance on the other frames, 2.2% on frame 26 where she is re-found. Without the size check
(`refind_max_zoom` unbounded) frame 25 was read at presence 0.99, 52.3% off. The bounds leave
room for other CPUs and thread counts.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("tflite")
pytest.importorskip("skimage")

from nodes.landmarks.correspondence import MEDIAPIPE_TO_68  # noqa: E402
from nodes.landmarks.face_tracker import track_faces  # noqa: E402
from nodes.landmarks.tracking import FAILURE_REASONS  # noqa: E402

from .cases import make_talking_head  # noqa: E402

OCCLUSION = (20, 26)


@pytest.fixture(scope="module")
def video():
    return make_talking_head("astronaut", count=40, occlusion=OCCLUSION)


@pytest.fixture(scope="module")
def tracked(video):
    return track_faces(video.frames, with_iris=False)


def _errors(points: np.ndarray, video) -> np.ndarray:
    e = points[:, MEDIAPIPE_TO_68] - video.points[:, MEDIAPIPE_TO_68]
    return np.linalg.norm(e, axis=-1).mean(-1) / video.eye * 100


def test_the_video_holds_what_it_says(video):
    assert video.frames.shape == (40, 480, 640, 3) and np.isfinite(video.points).all()
    assert (video.occluded[:OCCLUSION[0]] == 0).all() and (video.occluded[OCCLUSION[1]:] == 0).all()
    assert (video.occluded[OCCLUSION[0] + 2:OCCLUSION[1] - 2] > 0.85).all()  # wholly hidden in the middle
    assert 30 < video.eye.min() and video.eye.max() < 50
    # the light dims: the face's mean sRGB brightness varies by a factor of 1.4 or more (measured 1.57)
    face = [video.frames[f, int(p[:, 1].min()):int(p[:, 1].max()), int(p[:, 0].min()):int(p[:, 0].max())].mean()
            for f, p in enumerate(video.points) if video.occluded[f] == 0]
    assert max(face) / min(face) > 1.4


def test_talking_head_is_followed_and_refound_after_the_hand(video, tracked):
    out = tracked
    visible = video.occluded < 0.5
    assert not out.failed[visible].any(), np.nonzero(out.failed & visible)[0]  # under 5%: none here
    assert out.failed[video.occluded > 0.85].all()  # a hidden face is not read
    errors = _errors(out.points, video)
    ok = ~out.failed
    assert errors[ok].max() < 7.0, errors.round(1)  # never a confident wrong read (measured at most 3.7)
    assert np.median(errors[ok]) < 4.0, np.median(errors[ok])
    after = OCCLUSION[1] + np.argmax(ok[OCCLUSION[1]:])  # the first frame read after the hand
    assert after <= OCCLUSION[1] + 1 and errors[after] < 5.0  # re-found: her, not grace_hopper
    assert out.detected[0] and out.detected[OCCLUSION[0]:after + 1].all() and not out.detected[after + 1:].any()
    assert FAILURE_REASONS[5].startswith("the re-found face's size jumped")


def test_without_the_size_check_the_half_hidden_face_is_read_wrong(video, tracked):
    # the control: the frames around the hand, the re-found face's size unbounded
    span = slice(OCCLUSION[0] - 2, OCCLUSION[1] + 2)
    part = video._replace(frames=video.frames[span], points=video.points[span], eye=video.eye[span],
                          occluded=video.occluded[span])
    loose = track_faces(part.frames, with_iris=False, refind_max_zoom=1e9)
    checked = tracked._replace(failed=tracked.failed[span], reasons=tracked.reasons[span])
    half = (part.occluded > 0.3) & (part.occluded < 0.85)
    wrong = ~loose.failed & half & (_errors(loose.points, part) > 20)
    assert wrong.any(), (_errors(loose.points, part).round(1), part.occluded.round(2))
    assert checked.failed[wrong].all() and (checked.reasons[wrong] == 5).all()
