"""A gap in a numbered frame pattern (frame 0005 missing among 0000-0009) is one error while
planning, before anything runs: exit 2 naming the node, its `path` parameter, the pattern and
the missing numbers; a run whose frames avoid the gap still runs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph
from nodegraph.cli import main
from nodegraph.errors import NodeError
from nodegraph.schedule import plan_run
from nodes.io._files import check_no_missing_files
from nodes.io.image import write_image

GAPS = (5, 7)


def _plates(folder: Path, count: int = 10, gaps: tuple[int, ...] = GAPS) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    for f in range(count):
        if f not in gaps:
            write_image(folder / f"plate.{f:04d}.png", np.full((8, 8, 3), f / count, np.float32),
                        ["R", "G", "B"], "uint8")
    return str(folder / "plate.%04d.png")


def _meshes(folder: Path, count: int = 10, gaps: tuple[int, ...] = GAPS) -> str:
    folder.mkdir(parents=True, exist_ok=True)
    for f in range(count):
        if f not in gaps:
            (folder / f"face.{f:04d}.obj").write_text(f"v 0 0 {f}\nv 1 0 {f}\nv 0 1 {f}\nf 1 2 3\n")
    return str(folder / "face.%04d.obj")


def _copy_graph(kind: str, source: str, dest: str) -> Graph:
    g = Graph()
    if kind == "image":
        g.add("io.LoadImageSequence", id="load", path=source)
        g.add("io.SaveImageSequence", id="save", path=dest)
        g.connect("load.images", "save.images")
    else:
        g.add("io.LoadMeshSequence", id="load", path=source)
        g.add("io.SaveMeshSequence", id="save", path=dest)
        g.connect("load.mesh", "save.mesh")
    return g


def test_the_check_names_the_run_frames_and_every_gap_of_the_pattern():
    check_no_missing_files("p.%04d.png", range(0, 5), 0, [0, 1, 2, 3, 4, 6, 9])  # the gaps are past the run
    with pytest.raises(ValueError) as err:
        check_no_missing_files("p.%04d.png", range(4, 8), 0, [0, 1, 2, 3, 4, 6, 9])
    text = str(err.value)
    assert "frames 5, 7 missing (file 'p.0005.png' and others)" in text
    assert "the pattern's files 0..9 lack numbers 5, 7, 8 (3 of 10)" in text
    # run frame f is file first + f: with files numbered from 100, frame 2 is file 102
    with pytest.raises(ValueError, match=r"frame 2 missing \(file 'p.0102.png'\).*lack number 102 \(1 of 4\)"):
        check_no_missing_files("p.%04d.png", range(0, 4), 100, [100, 101, 103])
    with pytest.raises(ValueError, match=r"numbers 0, 2, 4, .*\(25 in all\)"):  # long lists are cut
        check_no_missing_files("p.%04d.png", range(0, 51), 0, list(range(1, 51, 2)))
    # frames past the last file are the frame-count check's (`--frames` past a source's end)
    check_no_missing_files("p.%04d.png", range(3, 9), 0, [0, 1, 2, 3, 4])
    with pytest.raises(ValueError, match=r"frames 0, 1 missing .*the pattern's files 8..11 lack numbers 8, 9 \(2 of 4\)"):
        check_no_missing_files("p.%04d.png", range(0, 2), 8, [10, 11])  # a pinned first file that is absent


@pytest.mark.parametrize("kind", ["image", "mesh"])
def test_a_gap_is_refused_while_planning(tmp_path, kind):
    source = _plates(tmp_path / "in") if kind == "image" else _meshes(tmp_path / "in")
    dest = str(tmp_path / "out" / ("copy.%04d.png" if kind == "image" else "copy.%04d.obj"))
    g = _copy_graph(kind, source, dest)
    with pytest.raises(NodeError) as err:
        plan_run(g, chunk=2)  # planning only: nothing has run
    text = str(err.value)
    for piece in ("'load'", "'path'", source, "frame 5 missing", "lack numbers 5, 7 (2 of 10)"):
        assert piece in text, (piece, text)
    assert err.value.bad_input
    plan_run(g, chunk=2, frames=range(0, 5))  # frames before the gap: planned


@pytest.mark.parametrize("kind", ["image", "mesh"])
def test_the_command_line_exits_2_once_and_writes_nothing(tmp_path, capsys, kind):
    source = _plates(tmp_path / "in") if kind == "image" else _meshes(tmp_path / "in")
    out = tmp_path / "out"
    dest = str(out / ("copy.%04d.png" if kind == "image" else "copy.%04d.obj"))
    graph = tmp_path / "copy.json"
    _copy_graph(kind, source, dest).save(graph)
    code = main(["run", str(graph), "--no-cache", "--scheduler", "sync", "--chunk", "2", "--progress", "none"])
    err = capsys.readouterr().err
    assert code == 2, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if "lack numbers 5, 7" in line]
    assert len(lines) == 1 and "'load'" in lines[0] and source in lines[0], err
    assert not out.exists()
    assert main(["run", str(graph), "--no-cache", "--scheduler", "sync", "--chunk", "2", "--progress", "none",
                 "--frames", "0:5"]) == 0
    assert len(list(out.iterdir())) == 5
