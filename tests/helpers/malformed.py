"""Malformed OpenEXR and PNG files made from the repository's small fixtures, in named families, and the child
process that puts each family through kpcn's readers under limits (``tests/test_fuzz_readers.py``).

Every case is made from a fixture by a rule and a seed, so a family is the same list of files on every machine;
``KPCN_FUZZ_SCALE`` (an integer, 1 by default) multiplies the truncated and bit-flipped cases. The families and
the number of cases each holds at the current scale:

    python -m tests.helpers.malformed --count

A child (``--check FAMILY,... --out RESULTS``) writes the families' files to a temporary folder, reads each with every
reader of its format under ``RLIMIT_AS`` (the address space the readers' libraries take, plus
:data:`MEMORY_MARGIN`) and ``RLIMIT_CPU``, and writes one JSON line per (case, reader): what came of it (a
result, a ``KpcnError``, anything else), the message, the CPU seconds it took and the warnings it raised.
"""

from __future__ import annotations

import argparse
import json
import os
import struct
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures"
SCALE = max(1, int(os.environ.get("KPCN_FUZZ_SCALE", "1") or 1))
# the hypothesis profile of the property tests (registered in conftest.py): ci, or deep for a deeper pass
PROFILE = os.environ.get("KPCN_HYPOTHESIS_PROFILE") or ("deep" if SCALE > 1 else "ci")
MEMORY_MARGIN = 768 << 20  # bytes a reader may map beyond what its libraries took before the first case
CPU_LIMIT_S = 1.0  # CPU seconds a reader may take on one case

# Small fixtures of each layout (single part), and Blender 5's one part per pass for the multi-part cases.
EXR_BASES = {
    "kpcn": FIXTURES / "fixture-01024spp.exr",
    "cycles4": FIXTURES / "renderers/cycles45/studio-00256spp.exr",
    "cycles5": FIXTURES / "renderers/cycles5/studio-00256spp.exr",
    "mitsuba": FIXTURES / "renderers/mitsuba3/cornell-01024spp.exr",
    "pbrt": FIXTURES / "renderers/pbrt4/cornell-00016spp.exr",
}
EXR_MULTIPART = FIXTURES / "renderers/cycles5/studio-00016spp.exr"

EXR_MAGIC = b"\x76\x2f\x31\x01"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
MULTIPART_FLAG, TILED_FLAG, LONG_NAMES_FLAG, DEEP_FLAG = 0x1000, 0x200, 0x400, 0x800


@dataclass(frozen=True)
class Case:
    family: str
    name: str
    data: bytes
    suffix: str  # the file's suffix: the readers choose by it


# --- OpenEXR: the header as attributes, to rewrite one of them ---------------------------------------------------

@dataclass
class ExrHeader:
    version: int
    parts: list[list[list]]  # per part, [name, type, value bytes] of each attribute
    rest: bytes  # offset tables and chunks, as they were

    def build(self, version: int | None = None, sizes: dict | None = None) -> bytes:
        """The file's bytes; ``sizes``: (part, attribute name) -> the size field to write instead of the value's."""
        out = [EXR_MAGIC, struct.pack("<I", self.version if version is None else version)]
        for p, attrs in enumerate(self.parts):
            for name, typ, value in attrs:
                size = (sizes or {}).get((p, name), len(value))
                out += [name.encode() + b"\0", typ.encode() + b"\0", struct.pack("<i", size), value]
            out.append(b"\0")
        if self.version & MULTIPART_FLAG:
            out.append(b"\0")
        return b"".join(out) + self.rest

    def get(self, name: str, part: int = 0) -> bytes | None:
        return next((v for n, _, v in self.parts[part] if n == name), None)

    def set(self, name: str, value: bytes, part: int = 0) -> ExrHeader:
        parts = [[list(a) for a in attrs] for attrs in self.parts]
        for attr in parts[part]:
            if attr[0] == name:
                attr[2] = value
        return ExrHeader(self.version, parts, self.rest)


def parse_exr(data: bytes) -> tuple[ExrHeader, int]:
    """The header of a well-formed EXR file and where it ends (the offset tables begin there)."""
    version = struct.unpack_from("<I", data, 4)[0]
    pos, parts = 8, []
    while True:
        attrs = []
        while data[pos] != 0:
            end = data.index(b"\0", pos)
            name = data[pos:end].decode()
            tend = data.index(b"\0", end + 1)
            typ = data[end + 1:tend].decode()
            size = struct.unpack_from("<i", data, tend + 1)[0]
            attrs.append([name, typ, data[tend + 5:tend + 5 + size]])
            pos = tend + 5 + size
        pos += 1
        parts.append(attrs)
        if not version & MULTIPART_FLAG or data[pos] == 0:
            break
    pos += 1 if version & MULTIPART_FLAG else 0
    return ExrHeader(version, parts, data[pos:]), pos


def _box(x0, y0, x1, y1) -> bytes:
    return struct.pack("<4i", x0, y0, x1, y1)


def _chlist(names, pixel_type=2, x_sampling=1, y_sampling=1) -> bytes:
    return b"".join(n.encode() + b"\0" + struct.pack("<iB3xii", pixel_type, 0, x_sampling, y_sampling)
                    for n in names) + b"\0"


def _exr_header_cases(base: str, data: bytes) -> list[tuple[str, bytes]]:
    """Absurd values in one header field each, the rest of the file as it was."""
    h, end = parse_exr(data)
    (x0, y0, x1, y1) = struct.unpack("<4i", h.get("dataWindow"))
    channels = [n for n in h.get("channels").split(b"\0") if n and len(n) > 1 and n.isascii()]
    big, top, many = 1 << 30, 2**31 - 1, (base == "mitsuba", base == "kpcn")
    cases = {
        "window-huge": h.set("dataWindow", _box(0, 0, big, big)),
        "window-65536": h.set("dataWindow", _box(0, 0, 65535, 65535)),
        "window-int-range": h.set("dataWindow", _box(-(2**31), -(2**31), top, top)),
        "window-tall": h.set("dataWindow", _box(0, 0, x1, 200_000_000)),
        "window-wide": h.set("dataWindow", _box(0, 0, 200_000_000, y1)),
        # as many rows as before, so the chunk table fits and the binding would allocate the pixels (1 TiB)
        "window-beyond-memory": h.set("dataWindow", _box(x0, y0, x0 + (1 << 28), y1)),
        "window-negative-width": h.set("dataWindow", _box(x0, y0, x0 - 10, y1)),
        "window-negative-height": h.set("dataWindow", _box(x0, y0, x1, y0 - 1)),
        "window-inverted": h.set("dataWindow", _box(x1, y1, x0, y0)),
        "window-1x1": h.set("dataWindow", _box(0, 0, 0, 0)),
        "window-shifted": h.set("dataWindow", _box(x0 + 1000, y0 + 1000, x1 + 1000, y1 + 1000)),
        "window-short": h.set("dataWindow", _box(x0, y0, x1, y0 + (y1 - y0) // 2)),
        "window-long": h.set("dataWindow", _box(x0, y0, x1, y1 * 2 + 1)),
        "window-cut-value": h.set("dataWindow", _box(x0, y0, x1, y1)[:8]),
        "display-huge": h.set("displayWindow", _box(0, 0, big, big)),
        "display-negative": h.set("displayWindow", _box(0, 0, -5, -5)),
        # thousands of channels take the binding a quarter second a read: one base each shows it
        "channels-5000": h.set("channels", _chlist(f"c{i:04d}.R" for i in range(5000))) if many[0] else None,
        "channels-4097": h.set("channels", _chlist(f"c{i:04d}.R" for i in range(4097))) if many[1] else None,
        "channels-none": h.set("channels", b"\0"),
        "channels-type-3": h.set("channels", _chlist(["R", "G", "B"], pixel_type=3)),
        "channels-type-negative": h.set("channels", _chlist(["R", "G", "B"], pixel_type=-1)),
        "channels-sampling-0": h.set("channels", _chlist(["R", "G", "B"], x_sampling=0, y_sampling=0)),
        "channels-sampling-negative": h.set("channels", _chlist(["R", "G", "B"], x_sampling=-1)),
        "channels-sampling-2": h.set("channels", _chlist(["R", "G", "B"], x_sampling=2, y_sampling=2)),
        "channels-sampling-huge": h.set("channels", _chlist(["R", "G", "B"], y_sampling=top)),
        "channels-empty-name": h.set("channels", _chlist(["", "G", "B"])),
        "channels-duplicate": h.set("channels", _chlist(["R", "R", "R"])),
        "channels-long-name": h.set("channels", _chlist(["x" * 300 + ".R", "G", "B"])),
        "channels-unterminated": h.set("channels", h.get("channels")[:-1]),
        "channels-renamed": h.set("channels", _chlist(n.decode() + "~" for n in channels[:8])),
        "compression-10": h.set("compression", b"\x0a"),
        "compression-255": h.set("compression", b"\xff"),
        "line-order-255": h.set("lineOrder", b"\xff"),
        "type-tiled": h.set("type", b"tiledimage") if h.get("type") else None,
        "type-deep": h.set("type", b"deepscanline") if h.get("type") else None,
        "type-garbage": h.set("type", b"garbage\x01") if h.get("type") else None,
        "chunk-count-negative": h.set("chunkCount", struct.pack("<i", -1)) if h.get("chunkCount") else None,
        "chunk-count-huge": h.set("chunkCount", struct.pack("<i", top)) if h.get("chunkCount") else None,
        "samples-huge": h.set("samplesPerPixel", struct.pack("<i", top)) if h.get("samplesPerPixel") else None,
        "samples-negative": h.set("samplesPerPixel", struct.pack("<i", -7)) if h.get("samplesPerPixel") else None,
        "world-to-camera-nan": (h.set("worldToCamera", struct.pack("<16f", *[float("nan")] * 16))
                                if h.get("worldToCamera") else None),
        "world-to-camera-huge": (h.set("worldToCamera", struct.pack("<16f", *[3e38] * 16))
                                 if h.get("worldToCamera") else None),
    }
    out = [(name, hdr.build()) for name, hdr in cases.items() if hdr is not None]
    out += [
        ("version-1", h.build(version=(h.version & ~0xFF) | 1)),
        ("version-3", h.build(version=(h.version & ~0xFF) | 3)),
        ("flag-tiled", h.build(version=h.version | TILED_FLAG)),
        ("flag-deep", h.build(version=h.version | DEEP_FLAG)),
        ("flag-multipart", h.build(version=h.version | MULTIPART_FLAG)),
        ("flag-unknown", h.build(version=h.version | 0x10000)),
        ("flag-no-long-names", h.build(version=h.version & ~LONG_NAMES_FLAG)),
        ("size-negative", h.build(sizes={(0, "dataWindow"): -1})),
        ("size-huge", h.build(sizes={(0, "channels"): 2**31 - 1})),
        ("size-zero", h.build(sizes={(0, "dataWindow"): 0})),
        ("size-short", h.build(sizes={(0, "compression"): 0})),
    ]
    return out + _exr_table_cases(data, end)


def _exr_table_cases(data: bytes, end: int) -> list[tuple[str, bytes]]:
    """Absurd offsets in the chunk table (which begins at ``end``), and absurd leaders of the first chunk."""
    out = []
    n_offsets = (len(data) - end) // 8
    rest = data[end:]
    for name, value in (("offsets-zero", 0), ("offsets-past-end", len(data) + 10**6), ("offsets-negative", -8),
                        ("offsets-into-header", 8), ("offsets-huge", 2**62)):
        table = struct.pack("<q", value) * min(n_offsets, 4)
        out.append((name, data[:end] + table + rest[len(table):]))
    first = struct.unpack_from("<q", data, end)[0]
    if 0 < first < len(data) - 8:
        for name, y, size in (("chunk-size-huge", None, 2**31 - 1), ("chunk-size-negative", None, -5),
                              ("chunk-y-wrong", 10**6, None)):
            b = bytearray(data)
            if y is not None:
                struct.pack_into("<i", b, first, y)
            if size is not None:
                struct.pack_into("<i", b, first + 4, size)
            out.append((name, bytes(b)))
    return out


def _truncations(data: bytes, header_end: int, count: int, rng: np.random.Generator) -> list[int]:
    """``count`` offsets to cut at: half inside the header (every field boundary is near one), half after it."""
    head = np.unique(np.linspace(0, header_end + 16, count // 2, dtype=np.int64))
    tail = np.unique(rng.integers(header_end + 16, len(data), count - head.size))
    return [int(n) for n in np.concatenate([head, tail]) if n < len(data)]


def _bitflips(data: bytes, header_end: int, count: int, rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """``count`` copies with 1 to 8 bits flipped, two thirds of them in the header, where a flip changes what the
    file claims rather than a pixel."""
    out = []
    for i in range(count):
        b = bytearray(data)
        limit = header_end if i % 3 else len(data)
        positions = rng.integers(0, limit, int(rng.integers(1, 9)))
        for pos in positions:
            b[pos] ^= 1 << int(rng.integers(0, 8))
        out.append((f"{i:03d}-at-{'-'.join(str(int(p)) for p in sorted(positions)[:3])}", bytes(b)))
    return out


def exr_cases(family: str) -> list[Case]:
    bases = {name: path.read_bytes() for name, path in EXR_BASES.items()}
    rng = np.random.default_rng(sum(map(ord, family)))  # one seed per family: a family does not shift another
    out: list[tuple[str, bytes]] = []
    if family == "exr-truncated":
        for base, data in bases.items():
            end = parse_exr(data)[1]
            out += [(f"{base}-at-{n}", data[:n]) for n in _truncations(data, end, 36 * SCALE, rng)]
    elif family == "exr-bitflip":
        for base, data in bases.items():
            out += [(f"{base}-{name}", b) for name, b in _bitflips(data, parse_exr(data)[1], 40 * SCALE, rng)]
    elif family == "exr-header":
        for base, data in bases.items():
            out += [(f"{base}-{name}", b) for name, b in _exr_header_cases(base, data)]
    elif family == "exr-multipart":
        out += _multipart_cases(EXR_MULTIPART.read_bytes(), rng)
    elif family == "exr-magic":
        data = bases["kpcn"]
        out += [("empty", b""), ("magic-only", EXR_MAGIC), ("magic-version", data[:8]),
                ("wrong-magic", b"\x76\x2f\x31\x02" + data[4:]), ("png", _png(8, 8, 8, 0, bytes(64))),
                ("text", b"diffuse.R diffuse.G diffuse.B\n" * 40), ("zeros", bytes(4096)),
                ("ones", b"\xff" * 4096), ("magic-zeros", EXR_MAGIC + bytes(4096)),
                ("magic-ones", EXR_MAGIC + b"\xff" * 4096)]
        out += [(f"magic-random-{i}", EXR_MAGIC + struct.pack("<I", 2) + rng.bytes(int(rng.integers(1, 4096))))
                for i in range(10)]
    else:
        raise KeyError(family)
    return [Case(family, name, data, ".exr") for name, data in out]


def _multipart_cases(data: bytes, rng: np.random.Generator) -> list[tuple[str, bytes]]:
    """A Blender 5 file of one part per pass, cut at the end of each part's header, in the offset tables and in
    the chunks; and with parts whose windows or names disagree."""
    h, end = parse_exr(data)
    cuts, pos = [], 8
    for p, attrs in enumerate(h.parts):
        pos += sum(len(n) + len(t) + 6 + len(v) for n, t, v in attrs) + 1
        cuts += [(f"part-{p}-header-end", pos), (f"part-{p}-header-end-less-1", pos - 1)]
    cuts += [(f"offsets-{n}", n) for n in np.unique(rng.integers(end, end + 8 * 19 * 4, 8 * SCALE))]
    cuts += [(f"chunks-{n}", n) for n in np.unique(rng.integers(end + 8 * 19 * 4, len(data), 16 * SCALE))]
    out = [(name, data[:int(n)]) for name, n in cuts]
    last = len(h.parts) - 1
    (x0, y0, x1, y1) = struct.unpack("<4i", h.get("dataWindow", last))
    out += [("last-part-window-other", h.set("dataWindow", _box(x0, y0, x1 + 1, y1), last).build()),
            ("last-part-window-huge", h.set("dataWindow", _box(0, 0, 1 << 30, 1 << 30), last).build()),
            ("last-part-channels-5000", h.set("channels", _chlist(f"c{i:04d}.R" for i in range(5000)), last).build()),
            ("parts-same-name", h.set("name", h.get("name", 0), last).build()),
            ("part-without-name", h.set("name", b"", last).build()),
            ("no-multipart-flag", h.build(version=h.version & ~MULTIPART_FLAG)),
            ("chunk-count-huge", h.set("chunkCount", struct.pack("<i", 2**31 - 1), last).build()),
            ("chunk-count-negative", h.set("chunkCount", struct.pack("<i", -3), last).build())]
    return out


# --- PNG ---------------------------------------------------------------------------------------------------------

def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _png(width: int, height: int, depth: int, colour: int, raw: bytes, *, interlace: int = 0) -> bytes:
    """A PNG of rows ``raw`` (each already with its filter byte) whose IHDR says what the arguments say."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, interlace)
    return PNG_MAGIC + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw, 9)) + _chunk(b"IEND", b"")


def png_bases() -> dict[str, bytes]:
    """Small PNGs both PNG readers take: a 16-bit grey ramp (a λ map), and grey as 8-bit RGB (an environment
    map, and a λ map saved as colour)."""
    h, w = 8, 12
    grey = (np.add.outer(np.arange(h) * 4000, np.arange(w) * 2000) % 65536).astype(">u2")
    rgb = np.repeat((np.add.outer(np.arange(h) * 16, np.arange(w) * 8) % 256).astype(np.uint8)[..., None], 3, -1)
    rows16 = b"".join(b"\0" + row.tobytes() for row in grey)
    rows8 = b"".join(b"\0" + row.tobytes() for row in rgb)
    return {"grey16": _png(w, h, 16, 0, rows16), "rgb8": _png(w, h, 8, 2, rows8)}


def _png_chunks(data: bytes) -> list[tuple[int, bytes, int]]:
    """(offset, type, length) of each chunk."""
    out, pos = [], len(PNG_MAGIC)
    while pos + 8 <= len(data):
        length = struct.unpack_from(">I", data, pos)[0]
        out.append((pos, data[pos + 4:pos + 8], length))
        pos += 12 + length
    return out


def png_huge() -> list[tuple[str, bytes]]:
    """Headers that claim far more pixels than the file holds (74 bytes for 30000 x 30000)."""
    return [(f"{w}x{h}", _png(w, h, 8, 0, b"\0\0")) for w, h in
            ((30000, 30000), (9600, 9600), (2**31 - 1, 1), (1, 2**31 - 1), (65535, 65535))]


def png_cases(family: str) -> list[Case]:
    bases = png_bases()
    rng = np.random.default_rng(sum(map(ord, family)))
    out: list[tuple[str, bytes]] = []
    if family == "png-truncated":
        for base, data in bases.items():
            cuts = np.unique(np.concatenate([np.arange(0, 60), rng.integers(60, len(data), 14 * SCALE)]))
            out += [(f"{base}-at-{n}", data[:int(n)]) for n in cuts if n < len(data)]
    elif family == "png-bitflip":
        for base, data in bases.items():
            out += [(f"{base}-{name}", b) for name, b in _bitflips(data, 33, 24 * SCALE, rng)]
    elif family == "png-header":
        for base, data in bases.items():
            ihdr_body = data[16:29]
            w, h, depth, colour = struct.unpack(">IIBB", ihdr_body[:10])
            idat = data[33:]
            for name, body in (("width-0", struct.pack(">II", 0, h) + ihdr_body[8:]),
                               ("height-0", struct.pack(">II", w, 0) + ihdr_body[8:]),
                               ("width-2x", struct.pack(">II", w * 2, h) + ihdr_body[8:]),
                               ("height-2x", struct.pack(">II", w, h * 2) + ihdr_body[8:]),
                               ("depth-3", ihdr_body[:8] + bytes([3]) + ihdr_body[9:]),
                               ("depth-0", ihdr_body[:8] + bytes([0]) + ihdr_body[9:]),
                               ("colour-5", ihdr_body[:9] + bytes([5]) + ihdr_body[10:]),
                               ("colour-palette", ihdr_body[:9] + bytes([3]) + ihdr_body[10:]),
                               ("compression-1", ihdr_body[:10] + b"\x01" + ihdr_body[11:]),
                               ("filter-1", ihdr_body[:11] + b"\x01" + ihdr_body[12:]),
                               ("interlace-1", ihdr_body[:12] + b"\x01"),
                               ("interlace-7", ihdr_body[:12] + b"\x07"),
                               ("ihdr-short", ihdr_body[:9])):
                out.append((f"{base}-{name}", PNG_MAGIC + _chunk(b"IHDR", body) + idat))
            out += [(f"{base}-no-idat", data[:33] + _chunk(b"IEND", b"")),
                    (f"{base}-no-ihdr", PNG_MAGIC + idat),
                    (f"{base}-idat-garbage", data[:33] + _chunk(b"IDAT", rng.bytes(200)) + _chunk(b"IEND", b"")),
                    (f"{base}-idat-short", data[:33] + _chunk(b"IDAT", zlib.compress(b"\0" * 10))
                     + _chunk(b"IEND", b"")),
                    (f"{base}-chunk-length-huge", data[:33] + struct.pack(">I", 2**31 - 1) + data[37:]),
                    (f"{base}-filter-byte-9", data[:33] + _chunk(b"IDAT", zlib.compress(b"\x09" * 500))
                     + _chunk(b"IEND", b""))]
    elif family == "png-crc":
        for base, data in bases.items():
            for pos, kind, length in _png_chunks(data):
                at = pos + 8 + length
                b = bytearray(data)
                b[at] ^= 0xFF
                out.append((f"{base}-{kind.decode()}-crc", bytes(b)))
                b = bytearray(data)
                b[pos + 8 + length // 2] ^= 0x10  # the body changed, the CRC not
                out.append((f"{base}-{kind.decode()}-body", bytes(b)))
    elif family == "png-magic":
        data = bases["grey16"]
        out += [("empty", b""), ("magic-only", PNG_MAGIC), ("wrong-magic", b"\x89PNX" + data[4:]),
                ("exr", EXR_BASES["kpcn"].read_bytes()[:2000]), ("text", b"grey\n" * 100), ("zeros", bytes(512)),
                ("magic-random", PNG_MAGIC + rng.bytes(300))]
    elif family == "png-huge":
        out += png_huge()
    else:
        raise KeyError(family)
    return [Case(family, name, data, ".png") for name, data in out]


EXR_FAMILIES = ("exr-truncated", "exr-bitflip", "exr-header", "exr-multipart", "exr-magic")
PNG_FAMILIES = ("png-truncated", "png-bitflip", "png-header", "png-crc", "png-magic", "png-huge")


def cases(family: str) -> list[Case]:
    return exr_cases(family) if family.startswith("exr") else png_cases(family)


# --- the child: each case through each reader --------------------------------------------------------------------

def _read_exr_low(path):
    from prep import exr

    image = exr.read_image(path)
    return [image.channels[n] for n in image.channels], image.size


def _read_header(path):
    from prep import layouts

    return [], layouts.read_header(path).size


def _read_frame(path):
    from prep import layouts

    frame = layouts.read(path)
    return list(frame.layers.values()), frame.size


PNG_SHAPE = (8, 12)  # the PNG bases' size: a map read intact is taken at its size


def _read_slope_map(path):
    from kpcn_keras import slope_map

    return [slope_map.read(path, PNG_SHAPE, (0.25, 4.0))], PNG_SHAPE


def _read_environment(path):
    from prep.render.environment import load_texels
    from prep.render.scene import EnvironmentMap

    texels = load_texels(EnvironmentMap(image=str(path)))
    return [texels], texels.shape[:2]


READERS = {".exr": {"exr.read_image": _read_exr_low, "layouts.read_header": _read_header,
                    "layouts.read": _read_frame},
           ".png": {"slope_map.read": _read_slope_map, "environment.load_texels": _read_environment}}


def _limit_memory() -> int:
    import resource

    with open("/proc/self/statm") as f:
        mapped = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    limit = mapped + MEMORY_MARGIN
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    return limit


def _one(reader, path: Path) -> dict:
    import time
    import warnings

    from prep.errors import KpcnError

    start = time.process_time()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            arrays, size = reader(path)
            finite = all(bool(np.all(np.isfinite(a))) for a in arrays)
            shapes = all(a.shape[:2] == tuple(size) for a in arrays)
            outcome, message = "result", "" if finite and shapes else f"finite={finite} shape ok={shapes}"
        except KpcnError as exc:
            outcome, message = "kpcn-error", str(exc)
        except BaseException as exc:  # what a user would see as a traceback
            outcome, message = "other", f"{type(exc).__module__}.{type(exc).__name__}: {exc}"[:500]
    return {"outcome": outcome, "message": message, "cpu": time.process_time() - start,
            "warnings": [f"{w.category.__name__}: {w.message}"[:300] for w in caught]}


def check(families: list[str], out: Path, workdir: Path) -> None:
    """The child: every case of each of ``families`` (of one format) through every reader of its format, one JSON
    line each in ``out``."""
    import logging
    import resource

    logging.getLogger("kpcn").addHandler(logging.NullHandler())  # a reader's notes are not errors
    logging.getLogger("kpcn").propagate = False
    # the libraries the readers load, mapped (and their import's CPU spent) before the first case
    import matplotlib.image  # noqa: F401
    import OpenEXR  # noqa: F401
    import PIL.Image  # noqa: F401

    import kpcn_keras.slope_map  # noqa: F401
    import prep.layouts  # noqa: F401
    import prep.render.environment  # noqa: F401

    all_cases = [case for family in families for case in cases(family)]
    _limit_memory()
    soft = int(len(all_cases) * 3 * CPU_LIMIT_S) + 10
    resource.setrlimit(resource.RLIMIT_CPU, (soft, soft + 5))
    with open(out, "w") as results:
        for case in all_cases:
            path = workdir / f"{case.name}{case.suffix}"
            path.write_bytes(case.data)
            for reader_name, reader in READERS[case.suffix].items():
                row = {"family": case.family, "case": case.name, "reader": reader_name, "path": str(path),
                       **_one(reader, path)}
                results.write(json.dumps(row) + "\n")
                results.flush()
            path.unlink()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", action="store_true", help="print each family's cases and readers")
    parser.add_argument("--check", metavar="FAMILY,...", help="run the child on these families (of one format)")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--workdir", type=Path)
    args = parser.parse_args(argv)
    if args.check:
        check(args.check.split(","), args.out, args.workdir)
        return 0
    total = 0
    for family in EXR_FAMILIES + PNG_FAMILIES:
        n = len(cases(family))
        readers = len(READERS[".exr" if family.startswith("exr") else ".png"])
        total += n * readers
        print(f"{family:16s} {n:5d} cases x {readers} readers")
    print(f"{'total':16s} {total:5d} reads (KPCN_FUZZ_SCALE={SCALE})")
    return 0


if __name__ == "__main__":
    sys.path.insert(0, str(REPO))
    sys.exit(main())
