"""The denoised colour of kpcn's output EXR, read with numpy (Blender ships it) and the standard library.

Why not ``bpy.data.images.load``: kpcn's output keeps its layers (``default.R G B A``, ``albedo``, ``normal``, ...),
which Blender loads as a multilayer image, whose pixels its Python cannot read and whose first pass shown is not
the colour. kpcn writes that file one way (``prep/exr.py`` ``write_aovs``: one scanline part, ZIP or no
compression, half or float channels), and this reads that way alone, refusing anything else in one line."""

import struct
import zlib

import numpy as np

MAGIC = 20000630
NONE, ZIPS, ZIP = 0, 2, 3  # OpenEXR compression codes this reads, and their lines per block
LINES = {NONE: 1, ZIPS: 1, ZIP: 16}
TYPES = {1: np.dtype("<f2"), 2: np.dtype("<f4")}  # HALF, FLOAT (UINT is no colour)


class ExrError(Exception):
    """One line naming the file and what it holds that this reader does not."""


def _header(data: bytes, path: str):
    """(attributes {name: (type, bytes)}, offset after the header)."""
    magic, version = struct.unpack_from("<ii", data, 0)
    if magic != MAGIC:
        raise ExrError(f"{path}: not an OpenEXR file")
    if version & 0x1A00:  # tiled, long names... multi-part / deep
        raise ExrError(f"{path}: a tiled, multi-part or deep EXR (kpcn writes one scanline part)")
    attrs, at = {}, 8
    while data[at] != 0:
        name_end = data.index(b"\0", at)
        type_end = data.index(b"\0", name_end + 1)
        (size,) = struct.unpack_from("<i", data, type_end + 1)
        start = type_end + 5
        attrs[data[at:name_end].decode()] = (data[name_end + 1:type_end].decode(), data[start:start + size])
        at = start + size
    return attrs, at + 1


def _channels(chlist: bytes) -> list[tuple[str, np.dtype]]:
    out, at = [], 0
    while chlist[at] != 0:
        end = chlist.index(b"\0", at)
        (ptype,) = struct.unpack_from("<i", chlist, end + 1)
        out.append((chlist[at:end].decode(), TYPES.get(ptype)))
        at = end + 17  # type, pLinear + 3 reserved, xSampling, ySampling
    return out


def _unzip(block: bytes, raw_size: int) -> bytes:
    """OpenEXR's ZIP block: zlib, then its byte predictor undone, then its two halves interleaved."""
    if len(block) == raw_size:  # stored as it is where compression would not shrink it
        return block
    t = np.frombuffer(zlib.decompress(block), np.uint8).copy()
    t[1:] -= 128
    t = np.cumsum(t, dtype=np.uint8)
    out = np.empty_like(t)
    half = (len(t) + 1) // 2
    out[0::2], out[1::2] = t[:half], t[half:]
    return out.tobytes()


def read_colour(path: str, layer: str = "default") -> np.ndarray:
    """Layer ``layer``'s R G B (A: 1 where absent) as (H, W, 4) float32, top row first."""
    with open(path, "rb") as f:
        data = f.read()
    attrs, at = _header(data, path)
    compression = attrs["compression"][1][0]
    if compression not in LINES:
        raise ExrError(f"{path}: compression {compression} (kpcn writes ZIP)")
    x0, y0, x1, y1 = struct.unpack("<iiii", attrs["dataWindow"][1])
    width, height = x1 - x0 + 1, y1 - y0 + 1
    channels = _channels(attrs["channels"][1])
    if any(dtype is None for _, dtype in channels):
        raise ExrError(f"{path}: a channel of unsigned integers (kpcn writes half or float)")
    names = [name for name, _ in channels]
    wanted = [f"{layer}.{c}" for c in "RGB"]
    if not set(wanted) <= set(names):
        raise ExrError(f"{path}: no layer {layer} (R G B); its channels: {', '.join(names)}")
    lines = LINES[compression]
    blocks = -(-height // lines)
    offsets = struct.unpack_from(f"<{blocks}Q", data, at)
    planes = {name: np.empty((height, width), np.float32) for name in names}
    for offset in offsets:
        y, size = struct.unpack_from("<ii", data, offset)
        rows = min(lines, y1 - y + 1)
        raw_size = rows * width * sum(dtype.itemsize for _, dtype in channels)
        block = data[offset + 8:offset + 8 + size]
        raw = _unzip(block, raw_size) if compression else block
        at_byte = 0
        for row in range(rows):
            for name, dtype in channels:
                n = width * dtype.itemsize
                planes[name][y - y0 + row] = np.frombuffer(raw, dtype, width, at_byte)
                at_byte += n
    alpha = planes.get(f"{layer}.A", np.ones((height, width), np.float32))
    return np.stack([planes[n] for n in wanted] + [alpha], axis=-1)
