"""nodegraph's own node types, one subpackage per area (loaded as the `builtin` plugin)."""

from ._areas import import_modules

AREAS = ["io", "synth", "rigid", "stabilize", "report"]

import_modules(__name__, AREAS)
