"""Port types: the values that flow on the edges of a graph, gathered under one name.

Each concept lives in its own module; this one re-exports them all, so that
`from nodegraph.types import MeshSequence` keeps working for nodes and plugins:

- `nodegraph.ports`: the `PortType` protocol (frame axis, chunks, validation, fingerprint,
  plain-array storage), the registry of port types by name, the shared check helpers;
- `nodegraph.sequences`: `MeshSequence`, `RigidSequence`, `Landmarks2D`, `FlowSequence`,
  `ParamSequence`;
- `nodegraph.images`: `ImageSequence` and the sRGB curve;
- `nodegraph.face_model`: `FaceModel`;
- `nodegraph.cameras`: `Camera`, `CameraRig` and their JSON form;
- `nodegraph.models`: `TorchModel` with the architecture registry and model files;
- `nodegraph.values`: `Table`, `JsonValue`, `Files`.

Type names (what graph files, cache entries and model files store) are the class names.
"""

from __future__ import annotations

from .cameras import CAMERA_RIG_SCHEMA, CAMERA_SCHEMA, CM_PER_UNIT, Camera, CameraRig
from .face_model import FaceModel
from .images import COLOUR_SPACES, ImageSequence, linear_to_srgb, srgb_to_linear
from .models import TorchModel
from .ports import PortType, port_type_by_name, port_types
from .sequences import FlowSequence, Landmarks2D, MeshSequence, ParamSequence, RigidSequence
from .values import Files, JsonValue, Table

__all__ = [
    "PortType", "MeshSequence", "RigidSequence", "ImageSequence", "Landmarks2D",
    "FlowSequence", "ParamSequence", "FaceModel", "TorchModel", "Camera", "CameraRig", "Table",
    "JsonValue", "Files", "port_types", "port_type_by_name", "COLOUR_SPACES", "srgb_to_linear",
    "linear_to_srgb", "CAMERA_SCHEMA", "CAMERA_RIG_SCHEMA", "CM_PER_UNIT",
]
