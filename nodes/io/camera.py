"""Camera calibration files: our JSON form and OpenCV-style YAML/JSON, read and written.

Accepted for one camera (`load_camera`, `io.LoadCamera`):

- **our JSON** (`.json` with `"schema": "nodegraph.camera/1"`, see `nodegraph.Camera`);
- **OpenCV FileStorage YAML** (`.yaml` / `.yml`, `%YAML:1.0` header, matrices as
  `!!opencv-matrix` with `rows`, `cols`, `dt`, `data`), ROS `camera_info` YAML (matrices as
  plain `{rows, cols, data}`), and the **equivalent JSON** (`.json` without our schema:
  matrices as `{"type_id": "opencv-matrix", "rows", "cols", "dt", "data"}`, nested lists or
  flat lists). Keys, each with its accepted spellings (two spellings of one key are an error):

  ==============  =====================================================================
  intrinsics      `camera_matrix`, `K`, `cameraMatrix`, `intrinsic_matrix`: 3x3, no skew
  distortion      `distortion_coefficients`, `D`, `dist_coeffs`, `distCoeffs`, `dist`:
                  OpenCV order (k1, k2[, p1, p2[, k3[, k4, k5, k6[, s1..s4[, tx, ty]]]]]),
                  2, 4, 5, 8, 12 or 14 values (or none: no distortion)
  rotation        `R` / `rotation_matrix` (3x3) or `rvec` / `rotation_vector` (3, Rodrigues)
  translation     `T` / `tvec` / `translation_vector` / `t` (3)
  image size      `image_width` + `image_height`, `width` + `height`, or `image_size` /
                  `imageSize` ([width, height])
  name            `camera_name` or `name` (else the file name without extension)
  units           `units` ("mm", "cm" or "m"), the unit of the translation (optional)
  model           `distortion_model` (optional): plumb_bob, radtan, rational_polynomial
  ==============  =====================================================================

  R and T are world-to-camera as OpenCV's `calibrateCamera` / `solvePnP` return them
  (`x_cam = R x_world + T`). A file with neither R nor T (an intrinsics-only calibration)
  places the camera at the world origin; one without a distortion key is an error. Other
  keys (calibration time, reprojection error, per-view extrinsics, ...) are ignored.
  `Camera` models k1 and k2 only: non-zero p1, p2, k3, ... are an error unless
  `ignore_extra_distortion` is set, and then they are dropped. OpenCV files carry no
  length unit: the translation's unit comes from a `units` key or the `units` argument
  (a file without one and `units="from_file"` is an error). YAML is parsed with PyYAML (a
  dask dependency) after the `%YAML:1.0` line, which PyYAML does not accept, is removed.

Rigs (`load_camera_rig`, `io.LoadCameraRig`): a rig JSON (`"schema":
"nodegraph.camera_rig/1"`, see `nodegraph.CameraRig`) whose `cameras` entries are cameras
in our JSON form or paths of camera files (relative to the rig file's folder), or a list of
camera files, one camera each.

Written (`save_camera`, `io.SaveCamera`, `io.SaveCameraRig`): `.json` in our form (cm), or
for a camera `.yaml` / `.yml` as OpenCV FileStorage YAML (`camera_name`, `image_width`,
`image_height`, `camera_matrix`, `distortion_coefficients` (k1, k2, 0, 0, 0), `R`, `T`,
`units`), which `cv2.FileStorage` and this module read back. Numbers are written with
Python's shortest round-trip repr, so values load back exactly. Writes are atomic.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path
from typing import Any, Literal, Sequence

import numpy as np

from nodegraph import SEQUENCE, Files, In, InputError, Node, NodeParams, Out, Param
from nodegraph.types import CAMERA_RIG_SCHEMA, CAMERA_SCHEMA, CM_PER_UNIT, Camera, CameraRig

from ..geometry.rotation import axis_angle_to_rotmat
from ._files import atomic_path, files_value, format_of

__all__ = [
    "CAMERA_FORMATS", "parse_opencv_yaml", "camera_from_opencv",
    "camera_to_opencv_yaml", "load_camera", "save_camera", "load_camera_rig", "save_camera_rig",
    "rig_input_files", "LoadCamera", "SaveCamera", "LoadCameraRig", "SaveCameraRig",
]

CAMERA_FORMATS = {".json": "json", ".yaml": "yaml", ".yml": "yaml"}
"""Extension -> format of camera and rig files."""

Units = Literal["from_file", "mm", "cm", "m"]

_ALIASES: dict[str, tuple[str, ...]] = {
    "K": ("camera_matrix", "K", "cameraMatrix", "intrinsic_matrix"),
    "D": ("distortion_coefficients", "D", "dist_coeffs", "distCoeffs", "dist"),
    "R": ("R", "rotation_matrix"),
    "rvec": ("rvec", "rotation_vector"),
    "T": ("T", "tvec", "translation_vector", "t"),
    "name": ("camera_name", "name"),
}
_DISTORTION_COUNTS = (0, 2, 4, 5, 8, 12, 14)
_DISTORTION_MODELS = ("plumb_bob", "radtan", "rational_polynomial")
_OPENCV_DT = {"u": np.uint8, "c": np.int8, "w": np.uint16, "s": np.int16, "i": np.int32,
              "f": np.float32, "d": np.float64, "h": np.float16}


# -- pure functions -------------------------------------------------------------------------

def _where(path: str) -> str:
    return f"file '{path}'"


def parse_opencv_yaml(text: str, path: str = "<text>") -> dict[str, Any]:
    """Parse OpenCV FileStorage YAML into plain Python values.

    `!!opencv-matrix` (and other `!!opencv-*`) nodes become dicts with their keys plus
    `"type_id": "opencv-matrix"`, as OpenCV's JSON form spells them.

    Args:
        text: the file's text (a `%YAML:1.0` / `%YAML 1.x` first line is allowed).
        path: file name for error messages.
    Raises:
        InputError: (param "path") on a YAML syntax error (with line and column) or a
            document that is not a mapping.
    """
    import yaml

    class _Loader(yaml.SafeLoader):
        pass

    def opencv_node(loader: yaml.SafeLoader, suffix: str, node: yaml.Node) -> dict[str, Any]:
        if not isinstance(node, yaml.MappingNode):
            raise yaml.constructor.ConstructorError(None, None, f"expected a mapping under "
                                                    f"!!opencv-{suffix}", node.start_mark)
        value = loader.construct_mapping(node, deep=True)
        value["type_id"] = f"opencv-{suffix}"
        return value

    _Loader.add_multi_constructor("tag:yaml.org,2002:opencv-", opencv_node)
    lines = text.splitlines()
    if lines and lines[0].lstrip().startswith("%YAML"):
        lines[0] = ""  # OpenCV writes "%YAML:1.0", which is not YAML syntax; line numbers kept
    try:
        data = yaml.load("\n".join(lines), Loader=_Loader)  # noqa: S506 (a SafeLoader subclass)
    except yaml.YAMLError as err:
        raise InputError("path", f"{_where(path)}: expected OpenCV FileStorage YAML, found a "
                                 f"syntax error ({' '.join(str(err).split())})") from err
    if not isinstance(data, dict):
        raise InputError("path", f"{_where(path)}: expected a YAML mapping of calibration keys, "
                                 f"found {type(data).__name__}")
    return data


def _number_list(values: Any, path: str, key: str) -> np.ndarray:
    """Flat float64 array of a list of numbers (numeric strings such as '1e-05' accepted)."""
    if not isinstance(values, list):
        raise InputError("path", f"{_where(path)}: '{key}' data must be a list of numbers, found "
                                 f"{str(values)[:60]}")
    out = []
    for item in values:
        if isinstance(item, list):
            out.extend(_number_list(item, path, key).tolist())
            continue
        if isinstance(item, bool):
            raise InputError("path", f"{_where(path)}: '{key}' must hold numbers, found {item!r}")
        try:
            out.append(float(item))
        except (TypeError, ValueError):
            raise InputError("path", f"{_where(path)}: '{key}' must hold numbers, found "
                                     f"{item!r}") from None
    return np.asarray(out, np.float64)


def _opencv_matrix(value: Any, path: str, key: str) -> np.ndarray:
    """A matrix in any accepted spelling -> float64 array (rows, cols), or flat (N,) for a flat list."""
    if isinstance(value, dict):
        missing = [k for k in ("rows", "cols", "data") if k not in value]
        if missing:
            raise InputError("path", f"{_where(path)}: '{key}' must be a matrix with rows, cols "
                                     f"and data, found keys {sorted(value)}")
        rows, cols = value["rows"], value["cols"]
        if not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in (rows, cols)):
            raise InputError("path", f"{_where(path)}: '{key}' rows and cols must be integers >= 0, "
                                     f"found rows={rows!r}, cols={cols!r}")
        dt = str(value.get("dt", "d"))
        match = re.fullmatch(r"(\d*)([ucwsifdh])", dt)
        if match is None:
            raise InputError("path", f"{_where(path)}: '{key}' dt must be an OpenCV type such as "
                                     f"'d' or 'f', found '{dt}'")
        channels = int(match.group(1) or 1)
        data = _number_list(value["data"], path, key)
        if data.size != rows * cols * channels:
            raise InputError("path", f"{_where(path)}: '{key}' has rows={rows}, cols={cols}"
                                     f"{f', {channels} channels' if channels > 1 else ''} "
                                     f"({rows * cols * channels} values), found {data.size} values")
        return data.reshape(rows, cols * channels)
    if isinstance(value, list):
        if value and all(isinstance(row, list) for row in value):
            lengths = {len(row) for row in value}
            if len(lengths) != 1:
                raise InputError("path", f"{_where(path)}: '{key}' rows must have equal lengths, "
                                         f"found lengths {sorted(lengths)}")
            return _number_list(value, path, key).reshape(len(value), lengths.pop())
        return _number_list(value, path, key)
    raise InputError("path", f"{_where(path)}: '{key}' must be a matrix ({{rows, cols, data}} or a "
                             f"list), found {type(value).__name__} {str(value)[:40]}")


def _shape_text(array: np.ndarray) -> str:
    return "x".join(map(str, array.shape)) if array.ndim == 2 else f"{array.size} values"


def _matrix_3x3(array: np.ndarray, path: str, key: str) -> np.ndarray:
    if array.ndim == 1 and array.size == 9:
        array = array.reshape(3, 3)
    if array.shape != (3, 3):
        raise InputError("path", f"{_where(path)}: '{key}' must be 3x3, found {_shape_text(array)}")
    return array


def _vector(array: np.ndarray, path: str, key: str, size: int) -> np.ndarray:
    if array.ndim == 2 and 1 not in array.shape and array.size:
        raise InputError("path", f"{_where(path)}: '{key}' must be a vector of {size} values "
                                 f"(1xN or Nx1), found {_shape_text(array)}")
    flat = array.reshape(-1)
    if size >= 0 and flat.size != size:
        raise InputError("path", f"{_where(path)}: '{key}' must have {size} values, found "
                                 f"{flat.size}")
    return flat


def _pick(data: dict[str, Any], what: str, path: str) -> tuple[str, Any] | None:
    """(spelling, value) of key `what` in `data`, None when absent; two spellings are an error."""
    found = [k for k in _ALIASES[what] if k in data]
    if len(found) > 1:
        raise InputError("path", f"{_where(path)}: expected one of {list(_ALIASES[what])}, found "
                                 f"several: {found}")
    return (found[0], data[found[0]]) if found else None


def _image_size(data: dict[str, Any], path: str) -> tuple[int, int]:
    for wkey, hkey in (("image_width", "image_height"), ("width", "height")):
        if wkey in data or hkey in data:
            if wkey not in data or hkey not in data:
                raise InputError("path", f"{_where(path)}: expected both '{wkey}' and '{hkey}', "
                                         f"found only '{wkey if wkey in data else hkey}'")
            size = [data[wkey], data[hkey]]
            break
    else:
        key = next((k for k in ("image_size", "imageSize") if k in data), None)
        if key is None:
            raise InputError("path", f"{_where(path)}: expected the image size ('image_width' and "
                                     "'image_height', or 'image_size' [width, height]), found none")
        value = data[key]
        if isinstance(value, dict):
            value = _opencv_matrix(value, path, key).reshape(-1).tolist()
        if not isinstance(value, list) or len(value) != 2:
            raise InputError("path", f"{_where(path)}: '{key}' must be [width, height], found "
                                     f"{str(value)[:40]}")
        size = value
    out = []
    for name, value in zip(("width", "height"), size):
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if not isinstance(value, int) or isinstance(value, bool) or value <= 0:
            raise InputError("path", f"{_where(path)}: image {name} must be a positive integer "
                                     f"(pixels), found {value!r}")
        out.append(value)
    return out[0], out[1]


def _translation_cm(data: dict[str, Any], units: str, path: str) -> float:
    """Centimetres per unit of the file's translation, from its `units` key and/or `units`."""
    stated = data.get("units")
    if stated is not None and stated not in CM_PER_UNIT:
        raise InputError("path", f"{_where(path)}: 'units' must be one of {sorted(CM_PER_UNIT)}, "
                                 f"found {stated!r}")
    if units == "from_file":
        if stated is None:
            raise InputError("units", f"{_where(path)}: an OpenCV calibration states no length "
                                      "unit for its translation; set units to 'mm', 'cm' or 'm' "
                                      "(or add a 'units' key to the file)")
        return CM_PER_UNIT[stated]
    if units not in CM_PER_UNIT:
        raise InputError("units", f"expected one of 'from_file', 'mm', 'cm', 'm', found {units!r}")
    if stated is not None and stated != units:
        raise InputError("units", f"{_where(path)}: the file states units '{stated}', the "
                                  f"parameter says '{units}'")
    return CM_PER_UNIT[units]


def camera_from_opencv(data: dict[str, Any], path: str = "<data>", *, name: str = "",
                       units: str = "from_file", ignore_extra_distortion: bool = False) -> Camera:
    """Build a `Camera` from a parsed OpenCV-style calibration (YAML or JSON, see the module).

    Args:
        data: the parsed top-level mapping.
        path: file name for error messages (its stem names a camera that has no name key).
        name: camera name; "" = the file's `camera_name` / `name`, else the file stem.
        units: unit of the translation: "mm", "cm", "m", or "from_file" (its `units` key).
        ignore_extra_distortion: drop non-zero p1, p2, k3, ... instead of raising.
    Returns:
        the validated Camera, translation in cm.
    Raises:
        InputError: naming file and key: missing or ambiguous key, wrong shape, skew, an
            unsupported distortion model or coefficients, a non-rigid R, a missing unit.
    """
    where = _where(path)
    picked = _pick(data, "K", path)
    if picked is None:
        raise InputError("path", f"{where}: expected an intrinsic matrix (one of "
                                 f"{list(_ALIASES['K'])}), found keys {sorted(data)}")
    key, value = picked
    k = _matrix_3x3(_opencv_matrix(value, path, key), path, key)
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    if abs(k[0, 1]) > 1e-9 * max(abs(fx), 1.0):
        raise InputError("path", f"{where}: '{key}' must have zero skew (K[0][1]), found "
                                 f"{float(k[0, 1])!r}; Camera does not model skew")
    if np.abs(k[2] - np.array([0.0, 0.0, 1.0])).max() > 1e-12 or abs(k[1, 0]) > 1e-12:
        raise InputError("path", f"{where}: '{key}' must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], "
                                 f"found {k.tolist()}")

    model = data.get("distortion_model")
    if model is not None and model not in _DISTORTION_MODELS:
        raise InputError("path", f"{where}: 'distortion_model' must be one of "
                                 f"{list(_DISTORTION_MODELS)} (the pinhole model with radial "
                                 f"distortion), found {model!r}")
    picked = _pick(data, "D", path)
    if picked is None:
        raise InputError("path", f"{where}: expected distortion coefficients (one of "
                                 f"{list(_ALIASES['D'])}; write [0, 0, 0, 0, 0] for none), found "
                                 f"keys {sorted(data)}")
    key, value = picked
    coeffs = _vector(_opencv_matrix(value, path, key), path, key, -1)
    if coeffs.size not in _DISTORTION_COUNTS:
        raise InputError("path", f"{where}: '{key}' must have one of {list(_DISTORTION_COUNTS[1:])} "
                                 f"coefficients (OpenCV order k1, k2, p1, p2, k3, ...), found "
                                 f"{coeffs.size}")
    coeffs = np.concatenate([coeffs, np.zeros(2)])[: max(coeffs.size, 2)]
    extra = np.flatnonzero(coeffs[2:])
    if extra.size and not ignore_extra_distortion:
        labels = ["p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tx", "ty"]
        found = ", ".join(f"{labels[i]}={float(coeffs[2 + i])!r}" for i in extra)
        raise InputError("path", f"{where}: '{key}': Camera models radial k1, k2 only, found "
                                 f"{found}; recalibrate with those fixed to 0 or set "
                                 "ignore_extra_distortion to drop them")

    rot_key, rot = _pick(data, "R", path) or (None, None)
    rvec_key, rvec = _pick(data, "rvec", path) or (None, None)
    trans_key, trans = _pick(data, "T", path) or (None, None)
    extrinsics = np.eye(4)
    if rot_key and rvec_key:
        raise InputError("path", f"{where}: expected the rotation as '{rot_key}' or '{rvec_key}', "
                                 "found both")
    has_rot = rot_key is not None or rvec_key is not None
    if has_rot != (trans_key is not None):
        given = rot_key or rvec_key or trans_key
        raise InputError("path", f"{where}: expected a rotation (R or rvec) and a translation "
                                 f"(T or tvec) together, found only '{given}'")
    if has_rot:
        if rot_key:
            rotation = _matrix_3x3(_opencv_matrix(rot, path, rot_key), path, rot_key)
        else:
            rotation = axis_angle_to_rotmat(_vector(_opencv_matrix(rvec, path, rvec_key), path,
                                                    rvec_key, 3))  # OpenCV's Rodrigues vector
        extrinsics[:3, :3] = rotation
        extrinsics[:3, 3] = _vector(_opencv_matrix(trans, path, trans_key), path, trans_key, 3) \
            * _translation_cm(data, units, path)
    elif units != "from_file":
        _translation_cm(data, units, path)  # still refuses a contradicting 'units' key

    if not name:
        picked = _pick(data, "name", path)
        name = str(picked[1]) if picked else Path(path).stem
    width, height = _image_size(data, path)
    camera = Camera(fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), width=width,
                    height=height, world_to_camera=extrinsics, k1=float(coeffs[0]),
                    k2=float(coeffs[1]), name=name)
    try:
        camera.validate(where)
    except ValueError as err:
        message = str(err)
        if rot_key:
            message = message.replace("'world_to_camera' rotation block", f"'{rot_key}'")
        raise InputError("path", message) from err
    return camera


def _yaml_matrix(name: str, rows: int, cols: int, values: Sequence[float]) -> str:
    data = ", ".join(repr(float(v)) for v in values)
    return (f"{name}: !!opencv-matrix\n   rows: {rows}\n   cols: {cols}\n   dt: d\n"
            f"   data: [ {data} ]\n")


def camera_to_opencv_yaml(camera: Camera, units: str = "cm") -> str:
    """Return `camera` as OpenCV FileStorage YAML text (see the module docstring).

    Args:
        camera: the camera.
        units: unit of the written translation `T`: "mm", "cm" or "m" (stated in `units`).
    """
    if units not in CM_PER_UNIT:
        raise ValueError(f"units: expected one of {sorted(CM_PER_UNIT)}, found {units!r}")
    extrinsics = np.asarray(camera.world_to_camera, np.float64)
    trans = extrinsics[:3, 3] / CM_PER_UNIT[units]
    return ("%YAML:1.0\n---\n"
            f"camera_name: {json.dumps(camera.name)}\n"
            f"image_width: {camera.width}\nimage_height: {camera.height}\n"
            + _yaml_matrix("camera_matrix", 3, 3, camera.intrinsic_matrix().reshape(-1))
            + "distortion_model: plumb_bob\n"
            + _yaml_matrix("distortion_coefficients", 1, 5, [camera.k1, camera.k2, 0.0, 0.0, 0.0])
            + _yaml_matrix("R", 3, 3, extrinsics[:3, :3].reshape(-1))
            + _yaml_matrix("T", 3, 1, trans)
            + f"units: {units}\n")


# -- files ----------------------------------------------------------------------------------

def _json_text(value: Any, indent: int = 0) -> str:
    """JSON with one key per line and each innermost list of numbers on one line."""
    pad, inner = " " * indent, " " * (indent + 1)
    if isinstance(value, dict) and value:
        items = [f"{inner}{json.dumps(k)}: {_json_text(v, indent + 1)}" for k, v in value.items()]
        return "{\n" + ",\n".join(items) + f"\n{pad}}}"
    if isinstance(value, list) and any(isinstance(v, (list, dict)) for v in value):
        items = [f"{inner}{_json_text(v, indent + 1)}" for v in value]
        return "[\n" + ",\n".join(items) + f"\n{pad}]"
    return json.dumps(value, allow_nan=False)


def _read_file(path: str, what: str) -> tuple[str, Any]:
    """(format, parsed data) of a camera or rig file."""
    fmt = format_of(path, CAMERA_FORMATS)
    if not os.path.isfile(path):
        raise InputError("path", f"{_where(path)}: expected a {what}, found it missing")
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except (OSError, UnicodeDecodeError) as err:
        raise InputError("path", f"{_where(path)}: expected a readable {what}, found an "
                                 f"unreadable file ({type(err).__name__}: {err})") from err
    if fmt == "yaml":
        return fmt, parse_opencv_yaml(text, path)
    try:
        data = json.loads(text)
    except ValueError as err:
        raise InputError("path", f"{_where(path)}: expected a {what} in JSON, found invalid JSON "
                                 f"({err})") from err
    if not isinstance(data, dict):
        raise InputError("path", f"{_where(path)}: expected a JSON object, found "
                                 f"{type(data).__name__}")
    return fmt, data


def _camera_from_data(data: dict[str, Any], path: str, *, name: str, units: str,
                      ignore_extra_distortion: bool) -> Camera:
    schema = data.get("schema")
    if schema == CAMERA_RIG_SCHEMA:
        raise InputError("path", f"{_where(path)}: expected one camera, found a camera rig "
                                 "(load it with io.LoadCameraRig)")
    if schema is None:
        return camera_from_opencv(data, path, name=name, units=units,
                                  ignore_extra_distortion=ignore_extra_distortion)
    try:
        camera = Camera.from_json(data, _where(path))
    except ValueError as err:
        raise InputError("path", str(err)) from err
    stated = data.get("units", "cm")
    if units not in ("from_file", stated):
        raise InputError("units", f"{_where(path)}: the file states units '{stated}', the "
                                  f"parameter says '{units}'")
    if name:
        camera.name = name
    return camera


def load_camera(path: str | os.PathLike, *, name: str = "", units: str = "from_file",
                ignore_extra_distortion: bool = False) -> Camera:
    """Read one camera from our JSON, OpenCV YAML or OpenCV-style JSON (see the module).

    Args:
        path: a .json, .yaml or .yml file.
        name: camera name; "" = the name in the file, else (OpenCV files) the file stem.
        units: translation unit of OpenCV files ("mm", "cm", "m"; "from_file" = the file's
            `units` key). Our JSON states its own; a contradicting value is an error.
        ignore_extra_distortion: drop tangential and higher-order distortion terms.
    Returns:
        the validated Camera (translation in cm).
    Raises:
        InputError: naming the file and the field (param "path", or "units").
    """
    path = os.fspath(path)
    _, data = _read_file(path, "camera calibration")
    return _camera_from_data(data, path, name=name, units=units,
                             ignore_extra_distortion=ignore_extra_distortion)


def save_camera(path: str | os.PathLike, camera: Camera, *, units: str = "cm") -> None:
    """Write `camera` atomically: .json in our form (cm), .yaml / .yml as OpenCV YAML in `units`."""
    path = os.fspath(path)
    fmt = format_of(path, CAMERA_FORMATS)
    if fmt == "yaml":
        text = camera_to_opencv_yaml(camera, units)
    else:
        data = camera.to_json()
        if units not in CM_PER_UNIT:
            raise InputError("units", f"expected one of {sorted(CM_PER_UNIT)}, found {units!r}")
        matrix = np.array(data["world_to_camera"])
        matrix[:3, 3] /= CM_PER_UNIT[units]
        data.update(world_to_camera=matrix.tolist(), units=units)
        text = _json_text(data) + "\n"
    with atomic_path(path) as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


def _rig_entries(path: str) -> list[Any]:
    fmt, data = _read_file(path, "camera rig")
    if fmt != "json" or data.get("schema") != CAMERA_RIG_SCHEMA:
        raise InputError("path", f"{_where(path)}: expected a rig JSON with \"schema\": "
                                 f"\"{CAMERA_RIG_SCHEMA}\", found "
                                 f"{'YAML' if fmt == 'yaml' else repr(data.get('schema'))}; pass "
                                 "single camera files as camera_files")
    if sorted(data) != ["cameras", "schema"] or not isinstance(data["cameras"], list):
        raise InputError("path", f"{_where(path)}: expected keys 'schema' and 'cameras' (a list), "
                                 f"found keys {sorted(data)}")
    if not data["cameras"]:
        raise InputError("path", f"{_where(path)}: 'cameras' must list at least one camera, found "
                                 "none")
    return data["cameras"]


def _entry_file(path: str, entry: str) -> str:
    return entry if os.path.isabs(entry) else os.path.join(os.path.dirname(path), entry)


def rig_input_files(path: str = "", camera_files: Sequence[str] = ()) -> list[Path]:
    """Every existing file a rig load reads: the rig file, the camera files it references, and
    `camera_files`, in order (an unreadable rig file lists only itself)."""
    files = [Path(f) for f in camera_files if os.path.isfile(f)]
    if not path:
        return files
    if not os.path.isfile(path):
        return files
    out = [Path(path)]
    try:
        entries = _rig_entries(path)
    except InputError:
        return out + files  # the load itself reports what is wrong with the file
    out += [Path(_entry_file(path, e)) for e in entries
            if isinstance(e, str) and os.path.isfile(_entry_file(path, e))]
    return out + files


def load_camera_rig(path: str = "", camera_files: Sequence[str] = (), *,
                    names: Sequence[str] = (), units: str = "from_file",
                    ignore_extra_distortion: bool = False) -> CameraRig:
    """Read a rig file or several camera files (exactly one of the two) as a CameraRig.

    Args:
        path: rig JSON (see the module); entries are cameras in our JSON form or paths of
            camera files, relative to the rig file's folder.
        camera_files: camera files (any format `load_camera` reads), one camera each.
        names: camera names in rig order (empty = the names the files give).
        units, ignore_extra_distortion: as in `load_camera`, for every OpenCV file.
    Returns:
        the validated rig, cameras in file order.
    Raises:
        InputError: naming the file (and camera) at fault; duplicate names.
    """
    if bool(path) == bool(camera_files):
        raise InputError("path", "expected either a rig file ('path') or camera files "
                                 f"('camera_files'), found {'both' if path else 'neither'}")
    cameras: list[Camera] = []
    if path:
        path = os.fspath(path)
        for index, entry in enumerate(_rig_entries(path)):
            if isinstance(entry, str):
                cameras.append(load_camera(_entry_file(path, entry), units=units,
                                           ignore_extra_distortion=ignore_extra_distortion))
            elif isinstance(entry, dict):
                try:
                    cameras.append(Camera.from_json(entry, f"{_where(path)}: camera {index}"))
                except ValueError as err:
                    raise InputError("path", str(err)) from err
            else:
                raise InputError("path", f"{_where(path)}: camera {index} must be a camera object "
                                         f"or a file path, found {type(entry).__name__}")
    else:
        cameras = [load_camera(os.fspath(f), units=units,
                               ignore_extra_distortion=ignore_extra_distortion)
                   for f in camera_files]
    if names:
        if len(names) != len(cameras):
            raise InputError("names", f"expected {len(cameras)} names (one per camera), found "
                                      f"{len(names)}")
        for camera, name in zip(cameras, names):
            camera.name = name
    try:
        return CameraRig.from_cameras(cameras)
    except ValueError as err:
        source = f"{_where(path)}" if path else f"camera files {list(map(str, camera_files))}"
        raise InputError("names" if names else "path", f"{source}: {err}") from err


def save_camera_rig(path: str | os.PathLike, rig: CameraRig) -> None:
    """Write `rig` atomically as a rig JSON with every camera inline (cm)."""
    path = os.fspath(path)
    if format_of(path, CAMERA_FORMATS) != "json":
        raise InputError("path", f"'{path}': expected a .json rig file, found "
                                 f"'{os.path.splitext(path)[1]}'")
    with atomic_path(path) as tmp:
        Path(tmp).write_text(_json_text(rig.to_json()) + "\n", encoding="utf-8")


# -- nodes ----------------------------------------------------------------------------------

_UNITS_DOC = ("Unit of the translation of OpenCV files (mm, cm, m); from_file = the file's "
              "'units' key (our JSON always states it).")
_EXTRA_DOC = "Drop non-zero tangential/higher-order distortion (p1, p2, k3, ...) of OpenCV files."


class LoadCamera(Node):
    """Read a calibrated camera: our JSON, OpenCV FileStorage YAML or OpenCV-style JSON."""

    type_name = "io.LoadCamera"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Camera file (.json, .yaml, .yml).")
        name: str = Param("", description="Camera name; '' = the file's, else the file name.")
        units: Units = Param("from_file", description=_UNITS_DOC)
        ignore_extra_distortion: bool = Param(False, description=_EXTRA_DOC)

    camera = Out(Camera, doc="Intrinsics (px), world-to-camera (cm), size, k1, k2.")

    def run(self) -> dict[str, Camera]:
        p = self.params
        return {"camera": load_camera(p.path, name=p.name, units=p.units,
                                      ignore_extra_distortion=p.ignore_extra_distortion)}


class LoadCameraRig(Node):
    """Read several calibrated cameras: a rig JSON, or one camera file per camera."""

    type_name = "io.LoadCameraRig"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        path: str = Param("", input_file=True, description="Rig JSON (cameras inline or as "
                          "paths of camera files relative to it); '' when camera_files is set.")
        camera_files: list[str] = Param([], input_file=True, description="Camera files (.json, "
                                        ".yaml, .yml), one camera each, in rig order.")
        names: list[str] = Param([], description="Camera names in rig order; empty = from the "
                                 "files.")
        units: Units = Param("from_file", description=_UNITS_DOC)
        ignore_extra_distortion: bool = Param(False, description=_EXTRA_DOC)

    rig = Out(CameraRig, doc="Cameras (N) with intrinsics, world-to-camera, sizes, k1, k2.")

    def input_files(self, frames: range | None = None) -> list[Path]:
        return rig_input_files(self.params.path, self.params.camera_files)

    def run(self) -> dict[str, CameraRig]:
        p = self.params
        return {"rig": load_camera_rig(p.path, p.camera_files, names=p.names, units=p.units,
                                       ignore_extra_distortion=p.ignore_extra_distortion)}


class SaveCamera(Node):
    """Write a camera as our JSON (.json) or OpenCV FileStorage YAML (.yaml, .yml)."""

    type_name = "io.SaveCamera"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination .json, .yaml or .yml file.")
        units: Literal["mm", "cm", "m"] = Param("cm", description="Unit of the written "
                                                "translation (stated in the file).")

    camera = In(Camera, doc="The camera to write.")
    files = Out(Files, doc="The written file and its sha256.")

    def run(self, camera: Camera) -> dict[str, Files]:
        save_camera(self.params.path, camera, units=self.params.units)
        return {"files": files_value([self.params.path])}


class SaveCameraRig(Node):
    """Write a camera rig as a rig JSON with every camera inline (cm)."""

    type_name = "io.SaveCameraRig"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Destination .json file.")

    rig = In(CameraRig, doc="The rig to write.")
    files = Out(Files, doc="The written file and its sha256.")

    def run(self, rig: CameraRig) -> dict[str, Files]:
        save_camera_rig(self.params.path, rig)
        return {"files": files_value([self.params.path])}
