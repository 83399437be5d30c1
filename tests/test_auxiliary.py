"""The auxiliaries a frame gives the networks (prep.auxiliary): the variance estimated from a layer, the NLM
prefilter on analytic layers against float64 numpy, the oracle's replacement, OIDN's filters against pyoidn."""

import numpy as np
import pytest

from prep import auxiliary, baselines
from prep.errors import KpcnError

H, W = 40, 48
SIGMA = 0.05


def _bands(channels: int = 3) -> np.ndarray:
    """A piecewise-constant layer: four vertical bands, a different value in each channel."""
    values = np.array([[0.2, 0.6, 0.4], [0.7, 0.3, 0.5], [0.35, 0.8, 0.1], [0.55, 0.15, 0.9]])[:, :channels]
    return np.repeat(values, W // 4, axis=0)[None].repeat(H, axis=0)


def _noisy(clean: np.ndarray, seed: int = 3) -> np.ndarray:
    return clean + np.random.default_rng(seed).normal(0.0, SIGMA, clean.shape)


def _band_box_mean(noisy: np.ndarray, clean: np.ndarray) -> np.ndarray:
    """Float64 numpy: each pixel the mean of the pixels of its 3 x 3 box that lie in its own band (the ideal
    local average that knows the edges)."""
    out = np.empty_like(noisy)
    for y in range(H):
        for x in range(W):
            ys, xs = slice(max(y - 1, 0), y + 2), slice(max(x - 1, 0), x + 2)
            same = np.all(clean[ys, xs] == clean[y, x], axis=-1)
            out[y, x] = noisy[ys, xs][same].mean(axis=0)
    return out


def test_local_variance_reads_independent_noise_and_zero_on_a_constant_layer_and_a_clean_edge():
    flat = _noisy(np.full((H, W, 3), 0.5))
    v = auxiliary.local_variance(flat)
    assert v.shape == (H, W) and v.dtype == np.float32
    # the smallest of four estimates reads a little low: within 40% of sigma^2 on average
    assert 0.6 * SIGMA**2 < float(v.mean()) < 1.1 * SIGMA**2
    assert not auxiliary.local_variance(np.full((H, W, 3), 0.5)).any()
    assert not auxiliary.local_variance(_bands()).any()  # one direction runs along the edge


@pytest.mark.parametrize("name, channels", [("albedo", 3), ("normal", 3), ("depth", 1)])
def test_nlm_lowers_the_error_of_a_noisy_piecewise_constant_layer_at_least_as_a_band_aware_box_does(name, channels):
    clean = _bands(channels)
    clean = clean[..., 0] * 4.0 if name == "depth" else clean  # a depth in scene units, no clip
    noisy = _noisy(clean)
    got = auxiliary.nlm_layer(noisy.astype(np.float32), name)
    assert got.shape == noisy.shape and got.dtype == np.float32
    raw = np.mean((noisy - clean) ** 2)
    stack = (lambda a: a[..., None]) if clean.ndim == 2 else (lambda a: a)
    predicted = raw / np.mean((_band_box_mean(stack(noisy), stack(clean)) - stack(clean)) ** 2)
    assert predicted > 5.0  # the box's own factor: about 9 inside a band, less beside an edge
    assert raw / np.mean((got - clean) ** 2) >= predicted


@pytest.mark.parametrize("name, channels", [("albedo", 3), ("normal", 3), ("depth", 1)])
def test_a_noiseless_layer_is_returned_as_it_is(name, channels):
    for clean in (np.full((H, W, channels), 0.3), _bands(channels)):
        clean = clean[..., 0] * 4.0 if name == "depth" else clean
        got = auxiliary.nlm_layer(clean.astype(np.float32), name)
        np.testing.assert_allclose(got, clean, rtol=1e-6, atol=1e-7)


def test_a_frame_variance_guides_the_filter_where_it_has_one():
    clean = _bands()
    noisy = _noisy(clean).astype(np.float32)
    zero = auxiliary.nlm_layer(noisy, "albedo", np.zeros((H, W), np.float32))  # no variance: estimated
    given = auxiliary.nlm_layer(noisy, "albedo", np.full((H, W), SIGMA**2, np.float32))
    assert np.mean((zero - clean) ** 2) < np.mean((noisy - clean) ** 2)
    assert np.mean((given - clean) ** 2) < np.mean((noisy - clean) ** 2)
    assert not np.array_equal(zero, given)


def _layers(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    layers = {k: rng.uniform(0, 1, (8, 10, 3)).astype(np.float32)
              for k in ("default", "diffuse", "specular", "albedo", "normal")}
    layers["depth"] = rng.uniform(1, 5, (8, 10)).astype(np.float32)
    layers.update({k: rng.uniform(0, 0.1, (8, 10)).astype(np.float32)
                   for k in ("colorVariance", "diffuseVariance", "albedoVariance")})
    return layers


def test_the_oracle_gives_the_clean_auxiliaries_and_every_other_layer_unchanged():
    noisy, clean = _layers(1), _layers(2)
    kept = {k: v.copy() for k, v in noisy.items()}
    got = auxiliary.auxiliaries(noisy, "clean", clean=clean)
    assert set(got) == set(noisy)
    for k in got:
        expected = clean[k] if k in auxiliary.AUXILIARIES else kept[k]
        assert got[k].dtype == expected.dtype and np.array_equal(got[k], expected), k
        if k not in auxiliary.AUXILIARIES:
            assert got[k] is noisy[k]
    assert all(np.array_equal(noisy[k], kept[k]) for k in noisy)  # the frame's own layers untouched
    raw = auxiliary.auxiliaries(noisy, "raw")
    assert raw.keys() == noisy.keys() and all(raw[k] is noisy[k] for k in noisy)


def test_a_method_or_clean_render_that_does_not_fit_is_refused():
    with pytest.raises(KpcnError, match="expected one of raw, clean, oidn, nlm"):
        auxiliary.auxiliaries(_layers(1), "blur")
    with pytest.raises(KpcnError, match="give the cleaner render"):
        auxiliary.auxiliaries(_layers(1), "clean")
    small = {k: v[:4] for k, v in _layers(2).items()}
    with pytest.raises(KpcnError, match="its albedo is"):
        auxiliary.auxiliaries(_layers(1), "clean", clean=small)


@pytest.mark.skipif(not baselines.oidn_available(), reason="pyoidn (the optional extra oidn) is not installed")
def test_oidn_filters_the_albedo_and_normal_as_a_hand_call_of_pyoidn_does():
    import pyoidn

    layers = _layers(4)
    layers["normal"] = layers["normal"] * 2 - 1
    got = auxiliary.auxiliaries(layers, "oidn")

    def by_hand(name, image):
        out = np.empty_like(image)
        with pyoidn.Device() as device:
            device.commit()
            with pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT) as flt:
                flt.set_image(name, np.ascontiguousarray(image), pyoidn.OIDN_FORMAT_FLOAT3)
                flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3)
                flt.set_quality(pyoidn.OIDN_QUALITY_HIGH)
                flt.commit()
                flt.execute()
        return out

    np.testing.assert_array_equal(got["albedo"], by_hand(pyoidn.OIDN_IMAGE_ALBEDO, layers["albedo"]))
    np.testing.assert_array_equal(got["normal"], by_hand(pyoidn.OIDN_IMAGE_NORMAL, layers["normal"]))
    top = float(layers["depth"].max())
    grey = np.repeat((layers["depth"] / top)[..., None], 3, axis=-1).astype(np.float32)
    np.testing.assert_allclose(got["depth"], by_hand(pyoidn.OIDN_IMAGE_ALBEDO, grey).mean(-1) * top, rtol=1e-6)
    assert got["default"] is layers["default"]
