"""Where patches are cut (seed report §2.1, Fig. 3; §3.3.2).

A per-pixel importance map (variance-based, or a model's error map for error-based rounds) becomes
a PDF over patch positions: the importance summed over each P x P window, normalised, and mixed
with a uniform PDF so that flat regions are still seen. Positions are drawn without replacement,
in the order of successive sampling (each draw from the PDF renormalised over what is left).
"""

from __future__ import annotations

import numba
import numpy as np

# Keeps the variance ratio finite on black pixels; the same constant as the relative-variance features.
IMPORTANCE_EPS = 0.01


def variance_importance(aovs: dict[str, np.ndarray], colour_weight: float = 1.0, normal_weight: float = 1.0) -> np.ndarray:
    """Per-pixel importance: colour_weight * relative colour variance + normal_weight * normal variance.

    The colour term is colorVariance / (mean(default)^2 + IMPORTANCE_EPS), so that dark noisy regions
    count as much as bright ones; the normal term is the normal buffer's variance (geometry edges).
    """
    if colour_weight < 0 or normal_weight < 0 or colour_weight + normal_weight <= 0:
        raise ValueError(
            f"weights must be >= 0 and not both 0, got colour_weight={colour_weight}, normal_weight={normal_weight}"
        )
    mean = np.mean(np.maximum(aovs["default"].astype(np.float64), 0.0), axis=-1)
    colour = np.maximum(aovs["colorVariance"].astype(np.float64), 0.0) / (mean * mean + IMPORTANCE_EPS)
    normal = np.maximum(aovs["normalVariance"].astype(np.float64), 0.0)
    return colour_weight * colour + normal_weight * normal


@numba.njit(cache=True)
def _window_sums(image, size):
    """Sum of ``image`` (finite, >= 0) over every size x size window; output (H - size + 1, W - size + 1).

    Summed directly, along rows then along columns (O(H W size)), not as differences of an integral
    image: those cancel catastrophically when one pixel is many orders of magnitude above the rest (a
    firefly's variance), which zeroed or corrupted every window below and right of it. Sums of
    non-negative terms keep a relative error below 2 * size * machine epsilon.
    """
    h, w = image.shape
    oh, ow = h - size + 1, w - size + 1
    rows = np.zeros((h, ow))
    for y in range(h):
        for x in range(ow):
            s = 0.0
            for i in range(size):
                s += image[y, x + i]
            rows[y, x] = s
    out = np.zeros((oh, ow))
    for y in range(oh):
        for x in range(ow):
            s = 0.0
            for i in range(size):
                s += rows[y + i, x]
            out[y, x] = s
    return out


def patch_pdf(importance: np.ndarray, patch_size: int, uniform_mix: float = 0.1) -> np.ndarray:
    """PDF over top-left patch positions, shape (H - P + 1, W - P + 1), float64, sums to 1.

    ``uniform_mix`` of the mass is spread uniformly; the rest follows the windowed importance. An
    importance map that is zero (or non-finite) everywhere gives the uniform PDF.
    """
    importance = np.asarray(importance, dtype=np.float64)
    h, w = importance.shape
    if not 1 <= patch_size <= min(h, w):
        raise ValueError(f"patch_size must be in [1, {min(h, w)}] for a {w}x{h} image, got {patch_size}")
    if not 0.0 <= uniform_mix <= 1.0:
        raise ValueError(f"uniform_mix must be in [0, 1], got {uniform_mix}")
    importance = np.where(np.isfinite(importance), np.maximum(importance, 0.0), 0.0)
    peak = importance.max()
    if peak > 0.0:
        importance = importance / peak  # the PDF is scale-free; values <= 1 cannot overflow the sums
    sums = _window_sums(np.ascontiguousarray(importance), patch_size)
    uniform = np.full(sums.shape, 1.0 / sums.size)
    total = sums.sum()
    if not np.isfinite(total) or total <= 0.0:
        return uniform
    return uniform_mix * uniform + (1.0 - uniform_mix) * (sums / total)


def mix_pdfs(error_pdf: np.ndarray, variance_pdf: np.ndarray, error_weight: float) -> np.ndarray:
    """Error-based rounds (seed §3.3.2): ``error_weight`` * error PDF + the rest * variance PDF."""
    if error_pdf.shape != variance_pdf.shape:
        raise ValueError(f"PDF shapes differ: error {error_pdf.shape}, variance {variance_pdf.shape}")
    if not 0.0 <= error_weight <= 1.0:
        raise ValueError(f"error_weight must be in [0, 1], got {error_weight}")
    return error_weight * error_pdf + (1.0 - error_weight) * variance_pdf


def draw_positions(pdf: np.ndarray, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` distinct positions (y, x) drawn without replacement from ``pdf``; int32 (count, 2).

    Uses exponential keys (Efraimidis-Spirakis): the ``count`` smallest of -log(u) / p have the law of
    successive sampling. Positions of zero probability are never drawn; asking for more positions than
    have non-zero probability is an error.
    """
    pdf = np.asarray(pdf, dtype=np.float64)
    flat = pdf.ravel()
    if np.any(~np.isfinite(flat)) or np.any(flat < 0):
        raise ValueError("pdf must be finite and non-negative")
    support = int(np.count_nonzero(flat))
    if not 0 <= count <= support:
        raise ValueError(f"count must be in [0, {support}] (positions with non-zero probability), got {count}")
    u = rng.random(flat.size)
    with np.errstate(divide="ignore"):
        # log(-log1p(-u) / p), the same order: the ratio itself overflows to inf for a tiny p (1e-310),
        # which tied such positions with the zero-probability ones (key inf) and drew those instead
        keys = np.where(flat > 0, np.log(-np.log1p(-u)) - np.log(np.where(flat > 0, flat, 1.0)), np.inf)
    chosen = np.argpartition(keys, count - 1)[:count] if count else np.empty(0, dtype=np.int64)
    chosen = chosen[np.argsort(keys[chosen], kind="stable")]
    ys, xs = np.unravel_index(chosen, pdf.shape)
    return np.stack([ys, xs], axis=1).astype(np.int32)
