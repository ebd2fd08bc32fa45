"""Mutated copies of the shipped graphs: every one is refused with exit 2, naming the node or the
file, never with a traceback."""

from __future__ import annotations

import json
import random
from pathlib import Path
from typing import Any, Callable

import pytest

from nodegraph import registry
from nodegraph.cli import main

GRAPHS = sorted(Path(__file__).resolve().parents[1].glob("graphs/*.json"))
SEED = 20261201


def _node(data: dict, rng: random.Random) -> str:
    return rng.choice(sorted(data["nodes"]))


def _delete_key(data: dict, rng: random.Random) -> str:
    choice = rng.choice(["schema", "nodes", "type", "edge_end"])
    if choice in ("schema", "nodes"):
        del data[choice]
        return ""
    if choice == "type":
        node = _node(data, rng)
        del data["nodes"][node]["type"]
        return node
    edge = rng.randrange(len(data["edges"]))
    data["edges"][edge] = data["edges"][edge][:1]
    return ""


def _wrong_type(data: dict, rng: random.Random) -> str:
    node = _node(data, rng)
    params = data["nodes"][node].setdefault("params", {})
    if params and rng.random() < 0.7:
        name = rng.choice(sorted(params))
        value = params[name]
        params[name] = {"nested": True} if not isinstance(value, dict) else "a string"
        return node
    data["nodes"][node]["type_version"] = rng.choice(["1", 0, -3, 1.5, None, True])
    return node


def _non_finite(data: dict, rng: random.Random) -> str:
    node = _node(data, rng)
    params = data["nodes"][node].setdefault("params", {})
    numeric = [k for k, v in params.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    name = rng.choice(numeric) if numeric else "num_frames"
    params[name] = rng.choice([float("inf"), float("-inf"), float("nan")])
    return node


def _unknown_type(data: dict, rng: random.Random) -> str:
    node = _node(data, rng)
    data["nodes"][node]["type"] = data["nodes"][node]["type"] + "Typo"
    return node


def _unknown_param(data: dict, rng: random.Random) -> str:
    node = _node(data, rng)
    data["nodes"][node].setdefault("params", {})["no_such_param"] = 1
    return node


def _unknown_port(data: dict, rng: random.Random) -> str:
    edge = rng.randrange(len(data["edges"]))
    src, dst = data["edges"][edge]
    data["edges"][edge] = [src, dst + "_nope"]
    return dst.split(".")[0]


def _cycle(data: dict, rng: random.Random) -> str:
    src, dst = data["edges"][rng.randrange(len(data["edges"]))]
    back_src = dst.split(".")[0] + ".nope_out"
    data["edges"].append([back_src, src.split(".")[0] + ".nope_in"])
    # a real cycle through existing ports: connect a node's output to its own upstream's input
    a, b = src.split(".")[0], dst.split(".")[0]
    data["edges"].append([f"{b}.{src.split('.')[1]}", f"{a}.{dst.split('.')[1]}"])
    return ""


def _is_list_port(data: dict, ref: str) -> bool:
    node, _, port = ref.rpartition(".")
    decl = registry.get(data["nodes"][node]["type"]).inputs.get(port)
    return bool(decl is not None and decl.many)


def _doubled_input(data: dict, rng: random.Random) -> str:
    singles = [e for e in data["edges"] if not _is_list_port(data, e[1])]
    src, dst = rng.choice(singles)
    data["edges"].append([src, dst])
    return dst.split(".")[0]


def _dangling_parameter(data: dict, rng: random.Random) -> str:
    data.setdefault("parameters", {})["ghost"] = "no_node.path"
    return ""


MUTATIONS: list[Callable[[dict, random.Random], str]] = [
    _delete_key, _wrong_type, _non_finite, _unknown_type, _unknown_param, _unknown_port, _cycle,
    _doubled_input, _dangling_parameter]


def _cases() -> list[tuple[Path, str, int]]:
    return [(graph, m.__name__, seed) for graph in GRAPHS for m in MUTATIONS for seed in range(3)]


def _check_refused(path: Path, capsys: Any, named: str) -> None:
    for argv in (["validate", str(path)], ["run", str(path), "--explain"]):
        code = main(argv)
        captured = capsys.readouterr()
        assert code == 2, (argv, captured.out, captured.err)
        assert "Traceback" not in captured.err
        assert str(path) in captured.err or (named and f"'{named}'" in captured.err), captured.err


@pytest.mark.parametrize("graph, mutation, seed", _cases(),
                         ids=[f"{g.stem}-{m}-{s}" for g, m, s in _cases()])
def test_mutated_graph_is_refused_with_exit_2(tmp_path, capsys, graph, mutation, seed):
    rng = random.Random(f"{SEED}-{graph.name}-{mutation}-{seed}")
    data = json.loads(graph.read_text())
    named = globals()[mutation](data, rng)
    path = tmp_path / graph.name
    path.write_text(json.dumps(data))  # NaN/Infinity are written as JSON does not allow
    _check_refused(path, capsys, named)


@pytest.mark.parametrize("content", [
    b"", b"\x00\x01\x02garbage", b"\xff\xfe{", b"{", b"[]", b"null", b'"text"', b"42",
    b"[" * 100_000 + b"]" * 100_000, b'{"a":' * 50_000 + b"1" + b"}" * 50_000,
])
def test_garbage_files_are_refused_with_exit_2(tmp_path, capsys, content):
    path = tmp_path / "garbage.json"
    path.write_bytes(content)
    _check_refused(path, capsys, "")


@pytest.mark.parametrize("graph", GRAPHS, ids=[g.stem for g in GRAPHS])
def test_truncated_graph_files_are_refused(tmp_path, capsys, graph):
    text = graph.read_bytes()
    rng = random.Random(f"{SEED}-{graph.name}")
    for cut in sorted(rng.sample(range(1, len(text) - 1), 4)):
        path = tmp_path / graph.name
        path.write_bytes(text[:cut])
        _check_refused(path, capsys, "")


def test_shipped_graphs_are_valid(capsys):
    assert main(["validate", *map(str, GRAPHS)]) == 0
    from nodegraph import Graph

    for path in GRAPHS:  # the JSON form survives a load and a dump unchanged
        text = Graph.load(path).dumps()
        assert Graph.from_json(json.loads(text)).dumps() == text, path
