"""Optical flow: differentiable dense flow in torch (`dense.py`), the geometric flow of a rendered
surface (`geometric.py`), and the nodes (`nodes.py`).

Importing the package registers the nodes only; torch is imported when a node runs.
"""

from .nodes import OpticalFlow

__all__ = ["OpticalFlow"]
