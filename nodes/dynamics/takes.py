"""Train the removal network F on a day of one's own capture (Zoss et al. 2020, section 5).

The paper's method: capture the actor holding expressions while walking, running, jumping and on
an oscillating platform, train F on those takes with the moving-average target (eq. 5), apply
it to the actor's performances. Here:

- `dynamics.LoadTakes` (`take_files.py`) reads a glob or a folder of takes into one
  `nodegraph.takes.Takes` value.
- `dynamics.StabilizeTakes` gives every take a skull motion: the tracked `rigid` where the file
  has one, else mode pursuit (`nodes.stabilize`), expressed in the frame of the subject's
  neutral by a robust rigid fit of the take's stabilized median shape onto the neutral (so
  every take, and the network, share one skull frame: the neutral's).
- `dynamics.TrainRemovalTakes` trains F with the moving-average target on the held-expression
  takes (a name pattern; the rest, e.g. dialog, are not used), optionally on one vertex group
  (the network then records it and also cleans whole captures), and reports the training loss
  per epoch and a held-out take's error against its own moving-average target.
- `dynamics.TrainSynthesisTakes` trains the synthesis network H as in the paper: F's
  quasistatic output of the takes (dialog included) as input, the captures as the target.
- `dynamics.SaveReport` writes the reports (JSON) and shows them as a table.

Nothing depends on a vertex count or order: samples are farthest-point samples of the neutral,
the skull landmarks come from its bounding box, the propagation uses the takes' faces.
"""

from __future__ import annotations

import fnmatch
import json
from typing import Callable

import numpy as np
from pydantic import field_validator

from nodegraph import (SEQUENCE, Files, In, InputError, JsonValue, MeshSequence, Node, NodeParams, Out,
                       Param, RigidSequence, Table, TorchModel)
from nodegraph.files import check_output_suffix, files_value, write_text_atomic
from nodegraph.takes import Takes

from ..geometry.rigid import fit_rigid, stabilize_vertices
from .evaluate import rms_distance
from .features import moving_average_target, no_training_rows, select_samples, window_reach
from .removal import HALO, check_model, fit_removal, remove_dynamics
from .synthesis import fit_synthesis

__all__ = ["neutral_frame", "StabilizeTakes", "TrainRemovalTakes", "TrainSynthesisTakes", "SaveReport"]


def neutral_frame(median_shape: np.ndarray, neutral: np.ndarray, ids: np.ndarray | None = None,
                  rounds: int = 20) -> np.ndarray:
    """Robust rigid map (4, 4) from a take's stabilized shape onto the neutral (`y = A x`).

    Iteratively reweighted Kabsch with Cauchy weights at half the median residual, so the parts
    the take's expression moves away from the neutral (half the face in a smile) count little:
    on generated 400-point takes the skull frame lands within 0.014 cm (smile), 0.008 cm (jaw
    open) and 0.005 cm (neutral) of the truth, median over vertices and frames.

    Args:
        median_shape: (V, 3) the take's median shape in its own skull frame, cm.
        neutral: (V, 3) the subject's neutral, cm.
        ids: vertices to align (e.g. a region the expressions leave still), None = all.
        rounds: reweighting rounds.
    """
    x, y = np.asarray(median_shape, np.float64), np.asarray(neutral, np.float64)
    if ids is not None:
        x, y = x[ids], y[ids]
    weights = np.ones(len(x))
    for _ in range(rounds):
        fit = fit_rigid(x, y, weights)
        residual = np.linalg.norm(x @ fit.rotation.T + fit.translation - y, axis=1)
        scale = 0.5 * np.median(residual) + 1e-6
        weights = 1.0 / (1.0 + (residual / scale) ** 2)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = fit.rotation, fit.translation
    return out


class StabilizeTakes(Node):
    """Give every take a skull motion in the neutral's frame: its tracked rigid, else mode pursuit."""

    type_name = "dynamics.StabilizeTakes"
    version = 1
    kind = SEQUENCE
    resources = {"gpu": 1}

    class Params(NodeParams):
        group: str = Param("", description="Vertex group mode pursuit and the fit onto the neutral align "
                           "('' = all vertices, robustly weighted; a region that moves with the skull, "
                           "e.g. forehead and nose, is better when the takes have one).")
        max_vertices: int = Param(2000, ge=10, description="Mode pursuit's energy vertices "
                                  "(farthest-point sampled): its default, enough for a head.")
        restabilize: bool = Param(False, description="Stabilize every take, ignoring tracked rigid "
                                  "transforms (e.g. when they are not in the neutral's frame).")

    takes = In(Takes, doc="The takes (dynamics.LoadTakes).")
    neutral = In(MeshSequence, per_frame=False, doc="The subject's neutral (1 frame, the takes' topology "
                                                   "and vertex order): defines the skull frame.")
    stabilized = Out(Takes, doc="The takes, each with skull-to-world transforms (skull frame = the neutral's).")
    report = Out(JsonValue, doc="Per take: 'tracked' or 'mode pursuit' and the fit's median residual (cm).")

    def check_plan(self, producers: dict[str, list[Node]]) -> None:
        """Before anything runs: when the takes come from dynamics.LoadTakes and the neutral from
        a reader that knows its vertex count, a take of another vertex count than the neutral is
        one refusal (NPZ headers only), not a failure after every take was read."""
        takes = [n for n in producers.get("takes", []) if hasattr(n, "peek_vertex_counts")]
        self._takes_reader = next((n for n in producers.get("takes", []) if hasattr(n, "peek_takes")), None)
        neutral = [n for n in producers.get("neutral", []) if hasattr(n, "peek_vertex_count")]
        count = neutral[0].peek_vertex_count() if neutral else None
        if not takes or count is None:
            return
        for name, found in takes[0].peek_vertex_counts().items():
            if found != count:
                raise InputError("neutral", f"expected one frame of {found} vertices (the takes' topology and "
                                            f"vertex order: take '{name}' has {found}), found {count} vertices")

    def peek_takes(self, frames: range) -> list[tuple[str, int, float | None]] | None:
        """The takes of a run of `frames` as its reader (dynamics.LoadTakes) sees them while
        planning: (name, frames in the run, frame rate or None); None when unknown."""
        reader = getattr(self, "_takes_reader", None)
        return reader.peek_takes(frames) if reader is not None else None

    def run(self, takes: Takes, neutral: MeshSequence) -> dict:
        p = self.params
        rest = check_neutral(neutral, takes)
        ids = None
        if p.group:
            if p.group not in takes.groups:
                raise InputError("group", f"expected a vertex group '{p.group}' of the takes, found "
                                          f"{sorted(takes.groups) or 'none'}")
            ids = np.unique(np.asarray(takes.groups[p.group], np.int64))
        todo = [i for i in range(takes.num_takes) if p.restabilize or not takes.has_rigid[i]]
        skulls, report = [], {}
        for i in range(takes.num_takes):
            mesh = takes.take(i)
            if i not in todo:
                skulls.append(takes.skull(i))
                report[takes.names[i]] = {"skull": "tracked"}
                continue
            from ..stabilize.mode_pursuit import mode_pursuit

            self.progress(todo.index(i) / len(todo), f"mode pursuit on take {takes.names[i]}")
            result = mode_pursuit(mesh.vertices, vertex_ids=ids, max_vertices=p.max_vertices,
                                  device=self.device)
            matrices = np.asarray(result.matrices, np.float64)
            shape = np.median(stabilize_vertices(mesh.vertices, matrices), axis=0)
            to_neutral = neutral_frame(shape, rest, ids)
            matrices = matrices @ np.linalg.inv(to_neutral)  # skull frame := the neutral's
            residual = np.linalg.norm(shape @ to_neutral[:3, :3].T + to_neutral[:3, 3] - rest, axis=1)
            report[takes.names[i]] = {"skull": "mode pursuit",
                                      "median_residual_to_neutral_cm": round(float(np.median(residual)), 5)}
            skulls.append(RigidSequence(matrices=matrices))
        out = Takes.from_sequences(takes.names, [takes.take(i) for i in range(takes.num_takes)], skulls)
        return {"stabilized": out, "report": JsonValue(report)}


def check_neutral(neutral: MeshSequence, takes: Takes) -> np.ndarray:
    """The neutral's (V, 3) float64 vertices, or InputError ("neutral") when it is not one frame of
    the takes' vertex count."""
    if neutral.num_frames != 1 or neutral.num_vertices != takes.num_vertices:
        raise InputError("neutral", f"expected one frame of {takes.num_vertices} vertices (the takes' "
                                    f"topology and vertex order), found {neutral.num_frames} frames of "
                                    f"{neutral.num_vertices} vertices")
    return neutral.vertices[0].astype(np.float64)


class TrainRemovalTakes(Node):
    """Train the removal network F on held-expression takes with the moving-average target (eq. 5)."""

    type_name = "dynamics.TrainRemovalTakes"
    version = 2  # v2: input columns constant in F's training are read as their training value (standardize_inputs) in the held-out error
    kind = SEQUENCE
    resources = {"gpu": 1}

    class Params(NodeParams):
        held: str = Param("*", description="Name pattern (fnmatch) of the held-expression takes F trains "
                          "on; the moving-average target assumes the expression is held, so dialog "
                          "takes are left out.")
        held_out: str = Param("", description="Take kept out of training, whose error against its own "
                              "moving-average target is reported; '' = the last held-expression take "
                              "(by name) when there are at least two, '-' = none.")
        region: str = Param("", description="Vertex group of the takes to train on ('' = all vertices); "
                            "the network records it and then also cleans whole captures.")
        target_window_s: float = Param(0.1, gt=0, description="Half-width of the moving average (s), "
                                       "converted to frames at each take's rate: the 0.2 s average spans "
                                       "a whole period of skin modes from 5 Hz up (the paper: 10 frames "
                                       "at 128 fps, 0.08 s).")
        num_samples: int = Param(344, ge=1, description="Skin samples (farthest-point sampling of the "
                                 "neutral): the paper's count.")
        window: int = Param(10, ge=1, description="Half-size of the descriptor windows (samples).")
        feature_fps: float = Param(120.0, gt=0, description="Sample rate of the windows (1/s); takes at "
                                   "other rates are resampled, up to 1.3 x this rate.")
        hidden: list[int] = Param([128, 128], description="Hidden layer widths.")
        epochs: int = Param(40, ge=1, description="Passes over the training rows (paper: 250).")
        batch_size: int = Param(10000, ge=1, description="Rows per Adam step.")
        lr: float = Param(1e-3, gt=0, description="Adam learning rate.")
        max_rows: int = Param(200000, ge=1, description="(frame, sample) rows drawn for training.")
        seed: int | None = Param(None, ge=0, description="Seed of the rows, batch order and weights; none = "
                                 "derived from the task's cache key; an integer pins training.")

    takes = In(Takes, doc="Takes with skull motion (dynamics.StabilizeTakes).")
    neutral = In(MeshSequence, per_frame=False, doc="The subject's neutral (1 frame, the takes' topology).")
    model = Out(TorchModel, doc="Removal network F (dynamics.MLP).")
    report = Out(JsonValue, doc="Takes used, rows, loss per epoch, the held-out take's error.")

    def split_takes(self, names: list[str]) -> tuple[list[int], int | None]:
        """(indices of the takes F trains on, index of the held-out take or None) among `names`.

        Raises:
            InputError: ("held") no take matches `held`; ("held_out") not a take, or none left.
        """
        p = self.params
        held = [i for i, name in enumerate(names) if fnmatch.fnmatchcase(name, p.held)]
        if not held:
            raise InputError("held", f"expected takes matching '{p.held}', found none among {names}")
        if p.held_out == "-":
            out = None
        elif p.held_out:
            if p.held_out not in names:
                raise InputError("held_out", f"expected one of the takes {names}, found '{p.held_out}'")
            out = names.index(p.held_out)
        else:
            out = held[-1] if len(held) > 1 else None
        train = [i for i in held if i != out]
        if not train:
            raise InputError("held_out", f"expected a take left to train on, found only '{names[out]}'")
        return train, out

    def margin(self, fps: float) -> int:
        """Frames of a take at `fps` kept from its ends: the descriptor window's reach and the
        moving-average target's half-width."""
        p = self.params
        return max(window_reach(p.window, fps, p.feature_fps), target_half_width(p.target_window_s, fps))

    def check_frames(self, frames: range, producers: dict[str, list[Node]]) -> None:
        """Before anything runs, from the takes' headers (dynamics.LoadTakes through
        dynamics.StabilizeTakes): the take selection (`held`, `held_out`), the frame rates
        against the window, and that the run's frames of the chosen takes give a training row
        (--frames 0:4 is one refusal, not a failure after every take was stabilized)."""
        peeked = _peek_takes(producers, frames)
        if peeked is None:
            return
        train, out = self.split_takes([name for name, _, _ in peeked])
        chosen = [peeked[i] for i in train + ([out] if out is not None else [])]
        for name, _, fps in chosen:
            if fps is not None:
                _check_window(self.params, name, fps)
        _refuse_no_rows([peeked[i] for i in train], frames, self.margin)

    def run(self, takes: Takes, neutral: MeshSequence) -> dict:
        p = self.params
        rest = check_neutral(neutral, takes)
        if any(not takes.has_rigid[i] for i in range(takes.num_takes)):
            missing = [n for i, n in enumerate(takes.names) if not takes.has_rigid[i]]
            raise InputError("takes", f"expected a skull motion for every take (dynamics.StabilizeTakes), "
                                      f"found none for {missing}")
        train, out = self.split_takes(list(takes.names))
        region_ids = None
        if p.region:
            if p.region not in takes.groups:
                raise InputError("region", f"expected a vertex group '{p.region}' of the takes, found "
                                           f"{sorted(takes.groups) or 'none'}")
            region_ids = np.unique(np.asarray(takes.groups[p.region], np.int64))
        cut = (lambda v: v) if region_ids is None else (lambda v: v[:, region_ids])
        rest_part = rest if region_ids is None else rest[region_ids]
        samples = select_samples(rest_part, p.num_samples)
        for i in train + ([out] if out is not None else []):
            _check_window(p, takes.names[i], float(takes.fps[i]))
        seed = self.seed if p.seed is None else p.seed
        # one moving-average half-width per take, in its frames (the takes' rates differ)
        windows = [target_half_width(p.target_window_s, float(takes.fps[i])) for i in train]
        vertices = [cut(takes.take(i).vertices) for i in train]
        params = _RemovalParams(target="moving_average", window=p.window, feature_fps=p.feature_fps,
                                hidden=p.hidden, epochs=p.epochs, batch_size=p.batch_size, lr=p.lr,
                                max_rows=p.max_rows)
        try:
            model, report = fit_removal(params, vertices, [float(takes.fps[i]) for i in train],
                                        [takes.skull(i).matrices for i in train], None, [None] * len(train),
                                        rest_part, samples, seed, self.device, self.progress, windows)
        except InputError as err:
            raise _too_short(err, [takes.names[i] for i in train]) from err
        model.config["target"] = "moving_average"
        model.config["target_window_s"] = p.target_window_s
        if region_ids is not None:
            model.config.update(region=p.region, whole_vertices=int(takes.num_vertices))
            model.normalization["region_ids"] = region_ids
        report = {"takes": [takes.names[i] for i in train], "frames": int(sum(len(v) for v in vertices)),
                  "loss_per_epoch": report["losses"], "final_loss": report["final_loss"],
                  "rows": report["rows"], "seconds": report["seconds"]}
        if out is not None:
            report["held_out"] = held_out_error(model, takes, out, p.target_window_s, region_ids)
        return {"model": model, "report": JsonValue(report)}


def target_half_width(target_window_s: float, fps: float) -> int:
    """The moving-average target's half-width in frames of a take at `fps` (at least 1)."""
    return max(1, int(round(target_window_s * fps)))


def _check_window(p: NodeParams, name: str, fps: float) -> None:
    """InputError ("feature_fps") when a take at `fps` needs more frames of window than HALO."""
    if window_reach(p.window, fps, p.feature_fps) > HALO:
        raise InputError("feature_fps", f"take '{name}' at {fps:g} fps: expected a frame rate up to "
                                        f"{(HALO - 3) * p.feature_fps / p.window:g} fps for window {p.window} "
                                        f"at {p.feature_fps:g} fps")


def _peek_takes(producers: dict[str, list[Node]], frames: range) -> list[tuple[str, int, float | None]] | None:
    """The takes a trainer's 'takes' producer (dynamics.StabilizeTakes) sees while planning, or None."""
    readers = [n for n in producers.get("takes", []) if hasattr(n, "peek_takes")]
    return readers[0].peek_takes(frames) if readers else None


def _refuse_no_rows(takes: list[tuple[str, int, float | None]], frames: range,
                    margin: Callable[[float], int]) -> None:
    """InputError ("takes") when none of `takes` (name, frames in the run, fps) is longer than
    twice its margin (so `fit_removal` / `fit_synthesis` would find no training row); takes of
    unknown frame rate are not judged (run() does)."""
    if not takes or any(fps is None for _, _, fps in takes):
        return
    margins = [margin(fps) for _, _, fps in takes]
    if any(count > 2 * m for (_, count, _), m in zip(takes, margins)):
        return
    raise InputError("takes", f"--frames {frames.start}:{frames.stop}: takes {[name for name, _, _ in takes]}: "
                              f"{no_training_rows(margins, [count for _, count, _ in takes], 'take(s)')}; give "
                              f"longer takes or a longer --frames range")


def _too_short(err: InputError, names: list[str]) -> InputError:
    """The training functions' "no training frames" error ('captures') for the takes nodes: port
    'takes', the takes named, and what to change."""
    if err.port != "captures":
        return err
    return InputError("takes", f"takes {names}: {err.message.replace('capture(s)', 'take(s)')}; give longer takes "
                               f"or a longer --frames range")


class _RemovalParams(NodeParams):
    """The settings `fit_removal` reads (dynamics.TrainRemoval's, as TrainRemovalTakes sets them)."""

    target: str = "moving_average"
    window: int = 10
    feature_fps: float = 120.0
    target_window: int = 10
    hidden: list[int] = [128, 128]
    epochs: int = 40
    batch_size: int = 10000
    lr: float = 1e-3
    max_rows: int = 200000


def held_out_error(model: TorchModel, takes: Takes, index: int, target_window_s: float,
                   region_ids: np.ndarray | None) -> dict:
    """A take's RMS distance (mm) to its own moving-average target before and after removal.

    Frames within the moving average's half-width of either end are left out (the average is
    not defined there); over the network's region when it records one.
    """
    mesh, skull = takes.take(index), takes.skull(index).matrices
    fps = float(takes.fps[index])
    window = max(1, int(round(target_window_s * fps)))
    work = mesh.vertices if region_ids is None else mesh.vertices[:, region_ids]
    target = moving_average_target(work, skull, window=window)
    quasi, _ = remove_dynamics(model, mesh, skull, fps, region_ids)
    if region_ids is not None:
        quasi = quasi[:, region_ids]
    keep = slice(window, len(work) - window)
    before = rms_distance(work[keep], target[keep])
    after = rms_distance(quasi[keep], target[keep])
    return {"take": takes.names[index], "frames": int(len(work) - 2 * window),
            "rms_before_mm": round(10 * before, 4), "rms_after_mm": round(10 * after, 4),
            "reduction_pct": round(100 * (1 - after / before), 2) if before > 0 else 0.0}


class TrainSynthesisTakes(Node):
    """Train the synthesis network H as in the paper: quasistatic takes from F, their captures the target."""

    type_name = "dynamics.TrainSynthesisTakes"
    version = 2  # v2: input columns constant in F's training are read as their training value (standardize_inputs) in F's quasistatic takes
    kind = SEQUENCE
    resources = {"gpu": 1}

    class Params(NodeParams):
        takes: str = Param("*", description="Name pattern (fnmatch) of the takes H learns from: all by "
                           "default (held expressions and dialog: F's quasistatic output is the input, "
                           "the capture the target, so no take needs a held expression).")
        region: str = Param("", description="Vertex group of H's samples ('' = all vertices).")
        num_samples: int = Param(344, ge=1, description="Skin samples (farthest-point sampling of the neutral).")
        window: int = Param(10, ge=1, description="Half-size of the skull descriptor window (samples).")
        feature_fps: float = Param(120.0, gt=0, description="Sample rate of the window (1/s).")
        spacing_cm: float = Param(0.2, gt=0, description="Preferred stretch stencil spacing (cm).")
        hidden: list[int] = Param([256, 256], description="Hidden layer widths.")
        epochs: int = Param(30, ge=1, description="Passes over the training frames.")
        batch_size: int = Param(50, ge=1, description="Frames per Adam step.")
        lr: float = Param(1e-3, gt=0, description="Adam learning rate.")
        seed: int | None = Param(None, ge=0, description="Seed of the batch order and weights; none = "
                                 "derived from the task's cache key; an integer pins training.")

    takes = In(Takes, doc="Takes with skull motion (dynamics.StabilizeTakes).")
    neutral = In(MeshSequence, per_frame=False, doc="The subject's neutral (1 frame, the takes' topology).")
    removal = In(TorchModel, doc="Removal network F (dynamics.TrainRemovalTakes).")
    model = Out(TorchModel, doc="Synthesis network H (dynamics.MLP).")
    report = Out(JsonValue, doc="Takes used, rows, loss per epoch.")

    def choose_takes(self, names: list[str]) -> list[int]:
        """Indices of the takes H learns from among `names`; InputError ("takes") when none."""
        chosen = [i for i, name in enumerate(names) if fnmatch.fnmatchcase(name, self.params.takes)]
        if not chosen:
            raise InputError("takes", f"expected takes matching '{self.params.takes}', found none among {names}")
        return chosen

    def check_frames(self, frames: range, producers: dict[str, list[Node]]) -> None:
        """Before anything runs, from the takes' headers: a pattern matching no take, and run
        frames that give no training row, are one refusal each."""
        peeked = _peek_takes(producers, frames)
        if peeked is None:
            return
        chosen = self.choose_takes([name for name, _, _ in peeked])
        p = self.params
        _refuse_no_rows([peeked[i] for i in chosen], frames, lambda fps: window_reach(p.window, fps, p.feature_fps))

    def run(self, takes: Takes, neutral: MeshSequence, removal: TorchModel) -> dict:
        p = self.params
        rest = check_neutral(neutral, takes)
        chosen = self.choose_takes(list(takes.names))
        missing = [takes.names[i] for i in chosen if not takes.has_rigid[i]]
        if missing:
            raise InputError("takes", f"expected a skull motion for every take (dynamics.StabilizeTakes), "
                                      f"found none for {missing}")
        ids = None
        if p.region:
            if p.region not in takes.groups:
                raise InputError("region", f"expected a vertex group '{p.region}' of the takes, found "
                                           f"{sorted(takes.groups) or 'none'}")
            ids = np.unique(np.asarray(takes.groups[p.region], np.int64))
        captures, quasistatic, skulls, fps = [], [], [], []
        for n, i in enumerate(chosen):
            mesh, skull = takes.take(i), takes.skull(i).matrices
            region = check_model(removal, "removal", mesh, float(takes.fps[i]), port="removal", whole=True,
                                 mesh_port="takes")
            quasi, _ = remove_dynamics(removal, mesh, skull, float(takes.fps[i]), region)
            captures.append(mesh.vertices)
            quasistatic.append(quasi)
            skulls.append(skull)
            fps.append(float(takes.fps[i]))
            self.progress(0.2 * (n + 1) / len(chosen), f"quasistatic take {takes.names[i]} from F")
        samples = select_samples(rest, p.num_samples, ids)
        try:
            model, report = fit_synthesis(p, captures, quasistatic, skulls, [rest] * len(chosen), fps,
                                          [None] * len(chosen), rest, samples,
                                          self.seed if p.seed is None else p.seed, self.device,
                                          lambda f, m: self.progress(0.2 + 0.8 * f, m))
        except InputError as err:
            raise _too_short(err, [takes.names[i] for i in chosen]) from err
        report = {"takes": [takes.names[i] for i in chosen], "rows": report["rows"],
                  "loss_per_epoch": report["losses"], "final_loss": report["final_loss"],
                  "seconds": report["seconds"]}
        return {"model": model, "report": JsonValue(report)}


class SaveReport(Node):
    """Write the training reports (JSON) and show their numbers as a table."""

    type_name = "dynamics.SaveReport"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param("out/dynamics/train_report.json", output_file=True,
                          description="Output JSON file ('' = write nothing, only the table).")

        @field_validator("path")
        @classmethod
        def _suffix(cls, value: str) -> str:  # refused at validation, not after the training
            return check_output_suffix(value, [".json"], allow_empty=True)

    report = In(JsonValue, doc="The removal network's report (dynamics.TrainRemovalTakes).")
    synthesis = In(JsonValue, optional=True, doc="The synthesis network's report (dynamics.TrainSynthesisTakes).")
    files = Out(Files, doc="The written file.")
    table = Out(Table, doc="The scalar entries, nested ones flattened ('held_out.rms_after_mm').")

    def run(self, report: JsonValue, synthesis: JsonValue | None = None) -> dict:
        value = dict(report.value) if synthesis is None else {"removal": report.value, "synthesis": synthesis.value}
        rows: list[list] = []

        def add(prefix: str, item: object) -> None:
            if isinstance(item, dict):
                for key, sub in item.items():
                    add(f"{prefix}.{key}" if prefix else str(key), sub)
            elif isinstance(item, list) and item and all(isinstance(v, (int, float)) for v in item):
                rows.append([f"{prefix} (first, last)", f"{item[0]:g}, {item[-1]:g}"])
            elif isinstance(item, list):
                rows.append([prefix, ", ".join(str(v) for v in item)])
            else:
                rows.append([prefix, item])

        add("", value)
        paths = []
        if self.params.path:
            write_text_atomic(self.params.path, json.dumps(value, indent=2, sort_keys=True) + "\n")
            paths = [self.params.path]
        return {"files": files_value(paths), "table": Table(["entry", "value"], rows)}
