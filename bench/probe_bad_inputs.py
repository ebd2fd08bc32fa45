"""Probe every shipped graph with bad inputs, as a new user would, and print a verdict table.

    python bench/probe_bad_inputs.py [--long] [--only-long] [--only 'S1|S2'] [--start N --end M] [--jobs N]
                                     [--keep DIR] [--log FILE]

Each probe runs `nodegraph run graphs/<graph>.json ...` (or `validate`) in a subprocess, on tiny
inputs made here (a 12-frame synthetic whole-head capture with known skull motion, 80x64 plates,
a Live Link CSV, camera files, the bundled removal network and spoiled copies of each). A probe
expects one of:

- `refuse`: exit 2, no traceback, no staging folder or output left behind, the previous outputs
  and every input byte-identical, and no error line printed twice;
- `run`: exit 0 (and, where given, a check of the answer against the known truth, e.g. the
  stabilization of 3 or 4 vertices against the synthetic capture's true skull motion);
- `either`: a correct answer (exit 0 and the check) or a clean refusal (as `refuse`);
- `crash`: exit 1 from a node that raises as a bug would (a plugin node type made here), with
  its traceback printed once however many chunks hit it (the README's promise), and the run's
  outputs held back (the previous ones byte-identical).

A refusal of an output path or a model file must also come before anything runs (`early`: no
`FAILED` task line), and a probe may require the refusal to name the parameter or path at fault.

Besides the hand-written cases, every output path parameter of every shipped graph is pointed at
the run's input file, the inputs' folder, a path inside an input folder, a parent that is a file,
a read-only folder (run with root's capabilities dropped by `setpriv`, so that permissions apply
though the probe runs as root) and, on the light graphs, missing parent folders (made). Also:
more camera values, degenerate captures (one vertex, one point, duplicated vertices), odd images
and videos (0 and 1 frame, 1x1, 3x5, 8000x8, 16-bit, grey, RGBA), spoiled graph files (wrong
types, unknown keys, missing nodes, a cycle, not JSON), bad `--set` and `--frames` values, and an
unwritable cache folder.

The verdict is `ok` or `FAIL: why`. The table is printed as markdown: probe, exit code, the
error's first line (or the answer's figure), verdict; the last line counts the failures. The
exit status is 1 when any probe failed. `--long` adds `--frames a:b` on the heavy graphs (the
fits, the demo, the dynamics training): minutes each on a loaded machine.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
GRAPHS = ROOT / "graphs"
STAGING = ".nodegraph-staging."


@dataclass
class Probe:
    """One command and what it must do."""

    name: str
    argv: list[str]  # after `nodegraph`; "{in}" and "{out}" are replaced by the folders
    expect: str = "refuse"  # refuse | run | either
    check: Callable[[Path], str] | None = None  # on exit 0: "" when right, else what is wrong
    setup: Callable[[Path], None] | None = None  # before the run, in the probe's output folder
    keep: bool = False  # outputs written by `setup` must stay unchanged (a failed run keeps them)
    long: bool = False
    timeout: float = 600.0
    early: bool = False  # a refusal must come before anything runs (no FAILED task)
    env: dict[str, str] = field(default_factory=dict)  # extra environment ("{in}" replaced)
    user: bool = False  # run without root's capabilities (setpriv): file permissions apply
    names: str = ""  # a refusal must name this ("{in}" / "{out}" replaced): the parameter or path at fault


@dataclass
class Result:
    probe: Probe
    code: int
    seconds: float
    message: str
    verdict: str
    stderr: str = field(repr=False, default="")


# -- inputs ---------------------------------------------------------------------------------------

def _save_npz(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def make_inputs(folder: Path) -> dict:
    """Every good and bad input the probes use, under `folder`; returns facts the checks need."""
    from nodegraph import Camera, TorchModel
    from nodegraph.models import load_model, save_model
    from nodes.dynamics.files import BUNDLED_REMOVAL
    from nodes.io.camera import save_camera
    from nodes.io.face_model import load_face_model
    from nodes.io.image import write_image
    from nodes.io.livelink import LIVE_LINK_ANGLES, LIVE_LINK_SHAPES

    folder.mkdir(parents=True, exist_ok=True)
    env = os.environ | {"PYTHONPATH": str(ROOT)}
    # a whole-head capture with known skull motion (synthetic_capture.json, 12 frames)
    subprocess.run([*_nodegraph(), "run", str(GRAPHS / "synthetic_capture.json"), f"capture={folder}/head.npz",
                    f"truth={folder}/head_truth.npz", f"truth_rigid={folder}/head_rigid.npz",
                    f"expressions={folder}/head_expr.json", f"report={folder}/head_report", "num_frames=12",
                    "--no-cache", "--progress", "none"], check=True, env=env, capture_output=True)
    head = dict(np.load(folder / "head.npz"))
    rigid = np.load(folder / "head_rigid.npz")["matrices"]
    rigid_ids = head["groups/rigid"]
    v = head["vertices"]
    # 3, 4 and 10 well-spread rigid vertices; 5 collinear points moved by the true skull motion
    spread = rigid_ids[np.argsort(v[0, rigid_ids, 0])]
    pick = {3: spread[[0, len(spread) // 2, -1]], 4: spread[[0, len(spread) // 3, 2 * len(spread) // 3, -1]],
            10: spread[np.linspace(0, len(spread) - 1, 10).astype(int)]}
    for n, ids in pick.items():
        faces = np.array([[0, 1, 2]] + [[0, i, i + 1] for i in range(2, n - 1)], np.int32)
        _save_npz(folder / f"rigid{n}.npz", vertices=v[:, ids], faces=faces, fps=head["fps"])
    line_skull = np.stack([np.array([-5.0, 2.0, 3.0]) + t * np.array([1.0, 0.3, 0.2]) for t in range(5)])
    line_world = np.einsum("fij,vj->fvi", rigid[:, :3, :3], line_skull) + rigid[:, None, :3, 3]
    _save_npz(folder / "collinear.npz", vertices=line_world.astype(np.float32),
              faces=np.array([[0, 1, 2], [2, 3, 4]], np.int32), fps=head["fps"])
    # small captures and bad ones (24 vertices, 8 frames)
    rng = np.random.default_rng(3)
    base = rng.normal(scale=5.0, size=(24, 3)).astype(np.float32)
    small = {"vertices": base + rng.normal(scale=0.05, size=(8, 24, 3)).astype(np.float32),
             "faces": (np.arange(60, dtype=np.int32) % 24).reshape(20, 3), "fps": np.float64(30.0)}
    _save_npz(folder / "small.npz", **small)
    _save_npz(folder / "fps_negative.npz", **small | {"fps": np.float64(-30.0)})
    _save_npz(folder / "fps_huge.npz", **small | {"fps": np.float64(1e308)})
    faces = small["faces"].copy()
    faces[3, 1] = 24
    _save_npz(folder / "face_index_24.npz", **small | {"faces": faces})
    faces = small["faces"].copy()
    faces[0, 0] = -1
    _save_npz(folder / "face_index_neg.npz", **small | {"faces": faces})
    _save_npz(folder / "faces_float.npz", **small | {"faces": small["faces"].astype(np.float32) + 0.5})
    far = small["vertices"].copy()
    far[2, 5, 1] = 1e20
    _save_npz(folder / "coords_1e20.npz", **small | {"vertices": far})
    _save_npz(folder / "all_1e20.npz", **small | {"vertices": np.full_like(far, 1e20)})
    nan = small["vertices"].copy()
    nan[4, 7, 0] = np.nan
    _save_npz(folder / "coords_nan.npz", **small | {"vertices": nan})
    _save_npz(folder / "zero_frames.npz", **small | {"vertices": small["vertices"][:0]})
    _save_npz(folder / "vertices_2d.npz", **small | {"vertices": small["vertices"][0]})
    _save_npz(folder / "no_vertices.npz", faces=small["faces"], fps=30.0)
    _save_npz(folder / "still.npz", **small | {"vertices": np.repeat(base[None], 8, axis=0)})
    good = (folder / "small.npz").read_bytes()
    (folder / "truncated.npz").write_bytes(good[: len(good) // 2])
    (folder / "garbage.npz").write_bytes(b"PK\x03\x04 not really a zip")
    (folder / "empty.npz").write_bytes(b"")
    (folder / "garbage.usda").write_text("#usda 1.0\n( nonsense")
    # an OBJ pattern whose second file has a face index past its vertices
    for f in range(3):
        lines = [f"v {x:.4f} {y:.4f} {z:.4f}" for x, y, z in small["vertices"][f]]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in small["faces"]]
        if f == 1:
            lines.append("f 1 2 99")
        (folder / f"mesh.{f:04d}.obj").write_text("\n".join(lines) + "\n")
    # the ICT face region (the bundled removal network's topology), skulls
    face = load_face_model(region="face")
    f8 = np.repeat(face.neutral[None], 8, axis=0).astype(np.float32)
    eye = np.repeat(np.eye(4)[None], 8, axis=0)
    _save_npz(folder / "face.npz", vertices=f8, faces=face.faces, fps=30.0, rigid=eye)
    _save_npz(folder / "face_fps_negative.npz", vertices=f8, faces=face.faces, fps=-30.0, rigid=eye)
    _save_npz(folder / "face_neutral.npz", vertices=face.neutral[None].astype(np.float32), faces=face.faces)
    _save_npz(folder / "skull_short.npz", rigid=eye[:5])
    bad = eye.copy()
    bad[3, 1, 3] = np.nan
    _save_npz(folder / "skull_nan.npz", rigid=bad)
    bad = eye.copy()
    bad[2, 0, 3] = 1e20
    _save_npz(folder / "skull_1e20.npz", rigid=bad)
    bad = eye.copy()
    bad[1, :3, :3] *= 2.0
    _save_npz(folder / "skull_scaled.npz", rigid=bad)
    _save_npz(folder / "skull_shape.npz", rigid=eye[:, :3, :3])
    # takes for dynamics_train_captures
    (folder / "takes").mkdir(exist_ok=True)
    _save_npz(folder / "takes" / "hold_a.npz", vertices=f8, faces=face.faces, fps=30.0, rigid=eye)
    (folder / "takes_empty").mkdir(exist_ok=True)
    (folder / "takes_small").mkdir(exist_ok=True)
    _save_npz(folder / "takes_small" / "hold_a.npz", **small)
    (folder / "takes_fps").mkdir(exist_ok=True)
    _save_npz(folder / "takes_fps" / "hold_a.npz", vertices=f8, faces=face.faces, fps=-5.0, rigid=eye)
    # model files: the bundled removal network and spoiled copies with its metadata
    model = load_model(BUNDLED_REMOVAL)
    shutil.copy(BUNDLED_REMOVAL, folder / "removal.safetensors")
    state = dict(model.state)
    first = sorted(k for k in state if k.endswith("weight"))[0]
    spoiled = {"shape": state | {first: state[first][:, :-1]},
               "float64": {k: a.astype(np.float64) for k, a in state.items()},
               "missing": {k: a for k, a in state.items() if k != sorted(state)[-1]},
               "nan": state | {first: np.full_like(state[first], np.nan)}}
    for name, st in spoiled.items():
        save_model(TorchModel(model.architecture, model.config, st, model.normalization),
                   folder / f"model_{name}.safetensors")
    (folder / "model_garbage.safetensors").write_bytes(b"\x08\x00\x00\x00\x00\x00\x00\x00{}garbage")
    (folder / "model_truncated.safetensors").write_bytes(BUNDLED_REMOVAL.read_bytes()[:5000])
    # plates: 80 x 64 grey noise (no face), a gap pattern, garbage and mislabelled files
    for f in range(4):
        write_image(folder / f"plate.{f:04d}.png", rng.uniform(0.25, 0.75, (64, 80, 3)), ["R", "G", "B"], "uint8")
    (folder / "plates").mkdir(exist_ok=True)
    for f in range(3):
        shutil.copy(folder / f"plate.{f % 4:04d}.png", folder / "plates" / f"p.{f:04d}.png")
    for f in (0, 1, 2, 3, 5, 6, 7):
        shutil.copy(folder / f"plate.{f % 4:04d}.png", folder / f"gap.{f:04d}.png")
    (folder / "garbage.0000.png").write_bytes(b"\x89PNG\r\n\x1a\n truncated")
    png = (folder / "plate.0000.png").read_bytes()
    (folder / "cut.0000.png").write_bytes(png[: len(png) // 2])
    shutil.copy(folder / "plate.0000.png", folder / "mislabelled.0000.jpg")
    (folder / "notes.mp4").write_text("not a video")
    _video(folder / "clip.mp4", rng)
    clip = (folder / "clip.mp4").read_bytes()
    (folder / "clip_cut.mp4").write_bytes(clip[: len(clip) // 3])
    # a photo with a face (the astronaut, 256 px) for the long runs
    try:
        from skimage import data, transform

        photo = transform.resize(data.astronaut(), (256, 256), anti_aliasing=True)  # floats in [0, 1]
        for f in range(2):
            write_image(folder / f"astro.{f:04d}.png", photo, ["R", "G", "B"], "uint8")
    except ImportError:
        pass
    # cameras for the 80 x 64 plates
    cam = Camera(fx=110.0, fy=110.0, cx=40.0, cy=32.0, width=80, height=64)
    save_camera(folder / "camera.json", cam)
    text = json.loads((folder / "camera.json").read_text())
    for name, change in {"camera_nan": {"fx": "NaN"}, "camera_negative": {"fx": -110.0},
                         "camera_zero": {"fy": 0.0}, "camera_size": {"width": 1920, "height": 1080},
                         "camera_1e20": {"fx": 1e20}}.items():
        (folder / f"{name}.json").write_text(json.dumps(text | change).replace('"NaN"', "NaN"))
    (folder / "camera_garbage.json").write_text('{"fx": ')
    (folder / "camera_world.json").write_text(json.dumps(text | {"world_to_camera": [[1, 0], [0, 1]]}))
    # Live Link CSVs
    header = ["Timecode", "BlendShapeCount", *LIVE_LINK_SHAPES, *LIVE_LINK_ANGLES]
    rows = [",".join(header)]
    for f in range(6):  # 10 frames apart: the rows pass a second, so the rate is inferred
        rows.append(",".join([f"10:00:{10 * f // 30:02d}:{10 * f % 30:02d}.000", "61", *(f"{0.1 * (f % 3):.3f}" for _ in LIVE_LINK_SHAPES),
                              *("0.05" for _ in LIVE_LINK_ANGLES)]))
    (folder / "take.csv").write_text("\n".join(rows) + "\n")
    (folder / "take_nan.csv").write_text("\n".join(rows[:2] + [rows[2].replace("0.100", "nan", 1)] + rows[3:]))
    (folder / "take_text.csv").write_text("\n".join(rows[:2] + [rows[2].replace("0.100", "abc", 1)] + rows[3:]))
    (folder / "take_header.csv").write_text(rows[0] + "\n")
    (folder / "take_empty.csv").write_text("")
    (folder / "take_other.csv").write_text("a,b,c\n1,2,3\n")
    (folder / "take_binary.csv").write_bytes(b"\xff\xfe\x00garbage\x00")
    (folder / "take_timecode.csv").write_text("\n".join(rows[:2] + [rows[2].replace("10:00:00:10", "xx:yy", 1)]
                                                        + rows[3:]))
    (folder / "take_huge.csv").write_text("\n".join(rows[:2] + [rows[2].replace("0.100", "1e300", 1)] + rows[3:]))
    # graph copies with bad values a graph file can hold
    data = json.loads((GRAPHS / "fit_video_temporal.json").read_text())
    node = next(n for n, s in data["nodes"].items() if "hold_pose" in _params_of(s["type"]))
    data["nodes"][node].setdefault("params", {})["hold_pose"] = "yes"
    (folder / "hold_pose_yes.json").write_text(json.dumps(data))
    data = json.loads((GRAPHS / "dynamics_train_captures.json").read_text())
    data["nodes"]["stabilize"]["params"]["restabilize"] = "false"
    (folder / "restabilize_false.json").write_text(json.dumps(data))
    # a node type that fails as a bug would (exit 1), loaded as a plugin ($NODEGRAPH_PLUGINS)
    (folder / "plugins").mkdir(exist_ok=True)
    (folder / "plugins" / "probe_crash.py").write_text(
        '"""A node that raises as a bug would, for bench/probe_bad_inputs.py."""\n'
        "from nodegraph import FRAMEWISE, In, MeshSequence, Node, Out\n\n\n"
        "class Crash(Node):\n"
        '    """Divide by zero in every chunk."""\n\n'
        '    type_name = "probe.Crash"\n'
        "    version = 1\n"
        "    kind = FRAMEWISE\n"
        '    mesh = In(MeshSequence, doc="any mesh")\n'
        '    out = Out(MeshSequence, doc="never made")\n\n'
        "    def run(self, mesh):\n"
        '        return {"out": mesh.num_frames // 0}\n')
    (folder / "crash.json").write_text(json.dumps({
        "schema": "nodegraph/1",
        "nodes": {"load": {"type": "io.LoadMeshSequence", "type_version": 1, "params": {"path": "small.npz"}},
                  "save": {"type": "io.SaveMeshSequence", "type_version": 1, "params": {"path": "m.npz"}},
                  "crash": {"type": "probe.Crash", "type_version": 1, "params": {}}},
        "edges": [["load.mesh", "save.mesh"], ["load.mesh", "crash.mesh"]],
        "parameters": {"output": {"target": "save.path", "description": "the copy to write"}}}))
    # takes long enough to train on a slice (dynamics_train_captures --frames): 2 held takes of
    # the face region (200 points) with their skull motion, 60 and 120 frames at 120 fps
    from nodes.synth.dynamics import simulate_dynamics

    small_face = load_face_model(region="face", max_vertices=200)
    (folder / "takes_long").mkdir(exist_ok=True)
    for seed, (name, frames) in enumerate((("hold_a", 60), ("hold_b", 120))):
        sim = simulate_dynamics(small_face, motions=["oscillate@8"], expressions=["smile"], segment_frames=frames,
                                fps=120.0, seed=seed)
        _save_npz(folder / "takes_long" / f"{name}.npz", vertices=sim.capture.vertices, faces=small_face.faces,
                  fps=120.0, rigid=sim.skull.matrices)
    _save_npz(folder / "neutral_long.npz", vertices=sim.neutral.vertices, faces=small_face.faces)
    (folder / "a_file").write_text("a file, not a folder")
    make_more_inputs(folder, small, v, rigid, pick[10], head["fps"], rng)
    return {"head_rigid": rigid, "head_vertices": v[0]}


def make_more_inputs(folder: Path, small: dict, v: np.ndarray, rigid: np.ndarray, ids10: np.ndarray,
                     fps: np.ndarray, rng: np.random.Generator) -> None:
    """Inputs of the classes issue 30's hidden probe names that the first rounds did not make:
    degenerate captures, odd images and videos, more camera values, spoiled graph files, a
    read-only folder, a synthesis network for dynamics_retarget's path probes."""
    from nodegraph import TorchModel
    from nodegraph.models import load_model, save_model
    from nodes.dynamics.files import BUNDLED_REMOVAL
    from nodes.io.image import write_image

    # captures: one vertex; every vertex at one (moving) point; the 10 rigid vertices each twice
    _save_npz(folder / "one_vertex.npz", vertices=small["vertices"][:, :1], faces=np.zeros((0, 3), np.int32),
              fps=30.0)
    point = small["vertices"][:, :1].repeat(24, axis=1)
    _save_npz(folder / "one_point.npz", vertices=point, faces=small["faces"], fps=30.0)
    twice = np.concatenate([v[:, ids10], v[:, ids10]], axis=1)
    faces = np.array([[0, 1, 2]] + [[0, i, i + 1] for i in range(2, 19)], np.int32)
    _save_npz(folder / "rigid10_twice.npz", vertices=twice, faces=faces, fps=fps)
    # images: 1x1, 3x5, 8000x8, 16-bit, grayscale, RGBA; a video of 0 frames and one of 1 frame
    for name, (h, w), channels, depth in [("px1x1", (1, 1), ["R", "G", "B"], "uint8"),
                                          ("px3x5", (5, 3), ["R", "G", "B"], "uint8"),
                                          ("px8000x8", (8, 8000), ["R", "G", "B"], "uint8"),
                                          ("deep16", (64, 80), ["R", "G", "B"], "uint16"),
                                          ("grey", (64, 80), ["Y"], "uint8"),
                                          ("rgba", (64, 80), ["R", "G", "B", "A"], "uint8")]:
        for f in range(2):
            write_image(folder / f"{name}.{f:04d}.png", rng.uniform(0.25, 0.75, (h, w, len(channels))), channels,
                        depth)
    _video(folder / "video0.mp4", rng, frames=0)
    _video(folder / "video1.mp4", rng, frames=1)
    # camera values not yet probed
    text = json.loads((folder / "camera.json").read_text())
    for name, change in {"camera_fx0": {"fx": 0.0}, "camera_fx_huge": {"fx": 1e308}, "camera_cx_inf": {"cx": "INF"},
                         "camera_cy_nan": {"cy": "NaN"}, "camera_width0": {"width": 0},
                         "camera_height_neg": {"height": -64}, "camera_fx_text": {"fx": "abc"},
                         "camera_fx_bool": {"fx": True}}.items():
        (folder / f"{name}.json").write_text(json.dumps(text | change).replace('"NaN"', "NaN")
                                             .replace('"INF"', "Infinity"))
    no_fy = dict(text)
    no_fy.pop("fy", None)
    (folder / "camera_no_fy.json").write_text(json.dumps(no_fy))
    # graph files: wrong types, unknown keys, missing nodes, a cycle (copies of stabilize.json)
    base = json.loads((GRAPHS / "stabilize.json").read_text())
    stab = next(n for n, spec in base["nodes"].items() if spec["type"] == "stabilize.ModePursuit")
    load = next(n for n, spec in base["nodes"].items() if "max_vertices" not in spec.get("params", {})
                and spec["type"].startswith("io.Load"))

    def spoiled(name: str, change: Callable[[dict], None]) -> None:
        data = json.loads(json.dumps(base))
        change(data)
        (folder / f"graph_{name}.json").write_text(json.dumps(data))

    spoiled("number_as_text", lambda d: d["nodes"][stab].setdefault("params", {}).update(max_vertices="many"))
    spoiled("number_as_numeral_text", lambda d: d["nodes"][stab].setdefault("params", {}).update(max_vertices="400"))
    spoiled("bool_as_number", lambda d: d["nodes"][stab].setdefault("params", {}).update(compile=0))
    spoiled("list_for_text", lambda d: d["nodes"][stab].setdefault("params", {}).update(group=["rigid"]))
    spoiled("unknown_param", lambda d: d["nodes"][stab].setdefault("params", {}).update(nosuch=1))
    spoiled("unknown_node_key", lambda d: d["nodes"][stab].update(colour="red"))
    spoiled("unknown_top_key", lambda d: d.update(extra={"a": 1}))
    spoiled("edge_to_missing_node", lambda d: d["edges"].append([f"{load}.mesh", "nosuch.capture"]))
    spoiled("missing_node_in_parameter", lambda d: d["parameters"].update(bad={"target": "nosuch.path"}))
    spoiled("unknown_type", lambda d: d["nodes"][stab].update(type="stabilize.NoSuch"))
    spoiled("type_version_99", lambda d: d["nodes"][stab].update(type_version=99))
    spoiled("type_version_text", lambda d: d["nodes"][stab].update(type_version="one"))
    spoiled("nodes_a_list", lambda d: d.update(nodes=list(d["nodes"])))
    spoiled("edge_of_one_end", lambda d: d["edges"].append([f"{load}.mesh"]))
    spoiled("schema_2", lambda d: d.update(schema="nodegraph/2"))
    spoiled("params_null", lambda d: d["nodes"][stab].update(params=None))

    def cycle(d: dict) -> None:  # two mesh nodes feeding each other
        d["nodes"]["smooth_a"] = {"type": "mesh.SelectRegion", "type_version": 1, "params": {}}
        d["nodes"]["smooth_b"] = {"type": "mesh.SelectRegion", "type_version": 1, "params": {}}
        d["edges"] += [["smooth_a.region", "smooth_b.mesh"], ["smooth_b.region", "smooth_a.mesh"]]
    spoiled("cycle", cycle)
    (folder / "graph_not_json.json").write_text('{"schema": "nodegraph/1", "nodes": {')
    (folder / "graph_empty.json").write_text("")
    (folder / "graph_array.json").write_text("[1, 2, 3]")
    # a read-only folder (root-owned, mode 555) for probes run as another user
    (folder / "readonly").mkdir(exist_ok=True)
    (folder / "readonly" / "keep.txt").write_text("untouched")
    os.chmod(folder / "readonly", 0o555)
    # dynamics_retarget's H for the path probes: the bundled network labelled a synthesis network
    removal = load_model(BUNDLED_REMOVAL)
    save_model(TorchModel(removal.architecture, removal.config | {"kind": "synthesis"}, removal.state,
                          removal.normalization), folder / "synthesis_label.safetensors")


def _params_of(type_name: str) -> list[str]:
    from nodegraph import registry

    return list(registry.get(type_name).Params.model_fields)


def _video(path: Path, rng: np.random.Generator, frames: int = 12) -> None:
    import av

    with av.open(str(path), "w") as container:
        stream = container.add_stream("mpeg4", rate=24)
        stream.width, stream.height, stream.pix_fmt = 80, 64, "yuv420p"
        for _ in range(frames):
            frame = av.VideoFrame.from_ndarray(rng.integers(0, 255, (64, 80, 3), dtype=np.uint8), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
        if not frames:  # no packet muxed: write the header anyway (a file, not nothing)
            container.start_encoding()


def _nodegraph() -> list[str]:
    exe = Path(sys.executable).with_name("nodegraph")
    return [str(exe)] if exe.exists() else [sys.executable, "-c", "import sys; from nodegraph.cli import main; "
                                                                    "sys.exit(main())"]


# -- checks of answers ----------------------------------------------------------------------------

def _rotation_deg(a: np.ndarray) -> np.ndarray:
    return np.degrees(np.arccos(np.clip((np.trace(a, axis1=-2, axis2=-1) - 1) / 2, -1, 1)))


def stabilization_error(out: Path, truth: np.ndarray, head: np.ndarray) -> tuple[float, float]:
    """Largest rotation (degrees) and head-vertex distance (cm) between the stabilization's
    motion relative to frame 0 and the true one (both map frame 0's world to frame f's)."""
    rigid = np.load(out)["rigid"].astype(np.float64)
    found = rigid @ np.linalg.inv(rigid[0])
    true = truth @ np.linalg.inv(truth[0])
    delta = np.linalg.inv(true) @ found
    h = np.concatenate([head, np.ones((len(head), 1))], 1)
    moved = np.einsum("fij,vj->fvi", found, h)[..., :3] - np.einsum("fij,vj->fvi", true, h)[..., :3]
    return float(_rotation_deg(delta[:, :3, :3]).max()), float(np.linalg.norm(moved, axis=-1).max())


def _stab_check(facts: dict, max_deg: float = 0.5, max_cm: float = 0.5) -> Callable[[Path], str]:
    def check(out: Path) -> str:
        deg, cm = stabilization_error(out / "stab.npz", facts["head_rigid"], facts["head_vertices"])
        verdict = "" if deg <= max_deg and cm <= max_cm else f"wrong answer: "
        return f"{verdict}rotation off by up to {deg:.3f} deg, head vertices up to {cm:.3f} cm"
    return check


def _files_check(*names: str) -> Callable[[Path], str]:
    def check(out: Path) -> str:
        missing = [n for n in names if not (out / n).exists()]
        return f"wrong answer: missing outputs {missing}" if missing else f"wrote {', '.join(names)}"
    return check


def _report_frames_check(removal_frames: int) -> Callable[[Path], str]:
    """dynamics_train_captures' report: F trained on `removal_frames` frames (the slice asked for)."""
    def check(out: Path) -> str:
        report = json.loads((out / "r.json").read_text())["removal"]
        found = report["frames"]
        verdict = "" if found == removal_frames else f"wrong answer: expected {removal_frames} frames, "
        return f"{verdict}F trained on {found} frames of {report['takes']}"
    return check


# -- the probes -----------------------------------------------------------------------------------

def _write_previous(*names: str) -> Callable[[Path], None]:
    def setup(out: Path) -> None:
        for name in names:
            path = out / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(b"previous output " + name.encode())
    return setup


def probes(facts: dict) -> list[Probe]:
    R = "run"
    S = ["--no-cache", "--progress", "none"]
    P: list[Probe] = []

    def add(name: str, graph: str, *args: str, expect: str = "refuse", **kw) -> None:
        argv = ["run", str(GRAPHS / f"{graph}.json"), *args, *S] if graph else list(args)
        P.append(Probe(f"{graph or 'cli'}: {name}", argv, expect, **kw))

    stab_out = ["output={out}/stab.npz", "report={out}/report"]
    # command-line values and options, on a light graph
    st = ["capture={in}/small.npz", *stab_out]
    add("--scheduler nosuch", "stabilize", *st, "--scheduler", "nosuch")
    add("--scheduler tcp://127.0.0.1:1 (nothing listening)", "stabilize", *st, "--scheduler", "tcp://127.0.0.1:1")
    add("--frames 5:2", "stabilize", *st, "--frames", "5:2")
    add("--frames a:b", "stabilize", *st, "--frames", "a:b")
    add("--frames 0:99 past the 8 frames", "stabilize", *st, "--frames", "0:99")
    add("--frames -3:2", "stabilize", *st, "--frames", "-3:2")
    add("--chunk 0", "stabilize", *st, "--chunk", "0")
    add("--chunk -2", "stabilize", *st, "--chunk", "-2")
    add("--chunk many", "stabilize", *st, "--chunk", "many")
    add("unknown parameter nosuch=1", "stabilize", *st, "nosuch=1")
    add("--set nosuch.group=face", "stabilize", *st, "--set", "nosuch.group=face")
    add("--set stab.nosuch=1", "stabilize", *st, "--set", "stab.nosuch=1")
    add("--set stab.max_vertices=3", "stabilize", *st, "--set", "stab.max_vertices=3")
    add("--set stab.max_vertices=1e308", "stabilize", *st, "--set", "stab.max_vertices=1e308")
    add("--to nosuch", "stabilize", *st, "--to", "nosuch")
    add("--force nosuch", "stabilize", *st, "--force", "nosuch")
    add("--cache on a file", "", "run", str(GRAPHS / "stabilize.json"), *st, "--cache", "{in}/a_file",
        "--progress", "none")
    add("graph file missing", "", "run", "{in}/no_such_graph.json")
    add("validate a graph with \"hold_pose\": \"yes\"", "", "validate", "{in}/hold_pose_yes.json")
    add("validate a graph with \"restabilize\": \"false\"", "", "validate", "{in}/restabilize_false.json")
    add("--set stab.compile=yes", "stabilize", *st, "--set", "stab.compile=yes")
    add("--set stab.compile=1", "stabilize", *st, "--set", "stab.compile=1")
    add("a node raises (exit 1) in 4 chunks: its traceback once, nothing written", "", "run", "{in}/crash.json",
        "output={out}/m.npz", "--chunk", "2", *S, expect="crash", setup=_write_previous("m.npz"), keep=True,
        env={"NODEGRAPH_PLUGINS": "probe_crash", "PYTHONPATH": "{in}/plugins"})
    # stabilize.json: bad captures
    for name, text in [("garbage.npz", "garbage NPZ"), ("empty.npz", "empty file"), ("truncated.npz", "truncated NPZ"),
                       ("missing.npz", "missing file"), ("fps_negative.npz", "capture's own fps -30"),
                       ("fps_huge.npz", "capture's own fps 1e308"), ("face_index_24.npz", "face index 24 of 24 vertices"),
                       ("face_index_neg.npz", "face index -1"), ("faces_float.npz", "faces of float 0.5s"),
                       ("coords_1e20.npz", "one coordinate 1e20"), ("all_1e20.npz", "every coordinate 1e20"),
                       ("coords_nan.npz", "one coordinate NaN"), ("zero_frames.npz", "zero frames"),
                       ("vertices_2d.npz", "vertices [V,3] without frames"), ("no_vertices.npz", "no vertices array"),
                       ("garbage.usda", "garbage USD"), ("mesh.%04d.obj", "OBJ pattern, face index 99 in file 1"),
                       ("takes", "a folder")]:
        add(f"capture: {text}", "stabilize", f"capture={{in}}/{name}", *stab_out)
    add("capture of 5 collinear points", "stabilize", "capture={in}/collinear.npz", *stab_out)
    check = _stab_check(facts)
    add("capture of 3 rigid vertices", "stabilize", "capture={in}/rigid3.npz", *stab_out, expect="either",
        check=check)
    add("capture of 4 rigid vertices", "stabilize", "capture={in}/rigid4.npz", *stab_out, expect="either",
        check=check)
    add("capture of 10 rigid vertices", "stabilize", "capture={in}/rigid10.npz", *stab_out, expect=R, check=check)
    add("whole head, stab.max_vertices=10", "stabilize", "capture={in}/head.npz", *stab_out,
        "--set", "stab.max_vertices=10", expect=R, check=_stab_check(facts, 0.5, 1.0))
    add("whole head, --frames 2:9", "stabilize", "capture={in}/head.npz", *stab_out, "--frames", "2:9", expect=R,
        check=_files_check("stab.npz", "report"))
    add("still capture (no motion)", "stabilize", "capture={in}/still.npz", *stab_out, expect="either")
    add("group=nosuch", "stabilize", "capture={in}/head.npz", *stab_out, "group=nosuch")
    add("init_group=nosuch", "stabilize", "capture={in}/head.npz", *stab_out, "init_group=nosuch")
    add("output= the capture", "stabilize", "capture={in}/small.npz", "output={in}/small.npz",
        "report={out}/report")
    add("output=.txt", "stabilize", "capture={in}/small.npz", "output={out}/stab.txt", "report={out}/report")
    add("output= a folder", "stabilize", "capture={in}/small.npz", "output={in}/takes", "report={out}/report")
    add("output whose parent is a file", "stabilize", "capture={in}/small.npz", "output={in}/a_file/stab.npz",
        "report={out}/report")
    add("output under /proc", "stabilize", "capture={in}/small.npz", "output=/proc/stab.npz", "report={out}/report")
    add("report= the capture's folder", "stabilize", "capture={in}/small.npz", "output={out}/stab.npz",
        "report={in}")
    add("report= a file", "stabilize", "capture={in}/small.npz", "output={out}/stab.npz", "report={in}/a_file")
    add("output and report at one path", "stabilize", "capture={in}/small.npz", "output={out}/x",
        "report={out}/x")
    add("failing run keeps the previous outputs (--chunk 2, bad group)", "stabilize", "capture={in}/head.npz",
        *stab_out, "group=nosuch", "--chunk", "2", setup=_write_previous("stab.npz", "report/head_motion.png"),
        keep=True)
    add("failing run keeps the previous outputs (face index 24)", "stabilize", "capture={in}/face_index_24.npz",
        *stab_out, setup=_write_previous("stab.npz", "report/head_motion.png"), keep=True)

    # synthetic_capture.json
    sc = ["capture={out}/c.npz", "truth={out}/t.npz", "truth_rigid={out}/r.npz", "expressions={out}/e.json",
          "report={out}/report"]
    for value in ("0", "-1", "1e308", "many", "2.5", "nan"):
        add(f"num_frames={value}", "synthetic_capture", *sc, f"num_frames={value}")
    add("seed=-1", "synthetic_capture", *sc, "num_frames=4", "seed=-1", expect="either")
    add("capture=.txt", "synthetic_capture", *sc, "capture={out}/c.txt")
    add("capture and truth at one path", "synthetic_capture", *sc, "truth={out}/c.npz")
    add("truth_rigid=.obj", "synthetic_capture", *sc, "truth_rigid={out}/r.obj")
    add("report= a file", "synthetic_capture", *sc, "report={in}/a_file")
    add("--frames 2:5", "synthetic_capture", *sc, "num_frames=8", "--frames", "2:5", expect=R,
        check=_files_check("c.npz", "t.npz", "r.npz", "e.json"))
    add("--frames 6:12 past num_frames=8", "synthetic_capture", *sc, "num_frames=8", "--frames", "6:12")

    # livelink_to_render.json
    ll = ["images={out}/render.%04d.png"]
    for name, text in [("take_nan.csv", "a NaN cell"), ("take_text.csv", "a text cell"),
                       ("take_header.csv", "header only"), ("take_empty.csv", "empty"), ("take_other.csv", "other columns"),
                       ("take_binary.csv", "binary"), ("take_timecode.csv", "bad timecode"),
                       ("take_huge.csv", "a weight of 1e300"), ("no_such.csv", "missing"), ("plates", "a folder")]:
        add(f"csv: {text}", "livelink_to_render", f"csv={{in}}/{name}", *ll)
    for value in ("-1", "1e308", "nan", "fast"):
        add(f"fps={value}", "livelink_to_render", "csv={in}/take.csv", *ll, f"fps={value}")
    for value in ("-5", "0", "1e20"):
        add(f"distance_cm={value}", "livelink_to_render", "csv={in}/take.csv", *ll, f"distance_cm={value}")
    add("images=.txt", "livelink_to_render", "csv={in}/take.csv", "images={out}/render.%04d.txt")
    add("images= one file for every frame", "livelink_to_render", "csv={in}/take.csv", "images={out}/render.png")
    add("images= the input CSV's name as a pattern", "livelink_to_render", "csv={in}/take.csv",
        "images={in}/take.csv")
    add("--frames 1:3", "livelink_to_render", "csv={in}/take.csv", *ll, "fps=30", "--frames", "1:3", expect=R,
        check=_files_check("render.0001.png", "render.0002.png"), timeout=900)
    add("--frames 4:20 past the 6 rows", "livelink_to_render", "csv={in}/take.csv", *ll, "fps=30", "--frames", "4:20")
    add("failing run keeps the previous outputs (a NaN cell)", "livelink_to_render", "csv={in}/take_nan.csv", *ll,
        setup=_write_previous("render.0000.png", "render.0001.png"), keep=True)

    # dynamics_remove.json
    dr = ["capture={in}/face.npz", "skull={in}/face.npz", "model=", "output={out}/q.npz"]
    for name, text in [("skull_short.npz", "5 skull frames for 8"), ("skull_nan.npz", "a NaN translation"),
                       ("skull_1e20.npz", "a 1e20 translation"), ("skull_scaled.npz", "a scaled rotation"),
                       ("skull_shape.npz", "[F,3,3] matrices"), ("garbage.npz", "garbage")]:
        add(f"skull: {text}", "dynamics_remove", *dr, f"skull={{in}}/{name}")
    for name in ("shape", "float64", "missing", "nan", "garbage", "truncated"):
        add(f"model: {name} weights", "dynamics_remove", *dr, f"model={{in}}/model_{name}.safetensors")
    add("model=.pt", "dynamics_remove", *dr, "model={in}/removal.pt")
    add("capture of another topology (24 vertices)", "dynamics_remove", *dr, "capture={in}/small.npz",
        "skull={in}/small.npz")
    add("capture of another topology, --chunk 2 (printed once)", "dynamics_remove", *dr,
        "capture={in}/small.npz", "skull={in}/small.npz", "--chunk", "2")
    add("capture's own fps -30", "dynamics_remove", *dr, "capture={in}/face_fps_negative.npz")
    add("failing run keeps the previous outputs (a NaN skull frame, --chunk 2)", "dynamics_remove", *dr,
        "skull={in}/skull_nan.npz", "--chunk", "2", setup=_write_previous("q.npz"), keep=True)
    add("capture of one frame", "dynamics_remove", *dr, "capture={in}/face_neutral.npz",
        "skull={in}/face.npz")
    for value in ("-1", "1e308", "nan"):
        add(f"fps={value}", "dynamics_remove", *dr, f"fps={value}")
    add("output= the capture", "dynamics_remove", *dr, "output={in}/face.npz")
    add("output= the model", "dynamics_remove", *dr, "model={in}/removal.safetensors",
        "output={in}/removal.safetensors")
    add("--frames 2:6", "dynamics_remove", *dr, "--frames", "2:6", expect=R, check=_files_check("q.npz"))
    add("--frames 6:12 past the 8 frames", "dynamics_remove", *dr, "--frames", "6:12")

    # dynamics_train.json / dynamics_train_captures.json / dynamics_retarget.json (validation and files)
    dt = ["model={out}/f.safetensors", "synthesis_model={out}/h.safetensors"]
    for value in ("epochs=0", "epochs=-1", "rows=0", "samples=0", "samples=1e308", "max_vertices=3",
                  "region=nosuch"):
        add(value, "dynamics_train", *dt, value)
    add("model and synthesis_model at one path", "dynamics_train", *dt, "synthesis_model={out}/f.safetensors")
    add("model=.txt", "dynamics_train", *dt, "model={out}/f.txt")
    add("model= the bundled network's folder", "dynamics_train", *dt, "model={in}/takes")
    dc = ["captures={in}/takes", "neutral={in}/face_neutral.npz", "model={out}/f.safetensors",
          "synthesis_model={out}/h.safetensors", "report={out}/r.json"]
    add("captures: empty folder", "dynamics_train_captures", *dc, "captures={in}/takes_empty")
    add("captures: no match", "dynamics_train_captures", *dc, "captures={in}/takes/none_*.npz")
    add("captures: another topology than the neutral", "dynamics_train_captures", *dc, "captures={in}/takes_small")
    add("captures: a take's own fps -5", "dynamics_train_captures", *dc, "captures={in}/takes_fps")
    add("neutral: garbage", "dynamics_train_captures", *dc, "neutral={in}/garbage.npz")
    add("neutral: another topology", "dynamics_train_captures", *dc, "neutral={in}/small.npz")
    add("held_out=nosuch", "dynamics_train_captures", *dc, "held_out=nosuch")
    add("fps=-1", "dynamics_train_captures", *dc, "fps=-1")
    add("report=.npz", "dynamics_train_captures", *dc, "report={out}/r.npz")
    add("model= a take", "dynamics_train_captures", *dc, "model={in}/takes/hold_a.npz")
    add("neutral= a take (8 frames)", "dynamics_train_captures", *dc, "neutral={in}/takes/hold_a.npz")
    add("failing run keeps the previous outputs (held_out=nosuch)", "dynamics_train_captures", *dc,
        "held_out=nosuch", setup=_write_previous("f.safetensors", "h.safetensors", "r.json"), keep=True)
    # --frames a:b: frames a:b of every take (takes of 60 and 120 frames; the last held take is held out)
    dl = ["captures={in}/takes_long", "neutral={in}/neutral_long.npz", "model={out}/f.safetensors",
          "synthesis_model={out}/h.safetensors", "report={out}/r.json", "epochs=1", "rows=2000", "samples=16",
          "synthesis_samples=16", "synthesis_epochs=1"]
    add("--frames 10:50 (F on hold_a 10:50)", "dynamics_train_captures", *dl, "--frames", "10:50", expect=R,
        check=_report_frames_check(40))
    add("--frames 60:120 (hold_a ends at 60: F on hold_b 60:120)", "dynamics_train_captures", *dl,
        "--frames", "60:120", expect=R, check=_report_frames_check(60))
    add("--frames 130:150 past every take", "dynamics_train_captures", *dl, "--frames", "130:150")
    rt = ["removal_model={in}/removal.safetensors", "synthesis_model={in}/removal.safetensors",
          "output={out}/r.npz"]
    add("synthesis_model= a removal network", "dynamics_retarget", *rt)
    add("removal_model: float64 weights", "dynamics_retarget", *rt, "removal_model={in}/model_float64.safetensors")
    add("synthesis_model missing", "dynamics_retarget", *rt, "synthesis_model={in}/none.safetensors")
    add("max_vertices=-5", "dynamics_retarget", *rt, "max_vertices=-5")
    add("output=.obj", "dynamics_retarget", *rt, "output={out}/r.obj")

    # the image graphs: landmarks.json, fit_video.json, fit_video_temporal.json, video_to_animation.json
    lm = ["output={out}/l.npz", "report={out}/overlays"]
    for name, text in [("garbage.%04d.png", "garbage PNG"), ("cut.%04d.png", "truncated PNG"),
                       ("notes.mp4", "text named .mp4"), ("clip_cut.mp4", "truncated MP4"),
                       ("none.%04d.png", "missing pattern"), ("plates", "a folder of plates"),
                       ("mislabelled.%04d.jpg", "a PNG named .jpg")]:
        expect = "either" if "mislabelled" in name or name == "plates" else "refuse"
        add(f"images: {text}", "landmarks", f"images={{in}}/{name}", *lm, expect=expect, timeout=900)
    add("images: gap at frame 4, --chunk 2", "landmarks", "images={in}/gap.%04d.png", *lm, "--chunk", "2",
        setup=_write_previous("l.npz"), keep=True)
    add("report= the plates' folder", "landmarks", "images={in}/plates/p.%04d.png", "output={out}/l.npz",
        "report={in}/plates")
    add("output= a plate", "landmarks", "images={in}/plate.%04d.png", "output={in}/plate.0000.png",
        "report={out}/overlays")
    add("output=.txt", "landmarks", "images={in}/plate.%04d.png", "output={out}/l.txt", "report={out}/overlays")
    for value in ("biggest", "-1", "[1, 2, 3]", "[10, 10, 5, 5]"):
        add(f"face={value}", "landmarks", "images={in}/plate.%04d.png", *lm, f"face={value}")
    add("--frames 2:9 past the 4 plates", "landmarks", "images={in}/plate.%04d.png", *lm, "--frames", "2:9")
    add("--frames 1:3 (video)", "landmarks", "images={in}/clip.mp4", *lm, "--frames", "1:3", expect=R,
        check=_files_check("l.npz"), timeout=900)
    for graph in ("fit_video", "fit_video_temporal", "video_to_animation"):
        fo = ["images={in}/plate.%04d.png", "output={out}/fit.npz", "report={out}/fit"]
        if graph != "fit_video":
            fo.append("motion_report={out}/motion")
        cameras = ("camera_nan", "camera_negative", "camera_zero", "camera_1e20", "camera_garbage",
                   "camera_world", "no_such_camera", "camera_size") if graph == "fit_video" else ("camera_nan",)
        for name in cameras:  # each waits for TrackFaces (minutes at load 20): the full set on one graph
            add(f"camera: {name}", graph, *fo, f"camera={{in}}/{name}.json")
        add("output= a .png", graph, *fo, "output={out}/photo.png")
        add("output= a plate", graph, *fo, "output={in}/plate.0001.png")
        add("report= the plates' folder", graph, "images={in}/plates/p.%04d.png", "output={out}/fit.npz",
            "report={in}/plates", *fo[3:])
        add("images: truncated MP4", graph, *fo, "images={in}/clip_cut.mp4")
        add("face=centre_left", graph, *fo, "face=centre_left")
    va = ["images={in}/plate.%04d.png", "output={out}/fit.npz", "report={out}/fit", "motion_report={out}/motion"]
    add("csv=.txt", "video_to_animation", *va, "csv={out}/a.txt")
    add("usd=.obj", "video_to_animation", *va, "usd={out}/a.obj")
    add("gltf=.gltf", "video_to_animation", *va, "gltf={out}/a.gltf")
    add("usd and gltf at one path", "video_to_animation", *va, "usd={out}/a.usd", "gltf={out}/a.usd")
    add("a failing run leaves an existing csv= file untouched (no face in the plates)", "video_to_animation", *va,
        "csv={in}/take.csv")

    # demo.json (validation, outputs)
    dm = ["html={out}/index.html", "report={out}/stab", "dynamics_report={out}/dyn", "fit_report={out}/fit",
          "motion_report={out}/motion"]
    for value in ("num_frames=0", "num_frames=-5", "num_frames=1e308", "seed=abc", "face=bogus"):
        add(value, "demo", *dm, value)
    add("html=.txt", "demo", *dm, "html={out}/index.txt")
    add("report= a file", "demo", *dm, "report={in}/a_file")
    add("html under /proc", "demo", *dm, "html=/proc/index.html")

    # --frames a:b on the heavy graphs, on small inputs (--long)
    add("--frames 20:40, num_frames=48", "demo", *dm, "num_frames=48", "--frames", "20:40", expect=R, long=True,
        check=_files_check("index.html"), timeout=3600)
    for graph in ("fit_video", "fit_video_temporal", "video_to_animation"):
        fo = ["images={in}/astro.%04d.png", "output={out}/fit.npz", "report={out}/fit"]
        if graph != "fit_video":
            fo.append("motion_report={out}/motion")
        span = "1:2" if graph == "fit_video" else "0:2"
        add(f"--frames {span} (astronaut, 2 frames)", graph, *fo, "--frames", span, expect=R, long=True,
            check=_files_check("fit.npz"), timeout=3600)
    add("--frames 1:3 (no face in the plates)", "fit_video", "images={in}/plate.%04d.png", "output={out}/fit.npz",
        "report={out}/fit", "--frames", "1:3", expect="either", long=True, timeout=3600)
    tiny = ["epochs=1", "rows=2000", "samples=32", "synthesis_samples=32", "synthesis_epochs=1"]
    # too few frames to train on (the window reaches 11 / 14 frames each side at 96 / 128 fps): refused
    # while planning (was after 401 s of making both performances)
    for span in ("0:4", "0:20", "70:100"):
        add(f"--frames {span} (no training row)", "dynamics_train", *dt, *tiny, "--frames", span, early=True,
            names="--frames")
    add("--frames 100:400", "dynamics_train", *dt, *tiny, "--frames", "100:400", expect=R, long=True,
        check=_files_check("f.safetensors", "h.safetensors"), timeout=3600)
    add("--frames 0:4 (no training row)", "dynamics_train_captures", *dc, "epochs=1", "samples=32",
        "synthesis_samples=32", "synthesis_epochs=1", "--frames", "0:4", early=True, names="--frames")
    add("--frames 0:20 (trained networks)", "dynamics_retarget", "removal_model={in}/removal.safetensors",
        "synthesis_model={in}/synthesis.safetensors", "output={out}/r.npz", "--frames", "0:20", expect="either",
        long=True, timeout=3600)
    more_probes(add, facts)
    # a refused output path or model file is refused before anything runs (dynamics_retarget: every
    # probe there is a model file or an output)
    outputs = re.compile(r"(^|: )(output|report|model|synthesis_model|csv|usd|gltf|html|capture|truth_rigid|images)"
                         r"(=| and| whose| under)|: model: ")
    for probe in P:
        if probe.expect == "refuse" and not probe.keep and (outputs.search(probe.name) or "dynamics_retarget" in probe.name):
            probe.early = True
    return P


# good inputs of each shipped graph (every output path parameter is added, pointing into {out}),
# an input file of the run (for "output = the input"), and the graphs light enough to run in a probe
GOOD_INPUTS = {
    "stabilize": ["capture={in}/small.npz"],
    "synthetic_capture": ["num_frames=4"],
    "livelink_to_render": ["csv={in}/take.csv"],
    "dynamics_remove": ["capture={in}/face.npz", "skull={in}/face.npz", "model="],
    "dynamics_train": [],
    "dynamics_train_captures": ["captures={in}/takes", "neutral={in}/face_neutral.npz"],
    "dynamics_retarget": ["removal_model={in}/removal.safetensors",
                          "synthesis_model={in}/synthesis_label.safetensors"],
    "landmarks": ["images={in}/plate.%04d.png"],
    "fit_video": ["images={in}/plate.%04d.png"],
    "fit_video_temporal": ["images={in}/plate.%04d.png"],
    "video_to_animation": ["images={in}/plate.%04d.png"],
    "demo": [],
}
INPUT_FILE = {"stabilize": "{in}/small.npz", "livelink_to_render": "{in}/take.csv", "dynamics_remove": "{in}/face.npz",
              "dynamics_train_captures": "{in}/takes/hold_a.npz", "dynamics_retarget": "{in}/removal.safetensors",
              "landmarks": "{in}/plate.0001.png", "fit_video": "{in}/plate.0001.png",
              "fit_video_temporal": "{in}/plate.0001.png", "video_to_animation": "{in}/plate.0001.png"}
INPUT_FOLDER = {"dynamics_train_captures": "{in}/takes"}  # a folder given as an input
LIGHT = {"stabilize", "synthetic_capture", "livelink_to_render", "dynamics_remove"}


def output_parameters(graph: str) -> list[tuple[str, str]]:
    """(graph parameter, file or folder name of its default) of every output path parameter of a
    shipped graph whose default writes something."""
    from nodegraph import registry
    from nodegraph.params import field_flag

    data = json.loads((GRAPHS / f"{graph}.json").read_text())
    found = []
    for name, spec in data["parameters"].items():
        node, param = spec["target"].split(".", 1)
        cls = registry.get(data["nodes"][node]["type"])
        if param in cls.Params.model_fields and field_flag(cls.Params, param, "output_file", False):
            default = data["nodes"][node].get("params", {}).get(param, cls.Params.model_fields[param].default)
            if isinstance(default, str) and default:
                found.append((name, os.path.basename(default.rstrip("/"))))
    return found


def more_probes(add: Callable[..., None], facts: dict) -> None:
    """The classes of issue 30's list the first rounds did not probe (see make_more_inputs)."""
    # every output path parameter of every shipped graph pointed at: the run's input file, an
    # input folder, a path inside an input folder, a missing parent (light graphs: it is made),
    # a parent that is a file, and (no root capabilities) a read-only folder
    for graph, good in GOOD_INPUTS.items():
        outs = output_parameters(graph)
        base = [*good, *(f"{name}={{out}}/{leaf}" for name, leaf in outs)]
        for name, leaf in outs:
            rest = [a for a in base if not a.startswith(f"{name}=")]
            cases = []
            if graph in INPUT_FILE:
                cases.append(("the run's input file", INPUT_FILE[graph], INPUT_FILE[graph]))
                cases.append(("the inputs' folder", "{in}", "'{in}'"))
            if graph in INPUT_FOLDER:
                inside = f"{INPUT_FOLDER[graph]}/{leaf}"
                cases.append(("a path inside an input folder", inside, f"'{inside}'"))
            cases.append(("a parent that is a file", f"{{in}}/a_file/{leaf}", "a_file"))
            for what, value, names in cases:
                add(f"{name}= {what}", graph, *rest, f"{name}={value}", early=True, names=names)
            add(f"{name}= in a read-only folder (no root capabilities)", graph, *rest, f"{name}={{in}}/readonly/{leaf}",
                early=True, user=True, names="readonly")
            if graph in LIGHT:
                add(f"{name}= under missing folders (made)", graph, *rest, f"{name}={{out}}/new/deeper/{leaf}",
                    expect="run", timeout=900)
    # the cache folder: in a read-only folder (no root capabilities), under /proc, a file (above)
    st = ["capture={in}/small.npz", "output={out}/stab.npz", "report={out}/report"]
    for what, value, user in [("in a read-only folder (no root capabilities)", "{in}/readonly/cache", True),
                              ("the read-only folder itself (no root capabilities)", "{in}/readonly", True),
                              ("under /proc", "/proc/nodegraph_cache", False)]:
        add(f"--cache {what}", "", "run", str(GRAPHS / "stabilize.json"), *st, "--cache", value, "--progress", "none",
            user=user, names="cache")
    # camera files: more values of fx, cx, cy, width, height
    fo = ["images={in}/plate.%04d.png", "output={out}/fit.npz", "report={out}/fit"]
    for name in ("camera_fx0", "camera_fx_huge", "camera_cx_inf", "camera_cy_nan", "camera_width0",
                 "camera_height_neg", "camera_fx_text", "camera_fx_bool", "camera_no_fy"):
        add(f"camera: {name}", "fit_video", *fo, f"camera={{in}}/{name}.json", early=True, names=f"{name}.json")
    # captures: one vertex, every vertex at one point, 10 rigid vertices each given twice
    stab_out = ["output={out}/stab.npz", "report={out}/report"]
    add("capture of one vertex", "stabilize", "capture={in}/one_vertex.npz", *stab_out)
    add("capture of 24 vertices at one moving point", "stabilize", "capture={in}/one_point.npz", *stab_out)
    add("capture of 10 rigid vertices, each twice", "stabilize", "capture={in}/rigid10_twice.npz", *stab_out,
        expect="either", check=_stab_check(facts))
    add("capture: zero frames", "dynamics_remove", "capture={in}/zero_frames.npz", "skull={in}/face.npz", "model=",
        "output={out}/q.npz")
    # images and videos: 0 and 1 frame, odd sizes, 16-bit, grey, RGBA
    lm = ["output={out}/l.npz", "report={out}/overlays"]
    for name, text in [("video0.mp4", "a video of 0 frames"), ("px1x1.%04d.png", "1x1 PNGs"),
                       ("px3x5.%04d.png", "3x5 PNGs")]:
        add(f"images: {text}", "landmarks", f"images={{in}}/{name}", *lm, expect="either", timeout=900,
            check=_files_check("l.npz"))
    for name, text in [("video1.mp4", "a video of 1 frame"), ("px8000x8.%04d.png", "8000x8 PNGs"),
                       ("deep16.%04d.png", "16-bit PNGs"), ("grey.%04d.png", "grayscale PNGs"),
                       ("rgba.%04d.png", "RGBA PNGs")]:
        add(f"images: {text}", "landmarks", f"images={{in}}/{name}", *lm, expect="either", timeout=900,
            check=_files_check("l.npz"))
    add("images: a video of 0 frames", "fit_video", *fo, "images={in}/video0.mp4", early=True)
    # graph files: wrong types, unknown keys, missing nodes, a cycle, not a graph
    for name, expect in [("number_as_text", "refuse"), ("number_as_numeral_text", "either"),
                         ("bool_as_number", "refuse"), ("list_for_text", "refuse"), ("unknown_param", "refuse"),
                         ("unknown_node_key", "refuse"), ("unknown_top_key", "refuse"),
                         ("edge_to_missing_node", "refuse"), ("missing_node_in_parameter", "refuse"),
                         ("unknown_type", "refuse"), ("type_version_99", "refuse"), ("type_version_text", "refuse"),
                         ("nodes_a_list", "refuse"), ("edge_of_one_end", "refuse"), ("schema_2", "refuse"),
                         ("params_null", "either"), ("cycle", "refuse"), ("not_json", "refuse"),
                         ("empty", "refuse"), ("array", "refuse")]:
        add(f"validate graph_{name}.json", "", "validate", f"{{in}}/graph_{name}.json", expect=expect)
        if expect == "refuse":
            add(f"run graph_{name}.json", "", "run", f"{{in}}/graph_{name}.json", *st, "--no-cache",
                "--progress", "none", expect=expect)
    # --set with bad values
    for value in ("stab.max_vertices=abc", "stab.max_vertices=", "stab.max_vertices=[10]", "stab.iterations=-1",
                  "stab.group=[1, 2]", "stab.device=tpu", "stab", "=5", "stab.=5", ".max_vertices=5",
                  "stab.max_vertices=nan", "stab.max_vertices=inf", "stab.compile=null"):
        add(f"--set {value}", "stabilize", *st, "--set", value)
    # --frames: negative, reversed, empty, past the end, not numbers
    for value in ("--frames=-3:2", "--frames=3:3", "--frames=0:0", "--frames=:", "--frames=1.5:3",
                  "--frames=2:1", "--frames=8:9", "--frames=100:200", "--frames=-1", "--frames=0:-1",
                  "--frames=1:2:3", "--frames= "):
        add(value, "stabilize", *st, value)
    add("--frames=2: (to the end)", "stabilize", "capture={in}/head.npz", *stab_out, "--frames=2:", expect="either",
        check=_files_check("stab.npz"))


# -- running ----------------------------------------------------------------------------------------

def _snapshot(folder: Path) -> dict[str, str]:
    out = {}
    if folder.exists():
        for path in sorted(folder.rglob("*")):
            rel = str(path.relative_to(folder))
            out[rel] = hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "dir"
    return out


def _message(stderr: str) -> str:
    lines = [line.strip() for line in stderr.splitlines() if line.strip()]
    for key in ("expected", "FAILED", "error", "invalid", "refus", "cannot"):
        for line in lines:
            if key in line and not line.startswith("nodegraph: invalid graph"):
                return line
    return lines[-1] if lines else ""


def run_probe(probe: Probe, inputs: Path, work: Path, index: int, inputs_before: dict[str, str],
              log: str = "") -> Result:
    out = work / f"out{index:03d}"
    out.mkdir(parents=True, exist_ok=True)
    if probe.setup:
        probe.setup(out)
    before = _snapshot(out)
    argv = [a.replace("{in}", str(inputs)).replace("{out}", str(out)) for a in probe.argv]
    env = os.environ | {"PYTHONPATH": str(ROOT)}
    for key, value in probe.env.items():
        value = value.replace("{in}", str(inputs))
        env[key] = f"{value}{os.pathsep}{env[key]}" if key == "PYTHONPATH" else value
    # root ignores permissions: a probe of them runs with every capability dropped (still uid 0,
    # so the tools stay readable, but a mode-555 folder refuses writes as it would for a user)
    prefix = ["setpriv", "--bounding-set=-all", "--inh-caps=-all", "--"] if probe.user else []
    start = time.perf_counter()
    try:
        done = subprocess.run([*prefix, "nice", *_nodegraph(), *argv], capture_output=True, text=True, env=env,
                              timeout=probe.timeout, cwd=work)
        code, stderr = done.returncode, done.stderr + done.stdout
    except subprocess.TimeoutExpired as err:
        code, stderr = -1, f"timed out after {probe.timeout:.0f} s {err.stderr or ''}"
    seconds = time.perf_counter() - start
    after = _snapshot(out)
    problems: list[str] = []
    message = _message(stderr)
    if "Traceback" in stderr and code != 1:
        problems.append("prints a traceback")
    staged = [p for p in list(out.rglob(f"{STAGING}*")) + list(inputs.rglob(f"{STAGING}*"))]
    if staged:
        problems.append(f"left staging folders {[str(p) for p in staged[:2]]}")
    refused = code == 2
    if probe.expect == "crash":
        if code != 1:
            problems.append(f"expected exit 1, found {code}")
        # one traceback (with its chained causes) per distinct failure: its header once, its
        # innermost frame (the plugin's raising line) once
        headers = sum(line.startswith("traceback of ") for line in stderr.splitlines())
        raising = stderr.count('probe_crash.py", line')
        if "Traceback (most recent call last)" not in stderr or headers != 1 or raising != 1:
            problems.append(f"expected the traceback printed once, found {headers} header(s), the raising "
                            f"line {raising} time(s)")
        if after != before:
            changed = sorted(set(after.items()) ^ set(before.items()))
            problems.append(f"outputs changed: {[c[0] for c in changed][:3]}")
        message = next((line.strip() for line in stderr.splitlines() if "Error" in line), message)
    elif probe.expect == "run" or (probe.expect == "either" and not refused):
        if code != 0:
            problems.append(f"expected exit 0{' or 2' if probe.expect == 'either' else ''}, found {code}")
        elif probe.check:
            figure = probe.check(out)
            message = figure
            if figure.startswith("wrong answer"):
                problems.append(figure)
    else:
        if code != 2:
            problems.append(f"expected exit 2, found {code}")
        if after != before:
            changed = sorted(set(after.items()) ^ set(before.items()))
            problems.append(f"outputs changed: {[c[0] for c in changed][:3]}")
        lines = [line for line in stderr.splitlines() if line.strip() and ("expected" in line or "FAILED" in line)]
        if len(lines) != len(set(lines)):
            problems.append("the same error printed more than once")
        if refused and probe.early and any(line.lstrip().startswith("FAILED") for line in stderr.splitlines()):
            problems.append("refused only after running: expected the refusal before anything runs")
        must = probe.names.replace("{in}", str(inputs)).replace("{out}", str(out))
        if refused and must and must not in stderr:
            problems.append(f"the refusal does not name {probe.names!r}")
    if _snapshot(inputs) != inputs_before:
        problems.append("an input changed")
    verdict = "ok" if not problems else "FAIL: " + "; ".join(problems)
    if log:  # as each probe ends, so that a long session can be read while it runs
        with open(log, "a") as handle:
            handle.write(f"=== {probe.name} (exit {code}, {verdict})\n{' '.join(argv)}\n{stderr}\n")
    return Result(probe, code, seconds, message, verdict, stderr)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--long", action="store_true", help="also --frames a:b on the heavy graphs")
    parser.add_argument("--only-long", action="store_true", help="only the --long probes")
    parser.add_argument("--start", type=int, default=0, help="skip the first START short probes")
    parser.add_argument("--end", type=int, default=10 ** 6, help="stop before short probe END")
    parser.add_argument("--only", default="", help="run the probes whose name contains this (or one of "
                        "several separated by '|')")
    parser.add_argument("--jobs", type=int, default=2, help="probes run at once")
    parser.add_argument("--keep", default="", help="work folder to keep (default: a temporary one)")
    parser.add_argument("--log", default="", help="write every probe's stderr to this file")
    args = parser.parse_args()
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="probe_bad_inputs."))
    work.mkdir(parents=True, exist_ok=True)
    inputs = work / "in"
    start = time.perf_counter()
    facts = make_inputs(inputs)
    chosen = [p for p in probes(facts) if (args.long or not p.long) and (p.long or not args.only_long)
              and any(part in p.name for part in args.only.split("|"))]
    print(f"inputs made in {time.perf_counter() - start:.1f} s; {len(chosen)} probes; load {os.getloadavg()[0]:.1f}",
          file=sys.stderr)
    inputs_before = _snapshot(inputs)
    if args.log:
        Path(args.log).write_text("")
    results: list[Result] = []
    long_probes = sorted((p for p in chosen if p.long),  # the quicker dynamics graphs first, the demo last
                         key=lambda p: ("dynamics" not in p.name, "demo" in p.name))
    short = [p for p in chosen if not p.long][args.start:args.end]
    with concurrent.futures.ThreadPoolExecutor(max(1, args.jobs)) as pool:
        futures = [pool.submit(run_probe, p, inputs, work, i, inputs_before, args.log) for i, p in enumerate(short)]
        for future in futures:
            results.append(future.result())
            r = results[-1]
            print(f"[{len(results)}/{len(chosen)}] {r.code:>3} {r.seconds:6.1f} s {r.probe.name}: {r.verdict}",
                  file=sys.stderr)
    for i, p in enumerate(long_probes):  # one at a time: each uses every core
        if "dynamics_retarget" in p.name:  # needs a synthesis network: the one dynamics_train wrote
            trained = [r for r in results if r.probe.name == "dynamics_train: --frames 100:400"]
            synthesis = work / f"out{len(short) + long_probes.index(trained[0].probe):03d}" / "h.safetensors" \
                if trained else None
            if synthesis and synthesis.exists():
                shutil.copy(synthesis, inputs / "synthesis.safetensors")
                inputs_before = _snapshot(inputs)
        results.append(run_probe(p, inputs, work, len(short) + i, inputs_before, args.log))
        r = results[-1]
        print(f"[{len(results)}/{len(chosen)}] {r.code:>3} {r.seconds:6.1f} s {r.probe.name}: {r.verdict}",
              file=sys.stderr)
    print("| probe | exit | seconds | message | verdict |")
    print("|---|---|---|---|---|")
    for r in results:
        message = r.message.replace("|", "\\|").replace(str(work), "…")[:220]
        print(f"| {r.probe.name} | {r.code} | {r.seconds:.1f} | {message} | {r.verdict.replace('|', '/')} |")
    failed = [r for r in results if r.verdict != "ok"]
    print(f"\n{len(results)} probes, {len(failed)} failed; {time.perf_counter() - start:.0f} s wall, "
          f"load {os.getloadavg()[0]:.1f} (timings are noisy on a shared machine)")
    if not args.keep:
        os.chmod(inputs / "readonly", 0o755)
        shutil.rmtree(work, ignore_errors=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
