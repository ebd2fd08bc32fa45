"""Synthetic plates with known truth, for the tests and benches of the fit, flow and temporal nodes.

It lives in the test tree, not in `nodes/`, because no node or graph uses it: kept in the library
it would be installed, published and part of the import graph (and of the cache keys) of the areas
that held it. The benches import it as `tests.support.synthetic` after putting the repository root
on `sys.path` (they run from a clone, as they already read `graphs/` and `tests/` files from it);
pytest finds it through the `tests` package (`tests/__init__.py`, rootdir import).

Two kinds of plates, drawn by one renderer (`render_plates`: the differentiable renderer of
`nodes.render.renderer`, no gradients):

- `random_face_parameters` + `render_truth_plates`: the bundled head with a random identity, pose,
  expression, albedo tint and lighting unlike the default, in one or more cameras
  (`orbit_camera`), with Gaussian noise; the fit's tests and benches. World frame: the first
  camera at the origin looking down +z (OpenCV: x right, y down); the head about `distance_cm`
  in front of it. The head's rotation is `R = diag(1, -1, -1) @ R_model(yaw, pitch, roll)` (the
  model's y up, z out of the face, turned to face the camera), `R_model = Ry(yaw) Rx(pitch) Rz(roll)`.
- `make_scene` + `head_motion` + `render_scene_plates`: the bundled head posed by a parameter
  sequence in the layout of `nodes.temporal.layout`, through a pinhole 55 cm in front of it with
  the default lighting and a per-vertex textured albedo (skin pores would give a real plate its
  texture; the flow needs some), over a flat grey background; the flow and temporal tests and
  benches.

The ICT head's eye shells and eyelash strips are not drawn (`nodes.render.appearance.visible_faces`).
Torch is imported inside the functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from nodegraph import Camera, FaceModel, ImageSequence
from nodes.geometry.rotation import axis_angle_to_rotmat, euler_to_rotmat

__all__ = ["LANDMARK_FIT_BLINKS", "LANDMARK_FIT_FRAMES", "landmark_fit_truth", "per_frame_landmark_fit",
           "SYNTHETIC_IDENTITY_SEED", "orbit_camera", "random_face_parameters", "render_plates",
           "render_truth_plates", "Scene", "make_scene", "head_motion", "scene_vertices", "render_scene_plates"]

SYNTHETIC_IDENTITY_SEED = 918_273
"""Seed offset of the synthetic identities (used nowhere else in the project)."""


def render_plates(vertices: Any, faces: np.ndarray, camera: Camera, albedo: Any, sh: Any, background: Any, *,
                  supersample: int = 2, frames_per_call: int = 0, max_value: float | None = None,
                  device: str = "cpu") -> np.ndarray:
    """Render a vertex sequence through one camera: the plates of both kinds of synthetic truth.

    Args:
        vertices: (F, V, 3) world positions, cm (numpy or torch; its dtype is the render's).
        faces: (T, 3) int triangles drawn.
        camera: the camera (OpenCV convention); the plates have its width and height.
        albedo: (V, 3) linear albedo per vertex.
        sh: (9, 3) SH irradiance (`nodes.render.renderer.sh_from_lights`), world frame.
        background: (3,) linear colour.
        supersample: render at s times the size and average s x s blocks.
        frames_per_call: frames rendered together (0 = all at once). The renders do not depend
            on it in theory; the callers keep the batching their saved results were made with.
        max_value: upper clamp of the values (None: only negative values are clamped, to 0).
        device: torch device of the render.
    Returns:
        (F, H, W, 3) linear RGB, the dtype of `vertices` (float32 for the callers here).
    """
    import torch

    from nodes.geometry.mesh import triangle_adjacency
    from nodes.render.renderer import render_mesh

    verts = torch.as_tensor(vertices, device=device)
    count = verts.shape[0]
    step = frames_per_call or count
    extrinsics = torch.as_tensor(camera.world_to_camera, dtype=torch.float32, device=device).expand(count, 4, 4)
    intrinsics = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy], dtype=torch.float32,
                              device=device).expand(count, 4)
    adjacency = triangle_adjacency(faces)
    albedo_t = torch.as_tensor(albedo, device=device)[None]
    sh_t = torch.as_tensor(sh, device=device)[None]
    background_t = torch.as_tensor(background, device=device)
    parts = []
    with torch.no_grad():
        for start in range(0, count, step):
            batch = slice(start, start + step)
            out = render_mesh(verts[batch], faces, extrinsics[batch], intrinsics[batch], camera.height, camera.width,
                              albedo=albedo_t, sh=sh_t, background=background_t, supersample=supersample,
                              adjacency=adjacency)
            parts.append(out.image.clamp(0.0, max_value).cpu().numpy())
    return np.concatenate(parts)


def orbit_camera(base: Camera, yaw_deg: float, centre_cm: Sequence[float], name: str = "cam1") -> Camera:
    """A copy of `base` moved on a circle about `centre_cm` (world) by `yaw_deg` about the world's y.

    The camera keeps looking at the centre; positive yaw moves it to the camera's right (+x).
    """
    centre = np.asarray(centre_cm, np.float64)
    turn = axis_angle_to_rotmat(np.array([0.0, -np.deg2rad(yaw_deg), 0.0]))
    e0 = base.world_to_camera
    rot = e0[:3, :3] @ turn.T  # camera axes turned about the centre
    cam_centre = centre + turn @ (base.camera_to_world()[:3, 3] - centre)
    e = np.eye(4)
    e[:3, :3] = rot
    e[:3, 3] = -rot @ cam_centre
    return Camera(fx=base.fx, fy=base.fy, cx=base.cx, cy=base.cy, width=base.width, height=base.height,
                  world_to_camera=e, k1=base.k1, k2=base.k2, name=name)


def random_face_parameters(model: FaceModel, frames: int, seed: int, *, max_yaw_deg: float = 30.0,
                           max_pitch_deg: float = 10.0, max_roll_deg: float = 5.0,
                           distance_cm: float = 55.0, max_jaw: float = 0.6) -> dict[str, Any]:
    """Random identity (one), poses and expressions (per frame) and appearance.

    Returns:
        dict: identity (I,), rotation (F, 3, 3), translation (F, 3) cm, weights (F, K)
        (jawOpen in [0, max_jaw] and two mouth shapes in [0, 0.4] per frame), yaw_deg (F,),
        albedo_tint (3,), light dict (ambient (3,), direction (3,), intensity), background (3,).
    """
    rng = np.random.default_rng(SYNTHETIC_IDENTITY_SEED + seed)
    identity = rng.normal(0.0, 1.0, model.identity_deltas.shape[0]).astype(np.float32)
    yaw = rng.uniform(-max_yaw_deg, max_yaw_deg, frames)
    pitch = rng.uniform(-max_pitch_deg, max_pitch_deg, frames)
    roll = rng.uniform(-max_roll_deg, max_roll_deg, frames)
    r_model = euler_to_rotmat(np.deg2rad(np.stack([yaw, pitch, roll], 1)), "YXZ")
    rotation = np.diag([1.0, -1.0, -1.0])[None] @ r_model
    translation = np.stack([rng.uniform(-2, 2, frames), rng.uniform(-2, 2, frames),
                            distance_cm + rng.uniform(-3, 3, frames)], 1)
    names = model.expression_names
    weights = np.zeros((frames, len(names)), np.float32)
    weights[:, names.index("jawOpen")] = rng.uniform(0.0, max_jaw, frames)
    mouth = [i for i, n in enumerate(names) if n.startswith("mouth") and n != "mouthClose"]
    for f in range(frames):
        pick = rng.choice(mouth, 2, replace=False)
        weights[f, pick] = rng.uniform(0.0, 0.4, 2)
    light = {"ambient": rng.uniform(0.2, 0.45, 3), "direction": np.array([rng.choice([-1, 1]) * rng.uniform(0.5, 1.0),
                                                                           rng.uniform(-0.3, 0.3), 1.0]),
             "intensity": float(rng.uniform(0.5, 0.9))}
    return {"identity": identity, "rotation": rotation.astype(np.float32), "translation": translation.astype(np.float32),
            "weights": weights, "yaw_deg": yaw, "albedo_tint": rng.uniform(0.85, 1.15, 3).astype(np.float32),
            "light": light, "background": rng.uniform(0.05, 0.35, 3).astype(np.float32)}


def render_truth_plates(model: FaceModel, cameras: Sequence[Camera], truth: dict[str, Any], *, supersample: int = 2,
                        noise: float = 0.005, seed: int = 0) -> list[np.ndarray]:
    """Render the plates of `random_face_parameters` in each camera (CPU, one frame per render).

    Args:
        model: the face model the truth was drawn for.
        cameras: the cameras.
        truth: `random_face_parameters(model, ...)`.
        supersample: render at s times the size and average s x s blocks.
        noise: standard deviation of the Gaussian noise added to the [0, 1] clamped render.
        seed: seed of the noise.
    Returns:
        one (F, H, W, 3) float32 linear image array per camera, in [0, 1].
    """
    from nodes.render.appearance import default_albedo, visible_faces
    from nodes.render.renderer import sh_from_lights

    faces = visible_faces(model.faces, model.neutral.shape[0])
    verts = model.evaluate(truth["weights"], truth["identity"]) @ np.swapaxes(truth["rotation"], 1, 2) \
        + truth["translation"][:, None]
    albedo = np.clip(default_albedo(model) * truth["albedo_tint"], 0, 1)
    light = truth["light"]
    sh = sh_from_lights(light["ambient"], light["direction"], light["intensity"])
    rng = np.random.default_rng(seed)
    out = []
    for cam in cameras:
        images = render_plates(verts, faces, cam, albedo, sh, truth["background"], supersample=supersample,
                               frames_per_call=1, max_value=1.0)
        images = images + rng.normal(0.0, noise, (len(images), cam.height, cam.width, 3))
        out.append(np.clip(images, 0.0, 1.0).astype(np.float32))
    return out


@dataclass
class Scene:
    """A face model, a camera and an appearance to render plates with.

    Attributes:
        model: the face model (cm, y up, z out of the face).
        camera: the camera (OpenCV convention).
        albedo: (V, 3) float32 linear, textured.
        sh: (9, 3) float32 SH lighting.
        faces: (T, 3) int64 triangles drawn.
        background: (3,) linear grey.
    """

    model: FaceModel
    camera: Camera
    albedo: np.ndarray
    sh: np.ndarray
    faces: np.ndarray
    background: np.ndarray


def read_plates(plates: np.ndarray) -> tuple[ImageSequence, Any, Any]:
    """(F, H, W, 3) linear plates -> the sequence, `landmarks.DetectFaces`' boxes and
    `landmarks.FaceLandmarks`' 68 points on them (what the fit nodes take as the plate's reading)."""
    from nodegraph import run_node
    from nodes.landmarks import DetectFaces, FaceLandmarks

    seq = ImageSequence(plates, colour_space="linear")
    boxes = run_node(DetectFaces, images=seq)["boxes"]
    return seq, boxes, run_node(FaceLandmarks, images=seq, boxes=boxes)["landmarks68"]


def make_scene(size: int = 96, *, region: str = "", texture: float = 0.35, seed: int = 0,
               distance_cm: float = 55.0) -> Scene:
    """Build the synthetic scene.

    Args:
        size: image width and height, pixels (the face fills about 70% of it).
        region: model region ("" = the whole head; the default albedo needs its eye groups).
        texture: relative amplitude of the per-vertex albedo noise (0 = the default albedo).
        seed: seed of the texture.
        distance_cm: camera distance in front of the face, cm.
    Returns:
        Scene.
    """
    from nodes.io.face_model import load_face_model
    from nodes.render.appearance import DEFAULT_LIGHT, default_albedo, visible_faces
    from nodes.render.renderer import sh_from_lights

    model = load_face_model(region=region)
    rng = np.random.default_rng(seed)
    albedo = default_albedo(model)
    noise = rng.uniform(-1.0, 1.0, (len(albedo), 1)).astype(np.float32)
    albedo = np.clip(albedo * (1.0 + texture * noise), 0.0, 1.0).astype(np.float32)
    faces = visible_faces(model.faces, model.neutral.shape[0])
    focal = 520.0 * size / 256.0 * (distance_cm / 55.0)
    extrinsics = np.array([[1.0, 0, 0, 0], [0, -1, 0, 1.0], [0, 0, -1, distance_cm], [0, 0, 0, 1]])
    camera = Camera(fx=focal, fy=focal, cx=(size - 1) / 2.0, cy=(size - 1) / 2.0, width=size, height=size,
                    world_to_camera=extrinsics)
    sh = sh_from_lights(DEFAULT_LIGHT["ambient"], DEFAULT_LIGHT["direction"], DEFAULT_LIGHT["intensity"])
    return Scene(model, camera, albedo, sh, faces, np.asarray(DEFAULT_LIGHT["background"], np.float32))


def head_motion(frames: int, names: list[str], *, seed: int = 0, amplitude: float = 1.0,
                mouth_frames: tuple[int, int] | None = None) -> np.ndarray:
    """A smooth head performance: (F, 6 + K) values in the standard layout.

    Rotation (rad) and translation (cm) follow sums of slow sinusoids (about 0.1 rad and 1 cm
    at amplitude 1); `jawOpen` and a smile move slowly, and within `mouth_frames` (a, b) the
    jaw opens and closes fast (0 -> 0.7 -> 0 in b - a frames).
    """
    rng = np.random.default_rng(seed)
    t = np.arange(frames, dtype=np.float64)
    values = np.zeros((frames, 6 + len(names)))
    for c, scale in enumerate([0.06, 0.12, 0.04, 0.8, 0.6, 0.8]):
        freq = rng.uniform(0.02, 0.06, 2)
        phase = rng.uniform(0, 2 * np.pi, 2)
        values[:, c] = amplitude * scale * (0.6 * np.sin(2 * np.pi * freq[0] * t + phase[0])
                                            + 0.4 * np.sin(2 * np.pi * freq[1] * t + phase[1]))
    jaw = 6 + names.index("jawOpen")
    values[:, jaw] = 0.15 + 0.1 * np.sin(2 * np.pi * 0.03 * t)
    if "mouthSmileLeft" in names:
        values[:, 6 + names.index("mouthSmileLeft")] = 0.2 + 0.15 * np.sin(2 * np.pi * 0.025 * t + 1.0)
    if mouth_frames is not None:
        a, b = mouth_frames
        s = np.clip((t - a) / max(b - a, 1), 0.0, 1.0)
        values[:, jaw] += 0.7 * np.sin(np.pi * s) ** 2
    return values.astype(np.float32)


def scene_vertices(scene: Scene, values: np.ndarray, device: str = "cpu") -> Any:
    """(F, 6 + K) standard-layout values -> (F, V, 3) torch float32 world vertices, cm."""
    import torch

    from nodes.temporal.layout import posed_vertices

    v = torch.as_tensor(np.asarray(values, np.float32), device=device)
    neutral = torch.as_tensor(scene.model.neutral, device=device)
    deltas = torch.as_tensor(scene.model.expression_deltas, device=device)
    return posed_vertices(neutral, deltas, v[:, 0:3], v[:, 3:6], v[:, 6:])


def render_scene_plates(scene: Scene, values: np.ndarray, *, supersample: int = 2,
                        device: str = "cpu") -> ImageSequence:
    """Render the plates of a standard-layout parameter sequence (all frames in one render).

    Returns:
        ImageSequence (F, H, W, 3) float32 linear RGB (negative values clamped to 0).
    """
    images = render_plates(scene_vertices(scene, values, device), scene.faces, scene.camera, scene.albedo,
                           scene.sh, scene.background, supersample=supersample, device=device)
    return ImageSequence(images.astype(np.float32), ["R", "G", "B"], colour_space="linear")


LANDMARK_FIT_FRAMES = 90
LANDMARK_FIT_BLINKS = (20, 65)  # first frame of each 4-frame blink


def landmark_fit_truth(seed: int, shapes: list[str], frames: int = LANDMARK_FIT_FRAMES,
                       blinks: tuple[int, ...] = LANDMARK_FIT_BLINKS) -> np.ndarray:
    """(F, 12 + K) fit layout: a head 47 cm away turning +-3 degrees, smiling slowly, a jaw snap
    0 -> 0.7 over 2 frames at 40 and back at 46, blinks 0.05 -> 0.5, 0.95, 0.95, 0.5 at 20 and 65
    (tests/nodes/temporal/test_adaptive_landmarks.py's and bench/smoothing.py's shot); `shapes`
    are the model's expression names."""

    rng = np.random.default_rng(seed)
    t = np.arange(frames)
    k = {n: i for i, n in enumerate(shapes)}
    turn = 0.05 * np.sin(t[:, None] / np.array([11.0, 13.0, 17.0]) + rng.uniform(0, 6, 3))
    rotation = np.diag([1.0, -1.0, -1.0]) @ axis_angle_to_rotmat(turn)
    translation = np.stack([-2 + 0.5 * np.sin(t / 13), -1.7 + 0.3 * np.sin(t / 17), 47 + np.sin(t / 19)], 1)
    w = np.zeros((frames, len(shapes)))
    for n in ("mouthSmile_L", "mouthSmile_R"):
        w[:, k[n]] = 0.3 + 0.2 * np.sin(t / 15 + rng.uniform(0, 6))
    w[:, k["jawOpen"]] = 0.7 * np.clip((t - 39) / 2, 0, 1) * np.clip((47 - t) / 2, 0, 1)
    for n in ("eyeBlink_L", "eyeBlink_R"):
        w[:, k[n]] = 0.05
        for b in blinks:
            w[b:b + 4, k[n]] = [0.5, 0.95, 0.95, 0.5]
    return np.concatenate([rotation.reshape(frames, 9), translation, w], 1)


def per_frame_landmark_fit(truth: np.ndarray, project, seed: int, pixel_noise: float, prior: float = 1.0) -> np.ndarray:
    """Each frame: argmin |J d - n|^2 + prior |w + d_w|^2 (J the landmarks' Jacobian at the truth,
    n white pixel noise), applied as a rotation, a translation and weights clipped to [0, 1]: a
    per-frame fit as the real one behaves (weights pinned at 0 with spikes, correlated where the
    landmarks barely tell shapes apart). `project`: (N, 12 + K) rows -> (N, 136) pixels."""
    from nodes.temporal.adaptive import landmark_jacobian

    rng = np.random.default_rng(1000 + seed)
    out = truth.copy()
    k = truth.shape[1] - 12
    on_weights = np.r_[np.zeros(6), np.ones(k)]
    for f in range(len(truth)):
        rot = truth[f, :9].reshape(3, 3)

        def landmarks(c: np.ndarray, f: int = f, rot: np.ndarray = rot) -> np.ndarray:
            rows = np.tile(truth[f], (len(c), 1))
            rows[:, :9] = (rot @ axis_angle_to_rotmat(c[:, :3])).reshape(-1, 9)
            rows[:, 9:] = truth[f, 9:] + c[:, 3:]
            return project(rows)

        jac = landmark_jacobian(landmarks, np.zeros(6 + k))
        noise = rng.normal(0, pixel_noise, jac.shape[0])
        step = np.linalg.solve(jac.T @ jac + prior * np.diag(on_weights),
                               jac.T @ noise - prior * on_weights * np.r_[np.zeros(6), truth[f, 12:]])
        out[f, :9] = (rot @ axis_angle_to_rotmat(step[None, :3]))[0].reshape(9)
        out[f, 9:12] = truth[f, 9:12] + step[3:6]
        out[f, 12:] = np.clip(truth[f, 12:] + step[6:], 0, 1)
    return out
