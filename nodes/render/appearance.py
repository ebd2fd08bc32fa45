"""Default appearance of the bundled ICT head: per-vertex albedo, lighting, hidden parts.

The landmark network (MediaPipe's face mesh) reads a render of the head as a face only
when it looks like one: an experiment on this project found detection (presence 1.0 at yaw
+-30 deg, pitch +-10 deg, any jaw opening) and mouth tracking (r = 0.99 against the
geometry) with skin albedo, red lips, dark brows, white sclera with a dark iris and pupil, a
dark mouth interior with teeth and tongue drawn, the transparent eye shells (vertices
24591-25350) and the eyelash strips (25351-26718) hidden, a light from the front and above
with ambient about 0.35, a grey background, rendered at 2x and downsampled. Uniform skin
alone loses most of the mouth and eye signal; eyelid landmarks stay weak on renders.

Regions are found on the neutral head (cm, y up, z out of the face) from the model's
vertex groups and its 68 landmark vertices (Multi-PIE order): lips inside the outer-lip
polygon (points 48-59) seen from the front, brows within `BROW_HALF_WIDTH_CM` of the brow
polylines (17-21, 22-26), iris and pupil by the distance from each eyeball's front axis.
Albedo is linear light; transitions are smoothed over about 1.5 mm so that edges do not
alias. Pure numpy; `appearance_json` gives the JSON value of the `render.Render` node's
`appearance` port.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from nodegraph import FaceModel

__all__ = ["ICT_HIDDEN_VERTEX_RANGES", "COLOURS", "BROW_HALF_WIDTH_CM", "DEFAULT_LIGHT", "hidden_faces",
           "culled_faces", "visible_faces", "default_albedo", "default_sh", "appearance_json", "parse_appearance"]

ICT_HIDDEN_VERTEX_RANGES = ((24591, 25350), (25351, 26718))
"""Inclusive vertex ranges of the ICT head not drawn: transparent eye shells (lacrimal fluid,
eye blend, eye occlusion) and eyelash strips."""

COLOURS = {  # linear albedo (sRGB values in the comments)
    "skin": (0.62, 0.38, 0.28),      # ~ (205, 166, 145)
    "lips": (0.38, 0.085, 0.085),    # ~ (166, 82, 82)
    "brows": (0.035, 0.022, 0.016),  # ~ (52, 41, 34)
    "sclera": (0.80, 0.78, 0.74),
    "iris": (0.06, 0.035, 0.02),
    "pupil": (0.005, 0.005, 0.005),
    "mouth": (0.025, 0.008, 0.008),  # mouth socket
    "tongue": (0.40, 0.10, 0.10),    # gums and tongue
    "teeth": (0.80, 0.76, 0.64),
    "eye_socket": (0.30, 0.12, 0.10),
}
"""Linear albedo of each region of the default appearance."""

BROW_HALF_WIDTH_CM = 0.42
IRIS_RADIUS_CM = 0.58
PUPIL_RADIUS_CM = 0.24
_SOFT_CM = 0.15

DEFAULT_LIGHT = {"ambient": 0.35, "direction": (0.0, 0.6, 1.0), "intensity": 0.8,
                 "background": (0.21, 0.21, 0.21)}
"""Default lighting (world frame of the ICT head: y up, z out of the face): ambient, one
light from the front and above, and a grey background (linear 0.21 ~ sRGB 0.5)."""


def hidden_faces(faces: np.ndarray, ranges: tuple[tuple[int, int], ...] = ICT_HIDDEN_VERTEX_RANGES) -> np.ndarray:
    """Indices of the faces with a corner in any of the inclusive vertex `ranges`.

    Args:
        faces: (T, 3) int.
        ranges: inclusive (first, last) vertex ranges.
    Returns:
        (H,) int64 face indices, ascending.
    """
    faces = np.asarray(faces)
    hide = np.zeros(len(faces), bool)
    for first, last in ranges:
        hide |= ((faces >= first) & (faces <= last)).any(1)
    return np.flatnonzero(hide)


def culled_faces(faces: np.ndarray, num_vertices: int,
                 ranges: tuple[tuple[int, int], ...] = ICT_HIDDEN_VERTEX_RANGES) -> np.ndarray:
    """Indices of the faces not drawn: `hidden_faces` when the mesh is the whole head the ranges
    index (more than the last range's end vertices); none for a smaller mesh (a region or a
    reduced model is indexed differently, so the ranges do not apply).

    Args:
        faces: (T, 3) int vertex indices.
        num_vertices: V, the mesh's vertex count.
        ranges: inclusive (first, last) vertex ranges.
    Returns:
        (H,) int64 face indices, ascending.
    """
    if num_vertices <= max((last for _, last in ranges), default=-1):
        return np.zeros(0, np.int64)
    return hidden_faces(faces, ranges)


def visible_faces(faces: np.ndarray, num_vertices: int,
                  ranges: tuple[tuple[int, int], ...] = ICT_HIDDEN_VERTEX_RANGES) -> np.ndarray:
    """The triangles drawn: `faces` less those with a corner in the hidden vertex `ranges`
    (`culled_faces`: only when the mesh is the whole head the ranges index).

    Args:
        faces: (T, 3) int vertex indices.
        num_vertices: V, the mesh's vertex count.
        ranges: inclusive (first, last) vertex ranges.
    Returns:
        (T', 3) int64, in the order of `faces`.

    Example:
        >>> visible_faces(np.array([[0, 1, 2], [1, 2, 3]]), 4, ((3, 3),)).tolist()
        [[0, 1, 2]]
    """
    faces = np.asarray(faces, np.int64)
    return np.delete(faces, culled_faces(faces, num_vertices, ranges), axis=0)


def _inside_polygon(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """(N, 2) points, (P, 2) closed polygon -> (N,) bool, by the even-odd rule (vectorized)."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    px, py = points[:, None, 0], points[:, None, 1]
    crosses = (a[None, :, 1] > py) != (b[None, :, 1] > py)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[None, :, 0] + (py - a[None, :, 1]) * (b[None, :, 0] - a[None, :, 0]) / (b[None, :, 1] - a[None, :, 1])
    return ((crosses & (px < x_at)).sum(1) % 2) == 1


def _distance_to_segments(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """(N, 2) points -> (N,) distance to an open (P, 2) polyline."""
    a, b = polyline[:-1], polyline[1:]
    ab = b - a
    t = ((points[:, None] - a[None]) * ab[None]).sum(-1) / np.maximum((ab ** 2).sum(-1), 1e-12)[None]
    closest = a[None] + np.clip(t, 0, 1)[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=-1).min(1)


def _polygon_distance(points: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """Signed distance to a closed polygon: negative inside."""
    closed = np.concatenate([polygon, polygon[:1]])
    d = _distance_to_segments(points, closed)
    return np.where(_inside_polygon(points, polygon), -d, d)


def _blend(albedo: np.ndarray, where: np.ndarray, weight: np.ndarray, colour: tuple[float, float, float]) -> None:
    w = np.clip(weight, 0.0, 1.0)[:, None]
    albedo[where] = albedo[where] * (1 - w) + np.asarray(colour, np.float32) * w


def default_albedo(model: FaceModel) -> np.ndarray:
    """Per-vertex linear albedo of the default appearance (see the module docstring).

    Args:
        model: the bundled ICT head (or any model with its groups: face, eyeball_left,
            eyeball_right, teeth, gums_tongue, mouth_socket, eye_socket_left/right, and 68
            landmarks). Missing groups keep the skin colour.
    Returns:
        (V, 3) float32 linear albedo in [0, 1].
    """
    v = model.neutral.shape[0]
    albedo = np.tile(np.asarray(COLOURS["skin"], np.float32), (v, 1))
    groups = model.groups
    for name, colour in (("mouth_socket", "mouth"), ("gums_tongue", "tongue"), ("teeth", "teeth"),
                         ("eye_socket_left", "eye_socket"), ("eye_socket_right", "eye_socket")):
        if name in groups:
            albedo[groups[name]] = COLOURS[colour]
    for name in ("eyeball_left", "eyeball_right"):
        if name not in groups:
            continue
        idx = groups[name]
        eye = model.neutral[idx]
        front = eye[:, 2] > eye[:, 2].max() - 1.0
        axis = eye[front, :2].mean(0)  # (x, y) of the gaze axis (looking down +z)
        r = np.linalg.norm(eye[:, :2] - axis, axis=1)
        albedo[idx] = COLOURS["sclera"]
        front_half = eye[:, 2] > np.median(eye[:, 2])
        iris = (IRIS_RADIUS_CM + _SOFT_CM / 2 - r) / _SOFT_CM
        _blend(albedo, idx[front_half], iris[front_half], COLOURS["iris"])
        pupil = (PUPIL_RADIUS_CM + _SOFT_CM / 2 - r) / _SOFT_CM
        _blend(albedo, idx[front_half], pupil[front_half], COLOURS["pupil"])
    if len(model.landmarks) == 68 and "face" in groups:
        face = groups["face"]
        points = model.neutral[face]
        lm = model.neutral[model.landmarks]
        front = points[:, 2] > lm[[48, 54], 2].min() - 1.5
        xy = points[:, :2]
        lips = (-_polygon_distance(xy, lm[48:60, :2]) + _SOFT_CM / 2) / _SOFT_CM
        _blend(albedo, face[front], lips[front], COLOURS["lips"])
        brow_front = points[:, 2] > lm[17:27, 2].min() - 1.5
        for brow in (lm[17:22, :2], lm[22:27, :2]):
            d = _distance_to_segments(xy, brow)
            weight = (BROW_HALF_WIDTH_CM + _SOFT_CM / 2 - d) / _SOFT_CM
            _blend(albedo, face[brow_front], weight[brow_front], COLOURS["brows"])
    return albedo


def default_sh() -> np.ndarray:
    """(9, 3) SH irradiance of `DEFAULT_LIGHT` (world frame)."""
    from .renderer import sh_from_lights  # torch: only when asked for

    return sh_from_lights(DEFAULT_LIGHT["ambient"], DEFAULT_LIGHT["direction"], DEFAULT_LIGHT["intensity"])


def model_appearance(model: FaceModel, value: Any | None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """albedo, sh, background, hidden faces of an appearance JSON value (`parse_appearance`), or of
    the default appearance when `value` is None (ICT eye shells and lashes hidden when the model
    is the whole head: `culled_faces`).

    Raises:
        ValueError: as `parse_appearance`.
    """
    if value is None:
        return (default_albedo(model), default_sh(), np.asarray(DEFAULT_LIGHT["background"], np.float32),
                culled_faces(model.faces, model.neutral.shape[0]))
    return parse_appearance(value, model.neutral.shape[0], len(model.faces))


def appearance_json(albedo: np.ndarray, sh: np.ndarray, background: tuple[float, float, float],
                    hidden: np.ndarray | None = None) -> dict[str, Any]:
    """The JSON value of an appearance (the `render.Render` node's `appearance` port).

    Keys: "albedo" (V x 3 linear), "sh" (9 x 3, world frame), "background" (3 linear),
    "hidden_faces" (face indices not drawn).
    """
    return {"albedo": np.round(np.asarray(albedo, np.float64), 5).tolist(),
            "sh": np.round(np.asarray(sh, np.float64), 6).tolist(),
            "background": [float(c) for c in background],
            "hidden_faces": [] if hidden is None else [int(i) for i in hidden]}


def parse_appearance(value: Any, num_vertices: int, num_faces: int) -> tuple[np.ndarray, np.ndarray,
                                                                               np.ndarray, np.ndarray]:
    """Check an appearance JSON value against a mesh.

    Returns:
        albedo (V, 3) float32, sh (9, 3) float32, background (3,) float32, hidden (H,) int64.
    Raises:
        ValueError: "appearance: 'KEY' expected ..., found ..." for a missing or bad entry.
    """
    if not isinstance(value, dict):
        raise ValueError(f"appearance: expected a JSON object with 'albedo', 'sh', 'background', "
                         f"found {type(value).__name__}")
    missing = [k for k in ("albedo", "sh") if k not in value]
    if missing:
        raise ValueError(f"appearance: missing key(s) {missing}")
    albedo = np.asarray(value["albedo"], np.float32)
    if albedo.shape == (3,):
        albedo = np.tile(albedo, (num_vertices, 1))
    if albedo.shape != (num_vertices, 3):
        raise ValueError(f"appearance: 'albedo' expected ({num_vertices}, 3) (one per mesh vertex) or "
                         f"(3,), found {albedo.shape}")
    sh = np.asarray(value["sh"], np.float32)
    if sh.shape != (9, 3):
        raise ValueError(f"appearance: 'sh' expected (9, 3) coefficients, found {sh.shape}")
    background = np.asarray(value.get("background", (0.0, 0.0, 0.0)), np.float32)
    if background.shape != (3,):
        raise ValueError(f"appearance: 'background' expected 3 numbers, found {background.shape}")
    hidden = np.asarray(value.get("hidden_faces", []), np.int64).reshape(-1)
    if hidden.size and (hidden.min() < 0 or hidden.max() >= num_faces):
        raise ValueError(f"appearance: 'hidden_faces' expected face indices in 0..{num_faces - 1}, found "
                         f"{int(hidden.min())}..{int(hidden.max())}")
    for name, arr in (("albedo", albedo), ("sh", sh), ("background", background)):
        if not np.isfinite(arr).all():
            raise ValueError(f"appearance: '{name}' expected finite numbers, found NaN or inf")
    return albedo, sh, background, hidden
