"""Bad files given to the shipped graphs: each is exit 2, printed once, naming the node, the
parameter and the file (and the frame where one is at fault); nothing is written."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph.cli import main

GRAPHS = Path(__file__).resolve().parents[2] / "graphs"


def _capture(path: Path, num_frames: int = 4, **overrides) -> dict[str, np.ndarray]:
    """A small tracked mesh (24 vertices, 20 faces, a few cm of motion) saved as NPZ."""
    rng = np.random.default_rng(7)
    base = rng.normal(scale=5.0, size=(24, 3)).astype(np.float32)
    vertices = base + rng.normal(scale=0.1, size=(num_frames, 24, 3)).astype(np.float32)
    arrays = {"vertices": vertices, "faces": (np.arange(60, dtype=np.int32) % 24).reshape(20, 3),
              "rigid": np.repeat(np.eye(4)[None], num_frames, axis=0), "fps": np.float64(30.0)}
    arrays.update(overrides)
    np.savez(path, **arrays)
    return arrays


def _run(capsys, graph: str, *params: str) -> str:
    code = main(["run", str(GRAPHS / graph), *params, "--no-cache", "--scheduler", "sync"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err and "Errno" not in err, err
    return err


def _once(err: str, *pieces: str) -> None:
    """Every piece is in the error, and the error line holding the first is printed once."""
    lines = [line for line in err.splitlines() if pieces[0] in line and "expected" in line]
    assert len(lines) == 1, err
    for piece in pieces:
        assert piece in lines[0], (piece, err)


@pytest.mark.parametrize("overrides, text", [
    ({"fps": np.float64(-5.0)}, "expected the frame rate it stores ('fps') finite and in (0, 10000], found -5"),
    ({"fps": np.float64(1e308)}, "found 1e+308"),
    ({"fps": np.float64(0.0)}, "found 0"),
    ({"fps": np.float64(np.nan)}, "found nan"),
    ({"fps": np.float64(np.inf)}, "found inf"),
])
def test_a_capture_with_its_own_bad_fps_is_refused_naming_the_file(tmp_path, capsys, overrides, text):
    capture = tmp_path / "capture.npz"
    _capture(capture, **overrides)
    out = tmp_path / "out.npz"
    err = _run(capsys, "stabilize.json", f"capture={capture}", f"output={out}",
               f"report={tmp_path / 'report'}")
    _once(err, "io.LoadMeshSequence 'load'", "'path'", str(capture), text)
    assert not out.exists() and not (tmp_path / "report").exists()


@pytest.mark.parametrize("bad_index, shown", [(24, 24), (10 ** 6, 10 ** 6), (-1, -1)])
def test_face_indices_out_of_range_are_refused_naming_the_file(tmp_path, capsys, bad_index, shown):
    capture = tmp_path / "capture.npz"
    faces = (np.arange(60, dtype=np.int32) % 24).reshape(20, 3)
    faces[7, 2] = bad_index
    _capture(capture, faces=faces)
    out = tmp_path / "out.npz"
    err = _run(capsys, "stabilize.json", f"capture={capture}", f"output={out}",
               f"report={tmp_path / 'report'}")
    _once(err, "io.LoadMeshSequence 'load'", "'path'", str(capture),
          f"expected face vertex indices in 0..23 (24 vertices), found {shown} in face 7")
    assert not out.exists()


def test_face_indices_out_of_range_in_a_ply_pattern_name_the_first_file(tmp_path, capsys):
    from nodes.io.mesh import write_ply

    vertices = _capture(tmp_path / "good.npz")["vertices"]
    faces = (np.arange(60, dtype=np.int32) % 24).reshape(20, 3)
    faces[3, 0] = 30
    for f in range(4):
        write_ply(tmp_path / f"face.{f + 1:04d}.ply", vertices[f], faces)
    out = tmp_path / "out.npz"
    err = _run(capsys, "stabilize.json", f"capture={tmp_path / 'face.%04d.ply'}", f"output={out}",
               f"report={tmp_path / 'report'}")
    _once(err, "io.LoadMeshSequence 'load'", "'path'", f"file '{tmp_path / 'face.0001.ply'}'",
          "expected face vertex indices in 0..23 (24 vertices), found 30 in face 3")
    assert not out.exists()


@pytest.mark.parametrize("frame, value", [(0, 1e20), (2, 1e20), (3, -3e7)])
def test_coordinates_beyond_10_km_are_refused_naming_file_frame_and_vertex(tmp_path, capsys, frame, value):
    capture = tmp_path / "capture.npz"
    vertices = _capture(tmp_path / "good.npz")["vertices"].copy()
    vertices[frame, 5, 1] = value
    _capture(capture, vertices=vertices)
    out = tmp_path / "out.npz"
    err = _run(capsys, "stabilize.json", f"capture={capture}", f"output={out}",
               f"report={tmp_path / 'report'}")
    _once(err, "io.LoadMeshSequence 'load'", "'path'", f"frame {frame} (file '{capture}')",
          f"expected vertex coordinates within +-1e+06 cm, found {value:g} at vertex 5")
    assert "width" not in err and not out.exists()


def test_a_skull_translation_of_1e20_is_refused_naming_file_and_frame(tmp_path, capsys):
    from nodes.io.face_model import load_face_model

    face = load_face_model(region="face")  # the bundled network's topology
    capture, skull = tmp_path / "capture.npz", tmp_path / "skull.npz"
    np.savez(capture, vertices=np.repeat(face.neutral[None], 4, axis=0), faces=face.faces, fps=30.0)
    rigid = np.repeat(np.eye(4)[None], 4, axis=0)
    rigid[1, 0, 3] = 1e20
    np.savez(skull, rigid=rigid)
    out = tmp_path / "out.npz"
    err = _run(capsys, "dynamics_remove.json", f"capture={capture}", f"skull={skull}", "model=",
               f"output={out}")
    _once(err, "io.LoadRigidSequence 'skull'", "'path'", f"frame 1 (file '{skull}')",
          "expected a translation within +-1e+06 cm")
    assert not out.exists()


def _bundled_model():
    from nodegraph.models import load_model
    from nodes.dynamics.files import BUNDLED_REMOVAL

    return load_model(BUNDLED_REMOVAL)


@pytest.mark.parametrize("suffix", [".safetensors", ".npz"])
@pytest.mark.parametrize("spoil, text", [
    ("shape", "'2.weight': the module has shape (128, 128), stored (128, 127)"),
    ("float64", "'0.weight': the module has dtype torch.float32, stored float64"),
    ("missing", "missing from the stored state: ['4.bias']"),
    ("nan", "'2.weight': stored 16384 NaN values of 16384"),
])
def test_a_model_file_whose_weights_do_not_fit_its_config_is_refused_naming_the_file(
        tmp_path, capsys, suffix, spoil, text):
    from nodegraph import TorchModel
    from nodegraph.models import save_model

    model = _bundled_model()
    state = dict(model.state)
    if spoil == "shape":
        state["2.weight"] = state["2.weight"][:, :-1]
    elif spoil == "float64":
        state = {key: value.astype(np.float64) for key, value in state.items()}
    elif spoil == "nan":
        state["2.weight"] = np.full_like(state["2.weight"], np.nan)
    else:
        del state["4.bias"]
    path = tmp_path / f"removal{suffix}"
    save_model(TorchModel(model.architecture, model.config, state, model.normalization), path)
    capture, out = tmp_path / "capture.npz", tmp_path / "out.npz"
    _capture(capture)
    err = _run(capsys, "dynamics_remove.json", f"capture={capture}", f"skull={capture}",
               f"model={path}", f"output={out}")
    _once(err, "dynamics.LoadModel 'network'", "'path'", str(path),
          "expected the weights of the 'dynamics.MLP' module its config builds", text)
    assert not out.exists()


def test_a_model_file_of_an_unknown_architecture_is_refused_naming_the_file(tmp_path):
    from nodegraph import TorchModel
    from nodegraph.models import load_model, save_model

    model = _bundled_model()
    path = tmp_path / "removal.safetensors"
    save_model(TorchModel("dynamics.MLPP", model.config, model.state, model.normalization), path)
    with pytest.raises(ValueError, match=r"removal\.safetensors: unknown architecture 'dynamics\.MLPP'; "
                                         r"did you mean 'dynamics\.MLP'"):
        load_model(path)


def test_a_missing_camera_file_is_refused_naming_node_parameter_and_file(tmp_path, capsys):
    from nodes.io.image import write_image

    write_image(tmp_path / "plate.0000.png", np.zeros((32, 40, 3), np.uint8), ["R", "G", "B"], "uint8")
    camera, out = tmp_path / "no_such_camera.json", tmp_path / "fit.npz"
    for graph in ("fit_video.json", "fit_video_temporal.json"):
        err = _run(capsys, graph, f"images={tmp_path / 'plate.%04d.png'}", f"camera={camera}",
                   f"output={out}", f"report={tmp_path / 'report'}")
        _once(err, "fit.PlateCamera 'camera'", "'path'", str(camera), "found no file")
        assert "FileNotFoundError" not in err and not out.exists()


@pytest.mark.parametrize("value", ["1e308", "1e13", "-1", "nan", "inf"])
def test_an_absurd_fps_parameter_is_refused_at_validation(tmp_path, capsys, value):
    capture, out = tmp_path / "capture.npz", tmp_path / "out.npz"
    _capture(capture)
    err = _run(capsys, "dynamics_remove.json", f"capture={capture}", f"skull={capture}",
               f"fps={value}", f"output={out}")
    assert "node 'remove', 'fps'" in err and "OverflowError" not in err, err
    assert not out.exists()


def test_a_usd_capture_read_while_planning_does_not_deadlock_with_the_node_preloads(tmp_path):
    """A fresh process (pxr and torch not yet imported) reading a USD capture's header while
    planning, without a cache: stabilize.json hung forever when stab's preload imported torch
    in a background thread while planning imported pxr (both waited on the other's lock)."""
    import os
    import subprocess
    import sys

    capture = tmp_path / "capture.usda"
    capture.write_text("#usda 1.0\n( nonsense")
    argv = [sys.executable, "-c", "import sys; from nodegraph.cli import main; sys.exit(main())", "run",
            str(GRAPHS / "stabilize.json"), f"capture={capture}", f"output={tmp_path / 'out.npz'}",
            f"report={tmp_path / 'report'}", "--no-cache", "--progress", "none"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=300,
                          env=os.environ | {"PYTHONPATH": str(GRAPHS.parent)})
    assert done.returncode == 2, done.stderr
    assert f"file '{capture}': expected a readable USD stage" in done.stderr
    assert not (tmp_path / "out.npz").exists() and not (tmp_path / "report").exists()
