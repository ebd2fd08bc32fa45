"""Deep-energy fitting nodes (paper 2, see PAPERS.md §2 and `nodes.fit.solve`).

- `fit.PlateCamera`: a camera JSON file, or (no file) a pinhole from the plate's size and a
  typical field of view (`DEFAULT_FOV_DEG` horizontal).
- `fit.EstimateAppearance`: rigid alignment on a near-neutral frame, then per-vertex albedo
  and SH lighting from the plate (or the default appearance).
- `fit.EstimateIdentity`: the 40 identity components from a few frames (with a prior), from a
  file, or the mean; outputs the model with the identity applied.
- `fit.RigidPose`, `fit.Expression`: the paper's stages, framewise (chunks run in parallel).
- `fit.FlagFailures`: frames whose energy is far above the shot's median, or with no face.
- `fit.SaveFit` (NPZ) and `fit.FitReport` (overlay PNGs).

Multi-camera: the list ports `landmarks`, `boxes` and `cameras` take one connection per
camera, in the same order; the energies of the cameras are summed. Pose outputs: rotation
(9 values, row-major R, model to world), translation (cm, world). Torch is imported inside
`run()`.
"""

from __future__ import annotations

import dataclasses

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import field_validator

from nodegraph import (FRAMEWISE, SEQUENCE, Camera, FaceModel, Files, ImageSequence, In, InputError, JsonValue,
                       Landmarks2D, MeshSequence, Node, NodeParams, Out, Param, ParamSequence)
from nodegraph.files import atomic_path, check_output_suffix, files_value, write_npz_atomic

__all__ = ["DEFAULT_FOV_DEG", "POSE_NAMES", "PlateCamera", "EstimateAppearance", "EstimateIdentity", "RigidPose",
           "Expression", "FlagFailures", "SaveFit", "FitReport"]

DEFAULT_FOV_DEG = 40.0
"""Horizontal field of view of the default camera (no camera file): a typical video or phone
lens (about 50 mm full-frame equivalent is 40 degrees)."""

POSE_NAMES = [f"r{i}{j}" for i in range(3) for j in range(3)] + ["tx", "ty", "tz"]
"""Columns of a pose ParamSequence: row-major rotation (model to world), translation cm."""

_MIN_PRESENCE = 0.5

PHOTOMETRIC_WEIGHT = 500.0
"""Default w_p of the photometric term (`nodes.fit.photometric`). bench/fit.py, seed 0, 16 frames, the
true identity: median rotation 1.73 deg with landmarks only, 1.21 with w_p 68, 0.77 with 500."""

PHOTOMETRIC_REFERENCE_NOISE = 0.005
"""Plate noise (linear) at which `PHOTOMETRIC_WEIGHT` was chosen (bench/fit.py's default)."""


def photometric_weight_for(weight: float, appearance: JsonValue | None) -> float:
    """w_p for the fit of a plate whose noise `fit.EstimateAppearance` measured ('plate_noise').

    The landmark network's reading of a noisy plate jitters more than the photometric term's
    mean over its thousands of samples, so the photometric term's weight grows with the noise:
    `w_p * max(1, noise / PHOTOMETRIC_REFERENCE_NOISE)`. bench/fit.py, seed 0, noise 0.03, 16
    frames: median rotation 3.7 deg with w_p 500, 2.3 with 3000 (the factor, 6). Appearances
    without a measured noise (the default, or an older node's) keep `weight`.
    """
    noise = (appearance.value.get("plate_noise") if appearance is not None else None) or 0.0
    return float(weight) * max(1.0, float(noise) / PHOTOMETRIC_REFERENCE_NOISE)


# -- shared helpers --------------------------------------------------------------------------
def _check_views(landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
                 allow_mesh: bool = False) -> None:
    if not cameras:
        raise InputError("cameras", "expected at least one camera, found none")
    if len(landmarks) != len(cameras) or len(boxes) != len(cameras):
        raise InputError("landmarks", f"expected one landmarks and one boxes input per camera ({len(cameras)}), "
                         f"found {len(landmarks)} landmarks and {len(boxes)} boxes")
    frames = landmarks[0].points.shape[0]
    for c, (lm, bx) in enumerate(zip(landmarks, boxes)):
        if lm.points.shape[1:] != (68, 2) and not (allow_mesh and lm.points.shape[1:] == (468, 2)):
            want = "(F, 68, 2) Multi-PIE points or (F, 468, 2) face-mesh points" if allow_mesh else \
                "(F, 68, 2) Multi-PIE points"
            raise InputError("landmarks", f"camera {c}: expected {want}, found {lm.points.shape}")
        if bx.values.shape != (frames, 4):
            raise InputError("boxes", f"camera {c}: expected ({frames}, 4) x0 y0 x1 y1 boxes, found {bx.values.shape}")
        if lm.points.shape[0] != frames:
            raise InputError("landmarks", f"camera {c}: expected {frames} frames, found {lm.points.shape[0]}")


def _linear_rgb(images: ImageSequence, frames: Any = slice(None)) -> np.ndarray:
    """(F', H, W, 3) linear colour of the frames asked for (one channel repeated for grey plates)."""
    pixels = images.pixels[frames]
    single = pixels.ndim == images.pixels.ndim - 1  # one frame asked for
    plate = dataclasses.replace(images, pixels=pixels[None] if single else pixels).to_linear()  # these frames only
    idx = plate.colour_channels()
    pix = plate.pixels[0] if single else plate.pixels
    return pix[..., idx[:3]] if len(idx) >= 3 else np.repeat(pix[..., idx[:1]], 3, -1)


def _plate_crops(plates: list[np.ndarray], box: np.ndarray, seen: np.ndarray, frames: np.ndarray,
                 device: str) -> Any:
    """(B, C, S, S, 3) linear crops of the plates (`_linear_rgb`, one per camera) at the boxes (B
    selected frames), as the landmark network's input (`crop_and_resize`, S = 192); black where a
    view did not see the face."""
    import torch

    from ..landmarks.network import MESH_SIZE, crop_and_resize

    b, c = box.shape[:2]
    out = torch.zeros(b, c, MESH_SIZE, MESH_SIZE, 3, device=device)
    for cam, pix in enumerate(plates):
        rows = np.flatnonzero(seen[:, cam])
        if len(rows):
            out[rows, cam] = crop_and_resize(torch.as_tensor(np.ascontiguousarray(pix[frames[rows]], np.float32),
                                                             device=device), box[rows, cam], MESH_SIZE)
    return out


def _checked_plates(images: list[ImageSequence], cameras: list[Camera], frames: int) -> list[np.ndarray]:
    """The plates as `_linear_rgb` arrays (converted once per run), after checking them against the cameras."""
    if len(images) != len(cameras):
        raise InputError("images", f"expected one plate per camera ({len(cameras)}), found {len(images)}")
    for c, (seq, cam) in enumerate(zip(images, cameras)):
        f, h, w = seq.pixels.shape[:3]
        if f != frames:
            raise InputError("images", f"camera {c}: expected {frames} frames, found {f}")
        if (w, h) != (cam.width, cam.height):
            raise InputError("images", f"camera {c}: expected {cam.width}x{cam.height} plates (the camera's), "
                             f"found {w}x{h}")
    return [_linear_rgb(seq) for seq in images]


def _views(landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera], device: str,
           select: np.ndarray | None = None, allow_mesh: bool = False,
           plates: list[np.ndarray] | None = None, plates_selected: bool = False) -> Any:
    """FitViews of the landmarks: targets (F, C, 68, 2), or with `allow_mesh` and 468-point
    landmarks (F, C, 68 + 400, 2): the 68 Multi-PIE points, then `MESH_EXTRA_POINTS`. With
    `plates` (`_checked_plates`), their crops too (for the photometric term)."""
    import torch

    from ..landmarks.correspondence import MEDIAPIPE_TO_68, MESH_EXTRA_POINTS
    from .views import FitViews

    _check_views(landmarks, boxes, cameras, allow_mesh)
    if len({lm.points.shape[1] for lm in landmarks}) > 1:
        raise InputError("landmarks", f"expected one landmark scheme for every camera, found "
                         f"{[lm.points.shape[1] for lm in landmarks]} points")
    pts = np.stack([lm.points for lm in landmarks], 1).astype(np.float32)  # (F, C, 68 or 468, 2)
    if pts.shape[2] == 468:
        pts = pts[:, :, np.concatenate([MEDIAPIPE_TO_68, MESH_EXTRA_POINTS])]
    conf = np.stack([lm.confidence.min(1) for lm in landmarks], 1)  # (F, C)
    box = np.stack([b.values for b in boxes], 1).astype(np.float32)
    seen = np.isfinite(pts).all((2, 3)) & np.isfinite(box).all(2) & (conf >= _MIN_PRESENCE)
    frames = np.arange(len(pts)) if select is None else np.asarray(select)
    pts, box, seen = pts[frames], box[frames], seen[frames]
    pts = np.where(seen[..., None, None], pts, 0.0)
    box = np.where(seen[..., None], box, np.array([0.0, 0.0, 1.0, 1.0], np.float32))
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
    dist = np.array([[c.k1, c.k2] for c in cameras])
    crops = _plate_crops(plates, box, seen, np.arange(len(frames)) if plates_selected else frames, device) \
        if plates else None
    return FitViews(t(pts), t(box), torch.as_tensor(seen, device=device),
                    t(np.stack([c.world_to_camera for c in cameras])),
                    t([[c.fx, c.fy, c.cx, c.cy] for c in cameras]), t(dist) if np.abs(dist).max() > 0 else None,
                    t([[c.width, c.height] for c in cameras]), crops)


def _appearance(model: FaceModel, appearance: JsonValue | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from ..render.appearance import model_appearance

    try:
        return model_appearance(model, None if appearance is None else appearance.value)
    except ValueError as err:
        raise InputError("appearance", str(err).removeprefix("appearance: ")) from err


def _fit_model(model: FaceModel, appearance: JsonValue | None, device: str) -> Any:
    from .views import FitModel

    albedo, sh, background, hidden = _appearance(model, appearance)
    faces = np.delete(np.asarray(model.faces), hidden, axis=0)
    if len(model.landmarks) != 68:
        raise InputError("model", f"expected 68 landmark vertices, found {len(model.landmarks)}")
    noise = float(appearance.value.get("noise", 0.0)) if appearance is not None else 0.0
    if not np.isfinite(noise) or noise < 0:
        raise InputError("appearance", f"'noise': expected a standard deviation >= 0, found {noise}")
    return FitModel.build(model.neutral, model.expression_deltas, model.expression_names, faces, model.landmarks,
                          albedo, sh, background, device, noise=noise)


def _pose_values(state: Any) -> np.ndarray:
    return np.concatenate([state.rot.detach().cpu().numpy().reshape(-1, 9),
                           state.trans.detach().cpu().numpy()], 1).astype(np.float32)


def _state_from(values: np.ndarray, weights: np.ndarray, device: str) -> Any:
    import torch

    from .solve import PoseState

    t = lambda a: torch.as_tensor(np.ascontiguousarray(a, np.float32), device=device)  # noqa: E731
    return PoseState(t(values[:, :9].reshape(-1, 3, 3)), t(values[:, 9:12]), t(weights))


class _FitParams(NodeParams):
    iterations: int = Param(10, ge=1, le=500, description="Levenberg-Marquardt iterations per stage (at most).")
    rounds: int = Param(4, ge=1, le=10, description="Outer rounds (render, read with the network, anchor, "
                        "run the stages).")
    edge_weight: float = Param(1.0, ge=0, description="mu of the edge-preserving term on consecutive landmark "
                               "differences.")
    eyelid_weight: float = Param(0.2, ge=0, description="Weight of the eyelid landmarks (others 1).")
    supersample: int = Param(2, ge=1, le=4, description="Supersampling of the renders the network reads.")
    backprop_steps: int = Param(0, ge=0, le=200, description="Extra Adam steps on the deep energy "
                                "backpropagated through the network and the renderer (the paper's literal "
                                "solver; slow on a CPU).")
    photometric_weight: float = Param(PHOTOMETRIC_WEIGHT, ge=0, description="w_p of the photometric term "
                                      "(fit.photometric: the plate at the head's surface points against the "
                                      "render's colour, robust), 256-crop pixel^2 per (0.01 linear)^2 of mean "
                                      "residual, scaled up on noisy plates (fit.nodes.photometric_weight_for, from "
                                      "the appearance's 'plate_noise'); used when `images` is connected; 0 = "
                                      "landmarks only.")
    batch: int = Param(8, ge=1, description="Frames solved together.", affects_output=False)


def _run_fit(node: Node, stages_kind: str, landmarks: list[Landmarks2D], boxes: list[ParamSequence],
             cameras: list[Camera], model: FaceModel, appearance: JsonValue | None,
             start: np.ndarray | None, images: list[ImageSequence] | None = None) -> dict[str, Any]:
    import torch

    from ..landmarks.network import load_face_mesh
    from .solve import RIGID_STAGES, expression_stages, fit_stages, initial_pose, refine_backprop

    p = node.params
    torch.manual_seed(node.seed)
    dev = node.device
    fm = _fit_model(model, appearance, dev)
    views = _views(landmarks, boxes, cameras, dev)
    frames = views.seen.shape[0]
    plates = _checked_plates(images, cameras, frames) if images else None
    photo = bool(plates) and p.photometric_weight > 0
    k = len(model.expression_names)
    found = views.seen.any(1).cpu().numpy()
    pose = np.full((frames, 12), np.nan, np.float32)
    weights = np.full((frames, k), np.nan, np.float32)
    energy = np.full(frames, np.nan, np.float32)
    if start is not None:
        found &= np.isfinite(start).all(1)
    network = load_face_mesh(dev)
    idx = np.flatnonzero(found)
    for n0 in range(0, len(idx), p.batch):
        sel = idx[n0:n0 + p.batch]
        sub = _views(landmarks, boxes, cameras, dev, select=sel, plates=plates if photo else None)
        if start is None:
            state = initial_pose(fm, sub)
            stages, first_on_landmarks = RIGID_STAGES, True
        else:
            state = _state_from(start[sel, :12], np.nan_to_num(start[sel, 12:12 + k]) if start.shape[1] > 12
                                else np.zeros((len(sel), k), np.float32), dev)
            stages, first_on_landmarks = expression_stages(model.expression_names), False
            if getattr(p, "hold_pose", False):
                stages = tuple(dataclasses.replace(stage, rotation=False, translation=False) for stage in stages)
        state, e, _ = fit_stages(fm, sub, state, stages, network, outer=p.rounds,
                                 first_outer_on_landmarks=first_on_landmarks, prior=getattr(p, "prior", 100.0),
                                 edge_weight=p.edge_weight, eyelid_weight=p.eyelid_weight, iterations=p.iterations,
                                 supersample=p.supersample,
                                 photometric_weight=photometric_weight_for(p.photometric_weight, appearance) if photo
                                 else 0.0)
        if p.backprop_steps:
            state, e = refine_backprop(fm, sub, state, stages[-1], network, steps=p.backprop_steps,
                                       prior=getattr(p, "prior", 100.0), edge_weight=p.edge_weight,
                                       eyelid_weight=p.eyelid_weight, supersample=p.supersample)
        pose[sel] = _pose_values(state)
        weights[sel] = state.weights.cpu().numpy()
        energy[sel] = e.cpu().numpy()
        node.progress(min(n0 + p.batch, len(idx)) / max(len(idx), 1), f"{stages_kind}: {n0 + len(sel)} frames")
    return {"pose": pose, "weights": weights, "energy": energy, "failed": ~found}


# -- nodes -----------------------------------------------------------------------------------
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
        return [Path(self.params.path)] if self.params.path else []

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


def _mouth_gaps(landmarks: Landmarks2D, found: np.ndarray) -> np.ndarray:
    """(F,) inner-lip gap over the eye distance; inf where no face was found."""
    from ..landmarks.correspondence import inter_ocular_distance

    pts = landmarks.points.astype(np.float64)
    gap = np.linalg.norm(pts[:, 66] - pts[:, 62], axis=-1) / np.maximum(inter_ocular_distance(pts), 1e-6)
    return np.where(found & np.isfinite(gap), gap, np.inf)


def _near_neutral_frame(landmarks: Landmarks2D, found: np.ndarray) -> int:
    """The detected frame with the least open mouth (inner-lip gap over the eye distance)."""
    return int(np.argmin(_mouth_gaps(landmarks, found)))


def _painting_frames(landmarks: Landmarks2D, found: np.ndarray, count: int, exclude: int) -> np.ndarray:
    """Up to `count` detected frames other than `exclude`, the least open mouths first."""
    gap = _mouth_gaps(landmarks, found)
    gap[exclude] = np.inf
    order = np.argsort(gap, kind="stable")[:max(count, 0)]
    return order[np.isfinite(gap[order])]


def _render_noise(asked: float, plate_noise: float, above: float = 0.02) -> float:
    """fit.EstimateAppearance's render noise: `asked` >= 0 as given, -1 the plate's, -2 the plate's above `above`."""
    if asked >= 0:
        return float(asked)
    if asked == -1 or plate_noise > above:
        return float(plate_noise)
    return 0.0


def view_spread_deg(rot: Any, world_to_camera: Any, seen: Any) -> float:
    """Largest angle (degrees) between the head's orientation in any seen view and in the first.

    Args:
        rot: (B, 3, 3) torch, the frames' head rotations (model to world).
        world_to_camera: (C, 4, 4) torch, the cameras.
        seen: (B, C) bool torch, the views that saw the face.
    Returns:
        0 for a single view; the spread of the directions the head was seen from otherwise (the
        frames' turns and the cameras' placement both count).
    """
    import torch

    from ..geometry.rigid import rotation_angle

    in_cam = world_to_camera[None, :, :3, :3] @ rot[:, None]  # (B, C, 3, 3) model to each camera
    views = in_cam[seen.to(torch.bool)]
    if len(views) < 2:
        return 0.0
    rel = (views[:1].transpose(-1, -2) @ views).detach().cpu().numpy()
    return float(np.degrees(rotation_angle(rel).max()))


LIGHTING_FRAMES = 4
"""Frames fitting the lighting when the albedo is not painted (fit.EstimateAppearance)."""

LIGHT_FIRST_SPREAD = 10.0
"""Degrees of pose spread above which fit.EstimateAppearance keeps the default albedo (albedo 'auto') or
lights before it paints (albedo 'painted')."""

RELATIVE_STEPS = 32
"""Walk steps pooling the albedo's ratio to the default (fit.EstimateAppearance albedo 'relative')."""


def painting_frame_count(noise: float, target: float = 0.01, most: int = 8) -> int:
    """Frames `fit.EstimateAppearance` paints by default, for a plate of `noise` (linear).

    The painting frames' poses come from the landmarks alone, and every later fit aligns the
    plate to the painting (the photometric term), so a painting frame's pose error becomes
    every frame's. On a noisy plate that error is mostly random (bench/fit.py, noise 0.03, 16
    frames: the frames' errors spread 3.6 deg about their median), and n frames divide it by
    about sqrt(n): n = (noise / target)^2, at least 1, at most `most`. On a clean plate the
    error is a bias shared by the frames and one frame (the least open mouth) paints sharper
    (seed 1, noise 0.005: 2.4 deg with 1 frame, 3.2 with 8).
    """
    if not np.isfinite(noise) or noise <= target:
        return 1
    return int(min(max(round((noise / target) ** 2), 1), most))


class EstimateAppearance(Node):
    """Albedo and SH lighting from a near-neutral frame after a rigid alignment (or the default appearance)."""

    type_name = "fit.EstimateAppearance"
    version = 6
    kind = SEQUENCE
    resources = {"gpu": 1}

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
            "wrong. 30-frame synthetic shots seeds 0-5, median rotation with fit.EstimateIdentity version 5 (8 "
            "frames): 'auto' 0.70/0.94/0.78/0.76/0.63/1.03 deg, 'painted' 1.07/1.81/-/0.77/-/2.10. "
            "'painted': the plate divided by the shading at every vertex (see `light_first`); "
            "'relative': the default albedo times the plate's colour ratio to it, pooled over the mesh "
            "(`relative_steps`): the skin's colour from the plate, the features where the model puts them; "
            "'default': the default albedo, only the lighting estimated. 30-frame synthetic shots (random poses), "
            "seeds 0/1/2/5, median rotation: painted 0.98/1.55/1.07/2.38 deg (2.45/1.93/1.39/3.88 without "
            "light_first), 'default' 0.78/0.74/1.78/1.88, 'relative' seeds 1/2/5 1.07/2.07/1.96; on the demo's "
            "near-static shot painted 0.49, 'relative' 2.14, 'default' 2.57.")
        light_first: float = Param(LIGHT_FIRST_SPREAD, ge=0, le=180, description="albedo 'auto': the pose spread "
                                   "(degrees) above which the albedo is the default's; albedo 'painted': when the "
                                   f"first pass's poses of {LIGHTING_FRAMES} frames spread by more than this "
                                   "(degrees from the painting frame's), the passes before the last estimate only "
                                   "the lighting (default albedo, those frames, photometric), so that the pose the "
                                   "albedo is painted at comes from renders lit like the plate, and the last paints "
                                   "under that lighting; else the albedo is painted from the first pass on (a head "
                                   "seen from one direction does not tell the lighting's terms apart). 180 = never "
                                   "(as before version 5; 'auto' then always paints).")
        relative_steps: int = Param(RELATIVE_STEPS, ge=1, le=256, description="albedo 'relative': steps of the "
                                    "mesh walk pooling the ratio's evidence (fit.appearance.estimate_appearance).")
        prior_weight: float = Param(1.0, ge=0, description="Pull of each vertex's albedo toward the default "
                                    "(pixels' worth of evidence).")
        iterations: int = Param(10, ge=1, le=500, description="Levenberg-Marquardt iterations per rigid stage.")
        rounds: int = Param(4, ge=1, le=10, description="Outer rounds of the rigid fit (see fit.RigidPose).")
        frames_used: int = Param(0, ge=0, le=50, description="Frames painted: `frame`, then the detected "
                                 "frames with the least open mouths among the others (each vertex's albedo is "
                                 "their weighted mean; the lighting one fit to all); 0 = from the plate's noise "
                                 "(fit.nodes.painting_frame_count: 1 on a clean plate, up to 8 on a noisy one), "
                                 f"and at least {LIGHTING_FRAMES} for the lighting unless the albedo is 'painted' "
                                 "or 'auto' with light_first 180 (the light, fixed in the world, seen on the head in "
                                 "several poses).")
        passes: int = Param(2, ge=1, le=5, description="Alternations of rigid pose (with the current "
                            "appearance) and appearance (at that pose).")
        noise: float = Param(-2.0, ge=-2, description="Pixel noise (standard deviation, linear) added to the fit's "
                             "renders so that the network reads them as it reads a noisy plate; -1 = the plate's, "
                             "estimated (fit.appearance.estimate_noise); -2 = the plate's where it is above 0.02 "
                             "(where the painted albedo is pooled and so carries little of it), else none. "
                             "bench/fit.py: on a clean plate an albedo painted from one frame already carries the "
                             "plate's noise and adding it hurts (seed 0, noise 0.005: 1.6 -> 2.2 deg); at noise "
                             "0.015 it hurts too (seed 1: 1.4 -> 1.9); at 0.03 it helps (seed 0: 3.7 -> 2.9, seed 2: "
                             "3.6 -> 3.1).")

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
            value = appearance_json(albedo, app.sh, tuple(app.background), hidden)
            value["noise"] = noise
            fm = _fit_model(model, JsonValue(value), self.device)
        value["frame"] = int(frame + self.frames.start)
        painted = pick[:0] if unpainted else pick[:paint_count] if lit_first else pick
        value["frames"] = [int(f + self.frames.start) for f in painted]
        value["albedo_source"] = "default" if unpainted else "relative" if p.albedo == "relative" else "painted"
        value["lighting_frames"] = [int(f + self.frames.start) for f in pick]
        value["plate_noise"] = plate_noise
        value["pose_spread_deg"] = spread
        value["light_first"] = lit_first
        return {"appearance": JsonValue(value)}


IDENTITY_ROUNDS = 6
"""Rounds of fit.EstimateIdentity anchored on a render. The anchors tie the network's points to the
surface, but its contour points slide over the surface as the shape and pose change, so each
round moves only part of the way to the deep energy's minimum: with the true appearance
(30-frame synthetic shot seed 5, 8 frames) the frames' median pitch error was -1.37 deg after 2
rounds, -0.97 after 6 and 12 (prior 100); -1.46, -0.47, -0.37 with prior 30."""

IDENTITY_PRIOR = 30.0
"""lambda_id of fit.EstimateIdentity where its frames see the head from directions spread over more
than `IDENTITY_SPREAD_DEG` (else `IDENTITY_PRIOR_ONE_VIEW`). With 2 rounds a weaker prior than 100
let the unconverged shape drift (pitch worse); with `IDENTITY_ROUNDS` 30 recovers more of the
face's proportions: 30-frame synthetic shots seeds 0-5 with albedo 'auto' and 8 identity frames,
median rotation 0.70/0.94/0.78/0.76/0.63/1.03 deg (prior 100, 2 rounds, painted albedo:
0.98/1.55/1.07/1.14/1.62/2.38). Seed 5 with the true appearance: 0.84 deg at 30 (6 rounds), 1.12
at 10 (12 rounds), 1.52 at 100 (2 rounds); with 2 rounds, 10 and 3 overfit (identity error norm
9.4 and 19.2 against 5.6 at 100)."""

IDENTITY_PRIOR_ONE_VIEW = 100.0
"""lambda_id of fit.EstimateIdentity where its frames see the head from one direction: one view leaves
the shape's depth to the prior. skimage's astronaut (one photo, graphs/fit_video.json): the model's 68
points 0.108 of the eye distance from the network's at 30 (identity norm 22.4), 0.055 at 60, 0.061 at
100 (norm 11.7), 0.070 at 240."""

IDENTITY_SPREAD_DEG = 10.0
"""Spread of the viewing directions (`view_spread_deg`) above which the identity's frames count as
several views (as fit.EstimateAppearance's `light_first`)."""


class EstimateIdentity(Node):
    """The model's identity components: estimated from a few frames (with a prior), read from a file, or the mean."""

    type_name = "fit.EstimateIdentity"
    version = 5
    kind = SEQUENCE
    resources = {"gpu": 1}

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
                                      "shape's depth to the prior; fit.nodes.IDENTITY_PRIOR).")
        iterations: int = Param(15, ge=1, le=500, description="Levenberg-Marquardt iterations per round (at "
                                "most; every frame's unknowns and the identity together).")
        mesh_weight: float = Param(0.25, ge=0, description="Weight of each of the 400 face-mesh points past the "
                                   "68 (landmarks with 468 points only; the 68 weigh 1, eyelids less).")
        rounds: int = Param(IDENTITY_ROUNDS, ge=1, le=20, description="Rounds anchored on a render (after one on "
                            "the model's landmark vertices; see IDENTITY_ROUNDS).")
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
            plates = _checked_plates(images, cameras, views.seen.shape[0]) if images else None
            photo = bool(plates) and appearance is not None and p.photometric_weight > 0
            sub = _views(landmarks, boxes, cameras, self.device, select=pick, allow_mesh=True,
                         plates=plates if photo else None)
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
                                      photometric_weight=p.photometric_weight if photo else 0.0)
        fitted = FaceModel(neutral=model.evaluate(np.zeros(len(model.expression_names)), ident),
                           faces=model.faces, expression_deltas=model.expression_deltas,
                           expression_names=list(model.expression_names), identity_deltas=model.identity_deltas,
                           groups=model.groups, landmarks=model.landmarks, uv=model.uv, uv_faces=model.uv_faces)
        value: dict[str, Any] = {"identity": [float(x) for x in ident]}
        if p.mode == "estimate":
            value.update(identity_prior=float(prior), view_spread_deg=spread)
        return {"fitted_model": fitted, "identity": JsonValue(value)}


class RigidPose(Node):
    """Rigid head pose per frame: translation on non-jaw landmarks, then rotation + translation on non-jaw, jaw, all."""

    type_name = "fit.RigidPose"
    version = 5
    kind = FRAMEWISE
    resources = {"gpu": 1}
    Params = _FitParams

    landmarks = In(Landmarks2D, many=True, doc="(F, 68, 2) plate landmarks, one per camera.")
    boxes = In(ParamSequence, many=True, doc="Crop boxes x0 y0 x1 y1, one per camera.")
    cameras = In(Camera, many=True, doc="The calibrated cameras, in the same order.")
    model = In(FaceModel, doc="The face model (identity applied).")
    appearance = In(JsonValue, optional=True, doc="Albedo and lighting of the renders (default if absent).")
    images = In(ImageSequence, many=True, optional=True, doc="The plates, one per camera in the same order, for "
                "the photometric term (landmarks only when absent).")
    pose = Out(ParamSequence, doc="r00..r22 (model to world), tx ty tz cm; NaN where failed.")
    energy = Out(ParamSequence, doc="energy: final deep energy, 256-crop pixel^2.")
    failed = Out(ParamSequence, doc="failed: 1 where no camera found the face.")

    def run(self, landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
            model: FaceModel, appearance: JsonValue | None = None,
            images: list[ImageSequence] | None = None) -> dict[str, ParamSequence]:
        out = _run_fit(self, "rigid", landmarks, boxes, cameras, model, appearance, None, images)
        return {"pose": ParamSequence(out["pose"], list(POSE_NAMES)),
                "energy": ParamSequence(out["energy"][:, None], ["energy"]),
                "failed": ParamSequence(out["failed"].astype(np.float32)[:, None], ["failed"])}


class _ExpressionParams(_FitParams):
    prior: float = Param(100.0, ge=0, description="lambda of the L2 prior on the active weights (the paper's "
                         "1e2), 256-crop pixel^2 per unit weight^2.")
    hold_pose: bool = Param(False, description="Keep the rigid pose of `pose` fixed in every stage (re-estimating "
                            "the expression after temporal smoothing of the rigid motion); frames without "
                            "landmarks then keep the input's values instead of failing.")


class Expression(Node):
    """Jaw and mouth weights per frame (jaw open; all jaw; jaw + mouth with the rigid pose), from the rigid pose."""

    type_name = "fit.Expression"
    version = 5
    kind = FRAMEWISE
    resources = {"gpu": 1}
    Params = _ExpressionParams

    landmarks = In(Landmarks2D, many=True, doc="(F, 68, 2) plate landmarks, one per camera.")
    boxes = In(ParamSequence, many=True, doc="Crop boxes, one per camera.")
    cameras = In(Camera, many=True, doc="The cameras, in the same order.")
    model = In(FaceModel, doc="The face model (identity applied).")
    appearance = In(JsonValue, optional=True, doc="Albedo and lighting of the renders (default if absent).")
    pose = In(ParamSequence, doc="From fit.RigidPose (12 columns), or a fit (12 + one per expression weight, "
              "the weights then start the solve), e.g. temporally smoothed.")
    images = In(ImageSequence, many=True, optional=True, doc="The plates, one per camera in the same order, for "
                "the photometric term (landmarks only when absent).")
    keep = In(ParamSequence, optional=True, doc="(F, 1+) 1 in column 0: frames passed through unchanged from "
              "`pose` (e.g. frames filled by flow whose plates gave no usable landmarks).")
    fitted = Out(ParamSequence, doc="r00..r22, tx ty tz (cm), then one column per expression weight.")
    mesh = Out(MeshSequence, doc="(F, V, 3) the fitted head, world frame, cm (the unposed neutral where "
                  "failed: read `failed`).")
    energy = Out(ParamSequence, doc="energy: final deep energy, 256-crop pixel^2 (NaN for passed-through frames).")
    failed = Out(ParamSequence, doc="failed: 1 where no face or no rigid pose.")

    def run(self, landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
            model: FaceModel, pose: ParamSequence, appearance: JsonValue | None = None,
            keep: ParamSequence | None = None, images: list[ImageSequence] | None = None) -> dict[str, Any]:
        k = len(model.expression_names)
        start = np.asarray(pose.values, np.float32)
        if start.shape[1] not in (12, 12 + k):
            raise InputError("pose", f"expected 12 columns {POSE_NAMES} or {12 + k} (pose + the model's {k} "
                                     f"weights), found {start.shape[1]}")
        if keep is not None and (keep.num_frames != len(start) or keep.values.shape[1] < 1):
            raise InputError("keep", f"expected ({len(start)}, 1+) flags, found {keep.values.shape}")
        passed = keep.values[:, 0] > 0.5 if keep is not None else np.zeros(len(start), bool)
        out = _run_fit(self, "expression", landmarks, boxes, cameras, model, appearance,
                       np.where(passed[:, None], np.nan, start), images)
        finite = np.isfinite(start).all(1) if start.shape[1] == 12 + k else np.zeros(len(start), bool)
        through = finite & (passed | (out["failed"] & self.params.hold_pose))
        if through.any():
            out["pose"][through] = start[through, :12]
            out["weights"][through] = start[through, 12:]
            out["failed"] = out["failed"] & ~through
        values = np.concatenate([out["pose"], out["weights"]], 1)
        rot = out["pose"][:, :9].reshape(-1, 3, 3)
        verts = model.evaluate(np.nan_to_num(out["weights"])) @ np.swapaxes(np.nan_to_num(rot), 1, 2) \
            + np.nan_to_num(out["pose"][:, None, 9:12])
        verts[out["failed"]] = model.neutral  # meshes must be finite: failed frames hold the unposed neutral
        return {"fitted": ParamSequence(values, list(POSE_NAMES) + list(model.expression_names)),
                "mesh": MeshSequence(verts.astype(np.float32), np.asarray(model.faces)),
                "energy": ParamSequence(out["energy"][:, None], ["energy"]),
                "failed": ParamSequence(out["failed"].astype(np.float32)[:, None], ["failed"])}


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
        bad = failed.values[:, 0] > 0.5
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
                  "failed": flags.values[:, 0] > 0.5, "energy": energy.values[:, 0].astype(np.float32),
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
        written = []
        folder = Path(self.params.folder)
        for i, frame in enumerate(self.frames):
            if frame % self.params.every:
                continue
            img = plate[i]
            points = [(landmarks.points[i], (0.0, 1.0, 0.0))]
            v = fitted.values[i]
            if np.isfinite(v).all() and flags.values[i, 0] < 0.5:
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
