"""``prep.inputs``: the input sets and which serves which, two renders of one frame joined as one, and the studies'
variance of two renders from their difference (what a model of each set reads, ``restrict``, is held in
``test_input_sets.py`` with the shards and runs cut for it)."""

import numpy as np
import pytest
from helpers.tiny import random_aovs

from kpcn_keras.studies.pair_variance import pair_layers, pair_variance
from prep import exr
from prep.errors import OptionError
from prep.inputs import INPUT_SETS, InputSet, mean_layers


def test_input_sets_are_named_and_named_back():
    for name in INPUT_SETS:
        assert InputSet.named(name).name == name
    assert InputSet(split=False, variance=True).name == "no-split"
    with pytest.raises(OptionError, match="inputs must be one of full, no-variance, no-split, no-split-no-variance, "
                                          "got 'half'"):
        InputSet.named("half")


def test_a_set_serves_every_frame_that_has_at_least_what_it_reads():
    full, no_var, no_split, neither = (InputSet.named(n) for n in INPUT_SETS)
    assert neither.serves(full) and neither.serves(no_split) and neither.serves(no_var)
    assert not full.serves(no_var) and not full.serves(no_split)
    assert no_split.serves(full) and not no_split.serves(no_var)
    assert no_var.serves(full) and not no_var.serves(no_split)


def test_the_variance_of_two_half_renders_matches_the_analytic_variance_within_a_statistical_bound():
    # each render is the mean of n samples of N(mu, sigma^2), sigma smooth over the image: the pair's mean
    # has variance sigma^2 / (2 n)
    rng = np.random.default_rng(7)
    h = w = 96
    n = 4
    y, x = np.mgrid[0:h, 0:w] / h
    mu = 1.0 + np.sin(6 * x)[..., None] * np.ones(3)
    sigma = (0.2 + 0.3 * y)[..., None] * np.ones(3)
    renders = [mu + sigma * rng.standard_normal((n, h, w, 3)).mean(axis=0) for _ in range(2)]
    truth = (sigma[..., 0] ** 2) / (2 * n)
    for radius in (0, 1):
        est = pair_variance(renders[0], renders[1], radius=radius).astype(np.float64)
        ratio = est / truth
        # unsmoothed: per pixel (a - b)^2 / 4 averaged over 3 channels is truth * chi2_3 / 3 (variance 2/3), so
        # the mean ratio over h*w pixels has standard deviation sqrt(2 / (3 h w)); the box keeps the mean and
        # correlates neighbours (a bound of the unsmoothed std x 3 holds for any box of 9 pixels)
        std = np.sqrt(2.0 / (3 * h * w)) * (3 if radius else 1)
        assert abs(ratio.mean() - 1.0) < 5 * std, (radius, ratio.mean())
    smoothed = pair_variance(renders[0], renders[1]).astype(np.float64) / truth
    raw = pair_variance(renders[0], renders[1], radius=0).astype(np.float64) / truth
    assert smoothed.std() < raw.std() / 2  # the box averages about 9 pixels' worth of degrees of freedom


def test_pair_layers_average_each_layer_and_make_every_variance():
    a, b = random_aovs(5, 6, seed=1, variances=False), random_aovs(5, 6, seed=2, variances=False)
    both = pair_layers(a, b)
    np.testing.assert_allclose(both["default"], (a["default"].astype(np.float64) + b["default"]) / 2, rtol=1e-6)
    assert set(exr.VARIANCE_LAYERS) <= set(both)
    d = a["depth"].astype(np.float64) - b["depth"]
    np.testing.assert_allclose(pair_variance(a["depth"], b["depth"], radius=0), d * d / 4, rtol=1e-6)


def test_two_renders_join_as_one_render_of_all_their_samples():
    a, b = random_aovs(5, 6, seed=1), random_aovs(5, 6, seed=2)
    del b["specularVariance"]  # a variance one render lacks is not made up
    both = mean_layers(a, b)
    for k in b:
        a64, b64 = a[k].astype(np.float64), b[k].astype(np.float64)
        # the mean of two independent renders has a quarter of their summed variance
        expected = (a64 + b64) / 4 if k in exr.VARIANCE_LAYERS else (a64 + b64) / 2
        np.testing.assert_allclose(both[k], expected, rtol=1e-6, err_msg=k)
    assert "specularVariance" not in both and both["default"].dtype == np.float32
