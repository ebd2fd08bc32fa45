"""Synthetic captures with ground truth: expression curves, head motion, performances."""

from .._areas import import_modules

import_modules(__name__, ["expressions", "head_motion", "performance", "dynamics", "camera"])
