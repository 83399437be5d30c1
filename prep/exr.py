"""Reading and writing renders in the AOV layout of design.md (the Tungsten/KPCN dataset layout).

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
                              albedo, normal, depth (R G B accepted and averaged)
=================  =========  ===========================================================

In memory a render is a dict ``layer -> float32 array`` of shape (H, W, 3) for colour layers and
(H, W) for one-channel layers.

Non-finite values are repaired by one rule, applied per channel: NaN becomes 0, +inf becomes the
largest finite value of that channel (0 if it has none) and -inf the smallest. Repairs are counted
and reported once per file through the ``kpcn`` logger.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from prep.errors import KpcnError

log = logging.getLogger("kpcn")

RGB_LAYERS = ("default", "diffuse", "specular", "albedo", "normal")
VARIANCE_LAYERS = (
    "diffuseVariance",
    "specularVariance",
    "colorVariance",
    "albedoVariance",
    "normalVariance",
    "depthVariance",
)
SCALAR_LAYERS = ("depth",) + VARIANCE_LAYERS
BASE_LAYERS = ("diffuse", "specular", "albedo", "normal", "depth")

_RENDER_NAME = re.compile(r"^(?P<scene>.+)-(?P<spp>\d{5,})spp\.exr$")


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
    for full_name, channel in channels.items():
        layer, _, comp = full_name.rpartition(".")
        if not layer:  # unprefixed R, G, B is the beauty pass in many renderers
            layer = "default"
        pixels = np.asarray(channel.pixels)
        if pixels.ndim != 2:
            raise AOVError(f"{path}: channel {full_name!r} has shape {pixels.shape}, expected 2-D")
        layers.setdefault(layer, {})[comp] = pixels
    return layers


def _assemble(path, name: str, comps: dict[str, np.ndarray]) -> np.ndarray:
    if name in RGB_LAYERS:
        missing = [c for c in "RGB" if c not in comps]
        if missing:
            raise AOVError(
                f"{path}: layer {name!r} needs channels R G B, found {sorted(comps)}"
            )
        return np.stack([comps[c] for c in "RGB"], axis=-1).astype(np.float32)
    if "Z" in comps:
        return comps["Z"].astype(np.float32)
    if all(c in comps for c in "RGB"):
        return np.mean([comps[c].astype(np.float32) for c in "RGB"], axis=0).astype(np.float32)
    if len(comps) == 1:
        return next(iter(comps.values())).astype(np.float32)
    raise AOVError(f"{path}: layer {name!r} needs one channel Z (or R G B), found {sorted(comps)}")


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


def read_aovs(path: str | os.PathLike, *, variances: bool = True) -> dict[str, np.ndarray]:
    """Read one render; returns ``layer -> float32 array`` with every layer of the contract.

    ``variances=False`` reads a reference render, which needs no variance layers. ``default`` is
    derived as diffuse + specular when the file has none. Raises AOVError naming the file and layer.
    """
    import OpenEXR  # imported here so that modules using only the constants stay light

    path = Path(path)
    if not path.is_file():
        raise AOVError(f"{path}: no such file")
    try:
        with OpenEXR.File(str(path), separate_channels=True) as f:
            # the header dict is emptied when the file closes: read what we need inside
            lo, hi = f.header()["dataWindow"]
            raw = _group_channels(path, f.channels())
    except AOVError:
        raise
    except Exception as exc:  # the binding raises bare RuntimeErrors for corrupt files
        raise AOVError(f"{path}: not a readable OpenEXR file ({exc})") from None

    expected = (int(hi[1] - lo[1] + 1), int(hi[0] - lo[0] + 1))
    needed = BASE_LAYERS + (VARIANCE_LAYERS if variances else ())
    missing = [n for n in needed if n not in raw]
    if missing:
        raise AOVError(
            f"{path}: missing layer(s) {', '.join(missing)}; the file has {', '.join(sorted(raw)) or 'no layers'}"
        )
    wanted = needed + (("default",) if "default" in raw else ())
    out: dict[str, np.ndarray] = {}
    repaired: dict[str, int] = {}
    for name in wanted:
        image = _assemble(path, name, raw[name])
        if image.shape[:2] != expected:
            raise AOVError(
                f"{path}: layer {name!r} is {image.shape[1]}x{image.shape[0]}, "
                f"the data window is {expected[1]}x{expected[0]}"
            )
        image, count = repair_nonfinite(image)
        if count:
            repaired[name] = count
        out[name] = image
    if "default" not in out:
        out["default"] = out["diffuse"] + out["specular"]
    if repaired:
        detail = ", ".join(f"{k}: {v}" for k, v in repaired.items())
        log.warning("%s: repaired non-finite values (NaN->0, inf->channel's finite max/min): %s", path, detail)
    return out


def write_aovs(path: str | os.PathLike, layers: dict[str, np.ndarray], *, half: bool = False) -> Path:
    """Write ``layer -> array`` as one multi-layer EXR (ZIP), atomically: a temporary name, then rename.

    Colour layers (H, W, 3) become ``layer.R/G/B``, one-channel layers (H, W) become ``layer.Z``.
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
        if image.ndim == 3 and image.shape[2] == 3:
            for i, c in enumerate("RGB"):
                channels[f"{name}.{c}"] = np.ascontiguousarray(image[..., i], dtype=dtype)
        elif image.ndim == 2:
            channels[f"{name}.Z"] = np.ascontiguousarray(image, dtype=dtype)
        else:
            raise AOVError(f"{path}: layer {name!r} has shape {image.shape}, expected (H, W, 3) or (H, W)")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}.exr")
    try:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp))
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path
