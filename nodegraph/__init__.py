"""nodegraph: typed dataflow graphs for facial performance capture."""

from .errors import GraphError, GraphIssue, InputError, NodeError, NodegraphError
from .node import FRAMEWISE, SEQUENCE, In, Index, Kind, Node, NodeParams, Out, Param, run_node, windowed
from .graph import Graph, PortRef
from .runner import RunResult, explain, run
from .types import (FaceModel, Files, FlowSequence, ImageSequence, JsonValue, Landmarks2D,
                    MeshSequence, ParamSequence, PortType, RigidSequence, Table, TorchModel)
from .types import Camera, CameraRig
from .performance import Performance
from .models import register_architecture

__all__ = [
    "GraphError", "GraphIssue", "InputError", "NodeError", "NodegraphError",
    "FRAMEWISE", "SEQUENCE", "In", "Index", "Kind", "Node", "NodeParams", "Out", "Param", "run_node",
    "windowed", "FaceModel", "Files", "FlowSequence", "ImageSequence", "JsonValue",
    "Landmarks2D", "MeshSequence", "ParamSequence", "PortType", "RigidSequence", "Table",
    "TorchModel", "Graph", "PortRef", "RunResult", "explain", "run",
    "Camera", "CameraRig", "Performance", "register_architecture",
]
__version__ = "0.1.0"
