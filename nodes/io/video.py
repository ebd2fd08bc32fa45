"""Video files -> RGB frames through PyAV (FFmpeg).

Frame `f` of a video is the frame with the f-th smallest presentation timestamp (pts) among
the first video stream's packets (packets FFmpeg marks as discarded, e.g. cut by an edit
list, are not frames). A chunk seeks to the last keyframe at or before its first frame and
decodes forward, keeping the frames whose pts it wants; decoding from a keyframe is exact, so
a chunk equals the same frames of a full decode bit for bit. Should a seek land after a
wanted frame, the chunk retries from the keyframe before, and finally from the start.
Streams without timestamps are decoded from the start and counted in decoder output order.

Pixels are RGB float32 in [0, 1]: 8-bit formats converted through `rgb24` (/255), deeper
ones through `rgb48le` (/65535), both with FFmpeg's swscale. They are display-encoded, as
video stores them: the sequence's `colour_space` is "srgb" (the stream's own transfer curve,
e.g. BT.709, is not converted).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from nodegraph import FRAMEWISE, ImageSequence, InputError, Node, NodeParams, Out, Param

__all__ = ["VideoIndex", "video_index", "frame_to_rgb", "read_video_frames", "LoadVideo"]


class VideoIndex(NamedTuple):
    """What a demux pass (no decoding) tells about the first video stream.

    Attributes:
        pts: (F,) int64 sorted presentation timestamps of the frames, or None when the stream
            lacks timestamps or repeats them.
        seek_ts: (K,) int64, for each keyframe (sorted by pts) a timestamp at or before both
            its pts and dts, to seek to it with any demuxer; None with `pts`.
        key_pts: (K,) int64 keyframe presentation timestamps, sorted; None with `pts`.
        count: number of frames.
        fps: frames per second from the stream, or None when it has none.
    """

    pts: np.ndarray | None
    seek_ts: np.ndarray | None
    key_pts: np.ndarray | None
    count: int
    fps: float | None


def _open(path: str):
    import av

    if not os.path.isfile(path):
        raise InputError("path", f"file '{path}': expected a video file, found it missing")
    try:
        container = av.open(path)
    except (av.FFmpegError, OSError) as err:
        raise InputError("path", f"file '{path}': expected a readable video, found an unreadable "
                                 f"file ({err})") from err
    if not container.streams.video:
        container.close()
        raise InputError("path", f"file '{path}': expected a video stream, found none")
    return container


def video_index(path: str) -> VideoIndex:
    """Demux (without decoding) the first video stream of `path`: timestamps and keyframes.

    Raises:
        InputError: missing or unreadable file, no video stream.
    """
    import av

    container = _open(path)
    try:
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.guessed_rate
        fps = float(rate) if rate else None
        pts, keys, seeks, no_pts = [], [], [], 0
        for packet in container.demux(stream):
            if packet.size == 0 or packet.is_discard:
                continue
            if packet.pts is None:
                no_pts += 1
                continue
            pts.append(packet.pts)
            if packet.is_keyframe:
                keys.append(packet.pts)
                seeks.append(min(packet.pts, packet.dts if packet.dts is not None else packet.pts))
    except av.FFmpegError as err:
        raise InputError("path", f"file '{path}': expected a readable video, found a damaged "
                                 f"stream ({err})") from err
    finally:
        container.close()
    if no_pts or len(set(pts)) != len(pts) or not keys:
        return VideoIndex(None, None, None, _count_decoded(path), fps)
    order = np.argsort(keys)
    return VideoIndex(np.sort(np.asarray(pts, np.int64)), np.asarray(seeks, np.int64)[order],
                      np.asarray(keys, np.int64)[order], len(pts), fps)


def _count_decoded(path: str) -> int:
    """Count frames by decoding everything (for streams without usable timestamps)."""
    import av

    container = _open(path)
    try:
        return sum(1 for _ in container.decode(container.streams.video[0]))
    except av.FFmpegError as err:
        raise InputError("path", f"file '{path}': expected a readable video, found a damaged "
                                 f"stream ({err})") from err
    finally:
        container.close()


def frame_to_rgb(frame) -> np.ndarray:
    """Convert a decoded PyAV VideoFrame to (H, W, 3) float32 RGB in [0, 1]."""
    deep = max(c.bits for c in frame.format.components) > 8
    if deep:
        return frame.to_ndarray(format="rgb48le").astype(np.float32) / np.float32(65535)
    return frame.to_ndarray(format="rgb24").astype(np.float32) / np.float32(255)


def _decode(path: str, seek_ts: int | None, wanted: dict[int, int], out: np.ndarray,
            by_order: range | None = None) -> set[int]:
    """Decode from `seek_ts` (None = the start) into `out`; return the slots filled.

    `wanted` maps pts -> slot; with `by_order`, frames are taken by decoder output position.
    """
    container = _open(path)
    filled: set[int] = set()
    try:
        stream = container.streams.video[0]
        if seek_ts is not None:
            container.seek(int(seek_ts), stream=stream, backward=True, any_frame=False)
        for position, frame in enumerate(container.decode(stream)):
            if by_order is not None:
                if position >= by_order.stop:
                    break
                slot = position - by_order.start if position >= by_order.start else None
            else:
                slot = wanted.get(frame.pts)
            if slot is None or slot in filled:
                continue
            rgb = frame_to_rgb(frame)
            if rgb.shape != out.shape[1:]:
                raise InputError("path", f"frame {slot} of the chunk (file '{path}'): expected "
                                         f"{out.shape[2]}x{out.shape[1]} pixels as the stream, "
                                         f"found {rgb.shape[1]}x{rgb.shape[0]}")
            out[slot] = rgb
            filled.add(slot)
            if len(filled) == len(out):
                break
    finally:
        container.close()
    return filled


def read_video_frames(path: str, frames: range, index: VideoIndex | None = None) -> np.ndarray:
    """Decode frames `frames` (0-based) of the first video stream, decoding as little as possible.

    Args:
        path: a video file FFmpeg reads (.mp4, .mov, .mkv, ...).
        frames: frames to return.
        index: `video_index(path)` when already computed.
    Returns:
        (len(frames), H, W, 3) float32 RGB in [0, 1].
    Raises:
        InputError: naming file and frame: missing/unreadable file, frames outside the video,
            a frame that cannot be decoded.
    """
    import av

    index = index or video_index(path)
    if len(frames) and (frames.start < 0 or frames[-1] >= index.count):
        bad = frames.start if frames.start < 0 else frames[-1]
        raise InputError("path", f"frame {bad} (file '{path}'): expected a frame in "
                                 f"0..{index.count - 1}, the video has {index.count} frame(s)")
    container = _open(path)
    stream = container.streams.video[0]
    width, height = stream.codec_context.width, stream.codec_context.height
    container.close()
    out = np.empty((len(frames), height, width, 3), np.float32)
    if not len(frames):
        return out
    try:
        if index.pts is None:
            filled = _decode(path, None, {}, out, by_order=frames)
        else:
            wanted = {int(p): i for i, p in enumerate(index.pts[frames.start:frames.stop])}
            first = index.pts[frames.start]
            candidates = np.flatnonzero(index.key_pts <= first)[::-1]
            targets = [int(index.seek_ts[k]) for k in candidates if k > 0] + [None]
            for target in targets:
                filled = _decode(path, target, wanted, out)
                if len(filled) == len(out):
                    break
    except av.FFmpegError as err:
        raise InputError("path", f"frames {frames.start}:{frames.stop} (file '{path}'): expected "
                                 f"decodable frames, found a damaged stream ({err})") from err
    if len(filled) != len(out):
        missing = min(set(range(len(out))) - filled) + frames.start
        raise InputError("path", f"frame {missing} (file '{path}'): expected a decodable frame, "
                                 "found none (damaged or truncated stream)")
    return out


class LoadVideo(Node):
    """Decode a video file's first video stream to RGB float32 frames."""

    type_name = "io.LoadVideo"
    version = 2  # 2: colour_space "srgb"
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Video file (.mp4, .mov, .mkv, ...).")
        fps: float = Param(30.0, gt=0, description="Frames per second used when the stream "
                           "carries none (1/s).")

    images = Out(ImageSequence, doc="RGB pixels (F, H, W, 3) float32 in [0, 1], colour_space "
                 "srgb.")

    def frame_count(self) -> int | None:
        return video_index(self.params.path).count

    def input_files(self, frames: range | None = None) -> list[Path]:
        """The video file, whatever `frames` (every chunk reads the one file)."""
        return [Path(self.params.path)] if os.path.isfile(self.params.path) else []

    def run(self) -> dict[str, ImageSequence]:
        index = video_index(self.params.path)
        pixels = read_video_frames(self.params.path, self.frames, index)
        return {"images": ImageSequence(pixels=pixels, channels=["R", "G", "B"],
                                        fps=index.fps or self.params.fps, colour_space="srgb")}
