"""Synthetic plates with known parameters, for tests and benches of flow and temporal nodes.

The bundled ICT head (optionally cut to a region) is posed by a parameter sequence (the
layout of `nodes.temporal.layout`) and rendered through a pinhole 55 cm in front of it with
the default lighting and a per-vertex textured albedo (skin pores would give a real plate
its texture; the flow needs some), over a flat grey background.

Torch is imported inside the functions.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nodegraph import Camera, FaceModel, ImageSequence

__all__ = ["Scene", "make_scene", "head_motion", "render_plates", "scene_vertices"]


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
    from ..io.face_model import load_face_model
    from ..render.appearance import DEFAULT_LIGHT, default_albedo, hidden_faces
    from ..render.renderer import sh_from_lights

    model = load_face_model(region=region)
    rng = np.random.default_rng(seed)
    albedo = default_albedo(model)
    noise = rng.uniform(-1.0, 1.0, (len(albedo), 1)).astype(np.float32)
    albedo = np.clip(albedo * (1.0 + texture * noise), 0.0, 1.0).astype(np.float32)
    faces = np.asarray(model.faces, np.int64)
    if model.neutral.shape[0] > 26718:
        faces = np.setdiff1d(np.arange(len(faces)), hidden_faces(faces))
        faces = np.asarray(model.faces, np.int64)[faces]
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

    from .layout import posed_vertices

    v = torch.as_tensor(np.asarray(values, np.float32), device=device)
    neutral = torch.as_tensor(scene.model.neutral, device=device)
    deltas = torch.as_tensor(scene.model.expression_deltas, device=device)
    return posed_vertices(neutral, deltas, v[:, 0:3], v[:, 3:6], v[:, 6:])


def render_plates(scene: Scene, values: np.ndarray, *, supersample: int = 2, device: str = "cpu") -> ImageSequence:
    """Render the plates of a standard-layout parameter sequence: (F, H, W, 3) linear RGB."""
    import torch

    from ..render.renderer import render_mesh, triangle_adjacency

    verts = scene_vertices(scene, values, device)
    cam = scene.camera
    n = verts.shape[0]
    e = torch.as_tensor(cam.world_to_camera, dtype=torch.float32, device=device).expand(n, 4, 4)
    k = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy], dtype=torch.float32, device=device).expand(n, 4)
    with torch.no_grad():
        out = render_mesh(verts, scene.faces, e, k, cam.height, cam.width,
                          albedo=torch.as_tensor(scene.albedo, device=device)[None],
                          sh=torch.as_tensor(scene.sh, device=device)[None],
                          background=torch.as_tensor(scene.background, device=device), supersample=supersample,
                          adjacency=triangle_adjacency(scene.faces))
    return ImageSequence(out.image.clamp_min(0).cpu().numpy().astype(np.float32), ["R", "G", "B"],
                         colour_space="linear")
