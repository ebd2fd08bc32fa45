"""Write a performance as a USD skeletal animation (`export.UsdAnimation`, usd-core's UsdSkel).

The stage (y up, `metersPerUnit` 0.01: cm, `timeCodesPerSecond` = the shot's fps) holds

    /Head                  SkelRoot (the default prim)
      Skeleton             Skeleton with one joint, `head`: the head's rigid motion
        Animation          SkelAnimation: the joint's translations and rotations and the
                           `blendShapeWeights`, time-sampled at every frame
      Mesh                 Mesh of the fitted head (points, normals, `st` UVs), bound to
        <shape>            the joint (weight 1) and to one BlendShape per ARKit shape

so a DCC shows the head moving and its 52 ARKit shape keys animated. The posed points at time
`f` are `M_f (points + sum_s w_fs offsets_s)`, `M_f` the head joint's transform: the
performance's pose in the file's frame (`nodes.export.scene.head_transforms`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Camera, FaceModel, Param, Performance
from nodegraph.files import atomic_path

from ..geometry.mesh import vertex_normals
from .scene import SceneWriter, SceneWriterParams, blendshapes, head_quaternions, head_transforms

__all__ = ["write_usd_animation", "UsdAnimation", "USD_MODULES"]


USD_MODULES = ("pxr.Gf", "pxr.Sdf", "pxr.Tf", "pxr.Usd", "pxr.UsdGeom", "pxr.UsdSkel", "pxr.Vt")
"""What `write_usd_animation` imports (`Node.import_first` of the USD writer)."""


def write_usd_animation(path: str | Path, model: FaceModel, performance: Performance,
                        camera: Camera | None = None, *, asymmetry: bool = True, first_frame: int = 0) -> None:
    """Write the stage described in the module docstring to `path` (.usd, .usdc or .usda), atomically.

    Args:
        path: destination; the format follows the extension (.usd: binary crate).
        model: the fitted face model (its neutral is the mesh's rest points, cm).
        performance: F frames of pose and weights of `model`'s shapes.
        camera: the head's motion relative to it, y up (see `head_transforms`); None: the world.
        asymmetry: write the asymmetry shapes that make ICT's split shapes exact.
        first_frame: time code of the performance's first frame.
    """
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt

    shapes = blendshapes(performance, model, asymmetry=asymmetry)
    rigid = head_transforms(performance, camera)
    f = len(rigid)
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, 0.01)
    stage.SetTimeCodesPerSecond(float(performance.fps))
    stage.SetFramesPerSecond(float(performance.fps))
    stage.SetStartTimeCode(float(first_frame))
    stage.SetEndTimeCode(float(first_frame + max(f - 1, 0)))

    root = UsdSkel.Root.Define(stage, "/Head")
    stage.SetDefaultPrim(root.GetPrim())
    skeleton = UsdSkel.Skeleton.Define(stage, "/Head/Skeleton")
    skeleton.CreateJointsAttr(Vt.TokenArray(["head"]))
    skeleton.CreateJointNamesAttr(Vt.TokenArray(["head"]))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray([Gf.Matrix4d(1.0)]))

    tokens = [Tf.MakeValidIdentifier(n) for n in shapes.names]
    if len(set(tokens)) != len(tokens):
        tokens = [f"{t}_{i}" for i, t in enumerate(tokens)]
    anim = UsdSkel.Animation.Define(stage, "/Head/Skeleton/Animation")
    anim.CreateJointsAttr(Vt.TokenArray(["head"]))
    anim.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    UsdSkel.BindingAPI.Apply(skeleton.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])
    quats = head_quaternions(rigid)
    translations = anim.CreateTranslationsAttr()
    rotations = anim.CreateRotationsAttr()
    anim.CreateScalesAttr().Set(Vt.Vec3hArray([Gf.Vec3h(1.0, 1.0, 1.0)]))
    weights = anim.CreateBlendShapeWeightsAttr()
    for i in range(f):
        time = Usd.TimeCode(float(first_frame + i))
        translations.Set(Vt.Vec3fArray([Gf.Vec3f(*rigid[i, :3, 3].tolist())]), time)
        w, x, y, z = quats[i].tolist()
        rotations.Set(Vt.QuatfArray([Gf.Quatf(w, x, y, z)]), time)
        weights.Set(Vt.FloatArray(shapes.weights[i].tolist()), time)

    mesh = UsdGeom.Mesh.Define(stage, "/Head/Mesh")
    faces = np.asarray(model.faces, np.int64)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(model.neutral, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), 3, np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(vertex_normals(model.neutral, faces).astype(np.float32)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    lo, hi = model.neutral.min(0), model.neutral.max(0)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*lo.tolist()), Gf.Vec3f(*hi.tolist())]))
    if model.uv is not None and model.uv_faces is not None and len(model.uv_faces) == len(faces):
        st = UsdGeom.PrimvarsAPI(mesh).CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray,
                                                     UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(model.uv, np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(np.asarray(model.uv_faces, np.int32).reshape(-1)))
    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    binding.CreateJointIndicesPrimvar(constant=True, elementSize=1).Set(Vt.IntArray([0]))
    binding.CreateJointWeightsPrimvar(constant=True, elementSize=1).Set(Vt.FloatArray([1.0]))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))
    binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    targets = []
    for token, offsets in zip(tokens, shapes.offsets):
        shape = UsdSkel.BlendShape.Define(stage, mesh.GetPath().AppendChild(token))
        moved = np.flatnonzero(np.any(offsets != 0, axis=1)).astype(np.int32)
        if not moved.size:  # a shape the model lacks (tongueOut): one zero offset, so importers keep it
            moved = np.zeros(1, np.int32)
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(offsets[moved])))
        shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(moved))
        targets.append(shape.GetPath())
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)

    with atomic_path(path) as tmp:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"USD could not write '{path}'")


class UsdAnimation(SceneWriter):
    """Write the fitted head as a USD skeletal animation: mesh, 52 ARKit blendshapes, head motion."""

    type_name = "export.UsdAnimation"
    version = 1

    class Params(SceneWriterParams):
        suffixes = (".usd", ".usdc", ".usda")
        path: str = Param(..., output_file=True, description="Destination .usd / .usdc (binary) or .usda "
                          "(text, about 3x larger); '' = write nothing.")

    def import_first(self) -> tuple[str, ...]:
        return USD_MODULES if self.params.path else ()

    def write(self, path: Path, model: FaceModel, performance: Performance, camera: Camera | None) -> None:
        write_usd_animation(path, model, performance, camera, asymmetry=self.params.asymmetry_shapes,
                            first_frame=self.frames.start)
