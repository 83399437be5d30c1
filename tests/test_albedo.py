"""The albedo a denoised diffuse branch is multiplied back by (prep.albedo): the formula in float64, regions,
converged pixels, and what it does to noise and to an edge."""

import numpy as np
import pytest

from prep import albedo


def _reference(a, v, r, f, k, s):
    """The module docstring's formula pixel by pixel in float64 numpy, pixels beyond the frame its edge's."""
    a = np.clip(np.asarray(a, np.float64), 0.0, 1.0)
    v = np.maximum(np.asarray(v, np.float64), 0.0)
    h, w = v.shape

    def at(arr, y, x):
        return arr[min(max(y, 0), h - 1), min(max(x, 0), w - 1)]

    v = np.array([[np.mean([at(v, y + dy, x + dx) for dy in range(-s, s + 1) for dx in range(-s, s + 1)])
                   for x in range(w)] for y in range(h)])

    out = a.copy()
    for y in range(h):
        for x in range(w):
            if v[y, x] <= 0:
                continue
            num, den = np.zeros(3), 0.0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    d2 = 0.0
                    for ny in range(-f, f + 1):
                        for nx in range(-f, f + 1):
                            ap, aq = at(a, y + ny, x + nx), at(a, y + dy + ny, x + dx + nx)
                            vp, vq = at(v, y + ny, x + nx), at(v, y + dy + ny, x + dx + nx)
                            d2 += np.sum((ap - aq) ** 2 - (vp + min(vp, vq))) / (albedo.EPS + k * k * (vp + vq))
                    wt = np.exp(-max(d2 / (3 * (2 * f + 1) ** 2), 0.0))
                    num += wt * at(a, y + dy, x + dx)
                    den += wt
            out[y, x] = num / den
    return out


def _noisy_frame(h, w, seed):
    rng = np.random.default_rng(seed)
    a = rng.uniform(-0.1, 1.1, (h, w, 3)).astype(np.float32)  # beyond [0, 1] too: clipped, as remodulation does
    v = rng.uniform(0.0, 0.02, (h, w)).astype(np.float32)
    v[rng.random((h, w)) < 0.3] = 0.0  # converged pixels among noisy ones
    return a, v


@pytest.mark.parametrize("r, f, k, s", [(albedo.SEARCH_RADIUS, albedo.PATCH_RADIUS, albedo.STRENGTH,
                                         albedo.VARIANCE_RADIUS), (2, 0, 0.3, 0), (1, 2, 1.5, 2)])
def test_prefilter_matches_a_float64_evaluation_of_the_formula(r, f, k, s):
    a, v = _noisy_frame(9, 11, seed=1)
    got = albedo.prefilter(a, v, r=r, f=f, k=k, s=s)
    assert got.dtype == np.float32 and got.shape == a.shape
    np.testing.assert_allclose(got, _reference(a, v, r, f, k, s), rtol=1e-6, atol=1e-7)


def test_a_region_filtered_alone_equals_those_pixels_of_the_whole_frame():
    a, v = _noisy_frame(23, 17, seed=2)
    whole = albedo.prefilter(a, v)
    for region in [(0, 5, 0, 4), (3, 20, 6, 17), (22, 23, 16, 17), (0, 23, 0, 17)]:
        y0, y1, x0, x1 = region
        np.testing.assert_array_equal(albedo.prefilter(a, v, region), whole[y0:y1, x0:x1], err_msg=str(region))


def test_a_converged_pixel_keeps_its_albedo_and_a_frame_without_variance_is_its_clipped_albedo():
    a, v = _noisy_frame(12, 10, seed=3)
    v[2:9, 3:8] = 0.0  # converged: these pixels and, inside the block's edge, their neighbours too
    out = albedo.prefilter(a, v)
    converged = np.zeros(v.shape, bool)
    converged[3:8, 4:7] = True
    np.testing.assert_array_equal(out[converged], np.clip(a, 0, 1)[converged])
    assert (out[~converged] != np.clip(a, 0, 1)[~converged]).any()
    np.testing.assert_array_equal(albedo.prefilter(a, np.zeros_like(v)), np.clip(a, 0, 1))


def test_noise_of_an_albedo_falls_and_an_edge_does_not_bleed():
    # left half 0.2, right half 0.7, Gaussian noise of the variance the layer states: the filter averages each
    # side (its error variance falls by far more than 4x) and keeps them apart (each side's mean stays within
    # a few standard errors of the true value, up to the pixel beside the edge)
    rng = np.random.default_rng(4)
    h, w, sigma = 64, 64, 0.03
    truth = np.where(np.arange(w)[None, :, None] < w // 2, 0.2, 0.7) * np.ones((h, w, 3))
    noisy = (truth + rng.normal(0.0, sigma, truth.shape)).astype(np.float32)
    out = albedo.prefilter(noisy, np.full((h, w), sigma**2, np.float32)).astype(np.float64)
    assert np.mean((out - truth) ** 2) < np.mean((noisy - truth) ** 2) / 4
    for cols in (slice(0, w // 2 - 1), slice(w // 2 + 1, w)):
        bias = np.mean(out[:, cols] - truth[:, cols])
        assert abs(bias) < 5 * sigma / np.sqrt(out[:, cols].size), (cols, bias)
    next_to_edge = out[:, [w // 2 - 1, w // 2]] - truth[:, [w // 2 - 1, w // 2]]
    assert np.abs(next_to_edge.mean(axis=(0, 2))).max() < 0.01
