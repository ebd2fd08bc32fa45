"""Differentiable rendering: rasterizer with albedo and SH lighting (`renderer.py`, torch),
z-buffer kernel (`raster.py`, numba), default appearance of the bundled head
(`appearance.py`), and the `render.Render` node.

Importing the package registers the nodes only; torch and numba are imported when a node runs.
"""
