"""The secondary dynamics a step removed, as colour maps on the face: `report.DynamicsMap`.

The removed offsets `|capture - result|` (and, when the truth is known, the true offsets
`|capture - truth|` and what is left, `|result - truth|`) of one frame, per vertex in cm, are
rendered on the frame's surface seen from the front of the skull frame (flat lighting, one
shared colour scale), side by side with a colour bar.
Torch and matplotlib are imported inside the functions that draw.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from nodegraph import SEQUENCE, Files, In, InputError, MeshSequence, Node, NodeParams, Out, Param, RigidSequence
from nodegraph.files import files_value

from ..geometry.rigid import stabilize_vertices

__all__ = ["render_scalar_front", "plot_dynamics_map", "DynamicsMap"]


def render_scalar_front(skull_vertices: np.ndarray, faces: np.ndarray, values: np.ndarray, *, vmax: float,
                        size: int = 320, colormap: str = "magma") -> np.ndarray:
    """Render per-vertex values as colours on a mesh seen from +z (the ICT head's front).

    Args:
        skull_vertices: (V, 3) cm, skull frame (y up, z out of the face).
        faces: (T, 3) int triangles.
        values: (V,) scalars; 0..vmax spans the colour map.
        vmax: top of the colour scale (> 0).
        size: image height and width, pixels.
        colormap: matplotlib colour map name.
    Returns:
        (size, size, 3) float32 RGB in [0, 1], white background.
    """
    import torch
    from matplotlib import colormaps

    from ..render.renderer import render_mesh, sh_from_lights
    from ..geometry.camera import look_at

    lo, hi = skull_vertices.min(0), skull_vertices.max(0)
    centre = (lo + hi) / 2
    distance = 200.0  # cm: nearly orthographic
    half = 0.55 * float(max(hi[0] - lo[0], hi[1] - lo[1]))
    focal = (size / 2) * (distance - (hi[2] - centre[2])) / max(half, 1e-6)
    extrinsics = look_at(centre + [0.0, 0.0, distance], centre)
    colours = colormaps[colormap](np.clip(values / vmax, 0.0, 1.0))[:, :3].astype(np.float32)
    with torch.no_grad():
        out = render_mesh(torch.as_tensor(skull_vertices, dtype=torch.float32)[None], np.asarray(faces),
                          torch.as_tensor(extrinsics, dtype=torch.float32)[None],
                          torch.tensor([[focal, focal, (size - 1) / 2, (size - 1) / 2]], dtype=torch.float32),
                          size, size, albedo=torch.as_tensor(colours)[None],
                          sh=torch.as_tensor(sh_from_lights(1.0))[None], background=(1.0, 1.0, 1.0))
    return out.image[0].clamp(0, 1).numpy()


def plot_dynamics_map(panels: dict[str, np.ndarray], vmax_cm: float, path: str | os.PathLike, *,
                      title: str = "") -> Path:
    """Panels side by side (label -> (H, W, 3) image) with one colour bar of 0..vmax_cm (shown in mm)."""
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    from .plots import save_figure

    fig = Figure(figsize=(3.2 * len(panels) + 1.0, 3.9))
    fig.subplots_adjust(left=0.02, right=0.86, bottom=0.02, top=0.84, wspace=0.05)
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (label, image) in zip(axes, panels.items()):
        ax.imshow(image)
        ax.set_title(label, fontsize="medium")
        ax.set_axis_off()
    bar = fig.add_axes((0.88, 0.1, 0.025, 0.7))
    fig.colorbar(ScalarMappable(Normalize(0.0, vmax_cm * 10.0), "magma"), cax=bar, label="mm")
    if title:
        fig.suptitle(title)
    return save_figure(fig, path)


class DynamicsMap(Node):
    """Colour maps on the face of the dynamics a step removed (and the true ones, when known)."""

    type_name = "report.DynamicsMap"
    version = 1
    kind = SEQUENCE
    writes_files = True

    class Params(NodeParams):
        folder: str = Param("dynamics_report", output_file=True, description="Output folder (created): "
                            "dynamics.png.")
        frame: int = Param(-1, ge=-1, description="Frame shown (index in the run); -1 = the frame with the largest "
                           "mean true offset (the removed one without a truth).")
        vmax_mm: float = Param(0.0, ge=0, description="Top of the colour scale, mm; 0 = the 99th percentile of "
                               "the offsets shown.")
        size: int = Param(320, ge=64, le=2048, description="Size of each rendered panel, pixels.")

    capture = In(MeshSequence, doc="The capture with dynamics, world, cm.")
    result = In(MeshSequence, doc="The capture with the dynamics removed, world, cm (same topology).")
    skull = In(RigidSequence, doc="Skull-to-world transforms (the view is the skull frame's front).")
    truth = In(MeshSequence, optional=True, doc="The true result (e.g. synthetic quasistatic motion), world, cm.")
    files = Out(Files, doc="dynamics.png")

    def run(self, capture: MeshSequence, result: MeshSequence, skull: RigidSequence,
            truth: MeshSequence | None = None) -> dict[str, Files]:
        for port, mesh in (("result", result), ("truth", truth)):
            if mesh is not None and mesh.vertices.shape != capture.vertices.shape:
                raise InputError(port, f"expected vertices of the capture's shape {capture.vertices.shape}, found "
                                       f"{mesh.vertices.shape}")
        if skull.num_frames != capture.num_frames:
            raise InputError("skull", f"expected {capture.num_frames} frames (as the capture), found {skull.num_frames}")
        if not capture.faces.size:
            raise InputError("capture", "expected a mesh with faces (a point set cannot be drawn)")
        removed = np.linalg.norm(capture.vertices - result.vertices, axis=-1)  # (F, V) cm
        true = None if truth is None else np.linalg.norm(capture.vertices - truth.vertices, axis=-1)
        p = self.params
        if p.frame >= capture.num_frames:
            raise InputError("frame", f"expected a frame below {capture.num_frames}, found {p.frame}")
        frame = p.frame if p.frame >= 0 else int(np.argmax((true if true is not None else removed).mean(axis=1)))
        shown = {f"removed (frame {frame})": removed[frame]}
        if true is not None:
            shown["true"] = true[frame]
            shown["left after removal"] = np.linalg.norm(result.vertices[frame] - truth.vertices[frame], axis=-1)
        vmax_cm = p.vmax_mm / 10.0 if p.vmax_mm > 0 else float(np.percentile(np.concatenate(list(shown.values())), 99))
        vmax_cm = max(vmax_cm, 1e-4)
        front = stabilize_vertices(capture.vertices[frame:frame + 1], skull.matrices[frame:frame + 1])[0]
        panels = {label: render_scalar_front(front, capture.faces, values, vmax=vmax_cm, size=p.size)
                  for label, values in shown.items()}
        path = Path(p.folder) / "dynamics.png"  # its folder is made by the (staged) atomic write
        plot_dynamics_map(panels, vmax_cm, path, title="secondary dynamics, |offset| per vertex")
        return {"files": files_value([str(path)])}
