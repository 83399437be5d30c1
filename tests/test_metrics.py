import numpy as np
import pytest

from prep import baselines, metrics


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
    ta, tb = metrics.tonemap(np.float64(a)), metrics.tonemap(np.float64(b))
    c1 = metrics.SSIM_K[0] ** 2
    expected = (2 * ta * tb + c1) / (ta**2 + tb**2 + c1)
    got = metrics.dssim(np.full((2, 2, 3), a), np.full((2, 2, 3), b))
    assert got == pytest.approx((1 - expected) / 2, rel=1e-12)
