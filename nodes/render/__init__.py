"""Differentiable rendering: rasterizer with albedo and SH lighting (`renderer.py`, torch),
z-buffer and silhouette kernels (`raster.py`, numba), default appearance of the bundled head
(`appearance.py`), and the nodes (`nodes.py`).

Importing the package registers the nodes only; torch and numba are imported when a node runs.
"""

from .nodes import DefaultAppearance, Render

__all__ = ["DefaultAppearance", "Render"]
