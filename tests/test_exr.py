"""``prep.exr``: the AOV layout written and read back, and renders as real renderers write them: extremes,
non-finite values and broken files.

Every layer read by ``prep.exr.read_aovs`` is finite, float32, and follows the documented repair rule
(NaN -> 0, +inf -> the channel's largest finite value, -inf -> its smallest; finite values beyond float32
are clamped to float32 max); a file that cannot be read is one AOVError naming it, with nothing printed.
"""

import logging

import numpy as np
import pytest
from helpers.tiny import random_aovs

from prep import exr, features, metrics


@pytest.mark.parametrize("half", [False, True])
def test_round_trip_keeps_every_layer(tmp_path, half):
    aovs = random_aovs(17, 23, seed=1)
    path = exr.write_aovs(tmp_path / "scene-00004spp.exr", aovs, half=half)
    back = exr.read_aovs(path)
    assert set(back) == set(aovs)
    for name, image in aovs.items():
        assert back[name].shape == image.shape and back[name].dtype == np.float32
        expected = image.astype(np.float16).astype(np.float32) if half else image
        np.testing.assert_array_equal(back[name], expected, err_msg=name)


def test_missing_layer_is_named(tmp_path):
    aovs = random_aovs(8, 8)
    del aovs["albedoVariance"], aovs["normal"]
    path = exr.write_aovs(tmp_path / "broken-00004spp.exr", aovs)
    with pytest.raises(exr.AOVError) as err:
        exr.read_aovs(path)
    assert "normal" in str(err.value) and "albedoVariance" in str(err.value) and str(path) in str(err.value)


def test_a_folder_read_as_a_render_is_named_as_a_folder(tmp_path):
    with pytest.raises(exr.AOVError, match=f"^{tmp_path}: is a folder, expected an OpenEXR file$"):
        exr.read_header(tmp_path)


def test_reference_needs_no_variances_and_default_is_derived(tmp_path):
    aovs = random_aovs(8, 9, variances=False)
    del aovs["default"]
    back = exr.read_aovs(exr.write_aovs(tmp_path / "r-01024spp.exr", aovs), variances=False)
    np.testing.assert_allclose(back["default"], aovs["diffuse"] + aovs["specular"], rtol=1e-6)


def test_unreadable_file_is_an_error_naming_it(tmp_path):
    path = tmp_path / "garbage-00008spp.exr"
    path.write_bytes(b"not an exr at all")
    with pytest.raises(exr.AOVError, match="garbage-00008spp.exr"):
        exr.read_aovs(path)
    with pytest.raises(exr.AOVError, match="no such file"):
        exr.read_aovs(tmp_path / "absent-00008spp.exr")


def test_nonfinite_values_are_repaired_counted_and_reported(tmp_path, caplog):
    aovs = random_aovs(6, 7)
    aovs["diffuse"][1, 2, 0] = np.nan
    aovs["diffuse"][3, 3, 1] = np.inf
    aovs["depth"][0, 0] = -np.inf
    finite_max_g = np.max(np.delete(aovs["diffuse"][..., 1].ravel(), 3 * 7 + 3))
    path = exr.write_aovs(tmp_path / "nan-00004spp.exr", aovs)
    with caplog.at_level(logging.WARNING, logger="kpcn"):
        back = exr.read_aovs(path)
    assert back["diffuse"][1, 2, 0] == 0.0
    assert back["diffuse"][3, 3, 1] == finite_max_g
    assert back["depth"][0, 0] == np.min(aovs["depth"][np.isfinite(aovs["depth"])])
    assert all(np.isfinite(v).all() for v in back.values())
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 1 and "diffuse: 2" in messages[0] and "depth: 1" in messages[0]


def test_rgb_variance_layers_are_averaged(tmp_path):
    aovs = random_aovs(5, 5)
    rgb = np.random.default_rng(3).uniform(0, 1, (5, 5, 3)).astype(np.float32)
    aovs["colorVariance"] = rgb  # written as colorVariance.R/G/B
    back = exr.read_aovs(exr.write_aovs(tmp_path / "v-00004spp.exr", aovs))
    np.testing.assert_allclose(back["colorVariance"], rgb.mean(axis=-1), rtol=1e-6)


def test_reads_the_mitsuba_fixture(fixture_noisy, fixture_reference):
    noisy = exr.read_aovs(fixture_noisy)
    ref = exr.read_aovs(fixture_reference, variances=False)
    assert noisy["default"].shape == ref["default"].shape == (64, 64, 3)
    np.testing.assert_allclose(noisy["default"], noisy["diffuse"] + noisy["specular"], atol=1e-5)
    # that renderer's conventions: no hit -> zero depth, normal and albedo
    miss = noisy["depth"] == 0
    assert miss.any() and np.all(noisy["normal"][miss] == 0) and np.all(noisy["albedo"][miss] == 0)


def test_render_file_names():
    assert exr.render_filename("cornell-001", 8) == "cornell-001-00008spp.exr"
    assert exr.parse_render_filename("/x/cornell-001-00512spp.exr") == ("cornell-001", 512)
    with pytest.raises(exr.AOVError, match="spp.exr"):
        exr.parse_render_filename("cornell.exr")


def test_a_write_the_file_system_refuses_is_an_error_naming_the_file_and_leaves_nothing(tmp_path):
    # OpenEXR reports a failed write(2) as a RuntimeError naming the temporary file; files may not grow past
    # 16 kB here (RLIMIT_FSIZE: EFBIG, as a full disk gives ENOSPC)
    import resource

    from prep.errors import KpcnError

    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (16 << 10, hard))
    try:
        with pytest.raises(KpcnError) as raised:
            exr.write_aovs(tmp_path / "x.exr", random_aovs(64, 64))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert str(raised.value) == f"{tmp_path / 'x.exr'}: cannot write (File too large)"
    assert list(tmp_path.iterdir()) == []


def test_a_render_is_read_without_a_second_copy_of_its_pixels(tmp_path):
    import tracemalloc

    aovs = random_aovs(300, 200, seed=1)
    del aovs["default"]  # derived on reading
    exr.write_aovs(tmp_path / "r.exr", aovs)
    tracemalloc.start()
    try:
        back = exr.read_aovs(tmp_path / "r.exr")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    layer = 300 * 200 * 3 * 4  # one float32 RGB layer
    # the render itself and at most two layers more (one being assembled, a block of the derived default);
    # d097970 held the file's channels and the whole render at once: 2.6 times the render
    assert peak <= sum(image.nbytes for image in back.values()) + 2 * layer


def test_float32_layers_are_written_without_a_copy_of_their_pixels(tmp_path):
    import tracemalloc

    aovs = random_aovs(300, 200, seed=2)
    exr.write_aovs(tmp_path / "first.exr", aovs)  # imports what writing needs
    tracemalloc.start()
    try:
        exr.write_aovs(tmp_path / "w.exr", aovs)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # d097970 cast every channel through float64 and held a float32 copy of all of them: 6.7 MB here
    assert peak < 300 * 200 * 4  # less than one float32 channel
    back = exr.read_aovs(tmp_path / "w.exr")
    for name, image in aovs.items():
        np.testing.assert_array_equal(back[name], image)


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
                         [(layer, True) for layer in LAYERS]
                         + [(layer, False) for layer in LAYERS if layer != "default"])
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


def test_each_variance_layer_belongs_to_one_layer_of_the_layout():
    assert set(exr.VARIANCE_OF) == set(exr.RGB_LAYERS) | {"depth"}  # every layer has one, and only layers do
    assert exr.VARIANCE_LAYERS == tuple(exr.VARIANCE_OF.values()) and len(set(exr.VARIANCE_LAYERS)) == 6
    assert {exr.LAYER_OF_VARIANCE[exr.VARIANCE_OF[layer]] for layer in exr.VARIANCE_OF} == set(exr.VARIANCE_OF)
    assert set(exr.VARIANCE_LAYERS) <= set(exr.SCALAR_LAYERS)  # one value a pixel, whatever its layer's channels
