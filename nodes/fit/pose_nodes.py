"""The fit's per-frame stages (paper 2, PAPERS.md §2, `nodes.fit.solve`) and their batch driver.

- `fit.RigidPose`: rigid head pose per frame (translation, then rotation + translation on the
  non-jaw, jaw and all landmarks);
- `fit.Expression`: jaw and mouth weights per frame from the rigid pose (or with it held), and
  the eyeLook weights from the plate's iris centres where they are connected.

Both are framewise (chunks run in parallel); `_run_fit` solves `batch` frames together.
Multi-camera: the list ports `landmarks`, `boxes` and `cameras` take one connection per camera,
in the same order; the energies of the cameras are summed. Pose outputs: rotation (9 values,
row-major R, model to world), translation (cm, world). Torch is imported inside `run()`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from nodegraph import (FRAMEWISE, Camera, FaceModel, ImageSequence, In, InputError, JsonValue, Landmarks2D,
                       MeshSequence, Node, NodeParams, Out, Param, ParamSequence)
from nodegraph.flags import flags_to_mask

from .node_inputs import POSE_NAMES, _checked_plates, _fit_model, _pose_values, _state_from, _views
from .output_nodes import MAX_ENERGY_RMS, MAX_REPROJECTION, absolute_errors
from .tuning import PHOTOMETRIC_WEIGHT, photometric_frame_weights, photometric_weight_for

__all__ = ["RigidPose", "Expression"]


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
                                      "residual, scaled up on noisy plates "
                                      "(nodes.fit.tuning.photometric_weight_for, from the appearance's "
                                      "'plate_noise'); used when `images` is connected; 0 = landmarks only. The "
                                      "default holds the surface where the landmarks are ambiguous without "
                                      "outweighing them (measurements: nodes.fit.tuning.PHOTOMETRIC_WEIGHT).")
    batch: int = Param(8, ge=1, description="Frames solved together (a frame's result is the same in any "
                       "batch: tests/nodes/fit/test_batch_independence.py).", affects_output=False)


def _run_fit(node: Node, stages_kind: str, landmarks: list[Landmarks2D], boxes: list[ParamSequence],
             cameras: list[Camera], model: FaceModel, appearance: JsonValue | None,
             start: np.ndarray | None, images: list[ImageSequence] | None = None,
             iris: list[Landmarks2D] | None = None) -> dict[str, Any]:
    import torch

    from ..landmarks.network import load_face_mesh
    from .solve import (RETRY_YAWS, RIGID_STAGES, expression_stages, eye_stage, fit_stages, initial_pose,
                        refine_backprop, retry_from_starts)

    p = node.params
    torch.manual_seed(node.seed)
    dev = node.device
    eyes = None
    if iris is not None and start is not None and getattr(p, "iris_weight", 0.0) > 0:
        try:
            eyes = eye_stage(model.expression_names, iris_weight=p.iris_weight, prior=p.eye_prior)
        except ValueError as err:
            raise InputError("model", f"to read the iris: {err}") from err
    fm = _fit_model(model, appearance, dev, iris=eyes is not None)
    views = _views(landmarks, boxes, cameras, dev)
    frames = views.seen.shape[0]
    plates = _checked_plates(images, cameras, frames) if images else None
    photo = bool(plates) and p.photometric_weight > 0
    k = len(model.expression_names)
    found = views.seen.any(1).cpu().numpy()
    pose = np.full((frames, 12), np.nan, np.float32)
    weights = np.full((frames, k), np.nan, np.float32)
    energy = np.full(frames, np.nan, np.float32)
    retried = np.full(frames, -1, np.int64)  # -1: not re-solved; else the start kept (retry_from_starts)
    if start is not None:
        found &= np.isfinite(start).all(1)
    network = load_face_mesh(dev)
    idx = np.flatnonzero(found)
    # frames whose plate the albedo was painted from are fitted without the photometric term
    # (tuning.photometric_frame_weights), in batches of their own
    on = photometric_frame_weights(appearance, node.frames.start + idx) > 0 if photo else np.zeros(len(idx), bool)
    batches = [(group[n0:n0 + p.batch], with_photo) for group, with_photo in ((idx[on], True), (idx[~on], False))
               for n0 in range(0, len(group), p.batch)]
    done = 0
    for sel, with_photo in batches:
        sub = _views(landmarks, boxes, cameras, dev, select=sel, plates=plates if with_photo else None,
                     iris=iris if eyes is not None else None)
        if start is None:
            state = initial_pose(fm, sub)
            stages, first_on_landmarks = RIGID_STAGES, True
        else:
            state = _state_from(start[sel, :12], np.nan_to_num(start[sel, 12:12 + k]) if start.shape[1] > 12
                                else np.zeros((len(sel), k), np.float32), dev)
            stages, first_on_landmarks = expression_stages(model.expression_names), False
            if eyes is not None:
                stages = stages + (eyes,)
            if getattr(p, "hold_pose", False):
                stages = tuple(dataclasses.replace(stage, rotation=False, translation=False) for stage in stages)

        def solve(views: Any, state: Any, stages: tuple = stages, first_on_landmarks: bool = first_on_landmarks,
                  with_photo: bool = with_photo) -> tuple[Any, Any]:
            state, e, _ = fit_stages(fm, views, state, stages, network, outer=p.rounds,
                                     first_outer_on_landmarks=first_on_landmarks, prior=getattr(p, "prior", 100.0),
                                     edge_weight=p.edge_weight, eyelid_weight=p.eyelid_weight,
                                     iterations=p.iterations, supersample=p.supersample,
                                     photometric_weight=photometric_weight_for(p.photometric_weight, appearance)
                                     if with_photo else 0.0)
            if p.backprop_steps:
                state, e = refine_backprop(fm, views, state, stages[-1], network, steps=p.backprop_steps,
                                           prior=getattr(p, "prior", 100.0), edge_weight=p.edge_weight,
                                           eyelid_weight=p.eyelid_weight, supersample=p.supersample)
            return state, e

        state, e = solve(sub, state)
        if getattr(p, "retry", False) and start is None:
            wrong = _landed_wrong(_pose_values(state), state.weights.cpu().numpy(), e.cpu().numpy(), model,
                                  cameras, landmarks, boxes, sel)
            state, e, chosen = retry_from_starts(fm, sub, state, e, torch.as_tensor(wrong, device=e.device), solve,
                                                 RETRY_YAWS[1:])  # the first solve started from RETRY_YAWS[0]
            retried[sel] = np.where(wrong, chosen.cpu().numpy(), -1)
        pose[sel] = _pose_values(state)
        weights[sel] = state.weights.cpu().numpy()
        energy[sel] = e.cpu().numpy()
        done += len(sel)
        node.progress(done / max(len(idx), 1), f"{stages_kind}: {done} frames"
                      + (f", {int((retried >= 0).sum())} re-solved from other starts" if (retried >= 0).any() else ""))
    return {"pose": pose, "weights": weights, "energy": energy, "failed": ~found, "retried": retried}


def _landed_wrong(pose: np.ndarray, weights: np.ndarray, energy: np.ndarray, model: FaceModel,
                  cameras: list[Camera], landmarks: list[Landmarks2D], boxes: list[ParamSequence],
                  sel: np.ndarray) -> np.ndarray:
    """(N,) bool: the frames `sel` whose fit fit.FlagFailures' absolute checks would flag.

    The first camera's check, as fit.FlagFailures makes it (`absolute_errors`):
    the fitted 68 landmark vertices projected more than `MAX_REPROJECTION` eye distances RMS
    from the plate's, or (one camera) the energy above `MAX_ENERGY_RMS` eye distances RMS per
    landmark. `pose` (N, 12), `weights` (N, K), `energy` (N,) 256-crop pixel^2 of the frames `sel`.
    """
    reprojection, rms = absolute_errors(np.concatenate([pose, weights], 1), model, cameras[0], landmarks[0].points[sel],
                                        energy, boxes[0].values[sel] if len(cameras) == 1 else None)
    return (reprojection > MAX_REPROJECTION) | (rms > MAX_ENERGY_RMS)  # NaN: not checked


class _RigidParams(_FitParams):
    retry: bool = Param(True, description="Re-solve a frame that landed in a wrong minimum from other starts: "
                        "a frame whose fitted 68 landmarks project more than MAX_REPROJECTION (0.25) eye "
                        "distances RMS from the plate's, or (one camera) whose energy exceeds MAX_ENERGY_RMS "
                        "(0.15) eye distances RMS per landmark (fit.FlagFailures' absolute checks, first "
                        "camera), is solved again from the head turned away and turned 35 deg each way "
                        "(nodes.fit.solve.RETRY_YAWS, each at the depth of the plate's eye distance), keeping "
                        "the lowest final energy; `retried` says which. Other frames: no extra work.")


class RigidPose(Node):
    """Rigid head pose per frame: translation on non-jaw landmarks, then rotation + translation on non-jaw, jaw, all."""

    type_name = "fit.RigidPose"
    version = 8  # 8: a frame the absolute checks flag is solved again from other starts (`retry`, `retried`);
    # 7: no photometric term on painted frames, residual-scale weight; 6: Levenberg-Marquardt, float64
    kind = FRAMEWISE
    resources = {"gpu": 1}
    torch_threads = 1  # the same answer for any thread count (issue 30): chunks run side by side
    Params = _RigidParams

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
    retried = Out(ParamSequence, doc="retried: 1 where the first solve landed in a wrong minimum and the frame "
                  "was solved again from other starts (`retry`); start: the start kept, 0 the first solve's, "
                  "i the i-th of nodes.fit.solve.RETRY_YAWS[1:] (turned away, +35 deg, -35 deg); -1 not retried.")

    def run(self, landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
            model: FaceModel, appearance: JsonValue | None = None,
            images: list[ImageSequence] | None = None) -> dict[str, ParamSequence]:
        out = _run_fit(self, "rigid", landmarks, boxes, cameras, model, appearance, None, images)
        retried = out["retried"]
        return {"pose": ParamSequence(out["pose"], list(POSE_NAMES)),
                "energy": ParamSequence(out["energy"][:, None], ["energy"]),
                "failed": ParamSequence(out["failed"].astype(np.float32)[:, None], ["failed"]),
                "retried": ParamSequence(np.stack([retried >= 0, retried], 1).astype(np.float32),
                                         ["retried", "start"])}


class _ExpressionParams(_FitParams):
    prior: float = Param(100.0, ge=0, description="lambda of the L2 prior on the active weights (the paper's "
                         "1e2), 256-crop pixel^2 per unit weight^2.")
    hold_pose: bool = Param(False, description="Keep the rigid pose of `pose` fixed in every stage (re-estimating "
                            "the expression after temporal smoothing of the rigid motion); frames without "
                            "landmarks then keep the input's values instead of failing.")
    iris_weight: float = Param(1.0, ge=0, description="Weight of each iris centre (the `iris` port) in a last "
                               "stage that solves the eight eyeLook weights from the iris alone (the 68 points "
                               "and the photometric term do not count there; the prior does): the model's iris "
                               "centre, its eyeball's front turned by EYE_RANGE_RAD (30 deg) per unit weight, "
                               "against the plate's; 0 = the eyeLook weights are not solved.")
    eye_prior: float = Param(4.0, ge=0, description="lambda of the L2 prior on the eyeLook weights, 256-crop "
                             "pixel^2 per unit weight^2 (a unit weight moves the iris centre at least 9.4 such "
                             "pixels in tests/nodes/fit/test_eye_look.py's shot, crops 1.3 landmark extents wide, "
                             "so 4 shrinks a clean reading by at most 4%).")


class Expression(Node):
    """Jaw and mouth weights per frame (jaw open; all jaw; jaw + mouth with the rigid pose), from the rigid pose;
    the eyeLook weights from the plate's iris centres when `iris` is connected."""

    type_name = "fit.Expression"
    version = 9  # 9: no photometric term on painted frames, residual-scale weight; 8: outer rounds keep
    # each frame's best state read (fit.solve.fit_stages); 7: eyeLook
    # weights from the iris centres (`iris`); 6: Levenberg-Marquardt in float64
    kind = FRAMEWISE
    resources = {"gpu": 1}
    torch_threads = 1  # the same answer for any thread count (issue 30): chunks run side by side
    skips_unread_outputs = True  # the mesh only when an edge reads it
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
    iris = In(Landmarks2D, many=True, optional=True, doc="(F, 10, 2) iris points, pixels, one per camera in the "
              "same order (landmarks.TrackFaces: the subject's right eye's centre and 4 rim points, then the "
              "left's; NaN where not read): the eyeLook weights are solved from the centres (`iris_weight`).")
    fitted = Out(ParamSequence, doc="r00..r22, tx ty tz (cm), then one column per expression weight.")
    mesh = Out(MeshSequence, doc="(F, V, 3) the fitted head, world frame, cm (the unposed neutral where "
                  "failed: read `failed`).")
    energy = Out(ParamSequence, doc="energy: final deep energy, 256-crop pixel^2 (NaN for passed-through frames).")
    failed = Out(ParamSequence, doc="failed: 1 where no face or no rigid pose.")

    def run(self, landmarks: list[Landmarks2D], boxes: list[ParamSequence], cameras: list[Camera],
            model: FaceModel, pose: ParamSequence, appearance: JsonValue | None = None,
            keep: ParamSequence | None = None, images: list[ImageSequence] | None = None,
            iris: list[Landmarks2D] | None = None) -> dict[str, Any]:
        k = len(model.expression_names)
        start = np.asarray(pose.values, np.float32)
        if start.shape[1] not in (12, 12 + k):
            raise InputError("pose", f"expected 12 columns {POSE_NAMES} or {12 + k} (pose + the model's {k} "
                                     f"weights), found {start.shape[1]}")
        if keep is not None and (keep.num_frames != len(start) or keep.values.shape[1] < 1):
            raise InputError("keep", f"expected ({len(start)}, 1+) flags, found {keep.values.shape}")
        passed = flags_to_mask(keep, len(start), name=keep.names[0] if keep is not None else "", where="keep")
        out = _run_fit(self, "expression", landmarks, boxes, cameras, model, appearance,
                       np.where(passed[:, None], np.nan, start), images, iris or None)
        finite = np.isfinite(start).all(1) if start.shape[1] == 12 + k else np.zeros(len(start), bool)
        through = finite & (passed | (out["failed"] & self.params.hold_pose))
        if through.any():
            out["pose"][through] = start[through, :12]
            out["weights"][through] = start[through, 12:]
            out["failed"] = out["failed"] & ~through
        values = np.concatenate([out["pose"], out["weights"]], 1)
        result = {"fitted": ParamSequence(values, list(POSE_NAMES) + list(model.expression_names)),
                  "energy": ParamSequence(out["energy"][:, None], ["energy"]),
                  "failed": ParamSequence(out["failed"].astype(np.float32)[:, None], ["failed"])}
        if self.wants("mesh"):  # (F, V, 3): 1,800 frames of the ICT head are 577 MB; not made when no edge reads it
            rot = out["pose"][:, :9].reshape(-1, 3, 3)
            verts = model.evaluate(np.nan_to_num(out["weights"])) @ np.swapaxes(np.nan_to_num(rot), 1, 2) \
                + np.nan_to_num(out["pose"][:, None, 9:12])
            verts[out["failed"]] = model.neutral  # meshes must be finite: failed frames hold the unposed neutral
            result["mesh"] = MeshSequence(verts.astype(np.float32), np.asarray(model.faces))
        return result
