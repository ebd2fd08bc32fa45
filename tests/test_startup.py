"""Start-up: `import nodes` registers every node type without importing the heavy libraries.

Node modules declare ports and params at module level and import torch, scipy, matplotlib,
trimesh, pxr (usd-core), OpenImageIO and av inside `run()` or helper functions, so that the
CLI, graph validation and dask workers that only plan do not pay seconds of imports.
"""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

import nodes
from nodes._areas import import_modules

HEAVY = ("torch", "scipy", "matplotlib", "trimesh", "pxr", "OpenImageIO", "av")
NODES_DIR = Path(nodes.__file__).parent


def _run_python(code: str) -> dict:
    """Run `code` in a fresh interpreter (no plugins from the environment); return its JSON."""
    env = {k: v for k, v in os.environ.items() if k != "NODEGRAPH_PLUGINS"}
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                          timeout=300)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def _declared_type_names() -> set[str]:
    """Every `type_name = "..."` assigned in a class body under nodes/ (an AST scan)."""
    names = set()
    for path in NODES_DIR.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.ClassDef):
                for stmt in node.body:
                    if (isinstance(stmt, ast.Assign) and isinstance(stmt.value, ast.Constant)
                            and any(isinstance(t, ast.Name) and t.id == "type_name" for t in stmt.targets)):
                        names.add(stmt.value.value)
    return names


def test_import_nodes_imports_no_heavy_library():
    got = _run_python(
        "import json, sys\n"
        "import nodes\n"
        "nodes.import_all()\n"
        f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))")
    assert got == [], f"`import nodes` imported {got}; import them inside run() instead"


def test_registry_lists_every_node_type_without_heavy_imports():
    got = _run_python(
        "import json, sys\n"
        "from nodegraph import registry\n"
        "names = sorted(registry.all_types())\n"
        f"print(json.dumps({{'names': names, 'heavy': sorted(m for m in {HEAVY!r} if m in sys.modules)}}))")
    declared = _declared_type_names()
    assert len(declared) >= 20
    assert declared <= set(got["names"]), f"not registered: {sorted(declared - set(got['names']))}"
    assert got["heavy"] == []


def test_registry_imports_only_the_areas_a_graph_uses():
    got = _run_python(
        "import json, sys\n"
        "from nodegraph import Graph\n"
        "Graph.load('graphs/synthetic_capture.json')\n"
        "print(json.dumps(sorted(m for m in sys.modules if m.count('.') == 1 and m.startswith('nodes.'))))")
    assert {"nodes.io", "nodes.synth", "nodes.report"} <= set(got)
    assert "nodes.stabilize" not in got and "nodes.rigid" not in got


def test_import_modules_names_a_missing_module():
    with pytest.raises(ImportError, match=r"expected a module 'nodes\.no_such_area' .*found none") as info:
        import_modules("nodes", ["no_such_area"])
    assert info.value.name == "nodes.no_such_area"


def test_import_modules_propagates_a_missing_dependency(tmp_path, monkeypatch):
    package = tmp_path / "startup_pkg"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "needs_dep.py").write_text("import startup_no_such_dependency\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.raises(ModuleNotFoundError) as info:
        import_modules("startup_pkg", ["needs_dep"])
    assert info.value.name == "startup_no_such_dependency"
