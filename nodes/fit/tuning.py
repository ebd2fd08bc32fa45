"""Tuning constants of the fit nodes, and the measurements that chose them.

The nodes' parameter descriptions say what a parameter does and why its default; the numbers
behind the defaults live here (each constant's docstring) and in `bench/fit.py`'s output.

Measurements behind `fit.EstimateAppearance`'s parameters (bench/fit.py, synthetic shots):

- `albedo`: 30-frame synthetic shots seeds 0-5, median rotation error with fit.EstimateIdentity
  at 8 frames: 'auto' 0.70/0.94/0.78/0.76/0.63/1.03 deg, 'painted' 1.07/1.81/-/0.77/-/2.10.
  Seeds 0/1/2/5 (random poses): 'painted' 0.98/1.55/1.07/2.38 deg (2.45/1.93/1.39/3.88 with
  `light_first` 180, that is the lighting never fitted first), 'default' 0.78/0.74/1.78/1.88,
  'relative' (seeds 1/2/5) 1.07/2.07/1.96; on the demo's near-static shot 'painted' 0.49,
  'relative' 2.14, 'default' 2.57.
- `noise` (render noise, default -2 = the plate's above 0.02): on a clean plate an albedo painted
  from one frame already carries the plate's noise and adding it hurts (seed 0, plate noise
  0.005: 1.6 -> 2.2 deg); at 0.015 it hurts too (seed 1: 1.4 -> 1.9); at 0.03 it helps (seed 0:
  3.7 -> 2.9, seed 2: 3.6 -> 3.1).
- `frames_used` 0 (from the plate's noise): see `painting_frame_count` in
  `nodes.fit.frame_selection`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from nodegraph import JsonValue

__all__ = ["PHOTOMETRIC_WEIGHT", "PHOTOMETRIC_REFERENCE_NOISE", "photometric_weight_for", "photometric_frame_weights",
           "LIGHTING_FRAMES",
           "LIGHT_FIRST_SPREAD", "RELATIVE_STEPS", "IDENTITY_ROUNDS", "IDENTITY_PRIOR", "IDENTITY_PRIOR_ONE_VIEW",
           "IDENTITY_SPREAD_DEG"]

PHOTOMETRIC_WEIGHT = 500.0
"""Default w_p of the photometric term (`nodes.fit.photometric`). bench/fit.py, seed 0, 16 frames, the
true identity: median rotation 1.73 deg with landmarks only, 1.21 with w_p 68, 0.77 with 500."""

PHOTOMETRIC_REFERENCE_NOISE = 0.005
"""Plate noise (linear) at which `PHOTOMETRIC_WEIGHT` was chosen (bench/fit.py's default)."""


def photometric_weight_for(weight: float, appearance: JsonValue | None) -> float:
    """w_p for the fit of a plate whose noise `fit.EstimateAppearance` measured ('plate_noise').

    The landmark network's reading of a noisy plate jitters more than the photometric term's
    mean over its thousands of samples, so the photometric term's weight grows with the noise:
    `w_p * max(1, noise / PHOTOMETRIC_REFERENCE_NOISE)`. bench/fit.py, seed 0, noise 0.03, 16
    frames: median rotation 3.7 deg with w_p 500, 2.3 with 3000 (the factor, 6). Appearances
    without a measured noise (the default, or an older node's) keep `weight`.
    """
    noise = (appearance.value.get("plate_noise") if appearance is not None else None) or 0.0
    return float(weight) * max(1.0, float(noise) / PHOTOMETRIC_REFERENCE_NOISE)


def photometric_frame_weights(appearance: JsonValue | None, frames: Sequence[int]) -> np.ndarray:
    """(F,) factor of the photometric term for each of `frames` (absolute frame numbers): 0 for a
    frame whose plate the appearance's albedo was painted from ('albedo_source' 'painted', its
    'frames'), else 1.

    A painted albedo is that plate divided by the shading, so at the painting pose the render
    reproduces the plate: the term there carries no evidence of its own and only pulls the fit
    back to the first pass's pose and shape, through the photo's fine texture (hair, pores, JPEG
    blocks), whose gradients turn a 1e-4 px change of the landmarks into a different minimum.
    skimage's astronaut (one photo), 1-LSB noise on 0.1% of the pixels, 4 runs: with the term the
    rotation spread 8.4 deg, the weights 0.69, the depth 3.7 cm; without it 0.28 deg, 0.036 and
    0.15 cm. On four one-photo synthetic plates with truth the mean rotation error was the same
    (3.47 deg) with and without it. Frames not painted (a video's other frames) keep the term:
    there the painting is evidence of the skin's colour seen elsewhere.
    """
    value = appearance.value if appearance is not None else {}
    painted = set(value.get("frames") or []) if value.get("albedo_source") == "painted" else set()
    return np.array([0.0 if int(f) in painted else 1.0 for f in frames], np.float64)


LIGHTING_FRAMES = 4
"""Frames fitting the lighting when the albedo is not painted (fit.EstimateAppearance)."""

LIGHT_FIRST_SPREAD = 10.0
"""Degrees of pose spread above which fit.EstimateAppearance keeps the default albedo (albedo 'auto') or
lights before it paints (albedo 'painted')."""

RELATIVE_STEPS = 32
"""Walk steps pooling the albedo's ratio to the default (fit.EstimateAppearance albedo 'relative')."""


IDENTITY_ROUNDS = 6
"""Rounds of fit.EstimateIdentity anchored on a render. The anchors tie the network's points to the
surface, but its contour points slide over the surface as the shape and pose change, so each
round moves only part of the way to the deep energy's minimum: with the true appearance
(30-frame synthetic shot seed 5, 8 frames) the frames' median pitch error was -1.37 deg after 2
rounds, -0.97 after 6 and 12 (prior 100); -1.46, -0.47, -0.37 with prior 30."""

IDENTITY_PRIOR = 30.0
"""lambda_id of fit.EstimateIdentity where its frames see the head from directions spread over more
than `IDENTITY_SPREAD_DEG` (else `IDENTITY_PRIOR_ONE_VIEW`). With 2 rounds a weaker prior than 100
let the unconverged shape drift (pitch worse); with `IDENTITY_ROUNDS` 30 recovers more of the
face's proportions: 30-frame synthetic shots seeds 0-5 with albedo 'auto' and 8 identity frames,
median rotation 0.70/0.94/0.78/0.76/0.63/1.03 deg (prior 100, 2 rounds, painted albedo:
0.98/1.55/1.07/1.14/1.62/2.38). Seed 5 with the true appearance: 0.84 deg at 30 (6 rounds), 1.12
at 10 (12 rounds), 1.52 at 100 (2 rounds); with 2 rounds, 10 and 3 overfit (identity error norm
9.4 and 19.2 against 5.6 at 100)."""

IDENTITY_PRIOR_ONE_VIEW = 100.0
"""lambda_id of fit.EstimateIdentity where its frames see the head from one direction: one view leaves
the shape's depth to the prior. skimage's astronaut (one photo, graphs/fit_video.json): the model's 68
points 0.108 of the eye distance from the network's at 30 (identity norm 22.4), 0.055 at 60, 0.061 at
100 (norm 11.7), 0.070 at 240."""

IDENTITY_SPREAD_DEG = 10.0
"""Spread of the viewing directions (`view_spread_deg`) above which the identity's frames count as
several views (as fit.EstimateAppearance's `light_first`)."""
