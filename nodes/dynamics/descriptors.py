"""Feature nodes: skull and skin descriptors, surface stretch, the moving-average target.

Thin wrappers over `features.py`; the training and applying nodes compute the same features
internally (from their model's settings), these expose them for inspection and other graphs.
Vector features are `ParamSequence` columns: skull `b{j}_{k}_{xyz}`, skin `x{i}_{k}_{xyz}`,
stretch `s{i}_{u|v}` (j landmark, i sample, k window sample).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from nodegraph import (FRAMEWISE, In, InputError, MeshSequence, Node, NodeParams, Out, Param,
                       ParamSequence, RigidSequence, windowed)

from .features import (dynamic_offsets, moving_average_target, select_samples, skin_descriptor,
                       skull_descriptor, skull_landmarks, stretch_stencil, surface_stretch,
                       window_reach)
from .removal import HALO, _fps, region_vertices

__all__ = ["SkullDescriptor", "SkinDescriptor", "SurfaceStretch", "QuasistaticTarget"]

_XYZ = ("x", "y", "z")


def _check_reach(window: int, fps: float, feature_fps: float) -> None:
    if window_reach(window, fps, feature_fps) > HALO:
        raise InputError("fps", f"expected window * fps / feature_fps <= {HALO - 3} frames, found "
                                f"{window} * {fps:g} / {feature_fps:g}")


class _WindowParams(NodeParams):
    window: int = Param(10, ge=1, description="half-size of the window (samples)")
    feature_fps: float = Param(0.0, ge=0, description="sample rate of the window (1/s); 0 = fps")
    fps: float = Param(0.0, ge=0, description="capture frame rate (1/s); 0 = the mesh's fps")


class SkullDescriptor(Node):
    """The head motion history B(t): windowed canonical velocities of 5 skull landmarks."""

    type_name = "dynamics.SkullDescriptor"
    version = 1
    kind = windowed(HALO)
    Params = _WindowParams

    skull = In(RigidSequence, doc="skull-to-world transforms")
    rest = In(MeshSequence, per_frame=False, doc="skull-frame rest shape (1 frame): places the landmarks")
    descriptor = Out(ParamSequence, doc="(F, 5 * K * 3) cm/s")

    def run(self, skull: RigidSequence, rest: MeshSequence) -> dict:
        p = self.params
        fps = _fps(p.fps, rest)
        ffps = p.feature_fps or fps
        _check_reach(p.window, fps, ffps)
        if skull.num_frames < 2:
            raise InputError("skull", f"expected at least 2 frames, found {skull.num_frames}")
        b = skull_descriptor(skull.matrices, skull_landmarks(rest.vertices[0]), fps, window=p.window,
                             feature_fps=ffps)
        names = [f"b{j}_{k}_{c}" for j in range(5) for k in range(-p.window, p.window + 1) for c in _XYZ]
        return {"descriptor": ParamSequence(b, names)}


class SkinDescriptor(Node):
    """Skin motion histories X_i(t): windowed stabilized velocities of farthest-point samples."""

    type_name = "dynamics.SkinDescriptor"
    version = 1
    kind = windowed(HALO)

    class Params(_WindowParams):
        num_samples: int = Param(344, ge=1, description="samples (farthest-point sampling of the region)")
        region: str = Param("", description="vertex group of the samples ('' = all)")

    capture = In(MeshSequence, doc="world-space capture (cm)")
    skull = In(RigidSequence, doc="skull-to-world transforms")
    rest = In(MeshSequence, per_frame=False, doc="skull-frame rest shape (1 frame): picks the samples")
    descriptor = Out(ParamSequence, doc="(F, N * K * 3) cm/s")

    def run(self, capture: MeshSequence, skull: RigidSequence, rest: MeshSequence) -> dict:
        p = self.params
        fps = _fps(p.fps, capture)
        ffps = p.feature_fps or fps
        _check_reach(p.window, fps, ffps)
        if capture.num_frames < 2:
            raise InputError("capture", f"expected at least 2 frames, found {capture.num_frames}")
        ids = select_samples(rest.vertices[0], p.num_samples, region_vertices(capture, p.region))
        x = skin_descriptor(capture.vertices[:, ids], skull.matrices, fps, window=p.window, feature_fps=ffps)
        names = [f"x{i}_{k}_{c}" for i in range(len(ids)) for k in range(-p.window, p.window + 1) for c in _XYZ]
        return {"descriptor": ParamSequence(x.reshape(len(x), -1), names)}


class SurfaceStretch(Node):
    """Surface stretch S(t) along u and v of each sample against the neutral (eq. 8)."""

    type_name = "dynamics.SurfaceStretch"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        num_samples: int = Param(344, ge=1, description="samples (farthest-point sampling of the region)")
        region: str = Param("", description="vertex group of the samples ('' = all)")
        spacing_cm: float = Param(0.2, gt=0, description="preferred stencil spacing (cm)")

    mesh = In(MeshSequence, doc="performance (any rigid frame; cm)")
    neutral = In(MeshSequence, per_frame=False, doc="neutral shape (1 frame)")
    stretch = Out(ParamSequence, doc="(F, 2 N) relative length change along u, v")

    def run(self, mesh: MeshSequence, neutral: MeshSequence) -> dict:
        p = self.params
        rest = neutral.vertices[0]
        ids = select_samples(rest, p.num_samples, region_vertices(mesh, p.region))
        s = surface_stretch(mesh.vertices, rest, stretch_stencil(rest, ids, spacing_cm=p.spacing_cm))
        names = [f"s{i}_{a}" for i in range(len(ids)) for a in ("u", "v")]
        return {"stretch": ParamSequence(s.reshape(len(s), -1), names)}


class QuasistaticTarget(Node):
    """The paper's quasistatic target (eq. 5, moving average of stabilized positions) and offsets."""

    type_name = "dynamics.QuasistaticTarget"
    version = 1
    kind = windowed(10)

    class Params(NodeParams):
        window: int = Param(10, ge=1, le=10, description="half-size of the average (frames, <= halo)")

    capture = In(MeshSequence, doc="world-space capture (cm)")
    skull = In(RigidSequence, doc="skull-to-world transforms")
    quasistatic = Out(MeshSequence, doc="world-space moving-average target y(t) (cm)")
    offsets = Out(MeshSequence, doc="dynamic offsets T^-1 (x - y), skull frame (cm)")

    def run(self, capture: MeshSequence, skull: RigidSequence) -> dict:
        y = moving_average_target(capture.vertices, skull.matrices, window=self.params.window)
        dx = dynamic_offsets(capture.vertices, y, skull.matrices)
        return {"quasistatic": dataclasses.replace(capture, vertices=y.astype(np.float32)),
                "offsets": dataclasses.replace(capture, vertices=dx.astype(np.float32))}
