"""The linear face model port type: neutral + identity deltas + expression deltas."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .ports import PortType, check_array, check_index_groups, fail

__all__ = ["FaceModel"]


@dataclass(eq=False)
class FaceModel(PortType):
    """A linear face model: neutral + identity deltas + expression deltas.

    Attributes:
        neutral: (V, 3) float32, cm.
        faces: (T, 3) int.
        expression_deltas: (K, V, 3) float32, cm per unit weight.
        expression_names: K names (ARKit names for the ICT model).
        identity_deltas: (I, V, 3) float32, cm per unit weight (weights ~ N(0, 1)).
        groups: named vertex groups, name -> (N,) int vertex indices (e.g. "face",
            "rigid", "fitting").
        landmarks: (68,) int vertex index of each Multi-PIE 68-point landmark.
        uv, uv_faces: texture coordinates as in `MeshSequence`, or None.
    """

    neutral: np.ndarray
    faces: np.ndarray
    expression_deltas: np.ndarray
    expression_names: list[str]
    identity_deltas: np.ndarray
    groups: dict[str, np.ndarray] = field(default_factory=dict)
    landmarks: np.ndarray = field(default_factory=lambda: np.zeros((0,), np.int32))
    uv: np.ndarray | None = None
    uv_faces: np.ndarray | None = None

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "neutral", self.neutral, 2, (3,))
        v = self.neutral.shape[0]
        check_array(where, "expression_deltas", self.expression_deltas, 3, (v, 3))
        check_array(where, "identity_deltas", self.identity_deltas, 3, (v, 3))
        if len(self.expression_names) != self.expression_deltas.shape[0]:
            fail(where, f"{len(self.expression_names)} expression names for "
                        f"{self.expression_deltas.shape[0]} shapes")
        check_index_groups(where, self.groups, v)

    def evaluate(self, expression: Any, identity: Any = None) -> Any:
        """Return vertices `neutral + identity @ identity_deltas + expression @ expression_deltas`.

        Works on numpy arrays or, differentiably, on torch tensors (the deltas are moved to
        the tensor's device and dtype).

        Args:
            expression: (F, K) weights, or (K,).
            identity: (I,) weights, or (F, I), or None for the generic neutral.
        Returns:
            (F, V, 3) vertices in cm (or (V, 3) for a 1-D `expression`), same library as
            `expression`.
        """
        k, v = self.expression_deltas.shape[:2]
        if type(expression).__module__.startswith("torch"):
            import torch

            dev, dt = expression.device, expression.dtype
            exp_d = torch.as_tensor(self.expression_deltas, device=dev, dtype=dt).reshape(k, -1)
            out = torch.as_tensor(self.neutral, device=dev, dtype=dt).reshape(-1) + expression @ exp_d
            if identity is not None:
                n = self.identity_deltas.shape[0]
                id_d = torch.as_tensor(self.identity_deltas, device=dev, dtype=dt).reshape(n, -1)
                out = out + identity.to(dev, dt) @ id_d
            return out.reshape(*out.shape[:-1], v, 3)
        expression = np.asarray(expression, dtype=np.float32)
        out = self.neutral.reshape(-1) + expression @ self.expression_deltas.reshape(k, -1)
        if identity is not None:
            n = self.identity_deltas.shape[0]
            out = out + np.asarray(identity, np.float32) @ self.identity_deltas.reshape(n, -1)
        return out.reshape(*out.shape[:-1], v, 3).astype(np.float32)
