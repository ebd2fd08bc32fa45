"""Every figure with a legend of several series draws each series in its own colour (the
histograms drew every skull frame's line in black: the legend could not be read). The
figures' artists are inspected, no image comparison."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib.colors import to_rgba
from matplotlib.patches import StepPatch

from nodegraph import run_node
from nodes.io.face_model import load_face_model
from nodes.report import plots
from nodes.report.plots import SERIES_COLOURS, plot_head_motion, plot_position_histograms, position_histograms_figure
from nodes.report.stabilization import StabilizationReport
from nodes.synth.performance import generate_performance

BLACK = to_rgba("black")


@pytest.fixture
def figures(monkeypatch):
    """The figures the report functions save, by file name (still written)."""
    saved = {}
    save = plots.save_figure

    def keep(fig, path):
        saved[str(path).rsplit("/", 1)[-1]] = fig
        return save(fig, path)

    monkeypatch.setattr(plots, "save_figure", keep)
    return saved


def _histogram_colours(fig) -> list[dict[str, tuple]]:
    """Per panel: legend label (without its MAD) -> edge colour of its line (unfilled StepPatch)."""
    panels = []
    for ax in fig.axes:
        steps = [p for p in ax.patches if isinstance(p, StepPatch) and not p.get_fill()]
        panels.append({p.get_label().split(" (MAD")[0]: tuple(p.get_edgecolor()) for p in steps})
    return panels


def _assert_distinct(colours: dict[str, tuple], count: int) -> None:
    assert len(colours) == count, colours
    assert len(set(colours.values())) == count, colours
    assert BLACK not in colours.values(), colours


def _skulls(count: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(0)
    world = rng.normal(0.0, 1.0, (40, 6, 3))
    return world, {f"method_{i}": world + rng.normal(0.0, 0.1, world.shape) for i in range(count)}


def test_plot_position_histograms_gives_each_skull_frame_its_own_colour(figures, tmp_path):
    world, skulls = _skulls(4)
    plot_position_histograms(world, skulls, tmp_path / "histograms.png", vertices=[0, 5])
    panels = _histogram_colours(figures["histograms.png"])
    assert len(panels) == 6
    for colours in panels:
        _assert_distinct(colours, 4)
        assert colours == {k: to_rgba(c) for k, c in zip(skulls, SERIES_COLOURS)}
    # the legend shows the same colours (its handles of unfilled steps are lines)
    handles = figures["histograms.png"].axes[0].get_legend().legend_handles
    assert [to_rgba(h.get_color()) for h in handles[1:]] == [to_rgba(c) for c in SERIES_COLOURS[:4]]


def test_position_histograms_figure_keeps_world_grey_and_cycles_past_the_palette():
    world, skulls = _skulls(len(SERIES_COLOURS) + 1)
    fig = position_histograms_figure(world, skulls, vertices=[1])
    filled = [p for p in fig.axes[0].patches if p.get_fill()]
    assert [p.get_label().split(" (MAD")[0] for p in filled] == ["world"]
    assert tuple(filled[0].get_facecolor()) == to_rgba("0.7")
    colours = _histogram_colours(fig)[0]
    assert list(colours.values())[:len(SERIES_COLOURS)] == [to_rgba(c) for c in SERIES_COLOURS]
    assert colours[f"method_{len(SERIES_COLOURS)}"] == to_rgba(SERIES_COLOURS[0])
    assert to_rgba("0.7") not in colours.values()


def test_plot_head_motion_gives_each_label_its_own_colour(figures, tmp_path):
    motion = np.tile(np.eye(4), (12, 1, 1))
    curves = {}
    for i, label in enumerate(["truth", "icp", "procrustes", "mode_pursuit"]):
        curves[label] = motion.copy()
        curves[label][:, 0, 3] = np.linspace(0, 1 + i, 12)
    plot_head_motion(curves, tmp_path / "head_motion.png")
    fig = figures["head_motion.png"]
    for ax in fig.axes[:6]:
        colours = {line.get_label(): to_rgba(line.get_color()) for line in ax.get_lines()}
        assert len(colours) == 4 and len(set(colours.values())) == 4, colours


def test_stabilization_report_draws_every_estimate_in_its_own_colour(figures, tmp_path):
    model = load_face_model(region="face", max_vertices=120)
    perf = generate_performance(model, num_frames=30, seed=3, noise_cm=0.01)
    labels = ["first", "second", "third"]
    run_node(StabilizationReport, {"folder": str(tmp_path), "labels": labels}, capture=perf.capture,
             truth_rigid=perf.rigid, truth=perf.stabilized, estimates=[perf.rigid] * 3)
    panels = _histogram_colours(figures["histograms.png"])
    assert panels
    for colours in panels:
        _assert_distinct(colours, 4)  # the truth and the three estimates
    for ax in figures["head_motion.png"].axes[:6]:
        colours = {line.get_label(): to_rgba(line.get_color()) for line in ax.get_lines()}
        assert len(colours) == 4 and len(set(colours.values())) == 4, colours
