"""Shared fixtures: seeded generators, a scratch cache, the framework's test nodes."""

from __future__ import annotations

import os

import numpy as np
import pytest

import nodegraph.testing  # noqa: F401  (registers the test.* node types)

os.environ.setdefault("NODEGRAPH_PLUGINS", "nodegraph.testing")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(1234)


@pytest.fixture
def cache_dir(tmp_path):
    return tmp_path / "cache"


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except ImportError:
        has_cuda = False
    skip = pytest.mark.skip(reason="needs a CUDA GPU")
    for item in items:
        if "cuda" in item.keywords and not has_cuda:
            item.add_marker(skip)
