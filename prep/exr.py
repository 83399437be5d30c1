"""Reading and writing renders in the AOV layout of docs/formats.md §1 (the Tungsten/KPCN dataset layout).

A render is one multi-layer OpenEXR file whose channels are named ``<layer>.<C>``:

=================  =========  ===========================================================
layer              channels   meaning
=================  =========  ===========================================================
diffuse            R G B      radiance of paths whose first scattering is diffuse
specular           R G B      everything else (glossy, delta, emitters seen directly)
default            R G B      diffuse + specular (optional: derived when absent)
albedo             R G B      first-hit diffuse reflectance
normal             R G B      first-hit shading normal, world space, in [-1, 1]
depth              Z          distance to the first hit, 0 where the ray leaves the scene
<x>Variance        Z          variance of the pixel mean, x in diffuse, specular, color,
                              albedo, normal, depth (R G B accepted and averaged); the
                              layer of each is :data:`VARIANCE_OF`'s
=================  =========  ===========================================================

In memory a render is a dict ``layer -> float32 array`` of shape (H, W, 3) for colour layers and
(H, W) for one-channel layers.

Non-finite values are repaired by one rule, applied per channel: NaN becomes 0, +inf becomes the
largest finite value of that channel (0 if it has none) and -inf the smallest. Repairs are counted
and reported once per file through the ``kpcn`` logger. A derived ``default`` is summed in float64 and
clamped to the float32 range (:func:`to_float32`), so two finite float32 layers can never sum to inf.

Writing is atomic (``prep.files.atomic_path``); finite values beyond the range of the file's pixel type
(half or float) are clamped to its largest finite value rather than overflowing to inf. The OpenEXR library's
own messages about a corrupt file are captured and folded into the one error that names the file.
"""

from __future__ import annotations

import io
import logging
import os
import re
import sys
import tempfile
from contextlib import contextmanager, redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prep.errors import KpcnError
from prep.files import atomic_path
from prep.processes import flush_c_stdio, memory_shortfall

log = logging.getLogger("kpcn")

RGB_LAYERS = ("default", "diffuse", "specular", "albedo", "normal")
# Each layer with a variance -> the layer of its variance (of the pixel's mean, one value a pixel); the one
# place a variance layer is named from its layer, or a layer from its variance (LAYER_OF_VARIANCE).
VARIANCE_OF = {
    "diffuse": "diffuseVariance",
    "specular": "specularVariance",
    "default": "colorVariance",
    "albedo": "albedoVariance",
    "normal": "normalVariance",
    "depth": "depthVariance",
}
LAYER_OF_VARIANCE = {variance: layer for layer, variance in VARIANCE_OF.items()}
VARIANCE_LAYERS = tuple(VARIANCE_OF.values())
SCALAR_LAYERS = ("depth",) + VARIANCE_LAYERS
BASE_LAYERS = ("diffuse", "specular", "albedo", "normal", "depth")

_SUM_ROWS = 64  # rows per block of the derived default's float64 sum

_RENDER_NAME = re.compile(r"^(?P<scene>.+)-(?P<spp>\d{5,})spp\.exr$")
# the header attribute (int) that states a kpcn frame's samples per pixel where its name does not (a half of a
# pair, <scene>-<spp>spp-pair-a.exr: prep/render/blender/catalogue.pair_names); prep.layouts reads it
SPP_ATTRIBUTE = "kpcn.spp"


class AOVError(KpcnError, ValueError):
    """A render that does not follow the AOV layout; the message names the file and the layer."""


def render_filename(scene: str, spp: int) -> str:
    """``<scene>-<spp, 5 digits>spp.exr``."""
    if "/" in scene or not scene:
        raise ValueError(f"scene name must be a non-empty file name part, got {scene!r}")
    return f"{scene}-{int(spp):05d}spp.exr"


def parse_render_filename(path: str | os.PathLike) -> tuple[str, int]:
    """Inverse of :func:`render_filename`: ``(scene, spp)``; AOVError if the name does not fit."""
    name = Path(path).name
    m = _RENDER_NAME.match(name)
    if m is None:
        raise AOVError(f"{path}: file name {name!r} is not '<scene>-<spp, 5 digits>spp.exr'")
    return m.group("scene"), int(m.group("spp"))


def _group_channels(path, channels: dict) -> dict[str, dict[str, np.ndarray]]:
    layers: dict[str, dict[str, np.ndarray]] = {}
    for full_name, pixels in channels.items():
        layer, comp = _split_name(full_name)
        if pixels.ndim != 2:
            raise AOVError(f"{path}: channel {full_name!r} has shape {pixels.shape}, expected 2-D")
        layers.setdefault(layer, {})[comp] = pixels
    return layers


def _assemble(name: str, comps: dict[str, np.ndarray]) -> np.ndarray:
    """One layer as float32, (H, W, 3) or (H, W); its channels were checked by _check_layers. A float32
    channel is taken as it is, not copied (a render is read without a second copy of its pixels)."""
    if name in RGB_LAYERS:
        rgb = np.empty(comps["R"].shape + (3,), np.float32)
        for i, c in enumerate("RGB"):
            rgb[..., i] = comps[c]
        return rgb
    if "Z" in comps:
        return comps["Z"].astype(np.float32, copy=False)
    if len(comps) == 1:
        return next(iter(comps.values())).astype(np.float32, copy=False)
    return to_float32(np.mean([comps[c].astype(np.float64) for c in "RGB"], axis=0))


def to_float32(image, dtype=np.float32) -> np.ndarray:
    """``image`` cast to ``dtype`` (float32 or float16) with finite values beyond its range clamped to
    its largest finite magnitude, so that a cast never turns a finite value into inf. Non-finite values
    are kept as they are (the reader's repair rule deals with them)."""
    image = np.asarray(image, dtype=np.float64)
    big = float(np.finfo(dtype).max)
    return np.where(np.isfinite(image), np.clip(image, -big, big), image).astype(dtype)


@contextmanager
def _captured_native_output():
    """Send what native code writes to file descriptors 1 and 2 into a buffer for the block.

    The OpenEXR library prints its own diagnostics for corrupt files; the caller folds them into one
    error instead. Yields a list that holds the captured text once the block ends.
    """
    captured: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    text = io.StringIO()  # what the binding prints through Python (sys.stdout may not be fd 1)
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            with redirect_stdout(text), redirect_stderr(text):
                yield captured
        finally:
            # the binding prints through Python's and C's stdio, both buffered when fd 1 is not a tty
            sys.stdout.flush()
            sys.stderr.flush()
            flush_c_stdio()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read().decode(errors="replace"))
            captured.append(text.getvalue())


def _native_detail(path: Path, captured: list[str], exc: Exception) -> str:
    """The most telling line of what the library said: its first error code line, else the exception."""
    lines = [line.strip().removeprefix(f"{path}:").strip() for text in captured for line in text.splitlines()]
    coded = [line for line in lines if "EXR_ERR" in line]
    return coded[0] if coded else str(exc)


# Header attributes that describe a file's structure, not its content: the writer sets them itself.
STRUCTURAL_ATTRIBUTES = frozenset({"channels", "chunkCount", "compression", "dataWindow", "displayWindow",
                                   "lineOrder", "name", "type", "tiles", "version"})


@dataclass
class ExrImage:
    """What one OpenEXR file holds, every part of it: a multi-part file (Blender 5 writes one part per pass)
    reads as one set of channels. ``channels`` maps each channel's full name to its pixels (empty when read
    with ``header_only``); a name that two parts share is prefixed by the later part's name. ``attributes``
    are part 0's header attributes less the structural ones (:data:`STRUCTURAL_ATTRIBUTES`), for an output
    to carry; ``data_window`` and ``display_window`` are part 0's ((x0, y0), (x1, y1)); ``half`` names the
    channels stored as half floats."""

    path: Path
    size: tuple[int, int]
    names: tuple[str, ...]
    parts: tuple[str, ...]
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    attributes: dict = field(default_factory=dict)
    data_window: tuple = ((0, 0), (0, 0))
    display_window: tuple = ((0, 0), (0, 0))
    half: frozenset = frozenset()

    def components(self) -> dict[str, set[str]]:
        """``layer -> its component names`` (``a.b.R`` is component R of layer ``a.b``)."""
        out: dict[str, set[str]] = {}
        for name in self.names:
            layer, comp = _split_name(name)
            out.setdefault(layer, set()).add(comp)
        return out


def _window(value) -> tuple:
    lo, hi = value
    return (int(lo[0]), int(lo[1])), (int(hi[0]), int(hi[1]))


# More channels than any renderer writes (a Blender 5 file of every pass has about 80): a header claiming more is
# damaged or not a render, and refusing it bounds the time a header takes to parse and the line that lists layers.
MAX_CHANNELS = 4096
BYTES_PER_CHANNEL = 4  # a pixel of each channel as the readers hold it (float32; a half channel is widened)


def _read_parts(path: Path, header_only: bool) -> ExrImage:
    """Every part of ``path`` as the binding reads it; AOVError naming the file if the binding refuses it."""
    import OpenEXR  # imported here so that modules using only the constants stay light

    names, parts, channels, half = [], [], {}, set()
    try:
        with _captured_native_output() as captured:
            with OpenEXR.File(str(path), separate_channels=True, header_only=header_only) as f:
                # the header dict is emptied when the file closes: copy what we need inside
                header = f.parts[0].header
                attributes = {k: v for k, v in header.items() if k not in STRUCTURAL_ATTRIBUTES}
                data_window = _window(header["dataWindow"])
                display_window = _window(header.get("displayWindow", header["dataWindow"]))
                for i, part in enumerate(f.parts):
                    part_name = part.name() or f"part {i}"
                    parts.append(part_name)
                    if _window(part.header["dataWindow"]) != data_window:
                        raise AOVError(f"{path}: part {part_name!r} has data window "
                                       f"{_window(part.header['dataWindow'])}, part 0 has {data_window}")
                    listed = part.header["channels"] if header_only else part.channels.values()
                    for ch in listed:
                        name = ch.name
                        if name in names:
                            name = f"{part_name}.{name}"
                        names.append(name)
                        if not header_only:
                            channels[name] = np.asarray(ch.pixels)
                            if channels[name].dtype == np.float16:
                                half.add(name)
    except AOVError:
        raise
    except Exception as exc:  # the binding raises bare RuntimeErrors for corrupt files
        raise AOVError(f"{path}: not a readable OpenEXR file ({_native_detail(path, captured, exc)})") from None
    (x0, y0), (x1, y1) = data_window
    return ExrImage(path, (y1 - y0 + 1, x1 - x0 + 1), tuple(names), tuple(parts), channels, attributes,
                    data_window, display_window, frozenset(half))


def _check_claims(image: ExrImage) -> None:
    """AOVError naming the file if its header claims more channels than :data:`MAX_CHANNELS` or more pixels than
    this machine has memory for: refused before the binding allocates them."""
    count = len(image.names)
    if count > MAX_CHANNELS:
        raise AOVError(f"{image.path}: the header lists {count} channels, more than the {MAX_CHANNELS} a render can "
                       "have: the file is damaged or not a render")
    height, width = image.size
    short = memory_shortfall(height * width * count * BYTES_PER_CHANNEL)
    if short:
        raise AOVError(f"{image.path}: its {width}x{height} data window of {count} channels {short}")


def read_image(path: str | os.PathLike, *, header_only: bool = False) -> ExrImage:
    """Every part of the OpenEXR file ``path`` (:class:`ExrImage`); AOVError naming the file if it is not one, if
    its parts' data windows differ, if its header claims more than :func:`_check_claims` allows, or if a channel
    its header lists cannot be read (a multi-part file cut short: the binding drops those parts with a warning)."""
    path = Path(path)
    if path.is_dir():
        raise AOVError(f"{path}: is a folder, expected an OpenEXR file")
    if not path.is_file():
        raise AOVError(f"{path}: no such file")
    header = _read_parts(path, header_only=True)
    _check_claims(header)
    if header_only:
        return header
    image = _read_parts(path, header_only=False)
    lost = [name for name in header.names if name not in image.channels]
    if lost:
        raise AOVError(f"{path}: {len(lost)} of the {len(header.names)} channels its header lists could not be "
                       f"read ({', '.join(lost[:3])}{', ...' if len(lost) > 3 else ''}): the file is cut short or "
                       "damaged")
    return image


def _open(path: Path, *, header_only: bool = False):
    """(size, channel names, channels) of every part of ``path``; AOVError naming the file if unreadable."""
    image = read_image(path, header_only=header_only)
    return image.size, image.names, image.channels


def _check_layers(path, components: dict[str, set[str]], variances: bool | None) -> tuple[str, ...]:
    """The layers to read from a file whose channels are ``layer -> component names``; AOVError for a
    missing layer or a colour layer without R G B. ``variances``: True needs every variance layer, False
    reads none, None reads those present."""
    needed = BASE_LAYERS + (VARIANCE_LAYERS if variances else ())
    missing = [n for n in needed if n not in components]
    if missing:
        raise AOVError(
            f"{path}: missing layer(s) {', '.join(missing)}; the file has "
            f"{', '.join(sorted(components)) or 'no layers'}"
        )
    wanted = needed + (("default",) if "default" in components else ())
    if variances is None:
        wanted += tuple(n for n in VARIANCE_LAYERS if n in components)
    for name in wanted:
        comps = components[name]
        if name in RGB_LAYERS and not set("RGB") <= comps:
            raise AOVError(f"{path}: layer {name!r} needs channels R G B, found {sorted(comps)}")
        if name in SCALAR_LAYERS and "Z" not in comps and not set("RGB") <= comps and len(comps) != 1:
            raise AOVError(f"{path}: layer {name!r} needs one channel Z (or R G B), found {sorted(comps)}")
    return wanted


def _split_name(full_name: str) -> tuple[str, str]:
    layer, _, comp = full_name.rpartition(".")
    return layer or "default", comp  # unprefixed R, G, B is the beauty pass in many renderers


def read_header(path: str | os.PathLike, *, variances: bool | None = True) -> tuple[int, int]:
    """Check a render's header against the layout without decoding pixels; returns (height, width).

    Lets a command find a missing layer or a wrong size in every input before it writes anything.
    Raises AOVError naming the file and the layer.
    """
    path = Path(path)
    image = read_image(path, header_only=True)
    _check_layers(path, image.components(), variances)
    return image.size


def repair_nonfinite(image: np.ndarray) -> tuple[np.ndarray, int]:
    """Apply the repair rule of this module per channel; returns (repaired copy, count repaired)."""
    bad = ~np.isfinite(image)
    count = int(bad.sum())
    if count == 0:
        return image, 0
    out = image.copy()
    chans = out[..., None] if out.ndim == 2 else out
    for c in range(chans.shape[-1]):
        ch = chans[..., c]
        finite = ch[np.isfinite(ch)]
        hi = float(finite.max()) if finite.size else 0.0
        lo = float(finite.min()) if finite.size else 0.0
        ch[np.isnan(ch)] = 0.0
        ch[np.isposinf(ch)] = hi
        ch[np.isneginf(ch)] = lo
    return out, count


def repair_layers(layers: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], dict[str, int]]:
    """``layers`` with each layer repaired by :func:`repair_nonfinite` (in place of the dict's values), and the
    count repaired in each layer that had any: what :func:`repair_note` reports. The one place a set of layers
    is repaired: the files' readers (:func:`read_aovs`, ``prep.layouts``) and ``kpcn.denoise``'s arrays."""
    counts = {}
    for name in list(layers):
        layers[name], count = repair_nonfinite(layers[name])
        if count:
            counts[name] = count
    return layers, counts


def repair_note(counts: dict[str, int]) -> str:
    """The one line that reports :func:`repair_layers`' counts (``layer -> values repaired``)."""
    return ("repaired non-finite values (NaN->0, inf->channel's finite max/min): "
            + ", ".join(f"{k}: {v}" for k, v in counts.items()))


def read_aovs(path: str | os.PathLike, *, variances: bool | None = True) -> dict[str, np.ndarray]:
    """Read one render; returns ``layer -> float32 array`` with every layer of the contract.

    ``variances=False`` reads a reference render, which needs no variance layers, and reads none of them;
    ``variances=None`` reads the variance layers the file has, needing none (a reference whose convergence
    is measured: ``prep.convergence``). ``default`` is
    derived as diffuse + specular when the file has none. Raises AOVError naming the file and layer.
    """
    path = Path(path)
    expected, _, channels = _open(path)
    raw = _group_channels(path, channels)
    del channels
    wanted = _check_layers(path, {name: set(comps) for name, comps in raw.items()}, variances)
    for name in set(raw) - set(wanted):
        del raw[name]
    out: dict[str, np.ndarray] = {}
    for name in wanted:
        # each layer's channels are let go once assembled: the file's pixels and the render are never both held
        image = _assemble(name, raw.pop(name))
        if image.shape[:2] != expected:
            raise AOVError(
                f"{path}: layer {name!r} is {image.shape[1]}x{image.shape[0]}, "
                f"the data window is {expected[1]}x{expected[0]}"
            )
        out[name] = image
    out, repaired = repair_layers(out)  # layer by layer, each in place of the one read
    if "default" not in out:
        # in blocks of rows: the float64 sum of a whole frame would be the largest thing the read holds
        default = np.empty_like(out["diffuse"])
        for y in range(0, default.shape[0], _SUM_ROWS):
            rows = slice(y, y + _SUM_ROWS)
            default[rows] = to_float32(out["diffuse"][rows].astype(np.float64) + out["specular"][rows])
        out["default"] = default
    if repaired:
        log.warning("%s: %s", path, repair_note(repaired))
    return out


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """The (H, W, 3) float32 colour of an ordinary RGB EXR (an image, not a render): its unprefixed R G B
    channels, or those of layer ``default``. Non-finite values are left for the caller to judge.
    Raises AOVError naming the file."""
    path = Path(path)
    _, _, channels = _open(path)
    layers = _group_channels(path, channels)
    comps = layers.get("default", {})
    if not set("RGB") <= set(comps):
        raise AOVError(f"{path}: an RGB image needs channels R G B (unprefixed or default.R/G/B); the file has "
                       f"{', '.join(sorted(channels)) or 'no channels'}")
    return np.stack([comps[c] for c in "RGB"], axis=-1).astype(np.float32)


def write_aovs(path: str | os.PathLike, layers: dict[str, np.ndarray], *, half: bool = False,
               attributes: dict | None = None, windows: tuple | None = None) -> Path:
    """Write ``layer -> array`` as one multi-layer EXR (ZIP), atomically: a temporary name, then rename.

    Colour layers (H, W, 3) become ``layer.R/G/B``, one-channel layers (H, W) become ``layer.Z``; a layer
    ``<name>.A`` (H, W) is written as that channel (the alpha of colour layer ``name``). ``attributes``:
    header attributes to carry (an input's :attr:`ExrImage.attributes`); ``windows``: its (data window,
    display window), each ((x0, y0), (x1, y1)); the data window must be the layers' size.
    """
    import OpenEXR

    path = Path(path)
    dtype = np.float16 if half else np.float32
    channels = {}
    shape = None
    for name, image in layers.items():
        image = np.asarray(image)
        if shape is None:
            shape = image.shape[:2]
        if image.shape[:2] != shape:
            raise AOVError(f"{path}: layer {name!r} is {image.shape[:2]}, other layers are {shape}")
        # a float32 layer goes to a float32 file as it is (the binding writes (H, W, 3) as <layer>.R/G/B):
        # a frame is written without a copy of its pixels; anything else is cast and clamped channel by channel
        as_is = image.dtype == dtype == np.float32 and image.flags.c_contiguous
        if name.endswith(".A") and image.ndim == 2:
            channels[name] = np.ascontiguousarray(to_float32(image, dtype))
        elif image.ndim == 3 and image.shape[2] == 3:
            if as_is:
                channels[name] = image
            else:
                for i, c in enumerate("RGB"):
                    channels[f"{name}.{c}"] = np.ascontiguousarray(to_float32(image[..., i], dtype))
        elif image.ndim == 2:
            channels[f"{name}.Z"] = image if as_is else np.ascontiguousarray(to_float32(image, dtype))
        else:
            raise AOVError(f"{path}: layer {name!r} has shape {image.shape}, expected (H, W, 3) or (H, W)")
    header = {k: v for k, v in (attributes or {}).items() if k not in STRUCTURAL_ATTRIBUTES}
    header.update({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage})
    if windows is not None:
        (x0, y0), (x1, y1) = windows[0]
        if shape is not None and (y1 - y0 + 1, x1 - x0 + 1) != tuple(shape):
            raise AOVError(f"{path}: data window {windows[0]} is not the layers' {shape[1]}x{shape[0]}")
        for key, window in zip(("dataWindow", "displayWindow"), windows):
            header[key] = tuple(np.array(corner, np.int32) for corner in window)
    with atomic_path(path) as tmp:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
    return path
