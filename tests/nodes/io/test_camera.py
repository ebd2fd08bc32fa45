"""Tests of nodes.io.camera: our JSON form, OpenCV YAML/JSON calibrations, rigs, nodes."""

from __future__ import annotations

import ast
import json
import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from nodegraph import Camera, CameraRig, InputError, NodeError, run_node
from nodes.io.camera import (LoadCamera, LoadCameraRig, SaveCamera, SaveCameraRig, load_camera,
                             load_camera_rig, parse_opencv_yaml, save_camera, save_camera_rig)

# As OpenCV's calibration sample writes it (cv::FileStorage, YAML), with a known pose added.
OPENCV_YAML = """%YAML:1.0
---
calibration_time: "Wed 08 Jun 2016 11:11:11 AM"
image_width: 640
image_height: 480
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 6.5746697944293521e+02, 0., 3.1950000000000000e+02, 0.,
       6.5846697944293521e+02, 2.3950000000000000e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -4.1802327176423804e-01, 5.0715244063187526e-01, 0., 0., 0. ]
rvec: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 1.0000000000000001e-01, -2.0000000000000001e-01, 3.0000000000000000e-01 ]
tvec: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 10., -20., 500. ]
avg_reprojection_error: 3.9e-01
"""
K = np.array([[657.46697944293521, 0, 319.5], [0, 658.46697944293521, 239.5], [0, 0, 1]])
RVEC = np.array([0.1, -0.2, 0.3])
T_MM = np.array([10.0, -20.0, 500.0])


def write(path: Path, text: str) -> str:
    path.write_text(text)
    return str(path)


def make_camera(name: str = "cam0", seed: int = 0) -> Camera:
    rng = np.random.default_rng(seed)
    extrinsics = np.eye(4)
    extrinsics[:3, :3] = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    extrinsics[:3, 3] = rng.normal(size=3) * 100
    return Camera(fx=1234.5678901234, fy=1233.1, cx=640.25, cy=359.75, width=1280, height=720,
                  world_to_camera=extrinsics, k1=-0.0123456789, k2=1e-05, name=name)


# -- pure functions --------------------------------------------------------------------------

def test_parse_opencv_yaml_tags_matrices():
    data = parse_opencv_yaml(OPENCV_YAML)
    assert data["camera_matrix"]["type_id"] == "opencv-matrix"
    assert data["image_width"] == 640 and data["flags"] == 0


# -- one camera ------------------------------------------------------------------------------

@pytest.mark.parametrize("ext", ["json", "yaml", "yml"])
def test_round_trip_is_exact(tmp_path, ext):
    camera = make_camera()
    path = tmp_path / f"cam.{ext}"
    save_camera(path, camera)
    back = load_camera(path)
    assert back.fingerprint() == camera.fingerprint()
    np.testing.assert_array_equal(back.world_to_camera, camera.world_to_camera)


def test_json_form_is_documented_one(tmp_path):
    save_camera(tmp_path / "cam.json", make_camera())
    data = json.loads((tmp_path / "cam.json").read_text())
    assert data["schema"] == "nodegraph.camera/1" and data["units"] == "cm"
    assert sorted(data) == sorted(["schema", "name", "width", "height", "fx", "fy", "cx", "cy",
                                   "k1", "k2", "world_to_camera", "units"])


def test_save_in_other_units_loads_back_in_cm(tmp_path):
    camera = make_camera()
    for ext in ("json", "yaml"):
        save_camera(tmp_path / f"mm.{ext}", camera, units="mm")
        back = load_camera(tmp_path / f"mm.{ext}")
        np.testing.assert_allclose(back.world_to_camera, camera.world_to_camera, rtol=1e-15,
                                   atol=1e-12)
    assert "units: mm" in (tmp_path / "mm.yaml").read_text()


def test_opencv_yaml_sample_known_values(tmp_path):
    camera = load_camera(write(tmp_path / "left.yaml", OPENCV_YAML), units="mm")
    assert camera.name == "left" and (camera.width, camera.height) == (640, 480)
    np.testing.assert_array_equal(camera.intrinsic_matrix(), K)
    assert (camera.k1, camera.k2) == (-4.1802327176423804e-01, 5.0715244063187526e-01)
    np.testing.assert_allclose(camera.world_to_camera[:3, :3],
                               Rotation.from_rotvec(RVEC).as_matrix(), atol=1e-15)
    np.testing.assert_array_equal(camera.world_to_camera[:3, 3], T_MM / 10.0)  # mm -> cm
    np.testing.assert_array_equal(camera.world_to_camera[3], [0, 0, 0, 1])
    in_m = load_camera(tmp_path / "left.yaml", units="m")
    np.testing.assert_allclose(in_m.world_to_camera[:3, 3], T_MM * 100.0)


def test_opencv_json_and_ros_yaml_equal_the_yaml(tmp_path):
    reference = load_camera(write(tmp_path / "c.yaml", OPENCV_YAML), units="mm", name="c")

    def matrix(rows, cols, values):
        return {"type_id": "opencv-matrix", "rows": rows, "cols": cols, "dt": "d",
                "data": list(map(float, np.ravel(values)))}

    opencv_json = {"image_width": 640, "image_height": 480, "camera_matrix": matrix(3, 3, K),
                   "distortion_coefficients": matrix(1, 5, [-4.1802327176423804e-01,
                                                            5.0715244063187526e-01, 0, 0, 0]),
                   "R": matrix(3, 3, Rotation.from_rotvec(RVEC).as_matrix()),
                   "T": matrix(3, 1, T_MM), "units": "mm"}
    from_json = load_camera(write(tmp_path / "c.json", json.dumps(opencv_json)))
    np.testing.assert_allclose(from_json.world_to_camera, reference.world_to_camera, atol=1e-14)
    assert from_json.intrinsic_matrix().tolist() == reference.intrinsic_matrix().tolist()
    plain = {"image_size": [640, 480], "K": K.tolist(), "D": [-4.1802327176423804e-01,
                                                              5.0715244063187526e-01],
             "rvec": RVEC.tolist(), "tvec": T_MM.tolist()}
    from_lists = load_camera(write(tmp_path / "c2.json", json.dumps(plain)), units="mm", name="c")
    assert from_lists.fingerprint() == reference.fingerprint()
    ros = """image_width: 640
image_height: 480
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [657.46697944293521, 0, 319.5, 0, 658.46697944293521, 239.5, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.41802327176423804, 0.50715244063187526, 0, 0, 0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
"""
    intrinsics_only = load_camera(write(tmp_path / "ros.yaml", ros))
    assert intrinsics_only.name == "narrow_stereo"
    np.testing.assert_array_equal(intrinsics_only.world_to_camera, np.eye(4))
    assert intrinsics_only.intrinsic_matrix().tolist() == K.tolist()


def test_extra_distortion_is_an_error_unless_ignored(tmp_path):
    text = OPENCV_YAML.replace("5.0715244063187526e-01, 0., 0., 0. ]",
                               "5.0715244063187526e-01, 1e-3, 0., -5.7843597214487474e-01 ]")
    path = write(tmp_path / "k3.yaml", text)
    with pytest.raises(InputError, match=r"file '.*k3\.yaml': 'distortion_coefficients': Camera "
                                         r"models radial k1, k2 only, found p1=0\.001, "
                                         r"k3=-0\.578.*ignore_extra_distortion"):
        load_camera(path, units="mm")
    camera = load_camera(path, units="mm", ignore_extra_distortion=True)
    assert camera.k2 == 5.0715244063187526e-01


@pytest.mark.parametrize("edit, message", [
    (lambda t: t.replace("rows: 3\n   cols: 3\n   dt: d\n   data: [ 6.57",
                         "rows: 3\n   cols: 4\n   dt: d\n   data: [ 0., 6.57").replace(
                             "0., 0., 1. ]", "0., 0., 0., 1., 0. ]"),
     r"file '.*bad\.yaml': 'camera_matrix' must be 3x3, found 3x4"),
    (lambda t: t.replace("   data: [ 10., -20., 500. ]", "   data: [ 10., -20. ]"),
     r"file '.*bad\.yaml': 'tvec' has rows=3, cols=1 \(3 values\), found 2 values"),
    (lambda t: t.replace("image_height: 480\n", ""),
     r"file '.*bad\.yaml': expected both 'image_width' and 'image_height', found only "
     r"'image_width'"),
    (lambda t: t.replace("camera_matrix:", "intrinsics:"),
     r"file '.*bad\.yaml': expected an intrinsic matrix \(one of \['camera_matrix', 'K'"),
    (lambda t: t.replace("distortion_coefficients:", "distortion:"),
     r"file '.*bad\.yaml': expected distortion coefficients"),
    (lambda t: t.replace("tvec:", "tvec_unused:"),
     r"file '.*bad\.yaml': expected a rotation \(R or rvec\) and a translation \(T or tvec\) "
     r"together, found only 'rvec'"),
    (lambda t: t.replace("   dt: d\n   data: [ 10.", "   dt: q\n   data: [ 10."),
     r"'tvec' dt must be an OpenCV type such as 'd' or 'f', found 'q'"),
    (lambda t: t.replace("data: [ 10., -20., 500. ]", "data: [ 10., -20., abc ]"),
     r"file '.*bad\.yaml': 'tvec' must hold numbers, found 'abc'"),
    (lambda t: t.replace("flags: 0", "flags: [0"),
     r"file '.*bad\.yaml': expected OpenCV FileStorage YAML, found a syntax error .*line"),
    (lambda t: t.replace("6.5746697944293521e+02, 0., 3.195", "6.5746697944293521e+02, 2., 3.195"),
     r"'camera_matrix' must have zero skew"),
    (lambda t: t + "distortion_model: equidistant\n",
     r"'distortion_model' must be one of \['plumb_bob', 'radtan', 'rational_polynomial'\]"),
    (lambda t: t + "K: [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n",
     r"expected one of \['camera_matrix', 'K', .*found several: \['camera_matrix', 'K'\]"),
    (lambda t: t.replace("6.5746697944293521e+02, 0., 3.195", "-6.5746697944293521e+02, 0., 3.195"),
     r"file '.*bad\.yaml': 'fx' must be > 0"),
])
def test_error_names_file_and_field(tmp_path, edit, message):
    path = write(tmp_path / "bad.yaml", edit(OPENCV_YAML))
    with pytest.raises(InputError, match=message) as err:
        load_camera(path, units="mm")
    assert err.value.port == "path"


def test_error_non_rigid_rotation_names_r(tmp_path):
    data = {"image_size": [640, 480], "K": K.tolist(), "D": [0, 0, 0, 0, 0],
            "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1.01]], "T": [0, 0, 0], "units": "cm"}
    with pytest.raises(InputError, match=r"file '.*r\.json': 'R' must be orthonormal \(max "
                                         r"\|R R\^T - I\| <= 1e-05\), found 2\.01e-02"):
        load_camera(write(tmp_path / "r.json", json.dumps(data)))


def test_error_units(tmp_path):
    path = write(tmp_path / "c.yaml", OPENCV_YAML)
    with pytest.raises(InputError, match=r"file '.*c\.yaml': an OpenCV calibration states no "
                                         r"length unit.*set units to 'mm', 'cm' or 'm'") as err:
        load_camera(path)
    assert err.value.port == "units"
    save_camera(tmp_path / "ours.json", make_camera())
    with pytest.raises(InputError, match=r"the file states units 'cm', the parameter says 'mm'"):
        load_camera(tmp_path / "ours.json", units="mm")


def test_error_our_json_names_file_and_key(tmp_path):
    data = make_camera().to_json()
    data["fx"] = "wide"
    with pytest.raises(InputError, match=r"file '.*c\.json': 'fx' must be a number, found 'wide'"):
        load_camera(write(tmp_path / "c.json", json.dumps(data)))
    with pytest.raises(InputError, match=r"file '.*x\.json': expected a camera calibration in "
                                         r"JSON, found invalid JSON"):
        load_camera(write(tmp_path / "x.json", "{"))
    with pytest.raises(InputError, match=r"file '.*none\.json': expected a camera calibration, "
                                         r"found it missing"):
        load_camera(tmp_path / "none.json")
    with pytest.raises(InputError, match=r"expected an extension among \['\.json', '\.yaml', "
                                         r"'\.yml'\], found '\.xml'"):
        load_camera(write(tmp_path / "c.xml", "<opencv_storage/>"))


# -- rigs ------------------------------------------------------------------------------------

def test_rig_file_with_inline_and_referenced_cameras(tmp_path):
    (tmp_path / "cams").mkdir()
    write(tmp_path / "cams" / "left.yaml", OPENCV_YAML)
    right = make_camera("right", seed=1)
    rig_path = tmp_path / "rig.json"
    rig_path.write_text(json.dumps({"schema": "nodegraph.camera_rig/1",
                                    "cameras": ["cams/left.yaml", right.to_json()]}))
    rig = load_camera_rig(str(rig_path), units="mm")
    assert rig.names == ["left", "right"]
    assert rig.camera("right").fingerprint() == right.fingerprint()
    node = LoadCameraRig({"path": str(rig_path), "units": "mm"})
    assert node.input_files() == [rig_path, tmp_path / "cams" / "left.yaml"]
    assert run_node(node)["rig"].fingerprint() == rig.fingerprint()
    save_camera_rig(tmp_path / "out.json", rig)
    assert load_camera_rig(str(tmp_path / "out.json")).fingerprint() == rig.fingerprint()


def test_rig_from_camera_files_and_names(tmp_path):
    files = []
    for i in range(3):
        files.append(str(tmp_path / f"c{i}.json"))
        save_camera(files[-1], make_camera("camera", seed=i))
    with pytest.raises(InputError, match=r"camera files .*: CameraRig: camera names must be unique, "
                                         r"found \['camera'\]"):
        load_camera_rig(camera_files=files)
    rig = load_camera_rig(camera_files=files, names=["a", "b", "c"])
    assert rig.names == ["a", "b", "c"]
    assert rig.camera("b").fingerprint() == make_camera("b", seed=1).fingerprint()
    with pytest.raises(InputError, match=r"'names': expected 3 names \(one per camera\), found 2"):
        load_camera_rig(camera_files=files, names=["a", "b"])
    with pytest.raises(InputError, match=r"expected either a rig file \('path'\) or camera files "
                                         r"\('camera_files'\), found both"):
        load_camera_rig(files[0], files)
    node = LoadCameraRig({"camera_files": files, "names": ["a", "b", "c"]})
    assert node.input_files() == [Path(f) for f in files]


def test_rig_errors_name_the_camera(tmp_path):
    bad = make_camera().to_json()
    bad["fy"] = -1.0
    rig_path = write(tmp_path / "rig.json", json.dumps({"schema": "nodegraph.camera_rig/1",
                                                        "cameras": [bad]}))
    with pytest.raises(InputError, match=r"file '.*rig\.json': camera 0: 'fy' must be > 0"):
        load_camera_rig(rig_path)
    with pytest.raises(InputError, match=r"expected one camera, found a camera rig"):
        load_camera(rig_path)
    missing = write(tmp_path / "rig2.json", json.dumps({"schema": "nodegraph.camera_rig/1",
                                                        "cameras": ["gone.yaml"]}))
    with pytest.raises(InputError, match=r"file '.*gone\.yaml': expected a camera calibration, "
                                         r"found it missing"):
        load_camera_rig(missing)


# -- nodes -----------------------------------------------------------------------------------

def test_nodes_load_and_save(tmp_path):
    path = write(tmp_path / "cam.yaml", OPENCV_YAML)
    camera = run_node(LoadCamera, {"path": path, "units": "mm", "name": "A"})["camera"]
    assert camera.name == "A" and camera.width == 640
    files = run_node(SaveCamera, {"path": str(tmp_path / "out" / "a.json")}, camera=camera)["files"]
    assert files.paths == [str(tmp_path / "out" / "a.json")]
    assert load_camera(files.paths[0]).fingerprint() == camera.fingerprint()
    rig = CameraRig.from_cameras([camera])
    written = run_node(SaveCameraRig, {"path": str(tmp_path / "rig.json")}, rig=rig)["files"]
    assert load_camera_rig(written.paths[0]).fingerprint() == rig.fingerprint()
    assert not [n for n in os.listdir(tmp_path / "out") if n.endswith(".tmp")]
    with pytest.raises(NodeError, match=r"states no length unit") as err:
        run_node(LoadCamera, {"path": path})
    assert err.value.bad_input and err.value.port == "units"


# -- start-up --------------------------------------------------------------------------------

HEAVY = {"OpenImageIO", "av", "torch", "scipy", "matplotlib", "cv2", "yaml"}


@pytest.mark.parametrize("module", ["camera", "image", "video"])
def test_module_imports_no_heavy_library_at_top_level(module):
    tree = ast.parse(Path(__file__).parents[3].joinpath("nodes", "io", f"{module}.py").read_text())
    top = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            top |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            top.add(node.module.split(".")[0])
    assert not top & HEAVY, f"nodes/io/{module}.py imports {sorted(top & HEAVY)} at module level"
