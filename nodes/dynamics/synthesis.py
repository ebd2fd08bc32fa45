"""Synthesis of secondary dynamics: the network H (Zoss et al. 2020, section 6) as nodes.

`H(B(t), S(t)) -> dY(t)`: one MLP maps the head motion history of a (new) skull motion and the
surface stretch of the quasistatic performance at every sample (a global expression
descriptor) to the dynamic offsets of all samples jointly (skull frame). `dynamics.TrainSynthesis`
fits it on (quasistatic, dynamic) pairs; `dynamics.SynthesizeDynamics` predicts, propagates to
every vertex and returns `x = y + T(t) D(t)`; `dynamics.Retarget` moves a quasistatic
performance from one skull motion onto another (`T_new T_old^-1 y`).

Model config `kind` = "synthesis"; normalization as the removal network's plus
`stretch_stencil` (N, 4) vertex ids.
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from nodegraph import (FRAMEWISE, SEQUENCE, In, InputError, JsonValue, MeshSequence, Node, NodeParams,
                       Out, Param, ParamSequence, RigidSequence, TorchModel, windowed)

from .features import (apply_rigid_elementwise, dynamic_offsets, rotate_elementwise,
                       no_training_rows, select_samples, skull_descriptor, skull_landmarks,
                       stabilize_points, stretch_stencil, surface_stretch, training_mask, window_reach)
from .networks import predict, single_thread, standardize_inputs, standardize_stats, train_mlp
from .propagate import cached_interpolation_matrix, propagate_offsets
from .removal import (HALO, _check_lists, _fps, check_model, model_edges, refuse_short_run,
                      region_vertices)

__all__ = ["synthesis_inputs", "predict_synthesis", "fit_synthesis", "TrainSynthesis", "SynthesizeDynamics",
           "Retarget"]


def synthesis_inputs(quasistatic: np.ndarray, skull: np.ndarray, neutral: np.ndarray,
                     landmarks: np.ndarray, stencil: np.ndarray, fps: float, window: int,
                     feature_fps: float) -> np.ndarray:
    """Rows [B(t), S(t)] (F, L K 3 + 2 N) float32 of a quasistatic performance on a skull motion."""
    b = skull_descriptor(skull, landmarks, fps, window=window, feature_fps=feature_fps)
    s = surface_stretch(quasistatic, neutral, stencil).reshape(len(b), -1)
    return np.concatenate([b, s], axis=1)


def predict_synthesis(model: TorchModel, quasistatic: np.ndarray, skull: np.ndarray,
                      neutral: np.ndarray, fps: float) -> np.ndarray:
    """Sample offsets dy_i(t) (F, N, 3) float64, cm, skull frame, predicted frame by frame."""
    cfg, norm = model.config, model.normalization
    rows = synthesis_inputs(quasistatic, skull, neutral, norm["skull_landmarks"],
                            norm["stretch_stencil"], fps, int(cfg["window"]), float(cfg["feature_fps"]))
    net = model.build("cpu")
    rows = standardize_inputs(rows, norm["input_mean"], norm["input_std"])
    n = len(norm["sample_ids"])
    out = np.empty((len(rows), n, 3))
    with single_thread():
        for f in range(len(rows)):  # one call per frame: the same shapes whatever the chunk
            out[f] = (predict(net, rows[f:f + 1])[0] * norm["output_std"] + norm["output_mean"]).reshape(n, 3)
    return out


class TrainSynthesis(Node):
    """Train the synthesis network H on quasistatic performances and their dynamic captures."""

    type_name = "dynamics.TrainSynthesis"
    version = 1
    kind = SEQUENCE
    resources = {"gpu": 1}

    class Params(NodeParams):
        num_samples: int = Param(344, ge=1, description="skin samples (farthest-point sampling of the region)")
        region: str = Param("", description="vertex group of the samples ('' = all vertices)")
        window: int = Param(10, ge=1, description="half-size of the skull descriptor window (samples)")
        feature_fps: float = Param(120.0, gt=0, description="sample rate of the window (1/s)")
        spacing_cm: float = Param(0.2, gt=0, description="preferred stretch stencil spacing (cm)")
        hidden: list[int] = Param([256, 256], description="hidden layer widths")
        epochs: int = Param(30, ge=1, description="passes over the training frames")
        batch_size: int = Param(50, ge=1, description="frames per Adam step")
        lr: float = Param(1e-3, gt=0, description="Adam learning rate")
        seed: int | None = Param(None, ge=0, description="seed of the weight initialisation and of the row and batch order; none = derived from the task's cache key (it then changes with the inputs, parameters and code version); an integer pins training across versions")

    captures = In(MeshSequence, many=True, doc="world-space dynamic captures (cm)")
    quasistatic = In(MeshSequence, many=True, doc="their world-space quasistatic sequences (cm)")
    skulls = In(RigidSequence, many=True, doc="skull-to-world transforms")
    neutral = In(MeshSequence, many=True, per_frame=False, doc="skull-frame neutral of each capture (1 frame)")
    segments = In(ParamSequence, many=True, optional=True, doc="segment labels per frame")
    model = Out(TorchModel, doc="synthesis network H (dynamics.MLP)")
    report = Out(JsonValue, doc="rows, epochs, seconds, losses")

    def check_frames(self, frames: range, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: captures whose producers know their frame rate and segments
        (synth.DynamicPerformance) and whose run frames give no training row (--frames 0:4)
        are one refusal, not a failure after the captures were made."""
        p = self.params
        refuse_short_run(producers, frames, lambda fps: window_reach(p.window, fps, p.feature_fps))

    def run(self, captures: list[MeshSequence], quasistatic: list[MeshSequence],
            skulls: list[RigidSequence], neutral: list[MeshSequence],
            segments: list[ParamSequence]) -> dict:
        p = self.params
        count = _check_lists(captures=captures, quasistatic=quasistatic, skulls=skulls,
                             neutral=neutral, segments=segments)
        rest = neutral[0].vertices[0].astype(np.float64)
        samples = select_samples(rest, p.num_samples, region_vertices(captures[0], p.region))
        for i in range(count):
            if captures[i].num_vertices != len(rest) or neutral[i].num_vertices != len(rest):
                raise InputError("captures", f"expected {len(rest)} vertices in capture and neutral "
                                             f"{i} (as neutral 0), found {captures[i].num_vertices} "
                                             f"and {neutral[i].num_vertices}")
        model, report = fit_synthesis(
            p, [c.vertices for c in captures], [q.vertices for q in quasistatic], [s.matrices for s in skulls],
            [n.vertices[0] for n in neutral], [float(c.fps) for c in captures],
            [s.values[:, 0] for s in segments] if segments else [None] * count, rest, samples,
            self.seed if p.seed is None else p.seed, self.device, self.progress)
        return {"model": model, "report": JsonValue(report)}


def fit_synthesis(p: NodeParams, captures: list[np.ndarray], quasistatic: list[np.ndarray],
                  skulls: list[np.ndarray], neutrals: list[np.ndarray], fps: list[float],
                  segments: list[np.ndarray | None], rest: np.ndarray, samples: np.ndarray, seed: int,
                  device: str, progress: Callable[[float, str], None]) -> tuple[TorchModel, dict]:
    """Fit H on (quasistatic, dynamic) pairs (the body of dynamics.TrainSynthesis).

    Args:
        p: TrainSynthesis's parameters (window, feature_fps, spacing_cm, hidden, epochs,
            batch_size, lr).
        captures, quasistatic: per capture (F_i, V, 3) world positions, cm.
        skulls: per capture (F_i, 4, 4) skull-to-world.
        neutrals: per capture (V, 3) skull-frame neutral, cm.
        fps: per capture frames per second.
        segments: per capture (F_i,) segment labels or None.
        rest: (V, 3) the rest shape of the samples, landmarks and stencil, cm.
        samples: (N,) sample vertex indices.
        seed, device, progress: as for `train_mlp`.
    Returns:
        (the model, a report: rows, epochs, seconds, final_loss, losses).
    """
    stencil = stretch_stencil(rest, samples, spacing_cm=p.spacing_cm)
    landmarks = skull_landmarks(rest)
    inputs, targets = [], []
    for i in range(len(captures)):
        reach = window_reach(p.window, fps[i], p.feature_fps)
        frames = np.flatnonzero(training_mask(segments[i], len(captures[i]), reach))
        if not len(frames):  # a capture shorter than the window's reach gives no training rows
            continue
        rows = synthesis_inputs(quasistatic[i], skulls[i], neutrals[i], landmarks, stencil, fps[i],
                                p.window, p.feature_fps)
        dy = dynamic_offsets(captures[i][:, samples], quasistatic[i][:, samples], skulls[i])
        inputs.append(rows[frames])
        targets.append(dy[frames].reshape(len(frames), -1).astype(np.float32))
    if not inputs:
        raise InputError("captures", no_training_rows([window_reach(p.window, f, p.feature_fps) for f in fps],
                                                      [len(c) for c in captures]))
    x_all, y_all = np.concatenate(inputs), np.concatenate(targets)
    in_mean, in_std = standardize_stats(x_all)
    out_mean, out_std = standardize_stats(y_all)
    result = train_mlp((x_all - in_mean) / in_std, (y_all - out_mean) / out_std, hidden=p.hidden,
                       epochs=p.epochs, batch_size=p.batch_size, lr=p.lr, seed=seed % (2 ** 63),
                       device=device, progress=progress)
    config = {"in_features": int(x_all.shape[1]), "hidden": list(p.hidden),
              "out_features": int(y_all.shape[1]), "kind": "synthesis", "window": p.window,
              "feature_fps": p.feature_fps, "num_vertices": int(len(rest))}
    norm = {"input_mean": in_mean, "input_std": in_std, "output_mean": out_mean,
            "output_std": out_std, "sample_ids": samples.astype(np.int64),
            "skull_landmarks": landmarks, "stretch_stencil": stencil.astype(np.int64),
            "rest_vertices": np.asarray(rest, np.float32)}
    model = TorchModel.from_module("dynamics.MLP", config, result.module, norm)
    report = {"rows": int(len(x_all)), "epochs": p.epochs, "seconds": round(result.seconds, 3),
              "final_loss": result.losses[-1], "losses": [round(v, 6) for v in result.losses]}
    return model, report


class SynthesizeDynamics(Node):
    """Add secondary dynamics for a skull motion to a quasistatic performance (network H)."""

    type_name = "dynamics.SynthesizeDynamics"
    version = 2  # v2: input columns constant in H's training are read as their training value (standardize_inputs)
    kind = windowed(HALO)

    class Params(NodeParams):
        fps: float = Param(0.0, ge=0, description="frame rate (1/s); 0 = the mesh's fps")
        constraint_weight: float = Param(100.0, gt=0, description="weight of the sample offsets "
                                                                  "against smoothness in propagation")

    quasistatic = In(MeshSequence, doc="world-space quasistatic performance on `skull` (cm)")
    skull = In(RigidSequence, doc="skull-to-world transforms of the (new) head motion")
    neutral = In(MeshSequence, per_frame=False, doc="skull-frame neutral of the face (1 frame)")
    model = In(TorchModel, doc="synthesis network H (dynamics.TrainSynthesis / dynamics.LoadModel)")
    capture = Out(MeshSequence, doc="world-space performance with synthesized dynamics (cm)")
    offsets = Out(MeshSequence, doc="synthesized dynamic offsets per vertex, skull frame (cm)")

    def check_plan(self, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: a network read from a file (`peek_model`) that is not a
        synthesis network (a removal network given as H) is one refusal, not one per chunk after
        the performance was made."""
        model_nodes = [n for n in producers.get("model", []) if hasattr(n, "peek_model")]
        model = model_nodes[0].peek_model() if model_nodes else None
        if model is not None and (model.architecture != "dynamics.MLP" or model.config.get("kind") != "synthesis"):
            raise InputError("model", f"expected a dynamics.MLP synthesis network (dynamics.TrainSynthesis), found "
                                      f"architecture '{model.architecture}' kind {model.config.get('kind')!r}")

    def run(self, quasistatic: MeshSequence, skull: RigidSequence, neutral: MeshSequence,
            model: TorchModel) -> dict:
        fps = _fps(self.params.fps, quasistatic)
        check_model(model, "synthesis", quasistatic, fps, mesh_port="quasistatic")
        if neutral.num_frames != 1 or neutral.num_vertices != quasistatic.num_vertices:
            raise InputError("neutral", f"expected one frame of {quasistatic.num_vertices} vertices, "
                                        f"found {neutral.num_frames} frames of {neutral.num_vertices}")
        if quasistatic.num_frames < 2:
            raise InputError("quasistatic", f"expected at least 2 frames, found {quasistatic.num_frames}")
        sample = predict_synthesis(model, quasistatic.vertices, skull.matrices, neutral.vertices[0], fps)
        weights = cached_interpolation_matrix(model_edges(quasistatic, model), quasistatic.num_vertices,
                                              model.normalization["sample_ids"],
                                              constraint_weight=self.params.constraint_weight)
        full = propagate_offsets(weights, sample)
        world = rotate_elementwise(skull.matrices[:, :3, :3], full)
        out = (quasistatic.vertices.astype(np.float64) + world).astype(np.float32)
        return {"capture": dataclasses.replace(quasistatic, vertices=out, fps=fps),
                "offsets": dataclasses.replace(quasistatic, vertices=full.astype(np.float32), fps=fps)}


class Retarget(Node):
    """Put a quasistatic performance on a new head motion: `y_new = T_new(t) T_old(t)^-1 y(t)`."""

    type_name = "dynamics.Retarget"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        pass

    mesh = In(MeshSequence, doc="world-space quasistatic performance on `skull` (cm)")
    skull = In(RigidSequence, doc="its skull-to-world transforms")
    new_skull = In(RigidSequence, doc="skull-to-world transforms of the new head motion")
    retargeted = Out(MeshSequence, doc="world-space performance on the new head motion (cm)")

    def run(self, mesh: MeshSequence, skull: RigidSequence, new_skull: RigidSequence) -> dict:
        local = stabilize_points(mesh.vertices, skull.matrices)
        out = apply_rigid_elementwise(new_skull.matrices, local).astype(np.float32)
        return {"retargeted": dataclasses.replace(mesh, vertices=out)}
