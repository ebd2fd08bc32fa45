"""Frames of the issue-26 acceptance check (`bench/detect_faces.py --only-check`) that TrackFaces
flags as failed, at the check's own placement and noise seed: they must stay read within 10% of
the eye distance or flagged with a reason, never read elsewhere unflagged.

Why they fail (`nodes.landmarks.face_tracker`'s docstring): the face mesh's presence in the crop
of the reference points themselves is 0.00 (the astronaut darkened x0.25 and JPEG 6) and 0.20 (the
combined case: 25 px eye distance, roll 90, dark, a second smaller copy, with noise). Denoising
raises it on the noisy frame (0.91-0.99 in that crop), but the face mesh in the frame's
full-range detection denoised by a 1 px Gaussian and turned by the detector's roll plus 90 deg
read the dark background 7.6 eye distances from both faces at presence 0.71, its re-read agreeing
(0.09): a denoised look must not make this flagged frame a confident wrong face. TrackFaces on
the frames denoised first (Gaussian 2 px) reads the noisy one 10.2% off at presence 0.66 (1 px:
still failed) and the JPEG one not at all; on the camera man's 6 failed noisy frames 13.6 and
17.2% off (hand annotation), 4 still failed: no frame gains a read within 10%, so TrackFaces has
no denoised look. The bound 10% is the acceptance line of issue 26.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("tflite")

from nodes.landmarks.correspondence import MEDIAPIPE_TO_68  # noqa: E402
from nodes.landmarks.face_tracker import track_faces  # noqa: E402
from nodes.landmarks.tracking import FAILURE_REASONS  # noqa: E402

from .cases import CASES, degrade, error_percent, make_case  # noqa: E402

SHIFTS = [(0.0, 0.0), (0.013, 0.007), (-0.011, 0.017), (0.021, -0.013)]
"""`bench/detect_faces.py`'s placements: case i is moved by SHIFTS[i % 4] (fractions of the frame)."""
SPOILINGS = ("none", "dark", "blur", "jpeg 6", "noise", "grey", "16-bit")
"""`bench/detect_faces.py`'s spoilings: spoiling j of case i is seeded i + j."""


def check_frame(base: str, kind: str) -> tuple[np.ndarray, object]:
    """(frame, case) as the acceptance check makes them for the astronaut."""
    c_index = list(CASES).index(base)
    kw = dict(CASES[base])
    at = kw.pop("at", (0.5, 0.5))
    dx, dy = SHIFTS[c_index % len(SHIFTS)]
    case = make_case("astronaut", **kw, at=(at[0] + dx, at[1] + dy))
    return degrade(case.image, kind, seed=c_index + SPOILINGS.index(kind)), case


@pytest.mark.parametrize("base, kind", [("eye 25 px, roll 90, dark, second copy", "noise"),
                                        ("dark (x0.25)", "jpeg 6")])
def test_a_failed_check_frame_is_read_right_or_flagged(base, kind):
    frame, case = check_frame(base, kind)
    out = track_faces(frame[None], with_iris=False)
    if out.failed[0]:
        assert out.reasons[0] in (1, 2, 4), FAILURE_REASONS[int(out.reasons[0])]
        # a face not read (reason 2 or 4) keeps its best read (`weak_reads`), flagged; none found: NaN
        assert np.isnan(out.points[0]).all() == (out.reasons[0] == 1)
        return
    err = error_percent(out.points[0][MEDIAPIPE_TO_68], case.points[MEDIAPIPE_TO_68], case.eye)
    assert err < 10, f"{base}, {kind}: read {err:.1f}% of the eye distance off at presence {out.presence[0]:.2f}"
