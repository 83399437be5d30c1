"""The structure of a PNG file, checked before an image library decodes it (λ maps, environment maps).

PIL trusts what a file claims: a chunk whose length runs past the end of the file is read with a buffer of that
length (2 GiB for a damaged length field), and a critical chunk whose CRC does not match is decoded as it is.
:func:`check` walks the chunks first and refuses, in one line naming the file, a file that is not a PNG, a chunk
cut short or running past the end, a CRC that does not match on a critical chunk (IHDR, PLTE, IDAT, IEND, as
libpng refuses them), an IHDR of another length than 13 bytes, or a file without IHDR, IDAT or a closing IEND.
It returns the size the header states, for a reader to bound before decoding.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

from prep.errors import KpcnError

SIGNATURE = b"\x89PNG\r\n\x1a\n"
CRITICAL = (b"IHDR", b"PLTE", b"IDAT", b"IEND")


class PngError(KpcnError, ValueError):
    """A file that is not a whole, undamaged PNG; the message names the file and what was found."""


def check(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) of the PNG ``path`` as its IHDR states them; PngError naming the file and the chunk for a
    file whose structure is damaged (module docstring)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise PngError(f"{path}: cannot be read ({exc.strerror or exc})") from None
    if not data.startswith(SIGNATURE):
        raise PngError(f"{path}: not a PNG file (its first bytes are not the PNG signature)")
    pos, seen, size = len(SIGNATURE), [], None
    while pos < len(data):
        if pos + 12 > len(data):
            raise PngError(f"{path}: cut short: {len(data) - pos} bytes after the last whole chunk")
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length
        if end > len(data):
            raise PngError(f"{path}: chunk {kind!r} at byte {pos} claims {length} bytes, the file has "
                           f"{len(data) - pos - 12} left: cut short or damaged")
        body = data[pos + 8:pos + 8 + length]
        if kind in CRITICAL and zlib.crc32(kind + body) != struct.unpack_from(">I", data, end - 4)[0]:
            raise PngError(f"{path}: chunk {kind.decode(errors='replace')} at byte {pos} fails its CRC: damaged")
        if kind == b"IHDR":
            if length != 13 or seen:
                raise PngError(f"{path}: IHDR of {length} bytes at byte {pos}; a PNG starts with one of 13 bytes")
            size = struct.unpack(">II", body[:8])
        seen.append(kind)
        pos = end
        if kind == b"IEND":
            break
    lacking = [k.decode() for k in (b"IHDR", b"IDAT", b"IEND") if k not in seen]
    if lacking or size is None:
        raise PngError(f"{path}: no {', '.join(lacking)} chunk: cut short or damaged")
    return size
