"""graphs/dynamics_*.json: train F and H on generated captures, remove dynamics from a capture of
another identity, expression, oscillation frequency and frame rate, retarget to a new head motion.

Reduced settings (a 400-point face region, shorter corpus, fewer rows and epochs) keep this under
a minute; the full defaults are measured by bench/dynamics.py and stated in the README.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, registry, runner
from nodes.dynamics.evaluate import rms_distance
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import simulate_dynamics

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"
SMALL = {"max_vertices": 400, "epochs": 10, "rows": 40000, "samples": 100,
         "synthesis_samples": 100, "synthesis_epochs": 15}


def _check_types(path: Path) -> dict:
    data = json.loads(path.read_text())
    for spec in data["nodes"].values():
        registry.get(spec["type"]).Params(**spec["params"])
    for src, dst in data["edges"]:
        (a, out_port), (b, in_port) = src.split("."), dst.split(".")
        src_cls, dst_cls = (registry.get(data["nodes"][n]["type"]) for n in (a, b))
        assert out_port in src_cls.outputs and in_port in dst_cls.inputs, (src, dst)
        assert src_cls.outputs[out_port].type is dst_cls.inputs[in_port].type, (src, dst)
    return data


def test_dynamics_graphs_are_valid():
    for name in ("train", "remove", "retarget"):
        graph = Graph.load(GRAPHS / f"dynamics_{name}.json")
        assert graph.validate() == []
        _check_types(GRAPHS / f"dynamics_{name}.json")
    remove = json.loads((GRAPHS / "dynamics_remove.json").read_text())
    assert set(remove["parameters"]) == {"capture", "skull", "fps", "model", "output"}
    assert "model" in json.loads((GRAPHS / "dynamics_train.json").read_text())["parameters"]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    folder = tmp_path_factory.mktemp("dynamics")
    graph = Graph.load(GRAPHS / "dynamics_train.json")
    motions = ["walk", "run", "jump", "oscillate@6", "oscillate@8", "oscillate@11"]
    graph.set("captures_96", motions=motions, expressions=["neutral", "smile", "speech"], segment_frames=80)
    graph.set("captures_128", motions=motions, expressions=["neutral", "jaw_open", "speech"], segment_frames=80)
    graph.set("train_removal", batch_size=2000)
    paths = {"model": str(folder / "removal.safetensors"),
             "synthesis_model": str(folder / "synthesis.safetensors")}
    result = runner.run(graph, parameters={**SMALL, **paths}, scheduler="sync", cache=False)
    assert result.exit_code == 0, result.summary()
    return folder, paths


def test_remove_graph_on_another_face_expression_frequency_and_fps(trained):
    folder, paths = trained
    model = load_face_model(region="face", max_vertices=400)
    test = simulate_dynamics(model, motions=["oscillate@9"], expressions=["frown"], segment_frames=150,
                             fps=110.0, seed=7, stiffness_scale=0.95)
    np.savez(folder / "capture.npz", vertices=test.capture.vertices, faces=test.capture.faces)
    np.savez(folder / "skull.npz", rigid=test.skull.matrices)
    out = folder / "quasistatic.npz"
    result = runner.run(GRAPHS / "dynamics_remove.json", scheduler="sync", cache=False, chunk=64,
                        parameters={"capture": str(folder / "capture.npz"),
                                    "skull": str(folder / "skull.npz"), "fps": 110.0,
                                    "model": paths["model"], "output": str(out)})
    assert result.exit_code == 0, result.summary()
    with np.load(out) as saved:
        removed = saved["vertices"]
    assert removed.shape == test.capture.vertices.shape
    before = rms_distance(test.capture.vertices, test.quasistatic.vertices)
    after = rms_distance(removed, test.quasistatic.vertices)
    assert after < 0.5 * before, (before, after)


def test_retarget_graph_runs_and_reports(trained):
    folder, paths = trained
    graph = Graph.load(GRAPHS / "dynamics_retarget.json")
    graph.set("source", segment_frames=120)
    graph.set("target", segment_frames=120)
    result = runner.run(graph, scheduler="sync", cache=False, chunk=64,
                        parameters={"removal_model": paths["model"],
                                    "synthesis_model": paths["synthesis_model"],
                                    "output": str(folder / "retargeted.npz"), "max_vertices": 400})
    assert result.exit_code == 0, result.summary()
    removal = result.outputs["removal_error"]["table"]
    synthesis = result.outputs["synthesis_error"]["table"]
    assert removal.column("reduction_pct")[1] > 50.0, removal.format()
    assert synthesis.column("rms_mm")[1] < synthesis.column("rms_mm")[0], synthesis.format()
    with np.load(folder / "retargeted.npz") as saved:
        assert saved["vertices"].shape == (120, 400, 3)


def test_retarget_graph_refuses_a_removal_network_as_h_before_anything_runs(tmp_path, capsys):
    """A removal network given as the synthesis network is one refusal while planning (it was a
    FAILED task in every chunk, after the performances were made: 95 s at load ~18)."""
    from nodegraph.cli import main
    from nodes.dynamics.files import BUNDLED_REMOVAL

    code = main(["run", str(GRAPHS / "dynamics_retarget.json"), f"removal_model={BUNDLED_REMOVAL}",
                 f"synthesis_model={BUNDLED_REMOVAL}", f"output={tmp_path / 'r.npz'}", "--no-cache",
                 "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "'synthesize'" in err and "synthesis network" in err and "kind 'removal'" in err, err
    assert "FAILED" not in err and err.count("expected") == 1, err  # refused while planning, once
    assert not (tmp_path / "r.npz").exists()
