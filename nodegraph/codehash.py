"""Source hashes of a node's code: its module and every project module it imports, transitively.

A node's cache key holds the sha256 of the source of each project module its defining module
imports, directly or through other project modules, so that editing a helper
(`nodes/stabilize/penalty.py`) changes the key of every node that uses it. A package's
`__init__` that a statement only passes through (`from ..fit.energy import f` runs
`nodes/fit/__init__.py`; `from nodegraph import Node` takes a name `nodegraph/__init__.py`
re-exports from `nodegraph/node.py`) counts by its own source, and what it imports is not
followed: a temporal node's key covers the fit modules it calls, not every fit node, the
generator or the runner. A name the `__init__` does not visibly re-export follows it fully. "Project" means
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
# module name -> {project module it imports directly: "full" | "parent"}
_IMPORTS: dict[str, dict[str, str]] = {}
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


def _imported_names(text: str, name: str, is_package: bool) -> dict[str, str]:
    """Every module an import statement in `text` may load, with how far to follow it.

    Returns {module name: "full" | "parent"}. "full": the statement uses the module's own
    code (`import a.b`, `from a.b import f`, `from a import b` where `a/b.py` exists), so its
    imports are followed too. "parent": the module is a package whose `__init__` only runs on
    the way to a submodule, or whose names the statement takes from one known submodule; its own
    source counts, its other imports do not (`from nodegraph import Node` depends on
    `nodegraph/node.py`, not on every module `nodegraph/__init__.py` re-exports).
    `from a import x` of a name `a/__init__.py` does not visibly re-export follows `a` fully.
    """
    package = name if is_package else name.rpartition(".")[0]
    full: set[str] = set()
    named: dict[str, set[str]] = {}  # package -> names taken from it
    for match in _IMPORT.finditer(text):
        for item in match.group(1).split(","):
            module = item.split(" as ")[0].strip().rstrip("\\").strip()
            if module:
                full.add(module)
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
        taken = named.setdefault(stem, set())
        for item in names.strip("()").replace("\\", " ").split(","):
            alias = item.split(" as ")[0].strip()
            if alias == "*":
                full.add(stem)
            elif alias and alias.isidentifier():
                taken.add(alias)
    out: dict[str, str] = {}
    for stem, taken in named.items():
        where = locate(stem) if all(part.isidentifier() for part in stem.split(".")) else None
        if where is None or not where[1]:  # a plain module (or not ours): its code is used
            full.add(stem)
            continue
        exports = _reexports(stem)
        for alias in taken:
            if locate(f"{stem}.{alias}") is not None:
                full.add(f"{stem}.{alias}")  # a submodule
            elif alias in exports:
                full.add(exports[alias])
            else:
                full.add(stem)  # defined in the package's __init__ itself (or unknown): all of it
        out.setdefault(stem, "parent")
    for item in full:
        out[item] = "full"
    for item in list(out):
        bits = item.split(".")
        for i in range(1, len(bits)):
            out.setdefault(".".join(bits[:i]), "parent")
    return {item: how for item, how in out.items() if all(part.isidentifier() for part in item.split("."))}


# package name -> {name: submodule} its __init__ re-exports with `from .sub import name`
_REEXPORTS: dict[str, dict[str, str]] = {}
_RELATIVE_FROM = re.compile(r"^from[ \t]+\.([\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#;]+)", re.M)


def _reexports(package: str) -> dict[str, str]:
    """{name: submodule} that package `package`'s `__init__` takes, at top level, from its own
    submodules (`from .sub import name [as other]`, `from . import sub`)."""
    if package in _REEXPORTS:
        return _REEXPORTS[package]
    found: dict[str, str] = {}
    where = locate(package)
    if where is not None and where[1]:
        text = where[0].read_text("utf-8", "replace")
        for match in _RELATIVE_FROM.finditer(text):
            module, names = match.group(1), match.group(2)
            for item in names.strip("()").replace("\\", " ").split(","):
                parts = item.split(" as ")
                original, alias = parts[0].strip(), parts[-1].strip()
                if not alias.isidentifier() or not original.isidentifier():
                    continue
                target = f"{package}.{module}" if module else f"{package}.{original}"
                if locate(target) is not None:
                    found[alias] = target
    _REEXPORTS[package] = found
    return found


def _scan(name: str, roots: frozenset[str]) -> dict[str, str]:
    if name not in _IMPORTS:
        where = locate(name)
        if where is None:
            _IMPORTS[name] = {}
            return {}
        data = where[0].read_bytes()
        _HASHES[name] = hashlib.sha256(data).hexdigest()
        _IMPORTS[name] = _imported_names(data.decode("utf-8", "replace"), name, where[1])
    return {n: how for n, how in _IMPORTS[name].items() if n.split(".")[0] in roots and locate(n) is not None}


def _hash(name: str) -> None:
    if name not in _HASHES:
        where = locate(name)
        if where is not None:
            _HASHES[name] = hashlib.sha256(where[0].read_bytes()).hexdigest()


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
    seen: set[str] = set()  # modules whose imports were followed
    passed: set[str] = set()  # packages only passed through: their source, not their imports
    stack = [module]
    while stack:
        name = stack.pop()
        if name in seen or locate(name) is None:
            continue
        seen.add(name)
        for target, how in _scan(name, roots).items():
            if how == "full":
                stack.append(target)
            else:
                passed.add(target)
    for name in passed - seen:
        _hash(name)
    seen |= passed
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
    for memo in (_LOCATIONS, _HASHES, _IMPORTS, _CLOSURES, _REEXPORTS):
        memo.clear()
