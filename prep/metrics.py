"""Image error metrics of docs/method.md §9 "Measuring", on linear HDR colour (H, W, 3).

- MSE: mean((x - r)^2).
- relMSE (MrSE): mean((x - r)^2 / (r^2 + RELMSE_EPS)), per channel.
- relSE p99.9 (``relse_p999``): the 99.9th percentile over pixels of the per-pixel relative squared error,
  the mean over the channels (R, G, B) of the same terms (x - r)^2 / (r^2 + RELMSE_EPS) that relMSE averages
  (``relse``, written once for both). ``np.percentile`` with its default linear interpolation: with the n
  pixel errors sorted as s[0] <= ... <= s[n-1] and p = 0.999 (n - 1), it is s[floor p] + frac(p)
  (s[floor p + 1] - s[floor p]). It is the error of the worst 0.1 % of pixels (fireflies kept or made by a
  denoiser), which the mean hides. It does not see a single pixel: on a 256x256 frame it lies between the
  67th and the 66th worst pixel's error, and the worst pixel enters it only on images of at most 1000 pixels.
- SMAPE: mean(|x - r| / (|x| + |r| + SMAPE_EPS)).
- DSSIM: (1 - SSIM) / 2 on tonemapped images (``prep.colour.tonemap``), SSIM over the three channels, with 7x7 windows
  (the largest odd window that fits on images smaller than that; one window, the whole image, below 3x3).
- PSNR: 10 log10(1 / MSE) on tonemapped images (peak 1).
All are computed in float64.
"""

from __future__ import annotations

import numpy as np

from prep.colour import tonemap

RELMSE_EPS = 1e-2
SMAPE_EPS = 1e-2
SSIM_WINDOW = 7
SSIM_K = (0.01, 0.03)  # skimage's constants, for the one-window case
RELSE_PERCENTILE = 99.9
METRICS = ("mse", "relmse", "relse_p999", "smape", "dssim", "psnr")


def _pair(x, r):
    x = np.asarray(x, dtype=np.float64)
    r = np.asarray(r, dtype=np.float64)
    if x.shape != r.shape:
        raise ValueError(f"image and reference shapes differ: {x.shape} vs {r.shape}")
    return x, r


def mse(x, r) -> float:
    x, r = _pair(x, r)
    return float(np.mean((x - r) ** 2))


def relse(x, r) -> np.ndarray:
    """Element-wise relative squared error (x - r)^2 / (r^2 + RELMSE_EPS), float64, the shape of x."""
    x, r = _pair(x, r)
    return (x - r) ** 2 / (r * r + RELMSE_EPS)


def relmse(x, r) -> float:
    return float(np.mean(relse(x, r)))


def relse_pixels(x, r) -> np.ndarray:
    """Per-pixel relative squared error: ``relse`` averaged over the channels (last axis) of (H, W, C)
    images; a 2-D image is one channel."""
    err = relse(x, r)
    return err.mean(axis=-1) if err.ndim == 3 else err


def relse_p999(x, r) -> float:
    """The RELSE_PERCENTILE-th percentile over pixels of ``relse_pixels`` (np.percentile, linear)."""
    return float(np.percentile(relse_pixels(x, r), RELSE_PERCENTILE))


def smape(x, r) -> float:
    x, r = _pair(x, r)
    return float(np.mean(np.abs(x - r) / (np.abs(x) + np.abs(r) + SMAPE_EPS)))


def dssim(x, r) -> float:
    from skimage.metrics import structural_similarity

    x, r = _pair(x, r)
    side = min(x.shape[:2])
    window = min(SSIM_WINDOW, side if side % 2 else side - 1)
    if window >= 3:
        ssim = structural_similarity(tonemap(x), tonemap(r), channel_axis=-1, data_range=1.0, win_size=window)
    else:
        ssim = _global_ssim(tonemap(x), tonemap(r))
    return float((1.0 - ssim) / 2.0)


def _global_ssim(x, r) -> float:
    """SSIM of one window covering the whole (tiny) image, per channel, averaged; data range 1."""
    c1, c2 = SSIM_K[0] ** 2, SSIM_K[1] ** 2
    axes = (0, 1)
    mx, mr = x.mean(axes), r.mean(axes)
    vx, vr = x.var(axes), r.var(axes)
    cov = ((x - mx) * (r - mr)).mean(axes)
    ssim = ((2 * mx * mr + c1) * (2 * cov + c2)) / ((mx**2 + mr**2 + c1) * (vx + vr + c2))
    return float(ssim.mean())


def psnr(x, r) -> float:
    x, r = _pair(x, r)
    err = np.mean((tonemap(x) - tonemap(r)) ** 2)
    return float("inf") if err == 0 else float(10.0 * np.log10(1.0 / err))


def all_metrics(x, r) -> dict[str, float]:
    """Every metric of METRICS, in that order."""
    return {"mse": mse(x, r), "relmse": relmse(x, r), "relse_p999": relse_p999(x, r), "smape": smape(x, r),
            "dssim": dssim(x, r), "psnr": psnr(x, r)}
