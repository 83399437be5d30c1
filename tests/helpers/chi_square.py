"""Pearson's chi-square test of drawn counts against the counts a density predicts, after Mitsuba 3's ``chi2``
test (``mitsuba/python/chi2.py``): cells expected to hold fewer than :data:`MIN_EXPECTED` draws pooled together
(the chi-square distribution approximates the statistic only where every expected count is a few or more), the
p-value from the chi-square distribution's survival function, and Šidák's correction of the significance level
for a family of tests, so that the family as a whole rejects a right sampler with probability ``alpha``."""

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

MIN_EXPECTED = 5.0
# how far the expected counts may add up from the draws (a density integrated by quadrature is not exact);
# a density that integrates to more or less than one beyond this is a wrong density, not a test to run
TOTAL_RTOL = 1e-3


def sidak_level(alpha: float, tests: int) -> float:
    """The significance level of each of ``tests`` independent tests that together reject a true hypothesis with
    probability ``alpha``: 1 - (1 - alpha)^(1 / tests) (computed without the cancellation of a small alpha)."""
    if not 0.0 < alpha < 1.0 or tests < 1:
        raise ValueError(f"a significance level in (0, 1) and one test or more, got alpha {alpha}, tests {tests}")
    return -math.expm1(math.log1p(-alpha) / tests)


@dataclass(frozen=True)
class ChiSquare:
    """A test's outcome: the statistic over ``cells`` cells (``dof`` = cells - 1 degrees of freedom), its p-value,
    how many of the given cells were pooled, and the cells that hold draws where none is expected (p-value 0)."""

    statistic: float
    dof: int
    p_value: float
    cells: int
    pooled: int
    impossible: int
    worst: str  # the cells that add most to the statistic, for a failure's message

    def describe(self, level: float) -> str:
        return (f"chi-square {self.statistic:.1f}, {self.dof} degrees of freedom ({self.cells} cells, {self.pooled} "
                f"pooled; {self.impossible} with draws where none is expected): p-value {self.p_value:.3g} against "
                f"the level {level:.3g}; most off: {self.worst}")


def pooled_cells(observed, expected, min_expected: float = MIN_EXPECTED) -> list[list[int]]:
    """The cells of the test, as lists of indices into the flattened counts: in increasing expected count, each
    cell expected to hold fewer than ``min_expected`` draws joins a pool, which becomes a cell once its expected
    count reaches ``min_expected``; a pool left short at the end joins the last pool (or, without one, the
    smallest cell). Cells with neither draws nor expected ones are left out."""
    obs, exp = np.asarray(observed).ravel(), np.asarray(expected).ravel()
    pools: list[list[int]] = []
    cells: list[list[int]] = []
    pool: list[int] = []
    pool_expected = 0.0
    for i in np.argsort(exp, kind="stable").tolist():
        if exp[i] == 0 and obs[i] == 0:
            continue
        if exp[i] >= min_expected:
            cells.append([i])
            continue
        pool.append(i)
        pool_expected += exp[i]
        if pool_expected >= min_expected:
            pools.append(pool)
            pool, pool_expected = [], 0.0
    if pool:
        if pools:
            pools[-1] += pool
        elif cells:
            cells[0] = pool + cells[0]
        else:
            cells = [pool]
    return pools + cells


def _name(cell: list[int]) -> str:
    return f"cell {cell[0]}" if len(cell) == 1 else f"a pool of {len(cell)} cells"


def chi_square(observed, expected, min_expected: float = MIN_EXPECTED) -> ChiSquare:
    """Pearson's test of the counts ``observed`` against ``expected`` (arrays of one shape, any number of axes;
    the expected counts add up to the draws), low cells pooled (:func:`pooled_cells`)."""
    if np.shape(observed) != np.shape(expected):
        raise ValueError(f"observed counts of shape {np.shape(observed)}, expected ones of {np.shape(expected)}")
    obs = np.asarray(observed, np.float64).ravel()
    exp = np.asarray(expected, np.float64).ravel()
    if not (np.isfinite(obs).all() and np.isfinite(exp).all() and obs.min() >= 0 and exp.min() >= 0):
        raise ValueError("counts must be finite and non-negative")
    if abs(exp.sum() - obs.sum()) > TOTAL_RTOL * obs.sum():
        raise ValueError(f"the expected counts add up to {exp.sum():.6g}, the draws to {obs.sum():.6g}")
    cells = pooled_cells(obs, exp, min_expected)
    if len(cells) < 2:
        raise ValueError(f"{len(cells)} cell after pooling: no degree of freedom to test (too few draws)")
    cell_obs = np.array([obs[c].sum() for c in cells])
    cell_exp = np.array([exp[c].sum() for c in cells])
    impossible = int(((exp == 0) & (obs > 0)).sum())
    terms = (cell_obs - cell_exp) ** 2 / np.maximum(cell_exp, np.finfo(np.float64).tiny)
    statistic = float(terms.sum())
    worst = ", ".join(f"{_name(cells[j])}: {cell_obs[j]:.0f} drawn, {cell_exp[j]:.1f} expected"
                      for j in np.argsort(-terms, kind="stable")[:3])
    p_value = 0.0 if impossible else float(stats.chi2.sf(statistic, len(cells) - 1))
    return ChiSquare(statistic, len(cells) - 1, p_value, len(cells), sum(len(c) for c in cells if len(c) > 1),
                     impossible, worst)


def assert_follows(observed, expected, alpha: float = 0.01, tests: int = 1) -> ChiSquare:
    """Asserts that the counts ``observed`` may be drawn from ``expected``: the test (:func:`chi_square`) does not
    reject them at the level :func:`sidak_level` gives ``alpha`` over a family of ``tests``."""
    level = sidak_level(alpha, tests)
    result = chi_square(observed, expected)
    assert result.p_value >= level, f"the draws do not follow the expected counts: {result.describe(level)}"
    return result


def assert_rejects(observed, expected, alpha: float = 0.01, tests: int = 1) -> ChiSquare:
    """Asserts that the test rejects ``expected`` for the counts ``observed`` at the same level as
    :func:`assert_follows`: the check that a test has the power to see a wrong density."""
    level = sidak_level(alpha, tests)
    result = chi_square(observed, expected)
    assert result.p_value < level, f"the test does not reject a wrong density: {result.describe(level)}"
    return result
