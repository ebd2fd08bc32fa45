"""Small file helpers shared by the framework: atomic text writes and content hashes."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

__all__ = ["write_text_atomic", "file_sha256"]

_FILE_HASHES: dict[tuple[str, int, int], str] = {}


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write `text` to `path` through a temp file in the same folder and a rename.

    Parent folders are created; on any error the temp file is removed and `path` is untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def file_sha256(path: str | os.PathLike, *, memo: bool = True) -> str:
    """sha256 (hex) of a file's bytes, read in 4 MB blocks (never whole into memory).

    Args:
        path: the file.
        memo: remember the result per (absolute path, size, mtime) within the process; False
            hashes what is on disk now (e.g. a file just written, whose size and mtime may
            equal those of the previous version).
    """
    st = os.stat(path)
    key = (os.path.abspath(path), st.st_size, st.st_mtime_ns)
    if memo and key in _FILE_HASHES:
        return _FILE_HASHES[key]
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 22), b""):
            digest.update(block)
    if memo:
        _FILE_HASHES[key] = digest.hexdigest()
    return digest.hexdigest()
