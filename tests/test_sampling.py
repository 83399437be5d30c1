import numpy as np
import pytest

from prep import sampling


def test_positions_are_unique_and_inside_the_pdf():
    pdf = sampling.patch_pdf(np.random.default_rng(0).gamma(0.5, 1.0, (80, 90)), 17)
    assert pdf.shape == (64, 74)
    np.testing.assert_allclose(pdf.sum(), 1.0)
    pos = sampling.draw_positions(pdf, 500, np.random.default_rng(1))
    assert pos.shape == (500, 2) and pos.dtype == np.int32
    assert len({tuple(p) for p in pos}) == 500
    assert pos[:, 0].max() < 64 and pos[:, 1].max() < 74 and pos.min() >= 0


def test_draws_follow_the_pdf_chi_square():
    # a smooth synthetic PDF; with few draws per trial relative to the support, successive sampling
    # without replacement has marginals within O(count * max p) of the PDF, far below the test's power
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:40, 0:40]
    pdf = np.exp(-((yy - 12.0) ** 2 + (xx - 25.0) ** 2) / 200.0) + 0.2
    pdf /= pdf.sum()
    trials, count = 3000, 3
    hits = np.zeros(pdf.size)
    for _ in range(trials):
        pos = sampling.draw_positions(pdf, count, rng)
        hits[np.ravel_multi_index((pos[:, 0], pos[:, 1]), pdf.shape)] += 1
    # 16 bins of equal probability so every expected count is large
    order = np.argsort(pdf.ravel())
    bins = np.array_split(order, 16)
    expected = np.array([pdf.ravel()[b].sum() for b in bins]) * trials * count
    observed = np.array([hits[b].sum() for b in bins])
    chi2 = ((observed - expected) ** 2 / expected).sum()
    assert chi2 < 37.7  # chi-square 15 dof, p = 0.001


def test_zero_probability_positions_are_never_drawn():
    pdf = np.zeros((10, 10))
    pdf[2, 3] = pdf[7, 7] = pdf[0, 9] = 1 / 3
    pos = sampling.draw_positions(pdf, 3, np.random.default_rng(0))
    assert {tuple(p) for p in pos} == {(2, 3), (7, 7), (0, 9)}
    with pytest.raises(ValueError, match="got 4"):
        sampling.draw_positions(pdf, 4, np.random.default_rng(0))


def test_window_pdf_matches_a_direct_sum():
    imp = np.random.default_rng(2).uniform(0, 1, (12, 15))
    pdf = sampling.patch_pdf(imp, 5, uniform_mix=0.0)
    direct = np.array([[imp[y:y + 5, x:x + 5].sum() for x in range(11)] for y in range(8)])
    np.testing.assert_allclose(pdf, direct / direct.sum(), rtol=1e-10)


def test_flat_or_broken_importance_falls_back_to_uniform():
    for imp in (np.zeros((9, 9)), np.full((9, 9), np.nan)):
        pdf = sampling.patch_pdf(imp, 3)
        np.testing.assert_allclose(pdf, np.full((7, 7), 1 / 49))


def test_same_seed_same_positions():
    pdf = sampling.patch_pdf(np.random.default_rng(0).uniform(size=(30, 30)), 8)
    a = sampling.draw_positions(pdf, 20, np.random.default_rng(11))
    b = sampling.draw_positions(pdf, 20, np.random.default_rng(11))
    np.testing.assert_array_equal(a, b)


def test_bad_options_are_echoed():
    with pytest.raises(ValueError, match="got 40"):
        sampling.patch_pdf(np.ones((30, 30)), 40)
    with pytest.raises(ValueError, match="got 1.5"):
        sampling.patch_pdf(np.ones((30, 30)), 4, uniform_mix=1.5)
