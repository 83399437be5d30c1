"""PFM, the Portable Float Map: the image file of OIDN's example program ``oidnDenoise`` (docs/formats.md §1c).

A PFM file is three whitespace-ended ASCII tokens and the pixels: ``PF`` (three channels) or ``Pf`` (one), then
``<width> <height>``, then a scale whose sign gives the byte order of the float32 samples (negative: little
endian, positive: big endian), one whitespace character, and ``width * height * channels`` samples, the rows
from the bottom of the image to its top. The scale's magnitude multiplies every sample, as OIDN's reader
(``apps/utils/image_io.cpp``) applies it; writers, OIDN's and :func:`write`, write ``-1.0``. Bytes after the
pixels are left unread, as OIDN leaves them.

:func:`read` returns float32 (H, W, 3) or (H, W), rows top to bottom as every other image of kpcn;
:func:`write` writes little-endian ``-1.0`` files atomically (``prep.files.atomic_path``). A file that is not a
PFM, is cut short or names a size its bytes cannot hold is refused with a :class:`PfmError`, one line naming it.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from prep.errors import KpcnError
from prep.files import atomic_path

CHANNELS = {b"PF": 3, b"Pf": 1}  # the magic of a colour and of a greyscale map
HEADER_LIMIT = 256  # bytes the three header tokens may take: a longer one is not a PFM's
WHITESPACE = b" \t\r\n\v\f"


class PfmError(KpcnError, ValueError):
    """A file that is not a PFM :func:`read` takes; the message names it and what was found."""


def _tokens(path: Path, data: bytes) -> tuple[list[bytes], int]:
    """The header's three tokens (magic, width and height, scale: four in all) and the offset of the pixels."""
    tokens, pos = [], 0
    while len(tokens) < 4:
        while pos < len(data) and data[pos] in WHITESPACE:
            pos += 1
        end = pos
        while end < len(data) and data[end] not in WHITESPACE:
            end += 1
        if end == pos or end > HEADER_LIMIT or end >= len(data):
            found = data[: min(len(data), 16)]
            raise PfmError(f"{path}: not a PFM file (expected PF or Pf, a width, a height and a scale, each ended "
                           f"by whitespace; the file begins {found!r})")
        tokens.append(data[pos:end])
        pos = end
    return tokens, pos + 1  # one whitespace character ends the scale


def _header(path: Path, data: bytes) -> tuple[int, int, int, float, int]:
    """(height, width, channels, scale, offset of the pixels) of a PFM file's bytes ``data``."""
    tokens, offset = _tokens(path, data)
    if tokens[0] not in CHANNELS:
        raise PfmError(f"{path}: not a PFM file: it begins {tokens[0][:16]!r}, expected PF (colour) or Pf "
                       "(greyscale)" + ("; P= (two channels) is OIDN's own extension, not read here"
                                        if tokens[0] == b"P=" else ""))
    try:
        width, height = int(tokens[1]), int(tokens[2])
        scale = float(tokens[3])
    except ValueError:
        raise PfmError(f"{path}: a PFM header with width {tokens[1][:16]!r}, height {tokens[2][:16]!r} and "
                       f"scale {tokens[3][:16]!r}: expected two integers and a number") from None
    if width <= 0 or height <= 0:
        raise PfmError(f"{path}: a PFM image of {width}x{height} pixels: both must be at least 1")
    if scale == 0 or not np.isfinite(scale):
        raise PfmError(f"{path}: a PFM scale of {tokens[3].decode(errors='replace')}: it must be a non-zero "
                       "number (its sign is the byte order)")
    return height, width, CHANNELS[tokens[0]], scale, offset


def read(path: str | os.PathLike) -> np.ndarray:
    """The float32 pixels of the PFM file ``path``: (H, W, 3) for ``PF``, (H, W) for ``Pf``, the top row first,
    each sample times the scale's magnitude. PfmError naming the file for one that is missing or is not a whole
    PFM (module docstring)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PfmError(f"{path}: cannot be read as a PFM file: {exc.strerror or exc}") from None
    height, width, channels, scale, offset = _header(path, data)
    count = height * width * channels
    if len(data) - offset < 4 * count:
        raise PfmError(f"{path}: a {width}x{height} PFM of {channels} channel{'s' if channels > 1 else ''} needs "
                       f"{4 * count} bytes of pixels after its header, the file has {max(len(data) - offset, 0)}")
    order = "<" if scale < 0 else ">"
    pixels = np.frombuffer(data, f"{order}f4", count, offset).astype(np.float32)
    if abs(scale) != 1:
        pixels = pixels * np.float32(abs(scale))
    image = pixels.reshape((height, width, channels) if channels > 1 else (height, width))
    return np.ascontiguousarray(image[::-1])


def write(path: str | os.PathLike, image: np.ndarray) -> Path:
    """Write ``image`` ((H, W, 3) or (H, W), top row first; any real type, taken to float32) as a little-endian
    PFM (scale ``-1.0``), atomically. PfmError naming ``path`` for another shape."""
    path = Path(path)
    image = np.asarray(image)
    if not (image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)) or 0 in image.shape:
        raise PfmError(f"{path}: PFM holds (H, W, 3) colour or (H, W) greyscale, got an array of shape {image.shape}")
    magic = b"PF" if image.ndim == 3 else b"Pf"
    header = magic + b"\n" + f"{image.shape[1]} {image.shape[0]}\n-1.0\n".encode()
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(np.ascontiguousarray(image[::-1], "<f4").tobytes())
    return path
