"""A fit's result as a `Performance` (`fit.MakePerformance`), and a performance posed on the face
model as a mesh sequence (`fit.PosedMesh`)."""

from __future__ import annotations

import numpy as np

from nodegraph import (FRAMEWISE, FaceModel, ImageSequence, In, InputError, JsonValue, MeshSequence, Node, NodeParams,
                       Out, Param, ParamSequence, Performance)
from nodegraph.flags import flags_to_mask

__all__ = ["posed_vertices", "MakePerformance", "PosedMesh"]


def posed_vertices(model: FaceModel, performance: Performance) -> np.ndarray:
    """(F, V, 3) float32 world vertices, cm: `R_f (neutral + w_f @ deltas) + t_f`.

    The model's shapes are matched to the performance's by name (absent ones are 0); the model
    is taken as it is (its identity already applied: `fit.EstimateIdentity`'s `fitted_model`).

    Raises:
        ValueError: when the performance has a shape the model lacks.
    """
    local = model.evaluate(performance.weights_in(model.expression_names))
    return (np.einsum("fij,fvj->fvi", performance.rotation, local) + performance.translation[:, None]).astype(np.float32)


class MakePerformance(Node):
    """Collect a fitted sequence, its failure flags, the identity and the frame rate into a `Performance`."""

    type_name = "fit.MakePerformance"
    version = 1
    kind = FRAMEWISE

    class Params(NodeParams):
        fps: float = Param(0.0, ge=0, le=10000, description="Frames per second; 0 = the plates' (a video's own "
                           "rate; an image sequence's 30 unless its loader says otherwise).")

    fitted = In(ParamSequence, doc="From fit.Expression or the temporal nodes: r00..r22, tx, ty, tz, weights.")
    failed = In(ParamSequence, optional=True, doc="Flags (fit.FlagFailures' flags or temporal.FlowInfill's "
                "still_failed): its 'failed' column, NaN counting as failed (nodegraph.flags); absent: only frames "
                "with non-finite values failed.")
    identity = In(JsonValue, optional=True, doc="From fit.EstimateIdentity: {'identity': [I weights], ...}.")
    images = In(ImageSequence, optional=True, doc="The plates (for their frame rate).")
    performance = Out(Performance, doc="Pose (model-to-world, cm), weights by the model's shape names, flags.")

    def run(self, fitted: ParamSequence, failed: ParamSequence | None = None, identity: JsonValue | None = None,
            images: ImageSequence | None = None) -> dict[str, Performance]:
        fps = self.params.fps or (images.fps if images is not None else 30.0)
        flags = None if failed is None else flags_to_mask(failed, fitted.num_frames)
        ident = None
        if identity is not None:
            value = identity.value.get("identity") if isinstance(identity.value, dict) else None
            if value is None:
                raise InputError("identity", "expected {'identity': [weights], ...} (fit.EstimateIdentity), found "
                                             f"{type(identity.value).__name__}")
            ident = np.asarray(value, np.float32)
        try:
            return {"performance": Performance.from_params(fitted, failed=flags, identity=ident, fps=float(fps))}
        except ValueError as err:
            raise InputError("fitted", str(err).removeprefix("fitted: ")) from err


class PosedMesh(Node):
    """Pose the face model by a performance: the head's world vertices at every frame."""

    type_name = "fit.PosedMesh"
    version = 1
    kind = FRAMEWISE

    performance = In(Performance, doc="Pose and weights (by the model's shape names).")
    model = In(FaceModel, doc="The face model (as fitted: identity applied).")
    mesh = Out(MeshSequence, doc="(F, V, 3) cm, world frame, with the model's faces, uv and groups.")

    def run(self, performance: Performance, model: FaceModel) -> dict[str, MeshSequence]:
        try:
            vertices = posed_vertices(model, performance)
        except ValueError as err:
            raise InputError("performance", str(err)) from err
        return {"mesh": MeshSequence(vertices, np.asarray(model.faces), groups=dict(model.groups), uv=model.uv,
                                     uv_faces=model.uv_faces,
                                     fps=float(performance.fps))}
