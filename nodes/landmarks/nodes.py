"""Landmark nodes: frames from images or video, face detection, face landmarks (468 and 68
points), the NPZ saver and overlay images.

- `landmarks.LoadFrames`: an image pattern or a video file (by extension) -> images.
- `landmarks.DetectFaces`: images -> square crop boxes (x0 y0 x1 y1, pixels; NaN where no
  face), detector scores, failure flags and rolls (BlazeFace over an image pyramid,
  `nodes.landmarks.network`; which face and following it, `nodes.landmarks.tracking`).
- `landmarks.FaceLandmarks`: images + boxes (+ rolls) -> 468 face-mesh points, the 68
  Multi-PIE points (`nodes.landmarks.correspondence`) and face presence, read in crops turned
  upright. A heatmap network (3D-FAN style,
  a `TorchModel`) may replace the face mesh for the 68 points (`nodes.landmarks.heatmap`).
- `landmarks.SaveLandmarks`: one NPZ with boxes [F, 4], landmarks68 [F, 68, 2],
  landmarks468 [F, 468, 2], presence [F], failed [F].
- `landmarks.LandmarkOverlays`: one PNG per frame with the box and the points drawn.

Pixel coordinates: origin top-left, x right, y down, pixel centres at integers. Frames where
detection failed have NaN boxes and points and confidence 0. Torch is imported inside
`run()` (see tests/test_startup.py).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Files, ImageSequence, In, Index, InputError, Landmarks2D, Node,
                       NodeParams, Out, Param, ParamSequence, TorchModel)
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic
from nodegraph.flags import flags_to_mask
from nodegraph.params import ParamProblem, number_problem

from .correspondence import MEDIAPIPE_TO_68
from .tracking import FACE_CHOICES, FAILURE_REASONS

__all__ = ["VIDEO_EXTENSIONS", "network_images", "LoadFrames", "DetectFaces", "FaceLandmarks", "TrackFaces",
           "SaveLandmarks", "LandmarkOverlays", "draw_overlay"]

VIDEO_EXTENSIONS = (".mp4", ".mov", ".mkv", ".avi", ".webm", ".m4v", ".mpg", ".mpeg")
"""Extensions `landmarks.LoadFrames` reads as video; anything else is an image pattern."""

BOX_NAMES = ["x0", "y0", "x1", "y1"]


def _is_video(path: str) -> bool:
    return path.lower().endswith(VIDEO_EXTENSIONS)


def network_images(images: ImageSequence, where: str = "images") -> np.ndarray:
    """(F, H, W, 3) sRGB-encoded RGB in [0, 1] for the networks (grey is replicated); never write into it.

    Frames already in [0, 1] (8/16-bit files and video, the usual case) come back as a
    view of the input, not a copy: a sequence node (TrackFaces) gets the whole shot, and a clipped
    copy of it was one more copy of the video (fit_video.json on 96 frames of 512^2: the
    process's memory after TrackFaces 1,266 -> 968 MB). Other frames are clipped into a new
    array (NaN stays NaN)."""
    idx = images.colour_channels()
    if not idx:
        raise InputError(where, f"expected RGB or grey images, found channels {images.channels}")
    pixels = images.to_srgb().rgb()  # consecutive channels are a view (a list index copied 48 frames of 512^2 in 0.5 s)
    if not (pixels.dtype == np.float32 and pixels.size and pixels.min() >= 0.0 and pixels.max() <= 1.0):
        pixels = np.clip(pixels, 0.0, 1.0, out=np.empty(pixels.shape, np.float32))  # one pass into a new array
    return pixels  # may be the upstream node's value (its callers only read it; torch warns on read-only arrays)


class LoadFrames(Node):
    """Read frames from a numbered image pattern or a video file (chosen by the extension): an
    `io.LoadImageSequence` (colour space auto) or an `io.LoadVideo` under one node type, so a
    landmark graph takes either source with one parameter."""

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

    def _loader(self) -> Node:
        """The io node that reads `path`, with this node's id (its errors name this node)."""
        p = self.params
        if _is_video(p.path):
            from ..io.video import LoadVideo

            return LoadVideo(path=p.path, fps=p.fps, node_id=self.node_id)
        from ..io.image import LoadImageSequence

        return LoadImageSequence(path=p.path, first_frame=p.first_frame, fps=p.fps, node_id=self.node_id)

    def frame_count(self) -> int | None:
        return self._loader().frame_count()

    def input_files(self, frames: range | None = None) -> list[Path]:
        return self._loader().input_files(frames)

    def run(self) -> dict[str, ImageSequence]:
        return dict(self.run_delegate(self._loader()))


def _face_problem(value: object) -> str:
    """Why `value` is not a `face` choice ("" when it is one)."""
    if isinstance(value, str):
        return "" if value in FACE_CHOICES else (f"expected one of {list(FACE_CHOICES)}, an index >= 0 or a box "
                                                 f"[x0, y0, x1, y1] in pixels, found the string {value!r}")
    if isinstance(value, bool):
        return f"expected a name, an index >= 0 or a box [x0, y0, x1, y1], found {value!r}"
    if isinstance(value, int):
        return "" if value >= 0 else f"expected an index >= 0 (0 = the leftmost face), found {value}"
    if isinstance(value, (list, tuple)):
        if len(value) != 4 or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            return f"expected a box of 4 numbers [x0, y0, x1, y1] in pixels, found {list(value)!r}"
        if not all(np.isfinite(value)) or not (value[2] > value[0] and value[3] > value[1]):
            return f"expected a box [x0, y0, x1, y1] with x1 > x0 and y1 > y0, found {list(value)!r}"
        return ""
    return f"expected one of {list(FACE_CHOICES)}, an index >= 0 or a box [x0, y0, x1, y1], found {value!r}"


class _FaceParams(NodeParams):
    """Which face and the detector's settings (`landmarks.DetectFaces`, `landmarks.TrackFaces`)."""

    face: Literal["largest", "centre", "score"] | Index | Annotated[list[float], Field(min_length=4, max_length=4)] = \
        Param("largest", description="Which face: 'largest' (box area), 'centre' (nearest the image centre), "
              "'score' (most confident), an index in reading order (0 = leftmost box centre; ties top to "
              "bottom) or a box [x0, y0, x1, y1] in pixels (the detection overlapping it most). Applied on the "
              "first frame where it finds a face; later frames follow that person.")
    min_face_px: float = Param(40.0, ge=0, description="Smallest face looked for: its detector box side, "
                               "pixels (about 2.1 eye distances). Finer pyramid levels are added only when the "
                               "whole frame (squeezed to 128 x 128) would miss such a face: none for frames of "
                               "at most 256 px at 40; 0 = the whole frame only.")
    pyramid_min_score: float = Param(0.7, ge=0, le=1, description="Least score of a detection from the finer "
                                     "pyramid levels (they see many more background windows).")
    min_score: float = Param(0.5, ge=0, le=1, description="Detections below this score are dropped.")
    iou: float = Param(0.3, gt=0, le=1, description="Overlap (IoU) of the weighted non-maximum suppression.")
    box_scale: float = Param(1.5, gt=0, description="Crop side over the longer side of the face box.")

    @model_validator(mode="before")
    @classmethod
    def _strict_numbers(cls, data: Any) -> Any:
        # Replaces NodeParams' check of the same name, which reads the Literal names of `face`
        # as "expected an integer"; the other fields get the same check as there.
        if isinstance(data, dict):
            for name, value in data.items():
                if name == "face":
                    problem = _face_problem(value)
                elif name in cls.model_fields:
                    info = cls.model_fields[name]
                    problem = number_problem(info.annotation, value, tuple(info.metadata))
                else:
                    continue
                if problem:
                    raise ParamProblem(name, problem)
        return data


class DetectFaces(Node):
    """Detect faces over an image pyramid, choose one, follow it; give its face-mesh crop box.

    Sequence node: following a person is a chain through all frames before (the choice is made
    on the first frame where it finds a face, every later frame takes the detection overlapping
    the previous frame's most), so a chunk cannot start it alone without possibly picking the
    other person; a halo (`windowed`) would only make that rarer, so the node sees all frames.
    """

    type_name = "landmarks.DetectFaces"
    version = 2
    kind = SEQUENCE
    resources = {"gpu": 1}
    torch_threads = 1  # the same points for any thread count (issue 30): the fit amplifies rounding

    class Params(_FaceParams):
        track_iou: float = Param(0.3, gt=0, le=1, description="Least overlap (IoU) with the previous frame's face "
                                 "that continues following it; below it the frame fails and the choice is made "
                                 "again on the next frame.")
        batch: int = Param(8, ge=1, description="Frames per network call.", affects_output=False)

    images = In(ImageSequence, doc="RGB frames (converted to sRGB for the network).")
    boxes = Out(ParamSequence, doc="x0 y0 x1 y1: square crop box, pixels (NaN where no face).")
    scores = Out(ParamSequence, doc="score: detector confidence in [0, 1] (0 where no face).")
    failed = Out(ParamSequence, doc="failed: 1 where no face was found (or the followed face was lost), else 0.")
    rolls = Out(ParamSequence, doc="roll: the eye line's angle from the detector's eye keypoints, radians, "
                "clockwise on screen (0 upright; NaN where no face); for landmarks.FaceLandmarks.")

    def run(self, images: ImageSequence) -> dict[str, ParamSequence]:
        import torch

        from .network import detect_all_faces, load_face_detector, select_faces
        from .tracking import follow_faces

        p = self.params
        pixels = network_images(images)
        detector = load_face_detector(self.device)
        faces = []
        for start in range(0, len(pixels), p.batch):
            batch = torch.as_tensor(pixels[start:start + p.batch], device=self.device)
            faces += detect_all_faces(batch, detector, min_score=p.min_score, iou=p.iou, min_face_px=p.min_face_px,
                                      pyramid_min_score=p.pyramid_min_score)
            self.progress(min(start + p.batch, len(pixels)) / max(len(pixels), 1), "detecting faces")
        chosen = follow_faces([f.boxes for f in faces], [f.scores for f in faces], p.face, pixels.shape[1:3],
                              min_iou=p.track_iou)
        det = select_faces(faces, chosen, p.box_scale)
        return {"boxes": ParamSequence(det.boxes.astype(np.float32), list(BOX_NAMES)),
                "scores": ParamSequence(det.scores.astype(np.float32)[:, None], ["score"]),
                "failed": ParamSequence((~det.found).astype(np.float32)[:, None], ["failed"]),
                "rolls": ParamSequence(det.rolls.astype(np.float32)[:, None], ["roll"])}


class FaceLandmarks(Node):
    """Face landmarks in each frame's crop box: 468 face-mesh points, the 68 Multi-PIE points, presence."""

    type_name = "landmarks.FaceLandmarks"
    version = 2
    kind = FRAMEWISE
    resources = {"gpu": 1}
    torch_threads = 1  # the same points for any thread count (issue 30): the fit amplifies rounding

    class Params(NodeParams):
        heatmap_input_size: int = Param(256, ge=8, description="Crop side of a connected heatmap network "
                                        "(3D-FAN: 256).")
        beta: float = Param(50.0, gt=0, description="Soft-argmax inverse temperature of the heatmap head.")
        roll_passes: int = Param(3, ge=0, description="Face-mesh passes after the first that turn the crop by "
                                 "the eye line of the points found (the detector's roll reads a 90 deg roll as "
                                 "about 40); 0 = the crop turned by `rolls` only (upright without them).")
        batch: int = Param(8, ge=1, description="Frames per network call.", affects_output=False)

    images = In(ImageSequence, doc="RGB frames (converted to sRGB for the network).")
    boxes = In(ParamSequence, doc="x0 y0 x1 y1 crop boxes, pixels (landmarks.DetectFaces).")
    rolls = In(ParamSequence, optional=True, doc="roll: first turn of each crop about its centre, radians "
               "(landmarks.DetectFaces); absent = upright, then `roll_passes`.")
    heatmap_model = In(TorchModel, optional=True, doc="A heatmap network (B, 3, S, S) -> (B, 68, h, w); "
                       "replaces the face mesh for landmarks68.")
    landmarks468 = Out(Landmarks2D, doc="(F, 468, 2) face-mesh points, pixels; confidence = presence.")
    landmarks68 = Out(Landmarks2D, doc="(F, 68, 2) Multi-PIE points, pixels; confidence = presence.")
    presence = Out(ParamSequence, doc="presence: face presence in [0, 1] (0 where no box).")
    iris = Out(Landmarks2D, doc="(F, 10, 2) iris points, pixels: the subject's right eye's 5 (centre, then 4 on "
               "the rim), then the left eye's (MediaPipe's iris model in eye crops from the face-mesh points); "
               "confidence = presence.")

    def run(self, images: ImageSequence, boxes: ParamSequence, rolls: ParamSequence | None = None,
            heatmap_model: TorchModel | None = None) -> dict[str, object]:
        import torch

        from .heatmap import HeatmapLandmarks
        from .iris import iris_landmarks, load_iris_network
        from .network import face_landmarks, load_face_mesh, upright_face_landmarks

        p = self.params
        if boxes.values.shape[1] != 4:
            raise InputError("boxes", f"expected 4 columns {BOX_NAMES}, found {boxes.names}")
        if rolls is not None and rolls.values.shape[1] != 1:
            raise InputError("rolls", f"expected 1 column ['roll'], found {rolls.names}")
        first_roll = np.zeros(len(boxes.values)) if rolls is None else np.nan_to_num(rolls.values[:, 0].astype(np.float64))
        pixels = network_images(images)
        frames = len(pixels)
        mesh = load_face_mesh(self.device)
        iris_net = load_iris_network(self.device)
        heatmap = None
        if heatmap_model is not None:
            heatmap = HeatmapLandmarks(heatmap_model.build(self.device).eval(), p.heatmap_input_size, beta=p.beta)
        pts468 = np.full((frames, 468, 2), np.nan, np.float32)
        pts68 = np.full((frames, 68, 2), np.nan, np.float32)
        presence = np.zeros(frames, np.float32)
        presence68 = np.zeros(frames, np.float32)
        iris = np.full((frames, 10, 2), np.nan, np.float32)
        valid = np.flatnonzero(np.isfinite(boxes.values).all(1) & (boxes.values[:, 2] > boxes.values[:, 0]) &
                               (boxes.values[:, 3] > boxes.values[:, 1]))
        with torch.no_grad():
            for start in range(0, len(valid), p.batch):
                sel = valid[start:start + p.batch]
                batch = torch.as_tensor(pixels[sel], device=self.device)
                box = boxes.values[sel].astype(np.float64)
                points, pres, roll = upright_face_landmarks(batch, box, mesh, first_roll[sel], p.roll_passes)
                pts468[sel] = points.cpu().numpy()
                presence[sel] = pres.cpu().numpy()
                iris[sel] = iris_landmarks(batch, pts468[sel], iris_net).reshape(len(sel), 10, 2)
                if heatmap is not None:  # in the face mesh's upright crop
                    points68, pres68 = face_landmarks(batch, box, heatmap, roll)
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
                "presence": ParamSequence(presence[:, None], ["presence"]),
                "iris": Landmarks2D(iris, np.repeat(presence[:, None], 10, 1))}


class TrackFaces(Node):
    """Follow one face through a video by its own landmarks: 468 / 68 points, iris, presence; the
    detector runs only when the face is lost (MediaPipe's Face Landmarker front end).

    After a detection, each frame's face-mesh crop comes from the previous frames' points
    (`nodes.landmarks.face_tracker`), so the crop moves, zooms and rolls with the face at the
    cost of one face-mesh read; the detector (the image pyramid of `landmarks.DetectFaces`) runs
    again where the presence drops below `min_presence`. Sequence node: each frame's crop comes
    from the frame before.
    """

    type_name = "landmarks.TrackFaces"
    version = 8  # 8: `weak_reads` (a face found but not read at min_presence keeps its best read, failed);
    # 7: `mean_of_framings` (the fit graphs read once, as the fit reads its renders);
    # 6: a detected face's points are the mean of 15 crop framings' reads (FRAMINGS);
    # 5: a re-found face must keep its size (reason 5); 4: sharpened looks at amount 6,
    # confirmed at presence 0.9; 3: the full-range look
    # (`full_range`); 2: the quarter-turned and sharpened looks
    kind = SEQUENCE
    resources = {"gpu": 1}
    torch_threads = 1  # the same points for any thread count (issue 30): the fit amplifies rounding

    class Params(_FaceParams):
        min_presence: float = Param(0.5, ge=0, le=1, description="Least face-mesh presence of a face read: "
                                    "below it the followed face is lost (the detector runs), and a detection "
                                    "the face mesh does not confirm is not taken (MediaPipe's tracking "
                                    "confidence, 0.5).")
        refind_frames: int = Param(30, ge=0, description="Frames (1 s at 30 fps) during which a lost face is "
                                   "looked for only where it was last seen (so another face in view is not "
                                   "taken for it); after them the choice `face` is made afresh.")
        reread: float = Param(0.05, ge=0, description="Crop movement (the larger of the centre's shift in crop "
                              "sides, |log| of the side ratio and the roll change in radians) above which a "
                              "frame is read again (twice at most) in the crop of its own points: an off-centre "
                              "face is read less well. The default re-reads only fast moves, so a followed "
                              "frame mostly costs one face-mesh read (bench/detect_faces.py prints the extra "
                              "reads); 0 re-reads every frame: steadier points at up to three reads a frame.")
        velocity: float = Param(1.0, ge=0, le=1, description="How far each crop is moved on by the face's "
                                "motion over the last two frames (1 = constant velocity, 0 = where the last "
                                "frame's points were): a crop that lags a moving face drifts off it.")
        roll_passes: int = Param(3, ge=0, description="Face-mesh passes that re-turn a detection's crop by the "
                                 "eye line of the points found (as `landmarks.FaceLandmarks`).")
        with_iris: bool = Param(True, description="Run the iris model on both eyes of every frame read (`iris` "
                                "NaN without): it costs about as much as the face mesh again (bench/detect_faces.py).")
        enhance: bool = Param(True, description="Where no face is confirmed in a frame, detect and confirm once "
                              "more in the frame sharpened (unsharp mask, sigma 3 px, amount 6; a face found there "
                              "needs a face-mesh presence of 0.9) and follow a face "
                              "found there in sharpened frames (it reads small blurred faces the plain frame does "
                              "not: bench/detect_faces.py --only-check); costs up to three more detections "
                              "(upright and turned) on frames that fail.")
        quarter_turns: bool = Param(True, description="Where no face is confirmed in a frame (or its sharpened "
                                    "copy), detect again in it turned a quarter each way (the short-range "
                                    "detector misses small faces rolled 90 deg); the points are read in the frame "
                                    "as it is. Costs two more detections on frames that fail.")
        full_range: bool = Param(True, description="Where no face is confirmed in a frame, detect again with "
                                 "MediaPipe's full-range BlazeFace on the whole frame (192 x 192; it finds faces "
                                 "from about a 100 px box in 1080p), after the short-range looks and again on the "
                                 "sharpened frame: it sees some blurred, dark and noisy faces the short-range "
                                 "pyramid misses. Costs up to two full-range calls (about 4.7 short-range calls "
                                 "each) on frames that fail.")

        mean_of_framings: bool = Param(True, description="At a detection, the points are the mean of the face "
                                       "mesh's reads in 15 crop framings around the confirming read "
                                       "(`face_tracker.FRAMINGS`): closer to a human annotation on a near profile "
                                       "(bench/detect_faces.py: the camera man 13.0 -> 9.9% of the eye distance). "
                                       "False: one read, as the fit reads its renders; the fit graphs use False, "
                                       "since the fit compares the plate's reading with one reading of its render "
                                       "and a mean on one side only is a bias (skimage's astronaut: energy 996 "
                                       "one read, 1786 with the mean, every expression weight left at 0).")
        weak_reads: bool = Param(True, description="A frame that fails only for its read (reason 2: the face "
                                 "mesh's presence stays under min_presence; 4: two reads disagree; a face the "
                                 "detector found that the face mesh cannot read, e.g. a profile past about 60 deg "
                                 "of yaw) keeps the box, roll, points and presence of its best read; it stays "
                                 "failed and its points' "
                                 "confidence 0, so the fit leaves it out. Renders of the bundled head at 70 / "
                                 "80 / 90 deg of yaw: presence 0.005 / 0.004 / 0.001, the profile line (nose, "
                                 "lips, chin) read 7 / 12 / 20% of the nose-bridge-to-chin length off. False: "
                                 "NaN there, as for the other failures.")

    images = In(ImageSequence, doc="RGB frames (converted to sRGB for the networks).")
    boxes = Out(ParamSequence, doc="x0 y0 x1 y1: the square crop the points were read in, pixels (turned by "
                "`rolls` about its centre; NaN where failed, except the weak reads: `weak_reads`).")
    rolls = Out(ParamSequence, doc="roll: the crop's turn, radians, clockwise on screen (NaN where failed, except "
                "the weak reads).")
    failed = Out(ParamSequence, doc="failed: 1 where no face was read, else 0.")
    reasons = Out(ParamSequence, doc="reason: why a frame failed, as a code: "
                  + "; ".join(f"{i} {r}" for i, r in enumerate(FAILURE_REASONS) if i) + " (0: not failed).")
    landmarks468 = Out(Landmarks2D, doc="(F, 468, 2) face-mesh points, pixels (NaN where failed, except the "
                       "weak reads); confidence = presence (0 where failed).")
    landmarks68 = Out(Landmarks2D, doc="(F, 68, 2) Multi-PIE points, pixels; confidence = presence (0 where "
                      "failed).")
    presence = Out(ParamSequence, doc="presence: face presence in [0, 1] of the points given (0 where none: "
                   "failed, except the weak reads).")
    iris = Out(Landmarks2D, doc="(F, 10, 2) iris points, pixels (as `landmarks.FaceLandmarks`; NaN where "
               "failed or without `with_iris`).")

    def run(self, images: ImageSequence) -> dict[str, object]:
        from .face_tracker import FRAMINGS, track_faces

        p = self.params
        out = track_faces(network_images(images), device=self.device, face=p.face, min_score=p.min_score,
                          iou=p.iou, min_face_px=p.min_face_px, pyramid_min_score=p.pyramid_min_score,
                          box_scale=p.box_scale, min_presence=p.min_presence, refind_frames=p.refind_frames,
                          reread=p.reread, velocity=p.velocity, roll_passes=p.roll_passes, with_iris=p.with_iris,
                          enhance=p.enhance, quarter_turns=p.quarter_turns, full_range=p.full_range,
                          framings=FRAMINGS if p.mean_of_framings else (), weak_reads=p.weak_reads,
                          progress=self.progress)
        ok = (~out.failed).astype(np.float32)
        confidence = (out.presence * ok).astype(np.float32)[:, None]
        read = np.isfinite(out.points).all((1, 2))
        presence = np.where(read, out.presence, 0.0).astype(np.float32)[:, None]
        points = out.points.astype(np.float32)
        return {"boxes": ParamSequence(out.boxes.astype(np.float32), list(BOX_NAMES)),
                "rolls": ParamSequence(out.rolls.astype(np.float32)[:, None], ["roll"]),
                "failed": ParamSequence(out.failed.astype(np.float32)[:, None], ["failed"]),
                "reasons": ParamSequence(out.reasons.astype(np.float32)[:, None], ["reason"]),
                "landmarks468": Landmarks2D(points, np.repeat(confidence, 468, 1)),
                "landmarks68": Landmarks2D(points[:, MEDIAPIPE_TO_68], np.repeat(confidence, 68, 1)),
                "presence": ParamSequence(presence, ["presence"]),
                "iris": Landmarks2D(out.iris.reshape(-1, 10, 2).astype(np.float32), np.repeat(confidence, 10, 1))}


class SaveLandmarks(Node):
    """Write boxes, landmarks and flags of all frames to one NPZ file (atomically)."""

    type_name = "landmarks.SaveLandmarks"
    version = 2  # 2: failed read by nodegraph.flags (a NaN flag counts as failed; was saved as not failed)
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
    failed = In(ParamSequence, doc="failed: 1 where no face was found (read by nodegraph.flags: the 'failed' "
                "column, else the first; NaN counts as failed).")
    iris = In(Landmarks2D, optional=True, doc="(F, 10, 2) iris points, pixels (landmarks.FaceLandmarks or "
              "landmarks.TrackFaces): saved as iris [F, 2, 5, 2] with the per-eye gaze [F, 2, 2].")
    reasons = In(ParamSequence, optional=True, doc="reason: why each frame failed, a code (landmarks.TrackFaces): "
                 "saved as failed_reason [F] with the texts failure_reasons.")
    files = Out(Files, doc="The NPZ written and its sha256.")

    def run(self, boxes: ParamSequence, landmarks68: Landmarks2D, landmarks468: Landmarks2D,
            presence: ParamSequence, failed: ParamSequence, iris: Landmarks2D | None = None,
            reasons: ParamSequence | None = None) -> dict[str, Files]:
        path = self.params.path
        checks = [("boxes", boxes.values, (4,)), ("landmarks68", landmarks68.points, (68, 2)),
                  ("landmarks468", landmarks468.points, (468, 2)), ("presence", presence.values, (1,)),
                  ("failed", failed.values, (1,))]
        if iris is not None:
            checks.append(("iris", iris.points, (10, 2)))
        if reasons is not None:
            checks.append(("reasons", reasons.values, (1,)))
        for port, value, shape in checks:
            if tuple(value.shape[1:]) != shape:
                raise InputError(port, f"expected shape (F, {', '.join(map(str, shape))}), found {value.shape}")
        arrays = {"boxes": boxes.values.astype(np.float32),
                  "landmarks68": landmarks68.points.astype(np.float32),
                  "landmarks468": landmarks468.points.astype(np.float32),
                  "presence": presence.values[:, 0].astype(np.float32),
                  "failed": flags_to_mask(failed, len(failed.values)),
                  "frames": np.arange(self.frames.start, self.frames.stop, dtype=np.int64)}
        if iris is not None:
            from .tracking import eye_gaze

            arrays["iris"] = iris.points.reshape(-1, 2, 5, 2).astype(np.float32)
            arrays["gaze"] = eye_gaze(landmarks468.points, arrays["iris"]).astype(np.float32)
        if reasons is not None:
            arrays["failed_reason"] = np.nan_to_num(reasons.values[:, 0]).astype(np.int64)
            arrays["failure_reasons"] = np.array(FAILURE_REASONS)
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
    """Write one PNG per frame with the crop box (yellow), 468 points (green) and 68 points (red);
    a failed frame's best read (landmarks.TrackFaces' `weak_reads`, confidence 0) in grey."""

    type_name = "landmarks.LandmarkOverlays"
    version = 2  # 2: points of confidence 0 (a failed frame's weak read) drawn grey
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
        pixels = network_images(images)
        written = []
        for i, frame in enumerate(self.frames):
            weak = not (landmarks68.confidence[i] > 0).any()  # a failed frame's best read: grey
            img = draw_overlay(pixels[i], boxes.values[i],
                               [(landmarks468.points[i], (0.55, 0.55, 0.55) if weak else (0.0, 1.0, 0.0)),
                                (landmarks68.points[i], (0.8, 0.8, 0.8) if weak else (1.0, 0.0, 0.0))])
            path = folder / f"overlay.{frame:04d}.png"
            with atomic_path(path) as tmp:
                write_image(tmp, img, ["R", "G", "B"], "uint8")
            written.append(path)
            self.progress((i + 1) / len(self.frames), f"wrote {path}")
        return {"files": files_value(written)}
