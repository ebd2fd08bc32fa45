"""Import the modules of an area, skipping only the ones not present in this installation."""

from importlib import import_module


def import_modules(package: str, names: list[str]) -> None:
    """Import `package.name` for each name; a module that does not exist is skipped.

    An error raised inside an existing module (including a missing dependency) propagates.
    """
    for name in names:
        full = f"{package}.{name}"
        try:
            import_module(full)
        except ModuleNotFoundError as err:
            if err.name != full:
                raise
