"""What the fit hands on: failure flags, the NPZ, and overlay PNGs.

- `fit.FlagFailures`: frames with no face, whose final energy is far above the shot's median,
  or, absolutely (checks that also hold for a one-frame shot), whose fitted landmarks, projected
  into the camera, miss the plate's by more than a share of the eye distance, or whose energy as
  an RMS per landmark does.
- `fit.FittedLandmarks`: the fitted head's 68 points as the face mesh reads them on its render,
  the fit's landmarks in the network's own convention (contour points on the silhouette).
- `fit.SaveFit` (NPZ) and `fit.FitReport` (overlay PNGs).

Flags are read through `nodegraph.flags.flags_to_mask`. Torch is imported inside `run()`.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Camera, FaceModel, Files, ImageSequence, In, InputError, JsonValue,
                       Landmarks2D, Node, NodeParams, Out, Param, ParamSequence)
from nodegraph.flags import flags_to_mask

from .node_inputs import _fit_model, _state_from, _views
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic

__all__ = ["FIT_FAILURE_REASONS", "absolute_errors",
           "MAX_REPROJECTION", "MAX_ENERGY_RMS", "MIN_OUTLIER_ENERGY_RMS", "LandmarkProjection",
           "projected_landmarks68", "reprojection_error", "energy_rms", "read_fitted_landmarks", "FlagFailures",
           "FittedLandmarks", "SaveFit", "FitReport"]

FIT_FAILURE_REASONS = ("", "no face or no pose", "energy above factor x the shot's median",
                       "landmarks reprojected further than max_reprojection eye distances",
                       "energy above max_energy_rms eye distances")
"""Texts of fit.FlagFailures' `reason` codes (0: not failed), saved by fit.SaveFit as failure_reasons."""

MAX_REPROJECTION = 0.25
"""fit.FlagFailures' default bound on `reprojection_error` (RMS over the 68 points, in the fitted
head's eye distances).

Measured with graphs/fit_video.json (landmarks.TrackFaces, fit version 6): one photo of
skimage.data.astronaut() (512 px, frontal) 0.075 and 0.071 (camera fx 703.4 and 700); one of
skimage.data.camera() (the cameraman, near profile) 0.137; a 3-frame pan over the astronaut
(448 px crops moving 8 and 20 px a frame) 0.118-0.124: the share of a real face that the
40-component model's fixed 68 landmark vertices (jaw line, lips) do not reach, larger as the head
turns. A fit of the model's own landmarks with 0.3 px of noise: 0.005; a wrong minimum
(tests/nodes/fit/test_flag_failures.py: the start turned away from the camera): 2.25; a head
behind the camera: inf. The bound is 1.8x the largest good value."""

MAX_ENERGY_RMS = 0.15
"""fit.FlagFailures' default bound on `energy_rms` (the final deep energy as an RMS per landmark,
in the fitted head's eye distances). Measured as `MAX_REPROJECTION`: astronaut photo 0.040 and
0.047, cameraman 0.045 (the energy compares the network's reading of the render with the plate's
points, so it does not grow with the turn as the fixed vertices do), the 3-frame pan 0.080-0.082;
the synthetic wrong minimum 2.21. The bound is 1.8x the largest good value."""

MIN_OUTLIER_ENERGY_RMS = 0.075
"""fit.FlagFailures' floor under the relative check: a frame whose energy_rms is at most this is
never an energy outlier, however far above the shot's median. Half of `MAX_ENERGY_RMS`, under the
largest good value measured (0.082): on the demo's renders (40 frames) every frame's energy_rms is
0.007-0.050, so a frame at 0.046 was 11.5x the median and failed, though it fits to 5% of the eye
distance per landmark."""


class LandmarkProjection(NamedTuple):
    """The fitted model's 68 landmark vertices in a camera.

    Attributes:
        pixels: (F, 68, 2) float64, origin top-left (a point behind the camera projects mirrored
            through the centre, `project_points`).
        depth: (F, 68) depth in the camera frame, cm.
        eye_px: (F,) the fitted head's eye distance in pixels as if it faced the camera:
            fx * |v_36 - v_45| / depth of their midpoint (outer eye corners), unlike the plate's
            2D eye distance not shortened by a turned head.
    """

    pixels: np.ndarray
    depth: np.ndarray
    eye_px: np.ndarray


def projected_landmarks68(fitted: np.ndarray, model: FaceModel, camera: Camera) -> LandmarkProjection:
    """Project the fitted model's 68 landmark vertices into a camera.

    Args:
        fitted: (F, 12 + K) r00..r22 (row-major, model to world), tx ty tz (cm, world), then the
            model's K expression weights (fit.Expression's `fitted`); NaN rows stay NaN.
        model: the fitted model (identity applied), K expression shapes.
        camera: the camera (world to camera, intrinsics, radial distortion).
    Returns:
        LandmarkProjection.
    """
    from ..geometry.camera import project_points

    rot = fitted[:, :9].reshape(-1, 3, 3).astype(np.float64)
    trans = fitted[:, 9:12].astype(np.float64)
    points = model.evaluate(np.nan_to_num(fitted[:, 12:]))[:, model.landmarks].astype(np.float64)
    world = np.einsum("fij,flj->fli", rot, points) + trans[:, None]
    w2c = np.asarray(camera.world_to_camera, np.float64)
    pixels = project_points(world, w2c, [camera.fx, camera.fy, camera.cx, camera.cy],
                            [camera.k1, camera.k2] if (camera.k1 or camera.k2) else None)
    depth = world @ w2c[2, :3] + w2c[2, 3]
    eye_cm = np.linalg.norm(points[:, 36] - points[:, 45], axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        eye_px = camera.fx * eye_cm / np.abs(0.5 * (depth[:, 36] + depth[:, 45]))
    return LandmarkProjection(pixels, depth, eye_px)


def reprojection_error(projection: LandmarkProjection, detected: np.ndarray) -> np.ndarray:
    """RMS distance between projected and detected 68 landmarks, in the fitted head's eye distances.

    Args:
        projection: the fitted model's landmarks in the camera (`projected_landmarks68`).
        detected: (F, 68, 2) the plate's landmarks, pixels.
    Returns:
        (F,) sqrt(mean_l |p_l - d_l|^2) / projection.eye_px; NaN where either is NaN (no face or
        no pose), inf where a point lies at or behind the camera's plane.

    Example:
        >>> d = np.zeros((1, 68, 2))
        >>> proj = LandmarkProjection(d + [0.0, 1.0], np.full((1, 68), 50.0), np.array([10.0]))
        >>> reprojection_error(proj, d).round(3).tolist()
        [0.1]
    """
    rms = np.sqrt(((projection.pixels - np.asarray(detected, np.float64)) ** 2).sum(-1).mean(-1))
    with np.errstate(divide="ignore", invalid="ignore"):
        error = rms / projection.eye_px
    behind = (projection.depth <= 0).any(-1)  # NaN depths compare False: they stay NaN
    return np.where(behind & np.isfinite(rms), np.inf, error)


def energy_rms(energy: np.ndarray, boxes: np.ndarray, eye_px: np.ndarray, points: int = 68) -> np.ndarray:
    """The fit's final energy as an RMS per landmark, in eye distances.

    Args:
        energy: (F,) fit.Expression's energy, 256-crop pixel^2 (the crop is the box resampled to
            256 px; one camera).
        boxes: (F, 4) x0 y0 x1 y1 crop boxes, pixels.
        eye_px: (F,) the eye distance in pixels (`LandmarkProjection.eye_px`).
        points: landmarks the energy sums over.
    Returns:
        (F,) sqrt(energy / points) * (x1 - x0) / 256 / eye_px.

    Example:
        >>> energy_rms(np.array([68 * 4.0]), np.array([[0.0, 0.0, 128.0, 128.0]]), np.array([10.0])).tolist()
        [0.1]
    """
    side = np.asarray(boxes, np.float64)[:, 2] - np.asarray(boxes, np.float64)[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.sqrt(np.asarray(energy, np.float64) / points) * side / 256.0 / eye_px


class FlagFailures(Node):
    """Flag frames with no face, an energy far above the shot's median or the eye distance, or landmarks far off."""

    type_name = "fit.FlagFailures"
    version = 3  # 2: the absolute checks (fitted, model, camera, landmarks, boxes), columns reprojection,
    # energy_rms, reason; 3: no relative outlier at or under min_outlier_energy_rms
    kind = SEQUENCE

    class Params(NodeParams):
        factor: float = Param(4.0, gt=1, description="A frame fails when its energy exceeds factor x the "
                              "median energy of the fitted frames (and, with the absolute checks' inputs, "
                              "its energy_rms exceeds min_outlier_energy_rms).")
        min_outlier_energy_rms: float = Param(MIN_OUTLIER_ENERGY_RMS, ge=0, description="With the absolute "
                                              "checks' inputs: a frame whose energy_rms (eye distances) is at "
                                              "most this is not an energy outlier, however far above the "
                                              "median (a shot fitted to a few % of the eye distance has a "
                                              "tiny median). Default: nodes.fit.output_nodes."
                                              "MIN_OUTLIER_ENERGY_RMS, half of max_energy_rms.")
        max_reprojection: float = Param(MAX_REPROJECTION, ge=0, description="A frame fails when the fitted "
                                        "model's 68 landmark vertices, projected into the camera, miss the plate's "
                                        "by more than this RMS, in eye distances of the fitted head (as if it "
                                        "faced the camera); 0 = off. Holds for a one-frame shot, which the median "
                                        "cannot flag. Default: nodes.fit.output_nodes.MAX_REPROJECTION (measured).")
        max_energy_rms: float = Param(MAX_ENERGY_RMS, ge=0, description="A frame fails when its final energy, as "
                                      "an RMS per landmark, exceeds this many eye distances of the fitted head "
                                      "(one camera); 0 = off. Default: nodes.fit.output_nodes.MAX_ENERGY_RMS "
                                      "(measured).")

    energy = In(ParamSequence, doc="energy per frame (fit.Expression).")
    failed = In(ParamSequence, doc="failed per frame (fit.Expression).")
    fitted = In(ParamSequence, optional=True, doc="From fit.Expression (pose + weights), for the absolute checks.")
    model = In(FaceModel, optional=True, doc="The fitted model (identity applied), for the absolute checks.")
    camera = In(Camera, optional=True, doc="The first camera, for the absolute checks.")
    landmarks = In(Landmarks2D, optional=True, doc="(F, 68, 2) the first camera's plate landmarks, pixels, for "
                   "the absolute checks.")
    boxes = In(ParamSequence, optional=True, doc="(F, 4) the first camera's crop boxes, for the energy check.")
    flags = Out(ParamSequence, doc="failed: 1 = failed; energy_ratio: energy / median; reprojection and "
                "energy_rms: the absolute checks' values (NaN without their inputs); reason: why a frame "
                "failed, a code (" + "; ".join(f"{i} {r}" for i, r in enumerate(FIT_FAILURE_REASONS) if i)
                + "; 0: not failed).")

    def run(self, energy: ParamSequence, failed: ParamSequence, fitted: ParamSequence | None = None,
            model: FaceModel | None = None, camera: Camera | None = None, landmarks: Landmarks2D | None = None,
            boxes: ParamSequence | None = None) -> dict[str, ParamSequence]:
        p = self.params
        e = energy.values[:, 0].astype(np.float64)
        bad = flags_to_mask(failed, len(e)) | ~np.isfinite(e)
        ok = ~bad
        median = float(np.median(e[ok])) if ok.any() else np.nan
        ratio = e / max(median, 1e-9) if ok.any() else np.full_like(e, np.nan)
        reprojection, rms = self._absolute(e, fitted, model, camera, landmarks, boxes)

        def above(value: np.ndarray, bound: float) -> np.ndarray:  # NaN: not checked
            return ok & (bound > 0) & ~np.isnan(value) & ~(value <= bound)

        outlier = ok & (ratio > p.factor) & ~(rms <= p.min_outlier_energy_rms)  # NaN rms: the ratio alone
        reason = np.select([bad, outlier, above(reprojection, p.max_reprojection),
                            above(rms, p.max_energy_rms)], [1, 2, 3, 4], 0)
        values = np.stack([reason > 0, ratio, reprojection, rms, reason], 1).astype(np.float32)
        return {"flags": ParamSequence(values, ["failed", "energy_ratio", "reprojection", "energy_rms", "reason"])}

    def _absolute(self, energy: np.ndarray, fitted: ParamSequence | None, model: FaceModel | None,
                  camera: Camera | None, landmarks: Landmarks2D | None,
                  boxes: ParamSequence | None) -> tuple[np.ndarray, np.ndarray]:
        """(F,) reprojection_error and energy_rms; NaN where their inputs are not connected."""
        frames = len(energy)
        nothing = np.full(frames, np.nan)
        given = {"fitted": fitted, "model": model, "camera": camera, "landmarks": landmarks}
        if all(v is None for v in given.values()):
            if boxes is not None:
                raise InputError("boxes", "expected fitted, model, camera and landmarks with boxes for the "
                                          "energy check, found none of them connected")
            return nothing, nothing
        absent = [name for name, v in given.items() if v is None]
        if absent:
            raise InputError(absent[0], "expected fitted, model, camera and landmarks together for the "
                             f"absolute checks, found {', '.join(absent)} not connected")
        k = len(model.expression_names)
        if fitted.values.shape != (frames, 12 + k):
            raise InputError("fitted", f"expected ({frames}, {12 + k}) pose + {k} weights, found "
                             f"{fitted.values.shape}")
        if landmarks.points.shape != (frames, 68, 2):
            raise InputError("landmarks", f"expected ({frames}, 68, 2) plate landmarks, found "
                             f"{landmarks.points.shape}")
        if boxes is not None and boxes.values.shape != (frames, 4):
            raise InputError("boxes", f"expected ({frames}, 4) x0 y0 x1 y1 boxes, found {boxes.values.shape}")
        return absolute_errors(fitted.values, model, camera, landmarks.points, energy,
                               None if boxes is None else boxes.values)


def absolute_errors(fitted: np.ndarray, model: FaceModel, camera: Camera, points: np.ndarray, energy: np.ndarray,
                    boxes: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The absolute checks' measures of a fit against the plate (fit.FlagFailures, fit.RigidPose's retry).

    Args:
        fitted: (F, 12 + K) pose + weights; model, camera: the fit's; points: (F, 68, 2) the
            plate's landmarks, pixels; energy: (F,) final energies, 256-crop pixel^2; boxes:
            (F, 4) the crop boxes, or None.
    Returns:
        (F,) `reprojection_error` and (F,) `energy_rms` (NaN without boxes), in eye distances.
    """
    projection = projected_landmarks68(fitted, model, camera)
    reprojection = reprojection_error(projection, points)
    if boxes is None:
        return reprojection, np.full(len(energy), np.nan)
    return reprojection, energy_rms(energy, boxes, projection.eye_px)


READ_BATCH = 8
"""Frames rendered and read at once by `read_fitted_landmarks`."""


def read_fitted_landmarks(fm, landmarks: Landmarks2D, boxes: ParamSequence, camera: Camera, fitted: np.ndarray,
                          network, device: str, usable: np.ndarray | None = None) -> np.ndarray:
    """The face mesh's 68 points on renders of the fitted head, in the camera's crop boxes.

    The render is made as the fit makes it (`views.render_crops`: the plate's crop box, its
    sharpness and noise, the fit's appearance), so these are the points the fit's deep energy
    compared with the plate's: the fitted head's landmarks in the network's own convention. A
    contour point lies on the head's silhouette as it turns, and a brow where the painted brow is,
    unlike the model's fixed landmark vertices (`projected_landmarks68`).

    Args:
        fm: the fit's `FitModel` (identity and appearance applied); landmarks, boxes, camera: the
            plate's points (which frames saw the face), crop boxes and camera; fitted: (F, 12 + K)
            pose + weights (fit.Expression's `fitted`); network: the face mesh; usable: (F,)
            frames to read (default all: a frame is read where its fit is finite and the face seen).
    Returns:
        (F, 68, 2) float64 image pixels (centres at integers); NaN rows where not read.
    """
    import torch

    from ..geometry.image import crop_to_image
    from .views import network_points, render_crops

    k = fitted.shape[1] - 12
    views = _views([landmarks], [boxes], [camera], device)
    ok = np.isfinite(fitted).all(1) & views.seen[:, 0].cpu().numpy()
    if usable is not None:
        ok &= usable
    out = np.full((len(fitted), 68, 2), np.nan)
    index = np.flatnonzero(ok)
    size = int(network.input_size)
    for start in range(0, len(index), READ_BATCH):
        sel = index[start:start + READ_BATCH]
        state = _state_from(fitted[sel, :12], fitted[sel, 12:12 + k], device)
        sub = _views([landmarks], [boxes], [camera], device, select=sel)
        with torch.no_grad():
            crop, _, _ = render_crops(fm, sub, fm.vertices(state.weights, state.rot, state.trans))
            points, _ = network_points(crop, network)
            points = crop_to_image(points.reshape(len(sel), 1, 68, 2), sub.boxes[:, :1], size)[:, 0]
        out[sel] = points.double().cpu().numpy()
    return out


class FittedLandmarks(Node):
    """The fitted head's 68 points as the face mesh reads them on its render (the fit's landmarks).

    The model's 68 landmark vertices are fixed on the surface: its jaw line is not where a turned
    head's silhouette is, and its brows are where the mean head's are, not where this person's
    are. These points are read by the landmark network on a render of the fitted head, made as the
    fit renders it (the plate's crop box and sharpness, the fit's appearance, the painted albedo
    where there is one), so they follow the network's landmark convention (human annotations of
    real photos are closer to it than to the fixed vertices) and differ from the plate's points
    only by what the fit did not explain. skimage's astronaut and matplotlib's grace_hopper
    through graphs/fit_video.json: these points lie 1.1 and 1.3% of the eye distance from the
    plate's (mean over the 68), the fixed vertices 5.8 and 6.2% (brows 8.8 and 12.9%).
    """

    type_name = "fit.FittedLandmarks"
    version = 1
    kind = FRAMEWISE
    resources = {"gpu": 1}
    torch_threads = 1

    fitted = In(ParamSequence, doc="From fit.Expression (or a smoothed fit): pose + weights.")
    landmarks = In(Landmarks2D, doc="(F, 68, 2) the first camera's plate landmarks (which frames saw the face).")
    boxes = In(ParamSequence, doc="(F, 4) the first camera's crop boxes.")
    camera = In(Camera, doc="The first camera.")
    model = In(FaceModel, doc="The fitted model (identity applied).")
    appearance = In(JsonValue, optional=True, doc="Albedo and lighting of the fit's renders (default if absent).")
    flags = In(ParamSequence, optional=True, doc="Frames flagged failed (fit.FlagFailures) are not read.")
    landmarks68 = Out(Landmarks2D, doc="(F, 68, 2) the fitted head's points, image pixels; NaN where the frame "
                      "has no fit, no face or failed.")

    def run(self, fitted: ParamSequence, landmarks: Landmarks2D, boxes: ParamSequence, camera: Camera,
            model: FaceModel, appearance: JsonValue | None = None,
            flags: ParamSequence | None = None) -> dict[str, Landmarks2D]:
        from ..landmarks.network import load_face_mesh

        frames = len(self.frames)
        k = len(model.expression_names)
        if fitted.values.shape != (frames, 12 + k):
            raise InputError("fitted", f"expected ({frames}, {12 + k}) pose + {k} weights, found "
                             f"{fitted.values.shape}")
        usable = None if flags is None else ~flags_to_mask(flags, frames, where="flags")
        points = read_fitted_landmarks(_fit_model(model, appearance, self.device), landmarks, boxes, camera,
                                       fitted.values.astype(np.float64), load_face_mesh(self.device), self.device,
                                       usable)
        read = np.isfinite(points).all((1, 2))
        return {"landmarks68": Landmarks2D(points.astype(np.float32), read[:, None].repeat(68, 1).astype(np.float32))}


class SaveFit(Node):
    """Write the fit to one NPZ: rotation, translation (cm), weights, identity, failed (and why), the fit's 68 points.

    `landmarks68` are the fitted head's points as the network reads them on its render
    (fit.FittedLandmarks) where that input is connected, with the model's fixed landmark
    vertices projected beside them as `landmarks68_vertices`; without it, the projected vertices.
    """

    type_name = "fit.SaveFit"
    version = 3  # 2: failed_reason, failure_reasons, reprojection and energy_rms from fit.FlagFailures 2's flags;
    # 3: optional `landmarks68` (fit.FittedLandmarks) saved as landmarks68, the vertices as landmarks68_vertices
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination .npz file.")

        @field_validator("path")
        @classmethod
        def _npz(cls, value: str) -> str:
            return check_output_suffix(value, (".npz",))

    fitted = In(ParamSequence, doc="From fit.Expression.")
    flags = In(ParamSequence, doc="From fit.FlagFailures.")
    energy = In(ParamSequence, doc="From fit.Expression.")
    identity = In(JsonValue, doc="From fit.EstimateIdentity.")
    model = In(FaceModel, doc="The fitted model (identity applied).")
    camera = In(Camera, doc="The first camera (the landmark vertices are projected into it).")
    landmarks68 = In(Landmarks2D, optional=True, doc="(F, 68, 2) the fitted head's points read on its render "
                     "(fit.FittedLandmarks), saved as landmarks68.")
    files = Out(Files, doc="The NPZ written.")

    def run(self, fitted: ParamSequence, flags: ParamSequence, energy: ParamSequence, identity: JsonValue,
            model: FaceModel, camera: Camera, landmarks68: Landmarks2D | None = None) -> dict[str, Files]:
        path = self.params.path
        v = fitted.values
        k = len(model.expression_names)
        if v.shape[1] != 12 + k:
            raise InputError("fitted", f"expected {12 + k} columns (pose + {k} weights), found {v.shape[1]}")
        rot = v[:, :9].reshape(-1, 3, 3)
        trans = v[:, 9:12]
        weights = v[:, 12:]
        pts = projected_landmarks68(v, model, camera).pixels
        arrays = {"rotation": rot.astype(np.float32), "translation": trans.astype(np.float32),
                  "weights": weights.astype(np.float32), "expression_names": np.array(model.expression_names),
                  "identity": np.asarray(identity.value["identity"], np.float32),
                  "failed": flags_to_mask(flags, len(v), where="flags"),
                  "energy": energy.values[:, 0].astype(np.float32),
                  "landmarks68": pts.astype(np.float32),
                  "frames": np.arange(self.frames.start, self.frames.stop, dtype=np.int64)}
        if landmarks68 is not None:
            if landmarks68.points.shape != (len(v), 68, 2):
                raise InputError("landmarks68", f"expected ({len(v)}, 68, 2) points (fit.FittedLandmarks), found "
                                 f"{landmarks68.points.shape}")
            arrays["landmarks68_vertices"] = arrays["landmarks68"]
            arrays["landmarks68"] = landmarks68.points.astype(np.float32)
        if "reason" in flags.names:  # fit.FlagFailures 2
            arrays["failed_reason"] = np.nan_to_num(flags.values[:, flags.names.index("reason")]).astype(np.int64)
            arrays["failure_reasons"] = np.array(FIT_FAILURE_REASONS)
            for name in ("reprojection", "energy_rms"):
                arrays[name] = flags.values[:, flags.names.index(name)].astype(np.float32)
        write_npz_atomic(path, arrays)
        return {"files": files_value([path])}


class FitReport(Node):
    """One PNG per frame: the render blended over the plate, plate landmarks (green; grey where their
    confidence is 0, a failed frame's weak read) and the fitted head's (red, `read_fitted_landmarks`)."""

    type_name = "fit.FitReport"
    version = 4  # 4: optional `fitted_landmarks` (fit.FittedLandmarks: not read a second time);
    # 3: plate points of confidence 0 (landmarks.TrackFaces 8's weak reads) drawn grey
    kind = FRAMEWISE
    writes_files = True
    resources = {"gpu": 1}

    class Params(NodeParams):
        folder: str = Param(..., output_file=True, description="Folder of fit.%04d.png files.")
        blend: float = Param(0.5, ge=0, le=1, description="Opacity of the render over the plate.")
        every: int = Param(1, ge=1, description="Write the frames whose index is a multiple of this (1 = all).")

    images = In(ImageSequence, doc="Plate of the first camera.")
    landmarks = In(Landmarks2D, doc="(F, 68, 2) plate landmarks, pixels.")
    boxes = In(ParamSequence, doc="Crop boxes.")
    camera = In(Camera, doc="The first camera.")
    model = In(FaceModel, doc="The fitted model (identity applied).")
    appearance = In(JsonValue, optional=True, doc="Albedo and lighting.")
    fitted = In(ParamSequence, doc="From fit.Expression.")
    flags = In(ParamSequence, doc="From fit.FlagFailures.")
    fitted_landmarks = In(Landmarks2D, optional=True, doc="(F, 68, 2) the fitted head's points from "
                          "fit.FittedLandmarks (the same fit and flags): drawn, not read again on a render.")
    files = Out(Files, doc="The PNGs written by this chunk.")

    def run(self, images: ImageSequence, landmarks: Landmarks2D, boxes: ParamSequence, camera: Camera,
            model: FaceModel, fitted: ParamSequence, flags: ParamSequence,
            appearance: JsonValue | None = None, fitted_landmarks: Landmarks2D | None = None) -> dict[str, Files]:
        import torch

        from ..io.image import write_image
        from ..landmarks.network import load_face_mesh
        from ..landmarks.nodes import network_images, draw_overlay
        from ..render.renderer import render_mesh

        fm = _fit_model(model, appearance, self.device)
        plate = network_images(images)
        k = len(model.expression_names)
        failed = flags_to_mask(flags, len(self.frames), where="flags")
        if fitted_landmarks is not None:
            if fitted_landmarks.points.shape != (len(self.frames), 68, 2):
                raise InputError("fitted_landmarks", f"expected ({len(self.frames)}, 68, 2) points "
                                 f"(fit.FittedLandmarks), found {fitted_landmarks.points.shape}")
            read = fitted_landmarks.points
        else:
            drawn_frames = np.array([frame % self.params.every == 0 for frame in self.frames])
            read = read_fitted_landmarks(fm, landmarks, boxes, camera, fitted.values.astype(np.float64),
                                         load_face_mesh(self.device), self.device, drawn_frames & ~failed)
        written = []
        folder = Path(self.params.folder)
        for i, frame in enumerate(self.frames):
            if frame % self.params.every:
                continue
            img = plate[i]
            weak = not (landmarks.confidence[i] > 0).any()  # a failed frame's best read
            points = [(landmarks.points[i], (0.6, 0.6, 0.6) if weak else (0.0, 1.0, 0.0))]
            v = fitted.values[i]
            if np.isfinite(v).all() and not failed[i]:
                state = _state_from(v[None, :12], v[None, 12:12 + k], self.device)
                with torch.no_grad():
                    verts = fm.vertices(state.weights, state.rot, state.trans)
                    out = render_mesh(verts, fm.faces, torch.as_tensor(camera.world_to_camera, dtype=torch.float32)[None],
                                      torch.tensor([[camera.fx, camera.fy, camera.cx, camera.cy]]), camera.height,
                                      camera.width, albedo=fm.albedo, sh=fm.sh, background=fm.background,
                                      adjacency=fm.adjacency)
                from nodegraph.types import linear_to_srgb

                render = linear_to_srgb(out.image[0].clamp(0, 1).cpu().numpy())
                alpha = self.params.blend * out.alpha[0].cpu().numpy()[..., None]
                img = img * (1 - alpha) + render * alpha
                if np.isfinite(read[i]).all():
                    points.append((read[i], (1.0, 0.0, 0.0)))
            drawn = draw_overlay(img, boxes.values[i], points)
            path = folder / f"fit.{frame:04d}.png"
            with atomic_path(path) as tmp:
                write_image(tmp, drawn, ["R", "G", "B"], "uint8")
            written.append(path)
            self.progress((i + 1) / len(self.frames), f"wrote {path}")
        return {"files": files_value(written)}
