"""What the fit hands on: failure flags, the NPZ, and overlay PNGs.

- `fit.FlagFailures`: frames with no face, whose final energy is far above the shot's median,
  or whose fitted landmarks, projected into the camera, miss the plate's landmarks by more than
  a share of the eye distance (an absolute check, which also holds for a one-frame shot).
- `fit.SaveFit` (NPZ) and `fit.FitReport` (overlay PNGs).

Flags are read through `nodegraph.flags.flags_to_mask`. Torch is imported inside `run()`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Camera, FaceModel, Files, ImageSequence, In, InputError, JsonValue,
                       Landmarks2D, Node, NodeParams, Out, Param, ParamSequence)
from nodegraph.flags import flags_to_mask

from .node_inputs import _fit_model, _state_from, _views
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic

__all__ = ["FIT_FAILURE_REASONS", "MAX_REPROJECTION", "projected_landmarks68", "reprojection_error",
           "FlagFailures", "SaveFit", "FitReport"]

FIT_FAILURE_REASONS = ("", "no face or no pose", "energy above factor x the shot's median",
                       "landmarks reprojected further than max_reprojection of the eye distance")
"""Texts of fit.FlagFailures' `reason` codes (0: not failed), saved by fit.SaveFit as failure_reasons."""

MAX_REPROJECTION = 0.15
"""fit.FlagFailures' default bound on `reprojection_error` (RMS over the 68 points / eye distance).

Measured with graphs/fit_video.json (landmarks.TrackFaces, fit version 6): good fits of real
photos sit at 0.077-0.081 (skimage.data.astronaut(), 512 px, default camera fx 703.354 and fx
703.4), the share of a real face that the 40-component model and its fixed 68 landmark vertices
(jaw line, lips) do not reach; a fit of the model's own landmarks with 0.3 px of noise at 0.005;
a wrong minimum (tests/nodes/fit/test_flag_failures.py: the start turned away from the camera)
at 0.51, and a head behind the camera at inf. The bound is about twice the good real fits."""


def projected_landmarks68(fitted: np.ndarray, model: FaceModel, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The fitted model's 68 landmark vertices projected into a camera, and their depths.

    Args:
        fitted: (F, 12 + K) r00..r22 (row-major, model to world), tx ty tz (cm, world), then the
            model's K expression weights (fit.Expression's `fitted`); NaN rows stay NaN.
        model: the fitted model (identity applied), K expression shapes.
        camera: the camera (world to camera, intrinsics, radial distortion).
    Returns:
        (F, 68, 2) float64 pixels (origin top-left; a point behind the camera projects mirrored
        through the centre, `project_points`) and (F, 68) depths in the camera frame, cm.
    """
    from ..geometry.camera import project_points

    rot = fitted[:, :9].reshape(-1, 3, 3).astype(np.float64)
    trans = fitted[:, 9:12].astype(np.float64)
    points = model.evaluate(np.nan_to_num(fitted[:, 12:]))[:, model.landmarks].astype(np.float64)
    world = np.einsum("fij,flj->fli", rot, points) + trans[:, None]
    w2c = np.asarray(camera.world_to_camera, np.float64)
    pixels = project_points(world, w2c, [camera.fx, camera.fy, camera.cx, camera.cy],
                            [camera.k1, camera.k2] if (camera.k1 or camera.k2) else None)
    return pixels, world @ w2c[2, :3] + w2c[2, 3]


def reprojection_error(projected: np.ndarray, detected: np.ndarray, depth: np.ndarray | None = None) -> np.ndarray:
    """RMS distance between projected and detected 68 landmarks, in eye distances.

    Args:
        projected: (F, 68, 2) the fitted model's landmarks in the image (`projected_landmarks68`), pixels.
        detected: (F, 68, 2) the plate's landmarks, pixels.
        depth: (F, 68) the projected points' depths in the camera, cm, or None.
    Returns:
        (F,) sqrt(mean_l |p_l - d_l|^2) / |d_36 - d_45| (outer eye corners); NaN where either
        is NaN (no face or no pose), inf where a point lies at or behind the camera's plane.

    Example:
        >>> d = np.zeros((1, 68, 2)); d[0, 45, 0] = 10.0
        >>> reprojection_error(d + [0.0, 1.0], d).round(3).tolist()
        [0.1]
    """
    detected = np.asarray(detected, np.float64)
    eye = np.linalg.norm(detected[:, 36] - detected[:, 45], axis=-1)
    rms = np.sqrt(((np.asarray(projected, np.float64) - detected) ** 2).sum(-1).mean(-1))
    error = rms / np.where(eye > 0, eye, np.nan)
    if depth is not None:
        behind = (np.asarray(depth) <= 0).any(-1)  # NaN depths compare False: they stay NaN
        error = np.where(behind & np.isfinite(eye), np.inf, error)
    return error


class FlagFailures(Node):
    """Flag frames with no face, an energy far above the shot's median, or landmarks reprojected far off."""

    type_name = "fit.FlagFailures"
    version = 2  # 2: the absolute reprojection check (fitted, model, camera, landmarks), columns reprojection, reason
    kind = SEQUENCE

    class Params(NodeParams):
        factor: float = Param(4.0, gt=1, description="A frame fails when its energy exceeds factor x the "
                              "median energy of the fitted frames.")
        max_reprojection: float = Param(MAX_REPROJECTION, ge=0, description="A frame fails when the fitted "
                                        "model's 68 landmarks, projected into the camera, miss the plate's by "
                                        "more than this RMS, in eye distances (outer eye corners); needs "
                                        "`fitted`, `model`, `camera` and `landmarks`; 0 = off. This check holds "
                                        "for a one-frame shot, which the median cannot flag. Default: "
                                        "nodes.fit.output_nodes.MAX_REPROJECTION, from measurements.")

    energy = In(ParamSequence, doc="energy per frame (fit.Expression).")
    failed = In(ParamSequence, doc="failed per frame (fit.Expression).")
    fitted = In(ParamSequence, optional=True, doc="From fit.Expression (pose + weights), for the reprojection check.")
    model = In(FaceModel, optional=True, doc="The fitted model (identity applied), for the reprojection check.")
    camera = In(Camera, optional=True, doc="The first camera, for the reprojection check.")
    landmarks = In(Landmarks2D, optional=True, doc="(F, 68, 2) the first camera's plate landmarks, pixels, for "
                   "the reprojection check.")
    flags = Out(ParamSequence, doc="failed: 1 = failed; energy_ratio: energy / median; reprojection: RMS "
                "landmark distance / eye distance (NaN without the check's inputs); reason: why a frame "
                "failed, a code (" + "; ".join(f"{i} {r}" for i, r in enumerate(FIT_FAILURE_REASONS) if i)
                + "; 0: not failed).")

    def run(self, energy: ParamSequence, failed: ParamSequence, fitted: ParamSequence | None = None,
            model: FaceModel | None = None, camera: Camera | None = None,
            landmarks: Landmarks2D | None = None) -> dict[str, ParamSequence]:
        e = energy.values[:, 0].astype(np.float64)
        bad = flags_to_mask(failed, len(e)) | ~np.isfinite(e)
        ok = ~bad
        median = float(np.median(e[ok])) if ok.any() else np.nan
        ratio = e / max(median, 1e-9) if ok.any() else np.full_like(e, np.nan)
        outlier = ok & (ratio > self.params.factor)
        reprojection = self._reprojection(len(e), fitted, model, camera, landmarks)
        far = ok & ~outlier & (self.params.max_reprojection > 0) & ~(reprojection <= self.params.max_reprojection)
        far &= ~np.isnan(reprojection)  # NaN: no check (its inputs absent, or no landmarks on a fitted frame)
        reason = np.select([bad, outlier, far], [1, 2, 3], 0)
        return {"flags": ParamSequence(np.stack([(reason > 0).astype(np.float32), ratio.astype(np.float32),
                                                 reprojection.astype(np.float32), reason.astype(np.float32)], 1),
                                       ["failed", "energy_ratio", "reprojection", "reason"])}

    def _reprojection(self, frames: int, fitted: ParamSequence | None, model: FaceModel | None,
                      camera: Camera | None, landmarks: Landmarks2D | None) -> np.ndarray:
        given = {"fitted": fitted, "model": model, "camera": camera, "landmarks": landmarks}
        if all(v is None for v in given.values()):
            return np.full(frames, np.nan)
        absent = [name for name, v in given.items() if v is None]
        if absent:
            raise InputError(absent[0], "expected fitted, model, camera and landmarks together for the "
                             f"reprojection check, found {', '.join(absent)} not connected")
        k = len(model.expression_names)
        if fitted.values.shape != (frames, 12 + k):
            raise InputError("fitted", f"expected ({frames}, {12 + k}) pose + {k} weights, found "
                             f"{fitted.values.shape}")
        if landmarks.points.shape != (frames, 68, 2):
            raise InputError("landmarks", f"expected ({frames}, 68, 2) plate landmarks, found "
                             f"{landmarks.points.shape}")
        pixels, depth = projected_landmarks68(fitted.values, model, camera)
        return reprojection_error(pixels, landmarks.points, depth)


class SaveFit(Node):
    """Write the fit to one NPZ: rotation, translation (cm), weights, identity, failed (and why), projected 68 points."""

    type_name = "fit.SaveFit"
    version = 2  # 2: failed_reason, failure_reasons and reprojection from fit.FlagFailures 2's flags
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
    camera = In(Camera, doc="The first camera (landmarks68 are projected into it).")
    files = Out(Files, doc="The NPZ written.")

    def run(self, fitted: ParamSequence, flags: ParamSequence, energy: ParamSequence, identity: JsonValue,
            model: FaceModel, camera: Camera) -> dict[str, Files]:
        path = self.params.path
        v = fitted.values
        k = len(model.expression_names)
        if v.shape[1] != 12 + k:
            raise InputError("fitted", f"expected {12 + k} columns (pose + {k} weights), found {v.shape[1]}")
        rot = v[:, :9].reshape(-1, 3, 3)
        trans = v[:, 9:12]
        weights = v[:, 12:]
        pts, _ = projected_landmarks68(v, model, camera)
        arrays = {"rotation": rot.astype(np.float32), "translation": trans.astype(np.float32),
                  "weights": weights.astype(np.float32), "expression_names": np.array(model.expression_names),
                  "identity": np.asarray(identity.value["identity"], np.float32),
                  "failed": flags_to_mask(flags, len(v), where="flags"),
                  "energy": energy.values[:, 0].astype(np.float32),
                  "landmarks68": pts.astype(np.float32),
                  "frames": np.arange(self.frames.start, self.frames.stop, dtype=np.int64)}
        if "reason" in flags.names:  # fit.FlagFailures 2
            arrays["failed_reason"] = np.nan_to_num(flags.values[:, flags.names.index("reason")]).astype(np.int64)
            arrays["failure_reasons"] = np.array(FIT_FAILURE_REASONS)
            arrays["reprojection"] = flags.values[:, flags.names.index("reprojection")].astype(np.float32)
        write_npz_atomic(path, arrays)
        return {"files": files_value([path])}


class FitReport(Node):
    """One PNG per frame: the render blended over the plate, plate landmarks (green) and render landmarks (red)."""

    type_name = "fit.FitReport"
    version = 2
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
    files = Out(Files, doc="The PNGs written by this chunk.")

    def run(self, images: ImageSequence, landmarks: Landmarks2D, boxes: ParamSequence, camera: Camera,
            model: FaceModel, fitted: ParamSequence, flags: ParamSequence,
            appearance: JsonValue | None = None) -> dict[str, Files]:
        import torch

        from ..io.image import write_image
        from ..landmarks.network import load_face_mesh
        from ..landmarks.nodes import network_images, draw_overlay
        from ..render.renderer import render_mesh
        from .views import crop_to_image, network_points, render_crops

        fm = _fit_model(model, appearance, self.device)
        views = _views([landmarks], [boxes], [camera], self.device)
        plate = network_images(images)
        net = load_face_mesh(self.device)
        k = len(model.expression_names)
        failed = flags_to_mask(flags, len(self.frames), where="flags")
        written = []
        folder = Path(self.params.folder)
        for i, frame in enumerate(self.frames):
            if frame % self.params.every:
                continue
            img = plate[i]
            points = [(landmarks.points[i], (0.0, 1.0, 0.0))]
            v = fitted.values[i]
            if np.isfinite(v).all() and not failed[i]:
                state = _state_from(v[None, :12], v[None, 12:12 + k], self.device)
                with torch.no_grad():
                    verts = fm.vertices(state.weights, state.rot, state.trans)
                    out = render_mesh(verts, fm.faces, torch.as_tensor(camera.world_to_camera, dtype=torch.float32)[None],
                                      torch.tensor([[camera.fx, camera.fy, camera.cx, camera.cy]]), camera.height,
                                      camera.width, albedo=fm.albedo, sh=fm.sh, background=fm.background,
                                      adjacency=fm.adjacency)
                    sub = _views([landmarks], [boxes], [camera], self.device, select=np.array([i]))
                    crop, _, _ = render_crops(fm, sub, verts)
                    rp, _ = network_points(crop, net)
                    rp = crop_to_image(rp.reshape(1, 1, 68, 2), sub.boxes, int(net.input_size))[0, 0]
                from nodegraph.types import linear_to_srgb

                render = linear_to_srgb(out.image[0].clamp(0, 1).cpu().numpy())
                alpha = self.params.blend * out.alpha[0].cpu().numpy()[..., None]
                img = img * (1 - alpha) + render * alpha
                points.append((rp.cpu().numpy(), (1.0, 0.0, 0.0)))
            drawn = draw_overlay(img, boxes.values[i], points)
            path = folder / f"fit.{frame:04d}.png"
            with atomic_path(path) as tmp:
                write_image(tmp, drawn, ["R", "G", "B"], "uint8")
            written.append(path)
            self.progress((i + 1) / len(self.frames), f"wrote {path}")
        return {"files": files_value(written)}
