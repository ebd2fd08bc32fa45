"""Write a performance as binary glTF 2.0 (`export.GltfAnimation`): a head mesh with morph targets
and an animation of its weights, rotation and translation.

pygltflib writes the JSON document and the GLB container (chunk headers, padding, the schema's
field names), which is the part a hand-written packer gets wrong; the buffers are packed here
with numpy: float32 accessors with `min` / `max` where the Khronos rules ask for them, every
buffer view 4-byte aligned, LINEAR samplers, times in seconds.

glTF is in metres, y up: vertices are the model's cm times 0.01. The mesh's vertices are split
where a vertex has several UVs (glTF's attributes are per vertex), each copy carrying its
vertex's offsets, so every copy poses like the vertex it came from. Morph target names are in
`mesh.extras.targetNames` (Blender's importer and three.js read them there).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from nodegraph import Camera, FaceModel, Param, Performance
from nodegraph.files import atomic_path

from ..geometry.mesh import vertex_normals
from .scene import SceneWriter, SceneWriterParams, blendshapes, head_quaternions, head_transforms

__all__ = ["split_uv_seams", "write_gltf_animation", "GltfAnimation"]

M_PER_CM = 0.01
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963
_FLOAT, _UNSIGNED_INT = 5126, 5125


def split_uv_seams(faces: np.ndarray, uv_faces: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Make UVs per vertex: one vertex per distinct (vertex, uv) corner pair.

    Args:
        faces: (T, 3) vertex indices; uv_faces: (T, 3) uv indices, or None.
    Returns:
        new faces (T, 3), uv index of each new vertex (N,) or None, source vertex of each new vertex (N,).
    """
    faces = np.asarray(faces, np.int64)
    if uv_faces is None:
        return faces, None, np.arange(faces.max() + 1 if faces.size else 0)
    pairs = np.stack([faces.reshape(-1), np.asarray(uv_faces, np.int64).reshape(-1)], axis=1)
    unique, inverse = np.unique(pairs, axis=0, return_inverse=True)
    return inverse.reshape(faces.shape), unique[:, 1], unique[:, 0]


class _Packer:
    """Buffer views and accessors of one binary buffer."""

    def __init__(self) -> None:
        import pygltflib

        self.lib = pygltflib
        self.chunks: list[bytes] = []
        self.offset = 0
        self.views: list = []
        self.accessors: list = []

    def add(self, array: np.ndarray, kind: str, *, target: int | None = None, bounds: bool = False) -> int:
        """Append an accessor of `array` (float32 or uint32) of glTF type `kind`; return its index."""
        array = np.ascontiguousarray(array)
        data = array.tobytes()
        self.views.append(self.lib.BufferView(buffer=0, byteOffset=self.offset, byteLength=len(data), target=target))
        pad = (-len(data)) % 4
        self.chunks.append(data + b"\0" * pad)
        self.offset += len(data) + pad
        count = array.shape[0]
        accessor = self.lib.Accessor(bufferView=len(self.views) - 1, byteOffset=0,
                                     componentType=_UNSIGNED_INT if array.dtype == np.uint32 else _FLOAT,
                                     count=int(count), type=kind)
        if bounds:
            flat = array.reshape(count, -1).astype(np.float64)
            accessor.min = flat.min(axis=0).tolist() if count else [0.0] * flat.shape[1]
            accessor.max = flat.max(axis=0).tolist() if count else [0.0] * flat.shape[1]
        self.accessors.append(accessor)
        return len(self.accessors) - 1

    def blob(self) -> bytes:
        return b"".join(self.chunks)


def write_gltf_animation(path: str | Path, model: FaceModel, performance: Performance,
                         camera: Camera | None = None, *, asymmetry: bool = True) -> None:
    """Write the head, its morph targets and the animation to `path` (.glb), atomically.

    Args:
        path: destination .glb.
        model: the fitted face model (cm; written in metres).
        performance: F frames of pose and weights of `model`'s shapes.
        camera: the head's motion relative to it, y up (see `head_transforms`); None: the world.
        asymmetry: write the asymmetry shapes that make ICT's split shapes exact.
    """
    import pygltflib as gl

    shapes = blendshapes(performance, model, asymmetry=asymmetry)
    rigid = head_transforms(performance, camera)
    f = len(rigid)
    faces, uv_index, source = split_uv_seams(model.faces, model.uv_faces if model.uv is not None else None)
    pack = _Packer()
    positions = (model.neutral[source] * M_PER_CM).astype(np.float32)
    attributes = gl.Attributes(
        POSITION=pack.add(positions, gl.VEC3, target=_ARRAY_BUFFER, bounds=True),
        NORMAL=pack.add(vertex_normals(model.neutral, model.faces)[source].astype(np.float32), gl.VEC3,
                        target=_ARRAY_BUFFER))
    if uv_index is not None:
        uv = np.asarray(model.uv, np.float32)[uv_index]
        attributes.TEXCOORD_0 = pack.add(np.stack([uv[:, 0], 1.0 - uv[:, 1]], 1).astype(np.float32), gl.VEC2,
                                         target=_ARRAY_BUFFER)
    indices = pack.add(faces.reshape(-1).astype(np.uint32), gl.SCALAR, target=_ELEMENT_ARRAY_BUFFER)
    targets = [{"POSITION": pack.add((offsets[source] * M_PER_CM).astype(np.float32), gl.VEC3,
                                     target=_ARRAY_BUFFER, bounds=True)} for offsets in shapes.offsets]
    primitive = gl.Primitive(attributes=attributes, indices=indices, mode=gl.TRIANGLES, targets=targets)
    mesh = gl.Mesh(name="Head", primitives=[primitive], weights=[0.0] * len(shapes.names),
                   extras={"targetNames": list(shapes.names)})

    times = (np.arange(f) / float(performance.fps)).astype(np.float32)
    quats = head_quaternions(rigid)[:, [1, 2, 3, 0]].astype(np.float32)  # glTF's order: x, y, z, w
    translation = (rigid[:, :3, 3] * M_PER_CM).astype(np.float32)
    time_acc = pack.add(times, gl.SCALAR, bounds=True)
    samplers = [gl.AnimationSampler(input=time_acc, output=pack.add(shapes.weights.reshape(-1), gl.SCALAR),
                                    interpolation=gl.ANIM_LINEAR),
                gl.AnimationSampler(input=time_acc, output=pack.add(quats, gl.VEC4), interpolation=gl.ANIM_LINEAR),
                gl.AnimationSampler(input=time_acc, output=pack.add(translation, gl.VEC3),
                                    interpolation=gl.ANIM_LINEAR)]
    channels = [gl.AnimationChannel(sampler=i, target=gl.AnimationChannelTarget(node=0, path=p))
                for i, p in enumerate(("weights", "rotation", "translation"))]
    first = {"rotation": quats[0].tolist(), "translation": translation[0].tolist()} if f else {}
    node = gl.Node(name="Head", mesh=0, **first)
    blob = pack.blob()
    document = gl.GLTF2(asset=gl.Asset(version="2.0", generator="nodegraph export.GltfAnimation"),
                        scene=0, scenes=[gl.Scene(nodes=[0])], nodes=[node], meshes=[mesh],
                        accessors=pack.accessors, bufferViews=pack.views, buffers=[gl.Buffer(byteLength=len(blob))],
                        animations=[gl.Animation(name="performance", samplers=samplers, channels=channels)] if f
                        else [])
    document.set_binary_blob(blob)
    with atomic_path(path) as tmp:
        document.save_binary(str(tmp))


class GltfAnimation(SceneWriter):
    """Write the fitted head as binary glTF 2.0: mesh, ARKit-named morph targets, weight and head animation."""

    type_name = "export.GltfAnimation"
    version = 1

    class Params(SceneWriterParams):
        suffixes = (".glb",)
        path: str = Param(..., output_file=True, description="Destination .glb; '' = write nothing.")

    def write(self, path: Path, model: FaceModel, performance: Performance, camera: Camera | None) -> None:
        write_gltf_animation(path, model, performance, camera, asymmetry=self.params.asymmetry_shapes)
