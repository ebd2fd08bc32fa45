"""`position_histograms_figure` adds its StepPatches without `ax.stairs` (whose data-limit
update walked every patch path: a third of the figure's time) and sets the limits itself. Each
panel must look as `ax.stairs` would draw it: the same limits (autoscaling with 5% margins, y
sticky at 0) and the same colours (`stairs(color=)` colours a filled patch's face, a line's
edge), so that histograms.png is unchanged."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import StepPatch

from nodes.report.plots import position_histograms_figure


def test_histogram_panels_match_stairs():
    rng = np.random.default_rng(0)
    world = rng.normal(0, 1.0, (300, 5, 3)).astype(np.float32)
    skulls = {"a": rng.normal(0, 0.05, (300, 5, 3)), "b": rng.standard_t(3, (300, 5, 3)) * 0.02}
    fig = position_histograms_figure(world, skulls, vertices=[1, 4])
    for ax in fig.axes:
        patches = [p for p in ax.patches if isinstance(p, StepPatch)]
        assert len(patches) == 3
        reference = Figure().subplots()
        for patch in patches:
            values, edges, _ = patch.get_data()
            colour = patch.get_facecolor() if patch.get_fill() else patch.get_edgecolor()
            drawn = reference.stairs(values, edges, fill=patch.get_fill(), color=colour, linewidth=1.2,
                                     label=patch.get_label())
            np.testing.assert_array_equal(drawn.get_facecolor(), patch.get_facecolor())
            np.testing.assert_array_equal(drawn.get_edgecolor(), patch.get_edgecolor())
        np.testing.assert_allclose(ax.get_xlim(), reference.get_xlim(), rtol=1e-12)
        np.testing.assert_allclose(ax.get_ylim(), reference.get_ylim(), rtol=1e-12)
        assert [t.get_text() for t in ax.get_legend().get_texts()] == [p.get_label() for p in patches]
