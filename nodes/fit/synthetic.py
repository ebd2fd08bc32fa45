"""Synthetic plates for testing the fit: renders of the bundled head with a random identity,
pose, expression, albedo tint and lighting unlike the default, with their ground truth.

World frame: the first camera at the origin looking down +z (OpenCV: x right, y down);
the head about `distance_cm` in front of it. The head's rotation is
`R = diag(1, -1, -1) @ R_model(yaw, pitch, roll)` (the model's y up, z out of the face,
turned to face the camera), `R_model = Ry(yaw) Rx(pitch) Rz(roll)`.
Torch is imported inside the functions.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from nodegraph import Camera, FaceModel

from ..geometry.rotation import axis_angle_to_rotmat, euler_to_rotmat

__all__ = ["orbit_camera", "random_face_parameters", "render_plates"]

SYNTHETIC_IDENTITY_SEED = 918_273
"""Seed offset of the synthetic identities (used nowhere else in the project)."""


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


def render_plates(model: FaceModel, cameras: Sequence[Camera], truth: dict[str, Any], *, supersample: int = 2,
                  noise: float = 0.005, seed: int = 0) -> list[np.ndarray]:
    """Render the plates of `random_face_parameters` in each camera.

    Returns:
        one (F, H, W, 3) float32 linear image array per camera (Gaussian noise of `noise`).
    """
    import torch

    from ..render.appearance import default_albedo, hidden_faces
    from ..render.renderer import render_mesh, sh_from_lights, triangle_adjacency

    faces = np.delete(model.faces, hidden_faces(model.faces), axis=0)
    adjacency = triangle_adjacency(faces)
    verts = model.evaluate(truth["weights"], truth["identity"]) @ np.swapaxes(truth["rotation"], 1, 2) \
        + truth["translation"][:, None]
    albedo = torch.as_tensor(np.clip(default_albedo(model) * truth["albedo_tint"], 0, 1))[None]
    light = truth["light"]
    sh = torch.as_tensor(sh_from_lights(light["ambient"], light["direction"], light["intensity"]))[None]
    rng = np.random.default_rng(seed)
    out = []
    for cam in cameras:
        frames = []
        with torch.no_grad():
            for f in range(len(verts)):
                r = render_mesh(torch.as_tensor(verts[f:f + 1]), faces,
                                torch.as_tensor(cam.world_to_camera, dtype=torch.float32)[None],
                                torch.tensor([[cam.fx, cam.fy, cam.cx, cam.cy]]), cam.height, cam.width,
                                albedo=albedo, sh=sh, background=torch.as_tensor(truth["background"]),
                                supersample=supersample, adjacency=adjacency)
                frames.append(r.image[0].clamp(0, 1).numpy())
        images = np.stack(frames) + rng.normal(0.0, noise, (len(frames), cam.height, cam.width, 3))
        out.append(np.clip(images, 0.0, 1.0).astype(np.float32))
    return out
