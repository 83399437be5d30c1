"""``kpcn_keras.risk.pair_risk``: the error of a denoiser's output of two renders' mean, estimated from the two
renders alone, against the true error of linear denoisers on heavy-tailed, heteroscedastic noise whose colour and
albedo share part of it (as a path tracer's do), over many independent pairs."""

import numpy as np
import pytest

from kpcn_keras.risk import pair_risk
from prep.inputs import box_mean

H = W = 24
TRIALS = 1000


def _blur(image: np.ndarray, radius: int) -> np.ndarray:
    return np.stack([box_mean(image[..., i], radius) for i in range(3)], -1)


def _denoisers():
    """Two affine denoisers of (colour, albedo): a box blur, and a smaller blur guided by the albedo's detail
    (so the albedo's noise, correlated with the colour's, reaches the output)."""
    return {
        "blur": lambda colour, albedo: _blur(colour, 2),
        "guided": lambda colour, albedo: _blur(colour, 1) + 0.5 * (albedo - _blur(albedo, 1)),
    }


def _render(clean, albedo, sigma, rng):
    """One render: colour and albedo with skewed (gamma 0.3, unit variance) noise, a share of it in common."""
    shared = (rng.gamma(0.3, 1.0, clean.shape) - 0.3) / np.sqrt(0.3)
    own = (rng.gamma(0.3, 1.0, clean.shape) - 0.3) / np.sqrt(0.3)
    return clean + sigma * shared, albedo + 0.2 * sigma * (0.7 * shared + 0.7 * own)


def _trials(seed: int):
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W] / H
    clean = (0.5 + 0.4 * np.sin(7 * x) * np.cos(5 * y))[..., None] * np.array([1.0, 0.8, 0.6])
    albedo = np.clip(clean * 0.9, 0, 1)
    sigma = (0.05 + 0.4 * y)[..., None] * np.ones(3)
    weight = 1.0 / (clean**2 + 0.01)  # held fixed, as the guard holds its weight
    out = {name: {"estimate": [], "naive": [], "true": []} for name in _denoisers()}
    for _ in range(TRIALS):
        (ca, aa), (cb, ab) = _render(clean, albedo, sigma, rng), _render(clean, albedo, sigma, rng)
        m, d, am = (ca + cb) / 2, (ca - cb) / 2, (aa + ab) / 2
        for name, f in _denoisers().items():
            fm, fa, fb = f(m, am), f(ca, aa), f(cb, ab)
            out[name]["estimate"].append(pair_risk(weight, m, d, fm, fa, fb).mean())
            out[name]["naive"].append((weight * ((fm - m) ** 2 - d**2)).mean())  # without the covariance term
            out[name]["true"].append((weight * (fm - clean) ** 2).mean())
    return {name: {k: np.array(v) for k, v in rows.items()} for name, rows in out.items()}


@pytest.mark.slow
def test_the_pair_estimate_of_a_linear_denoisers_error_is_unbiased_on_skewed_correlated_noise():
    for name, rows in _trials(3).items():
        diff = rows["estimate"] - rows["true"]
        se = diff.std(ddof=1) / np.sqrt(TRIALS)
        # unbiased: the mean difference from the true error within 4 standard errors of 0 ...
        assert abs(diff.mean()) < 4 * se, (name, diff.mean(), se)
        # ... a bound tight enough to matter: the estimate without the covariance term misses it by far more
        naive = rows["naive"] - rows["true"]
        assert abs(naive.mean()) > 10 * max(se, naive.std(ddof=1) / np.sqrt(TRIALS)), (name, naive.mean(), se)


@pytest.mark.slow
def test_the_pair_estimate_ranks_two_denoisers_as_their_true_errors_do_on_average():
    rows = _trials(4)
    est = rows["guided"]["estimate"] - rows["blur"]["estimate"]
    true = rows["guided"]["true"] - rows["blur"]["true"]
    se = (est - true).std(ddof=1) / np.sqrt(TRIALS)
    assert abs((est - true).mean()) < 4 * se
    assert abs(true.mean()) > 4 * se  # the two differ by more than the estimate's error: the ranking is tested
