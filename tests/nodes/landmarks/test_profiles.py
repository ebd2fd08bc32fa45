"""landmarks.TrackFaces on a head turned to a profile: renders of the bundled head at 0-90 deg of
yaw. Up to 60 deg the face is read (not failed); past it the face mesh cannot see the far side and
the frame fails, but keeps the detector's box and its best read (`weak_reads`), flagged, with the
profile line (nose, lips, chin) where the head is."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, ImageSequence, run_node  # noqa: E402
from nodes.fit.output_nodes import projected_landmarks68  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.landmarks import TrackFaces  # noqa: E402
from tests.support.synthetic import random_face_parameters, render_truth_plates  # noqa: E402

YAWS = (0.0, 60.0, 75.0, 90.0)
PROFILE_LINE = [8, 27, 28, 29, 30, 33, 51, 57, 62, 66]  # chin, nose bridge to base, lips' middle


@pytest.fixture(scope="module")
def turned():
    """The mean head, neutral, 130 cm in front of a 512^2 30 deg camera (face ~200 px), turned."""
    model = load_face_model()
    cam = Camera.from_fov(512, 512, 30.0)
    truth = random_face_parameters(model, len(YAWS), seed=1)
    truth["identity"][:] = 0
    truth["weights"][:] = 0
    a = np.radians(YAWS)
    turn = np.zeros((len(YAWS), 3, 3))
    turn[:, 0, 0], turn[:, 0, 2], turn[:, 1, 1], turn[:, 2, 0], turn[:, 2, 2] = np.cos(a), np.sin(a), 1, -np.sin(a), np.cos(a)
    truth["rotation"] = (np.diag([1.0, -1.0, -1.0])[None] @ turn).astype(np.float32)
    truth["translation"][:] = [0.0, 0.0, 130.0]
    plates = render_truth_plates(model, [cam], truth)[0]
    fitted = np.concatenate([truth["rotation"].reshape(-1, 9), truth["translation"], truth["weights"]], 1)
    out = [run_node(TrackFaces, {"with_iris": False}, images=ImageSequence(plates[i:i + 1], colour_space="linear"))
           for i in range(len(YAWS))]
    return out, projected_landmarks68(fitted.astype(np.float64), model, cam).pixels


def _profile_error(points: np.ndarray, truth: np.ndarray) -> float:
    """Mean distance of the profile line's points, in nose-bridge-to-chin lengths (a turn does not
    shorten it, unlike the eye distance)."""
    scale = np.linalg.norm(truth[27] - truth[8])
    return float(np.linalg.norm(points[PROFILE_LINE] - truth[PROFILE_LINE], axis=1).mean() / scale)


def test_up_to_60_deg_the_face_is_read(turned):
    out, truth = turned
    for i, yaw in enumerate(YAWS[:2]):
        assert out[i]["failed"].values[0, 0] == 0, yaw
        # measured 2.7% (0 deg) and 5.6% (60 deg): the network's own spread on renders
        assert _profile_error(out[i]["landmarks68"].points[0], truth[i]) < 0.12, yaw


def test_past_60_deg_a_flagged_box_and_read_where_the_head_is(turned):
    out, truth = turned
    for i, yaw in enumerate(YAWS[2:], 2):
        o = out[i]
        assert o["failed"].values[0, 0] == 1 and o["reasons"].values[0, 0] in (2, 4), yaw
        assert (o["landmarks68"].confidence[0] == 0).all()  # the fit leaves it out
        box = o["boxes"].values[0]
        assert np.isfinite(box).all() and np.isfinite(o["landmarks468"].points[0]).all()
        head = truth[i]
        assert (box[:2] < head.min(0)).all() and (box[2:] > head.max(0)).all(), (yaw, box, head.min(0), head.max(0))
        # measured 8-16% at 70-80 deg, 20% at 90 deg; a read of another place is > 100%
        assert _profile_error(o["landmarks68"].points[0], head) < 0.4, yaw
        assert 0 < o["presence"].values[0, 0] <= 1
