"""nodegraph's own node types, one subpackage per area (loaded as the `builtin` plugin)."""

from importlib import import_module

AREAS = ["io", "synth", "rigid", "stabilize", "report"]

for _area in AREAS:
    try:
        import_module(f"{__name__}.{_area}")
    except ModuleNotFoundError as _err:  # an area not written yet
        if _err.name != f"{__name__}.{_area}":
            raise
