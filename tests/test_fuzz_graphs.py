"""Mutated copies of the shipped graphs: every one is refused with exit 2, naming the node or the
file, never with a traceback."""

from __future__ import annotations

import functools
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


# -- bad parameter values and bad files given to the shipped graphs on the command line -----------
# Each case is refused with exit 2 before any heavy node runs (at validation, planning or the
# first file read), naming the node and the parameter, and leaves none of the graph's outputs.

@functools.lru_cache(maxsize=1)
def _face_capture() -> dict:
    """8 still frames of the ICT face region (the bundled removal network's topology)."""
    import numpy as np

    from nodes.io.face_model import load_face_model

    face = load_face_model(region="face")
    return {"vertices": np.repeat(face.neutral[None], 8, axis=0), "faces": face.faces, "fps": 30.0,
            "rigid": np.repeat(np.eye(4)[None], 8, axis=0)}


def _inputs(folder: Path) -> dict[str, Path]:
    """Tiny good inputs and bad files of every kind a user mistypes."""
    import numpy as np

    from nodes.io.image import write_image

    files = {"plates": folder / "plate.%04d.png", "capture": folder / "capture.npz",
             "folder": folder / "a_folder", "garbage_npz": folder / "garbage.npz",
             "garbage_png": folder / "garbage.0000.png", "text_mp4": folder / "notes.mp4",
             "garbage_json": folder / "camera.json", "garbage_model": folder / "model.safetensors",
             "empty_npz": folder / "empty.npz", "a_file": folder / "plain_file"}
    for f in range(2):
        write_image(folder / f"plate.{f:04d}.png", np.full((32, 40, 3), 90 + 40 * f, np.uint8),
                    ["R", "G", "B"], "uint8")
    rng = np.random.default_rng(3)
    np.savez(files["capture"], vertices=rng.normal(size=(8, 24, 3)).astype(np.float32),
             faces=(np.arange(60, dtype=np.int32) % 24).reshape(20, 3), fps=30.0,
             rigid=np.repeat(np.eye(4)[None], 8, axis=0))
    face = _face_capture()
    files["face_capture"] = folder / "face_capture.npz"
    np.savez(files["face_capture"], **face)
    files["takes"] = folder / "takes"
    files["takes"].mkdir()
    # 16 frames: enough to train on at 30 fps (margin 6 frames each side), so that the cases'
    # culprits, not a run too short to train, are what TrainRemovalTakes' planning check refuses
    np.savez(files["takes"] / "take_a.npz", **face | {"vertices": np.repeat(face["vertices"][:1], 16, axis=0),
                                                     "rigid": np.repeat(face["rigid"][:1], 16, axis=0)})
    files["neutral"] = folder / "neutral.npz"  # one frame: dynamics.LoadNeutral refuses a take
    np.savez(files["neutral"], **face | {"vertices": face["vertices"][:1], "rigid": face["rigid"][:1]})
    from nodes.dynamics.files import BUNDLED_REMOVAL

    files["model_file"] = BUNDLED_REMOVAL
    # the bundled network labelled a synthesis network: dynamics_retarget's H, enough for cases
    # refused before any network runs (dynamics.SynthesizeDynamics checks the kind while planning)
    from nodegraph import TorchModel
    from nodegraph.models import load_model, save_model

    removal = load_model(BUNDLED_REMOVAL)
    files["synthesis_file"] = folder / "synthesis.safetensors"
    save_model(TorchModel(removal.architecture, removal.config | {"kind": "synthesis"}, removal.state,
                          removal.normalization), files["synthesis_file"])
    files["folder"].mkdir()
    files["garbage_npz"].write_bytes(b"PK\x03\x04 not really a zip")
    files["garbage_png"].write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    files["text_mp4"].write_text("not a video")
    files["garbage_json"].write_text('{"fx": ')
    files["garbage_model"].write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    files["empty_npz"].write_bytes(b"")
    files["a_file"].write_text("a file, not a folder")
    from nodes.io.livelink import LIVE_LINK_SHAPES

    files["take_csv"] = folder / "take.csv"
    files["take_csv"].write_text("Timecode," + ",".join(LIVE_LINK_SHAPES) + "\n" + "".join(
        f"10:00:{f // 30:02d}:{f % 30:02d}.000," + ",".join("0.1" for _ in LIVE_LINK_SHAPES) + "\n"
        for f in range(34)))  # past a second: the rate (30) is inferred
    return files


OUTPUTS = {  # every output parameter of the graph, set to a path under the test's folder
    "landmarks": {"output": "out/landmarks.npz", "report": "out/overlays"},
    "fit_video": {"output": "out/fit.npz", "report": "out/fit"},
    "fit_video_temporal": {"output": "out/fit.npz", "report": "out/fit", "motion_report": "out/motion"},
    "dynamics_remove": {"output": "out/quasistatic.npz"},
    "dynamics_retarget": {"output": "out/retargeted.npz"},
    "dynamics_train": {"model": "out/removal.safetensors", "synthesis_model": "out/synthesis.safetensors"},
    "dynamics_train_captures": {"model": "out/removal.safetensors",
                                "synthesis_model": "out/synthesis.safetensors", "report": "out/report.json"},
    "stabilize": {"output": "out/stab.npz", "report": "out/report"},
    "livelink_to_render": {"images": "out/render.%04d.png"},
    "synthetic_capture": {"capture": "out/c.npz", "truth": "out/t.npz", "truth_rigid": "out/r.npz",
                          "expressions": "out/e.json", "report": "out/report"},
    "video_to_animation": {"output": "out/fit.npz", "report": "out/fit", "motion_report": "out/motion",
                           "csv": "out/a.csv", "usd": "out/a.usd", "gltf": "out/a.glb"},
    "demo": {"html": "out/index.html", "report": "out/stab", "dynamics_report": "out/dyn", "fit_report": "out/fit",
             "motion_report": "out/motion"},
}
GOOD = {  # good inputs, by name in `_inputs`
    "landmarks": {"images": "plates"},
    "fit_video": {"images": "plates", "camera": ""},
    "fit_video_temporal": {"images": "plates", "camera": ""},
    "dynamics_remove": {"capture": "face_capture", "skull": "face_capture", "model": ""},
    "dynamics_retarget": {"removal_model": "model_file", "synthesis_model": "synthesis_file"},
    "dynamics_train": {},
    "dynamics_train_captures": {"captures": "takes", "neutral": "neutral"},
    "stabilize": {"capture": "capture"},
    "livelink_to_render": {"csv": "take_csv"},
    "synthetic_capture": {},
    "video_to_animation": {"images": "plates", "camera": ""},
    "demo": {},
}
# (graph, parameter, value (an `_inputs` name, "@name" for that file's path as an output, or a
# literal), the node the error names)
BAD_VALUES = [
    ("landmarks", "images", "garbage_png", "frames"),
    ("landmarks", "images", "text_mp4", "frames"),
    ("landmarks", "images", "folder", "frames"),
    ("landmarks", "images", "missing.%04d.png", "frames"),
    ("landmarks", "face", "biggest", "track"),
    ("landmarks", "face", "-1", "track"),
    ("landmarks", "face", "[1, 2, 3]", "track"),
    ("landmarks", "output", "out/landmarks.txt", "save"),
    ("landmarks", "output", "@garbage_png", "save"),
    ("landmarks", "report", "@a_file", "overlays"),
    ("fit_video", "images", "garbage_png", "frames"),
    ("fit_video", "camera", "garbage_json", "camera"),
    ("fit_video", "camera", "folder", "camera"),
    ("fit_video", "camera", "camera.txt", "camera"),
    ("fit_video", "face", "centre_left", "track"),
    ("fit_video", "output", "out/fit.png", "save"),
    ("fit_video", "report", "@a_file", "report"),
    ("fit_video_temporal", "images", "text_mp4", "frames"),
    ("fit_video_temporal", "camera", "garbage_json", "camera"),
    ("fit_video_temporal", "output", "out/fit.json", "save"),
    ("fit_video_temporal", "motion_report", "@a_file", "motion"),
    ("dynamics_remove", "capture", "garbage_npz", "load"),
    ("dynamics_remove", "capture", "empty_npz", "load"),
    ("dynamics_remove", "capture", "missing.npz", "load"),
    ("dynamics_remove", "skull", "garbage_npz", "skull"),
    ("dynamics_remove", "model", "garbage_model", "network"),
    ("dynamics_remove", "model", "model.pt", "network"),
    ("dynamics_remove", "fps", "-1", "remove"),
    ("dynamics_remove", "fps", "fast", "remove"),
    ("dynamics_remove", "fps", "1e308", "remove"),
    ("dynamics_remove", "output", "@face_capture", "save"),
    ("dynamics_retarget", "removal_model", "garbage_model", "removal"),
    ("dynamics_retarget", "synthesis_model", "missing.safetensors", "synthesis"),
    ("dynamics_retarget", "region", "no_such_region", "face"),
    ("dynamics_retarget", "max_vertices", "-5", "face"),
    ("dynamics_retarget", "output", "out/retargeted.txt", "save"),
    ("dynamics_train", "epochs", "-1", "train_removal"),
    ("dynamics_train", "rows", "many", "train_removal"),
    ("dynamics_train", "samples", "0", "train_removal"),
    ("dynamics_train", "region", "no_such_region", "face"),
    ("dynamics_train", "max_vertices", "3", "face"),
    ("dynamics_retarget", "max_vertices", "9", "face"),
    ("dynamics_train", "model", "out/removal.pt", "save_removal"),
    ("dynamics_train", "synthesis_model", "@a_file", "save_synthesis"),
    ("dynamics_train_captures", "captures", "missing/take_*.npz", "takes"),
    ("dynamics_train_captures", "neutral", "garbage_npz", "neutral"),
    ("dynamics_train_captures", "fps", "-1", "takes"),
    ("dynamics_train_captures", "epochs", "2.5", "train"),
    ("dynamics_train_captures", "model", "out/removal.txt", "save"),
    ("dynamics_train_captures", "model", "@neutral", "save"),
    ("dynamics_train_captures", "neutral", "face_capture", "neutral"),  # a take (8 frames) as the neutral
    ("dynamics_train_captures", "report", "out/report.npz", "report"),
    ("stabilize", "capture", "garbage_npz", "load"),
    ("stabilize", "capture", "folder", "load"),
    ("stabilize", "output", "@capture", "save"),
    ("stabilize", "output", "out/stab.txt", "save"),
    ("stabilize", "report", "@a_file", "report"),
    ("stabilize", "group", "no_such_group", "stab"),
    ("livelink_to_render", "csv", "a_file", "csv"),
    ("livelink_to_render", "csv", "missing.csv", "csv"),
    ("livelink_to_render", "fps", "-1", "csv"),
    ("livelink_to_render", "distance_cm", "0", "csv"),
    ("livelink_to_render", "images", "out/render.%04d.txt", "save"),
    ("synthetic_capture", "num_frames", "0", "performance"),
    ("synthetic_capture", "capture", "out/c.txt", "save_capture"),
    ("synthetic_capture", "truth_rigid", "out/r.obj", "save_rigid"),
    ("video_to_animation", "csv", "out/a.txt", "csv"),
    ("video_to_animation", "usd", "out/a.obj", "usd"),
    ("video_to_animation", "gltf", "out/a.gltf", "gltf"),
    ("video_to_animation", "output", "@garbage_png", "save"),
    ("demo", "num_frames", "-5", "performance"),
    ("demo", "html", "out/index.txt", "html"),
    ("demo", "report", "@a_file", "report"),
]


@pytest.mark.parametrize("graph, name, value, node", BAD_VALUES,
                         ids=[f"{g}-{n}-{v}" for g, n, v, _ in BAD_VALUES])
def test_bad_parameter_or_file_is_exit_2_and_writes_nothing(tmp_path, capsys, graph, name, value, node):
    files = _inputs(tmp_path)
    outputs = {k: tmp_path / v for k, v in OUTPUTS[graph].items()}
    params = {k: str(files[v]) if v else "" for k, v in GOOD[graph].items()} | {k: str(v) for k, v in outputs.items()}
    if value.startswith("@"):
        params[name] = str(files[value[1:]])
    else:
        params[name] = str(files[value]) if value in files else (
            str(tmp_path / value) if "/" in value or "." in value and not value[0].isdigit()
            and not value.startswith("-") else value)
    before = {p: p.read_bytes() for p in files.values() if p.is_file()}
    argv = ["run", f"graphs/{graph}.json", *(f"{k}={v}" for k, v in params.items()),
            "--no-cache", "--scheduler", "sync"]
    code = main(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and f"'{node}'" in err, err
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").rglob("*")), err
    assert {p: p.read_bytes() for p in files.values() if p.is_file()} == before  # inputs untouched
