"""λ maps: the per-pixel slope of the asymmetric loss, for a network with a loss-specialisation module
(``ModelConfig.slope_module``; Vogels et al. 2018 §5.3; docs/denoise.md §6).

- **Training maps** (:func:`draw`): per patch, with probability :data:`CONSTANT_SHARE` one λ for the whole
  patch (log-uniform in the run's ``slope_range``, as a uniform-λ network draws it), else a smooth map: log λ
  drawn log-uniform at the nodes of a coarse grid of :data:`GRID_NODES` nodes a side, spanning the patch
  corner to corner, bilinearly interpolated between them (:func:`bilinear`), so that λ varies inside a patch
  as a painted map does and every value stays within the range.
- **Painted maps** (:func:`read`): a one-channel OpenEXR file holds λ itself, each value finite and within
  the run's range (a value outside it is refused, not clipped: the network never learned it); a greyscale
  PNG (8 or 16 bit) maps grey g in [0, 1] to λ = low (high / low)^g, log-linear as the training draws, so
  black is the range's low end, white its high end and mid grey its geometric middle. A map of another size
  than the frame is resized in log λ (:func:`bilinear`) when its aspect ratio matches the frame's to within
  a pixel, and refused otherwise. A map's size is read from its header before its pixels: one larger than
  twice the frame's sides (or 4096 a side, for a small frame) is refused before it is decoded (a PNG of a few
  bytes may claim 30000×30000). Errors are one line naming the file and what was found.
"""

from __future__ import annotations

import os
import struct
import warnings
from pathlib import Path

import numpy as np

from prep.errors import KpcnError

CONSTANT_SHARE = 0.5  # training patches with one λ: the uniform case stays as well learned as before
GRID_NODES = (2, 4)  # nodes a side of a training map's coarse grid, inclusive: a ramp up to a few bumps
PNG_SUFFIXES = (".png",)
EXR_SUFFIXES = (".exr",)
# a map's sides: at most twice the frame's (a map painted at a screen's double density), or this many pixels a
# side for a small frame; a larger map is refused from its header, before its pixels are decoded
MAP_SIDE_FACTOR, MAP_SIDE_FLOOR = 2, 4096
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def bilinear(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``values`` (h, w) resampled to ``shape`` (H, W) by bilinear interpolation with the corners aligned
    (the first and last pixel of each axis keep their values), float64; separable, as ``np.interp`` per axis."""
    values = np.asarray(values, np.float64)
    h, w = values.shape
    height, width = shape
    ys, xs = np.linspace(0.0, h - 1.0, height), np.linspace(0.0, w - 1.0, width)
    rows = np.stack([np.interp(xs, np.arange(w), row) for row in values])  # (h, W)
    return np.stack([np.interp(ys, np.arange(h), col) for col in rows.T], axis=1)  # (H, W)


def draw(rng: np.random.Generator, size: int, slope_range: tuple[float, float]) -> np.ndarray:
    """One training map (``size``, ``size``) of λ in ``slope_range`` (float32; the module docstring)."""
    lo, hi = np.log(slope_range)
    if rng.random() < CONSTANT_SHARE:
        return np.full((size, size), np.exp(rng.uniform(lo, hi)), np.float32)
    gy, gx = rng.integers(GRID_NODES[0], GRID_NODES[1] + 1, size=2)
    nodes = rng.uniform(lo, hi, (gy, gx))
    return np.exp(bilinear(nodes, (size, size))).astype(np.float32)


def is_map(slope) -> bool:
    """Whether ``slope`` is a map (an array of λ per pixel) rather than one λ (a number, or None)."""
    return slope is not None and np.ndim(slope) > 0


def range_error(slopes, slope_range: tuple[float, float]) -> str | None:
    """None if every λ of ``slopes`` is finite and within ``slope_range``, else what was found, one line (a
    value outside the range is refused, not clipped: the network never learned it)."""
    slopes = np.asarray(slopes, np.float64)
    lo, hi = slope_range
    if np.all(np.isfinite(slopes)) and slopes.min() >= lo and slopes.max() <= hi:
        return None
    finite = slopes[np.isfinite(slopes)]
    found = f"{finite.min():g} to {finite.max():g}" if finite.size else "no finite value"
    return (f"λ must lie within the run's trained range [{lo:g}, {hi:g}]; found {found}"
            + ("" if finite.size == slopes.size else f" and {slopes.size - finite.size} non-finite"))


def from_grey(grey: np.ndarray, slope_range: tuple[float, float]) -> np.ndarray:
    """λ (float64) of grey levels in [0, 1]: low (high / low)^g, log-linear over ``slope_range``."""
    lo, hi = np.log(np.asarray(slope_range, np.float64))
    return np.exp(lo + np.asarray(grey, np.float64) * (hi - lo))


def to_grey(slopes: np.ndarray, slope_range: tuple[float, float]) -> np.ndarray:
    """The inverse of :func:`from_grey`: grey levels in [0, 1] (float64) of λ, clipped to ``slope_range``."""
    lo, hi = np.log(np.asarray(slope_range, np.float64))
    return np.clip((np.log(np.asarray(slopes, np.float64)) - lo) / (hi - lo), 0.0, 1.0)


def png_bytes(slopes: np.ndarray, slope_range: tuple[float, float]) -> bytes:
    """A λ map as a 16-bit greyscale PNG over ``slope_range`` (what :func:`read` reads back, to 1/65535 of the
    range in log λ)."""
    import io

    from PIL import Image

    grey = np.round(to_grey(slopes, slope_range) * 65535.0).astype(np.uint16)
    buffer = io.BytesIO()
    Image.fromarray(grey).save(buffer, format="PNG")
    return buffer.getvalue()


def size_limit(shape: tuple[int, int]) -> tuple[int, int]:
    """The largest (H, W) of a map for a frame of ``shape`` (H, W): :data:`MAP_SIDE_FACTOR` times its sides, or
    :data:`MAP_SIDE_FLOOR` a side where that is more."""
    return tuple(max(MAP_SIDE_FACTOR * int(side), MAP_SIDE_FLOOR) for side in shape)


def _check_size(path: Path, size: tuple[int, int] | None, shape: tuple[int, int]) -> None:
    """KpcnError, one line stating the limit, for a map of ``size`` (H, W, from its header; None: unknown, left to
    the reader) larger than :func:`size_limit` allows a frame of ``shape``."""
    limit = size_limit(shape)
    if size is not None and (size[0] > limit[0] or size[1] > limit[1]):
        raise KpcnError(f"{path}: a λ map of {size[1]}×{size[0]} pixels for a frame of {shape[1]}×{shape[0]}: a map "
                        f"may be at most {limit[1]}×{limit[0]} (twice the frame's sides, or {MAP_SIDE_FLOOR} a "
                        "side); paint it at the frame's size")


def _png_size(path: Path) -> tuple[int, int] | None:
    """(H, W) as the PNG's header (IHDR, its first chunk) states them; None for a file that does not begin as a
    PNG (the reader then says what it is)."""
    with open(path, "rb") as f:
        head = f.read(24)
    if len(head) < 24 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    width, height = struct.unpack(">II", head[16:24])
    return height, width


def _grey(path: Path) -> np.ndarray:
    """A greyscale PNG's pixels as g in [0, 1] (float64); KpcnError naming the file for anything else."""
    from PIL import Image, UnidentifiedImageError

    from prep.png import check

    check(path)  # a damaged structure is refused before PIL trusts its lengths
    try:
        # its size was checked against the frame's (_check_size): PIL's own bound is no news to a user, and an
        # image past it (a frame of over 6000 pixels a side) is refused in one line
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", Image.DecompressionBombWarning)
            with Image.open(path) as image:
                mode = image.mode
                pixels = np.asarray(image)
    except Image.DecompressionBombError:
        raise KpcnError(f"{path}: a λ map of more pixels than the PNG reader decodes ({2 * Image.MAX_IMAGE_PIXELS}); "
                        "paint it at the frame's size") from None
    except (OSError, UnidentifiedImageError, ValueError, SyntaxError, EOFError) as exc:
        raise KpcnError(f"{path}: not a readable PNG ({exc})") from None
    if mode in ("L", "LA"):
        return (pixels[..., 0] if mode == "LA" else pixels) / 255.0
    if mode in ("I;16", "I;16B", "I"):
        return pixels.astype(np.float64) / 65535.0
    if mode in ("RGB", "RGBA") and np.array_equal(pixels[..., 0], pixels[..., 1]) \
            and np.array_equal(pixels[..., 0], pixels[..., 2]):
        return pixels[..., 0] / 255.0  # grey saved as colour
    raise KpcnError(f"{path}: a λ map PNG must be greyscale (8 or 16 bit); found mode {mode} with differing "
                    "colour channels")


def _exr(path: Path) -> np.ndarray:
    """A one-channel OpenEXR file's values (float64); KpcnError naming the file and its channels otherwise."""
    from prep.exr import read_image

    image = read_image(path)
    if len(image.channels) != 1:
        raise KpcnError(f"{path}: a λ map EXR must have one channel, λ itself; found "
                        f"{len(image.channels)}: {', '.join(sorted(image.channels)) or 'none'}")
    return np.asarray(next(iter(image.channels.values())), np.float64)


def read(path: str | os.PathLike, shape: tuple[int, int], slope_range: tuple[float, float]) -> np.ndarray:
    """The λ map (``shape`` = the frame's (H, W), float32) painted in ``path`` (the module docstring), for a
    run trained over ``slope_range``; KpcnError, one line naming the file, for a map it cannot take."""
    path = Path(path)
    lo, hi = (float(v) for v in slope_range)
    if not path.is_file():
        raise KpcnError(f"{path}: no such λ map file")
    suffix = path.suffix.lower()
    if suffix in PNG_SUFFIXES:
        _check_size(path, _png_size(path), shape)
        log_map = np.log(from_grey(_grey(path), (lo, hi)))
    elif suffix in EXR_SUFFIXES:
        from prep.exr import read_image

        _check_size(path, read_image(path, header_only=True).size, shape)
        slopes = _exr(path)
        outside = range_error(slopes, (lo, hi))
        if outside:
            raise KpcnError(f"{path}: {outside}")
        log_map = np.log(slopes)
    else:
        raise KpcnError(f"{path}: a λ map is a one-channel .exr (λ) or a greyscale .png (the λ range); found "
                        f"{suffix or 'no suffix'}")
    mh, mw = log_map.shape
    height, width = shape
    if (mh, mw) != (height, width):
        if abs(mh * width / mw - height) > 1.0:
            raise KpcnError(f"{path}: a λ map of {mw}×{mh} pixels for a frame of {width}×{height}: the aspect "
                            "ratios differ; paint it at the frame's size or at its aspect ratio")
        log_map = bilinear(log_map, (height, width))
    return np.exp(log_map).astype(np.float32)
