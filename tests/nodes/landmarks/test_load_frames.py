"""landmarks.LoadFrames reads exactly what io.LoadImageSequence and io.LoadVideo read, and names itself in errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import NodeError, run_node
from nodes.io.image import LoadImageSequence, write_image
from nodes.io.video import LoadVideo
from nodes.landmarks import LoadFrames


def _same(a, b) -> None:
    assert a.channels == b.channels and a.colour_space == b.colour_space and a.fps == b.fps
    assert a.pixels.dtype == b.pixels.dtype == np.float32
    np.testing.assert_array_equal(a.pixels, b.pixels)


@pytest.fixture
def frames() -> np.ndarray:
    return np.random.default_rng(0).random((3, 12, 16, 3)).astype(np.float32)


@pytest.mark.parametrize("suffix, bit_depth, space", [("png", "uint8", "srgb"), ("exr", "half", "linear")])
def test_image_patterns_read_as_io_load_image_sequence(tmp_path: Path, frames, suffix, bit_depth, space):
    for i, frame in enumerate(frames):
        write_image(tmp_path / f"plate.{i + 5:04d}.{suffix}", frame, ["R", "G", "B"], bit_depth)
    pattern = str(tmp_path / f"plate.%04d.{suffix}")
    for params in ({"path": pattern}, {"path": pattern, "first_frame": 6, "fps": 24.0}):
        got = run_node(LoadFrames, params)["images"]
        _same(got, run_node(LoadImageSequence, params)["images"])
        assert got.colour_space == space and len(got.pixels) == 3 - (params.get("first_frame", 5) - 5)


def test_video_reads_as_io_load_video(tmp_path: Path, frames):
    av = pytest.importorskip("av")
    video = tmp_path / "plate.mp4"
    with av.open(str(video), "w") as container:
        stream = container.add_stream("libx264", rate=25)
        stream.width, stream.height, stream.pix_fmt = 16, 12, "yuv420p"
        for frame in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray((frame * 255).round().astype(np.uint8),
                                                                   format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
    got = run_node(LoadFrames, {"path": str(video), "fps": 12.0})["images"]
    _same(got, run_node(LoadVideo, {"path": str(video), "fps": 12.0})["images"])
    assert got.fps == 25.0 and got.colour_space == "srgb" and got.pixels.shape == (3, 12, 16, 3)


@pytest.mark.parametrize("name, found", [("missing.%04d.png", "found none"), ("missing.mp4", "found it missing")])
def test_a_missing_source_is_bad_input_of_load_frames(tmp_path: Path, name, found):
    with pytest.raises(NodeError) as err:
        run_node(LoadFrames, {"path": str(tmp_path / name)})
    assert err.value.node_type == "landmarks.LoadFrames" and err.value.port == "path" and err.value.bad_input
    assert found in str(err.value)
