"""Windowed temporal nodes give the same result at any chunk size when run by `nodegraph.run`
(their halo covers the window): Average, FlowInfill, Hybrid and the flow on 10 frames, in one
chunk and in chunks of 2 and 3 frames, with the threads scheduler."""

from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("numba")

from nodegraph import (FRAMEWISE, SEQUENCE, Camera, FaceModel, FlowSequence, Graph, Node, NodeParams,  # noqa: E402
                       Out, ParamSequence, run)
from nodes.flow.geometric import render_flow  # noqa: E402
from nodes.temporal.layout import RIGID_NAMES  # noqa: E402
from tests.support.synthetic import head_motion, make_scene, scene_vertices  # noqa: E402

SIZE, FRAMES = 48, 10


class _Shot:
    """The shot the source nodes below serve (filled by the fixture)."""

    fitted: ClassVar[np.ndarray]
    failed: ClassVar[np.ndarray]
    flow: ClassVar[np.ndarray]
    valid: ClassVar[np.ndarray]
    names: ClassVar[list[str]]
    model: ClassVar[FaceModel]
    camera: ClassVar[Camera]


class ShotFrames(Node):
    """Per-frame inputs of the temporal nodes, sliced to the chunk."""

    type_name = "test.TemporalShotFrames"
    kind = FRAMEWISE

    class Params(NodeParams):
        pass

    fitted = Out(ParamSequence)
    failed = Out(ParamSequence)
    plate_flow = Out(FlowSequence)

    def frame_count(self) -> int:
        return len(_Shot.fitted)

    def run(self) -> dict:
        f = slice(self.frames.start, self.frames.stop)
        return {"fitted": ParamSequence(_Shot.fitted[f], list(RIGID_NAMES) + _Shot.names),
                "failed": ParamSequence(_Shot.failed[f, None].astype(np.float32), ["failed"]),
                "plate_flow": FlowSequence(_Shot.flow[f], _Shot.valid[f])}


class ShotScene(Node):
    """The model and camera of the shot."""

    type_name = "test.TemporalShotScene"
    kind = SEQUENCE

    class Params(NodeParams):
        pass

    model = Out(FaceModel)
    camera = Out(Camera)

    def frame_count(self) -> int:
        return len(_Shot.fitted)

    def run(self) -> dict:
        return {"model": _Shot.model, "camera": _Shot.camera}


@pytest.fixture(scope="module")
def shot():
    scene = make_scene(SIZE)
    names = scene.model.expression_names
    truth = head_motion(FRAMES, names, seed=4, mouth_frames=(3, 8))
    verts = scene_vertices(scene, truth)
    cam = scene.camera
    e = torch.as_tensor(cam.world_to_camera, dtype=torch.float32).expand(FRAMES - 1, 4, 4)
    k = torch.tensor([cam.fx, cam.fy, cam.cx, cam.cy]).expand(FRAMES - 1, 4)
    flow, _ = render_flow(verts[:-1], verts[1:], torch.as_tensor(scene.faces), e, k, SIZE, SIZE)
    rng = np.random.default_rng(1)
    noisy = truth.copy()
    noisy[:, :3] += rng.normal(0, 0.01, (FRAMES, 3))
    noisy[:, 3:6] += rng.normal(0, 0.1, (FRAMES, 3))
    failed = np.zeros(FRAMES, bool)
    failed[5:7] = True
    _Shot.fitted = noisy.astype(np.float32)
    _Shot.failed = failed
    _Shot.flow = np.zeros((FRAMES, SIZE, SIZE, 2), np.float32)
    _Shot.flow[:-1] = flow.permute(0, 2, 3, 1).numpy()
    _Shot.valid = np.r_[np.ones(FRAMES - 1, bool), False]
    _Shot.names = list(names)
    _Shot.model, _Shot.camera = scene.model, scene.camera
    return _Shot


def _graph() -> Graph:
    g = Graph()
    frames = g.add("test.TemporalShotFrames", id="frames")
    scene = g.add("test.TemporalShotScene", id="scene")
    average = g.add("temporal.Average", id="average")
    infill = g.add("temporal.FlowInfill", id="infill", iterations=3, stride=3)
    hybrid = g.add("temporal.Hybrid", id="hybrid", sweeps=2, iterations=2, stride=3)
    g.connect(frames["fitted"], average["fitted"])
    g.connect(frames["failed"], average["failed"])
    for node in (infill, hybrid):
        g.connect(frames["plate_flow"], node["plate_flow"])
        g.connect(scene["model"], node["model"])
        g.connect(scene["camera"], node["camera"])
    g.connect(frames["fitted"], infill["fitted"])
    g.connect(frames["failed"], infill["failed"])
    g.connect(infill["infilled"], hybrid["fitted"])
    g.connect(infill["still_failed"], hybrid["failed"])
    return g


def test_windowed_temporal_nodes_do_not_depend_on_the_chunk_size(shot):
    whole = run(_graph(), chunk=FRAMES, scheduler="threads", cache=False,
                outputs=["average", "infill", "hybrid"])
    assert whole.exit_code == 0, whole.summary()
    assert whole.outputs["infill"]["still_failed"].values.sum() == 0
    moved = np.abs(whole.outputs["hybrid"]["smoothed"].values - shot.fitted).max()
    assert moved > 1e-3  # the smoothing did something
    for chunk in (2, 3):
        split = run(_graph(), chunk=chunk, scheduler="threads", cache=False,
                    outputs=["average", "infill", "hybrid"])
        assert split.exit_code == 0, split.summary()
        assert len(split.plan.by_node["hybrid"]) > 1
        for node, port in (("average", "averaged"), ("infill", "infilled"), ("hybrid", "smoothed")):
            np.testing.assert_allclose(split.outputs[node][port].values, whole.outputs[node][port].values,
                                       atol=1e-5, err_msg=f"{node} at chunk {chunk}")
