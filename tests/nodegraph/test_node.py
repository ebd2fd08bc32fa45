"""The Node base: params, run_node, error wrapping, cache-key params."""

from __future__ import annotations

import numpy as np
import pytest

from nodegraph import NodeError, ParamSequence, run_node
from nodegraph.testing import Fail, Ramp, Scale, Sum


def test_run_node_runs_in_process():
    ramp = run_node(Ramp, {"num_frames": 5, "start": 1.0, "slope": 2.0})["values"]
    np.testing.assert_array_equal(ramp.values.ravel(), [1, 3, 5, 7, 9])
    scaled = run_node(Scale, {"factor": 0.5}, values=ramp)["scaled"]
    np.testing.assert_array_equal(scaled.values.ravel(), [0.5, 1.5, 2.5, 3.5, 4.5])


def test_run_node_source_uses_given_frames():
    out = run_node(Ramp, {"num_frames": 10}, frames=range(4, 7))["values"]
    np.testing.assert_array_equal(out.values.ravel(), [4, 5, 6])


def test_bad_param_names_node_and_param():
    with pytest.raises(NodeError, match="'factor'") as info:
        Scale({"factor": "many"}, node_id="scale1")
    assert "scale1" in str(info.value) and info.value.bad_input
    with pytest.raises(NodeError, match="'nope': unknown parameter"):
        Scale({"nope": 1})


def test_missing_and_wrong_inputs_name_the_port():
    with pytest.raises(NodeError, match="'values': required input is missing"):
        run_node(Scale, {}, frames=range(3))
    with pytest.raises(NodeError, match="'values': input expected ParamSequence, found int"):
        run_node(Scale, {}, values=3)


def test_optional_input_may_be_missing():
    a = ParamSequence(np.ones((3, 1), np.float32), ["v"])
    assert run_node(Sum, {}, a=a)["total"].values.sum() == 3


def test_input_error_and_crash_are_told_apart():
    values = run_node(Ramp, {"num_frames": 4})["values"]
    with pytest.raises(NodeError, match="'values': frame 2 is not acceptable") as info:
        run_node(Fail, {"frames": [2], "bad_input": True}, values=values)
    assert info.value.bad_input and info.value.port == "values"
    with pytest.raises(NodeError, match="deliberate failure") as info:
        run_node(Fail, {"frames": [2]}, values=values)
    assert not info.value.bad_input and isinstance(info.value.__cause__, RuntimeError)


def test_frame_count_mismatch_is_reported():
    values = run_node(Ramp, {"num_frames": 4})["values"]
    with pytest.raises(NodeError, match="expected 3 frames, found 4"):
        run_node(Scale, {}, frames=range(3), values=values)


def test_key_params_skip_outputs_neutral_params():
    assert Scale({"factor": 2.0, "label": "a"}).key_params() == Scale({"factor": 2.0, "label": "b"}).key_params()
    assert Scale({"factor": 2.0}).key_params() != Scale({"factor": 3.0}).key_params()
    assert len(Scale.code_hash()) == 64
