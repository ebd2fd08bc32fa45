"""File helpers of the io nodes: frame patterns, extension formats, NPZ row reads.

Atomic writes and the `Files` value of written paths are in `nodegraph.files` (`atomic_path`,
`files_value`), shared with the other areas.

Frame patterns name one file per frame with a single frame token:

- printf style `face.%04d.obj` (`%d` for no padding),
- hash style `face.####.obj` (padding = number of `#`),
- format style `face.{frame:04d}.obj` (or `{frame}`).

A loader maps run frame `f` (0-based) to file number `first_frame + f`.
"""

from __future__ import annotations

import os
import re
import struct
import zipfile
from pathlib import Path
from typing import Mapping, NamedTuple

import numpy as np

from nodegraph import InputError
from nodegraph.files import atomic_path, files_value  # noqa: F401  (still imported from here by image.py, camera.py)

__all__ = [
    "FrameToken", "frame_token", "is_frame_pattern", "expand_frame_pattern", "find_frame_numbers",
    "pattern_files", "frame_where", "check_frame_range", "check_no_missing_files", "format_of",
    "npz_keys", "npz_shape", "read_npz_rows", "read_npz_array",
]

_TOKEN = re.compile(r"%(0?)(\d*)d|(#+)|\{frame(?::0?(\d+)d)?\}")


class FrameToken(NamedTuple):
    """The frame token of a pattern.

    Attributes:
        head: text before the token.
        tail: text after the token.
        width: zero-padding width (0 = no padding).
    """

    head: str
    tail: str
    width: int


def frame_token(pattern: str) -> FrameToken | None:
    """Find the frame token of `pattern`; None when it has none.

    Args:
        pattern: a path such as `shot/face.%04d.obj`, `face.####.ply`, `img.{frame:04d}.exr`.
    Returns:
        FrameToken, or None for a plain path.
    Raises:
        InputError: (a ValueError, naming param "path") when there is more than one token.

    Example:
        >>> frame_token("a/face.####.obj")
        FrameToken(head='a/face.', tail='.obj', width=4)
    """
    matches = list(_TOKEN.finditer(pattern))
    if not matches:
        return None
    if len(matches) > 1:
        raise InputError("path", f"'{pattern}': expected one frame token (%04d, #### or "
                                 f"{{frame:04d}}), found {len(matches)}")
    match = matches[0]
    if match.group(3):
        width = len(match.group(3))
    elif match.group(0).startswith("%"):
        width = int(match.group(2)) if match.group(2) else 0
    else:
        width = int(match.group(4)) if match.group(4) else 0
    return FrameToken(pattern[:match.start()], pattern[match.end():], width)


def is_frame_pattern(path: str) -> bool:
    """Return True when `path` holds a frame token (see `frame_token`)."""
    return frame_token(path) is not None


def expand_frame_pattern(pattern: str, number: int) -> str:
    """Return the path of file `number` of `pattern`.

    Example:
        >>> expand_frame_pattern("face.%04d.obj", 12)
        'face.0012.obj'
    """
    token = frame_token(pattern)
    if token is None:
        raise ValueError(f"pattern '{pattern}': expected a frame token (%04d, #### or "
                         "{frame:04d}), found none")
    sign = "-" if number < 0 else ""
    return f"{token.head}{sign}{abs(int(number)):0{token.width}d}{token.tail}"


def find_frame_numbers(pattern: str) -> list[int]:
    """Return the sorted numbers of the existing files of `pattern` (one directory listing)."""
    token = frame_token(pattern)
    if token is None:
        raise ValueError(f"pattern '{pattern}': expected a frame token, found none")
    folder, head = os.path.split(token.head)
    if os.sep in token.tail or (os.altsep and os.altsep in token.tail):
        raise ValueError(f"pattern '{pattern}': the frame token must be in the file name")
    try:
        names = os.listdir(folder or ".")
    except (FileNotFoundError, NotADirectoryError):
        return []
    regex = re.compile(re.escape(head) + r"(-?\d+)" + re.escape(token.tail) + r"\Z")
    numbers = set()
    for name in names:
        match = regex.match(name)
        if match:
            number = int(match.group(1))
            # Keep only names the pattern itself writes ("0005" for %04d, not "00005").
            if os.path.basename(expand_frame_pattern(pattern, number)) == name:
                numbers.add(number)
    return sorted(numbers)


def pattern_files(pattern: str) -> list[Path]:
    """Return the existing files of `pattern`, or `[pattern]` for an existing plain path."""
    if frame_token(pattern) is None:
        return [Path(pattern)] if Path(pattern).is_file() else []
    return [Path(expand_frame_pattern(pattern, n)) for n in find_frame_numbers(pattern)]


def frame_where(frame: int, file: str | os.PathLike) -> str:
    """Return `frame F (file 'PATH')`, how load errors name the place of a bad frame."""
    return f"frame {frame} (file '{os.fspath(file)}')"


def check_frame_range(frames: range, count: int, path: str) -> None:
    """Raise InputError (param "path") when `frames` reach outside the `count` frames of `path`."""
    if len(frames) and (frames.start < 0 or frames[-1] >= count):
        bad = frames.start if frames.start < 0 else frames[-1]
        raise InputError("path", f"frame {bad} (file '{path}'): expected a frame in 0..{count - 1}, "
                                 f"the file has {count} frame(s)")


def check_no_missing_files(pattern: str, frames: range, first: int, numbers: list[int]) -> None:
    """Raise InputError (param "path") when a run frame of `frames` has no file in `pattern`.

    Run frame f is file number `first + f`; `numbers` are the pattern's existing numbers
    (`find_frame_numbers`). Called while planning (a source's `input_files`), so a gap in a
    numbered sequence is one error before anything runs, naming every missing number of the
    pattern between `first` and its last file, not a failure in whichever chunk reaches it.
    Frames past the last file are left to the frame-count check (`--frames` past a source's end).

    Example:
        >>> check_no_missing_files("p.%04d.png", range(0, 3), 0, [0, 1, 2, 4])
        >>> check_no_missing_files("p.%04d.png", range(0, 5), 0, [0, 1, 2, 4])
        Traceback (most recent call last):
        ...
        nodegraph.errors.InputError: 'path': 'p.%04d.png': expected a file for every frame of the run, found frame 3 missing (file 'p.0003.png'); the pattern's files 0..4 lack number 3 (1 of 5)
    """
    if not numbers:
        return
    present = set(numbers)
    missing = [f for f in frames if first + f <= numbers[-1] and first + f not in present]
    if not missing:
        return
    lo, hi = min(numbers[0], first), numbers[-1]
    gaps = [n for n in range(lo, hi + 1) if n not in present]

    def listed(values: list[int]) -> str:
        shown = ", ".join(str(v) for v in values[:20])
        return shown + (f", ... ({len(values)} in all)" if len(values) > 20 else "")

    raise InputError("path", f"'{pattern}': expected a file for every frame of the run, found "
                             f"frame{'s' if len(missing) > 1 else ''} {listed(missing)} missing (file "
                             f"'{expand_frame_pattern(pattern, first + missing[0])}'"
                             f"{' and others' if len(missing) > 1 else ''}); the pattern's files {lo}..{hi} "
                             f"lack number{'s' if len(gaps) > 1 else ''} {listed(gaps)} "
                             f"({len(gaps)} of {hi - lo + 1})")


def format_of(path: str, formats: Mapping[str, str], param: str = "path") -> str:
    """Return the format of `path` from its extension (case-insensitive).

    Args:
        path: file path or pattern.
        formats: extension with dot (".obj") -> format name.
        param: parameter named in the error.
    Raises:
        InputError: for an extension not in `formats`.
    """
    ext = os.path.splitext(path)[1].lower()
    if ext not in formats:
        raise InputError(param, f"'{path}': expected an extension among "
                                f"{sorted(formats)}, found '{ext or '(none)'}'")
    return formats[ext]


# -- NPZ members, read without loading whole arrays ----------------------------------------

def npz_keys(path: str | os.PathLike) -> list[str]:
    """Return the array names of an .npz file."""
    with zipfile.ZipFile(path) as zf:
        return [n[:-4] for n in zf.namelist() if n.endswith(".npy")]


def _read_header(fh) -> tuple[tuple[int, ...], bool, np.dtype]:
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        return np.lib.format.read_array_header_1_0(fh)
    if version == (2, 0):
        return np.lib.format.read_array_header_2_0(fh)
    raise ValueError(f"unsupported .npy version {version}")


def npz_shape(path: str | os.PathLike, key: str) -> tuple[tuple[int, ...], np.dtype]:
    """Return (shape, dtype) of member `key` of an .npz file from its header only.

    Raises:
        KeyError: when `key` is not in the file.
    """
    with zipfile.ZipFile(path) as zf, zf.open(f"{key}.npy") as fh:
        shape, _, dtype = _read_header(fh)
    return shape, dtype


def read_npz_array(path: str | os.PathLike, key: str) -> np.ndarray:
    """Load member `key` of an .npz file whole (no pickles)."""
    with np.load(path, allow_pickle=False) as data:
        return np.asarray(data[key])


def read_npz_rows(path: str | os.PathLike, key: str, start: int, stop: int) -> np.ndarray:
    """Return rows [start, stop) of member `key` of an .npz file, reading only those rows.

    Stored (uncompressed, `np.savez`) members are memory-mapped; compressed ones
    (`np.savez_compressed`) are streamed, decompressing but not keeping earlier rows.

    Args:
        path: the .npz file.
        key: member name (without ".npy").
        start, stop: row range along axis 0, 0 <= start <= stop <= rows.
    Returns:
        (stop - start, ...) array, a copy.
    Raises:
        KeyError: unknown member. ValueError: bad range or a truncated member.
    """
    path = os.fspath(path)
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo(f"{key}.npy")
        with zf.open(info) as fh:
            shape, fortran, dtype = _read_header(fh)
            header_len = fh.tell()
            if not shape or not 0 <= start <= stop <= shape[0]:
                raise ValueError(f"'{key}': rows {start}:{stop} outside 0:{shape[0] if shape else 0}")
            if fortran or dtype.hasobject:
                return np.asarray(read_npz_array(path, key)[start:stop])
            row_items = int(np.prod(shape[1:], dtype=np.int64))
            row_bytes = row_items * dtype.itemsize
            count = stop - start
            if info.compress_type == zipfile.ZIP_STORED:
                with open(path, "rb") as raw:
                    raw.seek(info.header_offset)
                    local = raw.read(30)
                name_len, extra_len = struct.unpack("<HH", local[26:30])
                offset = info.header_offset + 30 + name_len + extra_len + header_len
                if offset + shape[0] * row_bytes > os.path.getsize(path):
                    raise ValueError(f"'{key}': file is truncated")
                mapped = np.memmap(path, dtype=dtype, mode="r", offset=offset + start * row_bytes,
                                   shape=(count, *shape[1:])) if count else None
                out = np.array(mapped) if count else np.empty((0, *shape[1:]), dtype)
                del mapped
                return out
            skip = start * row_bytes
            while skip > 0:
                got = len(fh.read(min(skip, 1 << 24)))
                if got == 0:
                    raise ValueError(f"'{key}': file is truncated")
                skip -= got
            data = fh.read(count * row_bytes)
            if len(data) != count * row_bytes:
                raise ValueError(f"'{key}': file is truncated")
            return np.frombuffer(data, dtype=dtype).reshape(count, *shape[1:]).copy()
