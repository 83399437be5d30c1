import keras
import numpy as np
import pytest
from helpers.networks import randomise
from helpers.references import moved
from helpers.tiny import TINY_MODEL, build_tiny_shards, random_aovs

from kpcn_keras.batch import denoise_files
from kpcn_keras.config import TrainConfig
from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import network_input
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import train
from prep import colour, exr, features
from prep.albedo import prefilter
from prep.errors import OptionError


def _recombined(logs, aovs):
    """Each branch's log output back to linear colour in float64 by the inverses of the features table, the diffuse
    with the whole frame's prefiltered albedo, and their sum."""
    albedo = prefilter(aovs["albedo"], aovs["albedoVariance"])
    diffuse = np.expm1(logs["diffuse"].astype(np.float64)) * (albedo + colour.ALBEDO_EPS)
    specular = np.expm1(logs["specular"].astype(np.float64))
    return {"diffuse": diffuse, "specular": specular, "default": diffuse + specular}


def _untiled(denoiser, aovs, slope=None):
    """What tiling must equal: the whole frame's features (with ``slope``) through each network in one call,
    recombined (:func:`_recombined`)."""
    logs = {}
    for branch in features.BRANCHES:
        feats = network_input(features.branch_features(aovs, branch), denoiser.model_config, branch, slope)
        logs[branch] = keras.ops.convert_to_numpy(denoiser.models[branch].predict_on_batch(feats[None]))[0]
    return logs, _recombined(logs, aovs)


@pytest.mark.slow
@pytest.mark.parametrize("size, tile", [((45, 61), 16), ((13, 7), 2), ((1, 6), 4)], ids=["45x61/16", "13x7/2", "1x6/4"])
def test_tiles_equal_an_untiled_run(tiny_run, size, tile):
    # odd frames (partial tiles at the right and bottom), a tile smaller than the margin, a single row
    aovs = random_aovs(*size, seed=9)
    aovs["depth"][-1, -1] = 50.0  # the depth scale comes from one corner, outside most tiles
    logs, want = _untiled(Denoiser.from_run(Run(tiny_run)), aovs)
    tiled = Denoiser.from_run(Run(tiny_run), InferenceSettings(tile=tile))
    assert tiled.margin == 3  # 3 convs of 3x3 reach 3 pixels, the 5x5 kernel 2: the max of the two
    out = tiled(aovs)
    for name, image in out.items():
        assert image.dtype == np.float32 and image.shape == size + (3,)
        np.testing.assert_allclose(image, want[name], rtol=2e-5, atol=1e-6, err_msg=name)
    for branch in features.BRANCHES:
        np.testing.assert_allclose(tiled.run_branch(branch, aovs), logs[branch], rtol=1e-5, atol=1e-6)


TINY_UNET = {"arch": "unet", "width": 4, "depth": 1, "levels": 3, "kernel_size": 5}  # radius 13, alignment 4


@pytest.fixture(scope="module")
def tiny_unet_run(tmp_path_factory):
    """A tiny unet run with an alpha compositor of 2 levels (tiles then align to 4 x 2 = 8 pixels), on 32x32
    patches (its 27x27 receptive field does not fit the suite's usual 16)."""
    tmp = tmp_path_factory.mktemp("unet")
    shard_cfg = build_tiny_shards(tmp, patch_size=32, patches_per_image=4, patches_per_shard=4)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=shard_cfg.out_root, model=TINY_UNET, steps=2,
                                  steps_per_epoch=2, batch_size=2, val_batches=1, compositor_steps=2,
                                  compositor={"kind": "alpha", "levels": 2, "width": 4, "depth": 2})
    return train(cfg, tmp / "runs" / "r", verbose=0)


def _randomised(denoiser):
    """Random weights in every network (the trained heads are still near zero: near-box kernels, which
    would hide a tile that pools other blocks); the multiscale models share these objects."""
    for i, net in enumerate([*denoiser.networks.values(), *([denoiser.compositor] if denoiser.compositor else [])]):
        randomise(net, seed=20 + i, scale=0.2)
    return denoiser


@pytest.mark.slow
@pytest.mark.parametrize("multiscale", [False, True], ids=["unet", "unet+compositor"])
def test_unet_tiles_aligned_to_its_pooling_grid_equal_an_untiled_run(tiny_unet_run, multiscale):
    aovs = random_aovs(45, 61, seed=9)  # odd: partial tiles, and the unet pads each window itself
    denoiser = _randomised(Denoiser.from_run(Run(tiny_unet_run), InferenceSettings(tile=16), multiscale=multiscale))
    assert (denoiser.align, denoiser.margin) == ((8, 32) if multiscale else (4, 16))
    logs, want = _untiled(denoiser, aovs)
    out = denoiser(aovs)
    for name, image in out.items():
        np.testing.assert_allclose(image, want[name], rtol=2e-5, atol=1e-6, err_msg=name)
    for branch in features.BRANCHES:
        np.testing.assert_allclose(denoiser.run_branch(branch, aovs), logs[branch], rtol=1e-5, atol=1e-6)
    # the alignment matters: the same margins from tile starts off the grid pool other blocks
    denoiser.tile = 16 + denoiser.align // 2
    assert np.abs(denoiser.run_branch("diffuse", aovs) - logs["diffuse"]).max() > 1e-4


def _ensemble_reference(denoiser, aovs, members=8):
    """What a self-ensemble must equal: each branch's log output of the whole frame moved by each symmetry (numpy's
    own transposes and flips), moved back, the per-pixel median of the members; then :func:`_recombined`."""
    logs = {}
    for branch in features.BRANCHES:
        outs = [moved(_untiled(denoiser, {k: moved(v, s) for k, v in aovs.items()})[0][branch], s, inverse=True)
                for s in range(members)]
        logs[branch] = np.median(outs, axis=0)
    return logs, _recombined(logs, aovs)


@pytest.mark.slow
@pytest.mark.parametrize("arch", ["kpcn", "unet", "unet+compositor"])
def test_an_ensemble_is_the_median_of_the_networks_on_the_moved_frames_tile_by_tile(tiny_run, tiny_unet_run, arch):
    # odd sizes: moved tiles end where the frame does not, and a unet's windows must still start on the moved
    # frame's pooling grid
    run = tiny_run if arch == "kpcn" else tiny_unet_run
    plain = _randomised(Denoiser.from_run(Run(run), InferenceSettings(tile=16), multiscale=arch == "unet+compositor"))
    ensemble = Denoiser(plain.run, plain.record, plain.networks, plain.compositor,
                        settings=InferenceSettings(tile=16, ensemble=8))
    aovs = random_aovs(45, 61, seed=12)
    aovs["depth"][0, -1] = 40.0  # the depth scale from one corner, which moves
    logs, want = _ensemble_reference(plain, aovs)
    for name, image in ensemble(aovs).items():
        assert image.dtype == np.float32 and image.shape == (45, 61, 3)
        np.testing.assert_allclose(image, want[name], rtol=2e-5, atol=1e-6, err_msg=name)
    for branch in features.BRANCHES:
        np.testing.assert_allclose(ensemble.run_branch(branch, aovs), logs[branch], rtol=1e-5, atol=1e-6)
    # the members differ (the median is of something), and fewer members are the median of fewer
    assert np.abs(logs["diffuse"] - _untiled(plain, aovs)[0]["diffuse"]).max() > 1e-4
    two = Denoiser(plain.run, plain.record, plain.networks, plain.compositor,
                   settings=InferenceSettings(tile=16, ensemble=2))
    np.testing.assert_allclose(two.run_branch("specular", aovs), _ensemble_reference(plain, aovs, 2)[0]["specular"],
                               rtol=1e-5, atol=1e-6)


def test_an_ensemble_outside_one_to_eight_is_refused_echoing_it(tiny_run):
    for bad in (0, 9):
        with pytest.raises(OptionError, match=f"ensemble must be an integer in \\[1, 8\\], got {bad}"):
            Denoiser.from_run(Run(tiny_run), InferenceSettings(ensemble=bad))


TINY_DILATED = {**TINY_MODEL, "dilations": [1, 3, 2]}  # trunk radius 6, beyond the 5x5 kernel's 2


@pytest.mark.slow
def test_dilated_trunk_tiles_equal_an_untiled_run_and_need_their_whole_margin(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=shard_cfg.out_root, model=TINY_DILATED, steps=2,
                                  steps_per_epoch=2, batch_size=2, val_batches=1)
    denoiser = _randomised(Denoiser.from_run(Run(train(cfg, tmp_path / "r", verbose=0)), InferenceSettings(tile=8)))
    assert denoiser.margin == 6  # 1 + 3 + 2 dilated taps of 3x3 convolutions
    aovs = random_aovs(37, 29, seed=6)
    logs, want = _untiled(denoiser, aovs)
    for name, image in denoiser(aovs).items():
        np.testing.assert_allclose(image, want[name], rtol=2e-5, atol=1e-6, err_msg=name)
    denoiser.margin = 5  # the undilated stack's reach would be 3: a margin short of the dilated one shows seams
    assert np.abs(denoiser.run_branch("diffuse", aovs) - logs["diffuse"]).max() > 1e-4


@pytest.mark.slow
def test_one_denoiser_of_a_slope_input_run_denoises_at_the_slope_each_call_gives(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=shard_cfg.out_root, model=TINY_MODEL, steps=2,
                                  steps_per_epoch=2, batch_size=2, val_batches=1, loss="asymmetric", slope_input=True)
    denoiser = Denoiser.from_run(Run(train(cfg, tmp_path / "r", verbose=0)), InferenceSettings(tile=8))
    aovs = random_aovs(19, 22, seed=4)
    out = {}
    for slope in (1.0, 8.0, 2.5):
        out[slope] = denoiser(aovs, slope=slope)["default"]
        np.testing.assert_allclose(out[slope], _untiled(denoiser, aovs, slope)[1]["default"], rtol=2e-5, atol=1e-6)
    assert np.abs(out[1.0] - out[8.0]).max() > 1e-4  # λ reaches the networks
    np.testing.assert_array_equal(denoiser(aovs, slope=1.0)["default"], out[1.0])  # no λ stays behind
    with pytest.raises(OptionError,
                       match=r"slope is needed: .*r was trained with λ as an input, for λ in \[1.0, 8.0\]"):
        denoiser(aovs)


@pytest.mark.slow
def test_tiles_with_too_little_overlap_would_differ(tiny_run):
    # guards the test above: without the margin the tile seams are visible
    aovs = random_aovs(40, 40, seed=3)
    whole = Denoiser.from_run(Run(tiny_run), InferenceSettings(tile=4096)).run_branch("diffuse", aovs)
    seamy = Denoiser.from_run(Run(tiny_run), InferenceSettings(tile=8))
    seamy.margin = 0
    assert np.abs(seamy.run_branch("diffuse", aovs) - whole).max() > 1e-4


@pytest.mark.slow
@pytest.mark.parametrize("ensemble", [1, 8])
def test_memory_beyond_the_frame_and_the_output_is_bounded_by_the_tile(tiny_run, ensemble):
    # tracemalloc sees every numpy array (the features, their inputs' copies and the kernel's scratch, the
    # float64 recombination), not torch's own buffers (the network's activations, bounded by the tile anyway)
    import tracemalloc

    denoiser = Denoiser.from_run(Run(tiny_run), InferenceSettings(tile=32, ensemble=ensemble))
    denoiser.warm_up()
    side = denoiser.tile + 2 * denoiser.margin + 1  # a tile, its margins and the next pixel the gradients read
    # per window pixel: 27 float32 features, a float32 copy of the 14 input channels the kernel reads and its
    # 10 float64 buffers; twice that for the float64 recombination of the tile; 512 kB for the interpreter's
    # and keras's own objects. d097970 (whole-frame features and recombination): 5.3 MB beyond at 192x160
    bound = 2 * side**2 * (27 * 4 + 14 * 4 + 10 * 8) + 2**19
    if ensemble > 1:  # a member's window cut and moved (the render's 22 float32 channels, twice, a row and column
        # more each side), and the members' tile outputs, float32 RGB, held for their median and copied by it
        bound += 2 * (side + 2) ** 2 * 22 * 4 + 3 * ensemble * denoiser.tile**2 * 3 * 4
    for size in [(64, 48), (192, 160)]:  # 4 and 30 tiles
        aovs = random_aovs(*size, seed=2)
        tracemalloc.start()
        try:
            out = denoiser(aovs)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        beyond = peak - sum(image.nbytes for image in out.values())
        assert beyond <= bound, (size, beyond, bound)


@pytest.mark.slow
@pytest.mark.parametrize("png, reference", [(False, False), (True, False), (False, True), (True, True)])
def test_frame_bytes_bound_what_a_frame_holds_whole(tiny_run, tmp_path, png, reference):
    # what a pixel more costs (the difference of two frame heights at one width: fixed costs and the PNG's
    # blocks of rows cancel), measured by tracemalloc over the whole frame (reading, the tiles, writing, the
    # PNG, the metrics), against the bound the refusal uses: an upper bound, and not one so loose that it
    # refuses frames the machine can hold
    import gc
    import tracemalloc

    from kpcn_keras.batch import denoise_frame, frame_bytes

    denoiser = Denoiser.from_run(Run(tiny_run), InferenceSettings(tile=64))
    denoiser.warm_up()
    peaks = {}
    width = 96
    # the first frame a worker denoises also pays for what is done once a process (lazy imports, the PNG
    # encoder's and the metrics' first calls): a throwaway frame takes those out of the two measured
    for height in (64, 512, 1024):
        exr.write_aovs(tmp_path / f"n{height}.exr", random_aovs(height, width, seed=1))
        exr.write_aovs(tmp_path / f"r{height}.exr", random_aovs(height, width, seed=2, variances=False))
        gc.collect()
        tracemalloc.start()
        try:
            denoise_frame(denoiser, tmp_path / f"n{height}.exr", tmp_path / f"o{height}.exr",
                          tmp_path / f"r{height}.exr" if reference else None, png=png)
            peaks[height] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    measured = (peaks[1024] - peaks[512]) / ((1024 - 512) * width)
    bound = frame_bytes(1, 1, png=png, reference=reference)
    assert measured <= bound <= 2 * measured, (measured, bound)


def test_a_frame_the_machine_cannot_hold_is_refused_before_any_work(tiny_run, tmp_path):
    from kpcn_keras.batch import check_frame_memory, frame_bytes
    from prep.errors import KpcnError

    need_mb = frame_bytes(3000, 4000, png=False) / 2**20
    check_frame_memory("x.exr", (3000, 4000), png=False, available_mb=need_mb)
    with pytest.raises(KpcnError) as err:
        check_frame_memory("x.exr", (3000, 4000), png=False, available_mb=need_mb - 1)
    assert str(err.value) == (f"x.exr: denoising its 4000x3000 frame ({frame_bytes(1, 1, png=False)} bytes a pixel "
                              f"held whole) needs {need_mb / 1024:.1f} GiB, more than the "
                              f"{(need_mb - 1) / 1024:.1f} GiB this machine has available")
    with pytest.raises(KpcnError, match="with the reference.*; without --png it holds less"):
        check_frame_memory("x.exr", (3000, 4000), reference=True, available_mb=need_mb)


def test_recombination_inverts_the_branch_transforms(tiny_run):
    aovs = random_aovs(20, 20, seed=4)
    d = Denoiser.from_run(Run(tiny_run))
    out = d(aovs)
    diff_log = d.run_branch("diffuse", aovs)
    np.testing.assert_allclose(out["diffuse"], np.expm1(diff_log.astype(np.float64))
                               * (prefilter(aovs["albedo"], aovs["albedoVariance"]) + colour.ALBEDO_EPS), rtol=1e-5)
    np.testing.assert_allclose(out["default"], out["diffuse"] + out["specular"], rtol=1e-6)


def test_denoises_the_mitsuba_fixture(tiny_run, tmp_path, fixture_noisy, fixture_reference):
    report = denoise_files([fixture_noisy], Run(tiny_run), tmp_path / "fx.exr", fixture_reference).frames[0]
    out = exr.read_aovs(tmp_path / "fx.exr", variances=False)
    assert out["default"].shape == (64, 64, 3) and np.isfinite(out["default"]).all()
    assert (tmp_path / "fx.png").is_file()
    assert set(report.metrics) == set(report.input_metrics) == {
        "mse", "relmse", "relse_p999", "smape", "dssim", "psnr"}
    assert all(np.isfinite(v) for v in report.metrics.values())


# --- batches: one load, many frames ---

@pytest.mark.slow
def test_a_batch_equals_each_frame_alone(tiny_run, tmp_path):
    # bit-exact: the same networks run the same tiles of the same features; nothing carries over between
    # frames (no state in the models at inference, every tile's result depends on its own input only)
    names = ["a.exr", "b.exr", "c.exr"]
    for i, (name, size) in enumerate(zip(names, [(20, 24), (33, 17), (20, 24)])):
        exr.write_aovs(tmp_path / "in" / name, random_aovs(*size, seed=30 + i))
    exr.write_aovs(tmp_path / "in" / "old-denoised.exr", random_aovs(8, 8))
    batch = denoise_files([tmp_path / "in"], Run(tiny_run), tmp_path / "out", png=False)
    assert [f.input for f in batch.frames] == [str(tmp_path / "in" / n) for n in names]
    assert batch.skipped == (str(tmp_path / "in" / "old-denoised.exr"),)
    assert batch.load_s > 0 and batch.warmup_s > 0 and all(f.seconds > 0 for f in batch.frames)
    # the peak resident memory is this process's own high-water mark: at least what it holds now
    status = dict(line.split(":", 1) for line in open("/proc/self/status"))
    assert batch.peak_memory_mb >= int(status["VmRSS"].split()[0]) / 1024 * 0.9
    for name in names:
        alone = denoise_files([tmp_path / "in" / name], Run(tiny_run), tmp_path / "alone" / name, png=False)
        assert alone.frames[0].output == str(tmp_path / "alone" / name)
        together = exr.read_aovs(tmp_path / "out" / name.replace(".exr", "-denoised.exr"), variances=False)
        single = exr.read_aovs(tmp_path / "alone" / name, variances=False)
        for layer in ("default", "diffuse", "specular"):
            np.testing.assert_array_equal(together[layer], single[layer])


def test_panels_png_is_a_row_of_tonemapped_panels(tmp_path):
    from PIL import Image

    from kpcn_keras.panels import panels_png
    from prep.colour import tonemap

    image = random_aovs(10, 12)["default"]
    path = panels_png(tmp_path / "p.png", [("input", image), ("denoised", image * 0.5)], title="t")
    pixels = np.asarray(Image.open(path).convert("RGB"))
    assert pixels.shape == (28 + 10, 2 * 12 + 4, 3)
    np.testing.assert_array_equal(pixels[28:, :12], np.round(tonemap(image) * 255).astype(np.uint8))


def test_panels_png_tonemaps_a_block_of_rows_at_a_time(tmp_path):
    import tracemalloc

    from kpcn_keras.panels import PNG_ROWS, panels_png

    image = random_aovs(3 * PNG_ROWS + 132, 400, seed=1)["default"]
    panels_png(tmp_path / "warm.png", [("input", image[:4])])  # imports what drawing needs
    tracemalloc.start()
    try:
        panels_png(tmp_path / "p.png", [("input", image), ("denoised", image)], title="t")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    canvas = (28 + image.shape[0]) * (2 * 400 + 4) * 3
    # the canvas and a few float64 blocks of rows; d097970 tonemapped whole panels (28 MB here)
    assert peak <= canvas + 4 * PNG_ROWS * 400 * 3 * 8


def test_plan_outputs(tmp_path):
    from kpcn_keras.batch import plan_outputs
    from prep.errors import KpcnError, OptionError

    a, b = tmp_path / "x" / "a.exr", tmp_path / "y" / "a.exr"
    assert plan_outputs([a]) == [tmp_path / "x" / "a-denoised.exr"]
    assert plan_outputs([a], str(tmp_path / "new") + "/") == [tmp_path / "new" / "a-denoised.exr"]
    assert plan_outputs([a], tmp_path / "one.exr") == [tmp_path / "one.exr"]
    assert plan_outputs([a, tmp_path / "c"], tmp_path / "out") == [tmp_path / "out" / "a-denoised.exr",
                                                                  tmp_path / "out" / "c-denoised.exr"]
    with pytest.raises(OptionError, match="output must be a folder with several inputs"):
        plan_outputs([a, b], tmp_path / "one.exr")
    with pytest.raises(KpcnError, match="would both be written to"):
        plan_outputs([a, b], tmp_path / "out")
