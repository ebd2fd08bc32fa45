"""The fit nodes' inputs as the solver's tensors: checked landmarks, boxes, cameras and plates
become `FitViews`, the face model and appearance a `FitModel`, pose sequences `PoseState`s.

Shared by every fit node (`estimation_nodes`, `pose_nodes`, `output_nodes`). A face counts as
found in a view where its landmarks and box are finite and the landmarks' confidence is at least
`_MIN_PRESENCE`. Torch is imported inside the functions that build tensors.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from nodegraph import Camera, FaceModel, ImageSequence, InputError, JsonValue, Landmarks2D, ParamSequence

__all__ = ["POSE_NAMES"]

POSE_NAMES = [f"r{i}{j}" for i in range(3) for j in range(3)] + ["tx", "ty", "tz"]
"""Columns of a pose ParamSequence: row-major rotation (model to world), translation cm."""

_MIN_PRESENCE = 0.5


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
    rgb = dataclasses.replace(images, pixels=pixels[None] if single else pixels).to_linear().rgb()  # these frames only
    return rgb[0] if single else rgb


def _plate_crops(plates: list[np.ndarray], box: np.ndarray, seen: np.ndarray, frames: np.ndarray,
                 device: str) -> Any:
    """(B, C, S, S, 3) linear crops of the plates (`_linear_rgb`, one per camera) at the boxes (B
    selected frames), as the landmark network's input (`crop_and_resize`, S = 192); black where a
    view did not see the face."""
    import torch

    from ..geometry.image import crop_and_resize
    from ..landmarks.network import MESH_SIZE

    b, c = box.shape[:2]
    out = torch.zeros(b, c, MESH_SIZE, MESH_SIZE, 3, device=device)
    for cam, pix in enumerate(plates):
        rows = np.flatnonzero(seen[:, cam])
        if len(rows):
            out[rows, cam] = crop_and_resize(torch.as_tensor(np.ascontiguousarray(pix[frames[rows]], np.float32),
                                                             device=device), box[rows, cam], MESH_SIZE)
    return out


def _checked_plates(images: list[ImageSequence], cameras: list[Camera], frames: int,
                    select: np.ndarray | None = None) -> list[np.ndarray]:
    """The plates as `_linear_rgb` arrays (converted once per run; only the frames `select` when
    given: an identity uses 4 frames of a shot), after checking them against the cameras."""
    if len(images) != len(cameras):
        raise InputError("images", f"expected one plate per camera ({len(cameras)}), found {len(images)}")
    for c, (seq, cam) in enumerate(zip(images, cameras)):
        f, h, w = seq.pixels.shape[:3]
        if f != frames:
            raise InputError("images", f"camera {c}: expected {frames} frames, found {f}")
        if (w, h) != (cam.width, cam.height):
            raise InputError("images", f"camera {c}: expected {cam.width}x{cam.height} plates (the camera's), "
                             f"found {w}x{h}")
    return [_linear_rgb(seq, slice(None) if select is None else np.asarray(select)) for seq in images]


def _iris_centres(iris: list[Landmarks2D], cameras: list[Camera], frames: int) -> np.ndarray:
    """(F, C, 2, 2) iris centres (eye 0 the subject's right) of the `iris` port's (F, 10, 2) points
    (`landmarks.TrackFaces`: each eye's centre, then 4 rim points), NaN where not read."""
    if len(iris) != len(cameras):
        raise InputError("iris", f"expected one iris input per camera ({len(cameras)}), found {len(iris)}")
    for c, points in enumerate(iris):
        if points.points.shape != (frames, 10, 2):
            raise InputError("iris", f"camera {c}: expected ({frames}, 10, 2) iris points (5 per eye, the centre "
                             f"first; landmarks.TrackFaces), found {points.points.shape}")
    return np.stack([points.points[:, [0, 5]] for points in iris], 1).astype(np.float32)


def _views(landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera], device: str,
           select: np.ndarray | None = None, allow_mesh: bool = False,
           plates: list[np.ndarray] | None = None, plates_selected: bool = False,
           iris: list[Landmarks2D] | None = None) -> Any:
    """FitViews of the landmarks: targets (F, C, 68, 2), or with `allow_mesh` and 468-point
    landmarks (F, C, 68 + 400, 2): the 68 Multi-PIE points, then `MESH_EXTRA_POINTS`. With
    `plates` (`_checked_plates`), their crops too (for the photometric term); with `iris`, the
    iris centres (`_iris_centres`; NaN where the face was not seen)."""
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
    centres = _iris_centres(iris, cameras, len(pts)) if iris is not None else None
    frames = np.arange(len(pts)) if select is None else np.asarray(select)
    pts, box, seen = pts[frames], box[frames], seen[frames]
    if centres is not None:
        centres = np.where(seen[..., None, None], centres[frames], np.nan)
    pts = np.where(seen[..., None, None], pts, 0.0)
    box = np.where(seen[..., None], box, np.array([0.0, 0.0, 1.0, 1.0], np.float32))
    t = lambda a: torch.as_tensor(np.asarray(a, np.float32), device=device)  # noqa: E731
    dist = np.array([[c.k1, c.k2] for c in cameras])
    crops = _plate_crops(plates, box, seen, np.arange(len(frames)) if plates_selected else frames, device) \
        if plates else None
    return FitViews(t(pts), t(box), torch.as_tensor(seen, device=device),
                    t(np.stack([c.world_to_camera for c in cameras])),
                    t([[c.fx, c.fy, c.cx, c.cy] for c in cameras]), t(dist) if np.abs(dist).max() > 0 else None,
                    t([[c.width, c.height] for c in cameras]), crops,
                    None if centres is None else t(centres))


def _appearance(model: FaceModel, appearance: JsonValue | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    from ..render.appearance import model_appearance

    try:
        return model_appearance(model, None if appearance is None else appearance.value)
    except ValueError as err:
        raise InputError("appearance", str(err).removeprefix("appearance: ")) from err


def _fit_model(model: FaceModel, appearance: JsonValue | None, device: str, iris: bool = False) -> Any:
    """The FitModel of the model and appearance; with `iris`, its eyes as the eyeLook shapes turn
    them (`nodes.fit.energy.iris_model_points_at_corners`, placed from the eye corners)."""
    from .views import FitModel

    albedo, sh, background, hidden = _appearance(model, appearance)
    faces = np.delete(np.asarray(model.faces), hidden, axis=0)
    if len(model.landmarks) != 68:
        raise InputError("model", f"expected 68 landmark vertices, found {len(model.landmarks)}")
    noise = float(appearance.value.get("noise", 0.0)) if appearance is not None else 0.0
    if not np.isfinite(noise) or noise < 0:
        raise InputError("appearance", f"'noise': expected a standard deviation >= 0, found {noise}")
    fm = FitModel.build(model.neutral, model.expression_deltas, model.expression_names, faces, model.landmarks,
                        albedo, sh, background, device, noise=noise)
    if not iris:
        return fm
    import torch

    from .energy import iris_model_points_at_corners

    front, centres, turns = iris_model_points_at_corners(model.neutral, model.landmarks, list(model.expression_names))
    t = lambda a: torch.as_tensor(a, dtype=torch.float32, device=device)  # noqa: E731
    return dataclasses.replace(fm, iris=t(front), iris_centres=t(centres), iris_turns=t(turns))


def _pose_values(state: Any) -> np.ndarray:
    return np.concatenate([state.rot.detach().cpu().numpy().reshape(-1, 9),
                           state.trans.detach().cpu().numpy()], 1).astype(np.float32)


def _state_from(values: np.ndarray, weights: np.ndarray, device: str) -> Any:
    import torch

    from .solve import PoseState

    t = lambda a: torch.as_tensor(np.ascontiguousarray(a, np.float32), device=device)  # noqa: E731
    return PoseState(t(values[:, :9].reshape(-1, 3, 3)), t(values[:, 9:12]), t(weights))
