"""The exporters (export.LiveLinkCSV, export.UsdAnimation, export.GltfAnimation) and the fit's
Performance nodes: each file read back by an independent reader (the CSV by io.LoadLiveLinkCSV,
the USD by UsdSkel's own skinning, the glTF by pygltflib and the spec's arithmetic) gives the
posed vertices of FaceModel.evaluate, and passes the format's rules."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import Camera, NodeError, ParamSequence, Performance, run_node
from nodegraph.performance import POSE_COLUMNS
from nodes.export.gltf import GltfAnimation
from nodes.export.livelink import LiveLinkCSV
from nodes.export.usd import UsdAnimation
from nodes.fit.performance import MakePerformance, PosedMesh
from nodes.io.arkit import ANGLE_UNIT_RAD, ARKIT_NAMES, LIVE_LINK_HEADER, OPENCV_TO_ARKIT, head_angles
from nodes.io.face_model import load_face_model
from nodes.io.livelink import LoadLiveLinkCSV, read_live_link_csv

FRAMES = 12
TOL_CM = 1e-4  # the bound; float32 storage of ~100 cm values is good to ~1e-5 cm


@pytest.fixture(scope="module")
def model():
    return load_face_model()


@pytest.fixture(scope="module")
def camera():
    """A camera 80 cm in front of the world origin, looking back at it (not the identity)."""
    from scipy.spatial.transform import Rotation

    e = np.eye(4)
    e[:3, :3] = Rotation.from_euler("xyz", [3.0, 185.0, -2.0], degrees=True).as_matrix()
    e[:3, 3] = [1.0, -2.0, 80.0]
    return Camera(fx=500.0, fy=500.0, cx=128.0, cy=128.0, width=256, height=256, world_to_camera=e, name="cam")


@pytest.fixture(scope="module")
def performance(model):
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(7)
    rot = Rotation.from_rotvec(rng.normal(0, 0.3, (FRAMES, 3))).as_matrix().astype(np.float32)
    trans = rng.normal(0, 4, (FRAMES, 3)).astype(np.float32)
    weights = rng.uniform(0, 1, (FRAMES, len(model.expression_names))).astype(np.float32)
    return Performance(rot, trans, weights, list(model.expression_names), np.zeros(FRAMES, bool),
                       np.zeros(0, np.float32), 24.0)


def _reference(model, performance, camera):
    """(F, V, 3) posed vertices in the file's frame, float64, from FaceModel.evaluate."""
    world = np.einsum("fij,fvj->fvi", performance.rotation.astype(np.float64),
                      model.evaluate(performance.weights).astype(np.float64)) + performance.translation[:, None]
    e = np.asarray(camera.world_to_camera, np.float64)
    return np.einsum("ij,fvj->fvi", OPENCV_TO_ARKIT @ e[:3, :3], world) + OPENCV_TO_ARKIT @ e[:3, 3]


def test_performance_round_trips_the_fitted_param_layout(performance):
    performance.validate()
    params = performance.to_params()
    assert params.names[:12] == list(POSE_COLUMNS)
    back = Performance.from_params(params, fps=24.0)
    np.testing.assert_array_equal(back.rotation, performance.rotation)
    np.testing.assert_array_equal(back.weights, performance.weights)
    bad = params.values.copy()
    bad[3, 5] = np.nan
    flagged = Performance.from_params(ParamSequence(bad, params.names))
    assert flagged.failed.tolist() == [i == 3 for i in range(FRAMES)] and np.isfinite(flagged.rotation).all()
    with pytest.raises(ValueError, match="r00"):
        Performance.from_params(ParamSequence(params.values[:, 3:], params.names[3:]))
    with pytest.raises(ValueError, match="not a rotation"):
        Performance(performance.rotation * 2, performance.translation, performance.weights,
                    performance.expression_names, performance.failed).validate()


def test_make_performance_and_posed_mesh(model, performance):
    flags = ParamSequence(np.eye(FRAMES, 2, dtype=np.float32), ["failed", "energy_ratio"])
    from nodegraph import JsonValue

    out = run_node(MakePerformance, {"fps": 50.0}, fitted=performance.to_params(), failed=flags,
                   identity=JsonValue({"identity": [0.5] * 40}))["performance"]
    assert out.failed.tolist() == [True] + [False] * (FRAMES - 1) and out.fps == 50.0
    assert out.identity.shape == (40,)
    mesh = run_node(PosedMesh, performance=out, model=model)["mesh"]
    world = np.einsum("fij,fvj->fvi", performance.rotation, model.evaluate(performance.weights)) \
        + performance.translation[:, None]
    np.testing.assert_allclose(mesh.vertices, world, atol=TOL_CM)
    wrong = Performance(out.rotation, out.translation, out.weights[:, :1], ["noSuchShape"], out.failed)
    with pytest.raises(NodeError, match="performance.*noSuchShape"):
        run_node(PosedMesh, performance=wrong, model=model)


def test_live_link_csv_round_trip(tmp_path, model, performance, camera):
    path = tmp_path / "take.csv"
    run_node(LiveLinkCSV, {"path": str(path), "start_timecode": "01:00:00:00"}, performance=performance,
             camera=camera)
    lines = path.read_text().splitlines()
    assert lines[0] == ",".join(LIVE_LINK_HEADER) and len(lines) == FRAMES + 1
    assert all(line.split(",")[1] == "61" and len(line.split(",")) == 63 for line in lines[1:])
    assert lines[1].startswith("01:00:00:00.000,") and lines[2].startswith("01:00:00:01.000,")
    take = read_live_link_csv(path)
    assert take.arkit.min() >= 0 and take.arkit.max() <= 1
    later = tmp_path / "later.csv"  # a run of frames 30:42 carries its frames' timecodes
    run_node(LiveLinkCSV, {"path": str(later)}, performance=performance, frames=range(30, 30 + FRAMES))
    assert later.read_text().splitlines()[1].startswith("00:00:01:06.000,")  # 24 fps: frame 30 = 1 s 6 f
    back = run_node(LoadLiveLinkCSV, {"path": str(path), "fps": 24.0}, model=model)["performance"]
    names = model.expression_names
    plain = [i for i, n in enumerate(names) if not n.startswith(("browInnerUp", "cheekPuff"))]
    np.testing.assert_allclose(back.weights[:, plain], performance.weights[:, plain], atol=5.1e-7)
    half = (performance.weights[:, names.index("cheekPuff_L")] + performance.weights[:, names.index("cheekPuff_R")]) / 2
    np.testing.assert_allclose(back.weights[:, names.index("cheekPuff_L")], half, atol=5.1e-7)
    e = np.asarray(camera.world_to_camera)
    expected = head_angles(OPENCV_TO_ARKIT @ e[:3, :3] @ performance.rotation)
    np.testing.assert_allclose(head_angles(back.rotation), expected, atol=2e-6 * ANGLE_UNIT_RAD)


def test_live_link_csv_refuses_a_wrong_extension_before_running():
    with pytest.raises(Exception, match="ending in .csv"):
        LiveLinkCSV.Params(path="take.txt")
    with pytest.raises(Exception, match="timecode"):
        LiveLinkCSV.Params(path="take.csv", start_timecode="noon")


def _usd_posed(path) -> np.ndarray:
    """(F, V, 3) posed points of the stage's skinned mesh, computed by UsdSkel itself."""
    from pxr import Usd, UsdGeom, UsdSkel, Vt

    stage = Usd.Stage.Open(str(path))
    root = UsdSkel.Root(stage.GetDefaultPrim())
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.TraverseInstanceProxies())
    binding = cache.ComputeSkelBindings(root, Usd.TraverseInstanceProxies())[0]
    skel = cache.GetSkelQuery(binding.GetSkeleton())
    target = binding.GetSkinningTargets()[0]
    shapes = UsdSkel.BlendShapeQuery(UsdSkel.BindingAPI(target.GetPrim()))
    indices, offsets = shapes.ComputeBlendShapePointIndices(), shapes.ComputeSubShapePointOffsets()
    out = []
    for t in range(int(stage.GetStartTimeCode()), int(stage.GetEndTimeCode()) + 1):
        time = Usd.TimeCode(t)
        points = Vt.Vec3fArray(UsdGeom.Mesh(target.GetPrim()).GetPointsAttr().Get(time))
        weights = skel.GetAnimQuery().ComputeBlendShapeWeights(time)
        if target.GetBlendShapeMapper():
            weights = target.GetBlendShapeMapper().Remap(weights)
        sub = shapes.ComputeSubShapeWeights(weights)
        shapes.ComputeDeformedPoints(sub[0], sub[1], sub[2], indices, offsets, points)
        target.ComputeSkinnedPoints(skel.ComputeSkinningTransforms(time), points, time)
        out.append(np.array(points, np.float64))
    return np.stack(out)


def _usd_validation_errors(path) -> list[str]:
    """Errors of usd-core's validators (usdchecker's: UsdValidation, or the older ComplianceChecker)."""
    from pxr import Usd

    try:
        from pxr import UsdValidation
    except ImportError:
        from pxr import UsdUtils

        checker = UsdUtils.ComplianceChecker(arkit=False, skipARKitRootLayerCheck=False, rootPackageOnly=False,
                                             skipVariants=False, verbose=False)
        checker.CheckCompliance(str(path))
        return list(checker.GetErrors()) + list(checker.GetFailedChecks())
    registry = UsdValidation.ValidationRegistry()
    names = [m.name for m in registry.GetAllValidatorMetadata()]
    context = UsdValidation.ValidationContext(registry.GetOrLoadValidatorsByName(names))
    return [f"{e.GetName()}: {e.GetMessage()}" for e in context.Validate(Usd.Stage.Open(str(path)))
            if e.GetType() == UsdValidation.ValidationErrorType.Error]


def test_usd_animation_poses_like_the_model_and_validates(tmp_path, model, performance, camera):
    from pxr import Usd, UsdGeom, UsdSkel

    path = tmp_path / "head.usda"
    run_node(UsdAnimation, {"path": str(path)}, performance=performance, model=model, camera=camera)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y and UsdGeom.GetStageMetersPerUnit(stage) == 0.01
    assert stage.GetTimeCodesPerSecond() == 24.0 and stage.GetEndTimeCode() == FRAMES - 1
    assert stage.GetDefaultPrim().IsA(UsdSkel.Root)
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Head/Skeleton/Animation"))
    shapes = list(anim.GetBlendShapesAttr().Get())
    assert shapes[:52] == list(ARKIT_NAMES)
    for name in shapes:  # every shape has offsets (Blender's importer drops an empty one: tongueOut)
        assert len(UsdSkel.BlendShape(stage.GetPrimAtPath(f"/Head/Mesh/{name}")).GetOffsetsAttr().Get()) > 0, name
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Head/Mesh"))
    assert len(mesh.GetNormalsAttr().Get()) == len(model.neutral)
    assert UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st").GetInterpolation() == UsdGeom.Tokens.faceVarying
    jaw = shapes.index("jawOpen")
    np.testing.assert_allclose([anim.GetBlendShapeWeightsAttr().Get(t)[jaw] for t in range(FRAMES)],
                               performance.weights[:, model.expression_names.index("jawOpen")], atol=1e-7)
    got = _usd_posed(path)
    err = np.abs(got - _reference(model, performance, camera)).max()
    assert err < TOL_CM, err
    assert _usd_validation_errors(path) == []


def test_usd_validators_are_not_vacuous(tmp_path):
    """A stage that breaks a rule (a BlendShape on a mesh with no SkelBindingAPI) is reported."""
    from pxr import Usd, UsdGeom, UsdSkel

    path = tmp_path / "bad.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Mesh")
    mesh.GetPrim().CreateRelationship("skel:skeleton").SetTargets(["/Nowhere"])
    UsdSkel.BlendShape.Define(stage, "/Mesh/shape")
    stage.Save()
    try:
        from pxr import UsdValidation  # noqa: F401
    except ImportError:
        pytest.skip("this usd-core has the older ComplianceChecker")
    assert _usd_validation_errors(path)


def _accessor(doc, blob: bytes, index: int) -> np.ndarray:
    """Decode a float32 / uint32 accessor the way the glTF spec defines it (no sparse, tight packing)."""
    acc = doc.accessors[index]
    view = doc.bufferViews[acc.bufferView]
    width = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc.type]
    dtype = {5126: np.float32, 5125: np.uint32}[acc.componentType]
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    return np.frombuffer(blob, dtype, acc.count * width, start).reshape(acc.count, width)


def test_gltf_animation_follows_the_rules_and_poses_like_the_model(tmp_path, model, performance, camera):
    import pygltflib
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    path = tmp_path / "head.glb"
    run_node(GltfAnimation, {"path": str(path)}, performance=performance, model=model, camera=camera)
    assert path.read_bytes()[:4] == b"glTF"
    doc = pygltflib.GLTF2().load(str(path))
    blob = doc.binary_blob()
    assert doc.asset.version == "2.0" and doc.buffers[0].byteLength == len(blob)
    assert all(v.byteOffset % 4 == 0 for v in doc.bufferViews)
    prim = doc.meshes[0].primitives[0]
    names = doc.meshes[0].extras["targetNames"]
    assert names[:52] == list(ARKIT_NAMES) and len(prim.targets) == len(names)
    for index in [prim.attributes.POSITION] + [t["POSITION"] for t in prim.targets]:
        acc = doc.accessors[index]
        values = _accessor(doc, blob, index)
        assert acc.componentType == 5126
        np.testing.assert_allclose(acc.min, values.min(0), rtol=0, atol=0)
        np.testing.assert_allclose(acc.max, values.max(0), rtol=0, atol=0)
    anim = doc.animations[0]
    assert {c.target.path for c in anim.channels} == {"weights", "rotation", "translation"}
    assert all(s.interpolation == "LINEAR" for s in anim.samplers)
    times = _accessor(doc, blob, anim.samplers[0].input)[:, 0]
    np.testing.assert_allclose(times, np.arange(FRAMES) / 24.0, atol=1e-6)
    assert doc.accessors[anim.samplers[0].input].min == [0.0]

    outputs = {c.target.path: _accessor(doc, blob, anim.samplers[c.sampler].output) for c in anim.channels}
    positions = _accessor(doc, blob, prim.attributes.POSITION).astype(np.float64)
    targets = np.stack([_accessor(doc, blob, t["POSITION"]) for t in prim.targets]).astype(np.float64)
    weights = outputs["weights"].reshape(FRAMES, len(names))
    local = positions + np.einsum("fs,svc->fvc", weights, targets)
    rot = Rotation.from_quat(outputs["rotation"].astype(np.float64)).as_matrix()
    posed = (np.einsum("fij,fvj->fvi", rot, local) + outputs["translation"][:, None]) * 100.0  # m -> cm
    reference = _reference(model, performance, camera)
    for f in (0, FRAMES // 2, FRAMES - 1):  # every glTF vertex is one of the model's, posed the same
        dist, _ = cKDTree(reference[f]).query(posed[f])
        assert dist.max() < TOL_CM, dist.max()
        back, _ = cKDTree(posed[f]).query(reference[f])  # and every model vertex is there
        assert back.max() < TOL_CM, back.max()


def test_exporters_skip_an_empty_path_and_refuse_foreign_shapes(tmp_path, model, performance):
    for node in (LiveLinkCSV, UsdAnimation, GltfAnimation):
        inputs = {"performance": performance} if node is LiveLinkCSV else {"performance": performance, "model": model}
        assert run_node(node, {"path": ""}, **inputs)["files"].paths == []
    foreign = Performance(performance.rotation, performance.translation, performance.weights[:, :2], ["a", "b"],
                          performance.failed)
    with pytest.raises(NodeError, match="performance.*lacks"):
        run_node(UsdAnimation, {"path": str(tmp_path / "x.usd")}, performance=foreign, model=model)
    assert not (tmp_path / "x.usd").exists()
