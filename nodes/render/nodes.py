"""Render nodes: `render.DefaultAppearance` (albedo and lighting of the bundled head) and
`render.Render` (mesh sequence + camera + appearance -> images and buffers).

Torch and numba are imported inside `run()` (see tests/test_startup.py).
"""

from __future__ import annotations

import numpy as np

from nodegraph import (FRAMEWISE, SEQUENCE, Camera, FaceModel, ImageSequence, In, InputError, JsonValue,
                       MeshSequence, Node, NodeParams, Out, Param)

from .appearance import DEFAULT_LIGHT, appearance_json, culled_faces, default_albedo, parse_appearance

__all__ = ["DefaultAppearance", "Render", "BUFFER_CHANNELS"]

BUFFER_CHANNELS = ["Z", "triangle", "bary0", "bary1", "bary2"]
"""Channels of `render.Render`'s `buffers`: camera depth (cm, 0 = none), visible triangle
index into the mesh's faces (-1 = none), perspective-correct barycentrics."""


class DefaultAppearance(Node):
    """Albedo, SH lighting and hidden faces that the landmark network reads as a face (ICT head)."""

    type_name = "render.DefaultAppearance"
    version = 1
    kind = SEQUENCE

    class Params(NodeParams):
        ambient: float = Param(DEFAULT_LIGHT["ambient"], ge=0, description="Uniform irradiance (linear).")
        intensity: float = Param(DEFAULT_LIGHT["intensity"], ge=0, description="Irradiance of the key "
                                 "light on a surface facing it (linear).")
        direction: list[float] = Param(list(DEFAULT_LIGHT["direction"]), min_length=3, max_length=3,
                                       description="Direction towards the key light, world frame "
                                       "(ICT: y up, z out of the face).")
        background: list[float] = Param(list(DEFAULT_LIGHT["background"]), min_length=3, max_length=3,
                                        description="Background colour, linear RGB.")
        hide_eye_shells_and_lashes: bool = Param(True, description="Do not draw the ICT head's "
                                                 "transparent eye shells and eyelash strips "
                                                 "(vertices 24591-26718).")

    model = In(FaceModel, doc="The face model (its groups and 68 landmarks place the regions).")
    appearance = Out(JsonValue, doc="{'albedo': V x 3, 'sh': 9 x 3, 'background': 3, 'hidden_faces': [...]}")

    def run(self, model: FaceModel) -> dict[str, JsonValue]:
        from .renderer import sh_from_lights

        p = self.params
        if not any(p.direction):
            raise InputError("direction", f"expected a non-zero direction, found {p.direction}")
        sh = sh_from_lights(p.ambient, p.direction, p.intensity)
        hidden = culled_faces(model.faces, model.neutral.shape[0]) if p.hide_eye_shells_and_lashes else None
        return {"appearance": JsonValue(appearance_json(default_albedo(model), sh, tuple(p.background), hidden))}


class Render(Node):
    """Render a mesh sequence through a camera with albedo and SH lighting (differentiable renderer)."""

    type_name = "render.Render"
    version = 1
    kind = FRAMEWISE
    resources = {"gpu": 1}
    skips_unread_outputs = True  # the buffers only when an edge reads them

    class Params(NodeParams):
        supersample: int = Param(2, ge=1, le=4, description="Render at s times the camera's size and "
                                 "average s x s blocks (2 helps the landmark network).")
        antialias: bool = Param(True, description="Analytic silhouette antialiasing.")
        near_cm: float = Param(0.1, gt=0, description="Triangles with a corner closer than this to "
                               "the camera (camera z, cm) are not drawn.")
        batch: int = Param(4, ge=1, description="Frames rendered together.", affects_output=False)

    mesh = In(MeshSequence, doc="Vertices (F, V, 3) cm, world frame; faces drawn unless hidden.")
    camera = In(Camera, doc="The camera (OpenCV convention); the image has its width and height.")
    appearance = In(JsonValue, doc="From render.DefaultAppearance, or {'albedo': V x 3 or 3, 'sh': 9 x 3, "
                    "'background': 3, 'hidden_faces': [...]}.")
    background = In(ImageSequence, optional=True, doc="Background plate (F, H, W, 3); replaces the "
                    "appearance's background colour.")
    images = Out(ImageSequence, doc="(F, H, W, 3) linear RGB, colour_space 'linear'.")
    buffers = Out(ImageSequence, doc="(F, H, W, 5): Z (cm, 0 = none), triangle (-1 = none), bary0..2.")

    def run(self, mesh: MeshSequence, camera: Camera, appearance: JsonValue,
            background: ImageSequence | None = None) -> dict[str, ImageSequence]:
        import torch

        from ..geometry.mesh import triangle_adjacency
        from .renderer import render_mesh

        p = self.params
        try:
            albedo, sh, bg_colour, hidden = parse_appearance(appearance.value, mesh.num_vertices, len(mesh.faces))
        except ValueError as err:
            raise InputError("appearance", str(err).removeprefix("appearance: ")) from err
        if background is not None:
            shape = background.pixels.shape
            if shape[1:3] != (camera.height, camera.width) or len(background.colour_channels()) < 3:
                raise InputError("background", f"expected (F, {camera.height}, {camera.width}, 3) RGB "
                                 f"images (the camera's size), found {shape}")
            background = background.to_linear()
        keep = np.setdiff1d(np.arange(len(mesh.faces)), hidden)
        faces = mesh.faces[keep]
        if not len(faces):
            raise InputError("mesh", "expected triangles to draw, found none (no faces, or all hidden)")
        device = self.device
        dt = torch.float32
        adjacency = triangle_adjacency(faces)
        e = torch.as_tensor(camera.world_to_camera, dtype=dt, device=device)
        k = torch.tensor([camera.fx, camera.fy, camera.cx, camera.cy], dtype=dt, device=device)
        dist = None
        if camera.k1 or camera.k2:
            dist = torch.tensor([[camera.k1, camera.k2]], dtype=dt, device=device)
        albedo_t = torch.as_tensor(albedo, device=device)[None]
        sh_t = torch.as_tensor(sh, device=device)[None]
        frames = mesh.vertices.shape[0]
        images, buffers = [], []
        with torch.no_grad():
            for start in range(0, frames, p.batch):
                stop = min(start + p.batch, frames)
                n = stop - start
                verts = torch.as_tensor(mesh.vertices[start:stop], dtype=dt, device=device)
                if background is not None:
                    bg = torch.as_tensor(background.pixels[start:stop][..., background.colour_channels()[:3]],
                                         dtype=dt, device=device)
                else:
                    bg = torch.as_tensor(bg_colour, device=device)
                out = render_mesh(verts, faces, e.expand(n, 4, 4), k.expand(n, 4), camera.height, camera.width,
                                  albedo=albedo_t, sh=sh_t, background=bg,
                                  distortion=None if dist is None else dist.expand(n, 2),
                                  antialias=p.antialias, supersample=p.supersample, near=p.near_cm,
                                  adjacency=adjacency)
                images.append(out.image.clamp_min(0).cpu().numpy())
                tri = torch.where(out.triangle >= 0, torch.as_tensor(keep, device=device)[out.triangle.clamp_min(0)],
                                  out.triangle)
                if self.wants("buffers"):
                    buffers.append(torch.cat([out.depth[..., None], tri[..., None].to(dt), out.barycentrics],
                                             -1).cpu().numpy())
                self.progress(stop / frames, f"rendered {stop}/{frames} frames")
        out = {"images": ImageSequence(np.concatenate(images).astype(np.float32), ["R", "G", "B"], fps=mesh.fps,
                                       colour_space="linear")}
        if buffers:
            out["buffers"] = ImageSequence(np.concatenate(buffers).astype(np.float32), list(BUFFER_CHANNELS),
                                           fps=mesh.fps, colour_space="linear")
        return out
