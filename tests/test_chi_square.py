"""The suite's chi-square test (``helpers.chi_square``), which the sampling tests hold their draws to: its statistic
and p-value against closed forms, its pooling of low cells worked by hand, Šidák's level against its formula, and
its verdicts on dice, fair and loaded."""

import math

import numpy as np
import pytest
from helpers.chi_square import (
    assert_follows,
    assert_rejects,
    chi_square,
    pooled_cells,
    sidak_level,
)


def test_statistic_and_p_value_match_the_closed_form_of_two_degrees_of_freedom():
    # (10 - 20)^2 / 20 + 0 + (30 - 20)^2 / 20 = 10; with 2 degrees of freedom the survival function is exp(-x / 2)
    result = chi_square([10, 20, 30], [20, 20, 20])
    assert (result.statistic, result.dof, result.cells, result.pooled) == (10.0, 2, 3, 0)
    assert result.p_value == pytest.approx(math.exp(-5.0), rel=1e-12)


def test_the_p_value_of_one_degree_of_freedom_is_the_normal_tail():
    # with 1 degree of freedom the statistic is a squared standard normal: P(X > x) = erfc(sqrt(x / 2))
    result = chi_square([60, 40], [50, 50])
    assert (result.statistic, result.dof) == (4.0, 1)
    assert result.p_value == pytest.approx(math.erfc(math.sqrt(2.0)), rel=1e-12)


def test_low_cells_pool_in_increasing_expected_count_until_a_pool_expects_five():
    expected = [1.0, 2.0, 3.0, 10.0, 20.0]
    observed = [0, 4, 1, 12, 19]
    assert pooled_cells(observed, expected) == [[0, 1, 2], [3], [4]]
    result = chi_square(observed, expected)
    # the pool: 5 drawn, 6 expected
    assert result.statistic == pytest.approx(1 / 6 + 4 / 10 + 1 / 20, rel=1e-12)
    assert (result.dof, result.cells, result.pooled) == (2, 3, 3)


def test_a_pool_left_short_joins_the_last_pool_or_else_the_smallest_cell():
    # 1 + 4 reaches 5 and closes a pool; the second 4 is left short and joins it
    assert pooled_cells([1, 3, 0, 9, 22], [4.0, 4.0, 1.0, 10.0, 20.0]) == [[2, 0, 1], [3], [4]]
    # no pool closes: the two low cells join the cell of 10
    assert pooled_cells([2, 0, 9, 24], [1.0, 1.0, 10.0, 23.0]) == [[0, 1, 2], [3]]
    result = chi_square([2, 0, 9, 24], [1.0, 1.0, 10.0, 23.0])
    assert result.statistic == pytest.approx((11 - 12) ** 2 / 12 + (24 - 23) ** 2 / 23, rel=1e-12)
    assert result.dof == 1


def test_cells_with_neither_draws_nor_expected_ones_add_no_degree_of_freedom():
    plain = chi_square([10, 20, 30], [20, 20, 20])
    padded = chi_square([[0, 10, 0], [20, 30, 0]], [[0, 20, 0], [20, 20, 0]])
    assert (padded.statistic, padded.dof, padded.p_value) == (plain.statistic, plain.dof, plain.p_value)


def test_draws_where_none_is_expected_reject_at_any_level():
    result = chi_square([1, 49, 50], [0.0, 50.0, 50.0])
    assert result.p_value == 0.0 and result.impossible == 1
    with pytest.raises(AssertionError, match="1 with draws where none is expected"):
        assert_follows([1, 49, 50], [0.0, 50.0, 50.0], alpha=1e-12)


def test_sidak_level_is_the_formula_and_keeps_the_family_at_alpha():
    assert sidak_level(0.01, 1) == pytest.approx(0.01, rel=1e-15)
    for alpha, tests in [(0.05, 3), (0.01, 10), (1e-4, 2), (1e-9, 7)]:
        level = sidak_level(alpha, tests)
        if alpha > 1e-6:  # the formula as written loses the digits of a tiny alpha to 1 - alpha
            assert level == pytest.approx(1 - (1 - alpha) ** (1 / tests), rel=1e-12)
        # tests independent tests, each passing a true hypothesis with probability 1 - level: the family's
        # chance of a false rejection is alpha
        assert 1 - (1 - level) ** tests == pytest.approx(alpha, rel=1e-9)
        assert alpha / tests <= level < alpha  # a little above Bonferroni's level, below the single test's
    for alpha, tests in [(0.0, 1), (1.0, 1), (0.01, 0)]:
        with pytest.raises(ValueError, match="significance level"):
            sidak_level(alpha, tests)


def test_a_fair_die_passes_and_a_loaded_one_is_rejected():
    rng = np.random.default_rng(0)
    rolls = 6000
    fair = np.bincount(rng.integers(0, 6, rolls), minlength=6)
    expected = np.full(6, rolls / 6)
    assert_follows(fair, expected, alpha=0.01)
    # a six of probability 1/5 instead of 1/6: 1,200 sixes expected against 1,000
    loaded = np.bincount(rng.choice(6, rolls, p=[0.16] * 5 + [0.2]), minlength=6)
    assert_rejects(loaded, expected, alpha=0.01)
    with pytest.raises(AssertionError, match="do not follow"):
        assert_follows(loaded, expected, alpha=0.01)
    with pytest.raises(AssertionError, match="does not reject"):
        assert_rejects(fair, expected, alpha=0.01)


def test_a_fair_die_is_rejected_at_about_the_level_asked():
    # 4,000 fair experiments of 120 rolls: the test's false rejections come at the rate asked, within 4
    # standard deviations of a binomial count (the chi-square distribution approximates the statistic)
    counts = np.random.default_rng(1).multinomial(120, [1 / 6] * 6, size=4000)
    p_values = np.array([chi_square(c, np.full(6, 20.0)).p_value for c in counts])
    for level in (0.05, 0.01):
        rate = (p_values < level).mean()
        assert abs(rate - level) < 4 * math.sqrt(level * (1 - level) / len(counts)), (level, rate)


def test_bad_counts_are_refused_saying_why():
    with pytest.raises(ValueError, match=r"shape \(3,\), expected ones of \(2,\)"):
        chi_square([1, 2, 3], [3.0, 3.0])
    with pytest.raises(ValueError, match="finite and non-negative"):
        chi_square([1, -2, 3], [1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="add up to 30, the draws to 60"):
        chi_square([10, 20, 30], [10.0, 10.0, 10.0])
    with pytest.raises(ValueError, match="no degree of freedom"):
        chi_square([2, 1], [1.5, 1.5])
