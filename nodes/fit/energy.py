"""Landmark energies of the deep-energy fit (the paper's sections 4 and 8; see PAPERS.md §2)
as plain functions on tensors.

The fitted head is `x_R = R x(w) + t`: `x(w)` the face model's vertices (cm, model frame),
`R` (3, 3) and `t` (3,) cm its pose in the world frame. A landmark of the render is tied to
the head's surface by an *anchor*: a triangle (3 vertex indices) and barycentric weights,
so its world position is `sum_j b_j x_R[v_j]` (see `nodes.fit.views.anchor_points`).

Energy of one frame, summed over the calibrated cameras c that saw the face::

    E = sum_c sum_i W_i |s_c (p*_ci - q_ci)|^2                   (E1, data)
      + mu sum_c sum_(i,j) |s_c ((p*_cj - p*_ci) - (q_cj - q_ci))|^2   (E2, edges)
      + lambda sum_k w_k^2                                        (prior, active shapes)

with `p*` the network's landmarks on the plate and `q = pi_c(anchor(x_R)) + d` the network's
landmarks on the render (`d` the offset between the network's point and its anchor's
projection at anchoring time), image pixels. `s_c = 256 / side` of camera c's crop box
converts pixels to pixels of a 256 x 256 crop (the paper's 3D-FAN input), so that `lambda =
100` means what it means in the paper (residuals in 256-crop pixels, weights in [0, 1]).
The edges `(i, j)` are consecutive points along each contour of the 68 Multi-PIE points
(jaw, brows, nose, eyes, lips): the paper's edge-preserving term, which keeps the projected
size right when a few landmarks are off.

**Iris centres** (`iris_model_points`, `iris_points`): the ICT head's eyeballs do not move with
its eyeLook shapes (those only move the lids), so the fit turns each eyeball by the weights as the
exporters read them (`nodes.io.arkit.eye_angles`: a full shape is `EYE_RANGE_RAD` of yaw or
pitch, `R = R_y(yaw) R_x(pitch)`) about its centre (a sphere fitted to the eyeball); the iris
centre is the eyeball's front-most vertex so turned; the eyes sit where the mean head's do from
the model's eye corners (`iris_model_points_at_corners`: a fitted identity moves the eyeballs where
no landmark sees them). The stage solve re-linearizes it about the
current weights at every step, as it does the rotation, and compares it with the plate's relative
to the eye's corners (`iris_relative`), so that the head pose's error does not read as a look.

Torch is imported at the top: import this module from node `run()` methods only.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..geometry.camera import project_points_torch
from ..io.arkit import EYE_RANGE_RAD
from ..geometry.rotation import axis_angle_to_rotmat_torch as axis_angle_to_rotmat  # the fit's name
from ..geometry.rotation import rotmat_to_axis_angle
from ..geometry.rotation import skew_torch as _skew

__all__ = ["CROP_UNITS_PX", "EDGES_68", "landmark_weights", "axis_angle_to_rotmat", "rotmat_to_axis_angle",
           "posed_anchor_points", "project_views", "landmark_energy", "IRIS_EYEBALLS", "EYE_LOOK_ROTATIONS",
           "IRIS_CORNERS_68", "iris_relative", "eye_look_shapes", "eye_turns", "iris_model_points",
           "iris_model_points_at_corners", "IRIS_FRONT_FROM_CORNERS", "IRIS_CENTRE_FROM_CORNERS", "iris_points"]

CROP_UNITS_PX = 256.0
"""Residuals are measured in pixels of a crop box resized to this side (the paper's 256)."""


def _contour_edges() -> np.ndarray:
    runs = [range(0, 17), range(17, 22), range(22, 27), range(27, 31), range(31, 36)]
    loops = [range(36, 42), range(42, 48), range(48, 60), range(60, 68)]
    edges = [(a, a + 1) for r in runs for a in list(r)[:-1]]
    for r in loops:
        r = list(r)
        edges += [(a, b) for a, b in zip(r, r[1:] + r[:1])]
    return np.asarray(edges, np.int64)


EDGES_68 = _contour_edges()
"""(E, 2) consecutive Multi-PIE points along the jaw, brows, nose and around eyes and lips."""

JAW_68 = np.arange(0, 17)
EYELIDS_68 = np.array([37, 38, 40, 41, 43, 44, 46, 47])
MOUTH_68 = np.arange(48, 68)


def landmark_weights(set_name: str, *, eyelid: float = 0.2, mouth: float = 1.0, jaw: float = 1.0) -> np.ndarray:
    """Per-landmark weights W (the paper's weight matrix, diagonal) of one stage.

    Args:
        set_name: "non_jaw" (jaw contour 0-16 weight 0), "jaw" (only 0-16), "all", or "none"
            (every weight 0: the eye stage, where only the iris centres move the eyeLook weights).
        eyelid: weight of the eyelid points (37, 38, 40, 41, 43, 44, 46, 47): the network
            reads them poorly on renders, and blinks are not fitted.
        mouth: weight of the lip points 48-67 (the paper weights them up in the first
            expression stage).
        jaw: weight of the jaw contour points 0-16 in "all" (they slide along the silhouette
            instead of following the surface, so the anchored solve models them worst).
    Returns:
        (68,) float32 weights.
    """
    w = np.ones(68, np.float32)
    w[EYELIDS_68] = eyelid
    w[MOUTH_68] = mouth
    w[JAW_68] = jaw
    if set_name == "non_jaw":
        w[JAW_68] = 0.0
    elif set_name == "jaw":
        keep = np.zeros(68, bool)
        keep[JAW_68] = True
        w[~keep] = 0.0
        w[JAW_68] = 1.0
    elif set_name == "none":
        w[:] = 0.0
    elif set_name != "all":
        raise ValueError(f"set_name: expected 'non_jaw', 'jaw', 'all' or 'none', found {set_name!r}")
    return w


IRIS_EYEBALLS = ("eyeball_right", "eyeball_left")
"""The model's vertex groups of iris eye 0 (the subject's right, `nodes.landmarks.iris`) and eye 1."""

EYE_LOOK_ROTATIONS = {"eyeLookDown_R": (0, (1.0, 0.0, 0.0)), "eyeLookUp_R": (0, (-1.0, 0.0, 0.0)),
                      "eyeLookIn_R": (0, (0.0, 1.0, 0.0)), "eyeLookOut_R": (0, (0.0, -1.0, 0.0)),
                      "eyeLookDown_L": (1, (1.0, 0.0, 0.0)), "eyeLookUp_L": (1, (-1.0, 0.0, 0.0)),
                      "eyeLookIn_L": (1, (0.0, -1.0, 0.0)), "eyeLookOut_L": (1, (0.0, 1.0, 0.0))}
"""Eye (index into `IRIS_EYEBALLS`) and rotation axis of each eyeLook shape, model frame (x the
subject's left, y up, z out of the face), right-handed: about +x turns the gaze down, about +y
towards the subject's left (`nodes.io.arkit.eye_angles`' yaw and pitch)."""


IRIS_CORNERS_68 = np.array([[36, 39], [42, 45]])
"""The Multi-PIE eye corners of iris eye 0 (the subject's right) and eye 1: the iris residuals are
taken relative to their midpoint (`iris_relative`)."""


def iris_relative(values: Tensor) -> Tensor:
    """Make the iris centres' rows relative to their eye's corner midpoint.

    Applied to residuals `(target - predicted)` (or their Jacobian rows), it compares where each
    iris sits between its eye's corners on the plate and on the model: an error of the head's pose
    moves both alike and drops out to first order (a translation error of 0.3 cm is half a full
    look of the iris alone).

    Args:
        values: (B, C, L, ...) with the 68 Multi-PIE points first, then the two iris centres, then
            the four eye corners they are measured from (`IRIS_CORNERS_68`, flattened): L = 74.
    Returns:
        the same shape; the iris rows (L-6, L-5) minus the mean of their eye's corner rows.
    """
    mid = values[:, :, -4:].unflatten(2, (2, 2)).mean(3)  # (B, C, 2, ...)
    return torch.cat([values[:, :, :-6], values[:, :, -6:-4] - mid, values[:, :, -4:]], 2)


def eye_look_shapes(names: list[str]) -> list[int]:
    """Indices of the model's eyeLook shapes (`EYE_LOOK_ROTATIONS`' names it has), in model order."""
    return [i for i, n in enumerate(names) if n in EYE_LOOK_ROTATIONS]


def eye_turns(names: list[str], angle: float = EYE_RANGE_RAD) -> np.ndarray:
    """(K, 2, 2) yaw and pitch of each eye per unit weight of each of the K shapes, radians (0 for
    shapes other than `EYE_LOOK_ROTATIONS`; a full shape turns its eye by `angle`)."""
    turns = np.zeros((len(names), 2, 2))
    for k, name in enumerate(names):
        if name in EYE_LOOK_ROTATIONS:
            e, axis = EYE_LOOK_ROTATIONS[name]
            turns[k, e] = np.array([axis[1], axis[0]]) * angle  # yaw about y, pitch about x
    return turns


def iris_model_points(neutral: np.ndarray, eyeballs: list[np.ndarray], names: list[str], *,
                      angle: float = EYE_RANGE_RAD) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's two eyes for `iris_points`: front vertices, centres, and each shape's turn.

    Args:
        neutral: (V, 3) the model's neutral (identity applied), cm, model frame.
        eyeballs: two vertex index arrays, the eyeballs of iris eye 0 and eye 1 (`IRIS_EYEBALLS`).
        names: the K expression names.
        angle: eye rotation of a full shape, radians.
    Returns:
        front (2, 3) the iris centres at weight 0 (each eyeball's front-most vertex, largest z), cm;
        centres (2, 3) the eyeballs' centres of rotation (least-squares spheres), cm; turns
        (K, 2, 2) yaw and pitch of each eye per unit weight of each shape, radians (0 for shapes
        other than `EYE_LOOK_ROTATIONS`).
    Raises:
        ValueError: an eyeball with fewer than 4 vertices.

    Example:
        >>> ball = np.concatenate([np.eye(3), -np.eye(3)])  # unit octahedron: front vertex (0, 0, 1)
        >>> front, centres, turns = iris_model_points(np.concatenate([ball, ball]), [np.arange(6), np.arange(6, 12)],
        ...                                           ["eyeLookOut_L", "eyeLookDown_R"], angle=0.5)
        >>> front[1].tolist(), (np.round(centres[1], 6) + 0.0).tolist(), turns.tolist()
        ([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [[[0.0, 0.0], [0.5, 0.0]], [[0.0, 0.5], [0.0, 0.0]]])
    """
    neutral = np.asarray(neutral, np.float64)
    front = np.zeros((2, 3))
    centres = np.zeros((2, 3))
    for e, idx in enumerate(eyeballs):
        ball = neutral[np.asarray(idx)]
        if len(ball) < 4:
            raise ValueError(f"eyeball {IRIS_EYEBALLS[e]}: expected at least 4 vertices, found {len(ball)}")
        a = np.concatenate([2.0 * ball, np.ones((len(ball), 1))], 1)  # |x|^2 = 2 c.x + (r^2 - |c|^2)
        centres[e] = np.linalg.lstsq(a, (ball ** 2).sum(1), rcond=None)[0][:3]
        front[e] = ball[np.argmax(ball[:, 2])]
    return front, centres, eye_turns(names, angle)


IRIS_FRONT_FROM_CORNERS = np.array([[-0.0132, 0.0413, 0.1149], [0.0132, 0.0413, 0.1149]])
"""Iris centre at weight 0 of eye 0 (the subject's right) and eye 1, from its eye's corner midpoint
(`IRIS_CORNERS_68`), in eye distances (the 68 points' eye centres' distance), model frame: the ICT
mean head's eyeball front vertices (`iris_model_points` on its neutral; eye distance 6.513 cm)."""

IRIS_CENTRE_FROM_CORNERS = np.array([[0.0024, 0.0407, -0.1353], [-0.0024, 0.0407, -0.1353]])
"""Eyeball centre of rotation of eye 0 and eye 1 from its eye's corner midpoint, eye distances,
model frame: the ICT mean head's (least-squares spheres; radius 0.2507 eye distances)."""


def iris_model_points_at_corners(neutral: np.ndarray, landmarks: np.ndarray, names: list[str], *,
                                 angle: float = EYE_RANGE_RAD) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model's two eyes for `iris_points`, placed from its eye corners as on the mean head.

    A fitted identity moves the eyeballs where no landmark sees them: on skimage's astronaut
    (identity norm 12) they sat 0.06-0.07 eye distances lateral and 0.07 behind where the mean
    head's would be, and the fit read that as a look of 0.9-1.0 to one side. The eyes are
    therefore placed at the mean head's offsets from the model's own eye corners
    (`IRIS_FRONT_FROM_CORNERS`, `IRIS_CENTRE_FROM_CORNERS`), scaled by its eye distance. Over
    identities drawn from the prior (N(0, 1)) the eyeball fronts' own offsets from the corners
    spread by 0.009-0.011 eye distances (std), about 0.08 of a full look.

    Args:
        neutral: (V, 3) the model's neutral (identity applied), cm, model frame.
        landmarks: (68,) the Multi-PIE landmark vertices.
        names: the K expression names.
        angle: eye rotation of a full shape, radians.
    Returns:
        front (2, 3) cm, centres (2, 3) cm and turns (K, 2, 2) radians per unit weight, as
        `iris_model_points`.
    """
    points = np.asarray(neutral, np.float64)[np.asarray(landmarks)]
    eye_distance = float(np.linalg.norm(points[36:42].mean(0) - points[42:48].mean(0)))
    mid = points[IRIS_CORNERS_68].mean(1)  # (2, 3)
    return (mid + eye_distance * IRIS_FRONT_FROM_CORNERS, mid + eye_distance * IRIS_CENTRE_FROM_CORNERS,
            eye_turns(names, angle))


def iris_points(front: Tensor, centres: Tensor, turns: Tensor, weights: Tensor) -> tuple[Tensor, Tensor]:
    """The iris centres at the weights and their derivatives in the weights, model frame.

    `p_e(w) = c_e + R_y(yaw_e) R_x(pitch_e) (f_e - c_e)` with `(yaw_e, pitch_e) = sum_k w_k turns[k, e]`.

    Args:
        front: (2, 3) front vertices, cm; centres: (2, 3) cm; turns: (K, 2, 2) radians per unit
            weight (`iris_model_points`).
        weights: (B, K) expression weights.
    Returns:
        (B, 2, 3) iris centres, cm, and (B, 2, K, 3) d p / d w, cm per unit weight.
    """
    angles = torch.einsum("bk,ked->bed", weights, turns.to(weights.dtype))  # (B, 2, 2)
    zero = torch.zeros_like(angles[..., 0])
    rot_y = axis_angle_to_rotmat(torch.stack([zero, angles[..., 0], zero], -1))  # (B, 2, 3, 3)
    rot_x = axis_angle_to_rotmat(torch.stack([angles[..., 1], zero, zero], -1))
    v = front.to(weights.dtype) - centres.to(weights.dtype)
    vx = (rot_x @ v[None, :, :, None])[..., 0]  # R_x v, (B, 2, 3)
    turned = (rot_y @ vx[..., None])[..., 0]
    e_x = torch.tensor([1.0, 0.0, 0.0], dtype=weights.dtype, device=weights.device)
    e_y = torch.tensor([0.0, 1.0, 0.0], dtype=weights.dtype, device=weights.device)
    d_yaw = torch.linalg.cross(e_y.expand_as(turned), turned)
    d_pitch = (rot_y @ torch.linalg.cross(e_x.expand_as(vx), vx)[..., None])[..., 0]
    t = turns.to(weights.dtype)
    deriv = d_yaw[:, :, None] * t[None, :, :, 0].permute(0, 2, 1)[..., None] \
        + d_pitch[:, :, None] * t[None, :, :, 1].permute(0, 2, 1)[..., None]
    return centres.to(weights.dtype) + turned, deriv


def posed_anchor_points(neutral: Tensor, deltas: Tensor, weights: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """World positions of anchored surface points of the posed head.

    Args:
        neutral: (B, C, L, 3) anchor points of the model's neutral (identity included), cm.
        deltas: (B, C, L, K, 3) the expression shapes at the anchors, cm per unit weight.
        weights: (B, K) expression weights.
        rot: (B, 3, 3) model-to-world rotation; trans: (B, 3) cm.
    Returns:
        (B, C, L, 3) world points, cm.
    """
    local = neutral + torch.einsum("bk,bclkd->bcld", weights, deltas)
    return local @ rot[:, None].transpose(-1, -2) + trans[:, None, None, :]


def project_views(points: Tensor, world_to_camera: Tensor, intrinsics: Tensor, distortion: Tensor | None) -> Tensor:
    """(B, C, L, 3) world points -> (B, C, L, 2) pixels of camera c (`nodes.geometry.camera`).

    `world_to_camera` (C, 4, 4), `intrinsics` (C, 4), `distortion` (C, 2) or None.
    """
    return project_points_torch(points, world_to_camera[None], intrinsics[None],
                                None if distortion is None else distortion[None])


def project_views_jacobian(points: Tensor, world_to_camera: Tensor, intrinsics: Tensor,
                           distortion: Tensor | None) -> tuple[Tensor, Tensor]:
    """`project_views` and its derivative in the world point, by hand (pinhole + radial k1, k2).

    Args:
        points: (B, C, L, 3) world points, cm; world_to_camera (C, 4, 4); intrinsics (C, 4);
            distortion (C, 2) or None.
    Returns:
        (B, C, L, 2) pixels and (B, C, L, 2, 3) d pixel / d world point, pixels per cm.
    """
    rot = world_to_camera[:, :3, :3]  # (C, 3, 3)
    cam = points @ rot.transpose(-1, -2) + world_to_camera[:, None, :3, 3]
    z = cam[..., 2]
    inv = 1.0 / z
    x, y = cam[..., 0] * inv, cam[..., 1] * inv
    zero = torch.zeros_like(z)
    dx = torch.stack([inv, zero, -x * inv], -1)  # d x / d cam, (B, C, L, 3)
    dy = torch.stack([zero, inv, -y * inv], -1)
    if distortion is not None:
        k1, k2 = distortion[:, None, 0], distortion[:, None, 1]  # (C, 1)
        r2 = x * x + y * y
        factor = 1.0 + r2 * (k1 + k2 * r2)
        slope = 2.0 * (k1 + 2.0 * k2 * r2)  # d factor / d (x or y), over x or y
        dr2 = x[..., None] * dx + y[..., None] * dy  # (1/2) d r2 / d cam
        dx, dy = (factor[..., None] * dx + (x * slope)[..., None] * dr2,
                  factor[..., None] * dy + (y * slope)[..., None] * dr2)
        x, y = x * factor, y * factor
    fx, fy, cx, cy = (intrinsics[:, None, k] for k in range(4))  # (C, 1)
    pix = torch.stack([fx * x + cx, fy * y + cy], -1)
    jac = torch.stack([fx[..., None] * dx, fy[..., None] * dy], -2) @ rot[:, None]  # (B, C, L, 2, 3)
    return pix, jac


def landmark_energy(predicted: Tensor, target: Tensor, scale: Tensor, weights: Tensor, *,
                    edge_weight: float = 1.0) -> Tensor:
    """E1 + mu E2 of the module docstring, per frame.

    Args:
        predicted: (B, C, L, 2) render landmarks q, image pixels (the 68 Multi-PIE points
            first; the edge term is on those).
        target: (B, C, L, 2) plate landmarks p*, image pixels (rows of unseen views: any finite value).
        scale: (B, C) 256 / crop side, 0 for a view that did not see the face.
        weights: (L,) or (B, C, L) per-landmark weights W.
        edge_weight: mu of the edge term (0 = off); an edge counts when both its points have weight > 0.
    Returns:
        (B,) energy in squared 256-crop pixels.
    """
    r = (target - predicted) * scale[..., None, None]
    w = weights if weights.ndim == 3 else weights.expand(r.shape[:3])
    e = (w * (r * r).sum(-1)).sum((-1, -2))
    if edge_weight > 0 and r.shape[2] >= 68:  # the 68 Multi-PIE points come first
        a, b = EDGES_68[:, 0], EDGES_68[:, 1]
        de = r[:, :, b] - r[:, :, a]
        ew = ((w[..., a] > 0) & (w[..., b] > 0)).to(r.dtype)
        e = e + edge_weight * (ew * (de * de).sum(-1)).sum((-1, -2))
    return e
