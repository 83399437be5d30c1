"""Renders as real renderers write them: extremes, non-finite values and broken files (issue 5).

Every layer read by ``prep.exr.read_aovs`` is finite, float32, and follows the documented repair rule
(NaN -> 0, +inf -> the channel's largest finite value, -inf -> its smallest; finite values beyond float32
are clamped to float32 max); a file that cannot be read is one AOVError naming it, with nothing printed.
"""

import numpy as np
import pytest

from helpers import random_aovs
from prep import exr, features, metrics

F32_MAX = float(np.finfo(np.float32).max)
F16_MAX = float(np.finfo(np.float16).max)
LAYERS = sorted(random_aovs(1, 1))


def write(tmp_path, aovs, name="x-00004spp.exr", **kw):
    return exr.write_aovs(tmp_path / name, aovs, **kw)


def test_float32_max_without_a_default_layer_derives_a_finite_colour(tmp_path):
    aovs = random_aovs(6, 7)
    del aovs["default"]
    aovs["diffuse"][2, 3] = F32_MAX
    aovs["specular"][2, 3] = F32_MAX
    back = exr.read_aovs(write(tmp_path, aovs))
    assert np.isfinite(back["default"]).all()
    assert back["default"][2, 3].tolist() == [F32_MAX] * 3  # the float64 sum, clamped to float32
    expected = aovs["diffuse"].astype(np.float64) + aovs["specular"]
    mask = np.ones((6, 7), bool)
    mask[2, 3] = False
    np.testing.assert_allclose(back["default"][mask], expected[mask], rtol=1e-7)
    # and what reads it downstream stays finite: the metrics and both branches' features
    reference = exr.read_aovs(write(tmp_path, random_aovs(6, 7, variances=False), "x-00064spp.exr"),
                              variances=False)
    assert all(np.isfinite(v) for v in metrics.all_metrics(back["default"], reference["default"]).values())
    for branch in features.BRANCHES:
        assert np.isfinite(features.branch_features(back, branch)).all()


def test_finite_values_beyond_float32_are_clamped_when_written():
    image = np.array([[1e300, -1e300, 1.0, np.inf]])
    out = exr.to_float32(image)
    assert out.dtype == np.float32 and out.tolist() == [[F32_MAX, -F32_MAX, 1.0, np.inf]]
    half = exr.to_float32(np.array([1e6, 65504.0, -7e4, np.nan]), np.float16)
    assert half[:3].tolist() == [F16_MAX, 65504.0, -F16_MAX] and np.isnan(half[3])


def test_half_float_file_at_half_max_reads_finite(tmp_path):
    aovs = random_aovs(5, 6)
    aovs["specular"][1, 1] = 1e9  # more than half can hold: written as half max, not inf
    aovs["diffuse"][0, 0] = F16_MAX
    back = exr.read_aovs(write(tmp_path, aovs, half=True))
    assert back["specular"][1, 1].tolist() == [F16_MAX] * 3
    assert back["diffuse"][0, 0].tolist() == [F16_MAX] * 3
    assert all(np.isfinite(v).all() for v in back.values())


@pytest.mark.parametrize("value", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize("layer, with_default",
                         [(layer, True) for layer in LAYERS] + [(layer, False) for layer in LAYERS if layer != "default"])
def test_nonfinite_value_in_any_layer_is_repaired_by_the_documented_rule(tmp_path, layer, value, with_default):
    aovs = random_aovs(4, 5, seed=7)
    if not with_default:
        del aovs["default"]
    image = aovs[layer]
    channel = image[..., 1] if image.ndim == 3 else image
    finite = np.delete(channel.ravel(), 2 * 5 + 3).astype(np.float64)
    channel[2, 3] = value
    back = exr.read_aovs(write(tmp_path, aovs))
    assert all(np.isfinite(v).all() and v.dtype == np.float32 for v in back.values()), layer
    got = (back[layer][..., 1] if image.ndim == 3 else back[layer])[2, 3]
    expected = 0.0 if np.isnan(value) else (finite.max() if value > 0 else finite.min())
    assert got == np.float32(expected)
    if not with_default:  # derived after the repair, from repaired layers
        np.testing.assert_allclose(back["default"], back["diffuse"].astype(np.float64) + back["specular"],
                                   rtol=1e-7)


def test_a_layer_that_is_entirely_nonfinite_becomes_zero(tmp_path):
    aovs = random_aovs(3, 4)
    aovs["depth"][:] = np.inf
    aovs["normal"][..., 0] = np.nan
    back = exr.read_aovs(write(tmp_path, aovs))
    assert (back["depth"] == 0).all() and (back["normal"][..., 0] == 0).all()


def test_truncated_file_is_one_error_naming_it_and_prints_nothing(tmp_path, capfd):
    good = write(tmp_path, random_aovs(16, 16), "good-00004spp.exr")
    data = good.read_bytes()
    bad = tmp_path / "cut-00004spp.exr"
    bad.write_bytes(data[: len(data) // 2])
    capfd.readouterr()
    with pytest.raises(exr.AOVError) as err:
        exr.read_aovs(bad)
    assert str(bad) in str(err.value) and "not a readable OpenEXR file" in str(err.value)
    assert "\n" not in str(err.value)
    assert exr.read_header(bad) == (16, 16)  # the header is whole; only the pixels are cut
    out = capfd.readouterr()
    assert out.out == "" and out.err == ""


def test_header_check_finds_a_missing_layer_without_decoding(tmp_path):
    aovs = random_aovs(9, 8)
    del aovs["normalVariance"]
    path = write(tmp_path, aovs)
    with pytest.raises(exr.AOVError, match="normalVariance"):
        exr.read_header(path)
    assert exr.read_header(path, variances=False) == (9, 8)
