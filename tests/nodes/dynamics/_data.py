"""Small synthetic captures with secondary dynamics and networks trained on them, built once per
test session (a subsampled face region: 400 points)."""

from __future__ import annotations

from functools import lru_cache

from nodegraph import run_node
from nodes.dynamics.removal import TrainRemoval
from nodes.dynamics.synthesis import TrainSynthesis
from nodes.io.face_model import load_face_model
from nodes.synth.dynamics import DynamicCapture, simulate_dynamics

TRAIN_MOTIONS = ["walk", "run", "oscillate@6", "oscillate@8", "oscillate@11"]
"""Training programs; 9 Hz is held out."""


@lru_cache(maxsize=None)
def face_model(max_vertices: int = 400):
    return load_face_model(region="face", max_vertices=max_vertices)


@lru_cache(maxsize=None)
def training_capture() -> DynamicCapture:
    return simulate_dynamics(face_model(), motions=TRAIN_MOTIONS,
                             expressions=["neutral", "smile", "jaw_open"], segment_frames=120,
                             fps=120.0, seed=1)


@lru_cache(maxsize=None)
def synthesis_capture() -> DynamicCapture:
    return simulate_dynamics(face_model(), motions=["walk", "run", "jump", "oscillate@6",
                                                    "oscillate@8", "oscillate@11"],
                             expressions=["neutral", "smile", "jaw_open", "speech"],
                             segment_frames=120, fps=120.0, seed=1)


@lru_cache(maxsize=None)
def removal_model():
    data = training_capture()
    return run_node(TrainRemoval, {"num_samples": 100, "epochs": 8, "max_rows": 40000,
                                   "batch_size": 2000},
                    frames=range(data.capture.num_frames), captures=[data.capture],
                    skulls=[data.skull], quasistatic=[data.quasistatic], segments=[data.segments])


@lru_cache(maxsize=None)
def synthesis_model():
    data = synthesis_capture()
    return run_node(TrainSynthesis, {"num_samples": 100, "epochs": 12},
                    frames=range(data.capture.num_frames), captures=[data.capture],
                    quasistatic=[data.quasistatic], skulls=[data.skull], neutral=[data.neutral],
                    segments=[data.segments])
