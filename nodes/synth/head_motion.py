"""Synthetic rigid head motion: smooth random or scripted (nod, turn, walk) curves.

Angles are extrinsic XYZ Euler angles in radians (x = pitch, y = yaw, z = roll for the ICT
head, which is y up and z out of the face): `R = Rz(angle_z) @ Ry(angle_y) @ Rx(angle_x)`,
the same as `scipy.spatial.transform.Rotation.from_euler("xyz", angles)`. A pose rotates
about a pivot `p` (cm, skull frame) and then translates by `t`:
`x_world = R (x_skull - p) + p + t`, i.e. `M = [[R, p + t - R p], [0, 0, 0, 1]]`.
"""

from __future__ import annotations

import numpy as np

from ..geometry.rotation import euler_to_rotmat

__all__ = ["MOTIONS", "euler_xyz_to_rotmat", "poses_to_matrices", "smooth_curves",
           "head_motion_curves", "default_pivot"]

MOTIONS = ("smooth", "nod", "turn", "walk", "none")
"""Known head-motion kinds."""


def euler_xyz_to_rotmat(angles: np.ndarray) -> np.ndarray:
    """Return R = Rz(c) Ry(b) Rx(a) for angles (a, b, c) (extrinsic XYZ, radians): the head
    motion's convention of `nodes.geometry.rotation.euler_to_rotmat`.

    Args:
        angles: (..., 3) radians.
    Returns:
        (..., 3, 3) float64 rotation matrices acting on column vectors.

    Example:
        >>> np.round(euler_xyz_to_rotmat(np.array([0.0, 0.0, np.pi / 2])) @ [1, 0, 0], 6).tolist()
        [0.0, 1.0, 0.0]
    """
    return euler_to_rotmat(angles, "xyz")


def poses_to_matrices(angles: np.ndarray, translations: np.ndarray, pivot: np.ndarray) -> np.ndarray:
    """Build skull-to-world matrices rotating about `pivot` then translating.

    Args:
        angles: (F, 3) extrinsic XYZ Euler angles, radians.
        translations: (F, 3) cm.
        pivot: (3,) cm, skull frame.
    Returns:
        (F, 4, 4) float64 with `x_world = R (x - pivot) + pivot + t`.
    """
    rot = euler_xyz_to_rotmat(angles)
    pivot = np.asarray(pivot, dtype=np.float64)
    out = np.zeros(rot.shape[:-2] + (4, 4))
    out[..., :3, :3] = rot
    out[..., :3, 3] = pivot + np.asarray(translations, np.float64) - rot @ pivot
    out[..., 3, 3] = 1.0
    return out


def default_pivot(neutral: np.ndarray) -> np.ndarray:
    """A pivot near the top of the neck for a y-up, z-forward head (heuristic, from the bbox).

    x at the bbox centre, y at 45 % of the height from the bottom, z at 40 % of the depth from
    the back: (0, -4.1, -0.3) cm for the whole ICT head (near the atlanto-occipital joint,
    below and behind the ears), (0, -3.5, 3.3) for its "face" region.

    Args:
        neutral: (V, 3) cm.
    Returns:
        (3,) float64 cm.
    """
    lo, hi = neutral.min(axis=0).astype(np.float64), neutral.max(axis=0).astype(np.float64)
    return lo + np.array([0.5, 0.45, 0.4]) * (hi - lo)


def _peak_normalize(curves: np.ndarray, amplitude: float, *, per_column: bool = True) -> np.ndarray:
    """Scale so that the max |value| (of each column, or of all) is `amplitude` (zeros stay 0)."""
    peak = np.abs(curves).max(axis=0 if per_column else None, initial=0.0)
    return curves * np.where(peak > 0, amplitude / np.where(peak > 0, peak, 1.0), 0.0)


def smooth_curves(rng: np.random.Generator, num_frames: int, fps: float, columns: int,
                  max_frequency_hz: float, components: int = 6) -> np.ndarray:
    """Sums of random sinusoids (frequencies in [0.02, max] Hz, 1/f amplitudes), peak 1.

    Returns:
        (F, columns) float64, each column's max |value| = 1 (for F > 0).
    """
    t = np.arange(num_frames) / fps
    freq = rng.uniform(0.02, max(max_frequency_hz, 0.021), (components, columns))
    phase = rng.uniform(0.0, 2 * np.pi, (components, columns))
    amp = rng.uniform(0.5, 1.0, (components, columns)) / (1.0 + freq / 0.2)
    curves = (amp * np.sin(2 * np.pi * freq * t[:, None, None] + phase)).sum(axis=1)
    return _peak_normalize(curves - curves.mean(axis=0), 1.0)


def _ramps(rng: np.random.Generator, num_frames: int, fps: float, hold_s: tuple[float, float],
           move_s: tuple[float, float]) -> np.ndarray:
    """Piecewise-smooth moves between random targets in [-1, 1] (hold, then smoothstep move)."""
    t = np.arange(num_frames) / fps
    out = np.zeros(num_frames)
    time, value = 0.0, 0.0
    end = t[-1] if num_frames else 0.0
    while time < end:
        time += rng.uniform(*hold_s)
        move = rng.uniform(*move_s)
        target = rng.uniform(-1.0, 1.0)
        x = np.clip((t - time) / move, 0.0, 1.0)
        out += (target - value) * x * x * (3 - 2 * x)
        value, time = target, time + move
    return out


def head_motion_curves(num_frames: int, *, seed: int | np.random.SeedSequence, fps: float = 30.0,
                       motion: str = "smooth", rotation_deg: float = 10.0,
                       translation_cm: float = 2.0, max_frequency_hz: float = 0.5
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Generate head rotation angles and translations for a whole performance.

    Kinds:
        smooth: sums of random sinusoids up to `max_frequency_hz` on all 6 axes.
        nod: pitch (x) oscillation at 0.5-1.2 Hz in bouts, small vertical translation.
        turn: yaw (y) moves between random targets (hold 0.5-2 s, move 0.4-1.2 s), a little
            pitch and roll, small sideways translation.
        walk: vertical bob at a step rate of 1.6-2.2 Hz, lateral sway and roll at half of it.
        none: identity.
    For "smooth", each axis peaks at exactly `rotation_deg` (max |angle| over the sequence)
    and each translation axis at `translation_cm`; scripted kinds keep their axis ratios and
    their main axis peaks at those values.

    Args:
        num_frames: F.
        seed: int or SeedSequence.
        fps: frames per second.
        motion: one of MOTIONS.
        rotation_deg: peak |angle| per axis, degrees.
        translation_cm: peak |translation| per axis, cm.
        max_frequency_hz: highest frequency of "smooth" motion (Hz).
    Returns:
        angles (F, 3) float64 radians (extrinsic XYZ), translations (F, 3) float64 cm.
    Raises:
        ValueError: unknown `motion` (the known ones are listed) or fps <= 0.
    """
    if motion not in MOTIONS:
        raise ValueError(f"motion: expected one of {list(MOTIONS)}, found '{motion}'")
    if fps <= 0:
        raise ValueError(f"fps: expected > 0, found {fps}")
    rng = np.random.default_rng(seed)
    t = np.arange(num_frames) / fps
    rot = np.zeros((num_frames, 3))
    trans = np.zeros((num_frames, 3))
    if motion == "smooth":
        rot = smooth_curves(rng, num_frames, fps, 3, max_frequency_hz)
        trans = smooth_curves(rng, num_frames, fps, 3, max_frequency_hz)
    elif motion == "nod":
        freq = rng.uniform(0.5, 1.2)
        bouts = np.clip(_ramps(rng, num_frames, fps, (0.5, 2.0), (0.3, 0.8)) * 2.0, -1, 1)
        rot[:, 0] = np.abs(bouts) * np.sin(2 * np.pi * freq * t)
        trans[:, 1] = 0.3 * rot[:, 0]
    elif motion == "turn":
        rot[:, 1] = _ramps(rng, num_frames, fps, (0.5, 2.0), (0.4, 1.2))
        rot[:, 0] = 0.2 * smooth_curves(rng, num_frames, fps, 1, 0.3)[:, 0]
        rot[:, 2] = 0.2 * smooth_curves(rng, num_frames, fps, 1, 0.3)[:, 0]
        trans[:, 0] = 0.5 * rot[:, 1]
    elif motion == "walk":
        step = rng.uniform(1.6, 2.2)
        phase = rng.uniform(0.0, 2 * np.pi, 3)
        trans[:, 1] = np.sin(2 * np.pi * step * t + phase[0])
        trans[:, 0] = 0.5 * np.sin(np.pi * step * t + phase[1])
        rot[:, 2] = np.sin(np.pi * step * t + phase[1])
        rot[:, 0] = 0.3 * np.sin(2 * np.pi * step * t + phase[2])
    per_column = motion == "smooth"
    rot = _peak_normalize(rot, np.deg2rad(rotation_deg), per_column=per_column)
    trans = _peak_normalize(trans, translation_cm, per_column=per_column)
    return rot, trans
