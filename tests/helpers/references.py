"""float64 computations written independently of the library, which its code is held to: the features, the
variance importance and patch PDF, the kernel apply, the relSE, analytic form factors and the augmentation
moves; and the checks of the library's results against them."""

import math

import numpy as np

from helpers.numerics import FEATURE_RANGES
from prep import features as _features
from prep import sampling as _sampling
from prep.colour import ALBEDO_EPS
from prep.features import NUM_FEATURES
from prep.sampling import IMPORTANCE_EPS

# the float64 features the numba kernel is held to; it lives in the package, where the benchmark times it
reference_features = _features.reference_features


def reference_relse(colour, variance) -> np.ndarray:
    """float64 relSE of prep.convergence, written out again: sqrt(max(v, 0)) / (max(mean_RGB c, 0) + 0.01)."""
    colour, variance = np.asarray(colour, np.float64), np.asarray(variance, np.float64)
    return np.sqrt(np.maximum(variance, 0.0)) / (np.maximum(colour.mean(axis=-1), 0.0) + 0.01)


def _corner_form_factor(a, b, h):
    """Form factor from a differential area to a parallel a x b rectangle at height h whose corner is
    straight above it (standard closed form)."""
    x, y = a / h, b / h
    return (x / math.sqrt(1 + x * x) * math.atan(y / math.sqrt(1 + x * x))
            + y / math.sqrt(1 + y * y) * math.atan(x / math.sqrt(1 + y * y))) / (2 * math.pi)


def rect_form_factor(x0, x1, z0, z1, h):
    """Form factor from a differential area at the origin (normal +y) to the rectangle
    [x0, x1] x [z0, z1] at height h, parallel to it: signed corner decomposition (the corner form
    factor is odd in each extent)."""
    f = _corner_form_factor
    return f(x1, z1, h) - f(x0, z1, h) - f(x1, z0, h) + f(x0, z0, h)


def reference_log_colour(colour, albedo=None) -> np.ndarray:
    """log(1 + max(x, 0)), x = colour / (clip(albedo, 0, 1) + ALBEDO_EPS) for the diffuse branch, in float64."""
    x = np.asarray(colour, np.float64)
    if albedo is not None:
        x = x / (np.clip(np.asarray(albedo, np.float64), 0.0, 1.0) + ALBEDO_EPS)
    return np.log1p(np.maximum(x, 0.0))


def reference_importance(aovs: dict) -> np.ndarray:
    mean = np.maximum(aovs["default"].astype(np.float64), 0.0).sum(axis=-1) / 3.0
    colour = np.maximum(aovs["colorVariance"].astype(np.float64), 0.0) / (mean**2 + IMPORTANCE_EPS)
    return colour + np.maximum(aovs["normalVariance"].astype(np.float64), 0.0)


def reference_pdf(importance, p: int, mix: float) -> np.ndarray:
    """Explicit window sums (exactly rounded, math.fsum) of the finite, non-negative importance, normalised,
    mixed with the uniform PDF; uniform when nothing is left."""
    imp = np.asarray(importance, np.float64)
    imp = np.where(np.isfinite(imp), np.maximum(imp, 0.0), 0.0)
    if imp.max() > 0:
        imp = np.ldexp(imp, -np.frexp(imp.max())[1])  # an exact power-of-two scale, so that fsum cannot overflow
    h, w = imp.shape
    sums = np.array([[math.fsum(imp[y : y + p, x : x + p].ravel()) for x in range(w - p + 1)]
                     for y in range(h - p + 1)])
    total = math.fsum(sums.ravel())
    uniform = np.full(sums.shape, 1.0 / sums.size)
    if total <= 0:
        return uniform
    return mix * uniform + (1.0 - mix) * (sums / total)


def reference_kernel_apply(colour, logits, k: int):
    """float64: softmax with max subtraction, edge-replicated k x k windows, weighted sum. Returns the output
    (B, H, W, C) and the windows (B, H, W, k*k, C)."""
    c = np.asarray(colour, np.float64)
    z = np.asarray(logits, np.float64)
    z = z - z.max(axis=-1, keepdims=True)
    weights = np.exp(z)
    weights /= weights.sum(axis=-1, keepdims=True)
    r = k // 2
    h, w = c.shape[1:3]
    padded = np.pad(c, ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
    windows = np.stack([padded[:, i : i + h, j : j + w] for i in range(k) for j in range(k)], axis=3)
    return np.einsum("bhwt,bhwtc->bhwc", weights, windows), windows


def assert_features_in_documented_ranges(feats: np.ndarray) -> None:
    assert feats.shape[-1] == NUM_FEATURES
    assert np.isfinite(feats).all()
    f = feats.astype(np.float64)
    for first, stop, lo, hi in FEATURE_RANGES:
        block = f[..., first:stop]
        assert block.min() >= lo and block.max() <= hi, (
            f"channels {_features.FEATURE_NAMES[first:stop]}: [{block.min()}, {block.max()}] outside [{lo}, {hi}]")


def assert_features_match_reference(aovs: dict) -> None:
    for branch in _features.BRANCHES:
        got = _features.branch_features(aovs, branch)
        assert got.dtype == np.float32
        assert_features_in_documented_ranges(got)
        np.testing.assert_allclose(got, reference_features(aovs, branch), rtol=1e-6, atol=1e-6, err_msg=branch)


def assert_read_features_close(got: np.ndarray, want: np.ndarray, err_msg: str = "") -> None:
    """Features read back from a shard (recomputed from its float16 buffers) against the same pixels'
    features at full precision, within the format's bound (docs/formats.md §4) taken over the patch: a value
    within 2**-11 of itself, a difference within 2**-11 of the two values it is made of, which are at most
    1 (normal, albedo, depth) or the patch's largest colour and colour difference together. The exact
    per-channel bound is held in test_compact_shards.py."""
    colour = float(np.abs(want[..., 0:3]).max() + np.abs(want[..., 3:6]).max() + np.abs(want[..., 13:16]).max())
    np.testing.assert_allclose(got, want, rtol=2.0**-11 + 2.0**-22, atol=2.0**-10 * max(colour, 1.0) + 2.0**-24,
                               err_msg=err_msg)


def assert_pdf_is_a_distribution(pdf: np.ndarray, want: np.ndarray) -> None:
    assert pdf.shape == want.shape and pdf.dtype == np.float64
    assert np.isfinite(pdf).all() and pdf.min() >= 0.0
    assert abs(math.fsum(pdf.ravel()) - 1.0) <= 1e-12
    # direct sums of non-negative terms: relative accuracy, even beside a pixel 1e20 times brighter
    np.testing.assert_allclose(pdf, want, rtol=1e-12, atol=1e-300)


def assert_variance_pdf_matches(aovs: dict, patch: int, mix: float = 0.1) -> np.ndarray:
    importance = _sampling.variance_importance(aovs)
    np.testing.assert_allclose(importance, reference_importance(aovs), rtol=1e-12, atol=0)
    pdf = _sampling.patch_pdf(importance, patch, mix)
    assert_pdf_is_a_distribution(pdf, reference_pdf(importance, patch, mix))
    return pdf



def moved(image: np.ndarray, spatial: int, inverse: bool = False) -> np.ndarray:
    """``image`` (H, W, ...) transposed (bit 0 of ``spatial``), mirrored left-right (bit 1) and upside down
    (bit 2), in that order, or with ``inverse`` those undone: plain numpy, the reference for
    ``kpcn_keras.augment``'s moves."""
    steps = [(1, lambda x: np.swapaxes(x, 0, 1)), (2, lambda x: x[:, ::-1]), (4, lambda x: x[::-1])]
    for bit, step in reversed(steps) if inverse else steps:
        image = step(image) if spatial & bit else image
    return np.ascontiguousarray(image)
