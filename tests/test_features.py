import numpy as np
import pytest

from conftest import random_aovs
from prep import features
from prep.features import ALBEDO_EPS, REL_EPS


def reference_features(aovs, branch):
    """Independent float64 numpy version of the feature table in prep/features.py."""
    a = np.clip(aovs["albedo"].astype(np.float64), 0, 1)
    n = np.clip(aovs["normal"].astype(np.float64), -1, 1)
    depth = np.maximum(aovs["depth"].astype(np.float64), 0)
    d = depth / depth.max() if depth.max() > 0 else np.zeros_like(depth)
    x = aovs[branch].astype(np.float64)
    var = np.maximum(aovs[f"{branch}Variance"].astype(np.float64), 0)[..., None] * np.ones(3)
    if branch == "diffuse":
        x, var = x / (a + ALBEDO_EPS), var / (a + ALBEDO_EPS) ** 2
    x = np.maximum(x, 0)
    c = np.log1p(x)
    v_c = (var / (1 + x) ** 2).mean(-1)

    def dx(img):
        out = np.zeros_like(img)
        out[:, :-1] = img[:, 1:] - img[:, :-1]
        return out

    def dy(img):
        out = np.zeros_like(img)
        out[:-1] = img[1:] - img[:-1]
        return out

    rel = lambda v, m2: np.log1p(np.maximum(v, 0) / (m2 + REL_EPS))  # noqa: E731
    scale2 = 1 / depth.max() ** 2 if depth.max() > 0 else 0.0
    chans = [c, dx(c), dx(n), dx(a), dx(d)[..., None], dy(c), dy(n), dy(a), dy(d)[..., None],
             rel(v_c, (c * c).mean(-1))[..., None],
             rel(aovs["normalVariance"].astype(np.float64), (n * n).mean(-1))[..., None],
             rel(aovs["albedoVariance"].astype(np.float64), (a * a).mean(-1))[..., None],
             rel(aovs["depthVariance"].astype(np.float64) * scale2, d * d)[..., None]]
    return np.concatenate(chans, axis=-1)


@pytest.mark.parametrize("branch", ["diffuse", "specular"])
def test_features_equal_float64_reference(branch):
    aovs = random_aovs(19, 26, seed=7)
    aovs["albedo"][0, 0] = [1.5, -0.2, 0.0]  # out of range values are clipped the same way
    got = features.branch_features(aovs, branch)
    assert got.shape == (19, 26, features.NUM_FEATURES) and got.dtype == np.float32
    np.testing.assert_allclose(got, reference_features(aovs, branch), rtol=2e-6, atol=2e-6)


@pytest.mark.parametrize("branch", ["diffuse", "specular"])
def test_features_stay_finite_and_in_range_for_extreme_input(branch):
    big = np.finfo(np.float32).max
    aovs = random_aovs(8, 8, seed=2)
    aovs["diffuse"][:4] = big
    aovs["specular"][:, :4] = big
    aovs["diffuse"][4:, :2] = -big
    for name in ("diffuseVariance", "specularVariance", "normalVariance", "albedoVariance", "depthVariance"):
        aovs[name][::2] = big
        aovs[name][1::2] = -1.0
    aovs["albedo"][:] = 0.0
    aovs["depth"][:] = np.float32(1e-38)  # a tiny depth range makes the depth scale huge
    aovs["depth"][0, 0] = big
    got = features.branch_features(aovs, branch)
    assert np.isfinite(got).all()
    assert got[..., :3].min() >= 0 and got[..., :3].max() <= 95
    assert np.abs(got[..., 3:23]).max() <= 95
    assert got[..., 23:].min() >= 0 and got[..., 23:].max() < 300


def test_all_zero_render_gives_zero_features():
    aovs = {k: np.zeros_like(v) for k, v in random_aovs(5, 6).items()}
    for branch in features.BRANCHES:
        assert not features.branch_features(aovs, branch).any()


def test_colour_transforms_invert():
    aovs = random_aovs(9, 9, seed=4)
    d = features.branch_colour(aovs, "diffuse")
    s = features.branch_colour(aovs, "specular")
    np.testing.assert_array_equal(d, features.branch_features(aovs, "diffuse")[..., :3])
    np.testing.assert_allclose(features.diffuse_from_log(d, aovs["albedo"]), aovs["diffuse"], rtol=1e-5)
    np.testing.assert_allclose(features.specular_from_log(s), aovs["specular"], rtol=1e-5, atol=1e-6)


def test_unknown_branch_is_named():
    with pytest.raises(ValueError, match="'glossy'"):
        features.branch_features(random_aovs(4, 4), "glossy")
