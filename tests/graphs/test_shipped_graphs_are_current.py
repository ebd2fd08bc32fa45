"""Every shipped graph names the installed version of each node type: an older `type_version` is
migrated on load, but a user who copies a shipped graph should start from the current form, and
`nodegraph upgrade --check` is what a CI of theirs would run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from nodegraph import registry

GRAPHS = sorted((Path(__file__).resolve().parents[2] / "graphs").glob("*.json"))


@pytest.mark.parametrize("path", GRAPHS, ids=[p.stem for p in GRAPHS])
def test_shipped_graph_uses_current_node_versions(path):
    import nodes  # noqa: F401  (registers the node types)

    stale = []
    for node_id, spec in json.loads(path.read_text())["nodes"].items():
        installed = registry.get(spec["type"]).version
        if spec.get("type_version", 1) != installed:
            stale.append(f"{node_id}: {spec['type']} type_version {spec.get('type_version', 1)}, installed {installed}")
    assert stale == []
