"""Camera and CameraRig port types: checks, helpers, JSON form, storage without pickle."""

from __future__ import annotations

import io

import numpy as np
import pytest

from nodegraph.types import Camera, CameraRig, port_type_by_name


def _rotation(rng) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def _camera(rng, name="cam0") -> Camera:
    extrinsics = np.eye(4)
    extrinsics[:3, :3] = _rotation(rng)
    extrinsics[:3, 3] = rng.normal(size=3) * 50
    return Camera(fx=1500.25, fy=1499.5, cx=959.5, cy=539.25, width=1920, height=1080,
                  world_to_camera=extrinsics, k1=-0.12, k2=0.03, name=name)


def _npz_round_trip(value):
    buffer = io.BytesIO()
    np.savez(buffer, **value.to_arrays())
    buffer.seek(0)
    with np.load(buffer, allow_pickle=False) as data:
        return type(value).from_arrays({k: data[k] for k in data.files})


def test_camera_is_static_and_registered():
    assert not Camera.per_frame and not CameraRig.per_frame
    assert port_type_by_name("Camera") is Camera and port_type_by_name("CameraRig") is CameraRig


def test_camera_intrinsic_matrix_and_inverse_extrinsics(rng):
    camera = _camera(rng)
    camera.validate()
    np.testing.assert_array_equal(camera.intrinsic_matrix(),
                                  [[1500.25, 0, 959.5], [0, 1499.5, 539.25], [0, 0, 1]])
    np.testing.assert_allclose(camera.camera_to_world() @ camera.world_to_camera, np.eye(4),
                               atol=1e-12)


def test_camera_from_fov_projects_the_edge_of_the_view_to_the_image_edge():
    camera = Camera.from_fov(640, 480, 90.0, name="wide")
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == pytest.approx((320, 320, 319.5, 239.5))
    np.testing.assert_array_equal(camera.world_to_camera, np.eye(4))
    edge = camera.intrinsic_matrix() @ np.array([1.0, 0.0, 1.0])  # 45 degrees to the right
    assert edge[0] / edge[2] == pytest.approx(319.5 + 320.0)  # right border of pixel 639
    with pytest.raises(ValueError, match=r"fov_deg: expected .*\(0, 180\).*found 180"):
        Camera.from_fov(640, 480, 180.0)


def test_camera_storage_round_trip_is_exact(rng):
    camera = _camera(rng)
    back = _npz_round_trip(camera)
    assert back.fingerprint() == camera.fingerprint()
    assert (back.fx, back.k2, back.width, back.name) == (camera.fx, camera.k2, 1920, "cam0")
    np.testing.assert_array_equal(back.world_to_camera, camera.world_to_camera)
    assert all(a.dtype != object for a in camera.to_arrays().values())


def test_camera_fingerprint_changes_with_any_field(rng):
    camera = _camera(rng)
    base = camera.fingerprint()
    for change in [dict(fx=1500.0), dict(k1=-0.1), dict(width=1919), dict(name="cam1")]:
        assert Camera(**{**camera.__dict__, **change}).fingerprint() != base


def test_camera_json_round_trip_is_exact(rng):
    camera = _camera(rng)
    data = camera.to_json()
    assert data["schema"] == "nodegraph.camera/1" and data["units"] == "cm"
    back = Camera.from_json(data)
    assert back.fingerprint() == camera.fingerprint()


def test_camera_json_units_are_converted_to_cm(rng):
    data = _camera(rng).to_json()
    data["world_to_camera"][0][3] = 12.5
    data["units"] = "mm"
    assert Camera.from_json(data).world_to_camera[0, 3] == pytest.approx(1.25)


@pytest.mark.parametrize("change, message", [
    (dict(fx=0.0), r"'fx' must be > 0"),
    (dict(fy=-3.0), r"'fy' must be > 0"),
    (dict(cx=float("nan")), r"'cx' must be a finite number"),
    (dict(width=0), r"'width' must be a positive integer"),
    (dict(height=10.5), r"'height' must be a positive integer"),
    (dict(name=""), r"'name' must be a non-empty string"),
    (dict(world_to_camera=np.eye(3)), r"'world_to_camera' must have 2 axes|'world_to_camera' must "
                                      r"have size 4"),
    (dict(world_to_camera=np.diag([1.0, 1.0, 1.1, 1.0])), r"orthonormal.*found 2\.10e-01"),
    (dict(world_to_camera=np.diag([1.0, 1.0, -1.0, 1.0])), r"det \+1"),
    (dict(world_to_camera=np.full((4, 4), np.inf)), r"non-finite"),
])
def test_camera_validate_names_the_field(rng, change, message):
    camera = Camera(**{**_camera(rng).__dict__, **change})
    with pytest.raises(ValueError, match=message):
        camera.validate("cam.json")


@pytest.mark.parametrize("edit, message", [
    (lambda d: d.pop("fx"), r"cam\.json: missing key\(s\) \['fx'\]"),
    (lambda d: d.update(focal=3), r"cam\.json: unknown key\(s\) \['focal'\]"),
    (lambda d: d.update(fx="big"), r"cam\.json: 'fx' must be a number, found 'big'"),
    (lambda d: d.update(schema="x/1"), r"'schema' must be 'nodegraph\.camera/1', found 'x/1'"),
    (lambda d: d.update(units="inch"), r"'units' must be one of"),
    (lambda d: d.update(world_to_camera=[[1, 0, 0], [0, 1, 0], [0, 0, 1]]),
     r"'world_to_camera' must be 4x4, found shape \(3, 3\)"),
])
def test_camera_from_json_errors_name_the_key(rng, edit, message):
    data = _camera(rng).to_json()
    edit(data)
    with pytest.raises(ValueError, match=message):
        Camera.from_json(data, "cam.json")


def test_rig_stores_cameras_with_a_leading_axis(rng):
    cameras = [_camera(rng, "left"), _camera(rng, "right"), Camera.from_fov(64, 48, 40, "witness")]
    rig = CameraRig.from_cameras(cameras)
    assert rig.num_cameras == 3 and rig.world_to_camera.shape == (3, 4, 4)
    assert rig.image_size.tolist() == [[1920, 1080], [1920, 1080], [64, 48]]
    back = _npz_round_trip(rig)
    assert back.fingerprint() == rig.fingerprint()
    for original, restored in zip(cameras, back.cameras()):
        assert restored.fingerprint() == original.fingerprint()
    assert back.camera("right").fingerprint() == cameras[1].fingerprint()
    assert CameraRig.from_json(rig.to_json()).fingerprint() == rig.fingerprint()


def test_rig_errors(rng):
    with pytest.raises(ValueError, match=r"camera names must be unique, found \['a'\]"):
        CameraRig.from_cameras([_camera(rng, "a"), _camera(rng, "a")])
    with pytest.raises(ValueError, match="at least one camera"):
        CameraRig.from_cameras([])
    with pytest.raises(ValueError, match=r"camera 1 'b': 'fx' must be > 0"):
        CameraRig.from_cameras([_camera(rng, "a"), Camera(**{**_camera(rng, "b").__dict__,
                                                             "fx": -1.0})])
    rig = CameraRig.from_cameras([_camera(rng, "a")])
    with pytest.raises(KeyError, match=r"unknown camera 'z'; known: \['a'\]"):
        rig.camera("z")


@pytest.mark.parametrize("key", ["fx", "fy"])
def test_a_focal_length_beyond_1000_image_sizes_is_refused(key):
    good = dict(fx=110.0, fy=110.0, cx=40.0, cy=32.0, width=80, height=64)
    Camera(**good | {key: 80_000.0}).validate()  # 1000 x 80 px: a 0.057 deg field of view, still a lens
    with pytest.raises(ValueError, match=rf"'{key}' must be at most 1000 x the image size \(80 px\), found 1e\+20"):
        Camera(**good | {key: 1e20}).validate()
