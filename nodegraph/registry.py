"""Node types by stable name: built-ins and third-party plugins.

Node classes with a `type_name` register themselves when their module is imported. Modules
are found through the `nodegraph.nodes` entry-point group: nodegraph's own `nodes` package
is one such plugin, declared in pyproject.toml, so the framework never imports it directly.
A third-party package adds nodes by declaring, in its own pyproject.toml::

    [project.entry-points."nodegraph.nodes"]
    mystudio = "mystudio.nodes"

Modules listed in the environment variable `NODEGRAPH_PLUGINS` (comma-separated) are
imported too: a quick way to try nodes that are not packaged yet.

A plugin package may list its areas in `NODEGRAPH_AREAS` (submodule names, each holding the
node types whose names start with "<area>."), instead of importing them all in its
`__init__`: the registry then imports an area only when one of its types is asked for (so a
graph of three areas does not pay for the import of ten), and every area for `all_types()`
or an unknown name.
"""

from __future__ import annotations

import difflib
import os
from importlib import import_module
from importlib.metadata import entry_points
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from .node import Node

__all__ = ["register", "get", "all_types", "load_plugins", "ENTRY_POINT_GROUP"]

ENTRY_POINT_GROUP = "nodegraph.nodes"

_TYPES: dict[str, type["Node"]] = {}
_PLUGINS_LOADED = False
_LAZY_AREAS: dict[str, list[str]] = {}  # area name -> plugin packages that have such a submodule
_PLUGIN_MODULES: list[str] = []  # the plugin modules load_plugins() imported


def register(cls: type["Node"]) -> type["Node"]:
    """Register a node class under `cls.type_name`; a second, different class is an error."""
    name = cls.type_name
    known = _TYPES.get(name)
    if known is not None and (known.__module__, known.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"node type '{name}' registered twice: {known.__module__}.{known.__qualname__} "
                         f"and {cls.__module__}.{cls.__qualname__}")
    _TYPES[name] = cls
    return cls


def load_plugins() -> None:
    """Import every module of the `nodegraph.nodes` entry-point group (once)."""
    global _PLUGINS_LOADED
    if _PLUGINS_LOADED:
        return
    _PLUGINS_LOADED = True
    modules = [ep.load() for ep in entry_points(group=ENTRY_POINT_GROUP)]
    for name in filter(None, (m.strip() for m in os.environ.get("NODEGRAPH_PLUGINS", "").split(","))):
        modules.append(import_module(name))
    _PLUGIN_MODULES.extend(module.__name__ for module in modules)
    for module in modules:
        for area in getattr(module, "NODEGRAPH_AREAS", None) or []:
            _LAZY_AREAS.setdefault(area, []).append(module.__name__)


def _import_areas(areas: list[str]) -> None:
    for area in areas:
        for package in _LAZY_AREAS.pop(area, []):
            try:
                import_module(f"{package}.{area}")
            except ModuleNotFoundError as err:
                if err.name != f"{package}.{area}":
                    raise
                raise ImportError(f"{package}: NODEGRAPH_AREAS lists '{area}', but there is no module "
                                  f"'{package}.{area}'", name=f"{package}.{area}") from err


def get(name: str) -> type["Node"]:
    """Return the node class registered as `name`.

    Raises:
        KeyError: naming the unknown type and the closest known names.
    """
    if name not in _TYPES:
        load_plugins()
        _import_areas([name.partition(".")[0]])
    if name not in _TYPES:
        _import_areas(list(_LAZY_AREAS))  # all of them, for the error's close matches
    try:
        return _TYPES[name]
    except KeyError:
        close = difflib.get_close_matches(name, list(_TYPES), n=3)
        hint = f"; did you mean {', '.join(repr(c) for c in close)}?" if close else ""
        if not _PLUGIN_MODULES:
            hint += (f"; no node plugins are loaded (the '{ENTRY_POINT_GROUP}' entry-point group is empty and "
                     "NODEGRAPH_PLUGINS is unset): install the package (`pip install -e .`) or run with "
                     "NODEGRAPH_PLUGINS=nodes from a source checkout")
        raise KeyError(f"unknown node type '{name}'{hint}") from None


def all_types() -> dict[str, type["Node"]]:
    """Every registered node type by name, plugins included."""
    load_plugins()
    _import_areas(list(_LAZY_AREAS))
    return dict(sorted(_TYPES.items()))
