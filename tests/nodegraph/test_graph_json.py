"""Graph building, JSON round trip, validation errors (all at once, naming node and port), migration."""

from __future__ import annotations

import json

import pytest

from nodegraph import Graph, GraphError

from .helpers import chain


def _json():
    return {
        "schema": "nodegraph/1",
        "nodes": {
            "ramp": {"type": "test.Ramp", "type_version": 1, "params": {"num_frames": 10}},
            "scale": {"type": "test.Scale", "type_version": 1, "params": {"factor": 2.0}},
            "total": {"type": "test.Total", "type_version": 1, "params": {}},
        },
        "edges": [["ramp.values", "scale.values"], ["scale.scaled", "total.values"]],
        "parameters": {"factor": "scale.factor"},
    }


def _issues(data):
    with pytest.raises(GraphError) as info:
        Graph.from_json(data)
    return info.value.issues


def test_programmatic_graph_round_trips_through_json(tmp_path):
    g = chain()
    g.expose("frames", "ramp", "num_frames", description="length")
    path = tmp_path / "g.json"
    g.save(path)
    again = Graph.load(path)
    assert again.to_json() == g.to_json()
    assert json.loads(path.read_text()) == g.to_json()
    assert again.parameters["frames"].target == "ramp.num_frames"


def test_json_round_trip_is_identical():
    data = _json()
    assert Graph.from_json(data).to_json() == data


def test_every_problem_is_reported_at_once():
    data = _json()
    data["nodes"]["scale"]["params"]["factr"] = 3
    data["nodes"]["ramp"]["params"]["num_frames"] = -1
    data["nodes"]["x"] = {"type": "test.Nope", "params": {}}
    issues = _issues(data)
    where = {(i.node, i.port) for i in issues}
    assert ("scale", "factr") in where and ("ramp", "num_frames") in where and ("x", "") in where


@pytest.mark.parametrize("mutate, node, port, text", [
    (lambda d: d["nodes"]["scale"].update(type="test.Scael"), "scale", "", "unknown node type 'test.Scael'; did you mean 'test.Scale'"),
    (lambda d: d["nodes"]["scale"]["params"].update(speed=1), "scale", "speed", "unknown parameter"),
    (lambda d: d["nodes"]["scale"]["params"].update(factor="fast"), "scale", "factor", "expected a number"),
    (lambda d: d["edges"].pop(0), "scale", "values", "required input"),
    (lambda d: d["edges"].append(["ramp.values", "total.values"]), "total", "values", "connected twice"),
    (lambda d: d["edges"].append(["ramp.values", "scale.nope"]), "scale", "nope", "no input port"),
    (lambda d: d["edges"].append(["ghost.values", "total.values"]), "total", "values", "unknown node 'ghost'"),
    (lambda d: d["parameters"].update(speed="scale.speed"), "scale", "speed", "graph parameter 'speed'"),
])
def test_validation_error_names_node_and_port(mutate, node, port, text):
    data = _json()
    mutate(data)
    issues = _issues(data)
    match = [i for i in issues if i.node == node and i.port == port and text in i.message]
    assert match, [str(i) for i in issues]
    assert f"node '{node}'" in str(match[0])


def test_type_mismatch_is_reported():
    data = _json()
    data["nodes"]["model"] = {"type": "test.Total", "params": {}}
    data["edges"].append(["ramp.values", "model.values"])
    data["nodes"]["sum"] = {"type": "test.Sum", "params": {}}
    data["edges"] += [["ramp.values", "sum.a"], ["model.total", "sum.b"]]
    issues = _issues(data)
    assert any(i.node == "sum" and i.port == "b" and "type mismatch" in i.message and "JsonValue" in i.message
               for i in issues)


def test_cycle_is_reported():
    data = _json()
    data["nodes"]["sum"] = {"type": "test.Sum", "params": {}}
    data["edges"] = [["ramp.values", "sum.a"], ["scale.scaled", "sum.b"], ["sum.total", "scale.values"],
                     ["scale.scaled", "total.values"]]
    issues = _issues(data)
    assert any("cycle" in i.message and "sum" in i.message and "scale" in i.message for i in issues)


def test_bad_schema_is_reported():
    data = _json()
    data["schema"] = "nodegraph/0"
    assert any("schema" in i.port for i in _issues(data))


def test_add_and_connect_check_immediately():
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp")
    with pytest.raises(GraphError, match="'factor'"):
        g.add("test.Scale", id="s", factor="x")
    total = g.add("test.Total", id="t")
    with pytest.raises(GraphError, match="no output port 'nope'"):
        g.connect(ramp["nope"], total["values"])
    assert g.edges == []


def test_old_type_version_is_migrated_on_load():
    data = _json()
    data["nodes"]["off"] = {"type": "test.Offset", "type_version": 1, "params": {"amount": 2.5}}
    data["edges"] = [["ramp.values", "off.values"], ["off.shifted", "scale.values"], ["scale.scaled", "total.values"]]
    g = Graph.from_json(data)
    assert g.nodes["off"].params == {"offset": 2.5} and g.nodes["off"].type_version == 2
    assert g.migrations == ["off: test.Offset v1 -> v2"]


def test_newer_type_version_is_an_error():
    data = _json()
    data["nodes"]["scale"]["type_version"] = 9
    assert any(i.node == "scale" and "newer" in i.message for i in _issues(data))


def test_graph_parameters_apply_and_parse_strings():
    g = Graph.from_json(_json())
    g.apply({"factor": "3.5"}, strings=True)
    assert g.nodes["scale"].params["factor"] == "3.5" or g.nodes["scale"].params["factor"] == 3.5
    assert g.instantiate("scale").params.factor == 3.5
    with pytest.raises(GraphError, match="unknown graph parameter"):
        g.apply({"speed": 1})


def test_unknown_type_is_the_only_issue_of_its_many_input():
    """Two edges into one port of an unknown type: the unknown type is reported, not 'connected twice'
    (whether the port takes many inputs cannot be known)."""
    data = _json()
    data["nodes"]["report"] = {"type": "test.NoSuchReport", "type_version": 1, "params": {}}
    data["edges"] += [["ramp.values", "report.series"], ["scale.scaled", "report.series"]]
    issues = _issues(data)
    assert [(i.node, i.port) for i in issues] == [("report", "")]
    assert "unknown node type 'test.NoSuchReport'" in issues[0].message


def test_unknown_type_without_plugins_says_how_to_load_them(monkeypatch):
    """Run from a source checkout without installing, no entry point lists the built-in nodes: the
    error says so and how to fix it."""
    from nodegraph import registry

    monkeypatch.setattr(registry, "_PLUGINS_LOADED", False)
    monkeypatch.setattr(registry, "_PLUGIN_MODULES", [])
    monkeypatch.setattr(registry, "entry_points", lambda group: [])
    monkeypatch.delenv("NODEGRAPH_PLUGINS", raising=False)
    with pytest.raises(KeyError, match="NODEGRAPH_PLUGINS=nodes"):
        registry.get("fit.NoSuchNode")
    monkeypatch.setattr(registry, "_PLUGINS_LOADED", False)
    monkeypatch.setenv("NODEGRAPH_PLUGINS", "nodes")
    with pytest.raises(KeyError) as info:
        registry.get("fit.NoSuchNode")
    assert "NODEGRAPH_PLUGINS=nodes" not in str(info.value)
