"""Features of secondary dynamics (Zoss et al. 2020, sections 5.1 and 6.1), as numpy functions.

Conventions: `skull` matrices are skull-to-world `T(t)` (F, 4, 4) float64; positions in cm;
velocities in cm/s; `fps` is the capture's frame rate. Rigid maps are applied elementwise (no
batched BLAS), so a frame's result never depends on which other frames are computed with it.

- Skull velocity (eq. 2): `b_dot_j(t) = (I - T(t)^-1 T(t-1)) b_j * fps` for skull-frame
  landmarks `b_j`; skin velocity (eq. 4): `x_dot_i(t) = (T(t)^-1 x_i(t) - T(t-1)^-1 x_i(t-1)) * fps`.
  Both are backward differences; frame 0 repeats frame 1.
- Windows: the paper stacks the velocities of frames t-w..t+w (w = 10 at 128 fps). To use one
  network at any frame rate, the window is taken at a fixed feature rate `feature_fps`:
  sample k (k = -w..w) is the velocity at fractional frame `t + k fps / feature_fps`,
  interpolated with Catmull-Rom weights (exact when fps == feature_fps: the paper's feature).
  Frames beyond the sequence repeat its end frames. `window_reach` frames on each side are read.
- Quasistatic target (eq. 5): `y_i(t) = T(t) mean_{k=t-w..t+w} T(k)^-1 x_i(k)` (end frames
  repeated) and the dynamic offset (eq. 6) `dx_i(t) = T(t)^-1 (x_i(t) - y_i(t))` in the skull frame.
- Stretch (eq. 8): `s_i(t) = ((|D_u y(t)| - |D_u y(0)|) / |D_u y(0)|, same for v)` with `D_u y`
  the difference between the stencil vertices on either side of sample i along its u axis
  (tangent projection of the skull's x axis) and v = n x u, about `spacing_cm` apart.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = [
    "apply_rigid_elementwise", "rotate_elementwise", "stabilize_points", "skull_velocity",
    "skin_velocity", "window_weights", "window_reach", "window_gather", "skull_descriptor",
    "skin_descriptor", "moving_average_target", "dynamic_offsets", "stretch_stencil",
    "surface_stretch", "select_samples", "skull_landmarks", "segment_margin_mask", "training_mask",
    "no_training_rows",
]


def rotate_elementwise(rotations: np.ndarray, vectors: np.ndarray) -> np.ndarray:
    """Return `R @ v` per frame, computed with elementwise products (float64).

    Args:
        rotations: (F, 3, 3).
        vectors: (F, N, 3).
    Returns:
        (F, N, 3) float64.
    """
    r = np.asarray(rotations, np.float64)[:, None]  # (F, 1, 3, 3)
    v = np.asarray(vectors, np.float64)
    return (r[..., 0] * v[..., 0:1] + r[..., 1] * v[..., 1:2] + r[..., 2] * v[..., 2:3])


def apply_rigid_elementwise(matrices: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return `R @ x + t` per frame (float64, elementwise).

    Args:
        matrices: (F, 4, 4) rigid transforms.
        points: (F, N, 3), cm.
    Returns:
        (F, N, 3) float64, cm.
    """
    m = np.asarray(matrices, np.float64)
    return rotate_elementwise(m[:, :3, :3], points) + m[:, None, :3, 3]


def _inverse(matrices: np.ndarray) -> np.ndarray:
    m = np.asarray(matrices, np.float64)
    out = np.zeros_like(m)
    rt = np.swapaxes(m[:, :3, :3], 1, 2)
    out[:, :3, :3] = rt
    out[:, :3, 3] = -rotate_elementwise(rt, m[:, None, :3, 3])[:, 0]
    out[:, 3, 3] = 1.0
    return out


def stabilize_points(points: np.ndarray, skull: np.ndarray) -> np.ndarray:
    """Return `T(t)^-1 x(t)`: world points in the skull frame.

    Args:
        points: (F, N, 3) world positions, cm.
        skull: (F, 4, 4) skull-to-world.
    Returns:
        (F, N, 3) float64, cm.
    """
    return apply_rigid_elementwise(_inverse(skull), points)


def _check(name: str, value: np.ndarray, shape: str, ok: bool) -> None:
    if not ok:
        raise ValueError(f"{name}: expected shape {shape}, found {np.shape(value)}")


def skull_velocity(skull: np.ndarray, landmarks: np.ndarray, fps: float) -> np.ndarray:
    """Canonical velocities of skull landmarks (eq. 2), `(b - T(t)^-1 T(t-1) b) * fps`.

    Args:
        skull: (F, 4, 4) skull-to-world, F >= 2.
        landmarks: (L, 3) skull-frame points, cm.
        fps: frames per second.
    Returns:
        (F, L, 3) float64, cm/s, in the skull frame of frame t; frame 0 repeats frame 1.
    """
    skull = np.asarray(skull, np.float64)
    _check("skull", skull, "(F, 4, 4) with F >= 2", skull.ndim == 3 and skull.shape[1:] == (4, 4)
           and len(skull) >= 2)
    inv = _inverse(skull[1:])
    step = np.einsum("fij,fjk->fik", inv, skull[:-1], optimize=False)  # T(t)^-1 T(t-1)
    b = np.broadcast_to(np.asarray(landmarks, np.float64), (len(step),) + np.shape(landmarks))
    vel = (b - apply_rigid_elementwise(step, b)) * fps
    return np.concatenate([vel[:1], vel], axis=0)


def skin_velocity(points: np.ndarray, skull: np.ndarray, fps: float) -> np.ndarray:
    """Stabilized skin velocities (eq. 4), `(T(t)^-1 x(t) - T(t-1)^-1 x(t-1)) * fps`.

    Args:
        points: (F, N, 3) world positions, cm, F >= 2.
        skull: (F, 4, 4) skull-to-world.
        fps: frames per second.
    Returns:
        (F, N, 3) float64, cm/s, skull frame; frame 0 repeats frame 1.
    """
    _check("points", points, "(F, N, 3) with F >= 2", np.ndim(points) == 3 and len(points) >= 2)
    local = stabilize_points(points, skull)
    vel = (local[1:] - local[:-1]) * fps
    return np.concatenate([vel[:1], vel], axis=0)


def window_weights(window: int, fps: float, feature_fps: float) -> tuple[np.ndarray, np.ndarray]:
    """Catmull-Rom taps of the resampled window.

    Sample k (k = -window..window) sits at fractional frame offset `q_k = k fps / feature_fps`.

    Returns:
        offsets (K, 4) int64 frame offsets and weights (K, 4) float64 (rows sum to 1),
        K = 2 window + 1.
    """
    q = np.arange(-window, window + 1) * (fps / feature_fps)
    base = np.floor(q + 1e-9)
    tau = np.clip(q - base, 0.0, 1.0)
    tau = np.where(tau < 1e-9, 0.0, tau)
    t2, t3 = tau * tau, tau * tau * tau
    weights = np.stack([(-t3 + 2 * t2 - tau) / 2, (3 * t3 - 5 * t2 + 2) / 2,
                        (-3 * t3 + 4 * t2 + tau) / 2, (t3 - t2) / 2], axis=1)
    offsets = base.astype(np.int64)[:, None] + np.arange(-1, 3)[None]
    return offsets, weights


def window_reach(window: int, fps: float, feature_fps: float) -> int:
    """Frames read on each side of a frame by the windowed descriptors (velocity included)."""
    return int(math.ceil(window * fps / feature_fps - 1e-9)) + 3


def window_gather(signal: np.ndarray, centers: np.ndarray, window: int, fps: float,
                  feature_fps: float, columns: np.ndarray | None = None) -> np.ndarray:
    """Resampled windows of a per-frame signal around frames `centers`.

    Args:
        signal: (F, N, 3) per-frame values (e.g. velocities).
        centers: (R,) int frame indices.
        window: half-size w (samples at the feature rate).
        fps: the signal's frame rate; feature_fps: the window's sample rate.
        columns: (R,) int indices into axis 1 (one column per row), or None for all columns.
    Returns:
        (R, K, 3) when `columns` is given, else (R, K, N, 3); float64; K = 2 w + 1.
    """
    offsets, weights = window_weights(window, fps, feature_fps)
    frames = np.clip(np.asarray(centers)[:, None, None] + offsets[None], 0, len(signal) - 1)
    if columns is None:
        taps = signal[frames]  # (R, K, 4, N, 3)
        w = weights[None, :, :, None, None]
    else:
        taps = signal[frames, np.asarray(columns)[:, None, None]]  # (R, K, 4, 3)
        w = weights[None, :, :, None]
    out = taps[:, :, 0] * w[:, :, 0]
    for m in range(1, 4):
        out = out + taps[:, :, m] * w[:, :, m]
    return out


def skull_descriptor(skull: np.ndarray, landmarks: np.ndarray, fps: float, *, window: int = 10,
                     feature_fps: float | None = None) -> np.ndarray:
    """The head motion history B(t) (eq. 1): windowed canonical landmark velocities.

    Args:
        skull: (F, 4, 4) skull-to-world.
        landmarks: (L, 3) skull-frame points (5 in the paper), cm.
        fps: frames per second of the capture.
        window: half-size w_b.
        feature_fps: rate of the window samples (None = fps: the paper's feature).
    Returns:
        (F, L * K * 3) float32, cm/s, ordered (landmark, window sample, xyz).
    """
    feature_fps = fps if feature_fps is None else feature_fps
    vel = skull_velocity(skull, landmarks, fps)  # (F, L, 3)
    win = window_gather(vel, np.arange(len(vel)), window, fps, feature_fps)  # (F, K, L, 3)
    return np.ascontiguousarray(np.swapaxes(win, 1, 2).reshape(len(vel), -1), np.float32)


def skin_descriptor(points: np.ndarray, skull: np.ndarray, fps: float, *, window: int = 10,
                    feature_fps: float | None = None) -> np.ndarray:
    """The skin motion histories X_i(t) (eq. 3) of every point.

    Args:
        points: (F, N, 3) world positions of the samples, cm.
        skull: (F, 4, 4) skull-to-world.
        fps, window, feature_fps: as `skull_descriptor`.
    Returns:
        (F, N, K * 3) float32, cm/s, ordered (window sample, xyz).
    """
    feature_fps = fps if feature_fps is None else feature_fps
    vel = skin_velocity(points, skull, fps)
    win = window_gather(vel, np.arange(len(vel)), window, fps, feature_fps)  # (F, K, N, 3)
    return np.ascontiguousarray(np.swapaxes(win, 1, 2).reshape(len(vel), vel.shape[1], -1), np.float32)


def moving_average_target(points: np.ndarray, skull: np.ndarray, *, window: int = 10) -> np.ndarray:
    """The quasistatic target of eq. 5: centred moving average of stabilized positions.

    Args:
        points: (F, N, 3) world positions, cm.
        skull: (F, 4, 4) skull-to-world.
        window: half-size w (frames); end frames are repeated.
    Returns:
        (F, N, 3) float64 world positions, cm.
    """
    local = stabilize_points(points, skull)
    f = len(local)
    padded = np.concatenate([np.repeat(local[:1], window, 0), local,
                             np.repeat(local[-1:], window, 0)], axis=0)
    total = np.zeros_like(local)
    for shift in range(2 * window + 1):
        total += padded[shift:shift + f]
    return apply_rigid_elementwise(skull, total / (2 * window + 1))


def dynamic_offsets(points: np.ndarray, quasistatic: np.ndarray, skull: np.ndarray) -> np.ndarray:
    """Dynamic offsets of eq. 6, `T(t)^-1 (x(t) - y(t))` (a direction: rotation only).

    Args:
        points: (F, N, 3) world positions, cm.
        quasistatic: (F, N, 3) world positions, cm.
        skull: (F, 4, 4) skull-to-world.
    Returns:
        (F, N, 3) float64, cm, skull frame.
    """
    rt = np.swapaxes(np.asarray(skull, np.float64)[:, :3, :3], 1, 2)
    return rotate_elementwise(rt, np.asarray(points, np.float64) - np.asarray(quasistatic, np.float64))


def stretch_stencil(rest: np.ndarray, samples: np.ndarray, *, spacing_cm: float = 0.2,
                    candidates: int = 24) -> np.ndarray:
    """Pick, for each sample, the vertices on either side of it along u and v.

    u is the skull x axis projected onto the tangent plane (normal from the PCA of the 12
    nearest points), v = n x u. Among the `candidates` nearest vertices, the one on the +u side
    maximises `cos(d, u) - 0.3 | |d| - spacing | / spacing` (likewise -u, +v, -v).

    Args:
        rest: (V, 3) rest positions, cm.
        samples: (N,) vertex indices.
        spacing_cm: preferred distance to each stencil vertex (2 mm in the paper).
        candidates: nearest vertices considered.
    Returns:
        (N, 4) int64 vertex indices (u+, u-, v+, v-).
    """
    from scipy.spatial import cKDTree

    rest = np.asarray(rest, np.float64)
    count = min(candidates + 1, len(rest))
    _, idx = cKDTree(rest).query(rest[samples], count)
    near = rest[idx[:, 1:]] - rest[samples][:, None]  # (N, C, 3)
    local = near[:, :min(12, count - 1)]
    cov = np.einsum("nci,ncj->nij", local, local)
    normal = np.linalg.eigh(cov)[1][:, :, 0]
    u = np.array([1.0, 0.0, 0.0]) - normal[:, 0:1] * normal
    bad = np.linalg.norm(u, axis=1) < 1e-3
    u[bad] = (np.array([0.0, 1.0, 0.0]) - normal[bad, 1:2] * normal[bad])
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v = np.cross(normal, u)
    dist = np.linalg.norm(near, axis=2)
    unit = near / np.maximum(dist, 1e-9)[..., None]
    penalty = 0.3 * np.abs(dist - spacing_cm) / spacing_cm
    out = np.empty((len(samples), 4), np.int64)
    for col, axis in enumerate((u, -u, v, -v)):
        score = (unit * axis[:, None]).sum(-1) - penalty
        out[:, col] = idx[np.arange(len(samples)), 1 + np.argmax(score, axis=1)]
    return out


def surface_stretch(points: np.ndarray, neutral: np.ndarray, stencil: np.ndarray) -> np.ndarray:
    """Surface stretch S(t) of eq. 8 along u and v against the neutral.

    Args:
        points: (F, V, 3) positions (any rigid frame per frame: lengths are invariant), cm.
        neutral: (V, 3) neutral positions, cm.
        stencil: (N, 4) from `stretch_stencil`.
    Returns:
        (F, N, 2) float32, relative length change (0 = as the neutral).
    """
    p = np.asarray(points, np.float64)
    n = np.asarray(neutral, np.float64)
    out = []
    for a, b in ((0, 1), (2, 3)):
        d = p[:, stencil[:, a]] - p[:, stencil[:, b]]
        d0 = np.linalg.norm(n[stencil[:, a]] - n[stencil[:, b]], axis=-1)
        out.append((np.sqrt((d * d).sum(-1)) - d0) / np.maximum(d0, 1e-9))
    return np.stack(out, axis=-1).astype(np.float32)


def select_samples(rest: np.ndarray, count: int, region: np.ndarray | None = None) -> np.ndarray:
    """Farthest-point samples of the region (first pick nearest its centroid).

    Args:
        rest: (V, 3) positions, cm.
        count: number of samples (clipped to the region's size).
        region: (M,) vertex indices, or None for all.
    Returns:
        (min(count, M),) int64 vertex indices, ascending.
    """
    from ..geometry.sampling import farthest_point_sampling

    region = np.arange(len(rest)) if region is None else np.asarray(region, np.int64)
    pts = np.asarray(rest, np.float64)[region]
    first = int(((pts - pts.mean(0)) ** 2).sum(1).argmin())
    return np.sort(region[farthest_point_sampling(pts, count, first=first)])


def skull_landmarks(rest: np.ndarray) -> np.ndarray:
    """Five skull-frame landmarks spread over the head: centre, left, right, top, front.

    Centre of the bounding box plus 0.4 x its extent along -x, +x, +y and +z.

    Args:
        rest: (V, 3) rest positions, cm (skull frame).
    Returns:
        (5, 3) float64, cm.
    """
    lo, hi = np.asarray(rest, np.float64).min(0), np.asarray(rest, np.float64).max(0)
    c, e = (lo + hi) / 2, (hi - lo)
    return np.stack([c, c - [0.4 * e[0], 0, 0], c + [0.4 * e[0], 0, 0], c + [0, 0.4 * e[1], 0],
                     c + [0, 0, 0.4 * e[2]]])


def segment_margin_mask(segments: np.ndarray | None, count: int, margin: int) -> np.ndarray:
    """True for frames at least `margin` frames away from every segment change.

    Args:
        segments: (F,) segment labels, or None (one segment).
        count: F.
        margin: frames.
    Returns:
        (F,) bool.
    """
    ok = np.ones(count, bool)
    if segments is None:
        return ok
    labels = np.asarray(segments).reshape(-1)
    changes = np.flatnonzero(labels[1:] != labels[:-1]) + 1  # first frame of each new segment
    frames = np.arange(count)
    for c in changes:
        ok &= (frames < c - margin) | (frames >= c + margin)
    return ok


def training_mask(segments: np.ndarray | None, count: int, margin: int) -> np.ndarray:
    """The frames a trainer draws rows from: at least `margin` frames from every segment change
    and from both ends (the descriptor window's reach, and the target's half-width).

    Args:
        segments: (F,) segment labels, or None (one segment).
        count: F.
        margin: frames, >= 1.
    Returns:
        (F,) bool; all False when F <= 2 * margin.
    """
    ok = segment_margin_mask(segments, count, margin)
    ok[:margin] = ok[-margin:] = False
    return ok


def no_training_rows(margins: list[int], lengths: list[int], noun: str = "capture(s)") -> str:
    """The message of a training set with no frame to draw a row from (`training_mask` all False)."""
    return (f"expected frames at least {'/'.join(map(str, sorted(set(margins))))} frames away from segment "
            f"changes and ends (the descriptor window's reach and the target's half-width), found none in "
            f"{len(lengths)} {noun} of {list(lengths)} frames")
