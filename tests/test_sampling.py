import numpy as np
import pytest
from helpers.chi_square import assert_follows, assert_rejects
from helpers.numerics import PROPERTY, renders
from helpers.references import assert_pdf_is_a_distribution, assert_variance_pdf_matches, reference_pdf
from hypothesis import given, settings
from hypothesis import strategies as st

from prep import sampling


@pytest.mark.slow
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
    bins = np.array_split(np.argsort(pdf.ravel()), 16)
    observed = np.array([hits[b].sum() for b in bins])

    def expected(p):
        return np.array([p.ravel()[b].sum() for b in bins]) * trials * count

    assert_follows(observed, expected(pdf), alpha=1e-3)
    # the same draws reject a bump of 1.5 times the variance of the one drawn from
    wider = np.exp(-((yy - 12.0) ** 2 + (xx - 25.0) ** 2) / 300.0) + 0.2
    assert_rejects(observed, expected(wider / wider.sum()), alpha=1e-3)


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


# ---------------------------------------------------------------- hard numbers (from test_numerics)


@st.composite
def importance_maps(draw):
    h = draw(st.integers(1, 12))
    w = draw(st.integers(1, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    lo = draw(st.integers(-320, 308))
    hi = draw(st.integers(lo, 308))
    imp = np.minimum(10.0 ** rng.uniform(lo, hi, (h, w)), np.finfo(np.float64).max)
    imp[rng.uniform(size=(h, w)) < draw(st.floats(0, 1))] = 0.0
    specials = [np.nan, np.inf, -np.inf, -1.0, 0.0, 5e-324, np.finfo(np.float64).max, 1e20]
    for index, value in draw(st.lists(st.tuples(st.integers(0, h * w - 1), st.sampled_from(specials)), max_size=4)):
        imp.reshape(-1)[index] = value
    patch = draw(st.integers(1, min(h, w)))
    mix = draw(st.one_of(st.sampled_from([0.0, 0.1, 1.0]), st.floats(0, 1)))
    return imp, patch, mix


@pytest.mark.slow
@settings(max_examples=150, **PROPERTY)
@given(case=importance_maps())
def test_patch_pdf_of_any_importance_is_a_distribution_equal_to_explicit_window_sums(case):
    importance, patch, mix = case
    pdf = sampling.patch_pdf(importance, patch, mix)
    assert_pdf_is_a_distribution(pdf, reference_pdf(importance, patch, mix))
    count = min(3, int(np.count_nonzero(pdf)))
    pos = sampling.draw_positions(pdf, count, np.random.default_rng(0))
    assert len({tuple(p) for p in pos}) == count and (pdf[pos[:, 0], pos[:, 1]] > 0).all()


@pytest.mark.slow
@settings(max_examples=40, **PROPERTY)
@given(aovs=renders(), data=st.data())
def test_variance_pdf_of_any_finite_render_is_a_distribution_equal_to_float64_reference(aovs, data):
    h, w = aovs["depth"].shape
    patch = data.draw(st.integers(1, min(h, w)))
    assert_variance_pdf_matches(aovs, patch, data.draw(st.floats(0, 1)))
