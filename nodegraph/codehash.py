"""Source hashes of a node's code: its module and every project module it imports, transitively.

A node's cache key holds the sha256 of the source of each project module its defining module
imports, directly or through other project modules, so that editing a helper
(`nodes/stabilize/penalty.py`) changes the key of every node that uses it. "Project" means
the top-level package of the node's module (its plugin package, e.g. `nodes` or
`mystudio`) and `nodegraph` itself; third-party libraries (numpy, torch, ...) are versioned
by their installers and left out.

The import graph is found statically, without importing anything: every `import` /
`from ... import` statement anywhere in a module's text counts, including those inside
functions (node modules import their heavy math lazily inside `run`). Statements are found
by a regular expression over the source lines rather than a full parse (10x faster, which
matters at every start-up); a line inside a docstring that reads like an import counts too,
which can only add files to a key, never drop one. Module files are located on disk from
the package folders. Results are computed once per process.
"""

from __future__ import annotations

import hashlib
import importlib.util
import re
import sys
from pathlib import Path

__all__ = ["module_sources", "source_digest"]

# module name -> (file path, is package); None when not found
_LOCATIONS: dict[str, tuple[Path, bool] | None] = {}
# module name -> sha256 of its source bytes
_HASHES: dict[str, str] = {}
# module name -> project modules it imports directly
_IMPORTS: dict[str, set[str]] = {}
# root module -> {relative path: sha256} of its closure
_CLOSURES: dict[str, dict[str, str]] = {}

_CORE = "nodegraph"


def _top_locations(top: str) -> tuple[Path, bool] | None:
    module = sys.modules.get(top)
    if module is not None and getattr(module, "__file__", None):
        path = Path(module.__file__)
        return path, path.name == "__init__.py"
    try:
        spec = importlib.util.find_spec(top)  # a top-level spec is found without importing
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return None
    return Path(spec.origin), spec.submodule_search_locations is not None


def locate(name: str) -> tuple[Path, bool] | None:
    """File of module `name` and whether it is a package, found on disk (nothing imported)."""
    if name in _LOCATIONS:
        return _LOCATIONS[name]
    parts = name.split(".")
    found = _top_locations(parts[0])
    for part in parts[1:]:
        if found is None or not found[1]:
            found = None
            break
        folder = found[0].parent
        if (folder / part / "__init__.py").is_file():
            found = (folder / part / "__init__.py", True)
        elif (folder / f"{part}.py").is_file():
            found = (folder / f"{part}.py", False)
        else:
            found = None
    _LOCATIONS[name] = found
    return found


_IMPORT = re.compile(r"^[ \t]*import[ \t]+([^\n#;]+)", re.M)
_FROM = re.compile(r"^[ \t]*from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]+)", re.M)


def _imported_names(text: str, name: str, is_package: bool) -> set[str]:
    """Every module name an import statement in `text` may load (parents included)."""
    package = name if is_package else name.rpartition(".")[0]
    out: set[str] = set()
    for match in _IMPORT.finditer(text):
        for item in match.group(1).split(","):
            module = item.split(" as ")[0].strip().rstrip("\\").strip()
            if module:
                out.add(module)
    for match in _FROM.finditer(text):
        dots, module, names = match.group(1), match.group(2), match.group(3)
        if dots:
            base = package.split(".") if package else []
            if len(dots) - 1 > len(base):
                continue
            base = base[: len(base) - (len(dots) - 1)]
            stem = ".".join(base + ([module] if module else []))
        else:
            stem = module
        if not stem:
            continue
        out.add(stem)
        for item in names.strip("()").replace("\\", " ").split(","):
            alias = item.split(" as ")[0].strip()
            if alias and alias != "*" and alias.isidentifier():
                out.add(f"{stem}.{alias}")  # kept only when it is a module file
    parents = set()
    for item in out:
        bits = item.split(".")
        parents.update(".".join(bits[:i]) for i in range(1, len(bits)))
    return {item for item in out | parents if all(part.isidentifier() for part in item.split("."))}


def _scan(name: str, roots: frozenset[str]) -> set[str]:
    if name not in _IMPORTS:
        where = locate(name)
        if where is None:
            _IMPORTS[name] = set()
            return set()
        data = where[0].read_bytes()
        _HASHES[name] = hashlib.sha256(data).hexdigest()
        _IMPORTS[name] = _imported_names(data.decode("utf-8", "replace"), name, where[1])
    return {n for n in _IMPORTS[name] if n.split(".")[0] in roots and locate(n) is not None}


def _relative(name: str) -> str:
    path, is_package = locate(name)  # type: ignore[misc]
    stem = name.replace(".", "/")
    return f"{stem}/__init__.py" if is_package else f"{stem}.py"


def module_sources(module: str) -> dict[str, str]:
    """{relative path: sha256 of the source} of `module` and the project modules it imports.

    Args:
        module: dotted module name (e.g. "nodes.stabilize.node"); it need not be imported.
    Returns:
        sorted mapping like {"nodes/stabilize/penalty.py": "ab12..."}; empty when the module's
        file cannot be found (e.g. a class defined in an interactive session).
    """
    if module in _CLOSURES:
        return _CLOSURES[module]
    roots = frozenset({module.split(".")[0], _CORE})
    seen: set[str] = set()
    stack = [module]
    while stack:
        name = stack.pop()
        if name in seen or locate(name) is None:
            continue
        seen.add(name)
        stack.extend(_scan(name, roots) - seen)
    closure = dict(sorted((_relative(n), _HASHES[n]) for n in seen if n in _HASHES))
    _CLOSURES[module] = closure
    return closure


def source_digest(sources: dict[str, str]) -> str:
    """One sha256 over a `module_sources` mapping."""
    digest = hashlib.sha256()
    for path, sha in sorted(sources.items()):
        digest.update(f"{path}={sha};".encode())
    return digest.hexdigest()


def clear() -> None:
    """Forget everything computed (for tests that edit source files)."""
    for memo in (_LOCATIONS, _HASHES, _IMPORTS, _CLOSURES):
        memo.clear()
