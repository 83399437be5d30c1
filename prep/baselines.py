"""Classical denoisers to compare the networks with, at the same input spp."""

from __future__ import annotations

import numpy as np


def nlm_denoise(colour: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """scikit-image non-local means on the colour alone, in the log(1 + x) domain, back to linear.

    The filter is told the true noise level: sigma is the RMS over the image of the render's own
    per-pixel standard deviation (``colorVariance``) carried into the log domain by the delta method,
    sqrt(var) / (1 + x). Settings follow scikit-image's guide: h = 0.8 sigma, 5x5 patches, search
    radius 6.
    """
    from skimage.restoration import denoise_nl_means

    x = np.maximum(np.asarray(colour, dtype=np.float64), 0.0)
    log_c = np.log1p(x)
    var_log = np.maximum(np.asarray(variance, dtype=np.float64), 0.0)[..., None] / (1.0 + x) ** 2
    sigma = float(np.sqrt(np.mean(var_log)))
    out = denoise_nl_means(
        log_c, h=0.8 * sigma, sigma=sigma, patch_size=5, patch_distance=6, fast_mode=True, channel_axis=-1
    )
    return np.expm1(out).astype(np.float32)
