"""Checks shared by the graph tests."""

from __future__ import annotations

import json
from pathlib import Path

from nodegraph import Graph, registry


def check_graph_file(path: Path) -> dict:
    """Assert that every node's params, every edge's ports and exact port types in a shipped
    graph file exist and agree, and that the graph validates; return the parsed JSON."""
    spec = json.loads(path.read_text())
    for node in spec["nodes"].values():
        registry.get(node["type"]).Params(**node["params"])
    for src, dst in spec["edges"]:
        (a, out_port), (b, in_port) = src.split("."), dst.split(".")
        src_cls, dst_cls = (registry.get(spec["nodes"][n]["type"]) for n in (a, b))
        assert out_port in src_cls.outputs and in_port in dst_cls.inputs, (src, dst)
        assert src_cls.outputs[out_port].type is dst_cls.inputs[in_port].type, (src, dst)
    assert Graph.load(path).validate() == []
    return spec
