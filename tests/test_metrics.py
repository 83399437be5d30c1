import numpy as np
import pytest

from prep import baselines, colour, metrics
from prep.metrics import RELMSE_EPS


def test_metrics_on_a_hand_computed_case():
    ref = np.zeros((2, 2, 3))
    ref[0, 0] = 1.0
    x = ref.copy()
    x[0, 0, 0] = 2.0  # one channel off by 1 where ref = 1
    x[1, 1, 2] = 0.1  # one channel off by 0.1 where ref = 0
    n = 12
    assert metrics.mse(x, ref) == pytest.approx((1.0 + 0.01) / n)
    assert metrics.relmse(x, ref) == pytest.approx((1.0 / 1.01 + 0.01 / 0.01) / n)
    assert metrics.smape(x, ref) == pytest.approx((1.0 / 3.01 + 0.1 / 0.11) / n)


def test_identical_images_are_perfect():
    img = np.random.default_rng(0).gamma(1.0, 1.0, (32, 32, 3))
    assert metrics.dssim(img, img) == pytest.approx(0.0, abs=1e-12)
    assert metrics.psnr(img, img) == float("inf")
    assert metrics.relmse(img, img) == 0.0


def test_psnr_and_dssim_follow_the_tonemap():
    ref = np.full((16, 16, 3), 1.0)  # tonemaps to 0.5 ** (1 / 2.2)
    x = np.full((16, 16, 3), 3.0)  # tonemaps to 0.75 ** (1 / 2.2)
    err = (0.75 ** (1 / 2.2) - 0.5 ** (1 / 2.2)) ** 2
    assert metrics.psnr(x, ref) == pytest.approx(10 * np.log10(1 / err))
    noisy = ref + np.random.default_rng(1).normal(0, 0.5, ref.shape)
    assert 0 < metrics.dssim(noisy, ref) <= 1


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match=r"\(4, 4, 3\) vs \(4, 5, 3\)"):
        metrics.mse(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)))


def test_nlm_baseline_reduces_noise_on_a_known_signal():
    rng = np.random.default_rng(2)
    yy, xx = np.mgrid[0:48, 0:48] / 48.0
    clean = np.stack([0.5 + 0.4 * np.sin(6 * xx), 0.3 + 0.2 * yy, np.full_like(xx, 0.4)], -1)
    sigma = 0.08
    noisy = clean + rng.normal(0, sigma, clean.shape)
    out = baselines.nlm_denoise(noisy, np.full(clean.shape[:2], sigma**2))
    assert out.shape == clean.shape and out.dtype == np.float32
    assert metrics.mse(out, clean) < 0.5 * metrics.mse(noisy, clean)


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 2, 3), (2, 9, 3), (6, 7, 3)])
def test_dssim_is_defined_on_images_smaller_than_its_window(shape):
    rng = np.random.default_rng(5)
    x, r = rng.uniform(0, 4, shape), rng.uniform(0, 4, shape)
    assert metrics.dssim(x, x) == pytest.approx(0.0, abs=1e-12)
    assert 0.0 < metrics.dssim(x, r) <= 1.0


def test_one_window_ssim_of_constant_images_is_the_luminance_term():
    a, b = 0.5, 2.0
    ta, tb = colour.tonemap(np.float64(a)), colour.tonemap(np.float64(b))
    c1 = metrics.SSIM_K[0] ** 2
    expected = (2 * ta * tb + c1) / (ta**2 + tb**2 + c1)
    got = metrics.dssim(np.full((2, 2, 3), a), np.full((2, 2, 3), b))
    assert got == pytest.approx((1 - expected) / 2, rel=1e-12)


def _relse_p999_by_hand(x, r):
    """Independent float64 reference: per-pixel mean over channels of (x - r)^2 / (r^2 + 0.01) in explicit
    loops, then the 99.9th percentile of the sorted errors by linear interpolation between order statistics."""
    h, w, c = x.shape
    errors = []
    for i in range(h):
        for j in range(w):
            total = 0.0
            for k in range(c):
                d = float(x[i, j, k]) - float(r[i, j, k])
                total += d * d / (float(r[i, j, k]) ** 2 + 0.01)
            errors.append(total / c)
    s = sorted(errors)
    pos = 0.999 * (len(s) - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, len(s) - 1)
    return s[lo] + (pos - lo) * (s[hi] - s[lo])


def test_relmse_is_the_mean_of_the_relse_terms():
    rng = np.random.default_rng(7)
    r = rng.gamma(0.5, 1.0, (9, 11, 3))
    x = r + rng.normal(0, 0.3, r.shape)
    assert metrics.relmse(x, r) == float(np.mean(metrics.relse(x, r)))
    assert metrics.relmse(x, r) == pytest.approx(np.mean(metrics.relse_pixels(x, r)), rel=1e-12)
    assert metrics.relse_pixels(x, r).shape == (9, 11) and metrics.relse_pixels(x, r).dtype == np.float64


def test_relse_p999_on_a_hand_computed_case():
    # 1000 pixels whose errors are 0, 1, ..., 999 (all in the red channel, so 3 i there): the 99.9th
    # percentile sits at position 0.999 * 999 = 998.001, i.e. 998 + 0.001 * (999 - 998) = 998.001
    i = np.random.default_rng(3).permutation(1000).astype(np.float64)
    r = np.zeros((1000, 3))
    x = np.zeros((1000, 3))
    x[:, 0] = np.sqrt(3 * i * 0.01)  # (x - 0)^2 / (0 + 0.01) = 3 i; mean over R, G, B = i
    x, r = x.reshape(25, 40, 3), r.reshape(25, 40, 3)
    assert metrics.relse_p999(x, r) == pytest.approx(998.001, rel=1e-12)
    assert metrics.relmse(x, r) == pytest.approx(499.5, rel=1e-12)
    assert metrics.relse_p999(r, r) == 0.0


@pytest.mark.parametrize("shape", [(1, 1, 3), (2, 3, 3), (30, 30, 3), (64, 64, 3), (37, 53, 3)])
def test_relse_p999_equals_a_float64_reference(shape):
    rng = np.random.default_rng(sum(shape))
    r = rng.gamma(0.5, 1.0, shape)
    x = np.maximum(r + rng.normal(0, 0.5, shape) * np.sqrt(r + 0.01), 0).astype(np.float32)
    assert metrics.relse_p999(x, r) == pytest.approx(_relse_p999_by_hand(x, r), rel=1e-12)


def test_relse_p999_sees_fireflies_that_the_mean_hides():
    rng = np.random.default_rng(11)
    r = rng.uniform(0.2, 1.0, (30, 30, 3))  # 900 pixels: the worst one enters the percentile
    x = r * (1 + rng.normal(0, 0.05, r.shape))
    firefly = x.copy()
    firefly[17, 4] = 500.0
    mean_before, mean_after = metrics.relmse(x, r), metrics.relmse(firefly, r)
    p_before, p_after = metrics.relse_p999(x, r), metrics.relse_p999(firefly, r)
    # (rel 1e-10: the last bit of the position 0.999 * 899 times the firefly's gap of 5e5 to its neighbour)
    assert p_after == pytest.approx(_relse_p999_by_hand(firefly, r), rel=1e-10)
    # position 0.999 * 899 = 898.101: the firefly's error weighs 0.101 in the percentile, 1/900 in the mean
    assert p_after - p_before > 50 * (mean_after - mean_before) > 0
    assert p_after > 1000 * p_before

    # on a larger frame the percentile needs fireflies in at least 0.1 % of the pixels: 9 of 4096 here
    r = rng.uniform(0.2, 1.0, (64, 64, 3))
    x = r * (1 + rng.normal(0, 0.05, r.shape))
    one, nine = x.copy(), x.copy()
    one[5, 5] = 500.0
    nine[rng.choice(64, 9, replace=False), rng.choice(64, 9, replace=False)] = 500.0
    worst_clean = metrics.relse_pixels(x, r).max()
    assert metrics.relse_p999(one, r) <= worst_clean  # a single firefly in 4096 pixels is not seen
    assert metrics.relse_p999(nine, r) > 1000 * worst_clean
    assert metrics.relmse(nine, r) < 0.01 * metrics.relse_p999(nine, r)
    assert metrics.relse_p999(nine, r) == pytest.approx(_relse_p999_by_hand(nine, r), rel=1e-10)


def test_all_metrics_hold_every_metric_in_order():
    rng = np.random.default_rng(4)
    r = rng.gamma(1.0, 1.0, (8, 8, 3))
    x = r + rng.normal(0, 0.1, r.shape)
    values = metrics.all_metrics(x, r)
    assert tuple(values) == metrics.METRICS
    assert values["relse_p999"] == metrics.relse_p999(x, r) and values["relmse"] == metrics.relmse(x, r)


def test_the_error_split_puts_the_worst_pixels_error_in_its_tail_and_the_rest_in_its_body():
    from kpcn_keras.studies import error_tail

    reference = np.ones((100, 100, 3))
    x = reference + 0.1  # every pixel a little off ...
    x[:10, :10] += 2.9  # ... and 1 % of them far off, 3.0 in all
    got = error_tail.split(x.astype(np.float32), reference.astype(np.float32))
    far, near = 3.0**2 / (1 + RELMSE_EPS), 0.1**2 / (1 + RELMSE_EPS)  # relSE of one pixel of each kind
    total = 100 * far + 9900 * near
    assert got["relmse"] == pytest.approx(total / 10000, rel=1e-5)
    assert got["shares"] == pytest.approx([10 * far / total, 100 * far / total], rel=1e-5)
    assert got["body"] == pytest.approx(near, rel=1e-5)
