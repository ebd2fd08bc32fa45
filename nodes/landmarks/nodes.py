"""Landmark nodes: frames from images or video, face detection, face landmarks (468 and 68
points), the NPZ saver and overlay images.

- `landmarks.LoadFrames`: an image pattern or a video file (by extension) -> images.
- `landmarks.DetectFaces`: images -> square crop boxes (x0 y0 x1 y1, pixels; NaN where no
  face), detector scores, failure flags (BlazeFace, `nodes.landmarks.network`).
- `landmarks.FaceLandmarks`: images + boxes -> 468 face-mesh points, the 68 Multi-PIE points
  (`nodes.landmarks.correspondence`) and face presence. A heatmap network (3D-FAN style,
  a `TorchModel`) may replace the face mesh for the 68 points (`nodes.landmarks.heatmap`).
- `landmarks.SaveLandmarks`: one NPZ with boxes [F, 4], landmarks68 [F, 68, 2],
  landmarks468 [F, 468, 2], presence [F], failed [F].
- `landmarks.LandmarkOverlays`: one PNG per frame with the box and the points drawn.

Pixel coordinates: origin top-left, x right, y down, pixel centres at integers. Frames where
detection failed have NaN boxes and points and confidence 0. Torch is imported inside
`run()` (see tests/test_startup.py).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Files, ImageSequence, In, InputError, Landmarks2D, Node, NodeParams,
                       Out, Param, ParamSequence, TorchModel)
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic

from .correspondence import MEDIAPIPE_TO_68

__all__ = ["VIDEO_EXTENSIONS", "LoadFrames", "DetectFaces", "FaceLandmarks", "SaveLandmarks",
           "LandmarkOverlays", "draw_overlay"]

VIDEO_EXTENSIONS = (".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg")
"""Extensions `landmarks.LoadFrames` reads as video; anything else is an image pattern."""

BOX_NAMES = ["x0", "y0", "x1", "y1"]


def _is_video(path: str) -> bool:
    return path.lower().endswith(VIDEO_EXTENSIONS)


def _network_images(images: ImageSequence, where: str = "images") -> np.ndarray:
    """(F, H, W, 3) sRGB-encoded RGB in [0, 1] for the networks (grey is replicated)."""
    idx = images.colour_channels()
    if not idx:
        raise InputError(where, f"expected RGB or grey images, found channels {images.channels}")
    srgb = images.to_srgb().pixels
    pixels = srgb[..., idx[:3]] if len(idx) >= 3 else np.repeat(srgb[..., idx[:1]], 3, -1)
    return np.ascontiguousarray(np.clip(pixels, 0.0, 1.0), dtype=np.float32)


class LoadFrames(Node):
    """Read frames from a numbered image pattern or a video file (chosen by the extension)."""

    type_name = "landmarks.LoadFrames"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Image pattern (plate.%04d.png, "
                          "cam0.####.exr) or video file (" + ", ".join(VIDEO_EXTENSIONS) + ").")
        first_frame: int | None = Param(None, description="Images: number of the file of frame 0; "
                                        "None = the lowest found. Ignored for video.")
        fps: float = Param(30.0, gt=0, description="Frames per second when the source states none.")

    images = Out(ImageSequence, doc="(F, H, W, C) float32; video and integer files 'srgb', float files 'linear'.")

    def frame_count(self) -> int | None:
        p = self.params
        if _is_video(p.path):
            from ..io.video import video_index

            return video_index(p.path).count
        from ..io.image import LoadImageSequence

        return LoadImageSequence(path=p.path, first_frame=p.first_frame, fps=p.fps).frame_count()

    def input_files(self, frames: range | None = None) -> list[Path]:
        p = self.params
        if _is_video(p.path):
            return [Path(p.path)] if os.path.isfile(p.path) else []
        from ..io.image import image_frame_files

        return image_frame_files(p.path, frames, p.first_frame)

    def run(self) -> dict[str, ImageSequence]:
        p = self.params
        if _is_video(p.path):
            from ..io.video import read_video_frames, video_index

            index = video_index(p.path)
            pixels = read_video_frames(p.path, self.frames, index)
            return {"images": ImageSequence(pixels, ["R", "G", "B"], fps=index.fps or p.fps, colour_space="srgb")}
        from ..io.image import load_image_sequence

        return {"images": load_image_sequence(p.path, self.frames, first_frame=p.first_frame, fps=p.fps)}


class DetectFaces(Node):
    """Detect the best face per frame (BlazeFace) and give the square crop box of the face mesh."""

    type_name = "landmarks.DetectFaces"
    version = 1
    kind = FRAMEWISE
    resources = {"gpu": 1}

    class Params(NodeParams):
        min_score: float = Param(0.5, ge=0, le=1, description="Detections below this score are dropped.")
        iou: float = Param(0.3, gt=0, le=1, description="Overlap (IoU) of the weighted non-maximum suppression.")
        box_scale: float = Param(1.5, gt=0, description="Crop side over the longer side of the face box.")
        batch: int = Param(8, ge=1, description="Frames per network call.", affects_output=False)

    images = In(ImageSequence, doc="RGB frames (converted to sRGB for the network).")
    boxes = Out(ParamSequence, doc="x0 y0 x1 y1: square crop box, pixels (NaN where no face).")
    scores = Out(ParamSequence, doc="score: detector confidence in [0, 1] (0 where no face).")
    failed = Out(ParamSequence, doc="failed: 1 where no face was found, else 0.")

    def run(self, images: ImageSequence) -> dict[str, ParamSequence]:
        import torch

        from .network import detect_faces, load_face_detector

        p = self.params
        pixels = _network_images(images)
        detector = load_face_detector(self.device)
        boxes, scores, found = [], [], []
        for start in range(0, len(pixels), p.batch):
            batch = torch.as_tensor(pixels[start:start + p.batch], device=self.device)
            det = detect_faces(batch, detector, min_score=p.min_score, iou=p.iou, scale=p.box_scale)
            boxes.append(det.boxes)
            scores.append(det.scores)
            found.append(det.found)
            self.progress(min(start + p.batch, len(pixels)) / max(len(pixels), 1), "detecting faces")
        found_all = np.concatenate(found)
        return {"boxes": ParamSequence(np.concatenate(boxes).astype(np.float32), list(BOX_NAMES)),
                "scores": ParamSequence(np.concatenate(scores).astype(np.float32)[:, None], ["score"]),
                "failed": ParamSequence((~found_all).astype(np.float32)[:, None], ["failed"])}


class FaceLandmarks(Node):
    """Face landmarks in each frame's crop box: 468 face-mesh points, the 68 Multi-PIE points, presence."""

    type_name = "landmarks.FaceLandmarks"
    version = 1
    kind = FRAMEWISE
    resources = {"gpu": 1}

    class Params(NodeParams):
        heatmap_input_size: int = Param(256, ge=8, description="Crop side of a connected heatmap network "
                                        "(3D-FAN: 256).")
        beta: float = Param(50.0, gt=0, description="Soft-argmax inverse temperature of the heatmap head.")
        batch: int = Param(8, ge=1, description="Frames per network call.", affects_output=False)

    images = In(ImageSequence, doc="RGB frames (converted to sRGB for the network).")
    boxes = In(ParamSequence, doc="x0 y0 x1 y1 crop boxes, pixels (landmarks.DetectFaces).")
    heatmap_model = In(TorchModel, optional=True, doc="A heatmap network (B, 3, S, S) -> (B, 68, h, w); "
                       "replaces the face mesh for landmarks68.")
    landmarks468 = Out(Landmarks2D, doc="(F, 468, 2) face-mesh points, pixels; confidence = presence.")
    landmarks68 = Out(Landmarks2D, doc="(F, 68, 2) Multi-PIE points, pixels; confidence = presence.")
    presence = Out(ParamSequence, doc="presence: face presence in [0, 1] (0 where no box).")

    def run(self, images: ImageSequence, boxes: ParamSequence,
            heatmap_model: TorchModel | None = None) -> dict[str, object]:
        import torch

        from .heatmap import HeatmapLandmarks
        from .network import face_landmarks, load_face_mesh

        p = self.params
        if boxes.values.shape[1] != 4:
            raise InputError("boxes", f"expected 4 columns {BOX_NAMES}, found {boxes.names}")
        pixels = _network_images(images)
        frames = len(pixels)
        mesh = load_face_mesh(self.device)
        heatmap = None
        if heatmap_model is not None:
            heatmap = HeatmapLandmarks(heatmap_model.build(self.device).eval(), p.heatmap_input_size, beta=p.beta)
        pts468 = np.full((frames, 468, 2), np.nan, np.float32)
        pts68 = np.full((frames, 68, 2), np.nan, np.float32)
        presence = np.zeros(frames, np.float32)
        presence68 = np.zeros(frames, np.float32)
        valid = np.flatnonzero(np.isfinite(boxes.values).all(1) & (boxes.values[:, 2] > boxes.values[:, 0]) &
                               (boxes.values[:, 3] > boxes.values[:, 1]))
        with torch.no_grad():
            for start in range(0, len(valid), p.batch):
                sel = valid[start:start + p.batch]
                batch = torch.as_tensor(pixels[sel], device=self.device)
                box = boxes.values[sel].astype(np.float64)
                points, pres = face_landmarks(batch, box, mesh)
                pts468[sel] = points.cpu().numpy()
                presence[sel] = pres.cpu().numpy()
                if heatmap is not None:
                    points68, pres68 = face_landmarks(batch, box, heatmap)
                    if points68.shape[1] != 68:
                        raise InputError("heatmap_model", f"expected 68 heatmaps, found {points68.shape[1]}")
                    pts68[sel] = points68.cpu().numpy()
                    presence68[sel] = pres68.cpu().numpy()
                self.progress(min(start + p.batch, len(valid)) / max(len(valid), 1), "face landmarks")
        if heatmap is None:
            pts68 = pts468[:, MEDIAPIPE_TO_68]
            presence68 = presence
        return {"landmarks468": Landmarks2D(pts468, np.repeat(presence[:, None], 468, 1)),
                "landmarks68": Landmarks2D(pts68, np.repeat(presence68[:, None], 68, 1)),
                "presence": ParamSequence(presence[:, None], ["presence"])}


class SaveLandmarks(Node):
    """Write boxes, landmarks and flags of all frames to one NPZ file (atomically)."""

    type_name = "landmarks.SaveLandmarks"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination .npz file.")

        @field_validator("path")
        @classmethod
        def _npz(cls, value: str) -> str:
            return check_output_suffix(value, (".npz",))

    boxes = In(ParamSequence, doc="x0 y0 x1 y1 crop boxes, pixels.")
    landmarks68 = In(Landmarks2D, doc="(F, 68, 2) pixels.")
    landmarks468 = In(Landmarks2D, doc="(F, 468, 2) pixels.")
    presence = In(ParamSequence, doc="presence per frame.")
    failed = In(ParamSequence, doc="failed: 1 where no face was found.")
    files = Out(Files, doc="The NPZ written and its sha256.")

    def run(self, boxes: ParamSequence, landmarks68: Landmarks2D, landmarks468: Landmarks2D,
            presence: ParamSequence, failed: ParamSequence) -> dict[str, Files]:
        path = self.params.path
        if not path.lower().endswith(".npz"):  # before any work: the write checks it too
            raise InputError("path", f"expected a file name ending in .npz, found '{path}'")
        for port, value, shape in (("boxes", boxes.values, (4,)), ("landmarks68", landmarks68.points, (68, 2)),
                                   ("landmarks468", landmarks468.points, (468, 2)),
                                   ("presence", presence.values, (1,)), ("failed", failed.values, (1,))):
            if tuple(value.shape[1:]) != shape:
                raise InputError(port, f"expected shape (F, {', '.join(map(str, shape))}), found {value.shape}")
        arrays = {"boxes": boxes.values.astype(np.float32),
                  "landmarks68": landmarks68.points.astype(np.float32),
                  "landmarks468": landmarks468.points.astype(np.float32),
                  "presence": presence.values[:, 0].astype(np.float32),
                  "failed": failed.values[:, 0] > 0.5,
                  "frames": np.arange(self.frames.start, self.frames.stop, dtype=np.int64)}
        write_npz_atomic(path, arrays)
        return {"files": files_value([path])}


def draw_overlay(pixels: np.ndarray, box: np.ndarray | None, point_sets: list[tuple[np.ndarray, tuple]],
                 radius: int = 1) -> np.ndarray:
    """Draw a box outline and square dots on an image (vectorized, no drawing library).

    Args:
        pixels: (H, W, 3) float in [0, 1].
        box: (4,) x0 y0 x1 y1 pixels, or None / NaN for none.
        point_sets: [(points (N, 2) pixels, colour (3,))], drawn in order.
        radius: dot half-size, pixels.
    Returns:
        (H, W, 3) a drawn copy.
    """
    out = np.array(pixels, np.float32, order="C")
    h, w = out.shape[:2]
    if box is not None and np.isfinite(box).all():
        x0, y0, x1, y1 = np.round(box).astype(int)
        xs, ys = np.arange(max(x0, 0), min(x1, w - 1) + 1), np.arange(max(y0, 0), min(y1, h - 1) + 1)
        for y in (y0, y1):
            if 0 <= y < h:
                out[y, xs] = (1.0, 1.0, 0.0)
        for x in (x0, x1):
            if 0 <= x < w:
                out[ys, x] = (1.0, 1.0, 0.0)
    offsets = np.arange(-radius, radius + 1)
    for points, colour in point_sets:
        pts = np.round(points[np.isfinite(points).all(1)]).astype(int)
        if not len(pts):
            continue
        xs = (pts[:, None, None, 0] + offsets[None, None, :]).repeat(len(offsets), 1).reshape(-1)
        ys = (pts[:, None, None, 1] + offsets[None, :, None]).repeat(len(offsets), 2).reshape(-1)
        ok = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
        out[ys[ok], xs[ok]] = colour
    return out


class LandmarkOverlays(Node):
    """Write one PNG per frame with the crop box (yellow), 468 points (green) and 68 points (red)."""

    type_name = "landmarks.LandmarkOverlays"
    version = 1
    kind = FRAMEWISE
    writes_files = True

    class Params(NodeParams):
        folder: str = Param(..., output_file=True, description="Folder of overlay.%04d.png files.")

    images = In(ImageSequence, doc="The frames.")
    boxes = In(ParamSequence, doc="x0 y0 x1 y1 crop boxes, pixels.")
    landmarks68 = In(Landmarks2D, doc="(F, 68, 2) pixels.")
    landmarks468 = In(Landmarks2D, doc="(F, 468, 2) pixels.")
    files = Out(Files, doc="The PNGs written by this chunk.")

    def run(self, images: ImageSequence, boxes: ParamSequence, landmarks68: Landmarks2D,
            landmarks468: Landmarks2D) -> dict[str, Files]:
        from ..io.image import write_image

        folder = Path(self.params.folder)
        pixels = _network_images(images)
        written = []
        for i, frame in enumerate(self.frames):
            img = draw_overlay(pixels[i], boxes.values[i], [(landmarks468.points[i], (0.0, 1.0, 0.0)),
                                                             (landmarks68.points[i], (1.0, 0.0, 0.0))])
            path = folder / f"overlay.{frame:04d}.png"
            with atomic_path(path) as tmp:
                write_image(tmp, img, ["R", "G", "B"], "uint8")
            written.append(path)
            self.progress((i + 1) / len(self.frames), f"wrote {path}")
        return {"files": files_value(written)}
