"""Tests of nodes.io.video (PyAV decoding, chunked by keyframe seeks)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

av = pytest.importorskip("av")

import nodes.io.video as video  # noqa: E402
from nodegraph import InputError, NodeError, run_node  # noqa: E402
from nodes.io.video import LoadVideo, video_index  # noqa: E402

H, W, N = 48, 64, 30


def has_encoder(name: str) -> bool:
    try:
        av.codec.Codec(name, "w")
    except ValueError:  # av.codec.codec.UnknownCodecError is a ValueError
        return False
    return True


def make_frames(count: int = N, seed: int = 0) -> np.ndarray:
    """(count, H, W, 3) uint8 frames: a moving bar over a ramp with noise."""
    rng = np.random.default_rng(seed)
    frames = np.zeros((count, H, W, 3), np.uint8)
    frames[..., 0] = (np.arange(count) * 7 % 256)[:, None, None]
    frames[np.arange(count), :, np.arange(count) % W, 1] = 255
    frames[..., 2] = np.linspace(0, 255, W, dtype=np.uint8)[None, None, :]
    return frames + rng.integers(0, 30, frames.shape, dtype=np.uint8)


def write_video(path, frames: np.ndarray, codec: str, pix_fmt: str, options=None, gop=None,
                rate: int = 25) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=rate, options=options or {})
        stream.width, stream.height, stream.pix_fmt = W, H, pix_fmt
        if gop:
            stream.codec_context.gop_size = gop
        for image in frames:
            for packet in stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)


def lossy_video(tmp_path, frames):
    """A video with B-frames and short (open, when x264 exists) GOPs, so seeks matter."""
    if has_encoder("libx264"):
        path = tmp_path / "clip.mov"
        write_video(path, frames, "libx264", "yuv420p", {
            "x264-params": "bframes=3:b-adapt=0:keyint=7:min-keyint=7:scenecut=0:open-gop=1",
            "crf": "12"})
    elif has_encoder("mpeg4"):
        path = tmp_path / "clip.mp4"
        write_video(path, frames, "mpeg4", "yuv420p", {"bf": "2"}, gop=6)
    else:
        pytest.skip("neither libx264 nor mpeg4 encoders are available")
    return str(path)


def load(path: str, frames: range | None = None):
    return run_node(LoadVideo, {"path": path}, frames=frames)["images"]


@pytest.mark.skipif(not has_encoder("ffv1"), reason="ffv1 encoder not available")
def test_lossless_round_trip_and_stream_metadata(tmp_path):
    frames = make_frames()
    path = str(tmp_path / "clip.mkv")  # Matroska stores no frame count: it is counted
    write_video(path, frames, "ffv1", "bgr0", gop=5, rate=24)
    assert LoadVideo({"path": path}).frame_count() == N
    out = load(path)
    assert out.pixels.shape == (N, H, W, 3) and out.pixels.dtype == np.float32
    assert out.channels == ["R", "G", "B"] and out.fps == 24.0 and out.colour_space == "srgb"
    np.testing.assert_array_equal(out.pixels, frames.astype(np.float32) / np.float32(255))
    for chunk in [range(3, 9), range(29, 30)]:
        np.testing.assert_array_equal(load(path, chunk).pixels, out.pixels[chunk.start:chunk.stop])


def test_chunks_equal_full_decode_with_b_frames(tmp_path):
    frames = make_frames()
    path = lossy_video(tmp_path, frames)
    full = load(path)
    assert full.num_frames == N
    assert np.abs(full.pixels - frames / 255.0).mean() < 0.05  # it is the same picture
    for chunk in [range(0, 3), range(2, 5), range(5, 7), range(6, 9), range(13, 21), range(27, 30)]:
        part = load(path, chunk)
        np.testing.assert_array_equal(part.pixels, full.pixels[chunk.start:chunk.stop])


def test_late_chunk_seeks_instead_of_decoding_from_start(tmp_path, monkeypatch):
    path = lossy_video(tmp_path, make_frames())
    index = video_index(path)
    assert len(index.key_pts) > 1, "the test video needs several keyframes"
    seeks = []
    decode = video._decode

    def spy(path, seek_ts, wanted, out, by_order=None):
        seeks.append(seek_ts)
        return decode(path, seek_ts, wanted, out, by_order)

    monkeypatch.setattr(video, "_decode", spy)
    late = load(path, range(24, 27))
    assert seeks and seeks[0] is not None and seeks[0] > index.pts[0]
    monkeypatch.setattr(video, "_decode", decode)
    np.testing.assert_array_equal(late.pixels, load(path).pixels[24:27])


def test_input_files_is_the_video_for_any_chunk(tmp_path):
    path = lossy_video(tmp_path, make_frames(8))
    node = LoadVideo({"path": path})
    assert node.input_files() == node.input_files(range(2, 5)) == node.input_files(range(0)) \
        == [Path(path)]
    assert LoadVideo({"path": str(tmp_path / "none.mp4")}).input_files(range(0, 3)) == []


# -- bad input -------------------------------------------------------------------------------

def test_error_missing_file(tmp_path):
    path = str(tmp_path / "none.mp4")
    with pytest.raises(InputError, match="found it missing"):
        LoadVideo({"path": path}).frame_count()
    with pytest.raises(NodeError, match=r"file '.*none\.mp4': expected a video file, found it "
                                        r"missing") as err:
        load(path, range(0, 1))
    assert err.value.bad_input and err.value.port == "path"


def test_error_unreadable_file(tmp_path):
    path = tmp_path / "junk.mp4"
    path.write_bytes(b"not a video at all" * 10)
    with pytest.raises(NodeError, match=r"file '.*junk\.mp4': expected a readable video"):
        load(str(path), range(0, 1))


def test_error_frames_beyond_the_video(tmp_path):
    path = lossy_video(tmp_path, make_frames(8))
    with pytest.raises(NodeError, match=rf"frame 9 \(file '.*clip\..*'\): expected a frame in "
                                        r"0\.\.7, the video has 8 frame"):
        load(path, range(6, 10))
