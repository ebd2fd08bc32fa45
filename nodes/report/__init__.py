"""Errors against ground truth, tables and plots."""

from .._areas import import_modules

import_modules(__name__, ["metrics", "plots", "stabilization", "html", "dynamics_map"])
