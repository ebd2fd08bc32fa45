"""nodegraph: typed dataflow graphs for facial performance capture."""

from .errors import GraphError, GraphIssue, InputError, NodeError, NodegraphError
from .node import FRAMEWISE, SEQUENCE, In, Kind, Node, Out, run_node, windowed
from .params import Index, NodeParams, Param
from .graph import Graph, PortRef
from .runner import RunResult, explain, run
from .ports import PortType
from .sequences import FlowSequence, Landmarks2D, MeshSequence, ParamSequence, RigidSequence
from .images import ImageSequence
from .face_model import FaceModel
from .cameras import Camera, CameraRig
from .models import TorchModel, register_architecture
from .values import Files, JsonValue, Table
from .performance import Performance
from . import types  # noqa: F401  (the one-name view of every port type, `nodegraph.types`)

__all__ = [
    "GraphError", "GraphIssue", "InputError", "NodeError", "NodegraphError",
    "FRAMEWISE", "SEQUENCE", "In", "Index", "Kind", "Node", "NodeParams", "Out", "Param", "run_node",
    "windowed", "FaceModel", "Files", "FlowSequence", "ImageSequence", "JsonValue",
    "Landmarks2D", "MeshSequence", "ParamSequence", "PortType", "RigidSequence", "Table",
    "TorchModel", "Graph", "PortRef", "RunResult", "explain", "run",
    "Camera", "CameraRig", "Performance", "register_architecture",
]
__version__ = "0.1.0"
