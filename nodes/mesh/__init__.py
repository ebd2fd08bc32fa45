"""Mesh sequence edits: cut out a vertex group and put it back (`mesh.SelectRegion`, `mesh.ReplaceRegion`)."""

from .._areas import import_modules

import_modules(__name__, ["regions"])
