"""Docs that are generated: the node catalogue in docs/nodes.md matches the registry."""

from __future__ import annotations

from pathlib import Path

from nodegraph.cli import nodes_markdown

ROOT = Path(__file__).resolve().parents[1]


def test_node_catalogue_is_up_to_date():
    expected = nodes_markdown()
    found = (ROOT / "docs" / "nodes.md").read_text()
    assert found == expected, "docs/nodes.md is outdated: run `nodegraph nodes --markdown > docs/nodes.md`"
    assert "`stabilize.ModePursuit`" in found and "`test." not in found
