"""``prep.layouts``: each renderer's layout read as kpcn's, against float64 compositions of the same passes;
multi-part and single-part files alike; the one-line error of a layout kpcn does not read."""

from pathlib import Path

import numpy as np
import pytest
from helpers.exr_layouts import CYCLES5_RGB, cycles_channels, parts_of, write_channels

from prep import exr, layouts
from prep.exr import AOVError
from prep.inputs import InputSet


def _f64(channels, layer, comps="RGB"):
    return np.stack([channels[f"{layer}.{c}"].astype(np.float64) for c in comps], axis=-1)


def test_cycles_layers_are_the_composition_of_its_passes(tmp_path):
    ch = cycles_channels(9, 11, seed=1)
    frame = layouts.read(write_channels(tmp_path / "shot-00016spp.exr", ch, parts_of(ch)))
    assert frame.layout == "cycles" and frame.inputs == InputSet(split=True, variance=False)
    v = "ViewLayer"
    diffuse = (_f64(ch, f"{v}.Diffuse Direct") + _f64(ch, f"{v}.Diffuse Indirect")) * _f64(ch, f"{v}.Diffuse Color")
    specular = sum((_f64(ch, f"{v}.{lobe} Direct") + _f64(ch, f"{v}.{lobe} Indirect")) * _f64(ch, f"{v}.{lobe} Color")
                   for lobe in ("Glossy", "Transmission"))
    specular += sum(_f64(ch, f"{v}.{p}") for p in ("Emission", "Environment", "Volume Direct", "Volume Indirect"))
    np.testing.assert_allclose(frame.layers["diffuse"], diffuse, rtol=1e-6)
    np.testing.assert_allclose(frame.layers["specular"], specular, rtol=1e-6)
    # diffuse + specular is Combined, the renderer's own sum, to float precision
    np.testing.assert_allclose(frame.layers["diffuse"].astype(np.float64) + frame.layers["specular"],
                               frame.layers["default"], rtol=3e-7 * 16)
    np.testing.assert_array_equal(frame.layers["albedo"], _f64(ch, f"{v}.Diffuse Color").astype(np.float32))
    np.testing.assert_array_equal(frame.layers["normal"], _f64(ch, f"{v}.Normal", "XYZ").astype(np.float32))
    np.testing.assert_array_equal(frame.layers["depth"], ch[f"{v}.Denoising Depth.Z"])
    np.testing.assert_array_equal(frame.alpha, 1.0)
    assert frame.spp == 16


def test_a_multi_part_and_a_single_part_file_of_the_same_pixels_read_alike(tmp_path):
    ch = cycles_channels(8, 8, seed=2)
    multi = layouts.read(write_channels(tmp_path / "multi-00004spp.exr", ch, parts_of(ch)))
    single = layouts.read(write_channels(tmp_path / "single-00004spp.exr", ch))
    parts = [exr.read_image(tmp_path / f"{n}-00004spp.exr", header_only=True).parts for n in ("multi", "single")]
    assert len(parts[0]) == 19 and len(parts[1]) == 1
    assert multi.layers.keys() == single.layers.keys()
    for name in multi.layers:
        np.testing.assert_array_equal(multi.layers[name], single.layers[name], err_msg=name)


def test_blender_4_short_names_read_as_blender_5_long_names(tmp_path):
    long_to_short = dict(zip(CYCLES5_RGB[:13], ("DiffDir", "DiffInd", "DiffCol", "GlossDir", "GlossInd", "GlossCol",
                                                "TransDir", "TransInd", "TransCol", "Emit", "Env", "VolumeDir",
                                                "VolumeInd")))
    ch = cycles_channels(6, 7, seed=3, view="RenderLayer")
    short = {}
    for name, pixels in ch.items():
        view, rest = name.split(".", 1)
        layer, comp = rest.rsplit(".", 1)
        short[f"{view}.{long_to_short.get(layer, layer)}.{comp}"] = pixels
    a = layouts.read(write_channels(tmp_path / "long.exr", ch))
    b = layouts.read(write_channels(tmp_path / "short.exr", short))
    for name in a.layers:
        np.testing.assert_array_equal(a.layers[name], b.layers[name], err_msg=name)


def test_cycles_without_denoising_depth_takes_depth_with_the_background_as_zero(tmp_path):
    ch = cycles_channels(5, 5)
    del ch["ViewLayer.Denoising Depth.Z"]
    frame = layouts.read(write_channels(tmp_path / "d.exr", ch))
    assert frame.layers["depth"][0, 0] == 0 and frame.layers["depth"][1, 1] == ch["ViewLayer.Depth.Z"][1, 1]


def test_cycles_without_the_diffuse_passes_has_no_split_and_the_clipped_denoising_albedo(tmp_path):
    ch = {k: v for k, v in cycles_channels(5, 6).items() if ".Diffuse " not in k}
    ch["ViewLayer.Denoising Albedo.R"] = ch["ViewLayer.Denoising Albedo.R"] * 250
    frame = layouts.read(write_channels(tmp_path / "nosplit.exr", ch))
    assert frame.inputs == InputSet(split=False, variance=False) and "diffuse" not in frame.layers
    assert frame.layers["albedo"].max() <= 1.0


def _mitsuba_channels(h, w, seed=0):
    rng = np.random.default_rng(seed)
    ch = {}
    for layer, comps in (("path.", "XYZ"), ("aov.albedo.", "RGB"), ("aov.nn.", "XYZ"), ("aov.dd.", "T")):
        for c in comps:
            mean = rng.uniform(0, 1.5, (h, w)).astype(np.float32)
            ch[f"{layer}{c}"] = mean
            ch[f"m2_{layer}{c}"] = (mean.astype(np.float64) ** 2 + rng.uniform(0, 0.5, (h, w))).astype(np.float32)
    return ch


def test_mitsuba_variance_is_the_second_moment_less_the_squared_mean_over_the_spp(tmp_path):
    ch = _mitsuba_channels(7, 8, seed=4)
    frame = layouts.read(write_channels(tmp_path / "mi-00032spp.exr", ch))
    assert frame.layout == "mitsuba" and frame.inputs == InputSet(split=False, variance=True)

    def variance(prefix, comps):
        return np.mean([(ch[f"m2_{prefix}{c}"].astype(np.float64) - ch[f"{prefix}{c}"].astype(np.float64) ** 2) / 32
                        for c in comps], axis=0)

    sigma = np.sqrt(np.stack([(ch[f"m2_path.{c}"].astype(np.float64) - ch[f"path.{c}"].astype(np.float64) ** 2) / 32
                              for c in "XYZ"], axis=-1))
    np.testing.assert_allclose(frame.layers["colorVariance"],
                               ((sigma @ layouts.MITSUBA_XYZ_TO_RGB.T) ** 2).mean(axis=-1), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(frame.layers["albedoVariance"], variance("aov.albedo.", "RGB"), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(frame.layers["normalVariance"], variance("aov.nn.", "XYZ"), rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(frame.layers["depthVariance"], variance("aov.dd.", "T"), rtol=1e-5, atol=1e-9)
    assert frame.layers["albedo"].max() <= 1.0 < ch["aov.albedo.R"].max()  # clamped: metals exceed 1
    np.testing.assert_array_equal(frame.layers["depth"], ch["aov.dd.T"])
    xyz = np.stack([ch[f"path.{c}"].astype(np.float64) for c in "XYZ"], axis=-1)
    np.testing.assert_allclose(frame.layers["default"], xyz @ layouts.MITSUBA_XYZ_TO_RGB.T, rtol=1e-5, atol=1e-6)


def test_mitsuba_without_a_known_spp_is_read_without_variance(tmp_path):
    frame = layouts.read(write_channels(tmp_path / "mi.exr", _mitsuba_channels(4, 4)))
    assert frame.inputs == InputSet(split=False, variance=False)
    assert any("no spp known" in note for note in frame.notes)
    assert layouts.read(tmp_path / "mi.exr", spp=8).inputs.variance


def test_a_half_of_a_pair_has_its_own_spp_from_its_name(tmp_path):
    # Mitsuba writes no spp: a half's name (catalogue.pair_names, kpcn denoise --pair) gives it, 16 for a 32-spp frame
    ch = _mitsuba_channels(3, 4, seed=2)
    half = layouts.read(write_channels(tmp_path / "mi-00016spp-pair-b.exr", ch))
    whole = layouts.read(write_channels(tmp_path / "mi-00016spp.exr", ch))
    assert half.spp == whole.spp == 16 and half.inputs.variance
    np.testing.assert_array_equal(half.layers["colorVariance"], whole.layers["colorVariance"])
    assert layouts.read(write_channels(tmp_path / "mi-00016spp-pair-c.exr", ch)).spp is None  # no half of ours


def test_pbrt_variance_is_per_sample_and_depth_is_the_distance_to_the_camera(tmp_path):
    rng = np.random.default_rng(5)
    ch = {}
    for layer, comps in (("", "RGB"), ("Albedo.", "RGB"), ("Ns.", "XYZ"), ("P.", "XYZ"), ("Variance.", "RGB")):
        for c in comps:
            ch[f"{layer}{c}"] = rng.uniform(-1 if layer == "P." else 0, 2, (6, 5)).astype(np.float16)
    frame = layouts.read(write_channels(tmp_path / "pbrt-00064spp.exr", ch))
    assert frame.layout == "pbrt" and frame.inputs == InputSet(split=False, variance=True)
    p = np.stack([ch[f"P.{c}"].astype(np.float64) for c in "XYZ"], axis=-1)
    np.testing.assert_allclose(frame.layers["depth"], np.sqrt((p * p).sum(-1)), rtol=1e-6)
    var = np.mean([ch[f"Variance.{c}"].astype(np.float64) for c in "RGB"], axis=0) / 64
    np.testing.assert_allclose(frame.layers["colorVariance"], var, rtol=1e-6)
    assert frame.layers["default"].dtype == np.float32


def test_an_rgb_file_takes_albedo_and_normal_from_separate_files(tmp_path):
    rng = np.random.default_rng(6)
    colour, albedo, normal = (rng.uniform(0, 1, (5, 4, 3)).astype(np.float32) for _ in range(3))
    for name, image in (("c", colour), ("a", albedo), ("n", normal)):
        write_channels(tmp_path / f"{name}.exr", {c: image[..., i] for i, c in enumerate("RGB")})
    frame = layouts.read(tmp_path / "c.exr", albedo=tmp_path / "a.exr", normal=tmp_path / "n.exr")
    assert frame.layout == "rgb" and frame.inputs == InputSet(split=False, variance=False)
    np.testing.assert_array_equal(frame.layers["default"], colour)
    np.testing.assert_array_equal(frame.layers["albedo"], albedo)
    np.testing.assert_array_equal(frame.layers["normal"], normal)
    np.testing.assert_array_equal(frame.layers["depth"], 0)
    alone = layouts.read(tmp_path / "c.exr")
    np.testing.assert_array_equal(alone.layers["albedo"], 1)


def test_the_kpcn_layout_is_found_first_and_without_variance_says_so(tmp_path):
    from helpers.tiny import random_aovs

    aovs = random_aovs(4, 5)
    frame = layouts.read(exr.write_aovs(tmp_path / "k-00004spp.exr", aovs))
    assert frame.layout == "kpcn" and frame.inputs == InputSet()
    for name, image in exr.read_aovs(tmp_path / "k-00004spp.exr").items():
        np.testing.assert_array_equal(frame.layers[name], image, err_msg=name)
    no_var = {k: v for k, v in aovs.items() if "Variance" not in k}
    assert layouts.read(exr.write_aovs(tmp_path / "n-00004spp.exr", no_var)).inputs == InputSet(variance=False)


def test_a_file_of_no_layout_kpcn_reads_gets_one_line_naming_what_each_layout_missed(tmp_path):
    zeros = np.zeros((3, 3), np.float32)
    path = write_channels(tmp_path / "odd.exr", {"Y": zeros, "mask.Z": zeros})
    with pytest.raises(AOVError) as err:
        layouts.read(path)
    message = str(err.value)
    assert "\n" not in message and message.startswith(f"{path}: no layout kpcn reads: kpcn looks for ")
    for name, adapter in layouts.LAYOUTS.items():
        assert f"{name} looks for {adapter.looks_for}, missed " in message
    assert "kpcn looks for diffuse, specular, albedo, normal, depth, missed diffuse, specular, albedo" in message
    assert message.endswith("; the file has layers default, mask")
    with pytest.raises(AOVError, match=r"not a cycles file: cycles looks for <view layer>.Combined and Blender's "
                                       r"passes and it lacks <view layer>.Combined \(R G B\)"):
        layouts.read(path, "cycles")


def test_output_keeps_header_attributes_windows_and_alpha(tmp_path):
    ch = cycles_channels(6, 8)
    ch["ViewLayer.Combined.A"] = np.linspace(0, 1, 48, dtype=np.float32).reshape(6, 8)
    window = ((10, 20), (17, 25))
    header = {"dataWindow": tuple(np.array(c, np.int32) for c in window),
              "displayWindow": (np.array([0, 0], np.int32), np.array([63, 47], np.int32)),
              "Software": "Blender 5.0.1", "cycles.ViewLayer.samples": "16", "xDensity": 72.0}
    frame = layouts.read(write_channels(tmp_path / "in.exr", ch, parts_of(ch), header=header))
    assert frame.data_window == window and frame.spp == 16
    out = exr.write_aovs(tmp_path / "out.exr", {"default": frame.layers["default"], "default.A": frame.alpha},
                         attributes=frame.attributes, windows=(frame.data_window, frame.display_window))
    back = exr.read_image(out)
    assert back.data_window == window and back.display_window == ((0, 0), (63, 47))
    assert back.attributes["Software"] == "Blender 5.0.1" and back.attributes["xDensity"] == 72.0
    np.testing.assert_array_equal(back.channels["default.A"], ch["ViewLayer.Combined.A"])


# ---------------------------------------------------------------- the renderers' own files (tests/fixtures/renderers)

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"
# Two Cycles CPU renders of one seed differ by up to 4e-6 (fixtures/renderers/README.md), so the multi-part and the
# interleaved fixture, two renders, agree to that and not bit for bit.
CYCLES_JITTER = 1e-5
HALF_EPS = float(np.finfo(np.float16).eps)


def _raw(path):
    image = exr.read_image(path)
    return {name: pixels.astype(np.float64) for name, pixels in image.channels.items()}


@pytest.mark.parametrize("folder, names, precision", [
    ("cycles5", ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Glossy Direct", "Glossy Indirect",
                 "Glossy Color", "Transmission Direct", "Transmission Indirect", "Transmission Color", "Emission",
                 "Environment", "Volume Direct", "Volume Indirect"), 1e-6),
    ("cycles45", ("DiffDir", "DiffInd", "DiffCol", "GlossDir", "GlossInd", "GlossCol", "TransDir", "TransInd",
                  "TransCol", "Emit", "Env", "VolumeDir", "VolumeInd"), 4 * HALF_EPS),
])
def test_blenders_own_files_compose_to_their_combined(folder, names, precision):
    path = RENDERERS / folder / "studio-00016spp.exr"
    raw = _raw(path)
    frame = layouts.read(path)
    assert frame.layout == "cycles" and frame.inputs == InputSet(split=True, variance=False) and frame.spp == 16

    def rgb(p):
        return np.stack([raw[f"ViewLayer.{p}.{c}"] for c in "RGB"], axis=-1)

    dd, di, dc, gd, gi, gc, td, ti, tc, em, en, vd, vi = (rgb(n) for n in names)
    np.testing.assert_allclose(frame.layers["diffuse"], (dd + di) * dc, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(frame.layers["specular"], (gd + gi) * gc + (td + ti) * tc + em + en + vd + vi,
                               rtol=1e-6, atol=1e-6)
    combined = rgb("Combined")
    total = frame.layers["diffuse"].astype(np.float64) + frame.layers["specular"]
    assert np.abs(total - combined).max() <= precision * np.abs(combined).max()
    np.testing.assert_array_equal(frame.alpha, raw["ViewLayer.Combined.A"].astype(np.float32))
    assert frame.layers["depth"].min() == 0 and frame.layers["depth"].max() < 10  # Denoising Depth, not 1e10


def test_a_cycles_file_with_a_volume_reads_combined_as_the_sum_of_its_split():
    # Blender's own file of a fog cube (fixtures/renderers/make_cycles_volume.py): most of its light is Volume
    # Direct + Volume Indirect, which the reader puts in specular (docs/formats.md §1b says why), none in diffuse
    path = RENDERERS / "cycles5-volume" / "fog-00016spp.exr"
    raw = _raw(path)
    frame = layouts.read(path)
    assert frame.layout == "cycles" and frame.inputs == InputSet(split=True, variance=False) and not frame.notes

    def rgb(p):
        return np.stack([raw[f"ViewLayer.{p}.{c}"] for c in "RGB"], axis=-1)

    combined, volume = rgb("Combined"), rgb("Volume Direct") + rgb("Volume Indirect")
    assert volume.sum() > 0.5 * combined.sum()  # a split without the volume passes would miss most of the frame
    np.testing.assert_allclose(frame.layers["diffuse"],
                               (rgb("Diffuse Direct") + rgb("Diffuse Indirect")) * rgb("Diffuse Color"),
                               rtol=1e-6, atol=1e-7)
    surfaces = sum((rgb(f"{lobe} Direct") + rgb(f"{lobe} Indirect")) * rgb(f"{lobe} Color")
                   for lobe in ("Glossy", "Transmission")) + rgb("Emission") + rgb("Environment")
    np.testing.assert_allclose(frame.layers["specular"], surfaces + volume, rtol=1e-6, atol=1e-6)
    total = frame.layers["diffuse"].astype(np.float64) + frame.layers["specular"]
    assert np.abs(total - combined).max() <= 4 * np.finfo(np.float32).eps * np.abs(combined).max()


def test_pixels_whose_cycles_passes_are_nan_keep_their_combined_as_specular(tmp_path):
    # Blender writes NaN colour passes at some pixels of a smoke volume while their Combined is finite; the
    # split must still sum to Combined there (each layer's own repair would give 0 + 0: a black pixel)
    channels = cycles_channels(6, 5, seed=3)
    hit = np.zeros((6, 5), bool)
    hit[0, 1] = hit[4, 3] = True
    for name in ("Diffuse Color", "Glossy Color", "Transmission Color"):
        for c in "RGB":
            channels[f"ViewLayer.{name}.{c}"][hit] = np.nan
    path = write_channels(tmp_path / "smoke-00016spp.exr", channels, parts_of(channels))
    frame = layouts.read(path)
    combined = np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1).astype(np.float64)
    total = frame.layers["diffuse"].astype(np.float64) + frame.layers["specular"]
    np.testing.assert_allclose(total, combined, rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(frame.layers["specular"][hit], combined[hit].astype(np.float32))
    assert not frame.layers["diffuse"][hit].any() and not frame.layers["albedo"][hit].any()
    assert all(np.isfinite(a).all() for a in frame.layers.values())
    assert any("2 pixels whose light passes are not finite" in n for n in frame.notes)
    untouched = layouts.read(write_channels(tmp_path / "clean-00016spp.exr", cycles_channels(6, 5, seed=3)))
    np.testing.assert_array_equal(frame.layers["diffuse"][~hit], untouched.layers["diffuse"][~hit])


def test_blender_5s_multi_part_and_interleaved_files_read_alike():
    multi = layouts.read(RENDERERS / "cycles5" / "studio-00016spp.exr")
    interleaved = layouts.read(RENDERERS / "cycles5-interleaved" / "studio-00016spp.exr")
    assert len(exr.read_image(multi.path, header_only=True).parts) == 19
    assert len(exr.read_image(interleaved.path, header_only=True).parts) == 1
    assert multi.layers.keys() == interleaved.layers.keys() and multi.inputs == interleaved.inputs
    for name in multi.layers:
        np.testing.assert_allclose(multi.layers[name], interleaved.layers[name], atol=CYCLES_JITTER, err_msg=name)


def test_mitsubas_own_file_gives_the_variance_of_its_moments():
    path = RENDERERS / "mitsuba3" / "cornell-00016spp.exr"
    raw = _raw(path)
    frame = layouts.read(path)
    assert frame.layout == "mitsuba" and frame.inputs == InputSet(split=False, variance=True)
    # path.X Y Z is CIE XYZ: against the path-only reference, which Mitsuba's film wrote in sRGB, the mean colour
    # agrees to the noise only once taken to sRGB by mi.xyz_to_srgb's matrix (written out here)
    xyz_to_srgb = np.array([[3.240479, -1.537150, -0.498535], [-0.969256, 1.875991, 0.041556],
                            [0.055648, -0.204043, 1.057311]])
    xyz = np.stack([raw[f"path.{c}"] for c in "XYZ"], axis=-1)
    np.testing.assert_allclose(frame.layers["default"], xyz @ xyz_to_srgb.T, rtol=1e-5, atol=1e-6)
    ref = layouts.read(RENDERERS / "mitsuba3" / "cornell-01024spp.exr").layers["default"].astype(np.float64)
    assert np.abs(frame.layers["default"].mean(axis=(0, 1)) - ref.mean(axis=(0, 1))).max() < 0.01
    assert np.abs(xyz.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))).max() > 0.05
    sigma = np.sqrt(np.stack([np.maximum(raw[f"m2_path.{c}"] - raw[f"path.{c}"] ** 2, 0) / 16 for c in "XYZ"], -1))
    var = ((sigma @ xyz_to_srgb.T) ** 2).mean(axis=-1)
    np.testing.assert_allclose(frame.layers["colorVariance"], var, rtol=1e-5, atol=1e-12)
    np.testing.assert_array_equal(frame.layers["depth"], raw["aov.dd.T"].astype(np.float32))
    assert raw["aov.albedo.R"].max() > 1 >= frame.layers["albedo"].max()


def test_a_file_in_pbrts_layout_gives_its_variance_over_the_spp():
    path = RENDERERS / "pbrt4" / "cornell-00016spp.exr"
    raw = _raw(path)
    frame = layouts.read(path)
    assert frame.layout == "pbrt" and frame.inputs == InputSet(split=False, variance=True)
    var = np.mean([raw[f"Variance.{c}"] for c in "RGB"], axis=0) / 16
    np.testing.assert_allclose(frame.layers["colorVariance"], var, rtol=1e-6)
    p = np.stack([raw[f"P.{c}"] for c in "XYZ"], axis=-1)
    np.testing.assert_allclose(frame.layers["depth"], np.sqrt((p * p).sum(-1)), rtol=1e-6)


@pytest.mark.parametrize("path", sorted(RENDERERS.glob("*/*.exr")), ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_fixture_is_found_from_its_header_as_read(path):
    header = layouts.read_header(path)
    frame = layouts.read(path)
    assert (header.layout, header.inputs, header.size) == (frame.layout, frame.inputs, frame.size)
    assert header.spp == frame.spp


def test_pbrts_camera_space_normal_is_taken_to_world_space_by_its_header():
    # the pbrt-layout fixture holds Mitsuba's pixels, its normal rotated into pbrt's camera space and face-forwarded
    # (fixtures/renderers/README.md): back in world space it is Mitsuba's own, but where face-forwarding flipped it
    pbrt = layouts.read(RENDERERS / "pbrt4" / "cornell-00016spp.exr")
    world = layouts.read(RENDERERS / "mitsuba3" / "cornell-00016spp.exr").layers["normal"].astype(np.float64)
    hit = np.abs(world).sum(axis=-1) > 0
    dot = (pbrt.layers["normal"].astype(np.float64) * world).sum(axis=-1)[hit]
    assert np.median(dot) > 0.999 and (dot > 0.99).mean() > 0.8
    assert pbrt.spp == 16  # from the header's samplesPerPixel as well as the name
