"""Plots of captures: head-motion curves and per-vertex position histograms (Agg, no screen).

`plot_position_histograms` reproduces Fig. 5 of the mode-pursuit paper: over time, a vertex's
position (one coordinate, mean removed) is blurred by head motion in world space, while in
the skull frame it has a sharp mode at rest. `position_spread` gives that as a number (the
median absolute deviation per vertex and coordinate, cm).

Figures are drawn on `matplotlib.figure.Figure` objects (no pyplot state, safe in threads) and
written atomically: a temporary name in the same folder, then `os.replace`.
matplotlib is imported inside the functions that draw (not at import: `import nodes`
stays light).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Mapping, NamedTuple, Sequence

import numpy as np

from nodegraph import SEQUENCE, Files, In, Index, InputError, MeshSequence, Node, NodeParams, Out, Param, RigidSequence
from nodegraph.files import atomic_path, files_value

from ..geometry.rigid import stabilize_vertices
from ..geometry.rotation import rotmat_to_euler

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = [
    "rigid_to_euler_translation", "default_vertices",
    "PositionSpread", "position_spread", "plot_head_motion", "plot_rigid_curves", "plot_position_histograms",
    "position_histograms_figure", "SERIES_COLOURS", "save_figure", "CaptureReport",
]

_AXES = ("x", "y", "z")
# Distinct line colours of the series of a figure, in order (matplotlib's "tab10" without its grey,
# which is the world histogram's).
SERIES_COLOURS = ("#1f77b4", "#ff7f0e", "#2ca02c", "#d62728", "#9467bd", "#8c564b", "#e377c2", "#bcbd22",
                  "#17becf")


def rigid_to_euler_translation(matrices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split skull-to-world matrices into extrinsic XYZ Euler angles and translations.

    Args:
        matrices: (F, 4, 4) float, `x_world = M @ [x_skull, 1]`.
    Returns:
        angles (F, 3) degrees, with `R = Rz(z) Ry(y) Rx(x)` (scipy "xyz"); translation (F, 3) cm.
    """
    matrices = np.asarray(matrices, dtype=np.float64)
    if matrices.ndim != 3 or matrices.shape[1:] != (4, 4):
        raise ValueError(f"matrices: expected shape (F, 4, 4), found {matrices.shape}")
    if len(matrices) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    angles = np.rad2deg(rotmat_to_euler(matrices[:, :3, :3], "xyz"))
    return angles, matrices[:, :3, 3].copy()


def default_vertices(count_vertices: int, count: int = 4) -> np.ndarray:
    """`count` evenly spaced vertex indices in 0..V-1 (at most V)."""
    return np.unique(np.linspace(0, max(count_vertices - 1, 0), min(count, count_vertices)).round()
                     .astype(np.int64))


class PositionSpread(NamedTuple):
    """Median absolute deviation (cm) of positions over time.

    Attributes:
        world: (N, 3) per chosen vertex and coordinate, world frame.
        skull: label -> (N, 3), skull frame.
    """

    world: np.ndarray
    skull: dict[str, np.ndarray]


def _mad(positions: np.ndarray) -> np.ndarray:
    """(F, N, 3) -> (N, 3) median absolute deviation over frames."""
    return np.median(np.abs(positions - np.median(positions, axis=0)), axis=0)


def _as_mapping(skull: np.ndarray | Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    return dict(skull) if isinstance(skull, Mapping) else {"skull": skull}


def _check_positions(name: str, value: np.ndarray, like: tuple[int, ...] | None = None) -> np.ndarray:
    value = np.asarray(value)
    if value.ndim != 3 or value.shape[2] != 3:
        raise ValueError(f"{name}: expected shape (F, V, 3), found {value.shape}")
    if like is not None and value.shape != like:
        raise ValueError(f"{name}: expected shape {like} (from world), found {value.shape}")
    return value


def position_spread(world: np.ndarray, skull: np.ndarray | Mapping[str, np.ndarray],
                    vertices: Sequence[int] | None = None) -> PositionSpread:
    """Spread over time of some vertices' positions, in world and in the skull frame(s).

    Args:
        world: (F, V, 3) cm, world frame.
        skull: (F, V, 3) cm, skull frame, or label -> (F, V, 3) (several stabilizations).
        vertices: N vertex indices; None = `default_vertices(V)`.
    Returns:
        PositionSpread (median absolute deviations, cm); a sharp rest mode gives a small one.
    Raises:
        ValueError: shapes disagree or a vertex index is outside 0..V-1.
    """
    world = _check_positions("world", world)
    skulls = {k: _check_positions(f"skull['{k}']", v, world.shape) for k, v in _as_mapping(skull).items()}
    ids = default_vertices(world.shape[1]) if vertices is None else np.asarray(vertices, np.int64)
    if ids.size and (ids.min() < 0 or ids.max() >= world.shape[1]):
        raise ValueError(f"vertices: expected indices in 0..{world.shape[1] - 1}, found "
                         f"{int(ids.min())}..{int(ids.max())}")
    return PositionSpread(_mad(world[:, ids].astype(np.float64)),
                          {k: _mad(v[:, ids].astype(np.float64)) for k, v in skulls.items()})


def save_figure(fig: Figure, path: str | os.PathLike) -> Path:
    """Write `fig` as PNG atomically (`atomic_path`: temp file in the same folder, then os.replace)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    with atomic_path(path) as tmp, open(tmp, "wb") as handle:
        fig.savefig(handle, format="png", dpi=100)
    return Path(path)


def plot_head_motion(curves: Mapping[str, np.ndarray], path: str | os.PathLike,
                     fps: float = 30.0) -> Path:
    """Plot rotation angles (deg, extrinsic XYZ) and translations (cm) vs frame, one line per label.

    The translation is the matrices' translation column (where the skull-frame origin goes),
    which includes the effect of rotating about a pivot away from the origin.

    Args:
        curves: label -> (F, 4, 4) skull-to-world matrices (e.g. "truth", "estimate").
        path: PNG file to write.
        fps: frames per second (top axis in seconds).
    Returns:
        The written path.
    """
    if not curves:
        raise ValueError("curves: expected at least one label -> (F, 4, 4) matrices, found none")
    split = {}
    for label, matrices in curves.items():
        try:
            split[label] = rigid_to_euler_translation(matrices)
        except ValueError as err:
            raise ValueError(f"curves['{label}']: {err}") from err
    return plot_rigid_curves(split, path, fps=fps)


def plot_rigid_curves(curves: Mapping[str, tuple[np.ndarray, np.ndarray]], path: str | os.PathLike, *,
                      fps: float | None = None, first_frame: int = 0, shaded: np.ndarray | None = None,
                      dashed: str | None = None) -> Path:
    """The 2 x 3 figure of `plot_head_motion` from angles and translations already split.

    Args:
        curves: label -> (angles (F, 3) deg, translation (F, 3) cm); NaN frames leave gaps.
        path: PNG file to write.
        fps: frames per second of a top axis in seconds; None = no top axis.
        first_frame: number of the first frame (the x axis).
        shaded: (F,) bool frames drawn with a grey band (e.g. failed fits).
        dashed: a label drawn dashed in black (e.g. "truth"), before the others.
    Returns:
        The written path.
    """
    from matplotlib.figure import Figure

    # Fixed margins (no constrained layout: its solver was most of the report's time).
    fig = Figure(figsize=(12, 6))
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.08, top=0.88 if fps else 0.93, wspace=0.22, hspace=0.3)
    axes = fig.subplots(2, 3, sharex=True)
    count = len(next(iter(curves.values()))[0]) if curves else 0
    frames = first_frame + np.arange(count)
    if shaded is not None:
        for f in frames[np.asarray(shaded, bool)]:
            for ax in axes.flat:
                ax.axvspan(f - 0.5, f + 0.5, color="0.9", linewidth=0)
    order = ([dashed] if dashed in curves else []) + [k for k in curves if k != dashed]
    for label in order:
        angles, trans = curves[label]
        style = {"color": "black", "linestyle": "--"} if label == dashed else {}
        x = first_frame + np.arange(len(angles))
        for c in range(3):
            axes[0, c].plot(x, angles[:, c], label=label, linewidth=1, **style)
            axes[1, c].plot(x, trans[:, c], label=label, linewidth=1, **style)
    for c, name in enumerate(_AXES):
        axes[0, c].set_title(f"rotation about {name} (deg)")
        axes[1, c].set_title(f"translation {name} (cm)", y=1.0)  # fixed: no overlap search (no top ticks)
        axes[1, c].set_xlabel("frame")
        if fps:
            top = axes[0, c].secondary_xaxis("top", functions=(lambda f: f / fps, lambda s: s * fps))
            top.set_xlabel("s")
        for row in range(2):
            axes[row, c].grid(alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize="small")  # "best" searches overlaps: slow
    return save_figure(fig, path)


def plot_position_histograms(world: np.ndarray, skull: np.ndarray | Mapping[str, np.ndarray],
                             path: str | os.PathLike, vertices: Sequence[int] | None = None,
                             bins: int = 60, vertex_labels: Sequence[int] | None = None) -> Path:
    """Histograms over time of a few vertices' positions, world vs skull frame (paper Fig. 5).

    Writes `position_histograms_figure` (same arguments) as a PNG at `path`; returns the written path.
    """
    return save_figure(position_histograms_figure(world, skull, vertices, bins, vertex_labels), path)


def position_histograms_figure(world: np.ndarray, skull: np.ndarray | Mapping[str, np.ndarray],
                               vertices: Sequence[int] | None = None, bins: int = 60,
                               vertex_labels: Sequence[int] | None = None) -> Figure:
    """The figure of `plot_position_histograms`.

    One row per vertex, one column per coordinate; each panel overlays the mean-removed
    positions in world (grey, filled) and in each skull frame (a line of its own colour of
    `SERIES_COLOURS`, in order), on shared bins. The legend gives each one's median absolute
    deviation (see `position_spread`).

    Args:
        world: (F, V, 3) cm, world frame.
        skull: (F, V, 3) cm, skull frame, or label -> (F, V, 3).
        vertices: vertex indices; None = `default_vertices(V)` (4 evenly spaced).
        bins: histogram bins per panel.
        vertex_labels: the vertex numbers shown in the titles, one per shown vertex (e.g. the
            original indices when `world` holds only a subset); None = the indices.
    Returns:
        The figure (no canvas attached).
    """
    spread = position_spread(world, skull, vertices)
    skulls = _as_mapping(skull)
    ids = default_vertices(world.shape[1]) if vertices is None else np.asarray(vertices, np.int64)
    from matplotlib.figure import Figure
    from matplotlib.patches import StepPatch

    rows = max(len(ids), 1)
    fig = Figure(figsize=(12, 2.6 * rows))
    fig.subplots_adjust(left=0.06, right=0.99, bottom=0.3 / rows, top=1.0 - 0.25 / rows,
                        wspace=0.2, hspace=0.45)
    axes = np.atleast_2d(fig.subplots(rows, 3, squeeze=False))
    names = ids if vertex_labels is None else np.asarray(vertex_labels, np.int64)
    # An explicit colour per skull frame: `stairs(color=None)` draws the patch edge black.
    colours = {"world": "0.7"} | {k: SERIES_COLOURS[i % len(SERIES_COLOURS)] for i, k in enumerate(skulls)}
    for row, vertex in enumerate(ids):
        for c in range(3):
            ax = axes[row, c]
            series = {"world": world[:, vertex, c]} | {k: v[:, vertex, c] for k, v in skulls.items()}
            series = {k: np.asarray(s, np.float64) - np.mean(s) for k, s in series.items()}
            hi = max(float(np.abs(s).max(initial=0.0)) for s in series.values()) or 1.0
            edges = np.linspace(-hi, hi, bins + 1)
            top = 0
            for k, s in series.items():
                mad = spread.world[row, c] if k == "world" else spread.skull[k][row, c]
                counts, _ = np.histogram(s, bins=edges)
                top = max(top, int(counts.max(initial=0)))
                # A StepPatch (what `ax.stairs` draws) added without `add_patch`'s data-limit
                # update, which walks the patch's path segment by segment (a third of this
                # figure's time); the limits are set below to what autoscaling would give.
                # (`stairs(color=...)` is the face colour of a filled patch, the edge colour of a line.)
                colour = {"facecolor" if k == "world" else "edgecolor": colours[k]}
                ax.add_artist(StepPatch(counts, edges, baseline=0, fill=k == "world", linewidth=1.2,
                                        label=f"{k} (MAD {mad:.3f} cm)", **colour))
            margin = 0.05 * (edges[-1] - edges[0])  # matplotlib's default axes margins (5%)
            ax.set_xlim(edges[0] - margin, edges[-1] + margin)
            ax.set_ylim(0, (top or 1) * 1.05)  # sticky at the baseline 0
            ax.set_title(f"vertex {int(names[row])}, {_AXES[c]} - mean (cm)", fontsize="small", y=1.0)
            ax.legend(loc="upper right", fontsize="x-small")
    axes[-1, 0].set_ylabel("frames")
    return fig


class CaptureReport(Node):
    """Plot a capture's head motion and its vertex histograms in world vs skull frame."""

    type_name = "report.CaptureReport"
    version = 2  # v2: histograms.png draws each skull frame in its own colour (were all black)
    kind = SEQUENCE
    writes_files = True
    preload = ("matplotlib.figure", "matplotlib.backends.backend_agg")

    class Params(NodeParams):
        folder: str = Param("report", output_file=True, description="output folder (created if missing)")
        vertices: list[Index] = Param([], description="vertices for the histograms; [] = 4 evenly "
                                                    "spaced")

    capture = In(MeshSequence, doc="captured world-space mesh (cm)")
    rigid = In(RigidSequence, doc="skull-to-world transforms, x_world = M_f x_skull")
    files = Out(Files, doc="head_motion.png and histograms.png")

    def run(self, capture: MeshSequence, rigid: RigidSequence) -> dict[str, Files]:
        if rigid.num_frames != capture.num_frames:
            raise InputError("rigid", f"expected {capture.num_frames} frames (as 'capture'), "
                                      f"found {rigid.num_frames}")
        vertices = list(self.params.vertices) or None
        v = capture.num_vertices
        if vertices is not None and (min(vertices) < 0 or max(vertices) >= v):
            raise InputError("vertices", f"expected indices in 0..{v - 1}, found {vertices}")
        folder = Path(self.params.folder)
        ids = default_vertices(v) if vertices is None else np.asarray(vertices, np.int64)
        world = np.ascontiguousarray(capture.vertices[:, ids])  # only the vertices shown
        skull = stabilize_vertices(world, rigid.matrices)
        self.progress(0.1, "head motion")
        paths = [plot_head_motion({"rigid": rigid.matrices}, folder / "head_motion.png", capture.fps)]
        self.progress(0.5, "histograms")
        paths.append(plot_position_histograms(world, {"skull": skull}, folder / "histograms.png",
                                              np.arange(len(ids)), vertex_labels=ids))
        return {"files": files_value(paths)}
