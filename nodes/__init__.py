"""nodegraph's own node types, one subpackage per area (loaded as the `builtin` plugin).

`AREAS` lists the node areas; `nodes.geometry` (shared math, no nodes) is not one and is
imported by the areas' modules where they need it. The registry imports an area when one of
its node types ("<area>.Name") is first asked for (`NODEGRAPH_AREAS`), so starting a graph
pays only for its own areas; `import_all()` imports every area. No area imports torch,
scipy, matplotlib, trimesh, pxr, OpenImageIO or av at module level: node modules import
those inside `run()` (see tests/test_startup.py).
"""

from ._areas import import_modules

AREAS = ["io", "mesh", "synth", "rigid", "stabilize", "report", "render", "landmarks", "dynamics", "fit", "flow", "temporal", "export"]
NODEGRAPH_AREAS = AREAS


def import_all() -> None:
    """Import (and so register) every area's node types."""
    import_modules(__name__, AREAS)
