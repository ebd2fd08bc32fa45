"""Image sequences on disk through OpenImageIO: numbered EXR, PNG, TIFF, JPEG (and any format
OpenImageIO reads).

Pixels are float32 in memory, (F, H, W, C), origin top-left. Integer files (8/16 bit) are
scaled to [0, 1] when read and clipped to [0, 1] and rounded when written; float files are
kept as stored. Channels and alpha are preserved (names from the file, e.g. R, G, B, A; Y
for greyscale PNG); colour is never (un)premultiplied by alpha on read or write. Run frame `f` is file number `first_frame + f`.

Colour space (`ImageSequence.colour_space`): files with float or half pixels (EXR, HDR,
float TIFF) hold linear light and load as "linear"; integer files (8/16-bit PNG, JPEG,
TIFF, ...) hold sRGB-encoded values and load as "srgb" (the loader's `colour_space` param
overrides this, e.g. for linear 16-bit data). The saver writes each file in the space of its
pixel type (float/half: linear, integer: sRGB; its `colour_space` param overrides) and
converts the sequence when it is in the other space, with the exact sRGB curve on colour
channels (alpha and depth untouched): a linear sequence written to PNG is sRGB-encoded, an
sRGB sequence written to EXR is decoded to linear. Loading back gives the space written.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, get_args

import numpy as np
from pydantic import field_validator

from nodegraph import FRAMEWISE, Files, ImageSequence, In, InputError, Node, NodeParams, Out, Param

from ._files import (atomic_path, check_no_missing_files, expand_frame_pattern, files_value, find_frame_numbers,
                     format_of, frame_token, frame_where, pattern_files)

__all__ = ["IMAGE_WRITE_FORMATS", "read_image", "write_image", "image_frame_count",
           "image_frame_files", "load_image_sequence", "save_image_sequence", "LoadImageSequence",
           "SaveImageSequence"]

IMAGE_WRITE_FORMATS = {".exr": "exr", ".png": "png", ".tif": "tiff", ".tiff": "tiff",
                       ".jpg": "jpeg", ".jpeg": "jpeg"}
"""Extension -> format the saver writes."""

_DEPTHS: dict[str, tuple[str, ...]] = {  # first = the "auto" choice
    "exr": ("float", "half"), "png": ("uint8", "uint16"), "tiff": ("uint16", "uint8", "float"),
    "jpeg": ("uint8",),
}
_CHANNELS: dict[str, tuple[int, ...]] = {"png": (1, 2, 3, 4), "jpeg": (1, 3)}
BitDepth = Literal["auto", "uint8", "uint16", "half", "float"]
ColourSpaceChoice = Literal["auto", "linear", "srgb"]


def _file_colour_space(pixel_type: str) -> str:
    """Colour space a file's pixel type implies: float/half -> "linear", integer -> "srgb"."""
    return "linear" if pixel_type in ("half", "float", "double") else "srgb"


def _oiio():
    import OpenImageIO as oiio

    return oiio


def _read_formats() -> dict[str, str]:
    """Extension -> OpenImageIO format name for every format this OpenImageIO build reads."""
    out = {}
    for entry in _oiio().get_string_attribute("extension_list").split(";"):
        name, _, exts = entry.partition(":")
        out.update({f".{ext}": name for ext in exts.split(",") if ext})
    return out


def _open(path: str):
    """Open an image for reading with alpha left unassociated (values exactly as stored)."""
    oiio = _oiio()
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    return oiio.ImageInput.open(path, config)


def _header(path: str) -> tuple[int, int, list[str], str]:
    """(width, height, channel names, colour space) of an image file, reading only its header."""
    oiio = _oiio()
    inp = _open(path)
    if inp is None:
        raise ValueError(oiio.geterror() or "cannot open")
    try:
        spec = inp.spec()
        return spec.width, spec.height, list(spec.channelnames), _file_colour_space(str(spec.format))
    finally:
        inp.close()


def _read_image(path: str) -> tuple[np.ndarray, list[str], str]:
    """`read_image` plus the colour space the file's pixel type implies."""
    oiio = _oiio()
    inp = _open(path)
    if inp is None:
        raise ValueError(oiio.geterror() or "cannot open")
    try:
        spec = inp.spec()
        pixels = inp.read_image(0, 0, 0, spec.nchannels, "float")
        error = inp.geterror() if hasattr(inp, "geterror") else ""
        if pixels is None or error:
            raise ValueError(error or oiio.geterror() or "cannot read pixels")
        pixels = np.asarray(pixels, np.float32).reshape(spec.height, spec.width, spec.nchannels)
        return pixels, list(spec.channelnames), _file_colour_space(str(spec.format))
    finally:
        inp.close()


def read_image(path: str | os.PathLike) -> tuple[np.ndarray, list[str]]:
    """Read the first subimage of an image file.

    Args:
        path: any file OpenImageIO reads.
    Returns:
        pixels (H, W, C) float32 (integer formats scaled to [0, 1]) and the C channel names.
    Raises:
        ValueError: unreadable or truncated file (with OpenImageIO's message).
    """
    pixels, channels, _ = _read_image(os.fspath(path))
    return pixels, channels


def write_image(path: str | os.PathLike, pixels: np.ndarray, channels: list[str],
                bit_depth: str, quality: int = 95) -> None:
    """Write one image (format from the extension of `path`).

    Args:
        path: destination (written as is; wrap with `atomic_path` for atomic writes).
        pixels: (H, W, C) float.
        channels: C names; a channel named "A" is flagged as alpha.
        bit_depth: "uint8", "uint16" (values clipped to [0, 1], rounded to the nearest step),
            "half" or "float".
        quality: JPEG quality 1..100.
    Raises:
        OSError: when OpenImageIO cannot write.
    """
    oiio = _oiio()
    path = os.fspath(path)
    height, width, count = pixels.shape
    if bit_depth in ("uint8", "uint16"):
        top = 255 if bit_depth == "uint8" else 65535
        scaled = np.clip(np.asarray(pixels, np.float64), 0.0, 1.0) * top  # float64: exact ties
        data = np.round(scaled).astype(np.uint8 if top == 255 else np.uint16)
    else:
        data = np.ascontiguousarray(pixels, np.float32)
    spec = oiio.ImageSpec(width, height, count, bit_depth)
    spec.channelnames = tuple(channels)
    if "A" in channels:
        spec.alpha_channel = channels.index("A")
    spec.attribute("oiio:UnassociatedAlpha", 1)  # values are stored as given, not un-premultiplied
    if path.lower().endswith((".jpg", ".jpeg")):
        spec.attribute("Compression", f"jpeg:{int(quality)}")
    out = oiio.ImageOutput.create(path)
    if out is None:
        raise OSError(oiio.geterror() or f"no writer for '{path}'")
    try:
        if not out.open(path, spec) or not out.write_image(data):
            raise OSError(out.geterror() or oiio.geterror() or f"cannot write '{path}'")
    finally:
        out.close()


def _check_pattern(path: str) -> None:
    if frame_token(path) is None:
        raise InputError("path", f"expected a numbered pattern such as 'img.%04d.exr', found '{path}'")


def _single_file(path: str) -> bool:
    """True for a path without a frame token: one image file, read as a one-frame sequence."""
    if frame_token(path) is not None:
        return False
    if not os.path.isfile(path):
        raise InputError("path", f"expected a numbered pattern such as 'img.%04d.exr' or an existing image "
                                 f"file, found '{path}'")
    return True


def image_frame_count(path: str, first_frame: int | None = None) -> int:
    """Frames of a numbered image pattern: highest number found - first number + 1 (0 if none);
    1 for a single image file (a path without a frame token)."""
    if _single_file(path):
        return 1
    numbers = find_frame_numbers(path)
    first = first_frame if first_frame is not None else (numbers[0] if numbers else None)
    return max(0, numbers[-1] - first + 1) if numbers and first is not None else 0


def image_frame_files(path: str, frames: range | None = None,
                      first_frame: int | None = None) -> list[Path]:
    """Existing files of run frames `frames` of a numbered pattern (None = every file).

    Run frame f is file number first_frame + f (first_frame None = the lowest number found);
    a single image file is frame 0.

    Raises:
        InputError: (param "path") when a frame of `frames` has no file: a gap in the numbers
            (`check_no_missing_files`), found while planning, before anything runs.
    """
    if _single_file(path):
        return [Path(path)] if frames is None or 0 in frames else []
    if frames is None:
        return pattern_files(path)
    numbers = find_frame_numbers(path)
    first = first_frame if first_frame is not None else (numbers[0] if numbers else None)
    if first is None:
        return []
    check_no_missing_files(path, frames, first, numbers)
    present = set(numbers)  # frames past the last file: none (the frame-count check refuses them)
    return [Path(expand_frame_pattern(path, first + f)) for f in frames if first + f in present]


def load_image_sequence(path: str, frames: range, *, first_frame: int | None = None,
                        fps: float = 30.0, colour_space: str = "auto") -> ImageSequence:
    """Read run frames `frames` of a numbered image pattern (only those files, plus frame 0's header).

    Args:
        path: pattern such as `plate.%04d.exr` or `cam0.####.png`, or one image file (frame 0).
        frames: run frames; frame f is file number first_frame + f.
        first_frame: number of the file of frame 0; None = the lowest number found.
        fps: frames per second of the sequence.
        colour_space: "auto" (float/half files "linear", integer files "srgb"), or "linear"
            / "srgb" to declare the files' space (values are never converted on read).
    Returns:
        ImageSequence (len(frames), H, W, C) float32 with the channel names of frame 0.
    Raises:
        InputError: naming file and frame: unknown extension, missing or unreadable file,
            size, channels or (with "auto") pixel type different from frame 0.
    """
    if colour_space not in get_args(ColourSpaceChoice):
        raise InputError("colour_space", f"expected one of {list(get_args(ColourSpaceChoice))}, "
                                         f"found {colour_space!r}")
    format_of(path, _read_formats())
    single = _single_file(path)
    numbers = [0] if single else find_frame_numbers(path)
    first = first_frame if first_frame is not None else (numbers[0] if numbers else None)
    if first is None:
        raise InputError("path", f"expected files matching '{path}', found none")

    def file_of(frame: int) -> str:
        file = (path if frame == 0 else f"{path} (frame {frame})") if single else \
            expand_frame_pattern(path, first + frame)
        if not os.path.isfile(file):
            raise InputError("path", f"{frame_where(frame, file)}: expected the file of this frame, "
                                     "found it missing")
        return file

    def unreadable(frame: int, file: str, err: Exception) -> InputError:
        return InputError("path", f"{frame_where(frame, file)}: expected a readable image, found an "
                                  f"unreadable or truncated file ({str(err).strip()})")

    ref_file = file_of(0)
    try:
        width, height, channels, ref_space = _header(ref_file)
    except ValueError as err:
        raise unreadable(0, ref_file, err) from err
    pixels = np.empty((len(frames), height, width, len(channels)), np.float32)
    for i, f in enumerate(frames):
        file = file_of(f)
        try:
            image, names, space = _read_image(file)
        except ValueError as err:
            raise unreadable(f, file, err) from err
        if image.shape != pixels.shape[1:] or names != channels:
            raise InputError("path", f"{frame_where(f, file)}: expected {width}x{height} pixels with "
                                     f"channels {channels} as in frame 0 ('{ref_file}'), found "
                                     f"{image.shape[1]}x{image.shape[0]} with channels {names}")
        if colour_space == "auto" and space != ref_space:
            raise InputError("path", f"{frame_where(f, file)}: expected {ref_space} pixels "
                                     f"({'float' if ref_space == 'linear' else 'integer'}) as in "
                                     f"frame 0 ('{ref_file}'), found {space} "
                                     f"({'float' if space == 'linear' else 'integer'}); set "
                                     "colour_space to declare one space for all frames")
        pixels[i] = image
    return ImageSequence(pixels=pixels, channels=channels, fps=fps,
                         colour_space=ref_space if colour_space == "auto" else colour_space)


def save_image_sequence(path: str, images: ImageSequence, frames: range, *, first_frame: int = 0,
                        bit_depth: str = "auto", quality: int = 95, colour_space: str = "auto",
                        progress=None) -> list[str]:
    """Write one file per frame, atomically; return the written paths.

    Args:
        path: pattern with extension .exr, .png, .tif/.tiff, .jpg/.jpeg.
        images: (F, H, W, C) with F == len(frames).
        frames: run frames; frame f goes to file number first_frame + f.
        bit_depth: "auto" (EXR float, PNG uint8, TIFF uint16, JPEG uint8) or one the format
            stores: EXR float/half, PNG uint8/uint16, TIFF uint8/uint16/float, JPEG uint8.
        quality: JPEG quality 1..100.
        colour_space: space of the written files: "auto" (float/half depths "linear",
            integer depths "srgb"), "linear" or "srgb". `images` is converted to it first
            when its `colour_space` differs (exact sRGB curve, colour channels only).
    Raises:
        InputError: unknown extension, a depth or channel count the format cannot store,
            non-finite pixels for an integer format.
    """
    fmt = format_of(path, IMAGE_WRITE_FORMATS)
    _check_pattern(path)
    depth = _DEPTHS[fmt][0] if bit_depth == "auto" else bit_depth
    if depth not in _DEPTHS[fmt]:
        raise InputError("bit_depth", f"expected one of {list(_DEPTHS[fmt])} for {fmt.upper()} "
                                      f"('{path}'), found '{bit_depth}'")
    count = images.pixels.shape[3]
    if fmt in _CHANNELS and count not in _CHANNELS[fmt]:
        raise InputError("images", f"expected {' or '.join(map(str, _CHANNELS[fmt]))} channels for "
                                   f"{fmt.upper()} ('{path}'), found {count} {images.channels}; "
                                   "write EXR or TIFF instead")
    if colour_space not in get_args(ColourSpaceChoice):
        raise InputError("colour_space", f"expected one of {list(get_args(ColourSpaceChoice))}, "
                                         f"found {colour_space!r}")
    target = _file_colour_space(depth) if colour_space == "auto" else colour_space
    images = images.to_colour_space(target)
    written = []
    for i, f in enumerate(frames):
        if depth.startswith("uint") and not np.isfinite(images.pixels[i]).all():
            raise InputError("images", f"frame {f}: expected finite pixels for {depth} "
                                       f"{fmt.upper()}, found NaN/inf")
        file = expand_frame_pattern(path, first_frame + f)
        with atomic_path(file) as tmp:
            write_image(tmp, images.pixels[i], list(images.channels), depth, quality)
        written.append(file)
        if progress is not None:
            progress((i + 1) / len(frames), f"wrote {file}")
    return written


class LoadImageSequence(Node):
    """Read a numbered image sequence (EXR, PNG, TIFF, JPEG, ...) as float32 pixels."""

    type_name = "io.LoadImageSequence"
    version = 2  # 2: colour_space
    kind = FRAMEWISE

    class Params(NodeParams):
        path: str = Param(..., input_file=True, description="Numbered pattern: plate.%04d.exr, "
                          "cam0.####.png or img.{frame:04d}.tif.")
        first_frame: int | None = Param(None, description="Number of the file of frame 0; None = "
                                        "the lowest number found.")
        fps: float = Param(30.0, gt=0, description="Frames per second (1/s).")
        colour_space: ColourSpaceChoice = Param("auto", description="Colour space of the files: "
                                                "auto (float files linear, integer files srgb), "
                                                "linear or srgb (declared, not converted).")

    images = Out(ImageSequence, doc="Pixels (F, H, W, C) float32, integer files scaled to [0, 1]; "
                 "colour_space linear (float files) or srgb (integer files).")

    def frame_count(self) -> int | None:
        p = self.params
        count = image_frame_count(p.path, p.first_frame)
        if count == 0:  # missing or unreadable: reading frame 0 raises the error naming the file
            load_image_sequence(p.path, range(0, 1), first_frame=p.first_frame, fps=p.fps)
        return count

    def input_files(self, frames: range | None = None) -> list[Path]:
        """The existing files of run frames `frames` (None: every file of the pattern)."""
        return image_frame_files(self.params.path, frames, self.params.first_frame)

    def run(self) -> dict[str, ImageSequence]:
        p = self.params
        return {"images": load_image_sequence(p.path, self.frames, first_frame=p.first_frame,
                                               fps=p.fps, colour_space=p.colour_space)}


class SaveImageSequence(Node):
    """Write one image file per frame (EXR, PNG, TIFF or JPEG by extension), atomically."""

    type_name = "io.SaveImageSequence"
    version = 2  # 2: converts to the file's colour space
    kind = FRAMEWISE
    writes_files = True

    class Params(NodeParams):
        path: str = Param(..., output_file=True, description="Numbered pattern with extension .exr, .png, .tif, "
                          ".tiff, .jpg or .jpeg.")
        first_frame: int = Param(0, description="File number of run frame 0.")
        bit_depth: BitDepth = Param("auto", description="auto (EXR float, PNG uint8, TIFF uint16, "
                                    "JPEG uint8), uint8, uint16, half or float.")
        quality: int = Param(95, ge=1, le=100, description="JPEG quality (1..100).")
        colour_space: ColourSpaceChoice = Param("auto", description="Colour space of the files: "
                                                "auto (float/half linear, integer srgb), linear "
                                                "or srgb; the images are converted to it.")

        @field_validator("path")
        @classmethod
        def _pattern(cls, value: str) -> str:  # refused at validation, not after the frames were made
            if Path(value).suffix.lower() not in IMAGE_WRITE_FORMATS:
                raise ValueError(f"expected a numbered pattern ending in {', '.join(IMAGE_WRITE_FORMATS)}, "
                                 f"found '{value}'")
            if frame_token(value) is None:
                raise ValueError(f"expected a numbered pattern such as 'img.%04d.exr', found '{value}'")
            return value

    images = In(ImageSequence, doc="The frames to write (converted to the files' colour space).")
    files = Out(Files, doc="Paths written by this chunk and their sha256.")

    def run(self, images: ImageSequence) -> dict[str, Files]:
        p = self.params
        written = save_image_sequence(p.path, images, self.frames, first_frame=p.first_frame,
                                      bit_depth=p.bit_depth, quality=p.quality,
                                      colour_space=p.colour_space, progress=self.progress)
        return {"files": files_value(written)}
