"""Landmark nodes: ports, failure handling, the NPZ saver, overlays, error text."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import ImageSequence, Landmarks2D, NodeError, ParamSequence, run_node
from nodes.landmarks import DetectFaces, FaceLandmarks, LandmarkOverlays, SaveLandmarks
from nodes.landmarks.nodes import draw_overlay

pytest.importorskip("torch")
pytest.importorskip("tflite")
data = pytest.importorskip("skimage.data")


@pytest.fixture(scope="module")
def images() -> ImageSequence:
    face = data.astronaut()[:384, :384].astype(np.float32) / 255.0
    return ImageSequence(np.stack([face, np.full_like(face, 0.5)]), colour_space="srgb")


def test_detect_and_landmark_nodes_mark_the_failed_frame(images):
    det = run_node(DetectFaces, images=images)
    assert det["boxes"].names == ["x0", "y0", "x1", "y1"]
    assert det["failed"].values[:, 0].tolist() == [0.0, 1.0]
    assert np.isnan(det["boxes"].values[1]).all() and det["scores"].values[1, 0] == 0
    out = run_node(FaceLandmarks, images=images, boxes=det["boxes"])
    assert out["landmarks468"].points.shape == (2, 468, 2) and out["landmarks68"].points.shape == (2, 68, 2)
    assert np.isnan(out["landmarks68"].points[1]).all() and (out["landmarks68"].confidence[1] == 0).all()
    assert out["presence"].values[0, 0] > 0.9
    # a linear-light copy of the same frames gives the same points (converted back to sRGB)
    lin = run_node(FaceLandmarks, images=images.to_linear(), boxes=det["boxes"])
    np.testing.assert_allclose(lin["landmarks68"].points[0], out["landmarks68"].points[0], atol=0.05)


def test_save_landmarks_writes_the_npz(tmp_path, images):
    f = 2
    boxes = ParamSequence(np.ones((f, 4), np.float32), ["x0", "y0", "x1", "y1"])
    l68 = Landmarks2D(np.zeros((f, 68, 2), np.float32), np.ones((f, 68), np.float32))
    l468 = Landmarks2D(np.zeros((f, 468, 2), np.float32), np.ones((f, 468), np.float32))
    flag = ParamSequence(np.array([[0.0], [1.0]], np.float32), ["failed"])
    pres = ParamSequence(np.array([[1.0], [0.0]], np.float32), ["presence"])
    path = tmp_path / "sub" / "marks.npz"
    out = run_node(SaveLandmarks, {"path": str(path)}, boxes=boxes, landmarks68=l68, landmarks468=l468,
                   presence=pres, failed=flag)
    assert out["files"].paths == [str(path)]
    with np.load(path) as saved:
        assert saved["failed"].tolist() == [False, True] and saved["presence"].tolist() == [1.0, 0.0]
        assert sorted(saved.files) == ["boxes", "failed", "frames", "landmarks468", "landmarks68", "presence"]
    with pytest.raises(NodeError, match=r"'landmarks68'.*expected shape \(F, 68, 2\)"):
        run_node(SaveLandmarks, {"path": str(path)}, boxes=boxes, landmarks68=l468, landmarks468=l468,
                 presence=pres, failed=flag)
    with pytest.raises(NodeError, match=r"ending in \.npz"):
        run_node(SaveLandmarks, {"path": str(tmp_path / "x.json")}, boxes=boxes, landmarks68=l68,
                 landmarks468=l468, presence=pres, failed=flag)


def test_face_landmarks_error_names_the_boxes_port(images):
    with pytest.raises(NodeError, match=r"boxes.*expected 4 columns"):
        run_node(FaceLandmarks, images=images, boxes=ParamSequence(np.zeros((2, 3), np.float32), ["a", "b", "c"]))


def test_overlays_and_draw_overlay(tmp_path, images):
    img = draw_overlay(np.zeros((10, 10, 3)), np.array([1.0, 1, 8, 8]), [(np.array([[5.0, 5], [np.nan, 1]]),
                                                                          (1.0, 0.0, 0.0))])
    assert img[1, 4].tolist() == [1, 1, 0] and img[5, 5].tolist() == [1, 0, 0] and img[5, 6].tolist() == [1, 0, 0]
    boxes = ParamSequence(np.array([[10, 10, 100, 100], [np.nan] * 4], np.float32), ["x0", "y0", "x1", "y1"])
    l68 = Landmarks2D(np.full((2, 68, 2), 50, np.float32), np.ones((2, 68), np.float32))
    l468 = Landmarks2D(np.full((2, 468, 2), 60, np.float32), np.ones((2, 468), np.float32))
    out = run_node(LandmarkOverlays, {"folder": str(tmp_path)}, images=images, boxes=boxes, landmarks68=l68,
                   landmarks468=l468)
    assert [p.rsplit("/", 1)[-1] for p in out["files"].paths] == ["overlay.0000.png", "overlay.0001.png"]


@pytest.mark.parametrize("channels, colour_space", [(["R", "G", "B"], "srgb"), (["A", "R", "G", "B", "Z"], "srgb"),
                                                    (["R", "A", "G", "B"], "srgb"), (["Y"], "srgb"),
                                                    (["R", "G", "B"], "linear")])
def test_network_images_are_the_colour_channels_in_srgb_clipped(channels, colour_space):
    from nodes.landmarks.nodes import network_images
    from nodegraph.images import linear_to_srgb

    rng = np.random.default_rng(3)
    pixels = (rng.random((2, 5, 7, len(channels))) * 1.4 - 0.2).astype(np.float64)
    got = network_images(ImageSequence(pixels, channels=channels, colour_space=colour_space))
    colour = [i for i, name in enumerate(channels) if name not in ("A", "Z")]
    want = pixels.astype(np.float32)[..., colour]
    if colour_space == "linear":
        want = linear_to_srgb(want)
    want = np.repeat(want, 3, -1) if len(colour) == 1 else want
    assert got.dtype == np.float32 and got.flags.c_contiguous and got.shape == (2, 5, 7, 3)
    np.testing.assert_array_equal(got, np.clip(want, 0.0, 1.0))


@pytest.mark.parametrize("channels", [["R", "G", "B"], ["A", "R", "G", "B", "Z"], ["Y"]])
def test_network_images_in_range_are_not_copied(channels):
    """Frames already in [0, 1] (8-bit files, video) are passed as a view of the input, not a
    whole-shot copy (TrackFaces receives every frame); the values are the same as clipped."""
    from nodes.landmarks.nodes import network_images

    rng = np.random.default_rng(4)
    pixels = rng.random((3, 6, 5, len(channels))).astype(np.float32)
    seq = ImageSequence(pixels, channels=channels, colour_space="srgb")
    got = network_images(seq)
    colour = [i for i, name in enumerate(channels) if name not in ("A", "Z")]
    want = np.repeat(pixels[..., colour], 3, -1) if len(colour) == 1 else pixels[..., colour]
    np.testing.assert_array_equal(got, want)
    assert np.shares_memory(got, pixels) == (len(colour) == 3)  # grey is replicated: a new array
    pixels[0, 0, 0, colour[0]] = 1.5  # one value out of range: clipped into a copy
    clipped = network_images(ImageSequence(pixels, channels=channels, colour_space="srgb"))
    assert not np.shares_memory(clipped, pixels) and float(clipped.max()) == 1.0
