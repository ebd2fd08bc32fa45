"""The areas of nodes/ import one another only along the layers the README's design notes list:
the shared areas (geometry, io, mesh) from anywhere, an area from those it builds on in the
pipeline, never the synthetic generator (synth) outside itself, and never a private name of
another area. Checked on the import statements themselves (ast), functions' bodies included."""

from __future__ import annotations

import ast
from pathlib import Path

NODES = Path(__file__).resolve().parents[1] / "nodes"

SHARED = {"geometry", "io", "mesh"}
BUILDS_ON = {
    "geometry": set(),
    "io": {"geometry", "mesh"},
    "mesh": {"geometry"},
    "synth": set(),
    "rigid": set(),
    "stabilize": set(),
    "render": set(),
    "landmarks": set(),
    "flow": {"render"},
    "fit": {"render", "landmarks", "flow"},
    "temporal": {"fit", "flow", "render", "report"},
    "dynamics": {"stabilize"},
    "report": {"render"},
    "export": set(),
}
"""Area -> the non-shared areas it may import. temporal -> report: temporal.MotionReport draws with
the report area's plotting helpers. dynamics -> stabilize: dynamics.StabilizeTakes stabilizes the
training takes that carry no tracked skull by mode pursuit."""


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """(imported area, imported names) of every relative import from another area in a module."""
    area = path.relative_to(NODES).parts[0]
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level >= 2 and node.module:
            target = node.module.split(".")[0]
            if target != area and not target.startswith("_"):
                out.append((target, [a.name for a in node.names]))
    return out


def test_areas_import_only_along_the_layers():
    problems = []
    for path in sorted(NODES.glob("*/*.py")):
        area = path.relative_to(NODES).parts[0]
        if area not in BUILDS_ON:
            problems.append(f"{path.relative_to(NODES)}: area '{area}' missing from the layer table")
            continue
        for target, names in _imports(path):
            if target not in SHARED | BUILDS_ON[area]:
                problems.append(f"{path.relative_to(NODES)} imports {target} ({', '.join(names)})")
            private = [n for n in names if n.startswith("_")]
            if private:
                problems.append(f"{path.relative_to(NODES)} imports private {target}.{', '.join(private)}")
    assert problems == []


def test_the_layer_test_sees_imports():
    found = {t for p in NODES.glob("fit/*.py") for t, _ in _imports(p)}
    assert {"render", "landmarks", "geometry"} <= found


def test_the_library_does_not_import_the_test_support():
    """Helpers that only tests and benches use live in tests/support (`tests.support.synthetic`);
    nodes/ and nodegraph/ never import the tests package."""
    problems = []
    for root in (NODES, NODES.parent / "nodegraph"):
        for path in sorted(root.rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.Import):
                    modules = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    modules = [node.module]
                else:
                    continue
                problems += [f"{path.relative_to(NODES.parent)} imports {m}" for m in modules
                             if m.split(".")[0] == "tests"]
    assert problems == []
