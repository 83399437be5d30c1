"""BSDF sampling against its own density: directions drawn by ``bsdf_sample`` are distributed as the pdf
``bsdf_eval`` reports (a chi-square test over solid-angle bins, the mass below the horizon included), and
GGX draws visible normals, whose weight f cos / pdf never exceeds F (float64 references written here)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.chi_square import assert_follows, assert_rejects

from prep.render import EFFECTS
from prep.render.kernels import kernel_for
from prep.render.tracer import GLOSSY, PLASTIC

N = (0.0, 0.0, 1.0)


def ggx_pdf_visible(wo, wi, alpha):
    """Density of wi when h is drawn from the GGX normals visible from wo: G1(wo) D(h) / (4 cos_o)."""
    h = np.add(wo, wi)
    h /= np.linalg.norm(h)
    a2 = alpha * alpha
    d = a2 / (math.pi * (h[2] ** 2 * (a2 - 1) + 1) ** 2)
    # Smith G1 for GGX, in the tan form: 2 / (1 + sqrt(1 + a2 tan^2))
    tan2 = (1 - wo[2] ** 2) / wo[2] ** 2
    g1 = 2 / (1 + math.sqrt(1 + a2 * tan2))
    return g1 * d / (4 * wo[2])


def direction(theta_deg):
    t = math.radians(theta_deg)
    return (math.sin(t), 0.0, math.cos(t))


def draws(k, mk, kd, ks, alpha, wo, n, seed):
    rng = np.random.default_rng(seed)
    u = rng.random((n, 3))
    out = np.full((n, 3), np.nan)
    for i in range(n):
        wi, ok = k.bsdf_sample(mk, kd, ks, alpha, N, wo, u[i, 0], u[i, 1], u[i, 2])
        if ok:
            out[i] = wi
    return out


CASES = [(GLOSSY, 0.3, 30.0), (GLOSSY, 0.6, 80.0), (PLASTIC, 0.2, 60.0)]


# bins uniform in (cos theta, phi): equal solid angle; each bin's expected mass by midpoint quadrature of the pdf
NC, NPHI, SUB = 10, 16, 12


def binned(wi):
    """Counts of the directions ``wi`` (NaN rows: none drawn, below the horizon) in the (cos theta, phi) bins, the
    draws below the horizon in a last bin."""
    above = ~np.isnan(wi[:, 0])
    cos_i = np.clip(wi[above, 2], 0, 1 - 1e-12)
    phi = np.mod(np.arctan2(wi[above, 1], wi[above, 0]), 2 * math.pi)
    observed = np.histogram2d(cos_i, phi, bins=[NC, NPHI], range=[[0, 1], [0, 2 * math.pi]])[0]
    return np.append(observed.ravel(), len(wi) - above.sum())


def expected_counts(k, mk, kd, ks, alpha, wo, n):
    """The counts of :func:`binned` that ``n`` draws from ``bsdf_eval``'s pdf give, the mass it leaves outside the
    hemisphere (drawn below the horizon) in the last bin."""
    cc = (np.arange(NC * SUB) + 0.5) / (NC * SUB)
    pp = (np.arange(NPHI * SUB) + 0.5) / (NPHI * SUB) * 2 * math.pi
    dens = np.empty((NC * SUB, NPHI * SUB))
    for a, c in enumerate(cc):
        s = math.sqrt(1 - c * c)
        for b, p in enumerate(pp):
            dens[a, b] = k.bsdf_eval(mk, kd, ks, alpha, N, wo, (s * math.cos(p), s * math.sin(p), c))[2]
    cell = (1.0 / (NC * SUB)) * (2 * math.pi / (NPHI * SUB))
    expected = dens.reshape(NC, SUB, NPHI, SUB).sum(axis=(1, 3)) * cell * n
    below_expected = n - expected.sum()
    assert below_expected > -0.01 * n, "the pdf integrates to more than 1 over the hemisphere"
    return np.append(expected.ravel(), max(below_expected, 0.0))


@pytest.mark.parametrize("mk, alpha, theta", CASES, ids=["glossy-0.3-30", "glossy-0.6-80", "plastic-0.2-60"])
def test_sampled_directions_follow_the_reported_pdf(mk, alpha, theta):
    k = kernel_for(EFFECTS)
    kd, ks = (0.5, 0.4, 0.3), (0.04, 0.04, 0.04)
    wo = direction(theta)
    n = 40000
    observed = binned(draws(k, mk, kd, ks, alpha, wo, n, seed=1))
    # one test per case: together they reject a right sampler with probability 1e-4
    family = dict(alpha=1e-4, tests=len(CASES))
    assert_follows(observed, expected_counts(k, mk, kd, ks, alpha, wo, n), **family)
    # the same draws reject the pdf of a roughness a quarter higher
    assert_rejects(observed, expected_counts(k, mk, kd, ks, 1.25 * alpha, wo, n), **family)


@pytest.mark.parametrize("alpha, theta", [(0.2, 45.0), (0.8, 85.0)])
def test_glossy_pdf_is_the_visible_normal_density(alpha, theta):
    k = kernel_for(EFFECTS)
    wo = direction(theta)
    rng = np.random.default_rng(2)
    for _ in range(20):
        v = rng.normal(size=3)
        v[2] = abs(v[2]) + 0.05
        v /= np.linalg.norm(v)
        pdf = k.bsdf_eval(GLOSSY, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), alpha, N, wo, tuple(v))[2]
        np.testing.assert_allclose(pdf, ggx_pdf_visible(wo, v, alpha), rtol=1e-9)


def test_glossy_sample_weight_never_exceeds_the_fresnel_factor():
    # with F = 1 the weight f cos / pdf of a visible-normal sample is G1(wi) <= 1 at every angle; drawing
    # h from D alone gives weights far above 1 at grazing incidence (the fireflies of rough metals)
    k = kernel_for(EFFECTS)
    for alpha, theta in [(0.3, 50.0), (0.9, 88.0)]:
        wo = direction(theta)
        wi = draws(k, GLOSSY, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), alpha, wo, 4000, seed=3)
        weights = []
        for v in wi[~np.isnan(wi[:, 0])]:
            _, fs, pdf = k.bsdf_eval(GLOSSY, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0), alpha, N, wo, tuple(v))
            weights.append(fs[0] * v[2] / pdf)
        assert len(weights) > 3000
        assert max(weights) <= 1.0 + 1e-9, f"alpha {alpha}, theta {theta}: weight up to {max(weights):.3f}"
