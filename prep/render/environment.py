"""Environment maps: the latitude-longitude mapping, the procedural sky, image loading, and the tables
the kernels sample a map with.

The mapping (``scene.py`` states it for users): texel (row i, column j) of an H x W map covers polar
angles theta in [i, i + 1) pi / H from +y and azimuths phi in [j, j + 1) 2 pi / W - pi about y from +x
towards +z; the direction of (theta, phi) is (sin theta cos phi, cos theta, sin theta sin phi).
``tracer.py`` mirrors the mapping and the sampling below in numba (a test checks its texel of each
direction of :func:`texel_directions`).

Sampling is piecewise constant over the texels in proportion to luminance x sin theta (the texel's solid
angle up to a constant), by a marginal CDF over rows and a conditional CDF per row; within a texel the
point is uniform in (theta, phi). The density of a direction in texel (i, j) is ``pdf[i, j] / (2 pi^2
sin theta)`` with ``pdf`` the density over the unit square of (phi, theta) that :func:`sampling_tables`
returns.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from prep.errors import InputFileError, KpcnError
from prep.render.scene import EnvironmentMap, Sky, _luminance

# scene._luminance's weights as a vector, for luminance of whole maps as one product
LUMINANCE = np.array([_luminance(e) for e in np.eye(3)])
# Sky glow around the sun: a fraction of the sun's radiance, falling off over this angle (radians).
_GLOW, _GLOW_ANGLE = 2e-3, math.radians(8.0)


def texel_directions(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """(unit direction of each texel centre (H, W, 3), sin theta of each row (H,))."""
    theta = (np.arange(height) + 0.5) * math.pi / height
    phi = (np.arange(width) + 0.5) * 2 * math.pi / width - math.pi
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    d = np.stack([st * np.cos(phi)[None, :], np.broadcast_to(ct, (height, width)), st * np.sin(phi)[None, :]],
                 axis=-1)
    return d, np.sin(theta)


def bake_sky(sky: Sky) -> np.ndarray:
    """The (height, 2 height, 3) float64 radiance of ``sky`` at its texel centres."""
    d, _ = texel_directions(sky.height, 2 * sky.height)
    el, az = math.radians(sky.sun_elevation), math.radians(sky.sun_azimuth)
    sun_dir = np.array([math.cos(el) * math.cos(az), math.sin(el), math.cos(el) * math.sin(az)])
    up = np.clip(d[..., 1:2], 0.0, 1.0)
    above = np.asarray(sky.horizon) + (np.asarray(sky.zenith) - np.asarray(sky.horizon)) * np.sqrt(up)
    angle = np.arccos(np.clip(d @ sun_dir, -1.0, 1.0))[..., None]
    above = above + np.asarray(sky.sun) * _GLOW * np.exp(-angle / _GLOW_ANGLE)
    out = np.where(d[..., 1:2] >= 0.0, above, np.asarray(sky.ground))
    return np.where(angle <= math.radians(sky.sun_radius), np.asarray(sky.sun), out)


SRGB_GAMMA = 2.2


def load_image(path: str) -> np.ndarray:
    """(H, W, 3) linear float64 texels of a PNG (an environment map or an image texture; sRGB decoded with gamma
    2.2); InputFileError naming the file, for one whose structure is damaged (``prep.png.check``) or whose header
    claims more pixels than PIL decodes without suspecting a decompression bomb (``PIL.Image.MAX_IMAGE_PIXELS``),
    before decoding."""
    import matplotlib.image
    from PIL import Image

    from prep.png import check

    try:
        width, height = check(path)
    except KpcnError as exc:
        raise InputFileError(str(exc)) from None
    if width * height > Image.MAX_IMAGE_PIXELS:
        raise InputFileError(f"{path}: a PNG of {width} x {height} pixels, more than the {Image.MAX_IMAGE_PIXELS} "
                             "kpcn decodes from a PNG (PIL's decompression-bomb limit); an environment map may be an "
                             ".exr of any size")
    try:
        image = np.asarray(matplotlib.image.imread(path), dtype=np.float64)
    except (OSError, SyntaxError, ValueError, EOFError) as exc:
        raise InputFileError(f"{path}: not a readable PNG image ({exc})") from None
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    if image.ndim != 3 or image.shape[2] < 3 or image.size == 0:
        raise InputFileError(f"{path}: expected an RGB image, found shape {image.shape}")
    return np.clip(image[..., :3], 0.0, 1.0) ** SRGB_GAMMA


def load_texels(env: EnvironmentMap) -> np.ndarray:
    """The (H, W, 3) float64 radiance texels of ``env`` (scale applied); InputFileError naming an image
    file that cannot be read or is not an RGB map with finite, non-negative texels."""
    if env.sky is not None:
        texels = bake_sky(env.sky)
    else:
        path = Path(env.image)
        if path.suffix.lower() == ".exr":
            from prep.exr import AOVError, read_rgb

            try:
                texels = read_rgb(path).astype(np.float64)
            except AOVError as exc:
                raise InputFileError(str(exc)) from None
        else:
            texels = load_image(str(path))
        if texels.shape[0] < 2 or texels.shape[1] < 2:
            raise InputFileError(f"{path}: an environment map needs at least 2 x 2 texels, found "
                                 f"{texels.shape[1]} x {texels.shape[0]}")
        if not np.all(np.isfinite(texels)) or texels.min() < 0:
            raise InputFileError(f"{path}: environment texels must be finite and >= 0, found values from "
                                 f"{np.nanmin(texels):g} to {np.nanmax(texels):g}")
    return np.ascontiguousarray(texels * env.scale, dtype=np.float64)


def sampling_tables(texels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """(pdf (H, W) over the unit square of (phi, theta), row CDF (H,), column CDF per row (H, W), mean
    radiance luminance over the sphere). A black map gives zero tables (it is never sampled)."""
    height, width = texels.shape[:2]
    _, sin_t = texel_directions(height, width)
    lum = texels @ LUMINANCE
    weight = lum * sin_t[:, None]
    total = float(weight.sum())
    mean_lum = total / float(sin_t.sum() * width)
    if not total > 0:
        return np.zeros((height, width)), np.zeros(height), np.zeros((height, width)), 0.0
    rows = weight.sum(axis=1)
    row_cdf = np.cumsum(rows) / total
    row_cdf[-1] = 1.0
    with np.errstate(invalid="ignore", divide="ignore"):
        col_cdf = np.cumsum(weight, axis=1) / rows[:, None]
    col_cdf = np.where(rows[:, None] > 0, col_cdf, 0.0)
    col_cdf[rows > 0, -1] = 1.0
    pdf = weight * (height * width / total)
    return pdf, row_cdf, col_cdf, mean_lum

