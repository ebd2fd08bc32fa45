"""Tests of nodes.io.image (OpenImageIO image sequences)."""

from __future__ import annotations

import hashlib
import os

import numpy as np
import pytest

from nodegraph import ImageSequence, NodeError, run_node
from nodegraph.types import linear_to_srgb, srgb_to_linear
from nodes.io._files import expand_frame_pattern
from nodes.io.image import LoadImageSequence, SaveImageSequence, read_image, write_image


def make_images(frames: int = 4, channels=("R", "G", "B", "A"), seed: int = 0,
                colour_space: str = "srgb") -> ImageSequence:
    rng = np.random.default_rng(seed)
    pixels = rng.random((frames, 6, 7, len(channels))).astype(np.float32)
    return ImageSequence(pixels=pixels, channels=list(channels), fps=25.0,
                         colour_space=colour_space)


def save(images: ImageSequence, path: str, frames: range | None = None, **params):
    return run_node(SaveImageSequence, {"path": path, **params}, images=images, frames=frames)


def load(path: str, frames: range | None = None, **params) -> ImageSequence:
    return run_node(LoadImageSequence, {"path": path, **params}, frames=frames)["images"]


def quantize(pixels: np.ndarray, top: int) -> np.ndarray:
    """Independent reference of integer storage: clip, round to the nearest step, rescale."""
    return (np.round(np.clip(pixels.astype(np.float64), 0, 1) * top) / top).astype(np.float32)


@pytest.mark.parametrize("name, depth, reference", [
    ("img.%04d.exr", "float", lambda p: p),
    ("img.%04d.exr", "half", lambda p: p.astype(np.float16).astype(np.float32)),
    ("img.####.png", "uint8", lambda p: quantize(p, 255)),
    ("img.####.png", "uint16", lambda p: quantize(p, 65535)),
    ("img.{frame:03d}.tif", "uint8", lambda p: quantize(p, 255)),
    ("img.{frame:03d}.tiff", "uint16", lambda p: quantize(p, 65535)),
    ("img.%d.tif", "float", lambda p: p),
])
def test_round_trip_each_format_and_depth(tmp_path, name, depth, reference):
    space = "linear" if depth in ("float", "half") else "srgb"  # the file's own: no conversion
    images = make_images(colour_space=space)
    images.pixels[0, 0, 0, 0] = 1.5  # out of range: clipped by integer formats, kept by float
    path = str(tmp_path / name)
    files = save(images, path, bit_depth=depth, first_frame=1)["files"]
    assert len(files.paths) == 4
    assert files.sha256[2] == hashlib.sha256(open(files.paths[2], "rb").read()).hexdigest()
    back = load(path, fps=25.0)
    assert back.channels == ["R", "G", "B", "A"] and back.pixels.dtype == np.float32
    assert back.colour_space == space
    np.testing.assert_allclose(back.pixels, reference(images.pixels), rtol=0, atol=1e-7)


def test_auto_depth_per_format(tmp_path):
    import OpenImageIO as oiio

    images = make_images(1, ("R", "G", "B"))
    for ext, expected in [("exr", "float"), ("png", "uint8"), ("tif", "uint16"), ("jpg", "uint8")]:
        path = str(tmp_path / f"a.%04d.{ext}")
        save(images, path)
        inp = oiio.ImageInput.open(expand_frame_pattern(path, 0))
        assert str(inp.spec().format) == expected, ext
        inp.close()


def test_jpeg_quality_changes_error(tmp_path):
    y, x = np.mgrid[0:32, 0:48].astype(np.float32)
    smooth = np.stack([x / 47, y / 31, 0.5 + 0.4 * np.sin(x / 6)], -1)[None].repeat(2, 0)
    errors = []
    for quality in (30, 98):
        path = str(tmp_path / f"q{quality}.%04d.jpg")
        save(ImageSequence(pixels=smooth.copy()), path, quality=quality)
        errors.append(np.abs(load(path).pixels - smooth).mean())
    assert errors[1] < errors[0] and errors[1] < 0.01


def test_alpha_is_not_premultiplied(tmp_path):
    images = make_images(1)
    images.pixels[0, :, :, 3] = 0.25
    save(images, str(tmp_path / "a.%04d.png"), bit_depth="uint16")
    back = load(str(tmp_path / "a.%04d.png"))
    np.testing.assert_allclose(back.pixels, quantize(images.pixels, 65535), atol=1e-7)


def test_greyscale_png_has_one_channel(tmp_path):
    images = make_images(2, ("Y",))
    save(images, str(tmp_path / "g.%04d.png"))
    back = load(str(tmp_path / "g.%04d.png"))
    assert back.pixels.shape == (2, 6, 7, 1) and back.channels == ["Y"]


def test_chunked_load_equals_full_load_and_chunked_save(tmp_path):
    images = make_images(6, colour_space="linear")
    path = str(tmp_path / "c.%04d.exr")
    save(images.slice_frames(0, 3), path, range(0, 3))
    save(images.slice_frames(3, 6), path, range(3, 6))
    full = load(path)
    np.testing.assert_array_equal(full.pixels, images.pixels)
    for frames in [range(2, 5), range(5, 6)]:
        np.testing.assert_array_equal(load(path, frames).pixels, full.pixels[frames.start:frames.stop])


# -- bad input -------------------------------------------------------------------------------

def test_error_missing_frame_names_file_and_frame(tmp_path):
    path = str(tmp_path / "m.%04d.png")
    save(make_images(), path, first_frame=10)
    os.remove(expand_frame_pattern(path, 12))
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*m\.0012\.png'\).*missing") as err:
        load(path)
    assert err.value.bad_input and err.value.port == "path"


def test_error_size_differs_from_frame_0(tmp_path):
    path = str(tmp_path / "s.%04d.exr")
    save(make_images(3), path)
    write_image(expand_frame_pattern(path, 2), np.zeros((5, 7, 4), np.float32), list("RGBA"), "float")
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*s\.0002\.exr'\): expected 7x6 pixels "
                                        r".*found 7x5"):
        load(path, range(1, 3))


def test_error_channels_differ_from_frame_0(tmp_path):
    path = str(tmp_path / "s.%04d.exr")
    save(make_images(3), path)
    write_image(expand_frame_pattern(path, 1), np.zeros((6, 7, 3), np.float32), list("RGB"), "float")
    with pytest.raises(NodeError, match=r"frame 1 \(file '.*s\.0001\.exr'\).*channels "
                                        r"\['R', 'G', 'B'\]"):
        load(path)


def test_error_truncated_file_names_file_and_frame(tmp_path):
    path = str(tmp_path / "t.%04d.png")
    save(make_images(3), path)
    file = expand_frame_pattern(path, 1)
    data = open(file, "rb").read()
    open(file, "wb").write(data[:30])
    with pytest.raises(NodeError, match=r"frame 1 \(file '.*t\.0001\.png'\).*unreadable or truncated"):
        load(path)


def test_a_single_image_file_is_a_one_frame_sequence(tmp_path):
    images = make_images(1, channels=("R", "G", "B"))
    save(images, str(tmp_path / "still.%04d.png"))
    single = tmp_path / "photo.png"
    (tmp_path / "still.0000.png").rename(single)
    got = load(str(single))
    assert got.pixels.shape == (1, 6, 7, 3) and got.colour_space == "srgb"
    np.testing.assert_allclose(got.pixels, quantize(images.pixels, 255), atol=1e-6)
    from nodes.landmarks import LoadFrames

    frames = run_node(LoadFrames, {"path": str(single)})["images"]
    np.testing.assert_array_equal(frames.pixels, got.pixels)


def test_error_no_pattern_and_no_files(tmp_path):
    with pytest.raises(NodeError, match="expected a numbered pattern"):
        load(str(tmp_path / "plate.exr"))
    with pytest.raises(NodeError, match="expected files matching"):
        load(str(tmp_path / "plate.%04d.exr"))


def test_error_bad_save_choices(tmp_path):
    with pytest.raises(NodeError, match=r"invalid parameters: 'path': expected a numbered pattern ending in "
                                        r"\.exr, .*found '.*a\.%04d\.bmp'"):  # at validation
        save(make_images(1), str(tmp_path / "a.%04d.bmp"))
    with pytest.raises(NodeError, match=r"'path': expected a numbered pattern such as 'img\.%04d\.exr'"):
        save(make_images(1), str(tmp_path / "a.png"))
    with pytest.raises(NodeError, match=r"'bit_depth'.*\['float', 'half'\] for EXR.*found 'uint8'"):
        save(make_images(1), str(tmp_path / "a.%04d.exr"), bit_depth="uint8")
    with pytest.raises(NodeError, match=r"'images'.*1 or 3 channels for JPEG.*found 4"):
        save(make_images(1), str(tmp_path / "a.%04d.jpg"))
    nan = make_images(2)
    nan.pixels[1, 2, 3, 0] = np.nan
    with pytest.raises(NodeError, match=r"'images'.*frame 1.*NaN"):
        save(nan, str(tmp_path / "n.%04d.png"))
    assert sorted(os.listdir(tmp_path)) == ["n.0000.png"]


# -- colour space ----------------------------------------------------------------------------

@pytest.mark.parametrize("name, depth, space", [
    ("a.%04d.exr", "float", "linear"), ("a.%04d.exr", "half", "linear"),
    ("a.%04d.tif", "float", "linear"), ("a.%04d.tif", "uint16", "srgb"),
    ("a.%04d.tif", "uint8", "srgb"), ("a.%04d.png", "uint8", "srgb"),
    ("a.%04d.png", "uint16", "srgb"), ("a.%04d.jpg", "uint8", "srgb"),
])
def test_loader_sets_colour_space_from_pixel_type(tmp_path, name, depth, space):
    images = make_images(2, ("R", "G", "B"), colour_space=space)
    save(images, str(tmp_path / name), bit_depth=depth)
    assert load(str(tmp_path / name)).colour_space == space


def test_loader_colour_space_param_declares_without_converting(tmp_path):
    images = make_images(2, ("R", "G", "B"))
    save(images, str(tmp_path / "a.%04d.png"), bit_depth="uint16")
    auto = load(str(tmp_path / "a.%04d.png"))
    declared = load(str(tmp_path / "a.%04d.png"), colour_space="linear")
    assert declared.colour_space == "linear"
    np.testing.assert_array_equal(declared.pixels, auto.pixels)


def test_saver_encodes_linear_as_srgb_for_integer_files(tmp_path):
    images = make_images(2, colour_space="linear")
    path = str(tmp_path / "l.%04d.png")
    save(images, path, bit_depth="uint16")
    stored, _ = read_image(expand_frame_pattern(path, 1))
    expected = images.pixels[1].astype(np.float64)
    expected[..., :3] = linear_to_srgb(expected[..., :3])  # alpha is not converted
    np.testing.assert_allclose(stored, quantize(expected.astype(np.float32), 65535), atol=1e-7)
    back = load(path)
    assert back.colour_space == "srgb"
    np.testing.assert_allclose(back.to_linear().pixels, images.pixels, atol=1e-4)


def test_saver_decodes_srgb_to_linear_for_float_files(tmp_path):
    images = make_images(2, ("R", "G", "B", "A"), colour_space="srgb")
    path = str(tmp_path / "s.%04d.exr")
    save(images, path)
    back = load(path)
    assert back.colour_space == "linear"
    np.testing.assert_array_equal(back.pixels[..., :3], srgb_to_linear(images.pixels[..., :3]))
    np.testing.assert_array_equal(back.pixels[..., 3], images.pixels[..., 3])
    np.testing.assert_allclose(back.to_srgb().pixels, images.pixels, atol=2e-6)


def test_saver_colour_space_param_overrides_the_file_space(tmp_path):
    images = make_images(1, ("R", "G", "B"), colour_space="linear")
    path = str(tmp_path / "d.%04d.png")
    save(images, path, bit_depth="uint16", colour_space="linear")  # e.g. a data map
    back = load(path, colour_space="linear")
    np.testing.assert_allclose(back.pixels, quantize(images.pixels, 65535), atol=1e-7)


def test_error_frames_of_float_and_integer_pixels(tmp_path):
    path = str(tmp_path / "m.%04d.tif")
    save(make_images(3, ("R", "G", "B")), path, bit_depth="uint16")
    write_image(expand_frame_pattern(path, 2), np.zeros((6, 7, 3), np.float32), list("RGB"), "float")
    with pytest.raises(NodeError, match=r"frame 2 \(file '.*m\.0002\.tif'\): expected srgb pixels "
                                        r"\(integer\).*found linear \(float\)"):
        load(path)
    assert load(path, colour_space="srgb").pixels.shape == (3, 6, 7, 3)


# -- per-chunk input files -------------------------------------------------------------------

def test_input_files_per_chunk(tmp_path):
    path = str(tmp_path / "f.%04d.png")
    save(make_images(6, ("R", "G", "B")), path, first_frame=10)
    node = LoadImageSequence({"path": path})
    names = lambda files: [os.path.basename(f) for f in files]  # noqa: E731
    assert names(node.input_files()) == [f"f.{n:04d}.png" for n in range(10, 16)]
    assert names(node.input_files(range(2, 4))) == ["f.0012.png", "f.0013.png"]
    assert names(node.input_files(range(5, 8))) == ["f.0015.png"]  # beyond the files: none
    pinned = LoadImageSequence({"path": path, "first_frame": 12})
    assert names(pinned.input_files(range(0, 2))) == ["f.0012.png", "f.0013.png"]
    assert node.input_files(range(0)) == []
