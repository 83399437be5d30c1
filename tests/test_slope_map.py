"""λ maps and the loss-specialisation module: the map reader against float64 arithmetic, the
training maps' range and smoothness, and the module's contract: a constant map is the uniform λ, a map
changed in a region changes the output only within the kernel's radius of it, the trunk runs once for many
maps (``Denoiser.prepare``), tiles and ``.keras`` files change nothing."""

import struct
import warnings
import zlib

import numpy as np
import pytest
from helpers.exr_layouts import write_channels
from helpers.networks import randomise
from helpers.references import moved
from helpers.tiny import TINY_MODEL, random_aovs

from kpcn_keras import slope_map
from kpcn_keras.config import ModelConfig
from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import build_branch_model, kept_of, network_input, slope_module_parts
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from prep.errors import KpcnError, OptionError

RANGE = (1.0, 8.0)


def log_lerp(g, lo=RANGE[0], hi=RANGE[1]):
    return np.exp(np.log(lo) + np.asarray(g, np.float64) * (np.log(hi) - np.log(lo)))


# ---------------------------------------------------------------- reading a painted map


def test_a_greyscale_png_maps_grey_log_linearly_onto_the_range(tmp_path):
    from PIL import Image

    grey = np.arange(256, dtype=np.uint8).reshape(16, 16)
    Image.fromarray(grey, mode="L").save(tmp_path / "m.png")
    got = slope_map.read(tmp_path / "m.png", (16, 16), RANGE)
    np.testing.assert_allclose(got, log_lerp(grey / 255.0), rtol=1e-6)
    assert got[0, 0] == pytest.approx(1.0) and got[-1, -1] == pytest.approx(8.0, rel=1e-6)
    wide = (np.arange(16 * 16, dtype=np.uint16) * 257).reshape(16, 16)  # 16-bit grey
    Image.fromarray(wide).save(tmp_path / "w.png")
    np.testing.assert_allclose(slope_map.read(tmp_path / "w.png", (16, 16), RANGE), log_lerp(wide / 65535.0),
                               rtol=1e-6)


def test_a_one_channel_exr_holds_lambda_and_a_map_of_the_frames_aspect_is_resized_in_log_lambda(tmp_path):
    slopes = np.array([[1.0, 8.0], [2.0, 4.0]], np.float32)
    write_channels(tmp_path / "m.exr", {"Y": slopes})
    np.testing.assert_array_equal(slope_map.read(tmp_path / "m.exr", (2, 2), RANGE), slopes)
    got = slope_map.read(tmp_path / "m.exr", (5, 5), RANGE)
    # corners kept; the centre is the geometric mean of the four (bilinear in log λ)
    np.testing.assert_allclose(got[[0, 0, -1, -1], [0, -1, 0, -1]], [1.0, 8.0, 2.0, 4.0], rtol=1e-6)
    assert got[2, 2] == pytest.approx(np.exp(np.mean(np.log(slopes.astype(np.float64)))), rel=1e-6)


@pytest.mark.parametrize("name, make, needle", [
    ("wrong-aspect.exr", lambda p: write_channels(p, {"Y": np.ones((4, 8), np.float32)}), "8×4 pixels"),
    ("two.exr", lambda p: write_channels(p, {"R": np.ones((4, 4), np.float32), "G": np.ones((4, 4), np.float32)}),
     "found 2: G, R"),
    ("outside.exr", lambda p: write_channels(p, {"Y": np.full((4, 4), 9.0, np.float32)}), "found 9 to 9"),
    ("colour.png", lambda p: __import__("PIL.Image").Image.fromarray(
        np.dstack([np.zeros((4, 4), np.uint8), np.full((4, 4), 9, np.uint8), np.zeros((4, 4), np.uint8)])).save(p),
     "mode RGB"),
    ("map.tif", lambda p: p.write_bytes(b"x"), "found .tif"),
    ("absent.png", lambda p: None, "no such"),
])
def test_a_map_kpcn_cannot_take_is_refused_naming_the_file_and_what_it_found(tmp_path, name, make, needle):
    path = tmp_path / name
    make(path)
    with pytest.raises(KpcnError) as err:
        slope_map.read(path, (4, 4), RANGE)
    message = str(err.value)
    assert message.startswith(str(path)) and needle in message and "\n" not in message


def png_claiming(width: int, height: int) -> bytes:
    """A valid 8-bit greyscale PNG header (IHDR) saying ``width`` x ``height``, with a one-byte IDAT: a few dozen
    bytes that claim an image of any size."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\x00")) + chunk(b"IEND", b""))


@pytest.mark.parametrize("side", [9600, 30000])  # past PIL's warning, past its refusal
def test_a_png_whose_header_claims_a_huge_map_is_refused_from_its_header_stating_the_limit(tmp_path, side):
    path = tmp_path / "huge.png"
    path.write_bytes(png_claiming(side, side))
    assert path.stat().st_size < 80
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning on the way (PIL's DecompressionBombWarning) fails the test
        with pytest.raises(KpcnError) as err:
            slope_map.read(path, (16, 24), RANGE)
    message = str(err.value)
    assert message.startswith(f"{path}: ") and "\n" not in message, message
    assert f"{side}×{side}" in message and "4096" in message and "24×16" in message, message


def test_the_size_limit_of_a_map_is_twice_the_frames_sides_or_4096(tmp_path):
    path = tmp_path / "big.png"
    path.write_bytes(png_claiming(4300, 4300))  # within 2x a frame of 2150 a side: read (and found cut short)
    with pytest.raises(KpcnError, match="not a readable PNG"):
        slope_map.read(path, (2150, 2150), RANGE)
    with pytest.raises(KpcnError, match="4300×4300.*at most 4096×4096"):
        slope_map.read(path, (2000, 2000), RANGE)
    path.write_bytes(png_claiming(4096, 4096))  # within 4096 for a small frame
    with pytest.raises(KpcnError, match="not a readable PNG"):
        slope_map.read(path, (16, 16), RANGE)
    path.write_bytes(png_claiming(17000, 17000))  # within 2x a huge frame, past what PIL decodes: one line too
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(KpcnError, match="more pixels than the PNG reader decodes"):
            slope_map.read(path, (9000, 9000), RANGE)


# ---------------------------------------------------------------- training maps


def test_training_maps_stay_in_the_range_are_smooth_and_half_of_them_constant():
    rng = np.random.default_rng(0)
    maps = [slope_map.draw(rng, 65, RANGE) for _ in range(400)]
    constant = [m for m in maps if np.ptp(m) == 0]
    assert abs(len(constant) / len(maps) - slope_map.CONSTANT_SHARE) < 0.1  # 4 sigma of a binomial share
    lo, hi = np.log(RANGE)
    for m in maps:
        logs = np.log(m.astype(np.float64))
        assert logs.min() >= lo - 1e-6 and logs.max() <= hi + 1e-6
        # bilinear between nodes at least 64 / 3 pixels apart: a step between neighbours is at most the range
        # over that spacing
        steps = max(np.abs(np.diff(logs, axis=0)).max(), np.abs(np.diff(logs, axis=1)).max())
        assert steps <= (hi - lo) * (slope_map.GRID_NODES[1] - 1) / 64 + 1e-6
    assert max(np.ptp(m) for m in maps) > 3.0  # some vary across most of the range


# ---------------------------------------------------------------- the specialisation module


def module_model(arch="kpcn", **extra):
    cfg = ModelConfig(arch=arch, **TINY_MODEL, slope_channel=True, slope_module=2, **extra)
    model = build_branch_model(cfg)
    randomise(model, seed=1)
    return cfg, model


def outputs(model, x):
    return np.asarray(model.predict_on_batch(x[None]))[0]


MODULES = [("kpcn", {}), ("unet", {"levels": 2}), ("kpal", {}), ("kpcn", {"slope_mixture": 3}),
           ("unet", {"levels": 2, "slope_mixture": 2})]


@pytest.mark.parametrize("arch, extra", MODULES)
def test_the_module_keeps_lambda_out_of_the_trunk_and_its_parts_give_the_models_output(arch, extra, tmp_path):
    import keras

    cfg, model = module_model(arch, **extra)
    rng = np.random.default_rng(2)
    feats = rng.normal(0.5, 0.3, (18, 22, cfg.in_channels)).astype(np.float32)
    x1 = network_input(feats, cfg, "diffuse", 1.5)
    x2 = network_input(feats, cfg, "diffuse", slope_map.draw(np.random.default_rng(5), 22, RANGE)[:18])
    trunk, module = slope_module_parts(model)
    k1, k2 = (kept_of(trunk, x[None]) for x in (x1, x2))
    # the activations, then the noisy colour or a mixture's filtered colours
    assert [a.shape[-1] for a in k1[1:]] == [3 * (cfg.slope_mixture or 1)]
    for a1, a2 in zip(k1, k2):
        np.testing.assert_array_equal(a1, a2)  # λ never reaches the trunk
    for x, kept in ((x1, k1), (x2, k2)):
        got = module.predict_on_batch([*kept, x[None, ..., -1:]])  # the module reads λ alone of the features
        np.testing.assert_allclose(np.asarray(got)[0], outputs(model, x), rtol=1e-5, atol=1e-6)
    assert not np.allclose(outputs(model, x1), outputs(model, x2), atol=1e-4)  # and λ moves the output
    model.save(tmp_path / "m.keras")
    np.testing.assert_array_equal(outputs(keras.models.load_model(tmp_path / "m.keras"), x2), outputs(model, x2))


@pytest.mark.parametrize("extra", [{}, {"slope_mixture": 2}])
def test_a_map_changed_inside_a_region_changes_the_output_there_alone(extra):
    # 1x1 layers after the join: λ at a pixel sets that pixel's kernel (or mixture), whose taps read colour, not λ
    cfg, model = module_model(**extra)
    feats = np.random.default_rng(3).normal(0.5, 0.3, (40, 40, cfg.in_channels)).astype(np.float32)
    base = np.full((40, 40), 2.0)
    painted = base.copy()
    painted[15:22, 10:18] = 6.0
    changed = np.abs(outputs(model, network_input(feats, cfg, "diffuse", painted))
                     - outputs(model, network_input(feats, cfg, "diffuse", base))).max(axis=-1) > 0
    np.testing.assert_array_equal(changed, painted != base)


def test_a_mixtures_output_is_its_colour_filtered_by_the_mixture_of_its_kernels():
    from helpers.references import reference_kernel_apply

    from kpcn_keras.models import build_kernel_model, mixture_bias

    cfg, model = module_model(slope_mixture=3)
    feats = np.random.default_rng(4).normal(0.5, 0.3, (17, 19, cfg.in_channels)).astype(np.float32)
    x = network_input(feats, cfg, "diffuse", slope_map.draw(np.random.default_rng(6), 19, RANGE)[:17])
    kernels = np.asarray(build_kernel_model(model).predict_on_batch(x[None]), np.float64)
    np.testing.assert_allclose(kernels.sum(axis=-1), 1.0, atol=1e-5)  # a mixture of kernels is a kernel
    want, _ = reference_kernel_apply(x[None, ..., :3], np.log(np.maximum(kernels, 1e-30)), cfg.kernel_size)
    np.testing.assert_allclose(outputs(model, x), want[0], rtol=1e-4, atol=1e-5)
    # the starting kernels: Gaussians, the first widest, each peaked at the centre, none alike
    k, c = cfg.kernel_size, cfg.kernel_size // 2
    starts = mixture_bias(k, 3).reshape(3, k, k)
    assert all(starts[m].argmax() == c * k + c for m in range(3))
    assert starts[0][0, 0] > starts[1][0, 0] > starts[2][0, 0]


def test_a_module_needs_lambda_as_an_input_and_kernels_to_specialise():
    with pytest.raises(OptionError, match="slope_module.*--slope-input"):
        ModelConfig(slope_module=1)
    with pytest.raises(OptionError, match="slope_module.*dpcn"):
        ModelConfig(arch="dpcn", slope_channel=True, slope_module=1)
    with pytest.raises(OptionError, match="slope_mixture.*--slope-module"):
        ModelConfig(slope_channel=True, slope_mixture=2)
    with pytest.raises(OptionError, match="slope_mixture.*at least 2"):
        ModelConfig(slope_channel=True, slope_module=1, slope_mixture=1)
    assert not {"slope_module", "slope_mixture"} & set(ModelConfig().to_dict())  # older records unchanged


# ---------------------------------------------------------------- a run: maps, tiles, a prepared frame


@pytest.fixture(scope="module", params=["tiny_slope_module_run", "tiny_slope_mixture_run"])
def denoiser(request):
    den = Denoiser.from_run(Run(request.getfixturevalue(request.param)),
                            InferenceSettings(tile=16, precision="float32"))
    for model in den.networks.values():
        randomise(model, seed=4)
    return den


def test_a_constant_map_is_the_uniform_lambda_and_tiles_do_not_show(denoiser):
    aovs = random_aovs(37, 45, seed=6)
    uniform = denoiser(aovs, slope=3.0)["default"]
    np.testing.assert_array_equal(denoiser(aovs, slope=np.full((37, 45), 3.0))["default"], uniform)
    painted = np.where(np.arange(45) < 20, 1.0, 8.0)[None].repeat(37, 0)
    whole = Denoiser(denoiser.run, denoiser.record, denoiser.networks,
                     settings=InferenceSettings(tile=64, precision="float32"))
    np.testing.assert_allclose(denoiser(aovs, slope=painted)["default"], whole(aovs, slope=painted)["default"],
                               rtol=1e-5, atol=1e-6)


def test_a_prepared_frame_gives_the_full_denoise_for_every_map(denoiser):
    aovs = random_aovs(37, 45, seed=7)
    prepared = denoiser.prepare(aovs)
    rng = np.random.default_rng(8)
    for slope in (2.0, slope_map.bilinear(np.log(rng.uniform(1, 8, (3, 4))), (37, 45)).clip(0) + 1.0):
        got, want = prepared(slope), denoiser(aovs, slope=slope)
        for name in ("diffuse", "specular", "default"):
            np.testing.assert_allclose(got[name], want[name], rtol=1e-5, atol=1e-6)
    with pytest.raises(OptionError, match="shape"):
        prepared(np.full((36, 45), 2.0))


def test_an_ensemble_moves_a_painted_map_with_the_frame_and_prepares_no_frame(denoiser):
    aovs = random_aovs(21, 30, seed=11)
    painted = np.where(np.arange(30) < 11, 1.0, 8.0)[None].repeat(21, 0) * np.linspace(1, 0.5, 21)[:, None] + 0.5
    ensemble = Denoiser(denoiser.run, denoiser.record, denoiser.networks,
                        settings=InferenceSettings(tile=16, precision="float32", ensemble=8))
    for branch in ("diffuse", "specular"):
        members = [moved(denoiser.run_branch(branch, {k: moved(v, s) for k, v in aovs.items()}, moved(painted, s)), s,
                         inverse=True) for s in range(8)]
        np.testing.assert_allclose(ensemble.run_branch(branch, aovs, painted), np.median(members, axis=0), rtol=1e-5,
                                   atol=1e-6)
    with pytest.raises(KpcnError, match="prepared frame runs the networks once; load the run with ensemble 1"):
        ensemble.prepare(aovs)


def test_a_prepared_frame_re_applies_a_region_alone_as_the_full_frame_gives_it(denoiser):
    aovs = random_aovs(37, 45, seed=10)
    prepared = denoiser.prepare(aovs)
    slopes = np.full((37, 45), 2.0)
    slopes[9:30, 14:33] = 7.0  # across tile borders (tiles of 16)
    whole = prepared(slopes)
    for region in ((9, 30, 14, 33), (0, 37, 0, 45), (36, 37, 44, 45)):
        y0, y1, x0, x1 = region
        got = prepared(slopes, region=region)
        for name in ("diffuse", "specular", "default"):
            assert got[name].shape == (y1 - y0, x1 - x0, 3)
            np.testing.assert_array_equal(got[name], whole[name][y0:y1, x0:x1])
    for region, needle in (((5, 5, 0, 3), "non-empty"), ((0, 38, 0, 3), "45x37"), ((0, 1, 0), "four integers")):
        with pytest.raises(OptionError, match=needle):
            prepared(slopes, region=region)


def test_half_and_half_maps_match_each_uniform_frame_on_its_half_up_to_the_seam(denoiser):
    from kpcn_keras.figures import half_and_half

    aovs = random_aovs(24, 31, seed=12)
    got = half_and_half(denoiser, aovs, 1.0, 8.0)
    assert np.abs(got["low"] - got["high"]).max() > 1e-3  # λ matters, so equal halves are not a coincidence
    np.testing.assert_allclose(got["map"][:, :15], got["low"][:, :15], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got["map"][:, 15:], got["high"][:, 15:], rtol=1e-5, atol=1e-6)


def test_kpcn_figures_draws_the_half_and_half_map_for_a_run_with_the_module_alone(tmp_path, tiny_slope_module_run,
                                                                                  tiny_slope_mixture_run, tiny_run):
    from kpcn_keras.figures import make_figures
    from prep import exr

    exr.write_aovs(tmp_path / "f.exr", random_aovs(24, 31, seed=13))
    for run in (tiny_slope_module_run, tiny_slope_mixture_run):  # a mixture's kernels: the mixture of its kernels
        written = make_figures(Run(run), (tmp_path / "f.exr", None))
        assert {"kernels", "slopes", "slope_map"} <= set(written) and written["slope_map"].stat().st_size > 0
    assert "slope_map" not in make_figures(Run(tiny_run), (tmp_path / "f.exr", None))


def test_a_map_is_refused_by_a_run_without_the_module(tiny_run):
    den = Denoiser.from_run(Run(tiny_run))
    with pytest.raises(OptionError, match="--slope-module"):
        den(random_aovs(8, 8), slope=np.full((8, 8), 2.0))
    with pytest.raises(KpcnError, match="--slope-module"):
        den.prepare(random_aovs(8, 8))


# ---------------------------------------------------------------- kpcn denoise --slope-map


def test_kpcn_denoise_applies_a_painted_map_and_refuses_one_it_cannot_use(tmp_path, tiny_slope_module_run, tiny_run):
    from helpers.commands import assert_one_line_error, run_main
    from helpers.files import checksums
    from PIL import Image

    from prep import exr

    aovs = random_aovs(20, 24, seed=9)
    exr.write_aovs(tmp_path / "f.exr", aovs)
    grey = np.tile(np.linspace(0, 255, 12).astype(np.uint8), (10, 1))  # half the frame's size, its aspect
    Image.fromarray(grey, mode="L").save(tmp_path / "map.png")
    res = run_main("denoise", "f.exr", "--run", tiny_slope_module_run, "--slope-map", "map.png", "-o", "out.exr",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    den = Denoiser.from_run(Run(tiny_slope_module_run))
    want = den(exr.read_aovs(tmp_path / "f.exr"), slope=slope_map.read(tmp_path / "map.png", (20, 24), RANGE))
    np.testing.assert_array_equal(exr.read_aovs(tmp_path / "out.exr", variances=None)["default"], want["default"])

    Image.fromarray(np.zeros((10, 10), np.uint8), mode="L").save(tmp_path / "square.png")
    (tmp_path / "huge.png").write_bytes(png_claiming(9600, 9600))
    before = checksums(tmp_path)
    for args, needles in (
            (("--run", tiny_slope_module_run, "--slope-map", "huge.png"), ("huge.png", "9600×9600", "4096")),
            (("--run", tiny_slope_module_run, "--slope-map", "square.png"), ("square.png", "10×10", "24×20")),
            (("--run", tiny_slope_module_run, "--slope-map", "map.png", "--slope", "2"), ("--slope-map", "--slope")),
            (("--run", tiny_run, "--slope-map", "map.png"), ("--slope-map", "--slope-module"))):
        res = run_main("denoise", "f.exr", "-o", "other.exr", *args, cwd=tmp_path)
        assert_one_line_error(res, *needles)
        assert checksums(tmp_path) == before
