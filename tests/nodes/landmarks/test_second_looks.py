"""The second looks of landmarks.TrackFaces where the frame shows no face it can confirm
(`nodes.landmarks.face_tracker.LOOKS`): the frame turned a quarter each way (`quarter_turns`,
`unturn_faces`) and sharpened (`enhance`, `sharpen`). The unsharp mask itself; a small face
rolled 90 deg found only in the turned frame; a small blurred face read only in the sharpened
frame; face-free photos that stay failed with every look; the sharpened looks' mask strength
(amount 6) and their presence bar (0.9).

Measured (bench/detect_faces.py --only-check, at the placements of these tests): the astronaut at a 25
px eye distance in 1080p rolled 90 deg, darkened and beside a smaller copy is read at 2.2% of the
eye distance (nothing found without the turns); at a 25 px eye distance blurred by 3 px at 6.4%
(nothing found without sharpening); no face was read on 18 face-free skimage photos, plain, dark,
blurred or noisy. The bound 10% is the acceptance line of issue 26.
"""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("tflite")
skimage_data = pytest.importorskip("skimage.data")

from nodegraph import ImageSequence, run_node  # noqa: E402
from nodes.landmarks import TrackFaces  # noqa: E402
from nodes.landmarks.correspondence import MEDIAPIPE_TO_68  # noqa: E402
from nodes.landmarks.face_tracker import sharpen  # noqa: E402

from .cases import CASES, degrade, error_percent, make_case  # noqa: E402


def test_sharpen_keeps_a_ramp_and_steepens_a_blurred_edge():
    x = torch.linspace(0.2, 0.8, 64, dtype=torch.float64)
    ramp = x[None, None, :, None].expand(1, 40, 64, 3).contiguous()
    out = sharpen(ramp, 2.0, 3.0)
    # a Gaussian blur leaves a linear ramp unchanged away from the (replicated) edges: so does the mask
    assert torch.allclose(out[:, :, 10:-10], ramp[:, :, 10:-10], atol=1e-12)
    step = (torch.arange(64, dtype=torch.float64) >= 32).double() * 0.5 + 0.25
    from nodes.geometry.image import gaussian_blur

    blurred = gaussian_blur(step[None, None, :, None].expand(1, 8, 64, 3).contiguous(), 2.0)
    edge = sharpen(blurred, 2.0, 3.0)[0, 4, :, 0]
    assert edge[32] - edge[31] > 1.5 * (blurred[0, 4, 32, 0] - blurred[0, 4, 31, 0])  # steeper
    assert edge.min() >= 0 and edge.max() <= 1 and abs(float(edge[0]) - 0.25) < 1e-9  # clipped, flat part kept


def test_unturn_faces_maps_a_turned_frame_pixel_to_the_same_pixel_of_the_frame():
    from nodes.landmarks.face_tracker import unturn_faces
    from nodes.landmarks.network import Faces

    frame = np.random.default_rng(0).random((7, 11, 3))
    for turn in (1, 2, 3):
        turned = torch.rot90(torch.from_numpy(frame)[None], turn, dims=(1, 2))[0].numpy()
        assert np.array_equal(turned, np.rot90(frame, turn))
        yy, xx = np.mgrid[:turned.shape[0], :turned.shape[1]]
        p = np.stack([xx.ravel(), yy.ravel()], -1).astype(np.float64)
        faces = Faces(np.concatenate([p, p + 1], -1), np.repeat(p[:, None], 6, 1), np.ones(len(p)))
        boxes, keypoints, scores = unturn_faces(faces, turn, frame.shape[:2])
        x, y = keypoints[:, 0].round().astype(int).T
        assert np.array_equal(frame[y, x], turned[yy.ravel(), xx.ravel()])
        assert (boxes[:, 2:] - boxes[:, :2] == 1).all() and scores.shape == (len(p),)  # a unit box stays one


def test_a_small_blurred_face_is_read_in_the_sharpened_frame():
    case = make_case("astronaut", **CASES["eye 25 px in 1080p"])
    seq = ImageSequence(degrade(case.image, "blur")[None], colour_space="srgb")
    plain = run_node(TrackFaces, {"enhance": False, "with_iris": False}, images=seq)
    assert plain["failed"].values[0, 0] == 1
    out = run_node(TrackFaces, {"with_iris": False}, images=seq)
    assert out["failed"].values[0, 0] == 0
    err = error_percent(out["landmarks68"].points[0], case.points[MEDIAPIPE_TO_68], case.eye)
    assert err < 10, err


@pytest.mark.parametrize("name", ["coffee", "brick", "rocket"])
def test_a_face_free_photo_stays_failed_with_every_look(name):
    img = np.asarray(getattr(skimage_data, name)(), np.float32) / 255.0
    img = np.repeat(img[..., None], 3, -1) if img.ndim == 2 else img[..., :3]
    frames = np.stack([img] + [degrade(img, kind) for kind in ("dark", "blur", "noise")])
    out = run_node(TrackFaces, {"with_iris": False}, images=ImageSequence(frames, colour_space="srgb"))
    assert out["failed"].values[:, 0].tolist() == [1, 1, 1, 1]
    assert set(out["reasons"].values[:, 0].tolist()) <= {1, 2, 4}
    # a detection the face mesh could not read keeps its best read (`weak_reads`), flagged: no
    # point of it counts (confidence 0, so the fit leaves the frame out); nothing detected: NaN
    assert (out["landmarks468"].confidence == 0).all()
    reasons = out["reasons"].values[:, 0]
    assert (np.isnan(out["landmarks468"].points).all((1, 2)) == (reasons == 1)).all()
    assert ((out["presence"].values[:, 0] == 0) == (reasons == 1)).all()


def test_a_small_face_rolled_90_deg_is_found_in_the_frame_turned_back():
    # at the acceptance check's placement of this case (bench/detect_faces.py: SHIFTS[1]); centred
    # (at 0.4, 0.5) the upright look finds it in the sharpened frame
    kw = dict(CASES["eye 25 px, roll 90, dark, second copy"])
    x, y = kw.pop("at")
    case = make_case("astronaut", **kw, at=(x + 0.013, y + 0.007))
    seq = ImageSequence(case.image[None], colour_space="srgb")
    upright_only = run_node(TrackFaces, {"quarter_turns": False, "with_iris": False}, images=seq)
    assert upright_only["failed"].values[0, 0] == 1
    out = run_node(TrackFaces, {"with_iris": False}, images=seq)
    assert out["failed"].values[0, 0] == 0
    err = error_percent(out["landmarks68"].points[0], case.points[MEDIAPIPE_TO_68], case.eye)
    assert err < 10, err  # the larger face (the second copy sits 2.7 eye distances away)
    assert abs(out["rolls"].values[0, 0] - np.pi / 2) < 0.2  # the crop turned by the face's roll


def test_a_small_blurred_frontal_face_is_read_with_the_amount_6_mask():
    # grace_hopper (matplotlib's frontal portrait) at a 20 px eye distance in 817 x 1024, blurred by
    # 3 px, at the acceptance check's placement (bench/detect_faces.py: SHIFTS[2]); measured 8.2% of
    # the eye distance with the mask at amount 6, 11.2% at amount 3 (TrackFaces 3)
    from nodes.landmarks.face_tracker import track_faces

    kw = dict(CASES["eye 20 px in 817 x 1024"])
    x, y = kw.pop("at")
    case = make_case("grace_hopper", **kw, at=(x - 0.011, y + 0.017))
    frame = degrade(case.image, "blur")[None]
    errors = {}
    for amount in (3.0, 6.0):
        out = track_faces(frame, with_iris=False, sharpen_amount=amount)
        errors[amount] = (np.inf if out.failed[0] else
                          error_percent(out.points[0][MEDIAPIPE_TO_68], case.points[MEDIAPIPE_TO_68], case.eye))
    assert errors[6.0] < 10 <= errors[3.0], errors


def test_a_face_found_sharpened_needs_presence_0_9():
    # skimage's rocket 3 stops dark: at amount 6 the sharpened frame reads a face where there is
    # none at presence 0.67 (measured), which presence 0.5 would confirm
    from nodes.landmarks.face_tracker import track_faces

    img = np.ascontiguousarray(degrade(np.asarray(skimage_data.rocket(), np.float32) / 255.0, "dark"))[None]
    assert not track_faces(img, with_iris=False, sharpened_min_presence=0.5).failed[0]  # the control
    out = track_faces(img, with_iris=False)
    assert out.failed[0] and out.reasons[0] in (2, 4)  # kept as a weak read (`weak_reads`), flagged
    assert np.isnan(track_faces(img, with_iris=False, weak_reads=False).points).all()
