"""Error-based sampling rounds (docs/method.md §8): error maps, their patch PDFs, excluded positions."""

import numpy as np
import pytest
from helpers.chi_square import assert_follows, assert_rejects
from numpy.lib.stride_tricks import sliding_window_view

from prep import metrics, sampling


def numpy_error_map(output, reference, metric):
    """Float64 numpy reference: the channel mean of the metric's element term (docs/method.md §9 "Measuring")."""
    x = np.asarray(output, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if metric == "smape":
        terms = np.abs(x - r) / (np.abs(x) + np.abs(r) + metrics.SMAPE_EPS)
    else:
        terms = (x - r) ** 2 / (r * r + metrics.RELMSE_EPS)
    return terms.mean(axis=-1)


def numpy_patch_pdf(importance, size, uniform_mix):
    """Float64 numpy reference of the documented PDF: window sums, normalised, mixed with the uniform PDF."""
    sums = sliding_window_view(np.asarray(importance, dtype=np.float64), (size, size)).sum(axis=(-2, -1))
    return uniform_mix / sums.size + (1.0 - uniform_mix) * sums / sums.sum()


def hard_case(name, rng, shape=(6, 7, 3)):
    """(output, reference) float32 pairs at the edges of the float32 range."""
    sign = lambda: rng.choice([-1.0, 1.0], shape)  # noqa: E731
    if name == "zeros":
        return np.zeros(shape, np.float32), np.zeros(shape, np.float32)
    if name == "huge":
        out = (3e38 * sign()).astype(np.float32)
        ref = (3e38 * sign()).astype(np.float32)
        ref[0] = 0.0  # 3e38 against 0: relMSE 9e78 / eps-sized denominators
        out[1] = -ref[1]  # 3e38 against -3e38: the difference overflows float32
        return out, ref
    if name == "negative":
        return rng.uniform(-5.0, -0.01, shape).astype(np.float32), rng.uniform(-5.0, -0.01, shape).astype(np.float32)
    if name == "tiny":
        return (1e-30 * sign()).astype(np.float32), (1e-30 * sign() * rng.uniform(0.5, 2.0, shape)).astype(np.float32)
    magnitudes = np.array([0.0, 1e-30, 1e-3, 1.0, 1e10, 3e38])  # "mixed"
    out = (rng.choice(magnitudes, shape) * sign()).astype(np.float32)
    ref = (rng.choice(magnitudes, shape) * sign()).astype(np.float32)
    return out, ref


@pytest.mark.parametrize("metric", sampling.ERROR_METRICS)
def test_error_map_matches_numpy_on_random_images(metric):
    rng = np.random.default_rng(0)
    ref = rng.gamma(0.7, 1.0, (13, 17, 3)).astype(np.float32)
    out = (ref + rng.normal(0.0, 0.3, ref.shape)).astype(np.float32)
    err = sampling.error_map(out, ref, metric)
    assert err.shape == (13, 17) and err.dtype == np.float64
    np.testing.assert_allclose(err, numpy_error_map(out, ref, metric), rtol=1e-12, atol=0)
    # the map's mean is the whole-image metric of prep.metrics
    np.testing.assert_allclose(err.mean(), getattr(metrics, metric)(out, ref), rtol=1e-12)


@pytest.mark.parametrize("case", ["zeros", "huge", "negative", "tiny", "mixed"])
@pytest.mark.parametrize("metric", sampling.ERROR_METRICS)
def test_error_map_is_finite_and_exact_at_float32_extremes(metric, case):
    out, ref = hard_case(case, np.random.default_rng(1))
    err = sampling.error_map(out, ref, metric)
    assert np.all(np.isfinite(err)) and np.all(err >= 0)
    np.testing.assert_allclose(err, numpy_error_map(out, ref, metric), rtol=1e-12, atol=0)


def test_error_map_of_opposite_float32_maxima_is_finite():
    out = np.full((1, 1, 3), 3e38, np.float32)
    err = sampling.error_map(out, -out, "relmse")
    # (6e38)^2 / (9e76 + 0.01) = 4, though 6e38 itself overflows float32
    np.testing.assert_allclose(err, [[4.0]], rtol=1e-6)
    np.testing.assert_allclose(sampling.error_map(out, -out, "smape"), [[1.0]], rtol=1e-6)


def test_error_map_default_metric_is_smape():
    rng = np.random.default_rng(2)
    out, ref = rng.uniform(0, 2, (2, 5, 4, 3))
    np.testing.assert_array_equal(sampling.error_map(out, ref), sampling.error_map(out, ref, "smape"))


def test_error_map_rejects_bad_inputs_naming_the_problem():
    good = np.ones((4, 5, 3), np.float32)
    with pytest.raises(ValueError, match="got 'mse'"):
        sampling.error_map(good, good, "mse")
    with pytest.raises(ValueError, match=r"differ: \(4, 5, 3\) vs \(4, 6, 3\)"):
        sampling.error_map(good, np.ones((4, 6, 3)), "smape")
    with pytest.raises(ValueError, match=r"\(H, W, 3\).*\(4, 5, 4\)"):
        sampling.error_map(np.ones((4, 5, 4)), np.ones((4, 5, 4)))
    with pytest.raises(ValueError, match=r"\(H, W, 3\).*\(4, 5\)"):
        sampling.error_map(np.ones((4, 5)), np.ones((4, 5)))
    bad = good.copy()
    bad[1, 2, 0] = np.nan
    with pytest.raises(ValueError, match="output has 1 non-finite"):
        sampling.error_map(bad, good)
    bad = good.copy()
    bad[0, 0, 1], bad[3, 4, 2] = np.inf, -np.inf
    with pytest.raises(ValueError, match="reference has 2 non-finite"):
        sampling.error_map(good, bad, "relmse")


def test_error_map_refuses_float64_overflow_rather_than_returning_inf():
    out = np.full((2, 2, 3), 1e200)
    with pytest.raises(ValueError, match="overflows float64 at 4 pixels"):
        sampling.error_map(out, -out, "relmse")


@pytest.mark.slow
@pytest.mark.parametrize("metric", sampling.ERROR_METRICS)
def test_error_pdf_draws_follow_the_error_chi_square(metric):
    size, side, mix = 5, 24, 0.1
    rng = np.random.default_rng(3)
    ref = rng.uniform(0.5, 1.5, (side, side, 3)).astype(np.float32)
    out = (ref * (1.0 + 0.02 * rng.standard_normal(ref.shape))).astype(np.float32)
    out[5:10, 15:20] = ref[5:10, 15:20] + 4.0  # one badly denoised rectangle
    pdf = sampling.patch_pdf(sampling.error_map(out, ref, metric), size, uniform_mix=mix)
    n = side - size + 1
    assert pdf.shape == (n, n)

    draws = 20000
    draw_rng = np.random.default_rng(17)
    pos = np.concatenate([sampling.draw_positions(pdf, 1, draw_rng) for _ in range(draws)])
    # 4 x 4 cells of 5 x 5 positions; every expected count is well above 5
    cell = (pos[:, 0] // 5) * 4 + pos[:, 1] // 5
    observed = np.bincount(cell, minlength=16)

    def expected_counts(reference_pdf):
        return reference_pdf.reshape(4, 5, 4, 5).sum(axis=(1, 3)).ravel() * draws

    # one test per metric: the pair together rejects a right sampler with probability 1e-4
    family = dict(alpha=1e-4, tests=len(sampling.ERROR_METRICS))
    reference_pdf = numpy_patch_pdf(numpy_error_map(out, ref, metric), size, mix)
    assert_follows(observed, expected_counts(reference_pdf), **family)

    # the positions whose window overlaps the rectangle: much more than their area share
    overlap = (pos[:, 0] >= 1) & (pos[:, 0] <= 9) & (pos[:, 1] >= 11) & (pos[:, 1] <= 19)
    area_share = 81 / (n * n)
    assert overlap.mean() > 3 * area_share

    # the same draws reject wrong PDFs: uniform, and the error PDF without the uniform mix
    assert_rejects(observed, expected_counts(np.full((n, n), 1 / n**2)), **family)
    unmixed = numpy_patch_pdf(numpy_error_map(out, ref, metric), size, 0.0)
    assert_rejects(observed, expected_counts(unmixed), **family)


def test_excluded_positions_get_zero_and_the_rest_keep_their_ratios():
    pdf = sampling.patch_pdf(np.random.default_rng(4).gamma(0.5, 1.0, (11, 13)), 5)  # (7, 9)
    before = pdf.copy()
    used = np.array([[0, 0], [3, 4], [6, 8], [3, 4]], dtype=np.int32)  # (3, 4) repeats
    out = sampling.exclude_positions(pdf, used)
    np.testing.assert_array_equal(pdf, before)  # the caller's PDF is untouched
    keep = np.ones(pdf.shape, bool)
    keep[[0, 3, 6], [0, 4, 8]] = False
    reference = np.where(keep, pdf.astype(np.float64), 0.0) / pdf.astype(np.float64)[keep].sum()
    assert out.dtype == np.float64
    assert np.all(out[~keep] == 0.0)
    np.testing.assert_allclose(out.sum(), 1.0, rtol=1e-12)
    np.testing.assert_allclose(out, reference, rtol=1e-12, atol=0)


def test_draws_after_exclusion_never_hit_an_excluded_position():
    pdf = sampling.patch_pdf(np.random.default_rng(5).uniform(size=(10, 10)), 3)  # (8, 8)
    used = sampling.draw_positions(pdf, 20, np.random.default_rng(6))
    used_set = {tuple(p) for p in used}
    out = sampling.exclude_positions(pdf, used)
    rng = np.random.default_rng(7)
    # every position left, at once, is exactly the complement; one more is more than there is
    rest = sampling.draw_positions(out, 64 - 20, rng)
    assert {tuple(p) for p in rest} == {(y, x) for y in range(8) for x in range(8)} - used_set
    with pytest.raises(ValueError, match="got 45"):
        sampling.draw_positions(out, 45, rng)
    singles = {tuple(sampling.draw_positions(out, 1, rng)[0]) for _ in range(500)}
    assert not singles & used_set


def test_excluding_nothing_returns_a_float64_copy():
    pdf = np.full((3, 4), 1 / 12, np.float32)
    for empty in (np.empty((0, 2), np.int32), np.array([], dtype=np.int64), []):
        out = sampling.exclude_positions(pdf, empty)
        assert out.dtype == np.float64 and out is not pdf
        np.testing.assert_array_equal(out, pdf.astype(np.float64))


def test_excluding_all_mass_or_outside_positions_is_an_error():
    pdf = np.full((3, 4), 1 / 12)
    every = np.array([[y, x] for y in range(3) for x in range(4)])
    with pytest.raises(ValueError, match="no probability mass left after excluding 12 distinct"):
        sampling.exclude_positions(pdf, every)
    sparse = np.zeros((3, 4))
    sparse[1, 1] = sparse[2, 3] = 0.5
    with pytest.raises(ValueError, match="no probability mass left after excluding 2 distinct"):
        sampling.exclude_positions(sparse, [[1, 1], [2, 3]])
    with pytest.raises(ValueError, match=r"1 of 2 positions lie outside .*\(3, 4\).*\(3, 0\)"):
        sampling.exclude_positions(pdf, [[0, 0], [3, 0]])
    with pytest.raises(ValueError, match=r"2 of 2 positions lie outside .*\(0, -1\)"):
        sampling.exclude_positions(pdf, [[0, -1], [0, 4]])
