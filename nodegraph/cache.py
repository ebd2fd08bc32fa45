"""Content-addressed, persistent cache of node outputs, one entry per (node, chunk).

Key: sha256 of the canonical JSON of (node type, node version, hash of the node's source,
the parameters that affect output, content hashes of the files it reads, the keys of the
upstream values it consumes with their frame slices, its frame range). Nothing in a key
depends on the machine, the process or absolute paths, so keys agree across machines.

Layout under the cache folder (default `.nodegraph/cache`, or `NODEGRAPH_CACHE`)::

    objects/ab/<key>/manifest.json   # written last: its presence marks a complete entry
    objects/ab/<key>/<port>.npz      # one file per output port (no pickles)
    objects/ab/<key>/copy_<i>        # writers: copies of small written files (restored from here)
    written/ab/<key>.json            # writers: path, size, mtime and sha256 of each file written
    hashes/ab/<path hash>.json       # input files: sha256 remembered by (path, size, mtime)
    code/<digest>.json               # the source files behind a code hash (for --explain)
    errors/<node>/<start>-<stop>.json
    last/<node>.json                 # key descriptions of the last run, for --explain
    NODEGRAPH_CACHE                  # marker: `clear` and `gc` refuse folders without it

An entry is written into a temporary folder and renamed into place, so a crash leaves no
partial entry and concurrent workers never see one; when two write the same key, the
second rename loses and its copy is discarded. Reads check every file's size and sha256
against the manifest: a truncated or corrupted entry is removed and reported as a miss.
(That check is also why entries are not fsynced: after a power loss a damaged entry is
detected and recomputed, never returned.)

Nodes that write files (savers, reports) are cached like any other node, and their entry
counts as a hit only while every file they wrote is still on disk exactly as written: same
absolute path, and same size and mtime, or, when the mtime moved, the same sha256. A file
that is missing or differs is restored from the entry's copy when the writer's files were
small enough to keep one (`COPY_LIMIT`), else the writer runs again. Inside a run, writers'
files are staged until the run succeeds (`nodegraph.staging`): the record and the copies are
taken from the staged files, whose size and mtime the destinations keep when the run moves
them there by a rename; restored files are staged the same way.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import time
import uuid
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from .files import HashingWriter, file_sha256, staged_location, write_bytes_atomic, write_text_atomic
from .staging import unstaged
from .types import Files, PortType, port_type_by_name
from .writer_tag import HOST, WriterTag, pid_alive

__all__ = ["DEFAULT_CACHE", "MARKER", "COPY_LIMIT", "cache_dir_from_env", "canonical_json", "make_key",
           "Cache", "CorruptEntry", "NotACache", "resolve_cache"]

DEFAULT_CACHE = ".nodegraph/cache"
MARKER = "NODEGRAPH_CACHE"
COPY_LIMIT = 64 << 20  # writers whose files total at most this many bytes keep a copy in the entry
_SUBFOLDERS = ("objects", "tmp", "written", "hashes", "code", "errors", "last")


def cache_dir_from_env() -> Path:
    """`NODEGRAPH_CACHE` if set, else `.nodegraph/cache` (relative to the working folder)."""
    return Path(os.environ.get("NODEGRAPH_CACHE") or DEFAULT_CACHE)


def canonical_json(value: Any) -> str:
    """JSON with sorted keys and no whitespace: the same text for equal values anywhere."""
    return json.dumps(value, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def make_key(description: Mapping[str, Any]) -> str:
    """sha256 hex of the canonical JSON of a key description."""
    return hashlib.sha256(canonical_json(description).encode()).hexdigest()


class CorruptEntry(Exception):
    """A cache entry failed its integrity check (it has been removed)."""


class NotACache(ValueError):
    """A folder given as cache holds no nodegraph cache (no marker file): nothing was deleted."""


def _valid_manifest(manifest: Any) -> bool:
    """True when `manifest` has the shape `store` writes (anything else counts as corrupt)."""
    if not isinstance(manifest, dict):
        return False
    files, ports = manifest.get("files"), manifest.get("ports")
    if not isinstance(files, dict) or not isinstance(ports, dict):
        return False
    for info in files.values():
        if not (isinstance(info, dict) and isinstance(info.get("size"), int)
                and isinstance(info.get("sha256"), str)):
            return False
    for info in ports.values():
        if not (isinstance(info, dict) and info.get("file") in files and isinstance(info.get("type"), str)):
            return False
    copies = manifest.get("copies", [])
    return isinstance(copies, list) and all(
        isinstance(c, dict) and c.get("file") in files and isinstance(c.get("path"), str) for c in copies)


class Cache:
    """A cache folder (see the module docstring)."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else cache_dir_from_env()

    def __repr__(self) -> str:
        return f"Cache({str(self.root)!r})"

    def entry_dir(self, key: str) -> Path:
        return self.root / "objects" / key[:2] / key

    # -- queries -------------------------------------------------------------------------
    def contains(self, key: str, *, verify: bool = False) -> bool:
        """True when a complete entry exists whose files have the sizes its manifest lists.

        Sizes are checked here, cheaply; contents are checked on `load`, or here too with
        `verify=True` (then a corrupt entry is removed and reported absent).
        """
        manifest = self._manifest(key)
        if manifest is None:
            return False
        folder = self.entry_dir(key)
        for name, info in manifest["files"].items():
            try:
                if (folder / name).stat().st_size != info["size"]:
                    self._remove(key)
                    return False
            except FileNotFoundError:
                self._remove(key)
                return False
        if verify:
            for name, info in manifest["files"].items():
                try:
                    ok = file_sha256(folder / name, memo=False) == info["sha256"]
                except OSError:
                    ok = False
                if not ok:
                    self._remove(key)
                    return False
        return True

    def _manifest(self, key: str) -> dict[str, Any] | None:
        """The entry's manifest, or None when absent; a malformed one removes the entry."""
        try:
            manifest = json.loads((self.entry_dir(key) / "manifest.json").read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError, RecursionError):
            self._remove(key)
            return None
        if not _valid_manifest(manifest):
            self._remove(key)
            return None
        return manifest

    def load(self, key: str) -> dict[str, PortType]:
        """Return the values stored under `key` (read-only arrays).

        Raises:
            KeyError: no entry.
            CorruptEntry: the entry failed its integrity check; it was removed.
        """
        manifest = self._manifest(key)
        if manifest is None:
            raise KeyError(key)
        folder = self.entry_dir(key)
        values: dict[str, PortType] = {}
        try:
            for port, info in manifest["ports"].items():
                path = folder / info["file"]
                data = path.read_bytes()
                expected = manifest["files"][info["file"]]
                if len(data) != expected["size"] or hashlib.sha256(data).hexdigest() != expected["sha256"]:
                    raise CorruptEntry(f"cache entry {key[:12]}: '{info['file']}' does not match its manifest")
                with np.load(io.BytesIO(data), allow_pickle=False) as npz:
                    arrays = {name: npz[name] for name in npz.files}
                values[port] = port_type_by_name(info["type"]).from_arrays(arrays).readonly()
        except (CorruptEntry, OSError, ValueError, KeyError) as err:
            self._remove(key)
            if isinstance(err, CorruptEntry):
                raise
            raise CorruptEntry(f"cache entry {key[:12]}: unreadable ({type(err).__name__}: {err})") from err
        try:
            os.utime(folder / "manifest.json")
        except OSError:
            pass
        return values

    def description(self, key: str) -> dict[str, Any] | None:
        manifest = self._manifest(key)
        return None if manifest is None else manifest.get("description")

    # -- files written by writer nodes ---------------------------------------------------
    def _written_path(self, key: str) -> Path:
        return self.root / "written" / key[:2] / f"{key}.json"

    def record_written(self, key: str, files: Files, where: Mapping[str, str] | None = None) -> None:
        """Remember each file a writer wrote under `key`: path as given, absolute path,
        size, mtime (ns) and sha256 (the one the writer computed from what it wrote).

        `where`: absolute path -> where the file is now (a run's staged copy, whose size and
        mtime its destination gets when the run commits it by a rename)."""
        where = where or {}
        items = []
        for path, sha in zip(files.paths, files.sha256):
            st = os.stat(where.get(os.path.abspath(path), path))
            items.append({"path": path, "abs": os.path.abspath(path), "size": st.st_size,
                          "mtime_ns": st.st_mtime_ns, "sha256": sha})
        self._mark()
        _write_json_atomic(self._written_path(key), items)

    def written_state(self, key: str) -> tuple[str, list[str]]:
        """Whether a writer's files are still what it wrote under `key`.

        Returns:
            (state, paths): "intact" (nothing to do), "restorable" (the listed files are missing
            or differ and the entry keeps copies of all of them) or "stale" (the writer must
            run again; paths lists what differs, or is empty when nothing was recorded).
        """
        try:
            items = json.loads(self._written_path(key).read_text())
            if not isinstance(items, list):
                raise ValueError("not a list")
        except (OSError, ValueError):
            return "stale", []
        changed, touched = [], False
        for item in items:
            try:
                path = item["path"]
                if os.path.abspath(path) != item["abs"]:
                    return "stale", [path]  # the same relative path now points elsewhere
                st = os.stat(path)
                if st.st_size != item["size"]:
                    changed.append(path)
                elif st.st_mtime_ns != item["mtime_ns"]:
                    if file_sha256(path, memo=False) != item["sha256"]:
                        changed.append(path)
                    else:
                        item["mtime_ns"] = st.st_mtime_ns
                        touched = True
            except FileNotFoundError:
                changed.append(item["path"])
            except (OSError, KeyError, TypeError):
                return "stale", []
        if touched:
            _write_json_atomic(self._written_path(key), items)
        if not changed:
            return "intact", []
        manifest = self._manifest(key)
        copied = {c["path"] for c in manifest.get("copies", [])} if manifest else set()
        return ("restorable" if set(changed) <= copied else "stale"), changed

    def restore_written(self, key: str) -> list[str]:
        """Rewrite the missing or changed files of a writer's entry from its copies.

        Returns:
            the paths rewritten.
        Raises:
            CorruptEntry: a copy failed its integrity check (the entry was removed).
            KeyError: no entry, or it keeps no copy of a file that differs.
        """
        state, changed = self.written_state(key)
        if state == "intact":
            return []
        manifest = self._manifest(key)
        if manifest is None or state != "restorable":
            raise KeyError(key)
        folder = self.entry_dir(key)
        copies = {c["path"]: c["file"] for c in manifest.get("copies", [])}
        items = json.loads(self._written_path(key).read_text())
        for path in changed:
            data = (folder / copies[path]).read_bytes()
            if hashlib.sha256(data).hexdigest() != manifest["files"][copies[path]]["sha256"]:
                self._remove(key)
                raise CorruptEntry(f"cache entry {key[:12]}: the copy of '{path}' does not match its manifest")
            write_bytes_atomic(path, data)  # staged inside a run (see nodegraph.staging)
            st = os.stat(staged_location(path))  # a rename keeps size and mtime
            for item in items:
                if item["path"] == path:
                    item["size"], item["mtime_ns"] = st.st_size, st.st_mtime_ns
        _write_json_atomic(self._written_path(key), items)
        return changed

    # -- input file hashes and code records ----------------------------------------------
    def file_hash(self, path: str | os.PathLike) -> str:
        """sha256 of an input file, remembered in the cache by (absolute path, size, mtime).

        A file is read (streamed) once; later runs in any process only `stat` it.
        """
        st = os.stat(path)
        absolute = os.path.abspath(path)
        memo = self.root / "hashes" / _digest(absolute)[:2] / f"{_digest(absolute)}.json"
        try:
            known = json.loads(memo.read_text())
            if (isinstance(known, dict) and known.get("path") == absolute and known.get("size") == st.st_size
                    and known.get("mtime_ns") == st.st_mtime_ns and isinstance(known.get("sha256"), str)):
                return known["sha256"]
        except (OSError, ValueError):
            pass
        sha = file_sha256(path)
        try:
            self._mark()
            _write_json_atomic(memo, {"path": absolute, "size": st.st_size, "mtime_ns": st.st_mtime_ns,
                                      "sha256": sha})
        except OSError:
            pass  # a read-only cache still works; the hash is recomputed next time
        return sha

    def record_code(self, digest: str, sources: Mapping[str, str]) -> None:
        """Remember which source files a code hash stands for (for `--explain`)."""
        path = self.root / "code" / f"{digest}.json"
        if not path.exists():
            self._mark()
            _write_json_atomic(path, dict(sources))

    def code_sources(self, digest: str) -> dict[str, str] | None:
        try:
            value = json.loads((self.root / "code" / f"{digest}.json").read_text())
        except (OSError, ValueError):
            return None
        return value if isinstance(value, dict) else None

    def _mark(self) -> None:
        marker = self.root / MARKER
        if not marker.exists():
            self.root.mkdir(parents=True, exist_ok=True)
            marker.write_text("This folder is a nodegraph cache; `nodegraph cache clear` deletes its entries.\n")

    def is_cache(self) -> bool:
        """True when the folder carries the cache marker file."""
        return (self.root / MARKER).is_file()

    # -- writing -------------------------------------------------------------------------
    def store(self, key: str, values: Mapping[str, PortType], description: Mapping[str, Any],
              copies: list[str] | None = None, where: Mapping[str, str] | None = None) -> None:
        """Write an entry atomically (temp folder + rename); a concurrent twin is kept.

        Args:
            key, values, description: the entry.
            copies: paths of files a writer wrote, copied into the entry so that they can be
                restored without running it again.
            where: absolute path -> where a copied file is now (a run's staged copy).
        """
        where = where or {}
        final = self.entry_dir(key)
        if (final / "manifest.json").exists():
            return
        self._mark()
        tmp_root = self.root / "tmp"
        tmp_root.mkdir(parents=True, exist_ok=True)
        tmp = tmp_root / f"{key}.{WriterTag.new()}"
        tmp.mkdir()
        try:
            files, ports = {}, {}
            for port, value in values.items():
                name = f"{port}.npz"
                with open(tmp / name, "wb") as fh:
                    writer = HashingWriter(fh)
                    np.savez(writer, **value.to_arrays())
                files[name] = {"size": writer.size, "sha256": writer.digest.hexdigest()}
                ports[port] = {"file": name, "type": value.type_name}
            copy_list = []
            for index, path in enumerate(copies or []):
                name = f"copy_{index}"
                shutil.copyfile(where.get(os.path.abspath(path), path), tmp / name)
                files[name] = {"size": (tmp / name).stat().st_size, "sha256": file_sha256(tmp / name, memo=False)}
                copy_list.append({"path": path, "file": name})
            manifest = {"key": key, "created": time.time(), "files": files, "ports": ports,
                        "copies": copy_list, "description": dict(description)}
            with open(tmp / "manifest.json", "w") as fh:
                json.dump(manifest, fh, sort_keys=True)
            final.parent.mkdir(parents=True, exist_ok=True)
            try:
                os.rename(tmp, final)
            except OSError:
                if not (final / "manifest.json").exists():
                    # A stale incomplete folder (should not happen): replace it.
                    self._remove(key)
                    os.rename(tmp, final)
        finally:
            if tmp.exists():
                shutil.rmtree(tmp, ignore_errors=True)

    def _remove(self, key: str) -> None:
        folder = self.entry_dir(key)
        if not folder.exists():
            return
        trash = self.root / "tmp" / f"trash-{key}.{WriterTag.new()}"
        trash.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.rename(folder, trash)
        except OSError:
            return
        shutil.rmtree(trash, ignore_errors=True)

    # -- run records ---------------------------------------------------------------------
    def write_error(self, record: Mapping[str, Any]) -> Path:
        """Store a failed chunk's error record; return its path."""
        frames = record.get("frames") or ["all", ""]
        name = f"{frames[0]}-{frames[1]}.json" if frames[1] != "" else "all.json"
        path = self.root / "errors" / _safe(record["node"]) / name
        _write_json_atomic(path, record)
        return path

    def clear_error(self, node: str, frames: tuple[int, int] | None) -> None:
        name = f"{frames[0]}-{frames[1]}.json" if frames else "all.json"
        path = self.root / "errors" / _safe(node) / name
        if path.exists():
            path.unlink(missing_ok=True)

    def write_last(self, node: str, descriptions: Mapping[str, Any]) -> None:
        """Remember the key descriptions of `node`'s chunks in the last run (for --explain)."""
        _write_json_atomic(self.root / "last" / f"{_safe(node)}.json", descriptions)

    def read_last(self, node: str) -> dict[str, Any]:
        try:
            return json.loads((self.root / "last" / f"{_safe(node)}.json").read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    # -- maintenance ---------------------------------------------------------------------
    def entries(self) -> list[tuple[Path, int, float]]:
        """(folder, bytes, last use time) of every complete entry."""
        out = []
        for manifest in (self.root / "objects").glob("*/*/manifest.json"):
            folder = manifest.parent
            try:
                size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
                out.append((folder, size, manifest.stat().st_mtime))
            except FileNotFoundError:
                continue  # removed meanwhile by another process
        return out

    def temp_folders(self) -> list[tuple[Path, int]]:
        """(folder, bytes) of every temporary folder: entries being written, or left by a
        writer that died (e.g. `kill -9`)."""
        out = []
        for folder in (self.root / "tmp").glob("*"):
            try:
                size = sum(p.stat().st_size for p in folder.rglob("*") if p.is_file()) if folder.is_dir() \
                    else folder.stat().st_size
            except FileNotFoundError:
                continue
            out.append((folder, size))
        return out

    def info(self) -> dict[str, Any]:
        entries = self.entries()
        temps = self.temp_folders()
        errors = list((self.root / "errors").glob("*/*.json"))
        return {"path": str(self.root), "entries": len(entries),
                "bytes": int(sum(size for _, size, _ in entries) + sum(size for _, size in temps)),
                "temp_folders": len(temps), "temp_bytes": int(sum(size for _, size in temps)),
                "error_records": len(errors)}

    def _check_is_cache(self, action: str) -> bool:
        """False when there is nothing (no folder); NotACache when the folder is not a cache."""
        if not self.root.exists():
            return False
        if not self.is_cache():
            raise NotACache(f"cache {action}: '{self.root}' is not a nodegraph cache folder (no {MARKER} "
                            "marker file); nothing was deleted")
        return True

    def clear(self) -> None:
        """Delete every entry and record (only the cache's own subfolders; the marker stays).

        Raises:
            NotACache: the folder exists but carries no marker file.
        """
        if not self._check_is_cache("clear"):
            return
        for name in _SUBFOLDERS:
            folder = self.root / name
            if folder.is_dir():
                trash = self.root / f".trash.{name}.{uuid.uuid4().hex}"
                os.rename(folder, trash)
                shutil.rmtree(trash, ignore_errors=True)

    def gc(self, max_bytes: int) -> tuple[int, int]:
        """Delete least recently used entries until the total is <= max_bytes, and the
        temporary folders of writers that are gone (dead process on this host, or older than
        an hour).

        Returns:
            (entries removed, bytes freed).
        Raises:
            NotACache: the folder exists but carries no marker file.
        """
        if not self._check_is_cache("gc"):
            return 0, 0
        removed = freed = 0
        for folder, size in self.temp_folders():
            if self._writer_gone(folder):
                shutil.rmtree(folder, ignore_errors=True) if folder.is_dir() else folder.unlink(missing_ok=True)
                freed += size
        entries = sorted(self.entries(), key=lambda e: e[2])
        total = sum(size for _, size, _ in entries)
        for folder, size, _ in entries:
            if total <= max_bytes:
                break
            key = folder.name
            self._remove(key)
            self._written_path(key).unlink(missing_ok=True)
            total -= size
            removed += 1
            freed += size
        return removed, freed

    @staticmethod
    def _writer_gone(folder: Path) -> bool:
        tag = WriterTag.of_name(folder.name)
        if tag is not None and tag.host == HOST:
            return not pid_alive(tag.pid)
        try:
            return time.time() - folder.stat().st_mtime > 3600
        except FileNotFoundError:
            return False


def resolve_cache(cache: "Cache | str | os.PathLike | bool | None") -> "Cache | None":
    """The cache a run uses from its `cache` argument: None or True: `cache_dir_from_env()`;
    False: no cache (None); a folder: a Cache there; a Cache: itself."""
    if cache is False:
        return None
    if cache is None or cache is True:
        return Cache(cache_dir_from_env())
    return cache if isinstance(cache, Cache) else Cache(cache)


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _write_json_atomic(path: Path, value: Any) -> None:
    with unstaged():  # the cache's own records are never held back with a run's outputs
        write_text_atomic(path, json.dumps(value, indent=1, sort_keys=True, default=str))
