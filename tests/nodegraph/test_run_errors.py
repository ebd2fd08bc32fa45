"""Exit codes and messages users met: bad schedulers, strict booleans, huge floats, failures
repeated over chunks, tracebacks of node bugs, missing input files."""

from __future__ import annotations

import json
import socket
import time

import pytest

from nodegraph import Graph, NodeParams, Param, run
from nodegraph import dask_run, registry, runner
from nodegraph.cli import main
from nodegraph.errors import GraphError, NodeError, SchedulerError
from nodegraph.graph import parse_value

from .helpers import chain


def _failing(path, *, bad_input: bool, message: str = "", frames=(0, 5, 10, 15, 20, 25, 30, 35)):
    """ramp (40 frames) -> fail, failing in the chunks holding `frames` (8 chunks of 5)."""
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=40)
    fail = g.add("test.Fail", id="fail", frames=list(frames), bad_input=bad_input, message=message)
    g.connect(ramp["values"], fail["values"])
    g.expose("flag", fail, "bad_input")
    g.save(path)
    return path


@pytest.fixture
def graph_file(tmp_path):
    path = tmp_path / "chain.json"
    chain(num_frames=20).save(path)
    return path


# -- 1. the scheduler ------------------------------------------------------------------------

def test_unknown_scheduler_is_exit_2_in_one_line(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "--scheduler", "nosuch", "--cache", str(cache_dir),
                 "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("nodegraph: --scheduler: expected sync, threads, processes or a dask.distributed "
                           "address tcp://host:port, found 'nosuch'")


def test_unknown_scheduler_is_refused_before_planning():
    with pytest.raises(SchedulerError, match="found 'nosuch'"):
        run(chain(), scheduler="nosuch", cache=False)
    for good in ("tcp://farm:8786", "tcp://10.0.0.1:8786", "farm:8786", "tls://farm:8786"):
        runner.check_scheduler(good)


def test_unreachable_scheduler_fails_fast_with_exit_2(graph_file, cache_dir, capsys, monkeypatch):
    pytest.importorskip("distributed")
    assert runner.CONNECT_TIMEOUT_S <= 10
    monkeypatch.setattr(dask_run, "CONNECT_TIMEOUT_S", 1.0)
    with socket.socket() as sock:  # a port nothing listens on
        sock.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{sock.getsockname()[1]}"
    start = time.monotonic()
    assert main(["run", str(graph_file), "--scheduler", address, "--cache", str(cache_dir),
                 "--progress", "none"]) == 2
    assert time.monotonic() - start < 15
    err = capsys.readouterr().err
    assert f"--scheduler: expected a dask.distributed scheduler answering at {address}, found none within 1 s" in err
    assert "Traceback" not in err


def test_an_address_answered_by_something_else_than_dask_is_exit_2(graph_file, cache_dir, capsys, monkeypatch):
    """A port where a proxy or web server answers (its bytes read as a huge frame length gave
    numpy's ArrayMemoryError and exit 1 through a traceback) is exit 2 naming the address."""
    pytest.importorskip("distributed")
    import threading

    monkeypatch.setattr(dask_run, "CONNECT_TIMEOUT_S", 2.0)
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(4)
    address = f"tcp://127.0.0.1:{server.getsockname()[1]}"

    def answer() -> None:
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            with conn:
                conn.sendall(b"HTTP/1.1 200 OK\r\nContent-Length: 0\r\n\r\n" * 4)

    threading.Thread(target=answer, daemon=True).start()
    try:
        start = time.monotonic()
        code = main(["run", str(graph_file), "--scheduler", address, "--cache", str(cache_dir),
                     "--progress", "none"])
    finally:
        server.close()
    assert code == 2
    assert time.monotonic() - start < 15
    err = capsys.readouterr().err
    assert f"--scheduler: expected a dask.distributed scheduler answering at {address}" in err
    assert "Traceback" not in err


# -- 2. booleans -----------------------------------------------------------------------------

@pytest.mark.parametrize("value", ["yes", "true", 1, 0])
def test_graph_file_boolean_must_be_a_json_boolean(tmp_path, value):
    path = _failing(tmp_path / "g.json", bad_input=False)
    data = json.loads(path.read_text())
    data["nodes"]["fail"]["params"]["bad_input"] = value
    path.write_text(json.dumps(data))
    with pytest.raises(GraphError, match=r"node 'fail', 'bad_input': expected true or false, found"):
        Graph.load(path)


def test_command_line_booleans_still_parse(tmp_path, cache_dir, capsys):
    cls = registry.get("test.Fail")
    assert parse_value(cls, "bad_input", "true") is True and parse_value(cls, "bad_input", "false") is False
    path = _failing(tmp_path / "g.json", bad_input=False, frames=[])
    assert main(["run", str(path), "flag=true", "--set", "fail.bad_input=false", "--cache", str(cache_dir),
                 "--progress", "none"]) == 0
    assert main(["run", str(path), "flag=yes", "--cache", str(cache_dir)]) == 2
    assert "'bad_input': expected true or false, found the string 'yes'" in capsys.readouterr().err


# -- 3. float magnitudes ---------------------------------------------------------------------

def test_huge_float_on_the_command_line_is_exit_2_naming_the_parameter(graph_file, cache_dir, capsys):
    assert main(["run", str(graph_file), "--set", "ramp.slope=1e308", "--cache", str(cache_dir),
                 "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert "node 'ramp', 'slope': expected a number of magnitude at most 1e12" in err and "found 1e+308" in err


def test_declared_bounds_replace_the_magnitude_guard():
    class Params(NodeParams):
        free: float = Param(0.0)
        positive: float = Param(1.0, gt=0)
        wide: float = Param(0.0, ge=-1e20, le=1e20)
        many: list[float] = Param([])

    Params(free=1e12, positive=1e12, wide=1e19, many=[-1e12])
    for bad in ({"free": -2e12}, {"positive": 1e13}, {"many": [0.0, 1e300]}):
        with pytest.raises(ValueError, match="magnitude at most 1e12"):
            Params(**bad)
    with pytest.raises(ValueError, match="finite"):
        Params(free=float("inf"))


def test_no_node_default_breaks_the_strict_params():
    from nodegraph.params import number_problem

    bad = []
    for name, cls in registry.all_types().items():
        for field, info in cls.Params.model_fields.items():
            if not info.is_required():
                value = info.get_default(call_default_factory=True)
                problem = number_problem(info.annotation, value, tuple(info.metadata))
                if problem:
                    bad.append(f"{name}.{field}: {problem}")
    assert not bad


# -- 4. and 5. failures repeated over chunks, tracebacks of node bugs -------------------------

def test_same_bad_input_in_every_chunk_is_printed_once_with_its_count(tmp_path, cache_dir, capsys):
    path = _failing(tmp_path / "g.json", bad_input=True, message="expected a closed mesh, found 3 holes")
    assert main(["run", str(path), "--chunk", "5", "--cache", str(cache_dir), "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert err.count("FAILED") == 1
    assert "FAILED test.Fail 'fail': 'values': expected a closed mesh, found 3 holes (in 8 of 8 chunks)" in err
    assert err.count("error record") == 1 and "and 7 more in" in err
    assert "Traceback" not in err  # bad input: no traceback


def test_failure_in_some_chunks_names_them():
    g = Graph()
    ramp = g.add("test.Ramp", id="ramp", num_frames=40)
    fail = g.add("test.Fail", id="fail", frames=[3, 12], bad_input=True, message="bad topology")
    g.connect(ramp["values"], fail["values"])
    result = run(g, chunk=5, scheduler="sync", cache=False)
    assert result.summary().splitlines()[1:] == [
        "FAILED test.Fail 'fail': 'values': bad topology (in 2 of 8 chunks: frames 0:5, 10:15)"]


def test_node_bug_prints_its_traceback_once(tmp_path, cache_dir, capsys):
    path = _failing(tmp_path / "g.json", bad_input=False)
    assert main(["run", str(path), "--chunk", "5", "--cache", str(cache_dir), "--progress", "none"]) == 1
    err = capsys.readouterr().err
    assert err.count("traceback of test.Fail 'fail' (frames 0:5); the same in 7 more chunk(s):") == 1
    assert 'raise RuntimeError(self.params.message or f"deliberate failure' in err
    assert "RuntimeError: deliberate failure at frame 0" in err
    assert err.count("Traceback (most recent call last)") == 2  # the node's exception and its NodeError


# -- 6. missing input files ------------------------------------------------------------------

@pytest.mark.parametrize("cached", [True, False])
def test_missing_input_file_is_exit_2_naming_node_parameter_and_path(tmp_path, cache_dir, capsys, cached):
    g = Graph()
    g.add("test.ReadText", id="read", path=str(tmp_path / "v{frame}.txt"), num_frames=2)
    path = tmp_path / "g.json"
    g.save(path)
    cache = ["--cache", str(cache_dir)] if cached else ["--no-cache"]
    assert main(["run", str(path), *cache, "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert err.strip() == (f"nodegraph: test.ReadText 'read': 'path': expected a readable input file, found no "
                           f"file '{tmp_path / 'v0.txt'}'")
    with pytest.raises(NodeError) as info:
        run(g, cache=False)
    assert info.value.port == "path" and info.value.bad_input


def test_frames_past_a_sources_end_are_refused_before_running(tmp_path, cache_dir, capsys):
    """--frames 0:999 on a 20-frame capture failed in every chunk past frame 20, one different
    line per chunk; now one exit-2 line naming the source and its frame count, before running."""
    with pytest.raises(GraphError, match=r"node 'ramp': --frames 0:41: expected frames within the 40 frame\(s\) "
                                         r"this source has \(0:40\), found stop 41"):
        run(chain(40), frames=range(0, 41), cache=cache_dir, scheduler="sync")
    assert not (cache_dir / "objects").exists()
    assert run(chain(40), frames=range(10, 40), cache=cache_dir, scheduler="sync").ok  # up to the end is fine
    graph_file = tmp_path / "chain.json"
    chain(40).save(graph_file)
    assert main(["run", str(graph_file), "--frames", "0:999", "--cache", str(cache_dir), "--progress", "none"]) == 2
    err = capsys.readouterr().err
    assert err.count("expected frames within the 40 frame(s)") == 1 and "Traceback" not in err


def test_a_model_check_names_its_parameter_through_param_problem():
    """A Params validator raises ParamProblem(param, problem): errors name that parameter (the
    report does not read the name back out of the message text)."""
    from pydantic import model_validator

    from nodegraph.params import ParamProblem, format_validation_error

    class Params(NodeParams):
        low: float = Param(0.0, description="lower end")
        high: float = Param(1.0, description="upper end")

        @model_validator(mode="after")
        def _ordered(self) -> "Params":
            if not self.high > self.low:
                raise ParamProblem("high", f"expected more than low ({self.low}), found {self.high}")
            return self

    with pytest.raises(ValueError) as err:
        Params(low=2.0, high=1.0)
    assert format_validation_error(err.value) == [("high", "expected more than low (2.0), found 1.0")]
    # a plain ValueError whose text merely looks like "'name': ..." stays a model-wide message
    class Plain(NodeParams):
        @model_validator(mode="after")
        def _fail(self) -> "Plain":
            raise ValueError("'high': looks like a parameter")

    with pytest.raises(ValueError) as err:
        Plain()
    assert format_validation_error(err.value) == [("params", "'high': looks like a parameter")]
    # strict numbers go through the same path
    with pytest.raises(ValueError) as err:
        Params(low="0")
    assert format_validation_error(err.value) == [("low", "expected a number, found the string '0'")]


def test_graph_parameters_keep_node_and_parameter_apart(tmp_path):
    g = Graph()
    g.add("test.Ramp", id="shot", num_frames=4)
    g.expose("frames", "shot", "num_frames", description="how many")
    g.save(tmp_path / "g.json")
    assert json.loads((tmp_path / "g.json").read_text())["parameters"] == {
        "frames": {"target": "shot.num_frames", "description": "how many"}}
    loaded = Graph.load(tmp_path / "g.json")
    gp = loaded.parameters["frames"]
    assert (gp.node, gp.param, gp.target) == ("shot", "num_frames", "shot.num_frames")
    loaded.apply({"frames": 6})
    assert loaded.nodes["shot"].params["num_frames"] == 6


@pytest.mark.parametrize("under", ["", "sub"])
def test_a_cache_path_that_is_or_lies_under_a_file_is_exit_2_before_running(graph_file, tmp_path, capsys,
                                                                              monkeypatch, under):
    a_file = tmp_path / "a_file"
    a_file.write_text("not a folder")
    cache = a_file / under if under else a_file
    for argv in (["--cache", str(cache)], ["--explain", "--cache", str(cache)]):
        assert main(["run", str(graph_file), *argv, "--progress", "none"]) == 2
        err = capsys.readouterr().err
        assert f"--cache: expected a folder for the cache, found '{cache}'" in err and "Traceback" not in err, err
    monkeypatch.setenv("NODEGRAPH_CACHE", str(cache))  # the same from the environment
    assert main(["run", str(graph_file), "--progress", "none"]) == 2
    assert "$NODEGRAPH_CACHE: expected a folder" in capsys.readouterr().err
    assert a_file.read_text() == "not a folder"
