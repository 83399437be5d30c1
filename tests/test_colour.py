"""prep.colour: each transform against a float64 formula of its own (Python's math module, one value at a time),
and each forward transform followed by its inverse giving back its input to float64 rounding, on values from 0 and
subnormals to 1e300 and past the clamps (negative colours and variances, albedos outside [0, 1])."""

import math

import numpy as np
import pytest

from prep import colour

EPS = np.finfo(np.float64).eps
TINY = np.finfo(np.float64).smallest_subnormal


def values(rng, n=4000, top=300):
    """0, subnormals, tiny, moderate and huge (up to 1e``top``) non-negative float64s, log-uniform in between."""
    fixed = [0.0, TINY, 1e-310, 1e-300, 1e-30, 1e-8, 0.5, 1.0, 2.0, 1e8, 1e30, 10.0 ** top]
    return np.concatenate([fixed, 10.0 ** rng.uniform(-320, top, n), rng.uniform(0, 10, n)])


def albedos(rng, n):
    """Albedos in [-0.5, 1.5]: 0, 1 and both sides of the clamp among them."""
    a = rng.uniform(-0.5, 1.5, n)
    a[:4] = [0.0, 1.0, -0.5, 1.5]
    return a


def elementwise(f, *arrays):
    return np.array([f(*args) for args in zip(*(np.asarray(a, np.float64).ravel() for a in arrays))])


def test_log_colour_is_log1p_of_the_clamped_colour_and_linear_colour_inverts_it():
    rng = np.random.default_rng(0)
    x = values(rng)
    c = colour.log_colour(x)
    # numpy's log1p and expm1 (SIMD on some CPUs) and libm's each within a few ulps of the true value
    np.testing.assert_allclose(c, elementwise(lambda v: math.log1p(max(v, 0.0)), x), rtol=4 * EPS, atol=0)
    np.testing.assert_allclose(colour.linear_colour(c), elementwise(math.expm1, c), rtol=4 * EPS, atol=0)
    # log1p's error of a few ulps in c grows by (1 + c) through exp; expm1 adds its own ulps
    back = colour.linear_colour(c)
    assert (np.abs(back - x) <= (1.0 + c) * 4 * EPS * x + TINY).all()
    assert (colour.log_colour(-x) == 0.0).all()  # a negative colour (a renderer's rounding) comes back as 0


def test_irradiance_divides_by_the_clipped_albedo_and_remodulate_inverts_it():
    rng = np.random.default_rng(1)
    x = values(rng, top=290)  # / ALBEDO_EPS keeps 1e290 finite
    a = albedos(rng, x.size)
    want = elementwise(lambda v, al: v / (min(max(al, 0.0), 1.0) + 0.00316), x, a)
    irr = colour.irradiance(x, a)
    np.testing.assert_array_equal(irr, want)  # one division: correctly rounded on both sides
    back = colour.remodulate(irr, a)
    # two roundings, a division and a product: 1 ulp each; subnormal quotients lose their low bits
    assert (np.abs(back - x) <= 2 * EPS * x + 2 * TINY / colour.ALBEDO_EPS).all()
    assert colour.ALBEDO_EPS == 0.00316 and colour.REL_EPS == 0.01  # the constants every shard set records


def test_remodulate_adds_the_epsilon_in_the_albedos_precision():
    """A float32 albedo (a frame's, the prefiltered one) gives its own albedo term rounded to float32, what every
    denoised frame has been made with: within 6e-8 of the float64 term."""
    rng = np.random.default_rng(2)
    a32 = albedos(rng, 1000).astype(np.float32)
    irr = 10.0 ** rng.uniform(-5, 5, 1000)
    term32 = elementwise(lambda al: float(np.float32(min(max(al, 0.0), 1.0)) + np.float32(0.00316)), a32)
    np.testing.assert_array_equal(colour.remodulate(irr, a32), irr * term32)
    np.testing.assert_allclose(colour.remodulate(irr, a32), colour.remodulate(irr, a32.astype(np.float64)), rtol=6e-8)


def test_branch_transforms_invert_each_other():
    rng = np.random.default_rng(3)
    x = values(rng, top=290)
    a = albedos(rng, x.size)
    d = colour.diffuse_to_log(x, a)
    np.testing.assert_allclose(d, elementwise(lambda v, al: math.log1p(v / (min(max(al, 0.0), 1.0) + 0.00316)), x, a),
                               rtol=4 * EPS, atol=0)
    assert (np.abs(colour.diffuse_from_log(d, a) - x) <= (1.0 + d) * 6 * EPS * x + 2 * TINY / colour.ALBEDO_EPS).all()
    s = colour.specular_to_log(x)
    assert (np.abs(colour.specular_from_log(s) - x) <= (1.0 + s) * 4 * EPS * x + TINY).all()
    # the two make the features' colour channels and the shards' references
    aovs = {"diffuse": x.reshape(-1, 1, 1).repeat(3, -1), "specular": x.reshape(-1, 1, 1).repeat(3, -1),
            "albedo": a.reshape(-1, 1, 1).repeat(3, -1)}
    from prep.features import branch_colour

    np.testing.assert_array_equal(branch_colour(aovs, "diffuse"), d.reshape(-1, 1, 1).repeat(3, -1).astype(np.float32))
    np.testing.assert_array_equal(branch_colour(aovs, "specular"), s.reshape(-1, 1, 1).repeat(3, -1).astype(np.float32))


def test_variance_through_the_transforms():
    rng = np.random.default_rng(4)
    v = np.concatenate([[0.0], 10.0 ** rng.uniform(-100, 100, 3000)])
    x = np.concatenate([[0.0], 10.0 ** rng.uniform(-30, 50, 3000)])
    rng.shuffle(x)
    vlog = colour.log_variance(v, x)
    np.testing.assert_allclose(vlog, elementwise(lambda a, b: a / (1.0 + b) ** 2, v, x), rtol=2 * EPS, atol=0)
    np.testing.assert_allclose(colour.linear_variance(vlog, x), v, rtol=2 * EPS, atol=0)
    a = albedos(rng, v.size)
    want = elementwise(lambda var, al: var / (min(max(al, 0.0), 1.0) + 0.00316) ** 2, v, a)
    np.testing.assert_allclose(colour.irradiance_variance(v, a), want, rtol=2 * EPS, atol=0)


def test_relative_variance_matches_float64_and_inverts():
    rng = np.random.default_rng(7)
    for _ in range(200):
        v, m = float(rng.uniform(0, 1e3) ** rng.uniform(0, 2)), float(rng.uniform(0, 100) * rng.integers(2))
        r = colour.relative_variance(v, m)
        assert r == pytest.approx(np.log1p(np.float64(v) / (np.float64(m) + colour.REL_EPS)), rel=1e-14, abs=0)
        assert colour.variance_of(r, m) == pytest.approx(v, rel=1e-12, abs=1e-300)
    # a renderer's negative variance (rounding) counts as 0
    assert colour.relative_variance(-3.0, 1.0) == 0.0


@pytest.mark.parametrize("v,m", [(0.0, 0.0), (TINY, 0.0), (1e-300, 1e10), (1e300, 0.0), (3.4e38, 1e-30), (1.0, 1e300)])
def test_relative_variance_inverts_at_the_ends(v, m):
    r = colour.relative_variance(v, m)
    assert r == pytest.approx(math.log1p(v / (m + 0.01)), rel=2 * EPS, abs=0)
    assert abs(colour.variance_of(r, m) - v) <= (1.0 + r) * 4 * EPS * v + 4 * TINY * (m + 0.01)


def test_bounds_are_those_of_float32_input():
    f32 = np.finfo(np.float32)
    assert colour.LOG_COLOUR_MAX == math.log1p(float(f32.max) / 0.00316)
    assert colour.RELVAR_MAX == pytest.approx(math.log1p(float(f32.max) / float(f32.smallest_subnormal) ** 2 / 0.01),
                                              rel=2 * EPS)
    # the clamp of FinalColour: each of the two branches' linear colours below a quarter of float32's largest
    assert math.expm1(colour.LOG_LINEAR_MAX) * (1.0 + colour.ALBEDO_EPS) * 2 < float(f32.max)
    assert math.expm1(colour.LOG_LINEAR_MAX) > float(f32.max) / 5


def test_tonemap_is_reinhard_then_gamma():
    rng = np.random.default_rng(5)
    x = np.concatenate([values(rng, top=300), -values(rng, n=100)])
    t = colour.tonemap(x)
    want = elementwise(lambda v: (max(v, 0.0) / (1.0 + max(v, 0.0))) ** (1.0 / 2.2), x)
    np.testing.assert_allclose(t, want, rtol=4 * EPS, atol=0)
    assert t.min() == 0.0 and t.max() == 1.0  # 1e300 / (1 + 1e300) rounds to 1


@pytest.mark.parametrize("branch", ["diffuse", "specular"])
def test_the_features_kernel_computes_these_transforms(branch):
    """The numba kernel of prep.features writes the transforms' per-pixel arithmetic itself (its on-disk cache sees
    only its own file): its buffers are these functions' values, its relative variances bit for bit."""
    from prep.features import branch_buffers

    rng = np.random.default_rng(6)
    h, w = 9, 11
    aovs = {name: 10.0 ** rng.uniform(-8, 8, (h, w, 3)) for name in ("diffuse", "specular")}
    aovs["diffuse"][0, 0] = -1.0
    aovs["albedo"] = albedos(rng, h * w * 3).reshape(h, w, 3)
    aovs["normal"] = rng.uniform(-1.2, 1.2, (h, w, 3))
    aovs["depth"] = rng.uniform(0, 5, (h, w))
    for name in ("diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance"):
        aovs[name] = 10.0 ** rng.uniform(-10, 10, (h, w))
        aovs[name][1, 1] = -2.0
    buffers, relvar = branch_buffers(aovs, branch)
    x, var = aovs[branch], np.maximum(aovs[f"{branch}Variance"], 0.0)[..., None]
    if branch == "diffuse":
        x, var = colour.irradiance(x, aovs["albedo"]), colour.irradiance_variance(var, aovs["albedo"])
    x = np.maximum(x, 0.0)
    # numba's log1p and numpy's (SIMD on some CPUs) may differ by an ulp or two
    np.testing.assert_allclose(buffers[:h, :w, :3], colour.log_colour(x), rtol=4 * EPS, atol=0)
    c = buffers[:h, :w, :3]
    vlog = colour.log_variance(var, x)
    want = elementwise(lambda v, m: colour.relative_variance(v, m), (vlog[..., 0] + vlog[..., 1] + vlog[..., 2]) / 3.0,
                       (c[..., 0] * c[..., 0] + c[..., 1] * c[..., 1] + c[..., 2] * c[..., 2]) / 3.0)
    np.testing.assert_allclose(relvar[..., 0].ravel(), want, rtol=8 * EPS, atol=0)
    for k, (guide, lo) in enumerate((("normal", -1.0), ("albedo", 0.0)), start=1):
        g = np.clip(aovs[guide], lo, 1.0)
        mean_square = ((0.0 + g[..., 0] * g[..., 0]) + g[..., 1] * g[..., 1] + g[..., 2] * g[..., 2]) / 3.0
        want = elementwise(lambda v, m: colour.relative_variance(v, m), aovs[f"{guide}Variance"], mean_square)
        np.testing.assert_array_equal(relvar[..., k].ravel(), want)
