"""Temporal nodes: flow infill of failed frames and temporal smoothing of fitted parameters.

- `temporal.FlowInfill`: failed frames solved from their good neighbours by plate flow.
- `temporal.Average`: three-frame weighted average (quaternion mean for rotations).
- `temporal.SelfFlow`, `temporal.PlateFlow`: per-frame flow solves against both neighbours.
- `temporal.Hybrid`: averaging, then plate flow (the paper's best).
- `temporal.AdaptiveSmooth`: edge-preserving smoothing of the pose and the weights
  (`nodes.temporal.adaptive`): with the model and the camera, together in the metric of the
  projected 68 landmarks (noise measured there, in pixels); without, each curve by its own
  measured noise. A sequence node (the noise and the smoothing are the shot's).

The others are windowed: a frame's result depends only on frames within the halo, so any chunk size
gives the same result. Parameters use the layout of `nodes.temporal.layout` (rot_x..z
axis-angle rad, trans_x..z cm, weights by shape name). Torch is imported inside `run()`.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np

from nodegraph import (Camera, FaceModel, FlowSequence, In, InputError, JsonValue, Node, NodeParams, Out,
                       ParamSequence, Param)
from nodegraph import SEQUENCE, windowed
from nodegraph.flags import flags_to_mask, mask_to_flags

from .layout import from_unknowns, params_layout, to_unknowns

__all__ = ["FlowInfill", "Average", "SelfFlow", "PlateFlow", "Hybrid", "AdaptiveSmooth", "MAX_GAP", "MAX_SWEEPS"]

MAX_GAP = 8
"""Longest run of failed frames `temporal.FlowInfill` can solve (its halo), frames."""

MAX_SWEEPS = 3
"""Most smoothing sweeps (red-black sweeps reach 2 frames each: halo 2 * MAX_SWEEPS, + 1 for Hybrid)."""

Shapes = Literal["rigid", "jaw_mouth", "all"]


def _shape_ids(names: list[str], which: str) -> list[int]:
    if which == "rigid":
        return []
    if which == "all":
        return list(range(len(names)))
    return [i for i, n in enumerate(names) if n.startswith("jaw") or n.startswith("mouth")]


class _FlowNode(Node):
    """Shared set-up of the flow solves: model, camera, plate flow, layout."""

    resources = {"gpu": 1}

    def _setup(self, params: ParamSequence, model: FaceModel, camera: Camera, plate_flow: FlowSequence,
               shapes: str, stride: int) -> tuple[Any, Any, Any, Any, Any]:
        import torch

        from .flowfit import FlowModel

        try:
            layout = params_layout(params.names, model.expression_names, "fitted")
        except ValueError as err:
            raise InputError("fitted", str(err).removeprefix("fitted: ")) from err
        if plate_flow.flow.shape[1:3] != (camera.height, camera.width):
            raise InputError("plate_flow", f"expected flow of the camera's size ({camera.height}, {camera.width}), "
                             f"found {plate_flow.flow.shape[1:3]}")
        from ..render.appearance import visible_faces

        faces = visible_faces(model.faces, model.neutral.shape[0])
        fm = FlowModel.build(model.neutral, model.expression_deltas, faces, camera.world_to_camera,
                             [camera.fx, camera.fy, camera.cx, camera.cy], camera.height, camera.width,
                             _shape_ids(model.expression_names, shapes), stride=stride, device=self.device)
        x = to_unknowns(params.values, layout)
        have = layout.weights >= 0
        dev = self.device
        flows = torch.as_tensor(plate_flow.flow, dtype=torch.float64, device=dev)
        return fm, torch.as_tensor(x, device=dev), flows, layout, have

    @staticmethod
    def _pack(params: ParamSequence, x: Any, layout: Any, have: np.ndarray) -> ParamSequence:
        return ParamSequence(from_unknowns(x.cpu().numpy(), params.values, layout), list(params.names))


def _render_scene(fm: Any, model: FaceModel, appearance: JsonValue | None, device: str) -> Any:
    """The RenderScene of the optical render flow: the solve's faces, the appearance's albedo and light."""
    from ..flow.dense import FlowSettings
    from ..render.appearance import model_appearance
    from .opticalfit import RenderScene

    try:
        albedo, sh, background, _ = model_appearance(model, None if appearance is None else appearance.value)
    except ValueError as err:
        raise InputError("appearance", str(err).removeprefix("appearance: ")) from err
    return RenderScene.build(fm.faces.cpu().numpy(), albedo, sh, background, FlowSettings(), device)


class _SolveParams(NodeParams):
    shapes: Shapes = Param("jaw_mouth", description="Expression shapes solved with the pose: none ('rigid'), "
                           "ARKit jaw* and mouth* ('jaw_mouth'), or all.")
    iterations: int = Param(8, ge=1, le=50, description="Levenberg-Marquardt iterations per frame solve.")
    stride: int = Param(2, ge=1, le=8, description="Residual pixel stride (1 = every covered pixel).")


class FlowInfill(_FlowNode):
    """Solve frames the fit flagged as failed from their good neighbours by plate flow."""

    type_name = "temporal.FlowInfill"
    version = 1
    kind = windowed(MAX_GAP + 1)  # the run, its good neighbours and their pairs

    class Params(_SolveParams):
        max_gap: int = Param(MAX_GAP, ge=1, le=MAX_GAP, description="Longest run of failed frames solved; "
                             "longer runs stay failed.")
        sweeps: int = Param(1, ge=1, le=4, description="Forward + backward passes over a run.")
        reject_ratio: float = Param(6.0, gt=1, description="A solved frame stays failed when its mean squared "
                                    "plate-flow mismatch is above this many times that of the run's good "
                                    "neighbours (the plate does not follow the face there: no face, an "
                                    "occluder, a cut).")
        floor_px2: float = Param(0.25, gt=0, description="Least neighbour mismatch the ratio is taken of, "
                                 "pixels^2 (exact plate flow has none).")
        render_flow: Literal["geometric", "optical"] = Param(
            "geometric", description="Render flow matched to the plate flow: the exact screen motion of the "
            "model's surface (geometric), or flow.OpticalFlow (default settings, as the plates') on renders of "
            "the fit with `appearance` (optical; far slower; bench/temporal.py compares them).")
        optical_steps: int = Param(6, ge=1, le=100, description="render_flow 'optical': Levenberg-Marquardt "
                                   "iterations per frame solve (finite-difference Jacobian, batched renders and "
                                   "flows).")

    fitted = In(ParamSequence, doc="Fitted parameters (r00..r22 + tx ty tz cm as nodes.fit, or rot_x..z "
                    "rad + trans_x..z cm; weights by shape name).")
    failed = In(ParamSequence, doc="(F, 1+) flags, 1 (or NaN) in the 'failed' column where the fit failed.")
    plate_flow = In(FlowSequence, doc="Optical flow of the plates, frame f -> f + 1 (flow.OpticalFlow).")
    model = In(FaceModel, doc="The face model fitted.")
    camera = In(Camera, doc="The plates' camera.")
    appearance = In(JsonValue, optional=True, doc="render_flow 'optical': albedo and lighting of the renders "
                                                  "(fit.EstimateAppearance); the default appearance if absent.")
    infilled = Out(ParamSequence, doc="Parameters with the solved runs filled in.")
    still_failed = Out(ParamSequence, doc="(F, 1) 1 where frames stayed unsolved.")

    def run(self, fitted: ParamSequence, failed: ParamSequence, plate_flow: FlowSequence, model: FaceModel,
            camera: Camera, appearance: JsonValue | None = None) -> dict[str, ParamSequence]:
        from .sweeps import infill

        p = self.params
        fm, x, flows, layout, have = self._setup(fitted, model, camera, plate_flow, p.shapes, p.stride)
        scene = _render_scene(fm, model, appearance, self.device) if p.render_flow == "optical" else None
        mask = flags_to_mask(failed, len(x))
        at_start = self.frames.start == self.full_frames.start if len(self.full_frames) else True
        at_end = self.frames.stop == self.full_frames.stop if len(self.full_frames) else True
        x, still, _ = infill(fm, x, flows, plate_flow.valid, mask, max_gap=p.max_gap, sweeps=p.sweeps,
                             iterations=p.iterations, at_start=at_start, at_end=at_end,
                             reject_ratio=p.reject_ratio, floor_px2=p.floor_px2, optical=scene,
                             optical_steps=p.optical_steps, progress=self.progress)
        infilled = self._pack(fitted, x, layout, have)
        infilled.values[still] = fitted.values[still]  # unsolved or rejected: the fit's values (NaN if none)
        return {"infilled": infilled, "still_failed": mask_to_flags(still)}


class _SmoothParams(_SolveParams):
    sweeps: int = Param(2, ge=1, le=MAX_SWEEPS, description="Sweeps over the frames.")
    scheme: Literal["jacobi", "red_black"] = Param("jacobi", description="Jacobi (all frames from the "
                                                   "previous sweep) or red-black Gauss-Seidel sweeps.")
    prior_weight: float = Param(0.0, ge=0, description="Weight of the prior toward the input values "
                                "(units 0.01 rad, 0.1 cm, 0.1 weight; squared pixels of mean flow error).")
    shapes: Shapes = Param("rigid", description="Expression shapes solved with the pose ('rigid' = none).")


class _Smooth(_FlowNode):
    kind = windowed(2 * MAX_SWEEPS)
    _plate, _self, _average = 1.0, 0.0, False

    class Params(_SmoothParams):
        pass

    fitted = In(ParamSequence, doc="Parameters (rot_x..z rad, trans_x..z cm, weights by name).")
    plate_flow = In(FlowSequence, doc="Optical flow of the plates, frame f -> f + 1 (flow.OpticalFlow).")
    model = In(FaceModel, doc="The face model fitted.")
    camera = In(Camera, doc="The plates' camera.")
    failed = In(ParamSequence, optional=True, doc="(F, 1+) flags, 1 (or NaN) in the 'failed' column for frames "
                "to leave alone and not use.")
    smoothed = Out(ParamSequence, doc="Smoothed parameters.")

    def run(self, fitted: ParamSequence, plate_flow: FlowSequence, model: FaceModel, camera: Camera,
            failed: ParamSequence | None = None) -> dict[str, ParamSequence]:
        import torch

        from .averaging import average_params
        from .sweeps import smooth

        p = self.params
        fm, x, flows, layout, have = self._setup(fitted, model, camera, plate_flow, p.shapes, p.stride)
        mask = flags_to_mask(failed, len(x))
        prior = x.clone()
        if self._average:
            avg = average_params(x.cpu().numpy(), np.arange(3), np.arange(3, x.shape[1]),
                                 centre_weight=p.centre_weight, failed=mask)
            x = torch.as_tensor(avg, device=x.device)
            if not p.prior_to_raw:
                prior = x.clone()
        x = smooth(fm, x, flows, plate_flow.valid, ~mask, sweeps=p.sweeps, scheme=p.scheme,
                   parity=self.frames.start % 2, iterations=p.iterations, plate_weight=self._plate,
                   self_weight=self._self, prior_weight=p.prior_weight, prior=prior, progress=self.progress)
        smoothed = self._pack(fitted, x, layout, have)
        smoothed.values[mask] = fitted.values[mask]  # left alone: exactly as given (NaN stays NaN)
        return {"smoothed": smoothed}


class PlateFlow(_Smooth):
    """Per-frame plate-flow refinement against both neighbours (render flow matched to plate flow)."""

    type_name = "temporal.PlateFlow"
    version = 1


class SelfFlow(_Smooth):
    """Per-frame self-flow smoothing: render flow into the frame matched to render flow out of it."""

    type_name = "temporal.SelfFlow"
    version = 1
    _plate, _self = 0.0, 1.0

    class Params(_SmoothParams):
        prior_weight: float = Param(0.1, ge=0, description="Weight of the prior toward the input values "
                                    "(units 0.01 rad, 0.1 cm, 0.1 weight).")


class Hybrid(_Smooth):
    """Three-frame averaging, then plate-flow refinement against both neighbours (the paper's best)."""

    type_name = "temporal.Hybrid"
    version = 1
    kind = windowed(2 * MAX_SWEEPS + 1)
    _average = True

    class Params(_SmoothParams):
        centre_weight: float = Param(0.5, gt=0, le=1, description="Weight of the frame itself in the average.")
        prior_to_raw: bool = Param(False, description="Prior toward the raw input (True) or the averaged values.")
        prior_weight: float = Param(0.02, ge=0, description="Weight of the prior (units 0.01 rad, 0.1 cm, 0.1).")


class Average(Node):
    """Three-frame weighted average of the parameters (rotations by quaternion mean)."""

    type_name = "temporal.Average"
    version = 1
    kind = windowed(1)

    class Params(NodeParams):
        centre_weight: float = Param(0.5, gt=0, le=1, description="Weight of the frame itself; each "
                                     "neighbour gets (1 - c) / 2.")

    fitted = In(ParamSequence, doc="Parameters (r00..r22 + tx ty tz cm, or rot_x..z rad + trans_x..z cm; "
                "other columns averaged linearly).")
    failed = In(ParamSequence, optional=True, doc="(F, 1+) flags, 1 (or NaN) in the 'failed' column for frames "
                "to leave alone and not use.")
    averaged = Out(ParamSequence, doc="Averaged parameters.")

    def run(self, fitted: ParamSequence, failed: ParamSequence | None = None) -> dict[str, ParamSequence]:
        from .averaging import average_params

        try:
            layout = params_layout(fitted.names, [], "fitted")
        except ValueError as err:
            raise InputError("fitted", str(err).removeprefix("fitted: ")) from err
        mask = flags_to_mask(failed, fitted.num_frames)
        x = to_unknowns(fitted.values, layout)
        out = average_params(x, np.arange(3), np.arange(3, 6), centre_weight=self.params.centre_weight, failed=mask)
        others = np.setdiff1d(np.arange(fitted.values.shape[1]), np.r_[layout.rotation, layout.translation])
        out = from_unknowns(out, fitted.values, layout)
        avg = average_params(fitted.values, np.zeros(0, np.int64), others, centre_weight=self.params.centre_weight,
                             failed=mask)
        out[:, others] = avg[:, others]
        out[mask] = fitted.values[mask]  # left alone: exactly as given (NaN stays NaN)
        return {"averaged": ParamSequence(out.astype(np.float32), list(fitted.names))}


class AdaptiveSmooth(Node):
    """Smooth the pose and the expression weights by their measured noise, keeping blinks and snaps sharp."""

    type_name = "temporal.AdaptiveSmooth"
    version = 2  # 2: with model and camera, pose and weights smoothed together in the projected landmarks' metric
    kind = SEQUENCE

    class Params(NodeParams):
        fidelity: float = Param(0.85, gt=0, le=2, description="Residual RMS aimed at, in units of the measured "
                                "noise (1 = the discrepancy principle). Below 1 because a smoother keeps part of "
                                "the noise in its own degrees of freedom, so aiming at all of it smooths too much "
                                "(bench/smoothing.py prints the error to the truth and the landmark jitter and "
                                "deviation this gives against 3-frame averaging).")
        edge_k: float = Param(3.0, gt=0, description="A frame whose curvature exceeds edge_k noise std is an event "
                              "(blink, jaw snap, fast turn) and is not smoothed through.")
        weights: bool = Param(True, description="Smooth the expression weights too (false: the pose only).")

    fitted = In(ParamSequence, doc="Parameters (r00..r22 + tx ty tz cm + weights, or rot_x..z rad + trans_x..z cm + "
                "weights): e.g. fit.Expression's, or the temporal nodes'.")
    failed = In(ParamSequence, optional=True, doc="(F, 1+) flags, 1 (or NaN) in the 'failed' column for frames "
                "to leave alone and not use.")
    model = In(FaceModel, optional=True, doc="The fitted model (identity applied): with `camera`, the pose and "
               "the weights are smoothed together, their noise and smoothness measured on the projected 68 "
               "landmarks (pixels); without, each curve by its own noise.")
    camera = In(Camera, optional=True, doc="The plate's camera (with `model`).")
    smoothed = Out(ParamSequence, doc="Smoothed parameters (failed frames as given).")

    def run(self, fitted: ParamSequence, failed: ParamSequence | None = None, model: FaceModel | None = None,
            camera: Camera | None = None) -> dict[str, ParamSequence]:
        from .adaptive import FACE68_GROUPS, smooth_pose_and_weights

        if (model is None) != (camera is None):
            raise InputError("camera" if camera is None else "model", "expected both 'model' and 'camera' "
                             "connected (to smooth in the projected landmarks' metric) or neither, found one")
        try:
            layout = params_layout(fitted.names, [] if model is None else list(model.expression_names), "fitted")
        except ValueError as err:
            raise InputError("fitted", str(err).removeprefix("fitted: ")) from err
        pose = np.r_[layout.rotation, layout.translation]
        others = np.setdiff1d(np.arange(fitted.values.shape[1]), pose)
        linear = np.r_[layout.translation, others if self.params.weights else np.zeros(0, np.int64)]
        mask = flags_to_mask(failed, fitted.num_frames)
        landmarks = None
        if model is not None:
            if len(model.landmarks) != 68:
                raise InputError("model", f"expected a model with its 68 landmark vertices, found {len(model.landmarks)}")
            landmarks = _projected_landmarks_function(model, camera, layout)
        out = smooth_pose_and_weights(fitted.values, layout.rotation, linear, mask, matrix=layout.matrix,
                                      landmarks=landmarks, landmark_groups=None if landmarks is None else FACE68_GROUPS,
                                      fidelity=self.params.fidelity, edge_k=self.params.edge_k)
        return {"smoothed": ParamSequence(out.astype(np.float32), list(fitted.names))}


def _projected_landmarks_function(model: FaceModel, camera: Camera, layout: Any):
    """(N, D) rows of a sequence with `layout` -> (N, 136) pixels of the model's 68 landmarks posed by them."""
    from ..geometry.camera import project_points
    from ..geometry.rotation import axis_angle_to_rotmat

    index = np.asarray(model.landmarks, np.int64)
    neutral = np.asarray(model.neutral, np.float64)[index]  # (68, 3) cm
    have = layout.weights >= 0
    deltas = np.asarray(model.expression_deltas, np.float64)[have][:, index]  # (K', 68, 3) cm per unit weight
    columns = layout.weights[have]
    intrinsics = [camera.fx, camera.fy, camera.cx, camera.cy]
    distortion = [camera.k1, camera.k2] if (camera.k1 or camera.k2) else None

    def landmarks(rows: np.ndarray) -> np.ndarray:
        rows = np.asarray(rows, np.float64)
        local = neutral + np.einsum("nk,klc->nlc", rows[:, columns], deltas)
        rot = rows[:, layout.rotation].reshape(-1, 3, 3) if layout.matrix else axis_angle_to_rotmat(
            rows[:, layout.rotation])
        world = np.einsum("nij,nlj->nli", rot, local) + rows[:, layout.translation][:, None]
        return project_points(world, camera.world_to_camera, intrinsics, distortion).reshape(len(rows), -1)

    return landmarks
