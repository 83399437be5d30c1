"""Image error metrics of design.md "Measuring", on linear HDR colour (H, W, 3).

- MSE: mean((x - r)^2).
- relMSE (MrSE): mean((x - r)^2 / (r^2 + RELMSE_EPS)), per channel.
- SMAPE: mean(|x - r| / (|x| + |r| + SMAPE_EPS)).
- DSSIM: (1 - SSIM) / 2 on tonemapped images (``tonemap``), SSIM over the three channels.
- PSNR: 10 log10(1 / MSE) on tonemapped images (peak 1).
All are computed in float64.
"""

from __future__ import annotations

import numpy as np

RELMSE_EPS = 1e-2
SMAPE_EPS = 1e-2
METRICS = ("mse", "relmse", "smape", "dssim", "psnr")


def tonemap(x: np.ndarray) -> np.ndarray:
    """Display transform: Reinhard x / (1 + x) of max(x, 0), then gamma 1/2.2; values in [0, 1]."""
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    return (x / (1.0 + x)) ** (1.0 / 2.2)


def _pair(x, r):
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if x.shape != r.shape:
        raise ValueError(f"image and reference shapes differ: {x.shape} vs {r.shape}")
    return x, r


def mse(x, r) -> float:
    x, r = _pair(x, r)
    return float(np.mean((x - r) ** 2))


def relmse(x, r) -> float:
    x, r = _pair(x, r)
    return float(np.mean((x - r) ** 2 / (r * r + RELMSE_EPS)))


def smape(x, r) -> float:
    x, r = _pair(x, r)
    return float(np.mean(np.abs(x - r) / (np.abs(x) + np.abs(r) + SMAPE_EPS)))


def dssim(x, r) -> float:
    from skimage.metrics import structural_similarity

    x, r = _pair(x, r)
    ssim = structural_similarity(tonemap(x), tonemap(r), channel_axis=-1, data_range=1.0)
    return float((1.0 - ssim) / 2.0)


def psnr(x, r) -> float:
    x, r = _pair(x, r)
    err = np.mean((tonemap(x) - tonemap(r)) ** 2)
    return float("inf") if err == 0 else float(10.0 * np.log10(1.0 / err))


def all_metrics(x, r) -> dict[str, float]:
    return {"mse": mse(x, r), "relmse": relmse(x, r), "smape": smape(x, r), "dssim": dssim(x, r), "psnr": psnr(x, r)}
