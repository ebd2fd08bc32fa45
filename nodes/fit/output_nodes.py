"""What the fit hands on: failure flags, the NPZ, and overlay PNGs.

- `fit.FlagFailures`: frames with no face, or whose final energy is far above the shot's median.
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

__all__ = ["FlagFailures", "SaveFit", "FitReport"]


class FlagFailures(Node):
    """Flag frames with no face, or whose final energy is far above the shot's median."""

    type_name = "fit.FlagFailures"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        factor: float = Param(4.0, gt=1, description="A frame fails when its energy exceeds factor x the "
                              "median energy of the fitted frames.")

    energy = In(ParamSequence, doc="energy per frame (fit.Expression).")
    failed = In(ParamSequence, doc="failed per frame (fit.Expression).")
    flags = Out(ParamSequence, doc="failed: 1 = no face or energy outlier; energy_ratio: energy / median.")

    def run(self, energy: ParamSequence, failed: ParamSequence) -> dict[str, ParamSequence]:
        e = energy.values[:, 0].astype(np.float64)
        bad = flags_to_mask(failed, len(e))
        ok = ~bad & np.isfinite(e)
        median = float(np.median(e[ok])) if ok.any() else np.nan
        ratio = e / max(median, 1e-9) if ok.any() else np.full_like(e, np.nan)
        flags = bad | ~np.isfinite(e) | (ratio > self.params.factor)
        return {"flags": ParamSequence(np.stack([flags.astype(np.float32), ratio.astype(np.float32)], 1),
                                       ["failed", "energy_ratio"])}


class SaveFit(Node):
    """Write the fit to one NPZ: rotation, translation (cm), weights, identity, failed, projected 68 points."""

    type_name = "fit.SaveFit"
    version = 1
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
        from ..geometry.camera import project_points

        path = self.params.path
        v = fitted.values
        k = len(model.expression_names)
        if v.shape[1] != 12 + k:
            raise InputError("fitted", f"expected {12 + k} columns (pose + {k} weights), found {v.shape[1]}")
        rot = v[:, :9].reshape(-1, 3, 3)
        trans = v[:, 9:12]
        weights = v[:, 12:]
        lm = model.evaluate(np.nan_to_num(weights))[:, model.landmarks]
        world = np.einsum("fij,flj->fli", rot, lm) + trans[:, None]
        pts = project_points(world.astype(np.float64), camera.world_to_camera,
                             [camera.fx, camera.fy, camera.cx, camera.cy],
                             [camera.k1, camera.k2] if (camera.k1 or camera.k2) else None)
        arrays = {"rotation": rot.astype(np.float32), "translation": trans.astype(np.float32),
                  "weights": weights.astype(np.float32), "expression_names": np.array(model.expression_names),
                  "identity": np.asarray(identity.value["identity"], np.float32),
                  "failed": flags_to_mask(flags, len(v), where="flags"),
                  "energy": energy.values[:, 0].astype(np.float32),
                  "landmarks68": pts.astype(np.float32),
                  "frames": np.arange(self.frames.start, self.frames.stop, dtype=np.int64)}
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
