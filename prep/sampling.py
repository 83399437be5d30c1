"""Where patches are cut (docs/method.md §3, §8).

A per-pixel importance map (variance-based, or a model's error map for error-based rounds) becomes
a PDF over patch positions: the importance summed over each P x P window, normalised, and mixed
with a uniform PDF so that flat regions are still seen. Positions are drawn without replacement,
in the order of successive sampling (each draw from the PDF renormalised over what is left).

Error-based rounds (§3.3.2) take the importance from ``error_map`` (a denoised image's per-pixel
SMAPE or relMSE against its reference) through the same ``patch_pdf`` as the variance importance,
blend the two with ``mix_pdfs``, and remove the positions earlier rounds cut with
``exclude_positions`` before drawing.
"""

from __future__ import annotations

import numba
import numpy as np

from prep.exr import VARIANCE_OF
from prep.metrics import RELMSE_EPS, SMAPE_EPS

# Keeps the variance ratio finite on black pixels; the same constant as the relative-variance features.
IMPORTANCE_EPS = 0.01
# Per-pixel error maps for error-based rounds; the terms of the metrics of the same names (prep.metrics).
ERROR_METRICS = ("smape", "relmse")


def variance_importance(aovs: dict[str, np.ndarray], colour_weight: float = 1.0,
                        normal_weight: float = 1.0) -> np.ndarray:
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


def reference_error_variances(aovs: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """What :func:`variance_importance` reads, for a render that has no variance layers (another renderer's:
    Cycles writes none): ``colorVariance`` and ``normalVariance`` as the input's squared error to its
    reference, averaged over the channels. For an unbiased render against a converged reference its
    expectation is the variance of the pixel's mean, so the PDF still favours the noisy pixels; one frame
    gives one sample of it, a noisier map than a renderer's own variance. It is used for where patches are
    cut, never as a network input (a set of an input set with variance refuses such renders)."""
    def squared_error(layer):
        return np.mean((aovs[layer].astype(np.float64) - reference[layer]) ** 2, axis=-1)

    return {VARIANCE_OF[layer]: squared_error(layer) for layer in ("default", "normal")}


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


@numba.njit(cache=True)
def _error_pixels(output, reference, relative_squared, eps):
    """Mean over the last axis of the per-element error term; float64 (H, W).

    Inputs are float64 (H, W, C); ``relative_squared`` selects (x - r)^2 / (r^2 + eps), else
    |x - r| / (|x| + |r| + eps). In float64 every finite float32 input gives a finite term: |x - r| is at
    most 2 * 3.4e38 and its square 4.6e77, divided by at least eps, far below float64's 1.8e308.
    """
    h, w, c = output.shape
    out = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            s = 0.0
            for k in range(c):
                a = output[y, x, k]
                b = reference[y, x, k]
                d = a - b
                if relative_squared:
                    s += d * d / (b * b + eps)
                else:
                    s += abs(d) / (abs(a) + abs(b) + eps)
            out[y, x] = s / c
    return out


def error_map(output: np.ndarray, reference: np.ndarray, metric: str = "smape") -> np.ndarray:
    """Per-pixel error of a denoised colour image against its reference; float64 (H, W), finite, >= 0.

    ``output`` and ``reference`` are (H, W, 3) linear HDR colour. Each pixel is the mean over the three
    channels of the element term of ``metric`` (one of ERROR_METRICS), the terms of prep.metrics:
    "smape": |x - r| / (|x| + |r| + SMAPE_EPS); "relmse": (x - r)^2 / (r^2 + RELMSE_EPS). So the map's
    mean is the image's SMAPE or relMSE. Computed in float64: finite for any finite float32 input. A
    float64 input large enough to overflow (relMSE beyond ~1e154 in magnitude) is an error rather than an
    infinite pixel that ``patch_pdf`` would silently zero.

    Error-based rounds (docs/method.md §8) turn it into a patch PDF with ``patch_pdf``, exactly as the
    variance importance is (then ``mix_pdfs`` with the variance PDF).

    Raises ValueError for an unknown metric, shapes that differ or are not (H, W, 3), and any NaN or
    infinite value in either input (a diverged model's output must not become a PDF quietly).
    """
    if metric not in ERROR_METRICS:
        raise ValueError(f"metric must be one of {ERROR_METRICS}, got {metric!r}")
    output = np.asarray(output)
    reference = np.asarray(reference)
    if output.shape != reference.shape:
        raise ValueError(f"output and reference shapes differ: {output.shape} vs {reference.shape}")
    if output.ndim != 3 or output.shape[-1] != 3:
        raise ValueError(f"output and reference must be (H, W, 3) colour images, got shape {output.shape}")
    arrays = {}
    for name, image in (("output", output), ("reference", reference)):
        image = np.ascontiguousarray(image, dtype=np.float64)
        bad = int(np.count_nonzero(~np.isfinite(image)))
        if bad:
            raise ValueError(f"{name} has {bad} non-finite values (NaN or inf) of {image.size}")
        arrays[name] = image
    relative_squared = metric == "relmse"
    eps = RELMSE_EPS if relative_squared else SMAPE_EPS
    errors = _error_pixels(arrays["output"], arrays["reference"], relative_squared, float(eps))
    overflowed = int(np.count_nonzero(~np.isfinite(errors)))
    if overflowed:
        raise ValueError(
            f"{metric} error overflows float64 at {overflowed} pixels: float64 inputs too large in magnitude "
            f"(any finite float32 input is safe)"
        )
    return errors


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


def exclude_positions(pdf: np.ndarray, positions: np.ndarray) -> np.ndarray:
    """A float64 copy of ``pdf`` with ``positions`` at probability 0 and the rest renormalised to sum to 1.

    ``positions`` are (m, 2) integer top-left positions (y, x), as ``draw_positions`` returns them:
    the patches earlier rounds cut, so that a new round never draws them again. The remaining positions
    keep their ratios. A position may repeat (harmless); an empty array returns the PDF unchanged.
    Raises ValueError if a position lies outside the PDF or if no probability mass is left.
    """
    pdf = np.array(pdf, dtype=np.float64)  # a copy: the caller's PDF is left alone
    if pdf.ndim != 2:
        raise ValueError(f"pdf must be 2-D (positions y, x), got shape {pdf.shape}")
    if np.any(~np.isfinite(pdf)) or np.any(pdf < 0):
        raise ValueError("pdf must be finite and non-negative")
    positions = np.asarray(positions)
    if positions.size == 0:
        return pdf
    if positions.ndim != 2 or positions.shape[1] != 2 or not np.issubdtype(positions.dtype, np.integer):
        raise ValueError(f"positions must be (m, 2) integers (y, x), got {positions.dtype} {positions.shape}")
    ys, xs = positions[:, 0], positions[:, 1]
    outside = (ys < 0) | (ys >= pdf.shape[0]) | (xs < 0) | (xs >= pdf.shape[1])
    if np.any(outside):
        first = tuple(int(v) for v in positions[np.argmax(outside)])
        raise ValueError(
            f"{int(outside.sum())} of {len(positions)} positions lie outside the pdf's shape {pdf.shape}, "
            f"first (y, x) = {first}"
        )
    pdf_mass = pdf > 0
    pdf[ys, xs] = 0.0
    total = pdf.sum()
    if not total > 0.0:
        distinct = len({(int(y), int(x)) for y, x in zip(ys, xs)})
        raise ValueError(
            f"no probability mass left after excluding {distinct} distinct positions ({len(positions)} given) "
            f"from a {pdf.shape} pdf of {int(np.count_nonzero(pdf_mass))} positions with non-zero probability"
        )
    return pdf / total
