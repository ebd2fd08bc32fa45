"""Images over frames and their colour spaces: the `ImageSequence` port type and the exact
sRGB transfer curve (IEC 61966-2-1) that converts between its "linear" and "srgb" encodings."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import ClassVar, Sequence

import numpy as np

from .ports import PortType, check_array, fail

__all__ = ["ImageSequence", "COLOUR_SPACES", "srgb_to_linear", "linear_to_srgb"]


COLOUR_SPACES = ("linear", "srgb")
"""The colour spaces an `ImageSequence` declares (see `srgb_to_linear`)."""

_NON_COLOUR_CHANNELS = frozenset({"A", "ALPHA", "Z", "DEPTH"})


def srgb_to_linear(values: np.ndarray) -> np.ndarray:
    """Decode sRGB-encoded values to linear light with the exact IEC 61966-2-1 curve.

    `c <= 0.04045: c / 12.92`, else `((c + 0.055) / 1.055) ** 2.4`. Negative values follow
    the linear segment; values above 1 follow the power segment (no clipping). Computed in
    float64.

    Args:
        values: (...) float, sRGB-encoded (1 = display white).
    Returns:
        (...) float32 linear values.

    Example:
        >>> [round(float(v), 6) for v in srgb_to_linear(np.array([0.0, 0.5, 1.0]))]
        [0.0, 0.214041, 1.0]
    """
    c = np.asarray(values, np.float64)
    out = np.where(c <= 0.04045, c / 12.92, ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4)
    return out.astype(np.float32)


def linear_to_srgb(values: np.ndarray) -> np.ndarray:
    """Encode linear light as sRGB with the exact IEC 61966-2-1 curve (inverse of `srgb_to_linear`).

    `l <= 0.0031308: 12.92 l`, else `1.055 l ** (1 / 2.4) - 0.055`. Negative values follow
    the linear segment; values above 1 follow the power segment (no clipping). Computed in
    float64.

    Args:
        values: (...) float, linear light (1 = display white).
    Returns:
        (...) float32 sRGB-encoded values.

    Example:
        >>> linear_to_srgb(np.array([0.0, 0.214041, 1.0])).round(4).tolist()
        [0.0, 0.5, 1.0]
    """
    lin = np.asarray(values, np.float64)
    out = np.where(lin <= 0.0031308, lin * 12.92,
                   1.055 * np.maximum(lin, 0.0031308) ** (1.0 / 2.4) - 0.055)
    return out.astype(np.float32)


@dataclass(eq=False)
class ImageSequence(PortType):
    """Images over frames.

    Attributes:
        pixels: (F, H, W, C) float32 (8/16-bit integer files are scaled to [0, 1]).
        channels: C channel names, e.g. ["R", "G", "B", "A"].
        fps: frames per second.
        colour_space: how the colour channels encode light: "linear" (scene-linear, as EXR
            and other float files store it) or "srgb" (the sRGB transfer curve, as 8/16-bit
            PNG, JPEG, TIFF files and video store it). Alpha and depth channels (named A,
            Alpha, Z or Depth, also as the last part of a layer name such as "diffuse.A")
            are linear in both and never converted. `to_linear` / `to_srgb` convert.
    """

    pixels: np.ndarray
    channels: list[str] = field(default_factory=lambda: ["R", "G", "B"])
    fps: float = 30.0
    colour_space: str = "srgb"

    per_frame: ClassVar[bool] = True
    frame_fields: ClassVar[tuple[str, ...]] = ("pixels",)

    def validate(self, where: str = "") -> None:
        where = where or self.type_name
        check_array(where, "pixels", self.pixels, 4)
        if len(self.channels) != self.pixels.shape[3]:
            fail(where, f"{len(self.channels)} channel names for {self.pixels.shape[3]} channels")
        if self.colour_space not in COLOUR_SPACES:
            fail(where, f"'colour_space' must be one of {list(COLOUR_SPACES)}, found "
                        f"{self.colour_space!r}")

    @classmethod
    def concat_frames(cls, parts: Sequence["ImageSequence"]) -> "ImageSequence":
        """Concatenate chunks; chunks of different colour spaces or channels are refused."""
        for index, part in enumerate(parts[1:], start=1):
            if part.colour_space != parts[0].colour_space:
                raise ValueError(f"{cls.type_name}: chunk {index} has colour_space "
                                 f"'{part.colour_space}', chunk 0 has '{parts[0].colour_space}'")
            if list(part.channels) != list(parts[0].channels):
                raise ValueError(f"{cls.type_name}: chunk {index} has channels {part.channels}, "
                                 f"chunk 0 has {parts[0].channels}")
        return super().concat_frames(parts)

    def colour_channels(self) -> list[int]:
        """Indices of the channels that carry colour (all but alpha and depth, see the class)."""
        return [i for i, name in enumerate(self.channels)
                if name.rsplit(".", 1)[-1].upper() not in _NON_COLOUR_CHANNELS]

    def rgb(self) -> np.ndarray:
        """(F, H, W, 3) the first three colour channels (a view when they are consecutive), or a
        single colour channel repeated three times (grey); pixels as stored (no conversion). May
        share memory with `pixels`: read it, do not write into it."""
        idx = self.colour_channels()
        if len(idx) >= 3:
            first = idx[0]
            return self.pixels[..., first:first + 3] if idx[:3] == [first, first + 1, first + 2] \
                else self.pixels[..., idx[:3]]
        return np.repeat(self.pixels[..., idx[:1]], 3, -1)

    def to_colour_space(self, colour_space: str) -> "ImageSequence":
        """Return this sequence in `colour_space` ("linear" or "srgb"), converting colour
        channels with the exact sRGB curve; `self` when it is already there (nothing copied)."""
        if colour_space not in COLOUR_SPACES:
            raise ValueError(f"colour_space: expected one of {list(COLOUR_SPACES)}, found "
                             f"{colour_space!r}")
        if colour_space == self.colour_space:
            return self
        convert = srgb_to_linear if colour_space == "linear" else linear_to_srgb
        pixels = np.array(self.pixels, np.float32)
        idx = self.colour_channels()
        if idx:
            pixels[..., idx] = convert(pixels[..., idx])
        return dataclasses.replace(self, pixels=pixels, colour_space=colour_space)

    def to_linear(self) -> "ImageSequence":
        """Return the sequence with linear colour channels (decoded from sRGB when needed)."""
        return self.to_colour_space("linear")

    def to_srgb(self) -> "ImageSequence":
        """Return the sequence with sRGB-encoded colour channels (encoded when needed)."""
        return self.to_colour_space("srgb")
