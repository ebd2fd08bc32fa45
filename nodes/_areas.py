"""Import the modules of an area (importing a node module registers its node types)."""

from importlib import import_module


def import_modules(package: str, names: list[str]) -> None:
    """Import `package.name` for each name, in order.

    Args:
        package: the importing package, e.g. "nodes" or "nodes.io".
        names: its module (or subpackage) names, e.g. ["mesh", "image"].
    Raises:
        ImportError: naming the module when a listed module does not exist (a typo in the
            list, or a file missing from the installation): nothing is skipped silently, so a
            node type cannot vanish from the registry unnoticed. An error raised inside an
            existing module (including a missing third-party dependency) propagates as is.
    """
    for name in names:
        full = f"{package}.{name}"
        try:
            import_module(full)
        except ModuleNotFoundError as err:
            if err.name != full:
                raise
            raise ImportError(f"{package}: expected a module '{full}' (listed among the modules "
                              f"of '{package}'), found none", name=full) from err
