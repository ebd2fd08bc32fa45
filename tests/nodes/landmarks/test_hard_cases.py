"""Detection and landmarks on transformed photos with known answers (`cases.py`): rolled faces,
small faces in large frames, two people, dark frames; and following a person over a video.

`bench/detect_faces.py` prints every case at 4 placements; the bounds here leave margin over
those numbers. The camera man (grey, near profile, eye distance 23 px) reads about 12% off his
own reference after a mere shift of the frame, so his bounds are wide.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("tflite")
pytest.importorskip("skimage")

from nodegraph import ImageSequence, ParamSequence, run_node  # noqa: E402
from nodes.landmarks import DetectFaces, FaceLandmarks  # noqa: E402
from nodes.landmarks.correspondence import MEDIAPIPE_TO_68  # noqa: E402

from .cases import CASES, error_percent, make_case  # noqa: E402

BOUNDS = {  # case -> most error in % of the eye distance (astronaut, camera)
    "roll 30": (4, 30), "roll 90": (12, 35), "eye 25 px in 1080p": (4, 25),
    "eye 20 px in 817 x 1024": (5, 30), "dark (x0.25)": (4, 25),
}


def _detect_and_mark(images: np.ndarray, **params):
    seq = ImageSequence(np.ascontiguousarray(images, np.float32), colour_space="srgb")
    det = run_node(DetectFaces, params, images=seq)
    marks = run_node(FaceLandmarks, images=seq, boxes=det["boxes"], rolls=det["rolls"])
    return det, marks


def _centre(box):
    return (np.asarray(box[:2]) + np.asarray(box[2:])) / 2


@pytest.mark.parametrize("photo", ["astronaut", "camera"])
@pytest.mark.parametrize("case", sorted(BOUNDS))
def test_hard_case_is_found_and_read(photo, case):
    c = make_case(photo, **CASES[case])
    det, marks = _detect_and_mark(c.image[None])
    assert det["failed"].values[0, 0] == 0
    assert np.linalg.norm(_centre(det["boxes"].values[0]) - _centre(c.face_box)) < c.eye
    err = error_percent(marks["landmarks468"].points[0][MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye)
    assert err < BOUNDS[case][photo == "camera"], f"{photo} {case}: {err:.1f}% of the eye distance"


def test_two_people_largest_and_index_and_box():
    c = make_case("astronaut", **CASES["second smaller copy"])
    (other,) = c.others
    for face, want in (("largest", c.face_box), (0, c.face_box), (1, other), (list(map(float, other)), other)):
        det, marks = _detect_and_mark(c.image[None], face=face)
        assert np.linalg.norm(_centre(det["boxes"].values[0]) - _centre(want)) < c.eye, face
    det, marks = _detect_and_mark(c.image[None])
    err = error_percent(marks["landmarks468"].points[0][MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye)
    assert err < 4


def test_small_face_needs_the_pyramid():
    c = make_case("camera", **CASES["eye 20 px in 817 x 1024"])
    seq = ImageSequence(c.image[None], colour_space="srgb")
    assert run_node(DetectFaces, {"min_face_px": 0}, images=seq)["failed"].values[0, 0] == 1  # the old front end
    assert run_node(DetectFaces, images=seq)["failed"].values[0, 0] == 0


def test_video_follows_the_first_choice_loses_it_at_a_cut_and_refinds():
    # the astronaut with a smaller copy to her right; the copy grows past her from frame 2;
    # frame 3 is a cut to a face-free frame; frame 4 applies "largest" afresh (the copy).
    big = make_case("astronaut", eye_px=36, canvas=(480, 800), at=(0.3, 0.5), second=0.75)
    grown = make_case("astronaut", eye_px=30, canvas=(480, 800), at=(0.3, 0.5), second=1.6)
    blank = np.full_like(big.image, 0.35)
    frames = np.stack([big.image, big.image, grown.image, blank, grown.image])
    det = run_node(DetectFaces, images=ImageSequence(frames, colour_space="srgb"))
    centres = np.array([_centre(b) for b in det["boxes"].values])
    assert det["failed"].values[:, 0].tolist() == [0, 0, 0, 1, 0]
    for f in (0, 1, 2):  # still her, though the copy is larger on frame 2
        assert np.linalg.norm(centres[f] - _centre(big.face_box if f < 2 else grown.face_box)) < 30
    assert np.linalg.norm(centres[4] - _centre(grown.others[0])) < 30
    assert DetectFaces.kind.name == "sequence"  # following needs every earlier frame


def test_face_landmarks_rolls_port_turns_the_crop():
    c = make_case("astronaut", **CASES["roll 90"])
    seq = ImageSequence(c.image[None], colour_space="srgb")
    det = run_node(DetectFaces, images=seq)
    errors = {}
    for label, params, rolls in (("upright", {"roll_passes": 0}, None), ("detector", {"roll_passes": 0}, det["rolls"]),
                                 ("refined", {}, det["rolls"])):
        out = run_node(FaceLandmarks, params, images=seq, boxes=det["boxes"], rolls=rolls)
        errors[label] = error_percent(out["landmarks468"].points[0][MEDIAPIPE_TO_68], c.points[MEDIAPIPE_TO_68], c.eye)
    assert errors["refined"] < 12 < 30 < errors["upright"], errors
    assert 20 < np.rad2deg(det["rolls"].values[0, 0]) < 90  # the detector's keypoints under-read a 90 deg roll
    bad = ParamSequence(np.zeros((1, 2), np.float32), ["a", "b"])
    from nodegraph import NodeError

    with pytest.raises(NodeError, match=r"rolls.*expected 1 column"):
        run_node(FaceLandmarks, images=seq, boxes=det["boxes"], rolls=bad)


# Spoiled frames (`cases.degrade`) through landmarks.TrackFaces: the right face or a failed frame
# with a reason, never a confident wrong face. Measured on the astronaut at 4 placements
# (bench/detect_faces.py): every frame not failed within 8.0% of the eye distance; failed: roll
# 90 + blur / JPEG 6 / noise 1 of 4 each (presence, or two reads disagreeing), 25 px + blur 4 of
# 4 (the detector finds nothing). Without the second read a roll-90 noisy frame gave 58% at
# presence 0.92; without the extra roll tries roll 90 + blur and + JPEG failed 4 of 4. Those
# counts predate the second looks (landmarks.TrackFaces 2: the frame turned and sharpened where no
# face is confirmed), which read the 25 px blurred face here at 6.3% (test_second_looks.py).
SPOILED = [(base, kind) for base in ("upright", "roll 90", "eye 25 px in 1080p")
           for kind in ("dark", "blur", "jpeg 6", "noise", "grey", "16-bit")]


@pytest.mark.parametrize("base, kind", SPOILED)
def test_spoiled_frame_is_read_right_or_flagged(base, kind):
    from nodes.landmarks import TrackFaces
    from nodes.landmarks.tracking import FAILURE_REASONS

    from .cases import degrade

    c = make_case("astronaut", **CASES[base])
    seq = ImageSequence(degrade(c.image, kind)[None], colour_space="srgb")
    out = run_node(TrackFaces, images=seq)
    if out["failed"].values[0, 0]:
        reason = int(out["reasons"].values[0, 0])
        assert reason in (1, 2, 4), FAILURE_REASONS[reason]
        assert (out["landmarks68"].confidence[0] == 0).all()  # the fit leaves the frame out
        # a face not read (reason 2 or 4) keeps its best read (`weak_reads`) and its presence; none: NaN, 0
        assert np.isnan(out["landmarks68"].points[0]).all() == (reason == 1)
        assert (out["presence"].values[0, 0] == 0) == (reason == 1)
        assert (base, kind) in {("roll 90", "blur"), ("roll 90", "jpeg 6"), ("roll 90", "noise"),
                                ("eye 25 px in 1080p", "blur")}, f"{base}, {kind}: {FAILURE_REASONS[reason]}"
        return
    err = error_percent(out["landmarks68"].points[0], c.points[MEDIAPIPE_TO_68], c.eye)
    assert err < 10, f"{base}, {kind}: {err:.1f}% of the eye distance, presence {out['presence'].values[0, 0]:.2f}"


def test_a_16_bit_png_reads_like_the_8_bit_frame(tmp_path):
    from nodes.io.image import write_image
    from nodes.landmarks import LoadFrames, TrackFaces

    c = make_case("astronaut", **CASES["roll 30"])
    write_image(tmp_path / "plate.0000.png", c.image, ["R", "G", "B"], "uint16")
    images = run_node(LoadFrames, {"path": str(tmp_path / "plate.%04d.png")})["images"]
    assert images.pixels.dtype == np.float32 and images.pixels.shape == (1, 768, 768, 3)
    out = run_node(TrackFaces, images=images)
    assert out["failed"].values[0, 0] == 0
    assert error_percent(out["landmarks68"].points[0], c.points[MEDIAPIPE_TO_68], c.eye) < 4
