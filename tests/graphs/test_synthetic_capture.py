"""The graph graphs/synthetic_capture.json: valid, and it runs end to end in chunks."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, registry, runner
from nodes.io.face_model import load_face_model
from nodes.synth.performance import generate_performance

GRAPH = Path(__file__).resolve().parents[2] / "graphs" / "synthetic_capture.json"


def test_synthetic_capture_graph_types_ports_params_exist():
    data = json.loads(GRAPH.read_text())
    assert data["schema"] == "nodegraph/1"
    for node_id, spec in data["nodes"].items():
        cls = registry.get(spec["type"])
        cls.Params(**spec["params"])  # raises on unknown or invalid params
    for src, dst in data["edges"]:
        (a, out_port), (b, in_port) = src.split("."), dst.split(".")
        src_cls, dst_cls = (registry.get(data["nodes"][n]["type"]) for n in (a, b))
        assert out_port in src_cls.outputs and in_port in dst_cls.inputs, (src, dst)
        assert src_cls.outputs[out_port].type is dst_cls.inputs[in_port].type, (src, dst)
    names = set(data["parameters"])
    assert names == {"capture", "truth_rigid", "expressions", "truth", "report", "num_frames", "seed"}
    for entry in data["parameters"].values():
        node_id, param = entry["target"].split(".")
        assert param in registry.get(data["nodes"][node_id]["type"]).Params.model_fields


def test_synthetic_capture_graph_runs_in_chunks(tmp_path):
    graph = Graph.load(GRAPH)
    assert graph.validate() == []
    graph.set("model", region="face")  # smaller than the whole head, same code path
    out = {name: str(tmp_path / file) for name, file in (
        ("capture", "capture.npz"), ("truth", "truth.npz"), ("truth_rigid", "rigid.json"),
        ("expressions", "weights.json"), ("report", "report"))}
    result = runner.run(graph, parameters={**out, "num_frames": 12, "seed": 4}, scheduler="sync",
                        cache=False, chunk=5)
    assert result.exit_code == 0, result.summary()
    params = {**json.loads(GRAPH.read_text())["nodes"]["performance"]["params"],
              "num_frames": 12, "seed": 4}
    perf = generate_performance(load_face_model(region="face"), **params)
    with np.load(out["capture"]) as saved:
        np.testing.assert_array_equal(saved["vertices"], perf.capture.vertices)
    with np.load(out["truth"]) as saved:
        np.testing.assert_array_equal(saved["vertices"], perf.stabilized.vertices)
    rigid = json.loads(Path(out["truth_rigid"]).read_text())
    assert len(rigid["matrices"]) == 12
    assert {p.name for p in Path(out["report"]).iterdir()} == {"head_motion.png", "histograms.png"}
