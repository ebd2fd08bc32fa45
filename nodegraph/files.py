"""Small file helpers shared by the framework: atomic text writes and content hashes.

Inside a writer's task of a run, every helper here writes into the run's staging folder
instead of onto the destination, and reads (hashes) the staged bytes: see `nodegraph.staging`.
Writers that write through these helpers get all-or-nothing outputs for free.
"""

from __future__ import annotations

import hashlib
import io
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Mapping, TYPE_CHECKING, Iterator, Sequence

from . import staging as _staging

if TYPE_CHECKING:
    from .types import Files

__all__ = ["HashingWriter", "write_text_atomic", "write_npz_atomic", "write_bytes_atomic", "file_sha256", "atomic_path",
           "files_value", "check_output_suffix", "staged_location"]

_FILE_HASHES: dict[tuple[str, int, int], str] = {}


def _process_umask() -> int:
    """The process's umask, read once at import: setting it to read it, as `os.umask` must, would
    let a file another thread creates meanwhile get the temporary mask."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()


def staged_location(path: str | os.PathLike) -> Path:
    """Where the bytes of `path` are now: in a writer's task of a run, the staged copy of a
    file it wrote (see `nodegraph.staging`); else `path` itself."""
    return _staging.location(path)


def _destination(path: str | os.PathLike) -> Path:
    """The path to write for `path`: its staged location inside a writer's task, else `path`."""
    stage = _staging.current()
    return stage.stage(path) if stage is not None else Path(path)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write `text` to `path` through a temp file in the same folder and a rename.

    Parent folders are created; on any error the temp file is removed and `path` is untouched.
    Inside a writer's task of a run the file is staged (see the module docstring).
    """
    with atomic_path(path) as tmp:  # its permissions too: mkstemp's 0o600 left CSVs and reports unreadable to others
        tmp.write_text(text)


def file_sha256(path: str | os.PathLike, *, memo: bool = True) -> str:
    """sha256 (hex) of a file's bytes, read in 4 MB blocks (never whole into memory).

    Args:
        path: the file.
        memo: remember the result per (absolute path, size, mtime) within the process; False
            hashes what is on disk now (e.g. a file just written, whose size and mtime may
            equal those of the previous version).
    """
    path = staged_location(path)
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


@contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path next to `path`; on success move it onto `path` (os.replace).

    For writers that open the file themselves (binary formats, libraries that take a path).
    The temporary name keeps the extension of `path` (writers pick formats by extension) and
    lives in the same folder (so the replace is atomic). Parent folders are created. The
    file gets the usual permissions (0o666 minus the umask), not mkstemp's 0o600. On an
    exception the temporary file is removed and `path` is left untouched. Inside a writer's
    task of a run, the file lands in the run's staging folder instead (see the module docstring).

    Example:
        >>> import tempfile
        >>> target = Path(tempfile.mkdtemp()) / "out" / "a.txt"
        >>> with atomic_path(target) as tmp:
        ...     _ = tmp.write_text("hello")
        >>> target.read_text()
        'hello'
    """
    path = _destination(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=f".tmp{path.suffix}")
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    """Write `data` to `path` through a temp file and a rename (`atomic_path`)."""
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def files_value(paths: Sequence[str | os.PathLike]) -> Files:
    """Return the `Files` port value of just-written `paths` (kept as given) with their sha256.

    Hashes what is on disk now (`file_sha256(..., memo=False)`: a rewritten file may keep the
    size and mtime of its previous version).
    """
    from .types import Files

    return Files(paths=[str(p) for p in paths], sha256=[file_sha256(p, memo=False) for p in paths])


class HashingWriter:
    """A write-only stream that hashes (sha256) and counts what passes through it.

    Having no `tell`/`seek`, it makes `zipfile` (under `np.savez`) write the archive
    strictly forward (sizes in data descriptors), so the sha256 of the bytes written is the
    file's without reading the file back (a 210 MB capture: one pass instead of two).
    """

    def __init__(self, fh: Any) -> None:
        self._fh = fh
        self.digest = hashlib.sha256()
        self.size = 0

    def write(self, data: Any) -> int:
        self.digest.update(data)
        self.size += memoryview(data).nbytes
        return self._fh.write(data)

    def flush(self) -> None:
        self._fh.flush()

    def read(self, *args: Any) -> bytes:  # np.savez tells files from paths by a `read` attribute
        raise io.UnsupportedOperation("write-only stream")


def write_npz_atomic(path: str | os.PathLike, arrays: Mapping[str, Any]) -> str:
    """Write `arrays` as an uncompressed .npz through a temp file and a rename (`atomic_path`).

    Returns:
        The sha256 (hex) of the file written, hashed while writing (`HashingWriter`).
    Raises:
        ValueError: `path` does not end in .npz (the message names the path).
    """
    import numpy as np

    if Path(path).suffix.lower() != ".npz":
        raise ValueError(f"expected a file name ending in .npz, found '{os.fspath(path)}'")
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        writer = HashingWriter(fh)
        np.savez(writer, **arrays)
    return writer.digest.hexdigest()


def check_output_suffix(path: str, suffixes: Sequence[str], *, allow_empty: bool = False) -> str:
    """Return `path` when it ends in one of `suffixes` (case-insensitive), else raise ValueError.

    For the `field_validator` of an output path parameter, so a wrong extension is refused when
    the graph is validated, before anything runs. `allow_empty`: '' (write nothing) is accepted.
    """
    if allow_empty and path == "":
        return path
    if Path(path).suffix.lower() not in {s.lower() for s in suffixes}:
        want = " or ".join(suffixes) + (" (or '' to skip)" if allow_empty else "")
        raise ValueError(f"expected a file name ending in {want}, found '{path}'")
    return path
