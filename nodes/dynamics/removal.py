"""Removal of secondary dynamics: the network F (Zoss et al. 2020, section 5) as nodes.

`F(B(t), X_i(t)) -> dx_i(t)`: one MLP shared by all skin samples maps the head motion history
and the stabilized velocity history of sample i to its dynamic offset in the skull frame.
`dynamics.TrainRemoval` fits it (Adam, L2) on captures with known targets (the paper's moving
average, or the true quasistatic sequence of a synthetic capture); `dynamics.RemoveDynamics`
predicts the sample offsets of any capture of the same topology, propagates them to every
vertex (see `propagate.py`) and returns `y = x - T(t) D(t)`.

The model (`TorchModel`, architecture "dynamics.MLP") carries what applying it needs:
config `kind` = "removal", `window`, `feature_fps`, `num_vertices`; normalization
`input_mean`, `input_std`, `output_mean`, `output_std`, `sample_ids` (N,), `skull_landmarks`
(5, 3) cm, `rest_vertices` (V, 3) cm (the training rest shape, for the neighbour graph of
point sets). A network trained on a region of a bigger mesh (e.g. the ICT head's 'face')
records it: config `region` (the group's name) and `whole_vertices` (the whole mesh's vertex
count), normalization `region_ids` (V,) (the region's vertices in the whole mesh, in the
training vertex order). `dynamics.RemoveDynamics` then also takes a capture of the whole mesh:
it cuts the region, removes its dynamics and puts it back (the rest of the mesh unchanged).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, Literal

import numpy as np

from nodegraph import (SEQUENCE, FaceModel, In, InputError, JsonValue, MeshSequence, Node, NodeParams,
                       Out, Param, ParamSequence, RigidSequence, TorchModel, windowed)

from ..mesh.regions import select_region
from .features import (dynamic_offsets, moving_average_target, rotate_elementwise,
                       no_training_rows, select_samples, skin_descriptor, skin_velocity,
                       skull_descriptor, skull_landmarks, stabilize_points, training_mask,
                       window_gather, window_reach)
from .networks import predict, single_thread, standardize_inputs, standardize_stats, train_mlp
from .propagate import cached_edges, cached_interpolation_matrix, propagate_offsets

__all__ = ["HALO", "region_vertices", "topology_problem", "check_model", "locate_region", "model_edges",
           "removal_margin", "planned_training_frames", "fit_removal", "predict_removal", "remove_dynamics", "TrainRemoval", "RemoveDynamics"]

HALO = 16
"""Halo of the windowed dynamics nodes (frames): the window of w = 10 samples at the feature
rate plus interpolation taps covers captures up to `feature_fps * 13 / 10` frames per second."""


def region_vertices(mesh: MeshSequence, region: str, param: str = "region") -> np.ndarray:
    """Vertex indices of group `region` ('' = all), or InputError naming the known groups."""
    if not region:
        return np.arange(mesh.num_vertices)
    if region not in mesh.groups:
        raise InputError(param, f"expected a vertex group '{region}' in the capture, found groups "
                                f"{sorted(mesh.groups)} (use '' for all vertices)")
    return np.asarray(mesh.groups[region], np.int64)


def topology_problem(model: TorchModel, num_vertices: int, *, whole: bool = True) -> str:
    """'' when a capture of `num_vertices` vertices fits `model` (its training topology, or with
    `whole` the whole mesh the model's recorded region was cut from); else what the model
    expects, what was found and how to get a capture that fits."""
    count = int(model.config["num_vertices"])
    region = str(model.config.get("region", "") or "")
    whole_count = int(model.config.get("whole_vertices", 0) or 0)
    if num_vertices == count or (whole and region and num_vertices == whole_count):
        return ""
    if region and whole_count:
        expect = (f"a capture of the network's training topology ({count} vertices: region "
                  f"'{region}' of a {whole_count}-vertex mesh" + (", e.g. io.LoadFaceModel region "
                  f"'{region}'" if region == "face" else "") + ")" +
                  (f" or of that whole {whole_count}-vertex mesh (its region is cut and put back)"
                   if whole else ""))
        hint = (f"cut the region out of your capture with mesh.SelectRegion (group '{region}') when its "
                f"topology contains it, or train a network on your own captures with "
                f"graphs/dynamics_train_captures.json")
    else:
        expect = f"a capture of the network's training topology ({count} vertices)"
        hint = ("cut that region out of your capture (mesh.SelectRegion), or train a network on your "
                "own captures with graphs/dynamics_train_captures.json")
    return f"expected {expect}, found {num_vertices} vertices; {hint}"


def check_model(model: TorchModel, kind: str, mesh: MeshSequence, fps: float, port: str = "model",
                *, whole: bool = False, mesh_port: str = "capture") -> np.ndarray | None:
    """Check that `model` is a dynamics network of `kind` that fits `mesh` at `fps`.

    Returns:
        None when `mesh` has the training topology; with `whole`, the recorded region's vertex
        indices (V,) int64 when `mesh` is the whole mesh that region was cut from.
    """
    found = model.config.get("kind")
    if model.architecture != "dynamics.MLP" or found != kind:
        raise InputError(port, f"expected a dynamics.MLP {kind} network (dynamics.Train"
                               f"{'Removal' if kind == 'removal' else 'Synthesis'}), found "
                               f"architecture '{model.architecture}' kind {found!r}")
    problem = topology_problem(model, mesh.num_vertices, whole=whole)
    if problem:
        raise InputError(mesh_port, problem)
    reach = window_reach(int(model.config["window"]), fps, float(model.config["feature_fps"]))
    if reach > HALO:
        top = (HALO - 3) * float(model.config["feature_fps"]) / int(model.config["window"])
        raise InputError("fps", f"expected a frame rate up to {top:g} fps for this network "
                                f"(window {model.config['window']} at {model.config['feature_fps']} "
                                f"fps), found {fps:g}")
    count = int(model.config["num_vertices"])
    if mesh.num_vertices == count:
        return None
    ids = np.asarray(model.normalization["region_ids"], np.int64)
    if len(ids) != count or ids.min() < 0 or ids.max() >= mesh.num_vertices:
        raise InputError(port, f"expected a region vertex list of {count} indices below "
                               f"{mesh.num_vertices} in the network file, found {len(ids)} indices")
    return ids


def model_edges(mesh: MeshSequence, model: TorchModel) -> np.ndarray:
    """Neighbour edges for propagation: the mesh's, else a kNN graph of the training rest shape."""
    return cached_edges(model.normalization["rest_vertices"], mesh.faces)


def locate_region(part: FaceModel, whole: FaceModel, tol_cm: float = 1e-4) -> np.ndarray:
    """The vertex of `whole` that each vertex of `part` (a region and/or subsample of it) is.

    Vertices are matched by their neutral position and identity deltas (both must agree within
    `tol_cm`), so coinciding vertices with different identity behaviour are told apart.

    Returns:
        (V_part,) int64 indices into `whole`, in `part`'s vertex order.
    Raises:
        InputError: (port "region_model") a vertex that is not in `whole`, or two vertices of
            `part` on the same vertex of `whole`.
    """
    from scipy.spatial import cKDTree

    def rows(model: FaceModel) -> np.ndarray:
        ident = model.identity_deltas[:3].transpose(1, 0, 2).reshape(len(model.neutral), -1)
        return np.concatenate([model.neutral, ident], axis=1).astype(np.float64)

    dist, ids = cKDTree(rows(whole)).query(rows(part), k=1)
    if len(dist) and dist.max() > tol_cm:
        bad = int(np.argmax(dist))
        raise InputError("region_model", f"expected a region of the whole model, found vertex {bad} "
                                         f"{dist[bad]:.3g} cm from every vertex of it")
    if len(np.unique(ids)) != len(ids):
        raise InputError("region_model", "expected distinct vertices of the whole model, found "
                                         f"{len(ids) - len(np.unique(ids))} vertices matched twice")
    return ids.astype(np.int64)


def _fps(param: float, mesh: MeshSequence) -> float:
    return float(param) if param > 0 else float(mesh.fps)


def _check_lists(**lists: list) -> int:
    counts = {name: len(values) for name, values in lists.items() if values}
    first = next(iter(counts.values()))
    for name, count in counts.items():
        if count != first:
            raise InputError(name, f"expected {first} values (one per capture), found {count}")
    return first


class TrainRemoval(Node):
    """Train the removal network F on captures with known quasistatic targets."""

    type_name = "dynamics.TrainRemoval"
    version = 1
    kind = SEQUENCE
    resources = {"gpu": 1}

    class Params(NodeParams):
        target: Literal["moving_average", "truth"] = Param(
            "truth", description="training target: 'moving_average' (the paper's eq. 5, held "
                                 "expressions) or 'truth' (the connected quasistatic sequences)")
        num_samples: int = Param(344, ge=1, description="skin samples (farthest-point sampling of the region)")
        region: str = Param("", description="vertex group of the samples ('' = all vertices)")
        window: int = Param(10, ge=1, description="half-size of the descriptor windows (samples)")
        feature_fps: float = Param(120.0, gt=0, description="sample rate of the windows (1/s)")
        target_window: int = Param(10, ge=1, description="half-size of the moving-average target (frames)")
        hidden: list[int] = Param([128, 128], description="hidden layer widths")
        epochs: int = Param(40, ge=1, description="passes over the training rows (paper: 250)")
        batch_size: int = Param(10000, ge=1, description="rows per Adam step")
        lr: float = Param(1e-3, gt=0, description="Adam learning rate")
        max_rows: int = Param(200000, ge=1, description="(frame, sample) rows drawn for training")
        seed: int | None = Param(None, ge=0, description="seed of the weight initialisation and of the row and batch order; none = derived from the task's cache key (it then changes with the inputs, parameters and code version); an integer pins training across versions")
        region_name: str = Param("face", description="name recorded for the captures' region of the whole "
                                 "model (with `whole` and `region_model` connected): messages and the "
                                 "hint to cut it with mesh.SelectRegion name it")

    captures = In(MeshSequence, many=True, doc="world-space dynamic captures (cm)")
    whole = In(FaceModel, optional=True, doc="the whole face model (io.LoadFaceModel, no region); with "
                                            "`region_model`, the network records where the captures' "
                                            "vertices lie in it and so also cleans whole-head captures")
    region_model = In(FaceModel, optional=True, doc="the face model the captures are of (io.LoadFaceModel "
                                                   "with region / max_vertices)")
    skulls = In(RigidSequence, many=True, doc="skull-to-world transforms, one per capture")
    quasistatic = In(MeshSequence, many=True, optional=True,
                     doc="true world-space quasistatic sequences (for target 'truth')")
    segments = In(ParamSequence, many=True, optional=True,
                  doc="segment labels per frame; windows never straddle a change")
    model = Out(TorchModel, doc="removal network F (dynamics.MLP)")
    report = Out(JsonValue, doc="rows, epochs, seconds, losses")

    def check_frames(self, frames: range, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: captures whose producers know their frame rate and segments
        (synth.DynamicPerformance) and whose run frames give no training row (--frames 0:4)
        are one refusal, not a failure after the captures were made."""
        p = self.params
        refuse_short_run(producers, frames, lambda fps: removal_margin(p, fps, p.target_window))

    def run(self, captures: list[MeshSequence], skulls: list[RigidSequence],
            quasistatic: list[MeshSequence], segments: list[ParamSequence],
            whole: FaceModel | None = None, region_model: FaceModel | None = None) -> dict:
        p = self.params
        count = _check_lists(captures=captures, skulls=skulls, quasistatic=quasistatic, segments=segments)
        region_ids = None
        if (whole is None) != (region_model is None):
            raise InputError("whole" if whole is None else "region_model",
                             "expected both `whole` and `region_model` connected (to record the region), "
                             "found one")
        if whole is not None:
            region_ids = locate_region(region_model, whole)
            if len(region_ids) != captures[0].num_vertices:
                raise InputError("region_model", f"expected the captures' {captures[0].num_vertices} "
                                                 f"vertices, found {len(region_ids)}")
        first = captures[0]
        for i, c in enumerate(captures):
            if c.num_vertices != first.num_vertices:
                raise InputError("captures", f"expected every capture to have {first.num_vertices} "
                                             f"vertices (as capture 0), capture {i} has {c.num_vertices}")
        rest = stabilize_points(first.vertices[:1], skulls[0].matrices[:1])[0]
        samples = select_samples(rest, p.num_samples, region_vertices(first, p.region))
        seed = self.seed if p.seed is None else p.seed
        labels = [s.values[:, 0] for s in segments] if segments else [None] * count
        model, report = fit_removal(p, [c.vertices for c in captures], [float(c.fps) for c in captures],
                                    [s.matrices for s in skulls],
                                    [q.vertices for q in quasistatic] if quasistatic else None, labels,
                                    rest, samples, seed, self.device, self.progress)
        if region_ids is not None:
            model.config.update(region=p.region_name, whole_vertices=int(whole.neutral.shape[0]))
            model.normalization["region_ids"] = region_ids
        return {"model": model, "report": JsonValue(report)}


def planned_training_frames(producers: dict[str, list[Node]], frames: range,
                            margin_of: Callable[[float], int]) -> tuple[list[int], list[int]] | None:
    """While planning: per capture, the margin (frames) and how many of the run's `frames` a
    trainer could draw rows from (`training_mask`), when every producer of 'captures' (and of
    'segments', when connected) knows the frame rate and segment labels from its parameters
    (`peek_capture_timing(frames)`, e.g. synth.DynamicPerformance); None otherwise (run()
    then checks the values).

    Args:
        producers: the trainer's input port -> producing nodes (`check_frames`).
        frames: the run's frames.
        margin_of: fps -> the trainer's margin in frames (window reach, target half-width).
    """
    captures, segments = producers.get("captures", []), producers.get("segments", [])
    if not captures or not all(hasattr(n, "peek_capture_timing") for n in captures + segments):
        return None
    if segments and len(segments) != len(captures):
        return None  # run() reports the mismatch
    margins, counts = [], []
    for i, node in enumerate(captures):
        fps, _ = node.peek_capture_timing(frames)
        labels = segments[i].peek_capture_timing(frames)[1] if segments else None
        margins.append(margin_of(fps))
        counts.append(int(training_mask(labels, len(frames), margins[-1]).sum()))
    return margins, counts


def refuse_short_run(producers: dict[str, list[Node]], frames: range,
                     margin_of: Callable[[float], int]) -> None:
    """InputError ("captures") when the run's frames give the trainer no training row
    (`planned_training_frames`): --frames 0:4 is refused while planning, not after the
    captures were made."""
    planned = planned_training_frames(producers, frames, margin_of)
    if planned is None or sum(planned[1]) > 0:
        return
    raise InputError("captures", f"--frames {frames.start}:{frames.stop}: "
                                 f"{no_training_rows(planned[0], [len(frames)] * len(planned[0]))}; "
                                 f"pass a longer --frames range (more than twice the margin, within one segment)")


def removal_margin(p: NodeParams, fps: float, target_window: int) -> int:
    """Frames F's training keeps from segment changes and ends at `fps`: the descriptor
    window's reach, and the moving-average target's half-width `target_window` (frames)."""
    reach = window_reach(p.window, fps, p.feature_fps)
    return max(reach, target_window if p.target == "moving_average" else 0)


def fit_removal(p: NodeParams, vertices: list[np.ndarray], fps: list[float], skulls: list[np.ndarray],
                quasistatic: list[np.ndarray] | None, segments: list[np.ndarray | None], rest: np.ndarray,
                samples: np.ndarray, seed: int, device: str,
                progress: Callable[[float, str], None],
                target_windows: list[int] | None = None) -> tuple[TorchModel, dict]:
    """Draw training rows from captures and fit F (the body of dynamics.TrainRemoval).

    Args:
        p: TrainRemoval's parameters (target, window, feature_fps, target_window, hidden,
            epochs, batch_size, lr, max_rows).
        vertices: per capture (F_i, V, 3) world positions, cm.
        fps: per capture frames per second.
        skulls: per capture (F_i, 4, 4) skull-to-world.
        quasistatic: per capture (F_i, V, 3) true quasistatic positions (target 'truth'), or None.
        segments: per capture (F_i,) segment labels, or None (one segment).
        rest: (V, 3) skull-frame rest shape (landmarks, the kNN graph of point sets), cm.
        samples: (N,) sample vertex indices.
        seed: rows, batch order and weights.
        device: torch device.
        progress: callback (fraction, message); one message per epoch with its loss.
        target_windows: per capture half-width (frames) of the moving-average target; None =
            `p.target_window` for every capture.
    Returns:
        (the model, a report: rows, epochs, seconds, final_loss, losses).
    Raises:
        InputError: ("captures") no frame far enough from segment changes and ends.
    """
    landmarks = skull_landmarks(rest)
    rng = np.random.default_rng(seed)
    count = len(vertices)
    windows = list(target_windows) if target_windows is not None else [p.target_window] * count
    inputs, targets = [], []
    valid_frames = []
    margins = [removal_margin(p, fps[i], windows[i]) for i in range(count)]
    for i in range(count):
        valid_frames.append(np.flatnonzero(training_mask(segments[i], len(vertices[i]), margins[i])))
    total = sum(len(v) for v in valid_frames) * len(samples)
    if total == 0:
        raise InputError("captures", no_training_rows(margins, [len(v) for v in vertices]))
    for i in range(count):
        frames = valid_frames[i]
        quota = int(round(p.max_rows * len(frames) * len(samples) / total))
        if quota == 0 or not len(frames):
            continue
        pick = rng.choice(len(frames) * len(samples), min(quota, len(frames) * len(samples)),
                          replace=False)
        rows_f, rows_s = frames[pick // len(samples)], pick % len(samples)
        skull = skulls[i]
        x = vertices[i][:, samples]
        y = (quasistatic[i][:, samples] if p.target == "truth"
             else moving_average_target(x, skull, window=windows[i]))
        offsets = dynamic_offsets(x, y, skull)  # (F, N, 3)
        b = skull_descriptor(skull, landmarks, fps[i], window=p.window, feature_fps=p.feature_fps)
        vel = skin_velocity(x, skull, fps[i])
        skin = window_gather(vel, rows_f, p.window, fps[i], p.feature_fps, columns=rows_s)
        inputs.append(np.concatenate([b[rows_f], skin.reshape(len(rows_f), -1).astype(np.float32)], 1))
        targets.append(offsets[rows_f, rows_s].astype(np.float32))
        progress(0.1 * (i + 1) / count, f"features of capture {i + 1}/{count}")
    x_all, y_all = np.concatenate(inputs), np.concatenate(targets)
    in_mean, in_std = standardize_stats(x_all)
    out_mean, out_std = standardize_stats(y_all)
    result = train_mlp((x_all - in_mean) / in_std, (y_all - out_mean) / out_std,
                       hidden=p.hidden, epochs=p.epochs, batch_size=p.batch_size, lr=p.lr,
                       seed=seed % (2 ** 63), device=device,
                       progress=lambda f, m: progress(0.1 + 0.9 * f, m))
    config = {"in_features": int(x_all.shape[1]), "hidden": list(p.hidden), "out_features": 3,
              "kind": "removal", "window": p.window, "feature_fps": p.feature_fps,
              "num_vertices": int(vertices[0].shape[1]), "target": p.target}
    norm = {"input_mean": in_mean, "input_std": in_std, "output_mean": out_mean,
            "output_std": out_std, "sample_ids": samples.astype(np.int64),
            "skull_landmarks": landmarks, "rest_vertices": np.asarray(rest, np.float32)}
    model = TorchModel.from_module("dynamics.MLP", config, result.module, norm)
    report = {"rows": int(len(x_all)), "epochs": p.epochs, "seconds": round(result.seconds, 3),
              "final_loss": result.losses[-1], "losses": [round(v, 6) for v in result.losses]}
    return model, report


def predict_removal(model: TorchModel, vertices: np.ndarray, skull: np.ndarray, fps: float) -> np.ndarray:
    """Sample offsets dx_i(t) (F, N, 3) float64, cm, skull frame, predicted frame by frame."""
    cfg, norm = model.config, model.normalization
    ids = norm["sample_ids"]
    window, ffps = int(cfg["window"]), float(cfg["feature_fps"])
    b = skull_descriptor(skull, norm["skull_landmarks"], fps, window=window, feature_fps=ffps)
    x = skin_descriptor(vertices[:, ids], skull, fps, window=window, feature_fps=ffps)
    net = model.build("cpu")
    out = np.empty((len(b), len(ids), 3))
    mean, std = norm["input_mean"], norm["input_std"]
    with single_thread():
        for f in range(len(b)):  # one call per frame: the same shapes whatever the chunk
            rows = np.concatenate([np.broadcast_to(b[f], (len(ids), b.shape[1])), x[f]], axis=1)
            out[f] = predict(net, standardize_inputs(rows, mean, std)) * norm["output_std"] + norm["output_mean"]
    return out


def remove_dynamics(model: TorchModel, capture: MeshSequence, skull: np.ndarray, fps: float,
                    region: np.ndarray | None = None, *, constraint_weight: float = 100.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The body of dynamics.RemoveDynamics (the capture already checked by `check_model`).

    Args:
        model: removal network F.
        capture: (F, V, 3) world-space capture, the network's topology, or the whole mesh when
            `region` gives the region's vertices in it.
        skull: (F, 4, 4) skull-to-world.
        fps: frame rate of the capture.
        region: (V_region,) vertex indices of the network's region in `capture`, or None.
        constraint_weight: weight of the sample offsets against smoothness in propagation.
    Returns:
        quasistatic (F, V, 3) float32 world space, cm, and the removed offsets (F, V, 3)
        float64 in the skull frame, cm (0 outside the region).
    """
    work = capture if region is None else select_region(capture, region)
    if region is not None and work.faces.size and len(np.unique(work.faces)) < work.num_vertices:
        work = dataclasses.replace(work, faces=np.zeros((0, 3), np.int32))  # a point subset of the
        # mesh (trained on io.LoadFaceModel max_vertices): neighbours from the rest shape, as in training
    ids = model.normalization["sample_ids"]
    sample = predict_removal(model, work.vertices, skull, fps)
    weights = cached_interpolation_matrix(model_edges(work, model), work.num_vertices, ids,
                                          constraint_weight=constraint_weight)
    full = propagate_offsets(weights, sample)  # (F, V, 3), skull frame
    world = rotate_elementwise(skull[:, :3, :3], full)
    quasi = (work.vertices.astype(np.float64) - world).astype(np.float32)
    if region is not None:  # back into the whole mesh; outside the region nothing changes
        quasi_whole = np.array(capture.vertices, np.float32)
        quasi_whole[:, region] = quasi
        full_whole = np.zeros(capture.vertices.shape)
        full_whole[:, region] = full
        quasi, full = quasi_whole, full_whole
    return quasi, full


class RemoveDynamics(Node):
    """Remove secondary dynamics from a capture with a trained removal network F."""

    type_name = "dynamics.RemoveDynamics"
    version = 2  # v2: input columns constant in F's training are read as their training value (standardize_inputs)
    kind = windowed(HALO)

    class Params(NodeParams):
        fps: float = Param(0.0, ge=0, description="frame rate of the capture (1/s); 0 = the mesh's fps")
        constraint_weight: float = Param(100.0, gt=0, description="weight of the sample offsets "
                                                                  "against smoothness in propagation")

    capture = In(MeshSequence, doc="world-space capture with dynamics (cm): the training topology, or the "
                                   "whole mesh whose region the network records (the region is cleaned, the "
                                   "rest kept)")
    skull = In(RigidSequence, doc="skull-to-world transforms")
    model = In(TorchModel, doc="removal network F (dynamics.TrainRemoval / dynamics.LoadModel)")
    quasistatic = Out(MeshSequence, doc="world-space capture without secondary dynamics (cm)")
    offsets = Out(MeshSequence, doc="removed dynamic offsets per vertex, skull frame (cm)")

    def check_plan(self, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: when the network comes from a file reader (`peek_model`) and the
        capture from one that knows its vertex count (`peek_vertex_count`), refuse a capture
        that does not fit the network (one error for the run, not one per chunk)."""
        model_nodes = [n for n in producers.get("model", []) if hasattr(n, "peek_model")]
        capture_nodes = [n for n in producers.get("capture", []) if hasattr(n, "peek_vertex_count")]
        if not model_nodes or not capture_nodes:
            return  # other producers: run() checks the values
        model, count = model_nodes[0].peek_model(), capture_nodes[0].peek_vertex_count()
        if model is None or count is None:
            return  # unreadable files: their readers report them
        found = model.config.get("kind")
        if model.architecture != "dynamics.MLP" or found != "removal":
            raise InputError("model", f"expected a dynamics.MLP removal network (dynamics.TrainRemoval), "
                                      f"found architecture '{model.architecture}' kind {found!r}")
        problem = topology_problem(model, count, whole=True)
        if problem:
            raise InputError("capture", problem)

    def run(self, capture: MeshSequence, skull: RigidSequence, model: TorchModel) -> dict:
        fps = _fps(self.params.fps, capture)
        region = check_model(model, "removal", capture, fps, whole=True)
        if capture.num_frames < 2:
            raise InputError("capture", f"expected at least 2 frames, found {capture.num_frames}")
        quasi, full = remove_dynamics(model, capture, skull.matrices, fps, region,
                                      constraint_weight=self.params.constraint_weight)
        return {"quasistatic": dataclasses.replace(capture, vertices=quasi, fps=fps),
                "offsets": dataclasses.replace(capture, vertices=full.astype(np.float32), fps=fps)}
