"""fit.FitReport's overlays show the fitted head itself (a shaded render blended over the plate), not
only the two point sets: where the head is the overlay changes, far from it nothing does."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from nodegraph import Camera, ImageSequence, Landmarks2D, ParamSequence, run_node  # noqa: E402
from nodes.fit import FitReport, FittedLandmarks  # noqa: E402
from nodes.fit.output_nodes import projected_landmarks68  # noqa: E402
from nodes.io.face_model import load_face_model  # noqa: E402
from nodes.io.image import read_image  # noqa: E402

SIZE = 512
FACING = np.diag([1.0, -1.0, -1.0])  # the model (y up, z out of the face) facing a camera looking down +z


def _report(tmp_path, blend: float, failed: float = 0.0, confidence: float = 1.0,
            read_by_node: bool = False, shift: float = 0.0) -> np.ndarray:
    model = load_face_model()
    camera = Camera.from_fov(SIZE, SIZE, 30.0)
    k = len(model.expression_names)
    fitted = np.concatenate([FACING.ravel(), [0.0, 0.0, 110.0], np.zeros(k)])[None].astype(np.float32)
    marks = projected_landmarks68(fitted, model, camera).pixels.astype(np.float32)
    lo, hi = marks[0].min(0), marks[0].max(0)
    half, centre = 0.65 * (hi - lo).max(), (lo + hi) / 2
    box = np.concatenate([centre - half, centre + half])[None].astype(np.float32)
    plate = np.full((1, SIZE, SIZE, 3), 0.3, np.float32)
    folder = tmp_path / f"blend{blend}_{failed}_{confidence}_{read_by_node}_{shift}"
    inputs = dict(landmarks=Landmarks2D(marks, np.full((1, 68), confidence, np.float32)),
                  boxes=ParamSequence(box, ["x0", "y0", "x1", "y1"]), camera=camera, model=model,
                  fitted=ParamSequence(fitted, [f"v{i}" for i in range(fitted.shape[1])]),
                  flags=ParamSequence(np.array([[failed]], np.float32), ["failed"]))
    if read_by_node:  # the fitted head's points from fit.FittedLandmarks, as the fit graphs wire them
        read = run_node(FittedLandmarks, **inputs)["landmarks68"]
        inputs["fitted_landmarks"] = Landmarks2D(read.points + np.float32(shift), read.confidence)
    run_node(FitReport, {"folder": str(folder), "blend": blend}, images=ImageSequence(plate, colour_space="srgb"),
             **inputs)
    pixels, _ = read_image(folder / "fit.0000.png")
    return pixels[..., :3], box[0], marks[0]


def test_the_overlay_shows_the_fitted_head_inside_its_box_and_nothing_far_outside(tmp_path):
    shown, box, marks = _report(tmp_path, 0.5)
    points_only, _, _ = _report(tmp_path, 0.0)  # the same overlay without the render: box and points only
    diff = np.abs(shown - points_only).max(-1)
    yy, xx = np.mgrid[:SIZE, :SIZE]
    # the face between the eyes' and mouth's landmarks is covered by the head
    cheeks = (xx > marks[36, 0]) & (xx < marks[45, 0]) & (yy > marks[36, 1]) & (yy < marks[57, 1])
    assert cheeks.sum() > 500
    assert np.mean(diff[cheeks] > 0.02) > 0.8, np.mean(diff[cheeks] > 0.02)
    # the head (with neck and ears) may reach past the landmarks' box, but not a box side further away
    side = box[2] - box[0]
    far = (xx < box[0] - side) | (xx > box[2] + side) | (yy < box[1] - side) | (yy > box[3] + side)
    assert far.sum() > 1000
    assert diff[far].max() == 0.0
    changed = diff > 0.02
    assert changed.sum() > 0.3 * ((box[2] - box[0]) * (box[3] - box[1]))
    # a failed frame shows the plate and the plate's points only: on the face only their dots and lines
    failed, _, _ = _report(tmp_path, 0.5, failed=1.0)
    assert np.mean(np.abs(failed - points_only).max(-1)[cheeks] > 0.02) < 0.2


def test_a_failed_frames_weak_read_is_drawn_grey(tmp_path):
    # landmarks.TrackFaces 8 keeps a failed frame's best read with confidence 0: drawn grey, not green
    read, _, marks = _report(tmp_path, 0.0, failed=1.0, confidence=1.0)
    weak, _, _ = _report(tmp_path, 0.0, failed=1.0, confidence=0.0)
    x, y = np.round(marks[30]).astype(int)  # the nose tip's dot
    assert read[y, x, 1] > 0.9 and read[y, x, 0] < 0.1, read[y, x]
    assert np.allclose(weak[y, x], 0.6, atol=0.01), weak[y, x]


def test_the_points_of_fit_fitted_landmarks_are_drawn_as_the_report_reads_them(tmp_path):
    read_here, _, _ = _report(tmp_path, 0.5)
    given, _, _ = _report(tmp_path, 0.5, read_by_node=True)
    assert np.array_equal(read_here, given)
    failed_here, _, _ = _report(tmp_path, 0.5, failed=1.0)
    failed_given, _, _ = _report(tmp_path, 0.5, failed=1.0, read_by_node=True)
    assert np.array_equal(failed_here, failed_given)
    moved, _, _ = _report(tmp_path, 0.5, read_by_node=True, shift=30.0)  # the given points are the ones drawn
    assert not np.array_equal(read_here, moved)
