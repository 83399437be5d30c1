import numpy as np
import pytest
from helpers.numerics import F32_EPS, F32_TINY, PROPERTY, renders
from helpers.references import assert_features_match_reference
from helpers.tiny import random_aovs
from hypothesis import given, settings

from prep import colour, exr, features
from prep.colour import LOG_COLOUR_MAX
from prep.features import reference_features


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
    np.testing.assert_allclose(colour.diffuse_from_log(d, aovs["albedo"]), aovs["diffuse"], rtol=1e-5)
    np.testing.assert_allclose(colour.specular_from_log(s), aovs["specular"], rtol=1e-5, atol=1e-6)


def test_unknown_branch_is_named():
    with pytest.raises(ValueError, match="'glossy'"):
        features.branch_features(random_aovs(4, 4), "glossy")


def test_float32_and_float64_renders_give_the_same_features():
    aovs = random_aovs(11, 13, seed=9)
    wide = {name: image.astype(np.float64) for name, image in aovs.items()}
    for branch in features.BRANCHES:
        np.testing.assert_array_equal(features.branch_features(aovs, branch), features.branch_features(wide, branch))


@pytest.mark.parametrize("branch", features.BRANCHES)
def test_a_window_has_the_whole_image_features_bit_for_bit(branch):
    aovs = random_aovs(23, 31, seed=5)
    aovs["depth"][0, 0] = 1e3  # the depth scale comes from a pixel outside most windows
    whole = features.branch_features(aovs, branch)
    scale = features.depth_scale(aovs["depth"])
    windows = [(0, 23, 0, 31), (0, 1, 0, 1), (22, 23, 30, 31), (5, 12, 7, 8), (3, 23, 0, 17), (10, 11, 0, 31)]
    for y0, y1, x0, x1 in windows:
        np.testing.assert_array_equal(features.branch_features(aovs, branch, (y0, y1, x0, x1), scale=scale),
                                      whole[y0:y1, x0:x1])
        np.testing.assert_array_equal(features.branch_features(aovs, branch, (y0, y1, x0, x1)), whole[y0:y1, x0:x1])


def test_a_window_outside_the_image_is_refused():
    with pytest.raises(ValueError, match=r"\(0, 5, 3, 3\)"):
        features.branch_features(random_aovs(4, 4), "diffuse", (0, 5, 3, 3))


# ---------------------------------------------------------------- hard numbers (from test_numerics)


@settings(max_examples=60, **PROPERTY)
@given(aovs=renders())
def test_features_of_any_finite_float32_render_match_float64_and_stay_in_documented_ranges(aovs):
    assert_features_match_reference(aovs)


@settings(max_examples=60, **PROPERTY)
@given(aovs=renders())
def test_colour_transform_inverses_recover_the_clamped_input_to_float32_rounding(aovs):
    # c is rounded to float32 (relative 2^-24), which expm1 turns into a relative error of at most
    # (c + 1) * 2^-24 <= (LOG_COLOUR_MAX + 1) * 2^-24; subnormal inputs keep an absolute error of ~F32_TINY
    rtol = (LOG_COLOUR_MAX + 1) * F32_EPS / 2
    albedo = aovs["albedo"]
    diffuse = colour.diffuse_from_log(features.branch_colour(aovs, "diffuse"), albedo)
    specular = colour.specular_from_log(features.branch_colour(aovs, "specular"))
    for got, x in ((diffuse, aovs["diffuse"]), (specular, aovs["specular"])):
        assert np.isfinite(got).all() and got.min() >= 0
        np.testing.assert_allclose(got, np.maximum(x.astype(np.float64), 0.0), rtol=rtol, atol=2 * F32_TINY)
        assert np.isfinite(exr.to_float32(got)).all()
