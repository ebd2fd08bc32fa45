"""The fit's per-shot estimates, before the per-frame stages (paper 2, PAPERS.md §2).

- `fit.PlateCamera`: a camera JSON file, or (no file) a pinhole from the plate's size and a
  typical field of view (`DEFAULT_FOV_DEG` horizontal).
- `fit.EstimateAppearance`: rigid alignment on a near-neutral frame, then per-vertex albedo
  and SH lighting from the plate (or the default appearance).
- `fit.EstimateIdentity`: the 40 identity components from a few frames (with a prior), from a
  file, or the mean; outputs the model with the identity applied.

Defaults and the measurements behind them: `nodes.fit.tuning`. Torch is imported inside `run()`.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any, Literal

import numpy as np

from nodegraph import (SEQUENCE, Camera, FaceModel, ImageSequence, In, InputError, JsonValue, Landmarks2D, Node,
                       NodeParams, Out, Param, ParamSequence)

from .frame_selection import _near_neutral_frame, _painting_frames, _render_noise, painting_frame_count, view_spread_deg
from .node_inputs import _MIN_PRESENCE, _appearance, _checked_plates, _fit_model, _linear_rgb, _views
from .tuning import (IDENTITY_PRIOR, IDENTITY_PRIOR_ONE_VIEW, IDENTITY_ROUNDS, IDENTITY_SPREAD_DEG, LIGHT_FIRST_SPREAD,
                     LIGHTING_FRAMES, PHOTOMETRIC_WEIGHT, RELATIVE_STEPS, photometric_frame_weights)

__all__ = ["DEFAULT_FOV_DEG", "PlateCamera", "EstimateAppearance", "EstimateIdentity"]

DEFAULT_FOV_DEG = 40.0
"""Horizontal field of view of the default camera (no camera file): a typical video or phone
lens (about 50 mm full-frame equivalent is 40 degrees)."""


class PlateCamera(Node):
    """The plate's camera: a camera file, or a pinhole from the image size and a typical field of view."""

    type_name = "fit.PlateCamera"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param("", input_file=True, description="Camera file (our JSON, OpenCV YAML/JSON); '' = "
                          "a pinhole at the origin looking down +z with the plate's size.")
        fov_deg: float = Param(DEFAULT_FOV_DEG, gt=1, lt=170, description="Horizontal field of view of the "
                               "default camera, degrees.")

    images = In(ImageSequence, doc="The plate (its size).")
    camera = Out(Camera, doc="The camera (OpenCV convention, cm).")

    def input_files(self, frames: range | None = None) -> list[Path]:
        """The camera file, read once while planning so that a malformed one is refused before the
        plate is read and its faces followed (it was refused only after landmarks.TrackFaces ran)."""
        if not self.params.path:
            return []
        path = Path(self.params.path)
        if path.is_file():
            from ..io.camera import load_camera

            load_camera(self.params.path)
        return [path]

    def run(self, images: ImageSequence) -> dict[str, Camera]:
        h, w = images.pixels.shape[1:3]
        if not self.params.path:
            return {"camera": Camera.from_fov(int(w), int(h), self.params.fov_deg)}
        from ..io.camera import load_camera

        cam = load_camera(self.params.path)
        if (cam.width, cam.height) != (w, h):
            raise InputError("images", f"expected {cam.width} x {cam.height} images (camera '{self.params.path}'), "
                             f"found {w} x {h}")
        return {"camera": cam}


def _appearance_arrays(albedo: np.ndarray, sh: np.ndarray, background: np.ndarray, hidden: np.ndarray,
                       noise: float) -> dict[str, Any]:
    """`appearance_json`'s value with its albedo and sh as the float64 arrays its lists hold (rounded
    the same way): `_fit_model` reads the same float32 values from either, without the lists (a
    pass of fit.EstimateAppearance made its (V, 3) list and read it back, 0.1 s, for the next pass only)."""
    return {"albedo": np.round(np.asarray(albedo, np.float64), 5), "sh": np.round(np.asarray(sh, np.float64), 6),
            "background": [float(c) for c in background], "hidden_faces": [int(i) for i in hidden],
            "noise": float(noise)}


class EstimateAppearance(Node):
    """Albedo and SH lighting from a near-neutral frame after a rigid alignment (or the default appearance)."""

    type_name = "fit.EstimateAppearance"
    version = 7  # 7: the photometric term's residual-scale weight (photometric.RESIDUAL_SCALE_REFERENCE)
    kind = SEQUENCE
    resources = {"gpu": 1}
    torch_threads = 1  # the same answer for any thread count (issue 30): chunks run side by side

    class Params(NodeParams):
        mode: Literal["estimate", "default"] = Param("estimate", description="estimate from the plate, or the "
                                                     "default appearance (render.DefaultAppearance's).")
        frame: int = Param(-1, ge=-1, description="Frame (index in the shot) to estimate from; -1 = the "
                           "detected frame with the least open mouth.")
        albedo: Literal["auto", "painted", "relative", "default"] = Param(
            "auto", description="'auto': 'default' where the head turns (the first pass's poses of "
            f"{LIGHTING_FRAMES} frames spread by more than `light_first` degrees), else 'painted'. A turning "
            "head shows the lighting, and an albedo painted at one pose locks that pose's error into every later "
            "fit (the painted texture reproduces the plate there, so the landmark and photometric terms both hold "
            "it); one view does not tell the lighting's terms apart, and painting absorbs what the lighting gets "
            "wrong. 'painted': the plate divided by the shading at every vertex (see `light_first`); "
            "'relative': the default albedo times the plate's colour ratio to it, pooled over the mesh "
            "(`relative_steps`): the skin's colour from the plate, the features where the model puts them; "
            "'default': the default albedo, only the lighting estimated. 'auto' is the default because it was "
            "the most accurate on turning synthetic shots and close to 'painted' on near-static ones "
            "(measurements: nodes.fit.tuning).")
        light_first: float = Param(LIGHT_FIRST_SPREAD, ge=0, le=180, description="albedo 'auto': the pose spread "
                                   "(degrees) above which the albedo is the default's; albedo 'painted': when the "
                                   f"first pass's poses of {LIGHTING_FRAMES} frames spread by more than this "
                                   "(degrees from the painting frame's), the passes before the last estimate only "
                                   "the lighting (default albedo, those frames, photometric), so that the pose the "
                                   "albedo is painted at comes from renders lit like the plate, and the last paints "
                                   "under that lighting; else the albedo is painted from the first pass on (a head "
                                   "seen from one direction does not tell the lighting's terms apart). 180 = never "
                                   "('auto' then always paints).")
        relative_steps: int = Param(RELATIVE_STEPS, ge=1, le=256, description="albedo 'relative': steps of the "
                                    "mesh walk pooling the ratio's evidence (fit.appearance.estimate_appearance).")
        prior_weight: float = Param(1.0, ge=0, description="Pull of each vertex's albedo toward the default "
                                    "(pixels' worth of evidence).")
        iterations: int = Param(10, ge=1, le=500, description="Levenberg-Marquardt iterations per rigid stage.")
        rounds: int = Param(4, ge=1, le=10, description="Outer rounds of the rigid fit (see fit.RigidPose).")
        frames_used: int = Param(0, ge=0, le=50, description="Frames painted: `frame`, then the detected "
                                 "frames with the least open mouths among the others (each vertex's albedo is "
                                 "their weighted mean; the lighting one fit to all); 0 = from the plate's noise "
                                 "(nodes.fit.frame_selection.painting_frame_count: 1 on a clean plate, where one "
                                 "frame paints sharpest, up to 8 on a noisy one, where more frames average the "
                                 f"painting frames' pose errors), and at least {LIGHTING_FRAMES} for the lighting "
                                 "unless the albedo is 'painted' or 'auto' with light_first 180 (the light, fixed in "
                                 "the world, seen on the head in several poses).")
        passes: int = Param(2, ge=1, le=5, description="Alternations of rigid pose (with the current "
                            "appearance) and appearance (at that pose).")
        noise: float = Param(-2.0, ge=-2, description="Pixel noise (standard deviation, linear) added to the fit's "
                             "renders so that the network reads them as it reads a noisy plate; -1 = the plate's, "
                             "estimated (fit.appearance.estimate_noise); -2 = the plate's where it is above 0.02 "
                             "(where the painted albedo is pooled and so carries little of it), else none: an "
                             "albedo painted from one frame of a clean plate already carries the plate's noise, "
                             "and adding it there made the fit worse (measurements: nodes.fit.tuning).")

    images = In(ImageSequence, doc="Plate of the first camera.")
    landmarks = In(Landmarks2D, doc="(F, 68, 2) plate landmarks of the first camera, pixels.")
    boxes = In(ParamSequence, doc="x0 y0 x1 y1 crop boxes of the first camera.")
    camera = In(Camera, doc="The first camera.")
    model = In(FaceModel, doc="The face model (identity applied, if known).")
    appearance = Out(JsonValue, doc="{'albedo': V x 3, 'sh': 9 x 3, 'background': 3, 'hidden_faces': [...], "
                     "'noise': the noise added to the fit's renders; mode 'estimate': 'plate_noise' (the plate's, "
                     "estimated), 'frame' (the first frame painted), 'frames' (all the frames painted), "
                     "'lighting_frames' (the frames the lighting was fitted to), 'pose_spread_deg' and 'light_first' "
                     "(see `light_first`), 'albedo_source' ('painted', 'relative' or 'default': what the albedo is)}.")

    def run(self, images: ImageSequence, landmarks: Landmarks2D, boxes: ParamSequence, camera: Camera,
            model: FaceModel) -> dict[str, JsonValue]:
        from ..render.appearance import appearance_json
        from .appearance import estimate_noise

        p = self.params
        albedo0, sh0, bg0, hidden = _appearance(model, None)
        found = np.isfinite(boxes.values).all(1) & (landmarks.confidence.min(1) >= _MIN_PRESENCE)
        if p.mode == "default":
            value = appearance_json(albedo0, sh0, tuple(bg0), hidden)
            value["noise"] = float(p.noise)
            if p.noise < 0:  # the plate's noise: in the frame asked for, or the least open mouth's, or the first
                frame = p.frame - self.frames.start if p.frame >= 0 else \
                    (_near_neutral_frame(landmarks, found) if found.any() else 0)
                if not 0 <= frame < len(found):
                    raise InputError("frame", f"expected a frame of the shot ({self.frames.start}.."
                                     f"{self.frames.start + len(found) - 1}), found {p.frame}")
                value["noise"] = _render_noise(p.noise, estimate_noise(_linear_rgb(images, frame)))
            return {"appearance": JsonValue(value)}
        if not found.any():
            raise InputError("landmarks", "expected a frame with a face to estimate the appearance from, found none")
        frame = _near_neutral_frame(landmarks, found) if p.frame < 0 else p.frame - self.frames.start
        if not 0 <= frame < len(found) or not found[frame]:
            raise InputError("landmarks", f"expected a face in frame {p.frame}, found none")
        plate_noise = estimate_noise(_linear_rgb(images, frame))
        noise = _render_noise(p.noise, plate_noise)
        paint_count = p.frames_used or painting_frame_count(plate_noise)
        try_lit_first = p.albedo in ("auto", "painted") and p.light_first < 180
        paints_one = p.albedo in ("auto", "painted") and not try_lit_first
        count = p.frames_used or max(paint_count, 1 if paints_one else LIGHTING_FRAMES)
        lit_first, spread = False, 0.0
        pick = np.concatenate([[frame], _painting_frames(landmarks, found, count - 1, exclude=frame)]).astype(int)
        plates = _linear_rgb(images, pick)  # only the frames painted (a shot's plates can be gigabytes)
        from ..landmarks.network import load_face_mesh
        from .appearance import albedo_smoothing_steps, estimate_appearance
        from .solve import RIGID_STAGES, PoseState, fit_stages, initial_pose

        fm = _fit_model(model, None, self.device)
        views = _views([landmarks], [boxes], [camera], self.device, select=pick,
                       plates=[plates] if len(pick) > 1 else None, plates_selected=True)
        net = load_face_mesh(self.device)
        dist = np.array([camera.k1, camera.k2]) if (camera.k1 or camera.k2) else None
        intrinsics = np.array([camera.fx, camera.fy, camera.cx, camera.cy])
        smooth = albedo_smoothing_steps(plate_noise)
        state = initial_pose(fm, views)
        for n in range(p.passes):  # alternate: pose with the current appearance, then appearance at that pose
            # after the first pass, several frames' poses also fit the plate to the painting (photometric)
            photo = PHOTOMETRIC_WEIGHT if n > 0 and len(pick) > 1 else 0.0
            state, _, _ = fit_stages(fm, views, state, RIGID_STAGES, net, outer=p.rounds, iterations=p.iterations,
                                     first_outer_on_landmarks=n == 0, photometric_weight=photo)
            if n == 0 and try_lit_first:  # light first where the frames see the head from several directions
                spread = view_spread_deg(state.rot, views.world_to_camera, views.seen)
                lit_first = spread > p.light_first and (p.passes > 1 or p.albedo == "auto")
                keep = len(pick) if lit_first or p.frames_used else min(paint_count, len(pick))
                if keep < len(pick):  # paint as before: only the painting frames
                    pick, plates = pick[:keep], plates[:keep]
                    views = _views([landmarks], [boxes], [camera], self.device, select=pick,
                                   plates=[plates] if keep > 1 else None, plates_selected=True)
                    state = PoseState(state.rot[:keep], state.trans[:keep], state.weights[:keep])
            verts = fm.vertices(state.weights, state.rot, state.trans).detach().cpu().numpy()
            app = estimate_appearance(plates, verts, fm.faces, camera.world_to_camera, intrinsics, albedo0,
                                      distortion=dist, prior_weight=p.prior_weight, smooth_steps=smooth,
                                      relative_steps=p.relative_steps if p.albedo == "relative" else 0)
            unpainted = p.albedo == "default" or (lit_first and (p.albedo == "auto" or n < p.passes - 1))
            albedo = albedo0 if unpainted else app.albedo
            if lit_first and not unpainted and paint_count < len(pick):  # paint fewer frames, under that light
                albedo = estimate_appearance(plates[:paint_count], verts[:paint_count], fm.faces,
                                             camera.world_to_camera, intrinsics, albedo0, distortion=dist,
                                             prior_weight=p.prior_weight, smooth_steps=smooth, sh=app.sh).albedo
            if n < p.passes - 1:  # the next pass renders with it: the values the JSON holds, as arrays
                fm = _fit_model(model, JsonValue(_appearance_arrays(albedo, app.sh, app.background, hidden, noise)),
                                self.device)
        value = appearance_json(albedo, app.sh, tuple(app.background), hidden)
        value["noise"] = noise
        value["frame"] = int(frame + self.frames.start)
        painted = pick[:0] if unpainted else pick[:paint_count] if lit_first else pick
        value["frames"] = [int(f + self.frames.start) for f in painted]
        value["albedo_source"] = "default" if unpainted else "relative" if p.albedo == "relative" else "painted"
        value["lighting_frames"] = [int(f + self.frames.start) for f in pick]
        value["plate_noise"] = plate_noise
        value["pose_spread_deg"] = spread
        value["light_first"] = lit_first
        return {"appearance": JsonValue(value)}


class EstimateIdentity(Node):
    """The model's identity components: estimated from a few frames (with a prior), read from a file, or the mean."""

    type_name = "fit.EstimateIdentity"
    version = 7  # 7: no photometric term on painted frames, residual-scale weight; 6: Levenberg-Marquardt, float64
    kind = SEQUENCE
    resources = {"gpu": 1}
    torch_threads = 1  # the same answer for any thread count (issue 30): chunks run side by side

    class Params(NodeParams):
        mode: Literal["estimate", "file", "mean"] = Param("estimate", description="estimate, read 'path', or "
                                                         "all zeros (the model's average face).")
        path: str = Param("", input_file=True, description="mode 'file': NPZ with 'identity' [I] or JSON "
                          "{'identity': [...]}.")
        frames_used: int = Param(3, ge=1, le=50, description="Detected frames used (spread over the shot).")
        identity_prior: float = Param(-1.0, ge=-1, description="lambda_id of |identity|^2 (components are N(0, "
                                      "1)), 256-crop pixel^2 per unit^2; <= 0: from the frames' views, "
                                      f"{IDENTITY_PRIOR:g} where a first rigid fit sees the head from directions "
                                      f"spread over more than {IDENTITY_SPREAD_DEG:g} deg (frames turning, or "
                                      f"several cameras), else {IDENTITY_PRIOR_ONE_VIEW:g} (one view leaves the "
                                      "shape's depth to the prior; nodes.fit.tuning.IDENTITY_PRIOR).")
        iterations: int = Param(15, ge=1, le=500, description="Levenberg-Marquardt iterations per round (at "
                                "most; every frame's unknowns and the identity together).")
        mesh_weight: float = Param(0.25, ge=0, description="Weight of each of the 400 face-mesh points past the "
                                   "68 (landmarks with 468 points only; the 68 weigh 1, eyelids less).")
        rounds: int = Param(IDENTITY_ROUNDS, ge=1, le=20, description="Rounds anchored on a render (after one on "
                            "the model's landmark vertices; see nodes.fit.tuning.IDENTITY_ROUNDS).")
        photometric_weight: float = Param(PHOTOMETRIC_WEIGHT, ge=0, description="w_p of the photometric term "
                                          "(as fit.RigidPose's), used when `images` and `appearance` are "
                                          "connected: the frames' poses then constrain the shape as views do.")

    landmarks = In(Landmarks2D, many=True, doc="(F, 68, 2) Multi-PIE or (F, 468, 2) face-mesh plate landmarks "
                   "(the identity then also fits the 400 other face-mesh points: cheeks, forehead, nose), one per "
                   "camera.")
    boxes = In(ParamSequence, many=True, doc="Crop boxes, one per camera.")
    cameras = In(Camera, many=True, doc="The cameras, in the same order.")
    model = In(FaceModel, doc="The face model (mean identity).")
    appearance = In(JsonValue, optional=True, doc="From fit.EstimateAppearance (default appearance if absent).")
    images = In(ImageSequence, many=True, optional=True, doc="The plates, one per camera in the same order, for "
                "the photometric term (with `appearance` only).")
    fitted_model = Out(FaceModel, doc="The model with the identity added to its neutral.")
    identity = Out(JsonValue, doc="{'identity': [I floats]}; mode 'estimate' also 'identity_prior' (the "
                   "lambda_id used) and 'view_spread_deg' (`view_spread_deg` of the frames' first rigid fit).")

    def input_files(self, frames: range | None = None) -> list[Path]:
        return [Path(self.params.path)] if self.params.mode == "file" and self.params.path else []

    def _read(self, count: int) -> np.ndarray:
        path = self.params.path
        if not path:
            raise InputError("path", "mode 'file' expected an identity file, found ''")
        if path.lower().endswith(".npz"):
            with np.load(path) as data:
                if "identity" not in data:
                    raise InputError("path", f"expected an 'identity' array in '{path}', found {sorted(data)}")
                ident = np.asarray(data["identity"], np.float32).reshape(-1)
        else:
            ident = np.asarray(json.loads(Path(path).read_text()).get("identity", []), np.float32).reshape(-1)
        if ident.shape != (count,) or not np.isfinite(ident).all():
            raise InputError("path", f"expected {count} finite identity weights in '{path}', found {ident.shape}")
        return ident

    def run(self, landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
            model: FaceModel, appearance: JsonValue | None = None,
            images: list[ImageSequence] | None = None) -> dict[str, Any]:
        p = self.params
        count = model.identity_deltas.shape[0]
        if p.mode == "mean":
            ident = np.zeros(count, np.float32)
        elif p.mode == "file":
            ident = self._read(count)
        else:
            import torch

            from ..landmarks.correspondence import MESH_EXTRA_POINTS
            from ..landmarks.network import load_face_mesh
            from .identity import solve_identity
            from .solve import RIGID_STAGES, fit_stages, initial_pose

            views = _views(landmarks, boxes, cameras, self.device, allow_mesh=True)
            found = np.flatnonzero(views.seen.any(1).cpu().numpy())
            if not len(found):
                raise InputError("landmarks", "expected frames with a face to estimate the identity from, found none")
            pick = found[np.unique(np.linspace(0, len(found) - 1, min(p.frames_used, len(found))).round().astype(int))]
            fm = _fit_model(model, appearance, self.device)
            plates = _checked_plates(images, cameras, views.seen.shape[0], select=pick) if images else None
            photo = bool(plates) and appearance is not None and p.photometric_weight > 0
            # frames whose plate the albedo was painted from count no photometric term (see the function)
            frame_weight = photometric_frame_weights(appearance, self.frames.start + pick) if photo else None
            photo = photo and bool(frame_weight.any())
            sub = _views(landmarks, boxes, cameras, self.device, select=pick, allow_mesh=True,
                         plates=plates if photo else None, plates_selected=True)
            mesh = sub.target.shape[2] > 68
            sub68 = dataclasses.replace(sub, target=sub.target[:, :, :68])
            net = load_face_mesh(self.device)
            state, _, _ = fit_stages(fm, sub68, initial_pose(fm, sub68), RIGID_STAGES, net, outer=1, iterations=20)
            spread = view_spread_deg(state.rot, sub.world_to_camera, sub.seen)
            prior = p.identity_prior if p.identity_prior > 0 else \
                IDENTITY_PRIOR if spread > IDENTITY_SPREAD_DEG else IDENTITY_PRIOR_ONE_VIEW
            ident, _ = solve_identity(fm, model.identity_deltas, sub, state, net, identity_prior=prior,
                                      iterations=p.iterations, outer=p.rounds,
                                      extra_points=MESH_EXTRA_POINTS if mesh else None,
                                      extra_weight=p.mesh_weight,
                                      photometric_weight=p.photometric_weight if photo else 0.0,
                                      photometric={"frame_weight": torch.as_tensor(frame_weight)}
                                      if photo and not frame_weight.all() else None)
        fitted = FaceModel(neutral=model.evaluate(np.zeros(len(model.expression_names)), ident),
                           faces=model.faces, expression_deltas=model.expression_deltas,
                           expression_names=list(model.expression_names), identity_deltas=model.identity_deltas,
                           groups=model.groups, landmarks=model.landmarks, uv=model.uv, uv_faces=model.uv_faces)
        value: dict[str, Any] = {"identity": [float(x) for x in ident]}
        if p.mode == "estimate":
            value.update(identity_prior=float(prior), view_spread_deg=spread)
        return {"fitted_model": fitted, "identity": JsonValue(value)}
