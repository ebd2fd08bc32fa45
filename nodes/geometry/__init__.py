"""Shared geometry: pure functions on arrays and tensors, imported by the node areas.

Modules: `dualquat` (quaternions and dual quaternions, torch), `bspline` (cubic B-splines
over frames, torch), `rigid` (Kabsch / Umeyama and 4x4 rigid helpers, numpy, plus torch
twins), `sampling` (farthest-point sampling, numpy and torch), `camera` (pinhole projection
with radial distortion, numpy and torch), `image` (bilinear sampling, crops, box and
Gaussian filters, torch). Not a node area (no nodes): this package imports
none of its modules, so `import nodes` stays light; import the module you need.
"""
