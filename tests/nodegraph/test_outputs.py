"""Outputs never destroy inputs (checked before anything runs), and a run's outputs are
all-or-nothing: a failed run leaves previous outputs untouched and writes no partial ones."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from nodegraph import Graph, GraphError, run
from nodegraph.cli import main
from nodegraph.staging import STAGE_PREFIX


def _line(value: float) -> str:
    """A line as test.WriteText writes it."""
    return f"{np.float32(value)!r}\n"


def _staging_left(root: Path) -> list[Path]:
    return [p for p in root.rglob(f"{STAGE_PREFIX}*")]


def _lines_to(tmp_path: Path, source: Path, out: str, writer: str = "test.WriteText", param: str = "path") -> Graph:
    g = Graph()
    g.add("test.ReadLines", id="load", path=str(source))
    g.add(writer, id="save", **{param: out})
    g.connect("load.values", "save.values")
    return g


def _numbers(path: Path, count: int = 6) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("".join(f"{i}\n" for i in range(count)))
    return path


# -- A. outputs that would destroy inputs are refused before anything runs ----------------

def test_output_file_equal_to_an_input_file_is_refused_naming_both(tmp_path, cache_dir):
    source = _numbers(tmp_path / "shot.txt")
    before = source.read_text()
    with pytest.raises(GraphError) as info:
        run(_lines_to(tmp_path, source, str(source)), cache=cache_dir, scheduler="sync")
    text = str(info.value)
    assert "node 'save', 'path'" in text and "node 'load' parameter 'path'" in text and str(source) in text
    assert "would overwrite the input file" in text
    assert source.read_text() == before and not (cache_dir / "objects").exists()  # nothing ran


def test_output_equal_to_input_from_the_command_line_exits_2(tmp_path, cache_dir, monkeypatch, capsys):
    source = _numbers(tmp_path / "shot.txt")
    g = _lines_to(tmp_path, source, str(tmp_path / "out.txt"))
    g.expose("capture", "load", "path")
    g.expose("output", "save", "path")
    g.save(tmp_path / "g.json")
    monkeypatch.chdir(tmp_path)
    code = main(["run", str(tmp_path / "g.json"), "capture=shot.txt", "output=shot.txt", "--cache", str(cache_dir),
                 "--progress", "none"])
    assert code == 2
    err = capsys.readouterr().err
    assert "'save'" in err and "'load'" in err and "shot.txt" in err
    assert source.read_text() == "0\n1\n2\n3\n4\n5\n"


def test_output_pattern_that_could_produce_an_input_file_is_refused(tmp_path, cache_dir):
    for f in range(4):
        (tmp_path / f"v{f}.txt").write_text(f"{f}\n")
    g = Graph()
    g.add("test.ReadText", id="read", path=str(tmp_path / "v{frame}.txt"), num_frames=4)
    g.add("test.WriteText", id="write", path=str(tmp_path / "v{frame}.txt"))
    g.connect("read.values", "write.values")
    with pytest.raises(GraphError, match=r"node 'write', 'path'.*input pattern .*node 'read' parameter 'path'"):
        run(g, cache=cache_dir, scheduler="sync")
    # another prefix in the same folder is fine
    g.set("write", path=str(tmp_path / "w{frame}.txt"))
    assert run(g, cache=cache_dir, scheduler="sync").ok
    assert (tmp_path / "w3.txt").read_text() == _line(3)


def test_output_file_matching_an_input_pattern_is_refused(tmp_path, cache_dir):
    for f in range(4):
        (tmp_path / f"v{f}.txt").write_text(f"{f}\n")
    g = Graph()
    g.add("test.ReadText", id="read", path=str(tmp_path / "v{frame}.txt"), num_frames=4)
    g.add("test.WriteText", id="write", path=str(tmp_path / "v2.txt"))
    g.connect("read.values", "write.values")
    with pytest.raises(GraphError, match="would overwrite a file of the input pattern"):
        run(g, cache=cache_dir, scheduler="sync")


def test_output_folder_that_an_input_pattern_reads_is_refused(tmp_path, cache_dir):
    plates = tmp_path / "plates"
    plates.mkdir()
    for f in range(4):
        (plates / f"plate.{f:04d}.txt").write_text(f"{f}\n")
    g = Graph()
    g.add("test.ReadText", id="read", path=str(plates / "plate.{frame:04d}.txt"), num_frames=4)
    g.add("test.WriteSummary", id="report", folder=str(plates))
    g.connect("read.values", "report.values")
    with pytest.raises(GraphError) as info:
        run(g, cache=cache_dir, scheduler="sync")
    assert "node 'report', 'folder'" in str(info.value) and "the folder that the input pattern" in str(info.value)
    assert "node 'read' parameter 'path'" in str(info.value)
    assert sorted(p.name for p in plates.iterdir()) == [f"plate.{f:04d}.txt" for f in range(4)]
    g.set("report", folder=str(plates / "report"))  # a subfolder is fine
    assert run(g, cache=cache_dir, scheduler="sync").ok


def test_output_folder_containing_an_input_file_is_refused(tmp_path, cache_dir):
    source = _numbers(tmp_path / "data" / "takes" / "shot.txt")
    g = _lines_to(tmp_path, source, str(tmp_path / "data"), writer="test.WriteSummary", param="folder")
    with pytest.raises(GraphError, match="is \\(or contains\\) the folder of the input file"):
        run(g, cache=cache_dir, scheduler="sync")


def test_output_whose_parent_is_a_file_is_refused_before_running(tmp_path, cache_dir):
    source = _numbers(tmp_path / "shot.txt")
    (tmp_path / "afile").write_text("not a folder\n")
    g = _lines_to(tmp_path, source, str(tmp_path / "afile" / "sub" / "out.txt"))
    with pytest.raises(GraphError, match=r"node 'save', 'path'.*'.*afile' is a file, not a folder"):
        run(g, cache=cache_dir, scheduler="sync")
    assert not (cache_dir / "objects").exists()


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="needs permissions that apply (not root)")
def test_output_in_an_unwritable_folder_is_refused_before_running(tmp_path, cache_dir):
    source = _numbers(tmp_path / "shot.txt")
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        g = _lines_to(tmp_path, source, str(locked / "new" / "out.txt"))
        with pytest.raises(GraphError, match="is not writable"):
            run(g, cache=cache_dir, scheduler="sync")
        g.set("save", path=str(locked / "out.txt"))
        with pytest.raises(GraphError, match="cannot write in the folder"):
            run(g, cache=cache_dir, scheduler="sync")
    finally:
        locked.chmod(0o700)


def test_a_folder_that_refuses_new_files_is_found_even_when_os_access_says_yes(tmp_path, cache_dir, monkeypatch):
    """Root passes os.access everywhere; a read-only mount or /proc still refuses. The check
    makes (and removes) a hidden folder where the staging will, so such an output is exit 2
    before anything runs, not a raw Errno from the writer after the work."""
    import tempfile

    source = _numbers(tmp_path / "shot.txt")
    locked = tmp_path / "readonly"
    locked.mkdir()

    def refuse(*args: object, dir: str | os.PathLike | None = None, **kwargs: object) -> str:
        if dir is not None and Path(dir) == locked:
            raise PermissionError(30, "Read-only file system")
        return real_mkdtemp(*args, dir=dir, **kwargs)

    real_mkdtemp = tempfile.mkdtemp
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    g = _lines_to(tmp_path, source, str(locked / "out.txt"))
    with pytest.raises(GraphError, match=r"cannot write in the folder '.*readonly' \(Read-only file system\)"):
        run(g, cache=cache_dir, scheduler="sync")
    g.set("save", path=str(locked / "new" / "out.txt"))
    with pytest.raises(GraphError, match=r"'.*readonly' does not accept new folders \(Read-only file system\)"):
        run(g, cache=cache_dir, scheduler="sync")
    assert not (cache_dir / "objects").exists()
    assert list(locked.iterdir()) == []
    g.set("save", path=str(tmp_path / "fine" / "out.txt"))  # the probe leaves nothing where it succeeds
    run(g, cache=cache_dir, scheduler="sync")
    assert _staging_left(tmp_path) == []


@pytest.mark.skipif(not os.path.isdir("/proc/self"), reason="needs Linux's /proc")
def test_an_output_under_proc_is_refused_before_running_even_for_root(tmp_path, cache_dir, capsys):
    source = _numbers(tmp_path / "shot.txt")
    g = _lines_to(tmp_path, source, "/proc/nodegraph-test/out.txt")
    with pytest.raises(GraphError, match=r"node 'save', 'path': output '/proc/nodegraph-test/out.txt': "
                                         r"cannot create the folder"):
        run(g, cache=cache_dir, scheduler="sync")


@pytest.mark.parametrize("first, second, shown", [
    ("out.txt", "out.txt", "is also the output"),
    ("out.txt", "out.txt/inner.txt", "would be inside the output file"),
    ("lines.%04d.txt", "lines.{frame:04d}.txt", "could write the same files as the output pattern"),
])
def test_two_outputs_at_one_path_are_refused_before_running(tmp_path, cache_dir, first, second, shown):
    """stabilize.json output=r.npz report=r.npz ran the whole graph, then failed in the report's
    writer with a raw FileExistsError; now exit 2 before anything runs, naming both writers."""
    source = _numbers(tmp_path / "shot.txt")
    g = _lines_to(tmp_path, source, str(tmp_path / first))
    g.add("test.WriteText", id="save_again", path=str(tmp_path / second))
    g.connect("load.values", "save_again.values")
    with pytest.raises(GraphError, match=rf"node 'save_again', 'path': output '.*' {shown} '.*' of node 'save' "
                                         r"parameter 'path'; choose another output path"):
        run(g, cache=cache_dir, scheduler="sync")
    assert not (cache_dir / "objects").exists()
    g.set("save_again", path=str(tmp_path / "elsewhere.txt"))  # distinct paths are fine
    run(g, cache=cache_dir, scheduler="sync")
    assert (tmp_path / "elsewhere.txt").read_text() == "".join(_line(i) for i in range(6))


def test_output_inside_the_cache_folder_is_refused_before_running(tmp_path, cache_dir):
    """`nodegraph cache gc` / `clear` delete what is in the cache folder: an output there would be
    lost with the cache's entries."""
    source = _numbers(tmp_path / "shot.txt")
    inside = cache_dir / "results" / "lines.txt"
    with pytest.raises(GraphError, match=r"node 'save', 'path': output '.*lines.txt' is inside the cache folder"):
        run(_lines_to(tmp_path, source, str(inside)), cache=cache_dir, scheduler="sync")
    assert not inside.exists() and not (cache_dir / "objects").exists()  # nothing ran
    run(_lines_to(tmp_path, source, str(inside)), cache=False, scheduler="sync")  # no cache: nothing to clean
    assert inside.read_text() == "".join(_line(i) for i in range(6))


def test_empty_output_path_is_not_checked(tmp_path, cache_dir):
    source = _numbers(tmp_path / "shot.txt")
    g = _lines_to(tmp_path, source, "", writer="test.WriteSummary", param="folder")
    assert run(g, cache=cache_dir, scheduler="sync").ok


# -- B. all-or-nothing outputs -------------------------------------------------------------

def _ramp_writer(path: str, fail_frames: list[int] | None = None, num_frames: int = 8) -> Graph:
    """ramp -> fail (bad input on `fail_frames`) -> write (one file per frame)."""
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=num_frames)
    g.add("test.Fail", id="fail", frames=list(fail_frames or []), bad_input=True)
    g.add("test.WriteText", id="write", path=path)
    g.connect("ramp.values", "fail.values")
    g.connect("fail.passed", "write.values")
    return g


def test_chunked_writer_whose_input_fails_partway_writes_nothing(tmp_path, cache_dir):
    out = tmp_path / "out"
    result = run(_ramp_writer(str(out / "v{frame}.txt"), fail_frames=[5]), chunk=2, scheduler="threads",
                 cache=cache_dir)
    assert result.exit_code == 2
    assert result.executed("write") == 3  # the other chunks ran ...
    assert not out.exists()  # ... but their files were held back
    assert result.held_back == ["write"]
    assert "nothing written: 1 writer(s) held back (write) because node 'fail' failed" in result.summary()
    assert not _staging_left(tmp_path)
    # fixed: everything is written, the held-back chunks come from the cache
    fixed = run(_ramp_writer(str(out / "v{frame}.txt")), chunk=2, scheduler="threads", cache=cache_dir)
    assert fixed.ok and sorted(p.name for p in out.iterdir()) == [f"v{f}.txt" for f in range(8)]
    assert not _staging_left(tmp_path)


def test_failed_run_leaves_previous_outputs_untouched(tmp_path, cache_dir):
    out = tmp_path / "out"
    pattern = str(out / "v{frame}.txt")
    assert run(_ramp_writer(pattern), chunk=2, scheduler="sync", cache=cache_dir).ok
    before = {p.name: (p.read_text(), p.stat().st_mtime_ns) for p in out.iterdir()}
    g = _ramp_writer(pattern, fail_frames=[7])
    g.set("ramp", start=100.0)  # new values for every frame
    result = run(g, chunk=2, scheduler="sync", cache=cache_dir)
    assert result.exit_code == 2
    assert {p.name: (p.read_text(), p.stat().st_mtime_ns) for p in out.iterdir()} == before
    assert not _staging_left(tmp_path)


def test_writer_failing_after_writing_some_files_writes_none(tmp_path, cache_dir):
    g = Graph()
    g.add("test.Ramp", id="ramp", num_frames=8)
    g.add("test.WriteText", id="write", path=str(tmp_path / "out" / "v{frame}.txt"), fail_frames=[6])
    g.connect("ramp.values", "write.values")
    result = run(g, chunk=2, scheduler="sync", cache=cache_dir)
    assert result.exit_code == 1 and result.count("failed", "write") == 1 and result.executed("write") == 3
    assert not (tmp_path / "out").exists() and not _staging_left(tmp_path)


def test_writer_on_an_independent_branch_is_held_back_and_restored_later(tmp_path, cache_dir):
    def graph(fail: list[int]) -> Graph:
        g = Graph()
        g.add("test.Ramp", id="ramp", num_frames=6)
        g.add("test.WriteText", id="write", path=str(tmp_path / "good{start}.txt"))
        g.add("test.Fail", id="fail", frames=fail)
        g.add("test.Total", id="total")
        g.connect("ramp.values", "write.values")
        g.connect("ramp.values", "fail.values")
        g.connect("fail.passed", "total.values")
        return g

    failed = run(graph([2]), chunk=10, scheduler="threads", cache=cache_dir)
    assert failed.exit_code == 1 and failed.executed("write") == 1
    assert not (tmp_path / "good0.txt").exists() and failed.held_back == ["write"]
    fixed = run(graph([]), chunk=10, scheduler="threads", cache=cache_dir)
    assert fixed.ok and fixed.executed("write") == 0 and fixed.count("restored", "write") == 1
    assert (tmp_path / "good0.txt").read_text() == "".join(_line(v) for v in range(6))
    again = run(graph([]), chunk=10, scheduler="threads", cache=cache_dir)
    assert again.executed() == 0 and again.count("restored") == 0  # the committed file is intact


def test_restoring_a_deleted_file_is_held_back_by_a_failed_run(tmp_path, cache_dir):
    pattern = str(tmp_path / "out" / "v{frame}.txt")

    def graph(fail: list[int]) -> Graph:
        g = Graph()
        g.add("test.Ramp", id="ramp", num_frames=4)
        g.add("test.WriteText", id="write", path=pattern)
        g.add("test.Fail", id="fail", frames=fail)
        g.add("test.Total", id="total")
        g.connect("ramp.values", "write.values")
        g.connect("ramp.values", "fail.values")
        g.connect("fail.passed", "total.values")
        return g

    assert run(graph([]), chunk=2, scheduler="sync", cache=cache_dir).ok
    victim = tmp_path / "out" / "v1.txt"
    victim.unlink()
    failed = run(graph([3]), chunk=2, scheduler="sync", cache=cache_dir)
    assert failed.count("restored", "write") == 1 and not victim.exists()
    fixed = run(graph([]), chunk=2, scheduler="sync", cache=cache_dir)
    assert fixed.count("restored", "write") == 1 and victim.read_text() == _line(1)


def test_a_reader_of_files_written_in_the_same_run_sees_them_and_a_failure_undoes_them(tmp_path, cache_dir):
    out = tmp_path / "out"
    out.mkdir()
    (out / "v1.txt").write_text("old\n")

    def graph(fail: bool) -> Graph:
        g = Graph()
        g.add("test.Ramp", id="ramp", num_frames=3)
        g.add("test.WriteText", id="write", path=str(out / "v{frame}.txt"))
        g.add("test.JoinFiles", id="join", path=str(out / "all.txt"), fail=fail)
        g.connect("ramp.values", "write.values")
        g.connect("write.files", "join.parts")
        return g

    failed = run(graph(True), chunk=2, scheduler="threads", cache=cache_dir)
    assert failed.exit_code == 1 and failed.held_back == ["write", "join"]
    assert sorted(p.name for p in out.iterdir()) == ["v1.txt"] and (out / "v1.txt").read_text() == "old\n"
    assert not _staging_left(tmp_path)
    ok = run(graph(False), chunk=2, scheduler="threads", cache=cache_dir)
    assert ok.ok and (out / "all.txt").read_text() == "".join(_line(v) for v in range(3))
    assert sorted(p.name for p in out.iterdir()) == ["all.txt", "v0.txt", "v1.txt", "v2.txt"]


def test_all_or_nothing_with_worker_processes(tmp_path, cache_dir):
    out = tmp_path / "out"
    failed = run(_ramp_writer(str(out / "v{frame}.txt"), fail_frames=[5]), chunk=2, scheduler="processes",
                 workers=2, cache=cache_dir)
    assert failed.exit_code == 2 and not out.exists() and not _staging_left(tmp_path)
    fixed = run(_ramp_writer(str(out / "v{frame}.txt")), chunk=2, scheduler="processes", workers=2, cache=cache_dir)
    assert fixed.ok and len(list(out.iterdir())) == 8 and not _staging_left(tmp_path)
    again = run(_ramp_writer(str(out / "v{frame}.txt")), chunk=2, scheduler="sync", cache=cache_dir)
    assert again.executed() == 0 and again.count("restored") == 0


def test_cli_reports_what_it_held_back(tmp_path, cache_dir, capsys):
    g = _ramp_writer(str(tmp_path / "out" / "v{frame}.txt"), fail_frames=[5])
    g.save(tmp_path / "g.json")
    assert main(["run", str(tmp_path / "g.json"), "--chunk", "2", "--cache", str(cache_dir),
                 "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert "nothing written: 1 writer(s) held back (write) because node 'fail' failed" in err
    assert not (tmp_path / "out").exists()


def test_staging_folders_of_killed_runs_are_swept(tmp_path, cache_dir):
    import socket
    import subprocess
    import sys

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    host = socket.gethostname().replace(".", "-")
    out = tmp_path / "out"
    left = out / f"{STAGE_PREFIX}{host}.{int(dead.stdout)}.0123456789ab"
    (left / "files").mkdir(parents=True)
    (left / "files" / "v0.txt").write_text("partial\n")
    alive = out / f"{STAGE_PREFIX}{host}.{os.getpid()}.0123456789ab"  # a live run's: kept
    alive.mkdir()
    assert run(_ramp_writer(str(out / "v{frame}.txt"), num_frames=2), scheduler="sync", cache=cache_dir).ok
    assert not left.exists() and alive.exists()


@pytest.mark.parametrize("writer", ["text", "bytes", "npz"])
def test_atomic_writers_give_files_the_usual_permissions(tmp_path, writer):
    """A written file is readable as any file the user makes (0o666 minus the umask), not the
    temporary file's 0o600: the Live Link CSV and the reports were unreadable to other users."""
    import os
    import stat

    import numpy as np

    from nodegraph.files import write_bytes_atomic, write_npz_atomic, write_text_atomic

    path = tmp_path / f"out.{writer}"
    if writer == "text":
        write_text_atomic(path, "a,b\n1,2\n")
    elif writer == "bytes":
        write_bytes_atomic(path, b"\x00\x01")
    else:
        write_npz_atomic(path, {"a": np.zeros(3)})
    mask = os.umask(0o022)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left
