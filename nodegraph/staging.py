"""All-or-nothing outputs: the files writer nodes write in a run are held back until it succeeds.

While a writer's task runs, `nodegraph.files` (`atomic_path`, `write_text_atomic`,
`write_npz_atomic`, `write_bytes_atomic`, and so `nodegraph.models.save_model`) write each file
into a staging folder next to its destination instead of onto it: for a destination `D`, the
nearest existing folder `A` above it gets a hidden `A/.nodegraph-staging.<run>/files/<D
relative to A>`, so that nothing is created outside `A` and moving the file onto `D` later is a
rename on the same file system. The writer's `Files` value names the destinations, as before;
`location(path)` (and `file_sha256`, `files_value`) find the staged bytes meanwhile.

When the whole run has succeeded the runner moves every staged file onto its destination
(`commit`); when any task failed or was skipped it deletes them (`discard`), so a failed run
leaves the previous outputs untouched and writes no partial ones. A node that reads files an
upstream writer wrote in the same run (e.g. `report.Html` embedding report PNGs) needs them at
their destinations: the runner `publish`es them first, keeping a backup of any file they
replace, and `discard` puts the backups back (and removes the published files that replaced
nothing). A run killed outright (`kill -9`) leaves only the hidden staging folders behind; the
next run on the same host that stages next to them removes those whose process is gone.

No module-level state: the staging of the task being run is a context variable, set by the
runner around a writer's task (`staging`).
"""

from __future__ import annotations

import os
import shutil
import uuid
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

from .writer_tag import WriterTag

__all__ = ["STAGE_PREFIX", "StagedFile", "Staging", "new_token", "staging", "unstaged", "current", "location",
           "publish", "commit", "discard", "nearest_existing"]

STAGE_PREFIX = ".nodegraph-staging."
_CURRENT: ContextVar["Staging | None"] = ContextVar("nodegraph_staging", default=None)


def new_token() -> str:
    """A name part unique to one run: host, process id and a random suffix."""
    return str(WriterTag.new(12))


def nearest_existing(path: str | os.PathLike) -> Path:
    """The nearest existing ancestor of `path` (or `path` itself when it exists)."""
    here = Path(os.path.abspath(path))
    while not os.path.lexists(here) and here.parent != here:
        here = here.parent
    return here


@dataclass(frozen=True)
class StagedFile:
    """One held-back file: its destination, where it is staged, and the staging folder.

    Plain strings (absolute paths), so that it travels in task results between processes.
    """

    final: str
    staged: str
    root: str

    @property
    def relative(self) -> str:
        return os.path.relpath(self.staged, os.path.join(self.root, "files"))

    @property
    def backup(self) -> str:
        """Where `publish` keeps the file the destination held before (if any)."""
        return os.path.join(self.root, "backup", self.relative)

    @property
    def marker(self) -> str:
        """Present once the file was published (so `discard` knows to undo it)."""
        return os.path.join(self.root, "published", self.relative)


class Staging:
    """The files one task has written so far, by absolute destination."""

    def __init__(self, token: str):
        self.token = token
        self.files: dict[str, StagedFile] = {}

    def stage(self, path: str | os.PathLike) -> Path:
        """The staged path to write instead of `path` (its parent folders created).

        Raises:
            NotADirectoryError: the nearest existing path above `path` is a file.
        """
        final = os.path.abspath(path)
        entry = self.files.get(final)
        if entry is None:
            ancestor = nearest_existing(os.path.dirname(final))
            if not ancestor.is_dir():
                raise NotADirectoryError(f"cannot write '{final}': '{ancestor}' is a file, not a folder")
            root = ancestor / f"{STAGE_PREFIX}{self.token}"
            entry = StagedFile(final, str(root / "files" / os.path.relpath(final, ancestor)), str(root))
            self.files[final] = entry
        Path(entry.staged).parent.mkdir(parents=True, exist_ok=True)
        return Path(entry.staged)

    def location(self, path: str | os.PathLike) -> Path | None:
        entry = self.files.get(os.path.abspath(path))
        return Path(entry.staged) if entry is not None else None

    def entries(self) -> list[StagedFile]:
        return list(self.files.values())


@contextmanager
def staging(token: str | None) -> Iterator[Staging | None]:
    """Hold back the files written inside the block (nothing happens when `token` is empty)."""
    if not token:
        yield None
        return
    stage = Staging(token)
    reset = _CURRENT.set(stage)
    try:
        yield stage
    finally:
        _CURRENT.reset(reset)


@contextmanager
def unstaged() -> Iterator[None]:
    """Write straight to the paths inside the block (the framework's own files: cache records)."""
    reset = _CURRENT.set(None)
    try:
        yield
    finally:
        _CURRENT.reset(reset)


def current() -> Staging | None:
    """The staging of the task running in this context, or None (files go straight to their paths)."""
    return _CURRENT.get()


def location(path: str | os.PathLike) -> Path:
    """Where the bytes of `path` are now: its staged copy when the running task wrote it, else `path`."""
    stage = _CURRENT.get()
    staged = stage.location(path) if stage is not None else None
    return staged if staged is not None else Path(path)


def _put(source: str, final: str, *, link: bool) -> None:
    """Place `source` at `final` (a rename, or a hard link / copy when `link`), atomically."""
    os.makedirs(os.path.dirname(final), exist_ok=True)
    if not link:
        os.replace(source, final)
        return
    tmp = os.path.join(os.path.dirname(final), f".{os.path.basename(final)}.{uuid.uuid4().hex}.tmp")
    try:
        try:
            os.link(source, tmp)
        except OSError:
            shutil.copy2(source, tmp)
        os.replace(tmp, final)
    finally:
        if os.path.lexists(tmp):
            os.unlink(tmp)


def publish(entries: Iterable[StagedFile]) -> None:
    """Put staged files at their destinations now (for a reader in the same run), keeping
    the staged copy and a backup of what each destination held, so that `discard` can undo it.
    Idempotent: publishing the same file twice (two readers) leaves the same state."""
    for entry in entries:
        if not os.path.exists(entry.staged):
            continue
        try:
            if os.path.samefile(entry.staged, entry.final):
                continue
        except OSError:
            pass
        os.makedirs(os.path.dirname(entry.marker), exist_ok=True)
        Path(entry.marker).touch()
        if os.path.lexists(entry.final) and not os.path.lexists(entry.backup):
            os.makedirs(os.path.dirname(entry.backup), exist_ok=True)
            try:
                os.link(entry.final, entry.backup)
            except OSError:
                shutil.copy2(entry.final, entry.backup)
        _put(entry.staged, entry.final, link=True)


def commit(entries: Iterable[StagedFile]) -> list[str]:
    """Move every staged file onto its destination, then remove the staging folders.

    Returns:
        the destinations written.
    Raises:
        OSError: a file could not be moved (the others are still moved; the first error is raised).
    """
    entries = list(entries)
    written, first_error = [], None
    for entry in entries:
        try:
            if os.path.exists(entry.staged):
                _put(entry.staged, entry.final, link=False)
            written.append(entry.final)
        except OSError as err:
            first_error = first_error or err
    _remove_roots(entries)
    if first_error is not None:
        raise first_error
    return written


def discard(entries: Iterable[StagedFile], token: str = "", candidates: Iterable[str] = ()) -> None:
    """Drop staged files; undo published ones (backups back, new files removed, with the
    folders publishing created when they are empty); remove the staging folders. With
    `token`, also the staging folders of that run next to `candidates` (destinations whose
    tasks never reported back)."""
    entries = list(entries)
    for entry in entries:
        if not os.path.lexists(entry.marker):
            continue
        if os.path.lexists(entry.backup):
            os.replace(entry.backup, entry.final)
        elif os.path.lexists(entry.final):
            os.unlink(entry.final)
            stop = os.path.dirname(entry.root)
            folder = os.path.dirname(entry.final)
            while folder.startswith(stop + os.sep) and folder != stop:
                try:
                    os.rmdir(folder)
                except OSError:
                    break
                folder = os.path.dirname(folder)
    _remove_roots(entries)
    if token:
        for path in candidates:
            root = nearest_existing(path)
            for folder in (root, root.parent):
                shutil.rmtree(folder / f"{STAGE_PREFIX}{token}", ignore_errors=True)


def _remove_roots(entries: Iterable[StagedFile]) -> None:
    """Remove the staging folders of `entries`, and next to them those of runs on this host
    whose process is gone (killed outright)."""
    roots = list(dict.fromkeys(entry.root for entry in entries))
    for root in roots:
        shutil.rmtree(root, ignore_errors=True)
    for folder in dict.fromkeys(os.path.dirname(root) for root in roots):
        try:
            names = [n for n in os.listdir(folder) if n.startswith(STAGE_PREFIX)]
        except OSError:
            continue
        for name in names:
            tag = WriterTag.of_name(name[len(STAGE_PREFIX):])
            if tag is not None and tag.writer_gone():
                shutil.rmtree(os.path.join(folder, name), ignore_errors=True)
