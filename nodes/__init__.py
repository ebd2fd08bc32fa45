"""nodegraph's own node types, one subpackage per area (loaded as the `builtin` plugin).

`AREAS` lists the node areas; `nodes.geometry` (shared math, no nodes) is not one and is
imported by the areas' modules where they need it. Importing `nodes` registers every node
type without importing torch, scipy, matplotlib, trimesh, pxr, OpenImageIO or av: node
modules import those inside `run()` (see tests/test_startup.py).
"""

from ._areas import import_modules

AREAS = ["io", "synth", "rigid", "stabilize", "report", "render", "landmarks", "dynamics"]

import_modules(__name__, AREAS)
