"""Denoisers to compare the networks with, at the same input spp: non-local means (always there) and Intel
Open Image Denoise (the yardstick users hold up; the optional ``pyoidn`` package, ``pip install '.[oidn]'``).
"""

from __future__ import annotations

import numpy as np

from prep.colour import linear_colour, log_colour, log_variance


def nlm_denoise(colour: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """scikit-image non-local means on the colour alone, in the log(1 + x) domain, back to linear.

    The filter is told the true noise level: sigma is the RMS over the image of the render's own
    per-pixel standard deviation (``colorVariance``) carried into the log domain by the delta method,
    sqrt(var) / (1 + x). Settings follow scikit-image's guide: h = 0.8 sigma, 5x5 patches, search
    radius 6.
    """
    from skimage.restoration import denoise_nl_means

    x = np.maximum(np.asarray(colour, dtype=np.float64), 0.0)
    log_c = log_colour(x)
    var_log = log_variance(np.maximum(np.asarray(variance, dtype=np.float64), 0.0)[..., None], x)
    sigma = float(np.sqrt(np.mean(var_log)))
    out = denoise_nl_means(
        log_c, h=0.8 * sigma, sigma=sigma, patch_size=5, patch_distance=6, fast_mode=True, channel_axis=-1
    )
    return linear_colour(out).astype(np.float32)


def oidn_available() -> bool:
    """Whether Intel Open Image Denoise can run here (the optional ``pyoidn`` package is installed)."""
    import importlib.util

    return importlib.util.find_spec("pyoidn") is not None


def oidn_denoise(aovs: dict[str, np.ndarray]) -> np.ndarray:
    """Intel Open Image Denoise's ``RT`` filter, high quality, on the HDR colour with the albedo and normal
    layers of the same render as its auxiliary inputs (OIDN prefilters them: they are noisy too).

    OIDN wants non-negative linear HDR colour, albedo in [0, 1] and normals in [-1, 1]; the layers are
    clipped to that. ImportError (naming the package) if ``pyoidn`` is not installed.
    """
    try:
        import pyoidn
    except ImportError:
        raise ImportError("Intel Open Image Denoise needs the optional package pyoidn: pip install '.[oidn]'") from None

    def layer(name, lo, hi):
        return np.ascontiguousarray(np.clip(np.nan_to_num(aovs[name]), lo, hi), dtype=np.float32)

    colour = layer("default", 0.0, np.finfo(np.float32).max)
    return pyoidn.denoise(colour, albedo=layer("albedo", 0.0, 1.0), normal=layer("normal", -1.0, 1.0), hdr=True)
