"""ARKit blendshape names, their mapping to the ICT-FaceKit shapes, and the Live Link Face CSV
conventions (column order, timecodes, head and eye angles).

**Names.** ARKit has 52 shapes (`ARKIT_NAMES`, camelCase, in the order of the Live Link Face
app's CSV). The ICT head has 53: the same shapes with `_L` / `_R` for `Left` / `Right`
(`eyeBlink_L` is ARKit's `eyeBlinkLeft`), but it splits `browInnerUp` and `cheekPuff` into a
left and a right half, and has no `tongueOut`. Left and right are the subject's own, in both:
ICT's `_L` shapes move the vertices on the head's +x side, which is the subject's left (the
head faces +z with y up), as ARKit's `...Left` shapes do. So:

- an ICT name `<base>_L` / `<base>_R` maps to `<base>Left` / `<base>Right`, a name without a
  suffix to itself (`jawOpen`, `mouthLeft`: ARKit's own names);
- ARKit's `browInnerUp` and `cheekPuff` are the mean of the two ICT halves (written), and each
  half is ARKit's value (read);
- ARKit's `tongueOut` is written as 0 and ignored when read.

**Live Link Face CSV** (`LIVE_LINK_HEADER`): `Timecode`, `BlendShapeCount` (61), the 52 shapes
in PascalCase, then `HeadYaw, HeadPitch, HeadRoll` and each eye's yaw, pitch and roll. The
header's order is the app's own (checked against the header row of real takes quoted by public
readers). Timecodes are `HH:MM:SS:FF.mmm`: frame `FF` of the second at the timecode rate and
`mmm` the thousandths of a frame (a 60 fps take under a 30 fps timecode has `.500` rows).

**Angles.** We follow the convention of public Live Link Face readers that drive a head bone
(polyvox_filament's `getLiveLinkFaceBoneDrivers`: `HeadPitch` about x, `HeadYaw` about y,
`HeadRoll` about z, each value times pi/2 radians): a value is an angle over 90 degrees (so +-1 is
+-90 degrees), about the axes of ARKit's face frame (x the subject's left, y up, z out of the
face towards the camera), right-handed: positive yaw turns the face towards the subject's left,
positive pitch tilts it down, positive roll lowers its right side. The rotation of the face in
the camera's ARKit frame (x right, y up, z towards the viewer) is
`R = R_y(yaw) R_x(pitch) R_z(roll)`. Eye angles use the same units and axes; we derive them
from the eyeLook weights (a full `eyeLookOut` is `EYE_RANGE_RAD` of yaw).
"""

from __future__ import annotations

import re
from typing import Sequence

import numpy as np

from ..geometry.rotation import euler_to_rotmat, rotmat_to_euler

__all__ = ["LIVE_LINK_SHAPES", "ARKIT_NAMES", "LIVE_LINK_ANGLES", "LIVE_LINK_HEADER", "BLEND_SHAPE_COUNT",
           "SPLIT_SHAPES", "ANGLE_UNIT_RAD", "EYE_RANGE_RAD", "OPENCV_TO_ARKIT", "arkit_name", "to_arkit_weights",
           "from_arkit_weights", "shape_basis", "head_angles", "head_rotation", "eye_angles",
           "format_timecode", "parse_timecode"]

LIVE_LINK_SHAPES = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawRight", "JawLeft", "JawOpen", "MouthClose", "MouthFunnel",
    "MouthPucker", "MouthRight", "MouthLeft", "MouthSmileLeft", "MouthSmileRight", "MouthFrownLeft",
    "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft", "MouthStretchRight",
    "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper", "MouthPressLeft", "MouthPressRight",
    "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft", "MouthUpperUpRight", "BrowDownLeft",
    "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight", "CheekPuff", "CheekSquintLeft",
    "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
"""The 52 shapes as the Live Link Face app's CSV names and orders them (PascalCase)."""

ARKIT_NAMES = tuple(n[0].lower() + n[1:] for n in LIVE_LINK_SHAPES)
"""The 52 ARKit shape names (`ARFaceAnchor.BlendShapeLocation`, camelCase), in the CSV's order."""

LIVE_LINK_ANGLES = ("HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll",
                    "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
"""The 9 angle columns after the shapes (units: `ANGLE_UNIT_RAD`)."""

LIVE_LINK_HEADER = ("Timecode", "BlendShapeCount") + LIVE_LINK_SHAPES + LIVE_LINK_ANGLES
"""Every column of a Live Link Face CSV, in order (63)."""

BLEND_SHAPE_COUNT = len(LIVE_LINK_SHAPES) + len(LIVE_LINK_ANGLES)
"""The `BlendShapeCount` column's value: 61 (52 shapes and 9 angles)."""

SPLIT_SHAPES = {"browInnerUp": ("browInnerUp_L", "browInnerUp_R"), "cheekPuff": ("cheekPuff_L", "cheekPuff_R")}
"""ARKit shapes that the ICT head splits into a left and a right half."""

ANGLE_UNIT_RAD = np.pi / 2
"""Radians per unit of a Live Link angle column (+-1 is +-90 degrees)."""

EYE_RANGE_RAD = np.deg2rad(30.0)
"""Eye rotation of a full eyeLook shape (weight 1), radians: the eye angles written from the weights."""

OPENCV_TO_ARKIT = np.diag([1.0, -1.0, -1.0])
"""An OpenCV camera frame (x right, y down, z forward) to ARKit's (x right, y up, z towards the viewer)."""


def arkit_name(name: str) -> str:
    """The ARKit name of a face model's shape name (`eyeBlink_L` -> `eyeBlinkLeft`, `browInnerUp_L` ->
    `browInnerUp`); a name that is neither an ICT nor an ARKit shape is returned unchanged."""
    for arkit, halves in SPLIT_SHAPES.items():
        if name in halves:
            return arkit
    match = re.fullmatch(r"(.+)_([LR])", name)
    if match:
        return match.group(1) + ("Left" if match.group(2) == "L" else "Right")
    return name


def shape_basis(names: Sequence[str], *, asymmetry: bool = True) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Express a model's K shapes as the 52 ARKit shapes (plus extras) for blendshape files.

    Shape weights `s = w @ A.T` and shape offsets `D_s = B @ D_k` reproduce the model exactly,
    `sum_s s_s D_s = sum_k w_k D_k`: a shape with an ARKit name is itself; a split pair (L, R)
    becomes ARKit's shape (weight `(w_L + w_R) / 2`, offsets `D_L + D_R`) and, with `asymmetry`,
    `<name>Asymmetry` (weight `w_L - w_R`, offsets `(D_L - D_R) / 2`); `tongueOut` without a model
    shape has zero offsets; shapes of other names follow the 52 as they are.

    Args:
        names: the model's K shape names.
        asymmetry: add the asymmetry shapes of split pairs (False: a left-right difference is lost).
    Returns:
        (names of the S shapes: `ARKIT_NAMES` first, then extras), A (S, K), B (S, K) float64.
    """
    index = {n: i for i, n in enumerate(names)}
    k = len(names)
    out_names: list[str] = []
    a_rows: list[np.ndarray] = []
    b_rows: list[np.ndarray] = []

    def add(name: str, a: dict[int, float], b: dict[int, float]) -> None:
        ra, rb = np.zeros(k), np.zeros(k)
        for i, v in a.items():
            ra[i] = v
        for i, v in b.items():
            rb[i] = v
        out_names.append(name)
        a_rows.append(ra)
        b_rows.append(rb)

    used: set[int] = set()
    extras: list[tuple[str, dict[int, float], dict[int, float]]] = []
    for arkit in ARKIT_NAMES:
        if arkit in index:
            i = index[arkit]
            add(arkit, {i: 1.0}, {i: 1.0})
            used.add(i)
            continue
        halves = SPLIT_SHAPES.get(arkit)
        if halves and all(h in index for h in halves):
            left, right = index[halves[0]], index[halves[1]]
            add(arkit, {left: 0.5, right: 0.5}, {left: 1.0, right: 1.0})
            used.update((left, right))
            if asymmetry:
                extras.append((arkit + "Asymmetry", {left: 1.0, right: -1.0}, {left: 0.5, right: -0.5}))
            continue
        sided = [i for i, n in enumerate(names) if arkit_name(n) == arkit and i not in used]
        if len(sided) == 1:
            add(arkit, {sided[0]: 1.0}, {sided[0]: 1.0})
            used.add(sided[0])
        else:
            add(arkit, {}, {})
    for name, a, b in extras:
        add(name, a, b)
    for i, n in enumerate(names):
        if i not in used:
            add(n, {i: 1.0}, {i: 1.0})
    return out_names, np.array(a_rows).reshape(-1, k), np.array(b_rows).reshape(-1, k)


def to_arkit_weights(weights: np.ndarray, names: Sequence[str]) -> np.ndarray:
    """(F, K) weights of named shapes -> (F, 52) ARKit weights in `ARKIT_NAMES` order (not clipped).

    Split pairs give their mean; shapes the model lacks (`tongueOut` for the ICT head) are 0;
    shapes without an ARKit name are left out.
    """
    _, a, _ = shape_basis(names, asymmetry=False)
    return np.asarray(weights, np.float64) @ a[:len(ARKIT_NAMES)].T


def from_arkit_weights(arkit: np.ndarray, names: Sequence[str]) -> tuple[np.ndarray, list[str]]:
    """(F, 52) ARKit weights -> (F, K) weights of the model's named shapes.

    Each half of a split pair takes ARKit's value; a model shape without an ARKit counterpart is 0.

    Returns:
        (F, K) float32 weights, and the model names that had no ARKit counterpart.
    """
    arkit = np.asarray(arkit, np.float64)
    position = {n: i for i, n in enumerate(ARKIT_NAMES)}
    out = np.zeros((len(arkit), len(names)), np.float32)
    unmatched = []
    for k, name in enumerate(names):
        source = position.get(name, position.get(arkit_name(name)))
        if source is None:
            unmatched.append(name)
        else:
            out[:, k] = arkit[:, source]
    return out, unmatched


def head_angles(rotation: np.ndarray) -> np.ndarray:
    """(F, 3, 3) face rotations in ARKit's camera frame -> (F, 3) yaw, pitch, roll, radians.

    The inverse of `head_rotation` (`R = R_y(yaw) R_x(pitch) R_z(roll)`); pitch in [-pi/2, pi/2].
    """
    rot = np.asarray(rotation, np.float64).reshape(-1, 3, 3)
    return rotmat_to_euler(rot, "YXZ")


def head_rotation(angles: np.ndarray) -> np.ndarray:
    """(F, 3) yaw, pitch, roll radians -> (F, 3, 3) rotations `R_y(yaw) R_x(pitch) R_z(roll)`."""
    angles = np.asarray(angles, np.float64).reshape(-1, 3)
    return euler_to_rotmat(angles, "YXZ")


def eye_angles(arkit: np.ndarray) -> np.ndarray:
    """(F, 52) ARKit weights -> (F, 6) left eye yaw, pitch, roll, right eye yaw, pitch, roll, radians.

    Yaw towards the subject's left is positive (the left eye's `eyeLookOut`, the right eye's
    `eyeLookIn`), pitch down is positive (`eyeLookDown`); roll is 0. A full shape is `EYE_RANGE_RAD`.
    """
    w = {n: np.asarray(arkit, np.float64)[:, i] for i, n in enumerate(ARKIT_NAMES)}
    zero = np.zeros(len(arkit))
    left_yaw = w["eyeLookOutLeft"] - w["eyeLookInLeft"]
    right_yaw = w["eyeLookInRight"] - w["eyeLookOutRight"]
    left_pitch = w["eyeLookDownLeft"] - w["eyeLookUpLeft"]
    right_pitch = w["eyeLookDownRight"] - w["eyeLookUpRight"]
    return EYE_RANGE_RAD * np.stack([left_yaw, left_pitch, zero, right_yaw, right_pitch, zero], axis=1)


_TIMECODE = re.compile(r"\s*(\d+):(\d{1,2}):(\d{1,2})[:;.](\d+)(?:\.(\d+))?\s*")


def format_timecode(frame: int, fps: float, start: str = "00:00:00:00") -> str:
    """The `HH:MM:SS:FF.mmm` timecode of a frame, at a timecode rate of `round(fps)` frames a second.

    Args:
        frame: frame index from the start (>= 0).
        fps: the shot's frame rate (> 0); a rate that is not a whole number (29.97) gives
            fractional frames (`.mmm`).
        start: timecode of frame 0, `HH:MM:SS:FF` (optionally `.mmm`).
    Returns:
        e.g. `00:00:01:15.000` (frame 45 at 30 fps). Hours wrap at 24.

    Example:
        >>> format_timecode(45, 30.0)
        '00:00:01:15.000'
    """
    rate = max(1, int(round(fps)))
    h, m, s, ff = parse_timecode(start)
    start_units = round(((h * 3600 + m * 60 + s) * rate + ff) * 1000)
    units = start_units + round(frame * rate / fps * 1000)  # thousandths of a timecode frame
    frames, sub = divmod(int(units), 1000)
    seconds, ff_out = divmod(frames, rate)
    minutes, ss = divmod(seconds, 60)
    hours, mm = divmod(minutes, 60)
    return f"{hours % 24:02d}:{mm:02d}:{ss:02d}:{ff_out:02d}.{sub:03d}"


def parse_timecode(text: str) -> tuple[int, int, int, float]:
    """`HH:MM:SS:FF[.mmm]` (or `;` before the frames) -> (hours, minutes, seconds, frames + fraction).

    Raises:
        ValueError: naming the text when it is not a timecode.
    """
    match = _TIMECODE.fullmatch(str(text))
    if not match:
        raise ValueError(f"expected a timecode HH:MM:SS:FF or HH:MM:SS:FF.mmm, found {text!r}")
    h, m, s, ff, sub = match.groups()
    fraction = float("0." + sub) if sub else 0.0
    return int(h), int(m), int(s), int(ff) + fraction
