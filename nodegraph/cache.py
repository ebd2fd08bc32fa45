"""Content-addressed, persistent cache of node outputs, one entry per (node, chunk).

Key: sha256 of the canonical JSON of (node type, node version, hash of the node's source,
the parameters that affect output, content hashes of the files it reads, the keys of the
upstream values it consumes with their frame slices, its frame range). Nothing in a key
depends on the machine, the process or absolute paths, so keys agree across machines.

Layout under the cache folder (default `.nodegraph/cache`, or `NODEGRAPH_CACHE`)::

    objects/ab/<key>/manifest.json   # written last: its presence marks a complete entry
    objects/ab/<key>/<port>.npz      # one file per output port (no pickles)
    errors/<node>/<start>-<stop>.json
    last/<node>.json                 # key descriptions of the last run, for --explain

An entry is written into a temporary folder and renamed into place, so a crash leaves no
partial entry and concurrent workers never see one; when two write the same key, the
second rename loses and its copy is discarded. Reads check every file's size and sha256
against the manifest: a truncated or corrupted entry is removed and reported as a miss.
(That check is also why entries are not fsynced: after a power loss a damaged entry is
detected and recomputed, never returned.)
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

from .files import write_text_atomic
from .types import PortType, port_type_by_name

__all__ = ["DEFAULT_CACHE", "cache_dir_from_env", "canonical_json", "make_key", "Cache",
           "CorruptEntry"]

DEFAULT_CACHE = ".nodegraph/cache"


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


class Cache:
    """A cache folder (see the module docstring)."""

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else cache_dir_from_env()

    def __repr__(self) -> str:
        return f"Cache({str(self.root)!r})"

    def entry_dir(self, key: str) -> Path:
        return self.root / "objects" / key[:2] / key

    # -- queries -------------------------------------------------------------------------
    def contains(self, key: str) -> bool:
        """True when a complete entry exists whose files have the sizes its manifest lists.

        (Sizes are checked here, cheaply; contents are checked on `load`.)
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
        return True

    def _manifest(self, key: str) -> dict[str, Any] | None:
        try:
            return json.loads((self.entry_dir(key) / "manifest.json").read_text())
        except FileNotFoundError:
            return None
        except (json.JSONDecodeError, UnicodeDecodeError):
            self._remove(key)
            return None

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

    # -- writing -------------------------------------------------------------------------
    def store(self, key: str, values: Mapping[str, PortType], description: Mapping[str, Any]) -> None:
        """Write an entry atomically (temp folder + rename); a concurrent twin is kept."""
        final = self.entry_dir(key)
        if (final / "manifest.json").exists():
            return
        tmp_root = self.root / "tmp"
        tmp_root.mkdir(parents=True, exist_ok=True)
        tmp = tmp_root / f"{key}.{uuid.uuid4().hex}"
        tmp.mkdir()
        try:
            files, ports = {}, {}
            for port, value in values.items():
                name = f"{port}.npz"
                with open(tmp / name, "wb") as fh:
                    np.savez(fh, **value.to_arrays())
                data = (tmp / name).read_bytes()
                files[name] = {"size": len(data), "sha256": hashlib.sha256(data).hexdigest()}
                ports[port] = {"file": name, "type": value.type_name}
            manifest = {"key": key, "created": time.time(), "files": files, "ports": ports,
                        "description": dict(description)}
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
        trash = self.root / "tmp" / f"trash.{key}.{uuid.uuid4().hex}"
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
            size = sum(p.stat().st_size for p in folder.iterdir() if p.is_file())
            out.append((folder, size, manifest.stat().st_mtime))
        return out

    def info(self) -> dict[str, Any]:
        entries = self.entries()
        errors = list((self.root / "errors").glob("*/*.json"))
        return {"path": str(self.root), "entries": len(entries),
                "bytes": int(sum(size for _, size, _ in entries)), "error_records": len(errors)}

    def clear(self) -> None:
        if self.root.exists():
            shutil.rmtree(self.root)

    def gc(self, max_bytes: int) -> tuple[int, int]:
        """Delete least recently used entries until the total is <= max_bytes.

        Returns:
            (entries removed, bytes freed).
        """
        entries = sorted(self.entries(), key=lambda e: e[2])
        total = sum(size for _, size, _ in entries)
        removed = freed = 0
        for folder, size, _ in entries:
            if total <= max_bytes:
                break
            self._remove(folder.name)
            total -= size
            removed += 1
            freed += size
        tmp = self.root / "tmp"
        if tmp.exists():
            for stale in tmp.iterdir():
                if time.time() - stale.stat().st_mtime > 3600:
                    shutil.rmtree(stale, ignore_errors=True)
        return removed, freed


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name)


def _write_json_atomic(path: Path, value: Any) -> None:
    write_text_atomic(path, json.dumps(value, indent=1, sort_keys=True, default=str))
