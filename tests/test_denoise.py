import numpy as np
import pytest

from conftest import random_aovs
from kpcn_keras.denoise import Denoiser, denoise_file
from prep import exr, features


def test_tiles_equal_an_untiled_run(tiny_run):
    aovs = random_aovs(45, 61, seed=9)
    whole = Denoiser(tiny_run, tile=4096)
    tiled = Denoiser(tiny_run, tile=16)
    assert tiled.margin == 3  # 3 convs of 3x3 reach 3 pixels, the 5x5 kernel 2: the max of the two
    for branch in ("diffuse", "specular"):
        feats = features.branch_features(aovs, branch)
        np.testing.assert_allclose(tiled.run_branch(branch, feats), whole.run_branch(branch, feats), rtol=1e-5, atol=1e-6)


def test_tiles_with_too_little_overlap_would_differ(tiny_run):
    # guards the test above: without the margin the tile seams are visible
    aovs = random_aovs(40, 40, seed=3)
    feats = features.branch_features(aovs, "diffuse")
    whole = Denoiser(tiny_run, tile=4096).run_branch("diffuse", feats)
    seamy = Denoiser(tiny_run, tile=8)
    seamy.margin = 0
    assert np.abs(seamy.run_branch("diffuse", feats) - whole).max() > 1e-4


def test_recombination_inverts_the_branch_transforms(tiny_run):
    aovs = random_aovs(20, 20, seed=4)
    d = Denoiser(tiny_run)
    out = d(aovs)
    diff_log = d.run_branch("diffuse", features.branch_features(aovs, "diffuse"))
    np.testing.assert_allclose(out["diffuse"], np.expm1(diff_log.astype(np.float64)) * (np.clip(aovs["albedo"], 0, 1) + features.ALBEDO_EPS), rtol=1e-5)
    np.testing.assert_allclose(out["default"], out["diffuse"] + out["specular"], rtol=1e-6)


def test_denoises_the_mitsuba_fixture(tiny_run, tmp_path, fixture_noisy, fixture_reference):
    report = denoise_file(fixture_noisy, tiny_run, tmp_path / "fx.exr", fixture_reference)
    out = exr.read_aovs(tmp_path / "fx.exr", variances=False)
    assert out["default"].shape == (64, 64, 3) and np.isfinite(out["default"]).all()
    assert (tmp_path / "fx.png").is_file()
    assert set(report["metrics"]) == set(report["input_metrics"]) == {
        "mse", "relmse", "relse_p999", "smape", "dssim", "psnr"}
    assert all(np.isfinite(v) for v in report["metrics"].values())


# --- batches (issue 9): one load, many frames ---

def test_a_batch_equals_each_frame_alone(tiny_run, tmp_path):
    # bit-exact: the same networks run the same tiles of the same features; nothing carries over between
    # frames (no state in the models at inference, every tile's result depends on its own input only)
    from kpcn_keras.denoise import denoise_files

    names = ["a.exr", "b.exr", "c.exr"]
    for i, (name, size) in enumerate(zip(names, [(20, 24), (33, 17), (20, 24)])):
        exr.write_aovs(tmp_path / "in" / name, random_aovs(*size, seed=30 + i))
    exr.write_aovs(tmp_path / "in" / "old-denoised.exr", random_aovs(8, 8))
    batch = denoise_files([tmp_path / "in"], tiny_run, tmp_path / "out", png=False)
    assert [f["input"] for f in batch["frames"]] == [str(tmp_path / "in" / n) for n in names]
    assert batch["skipped"] == [str(tmp_path / "in" / "old-denoised.exr")]
    assert batch["load_s"] > 0 and batch["warmup_s"] > 0 and all(f["seconds"] > 0 for f in batch["frames"])
    # the peak resident memory is this process's own high-water mark: at least what it holds now
    status = dict(line.split(":", 1) for line in open("/proc/self/status"))
    assert batch["peak_memory_mb"] >= int(status["VmRSS"].split()[0]) / 1024 * 0.9
    for name in names:
        alone = denoise_file(tmp_path / "in" / name, tiny_run, tmp_path / "alone" / name, png=False)
        assert alone["output"] == str(tmp_path / "alone" / name)
        together = exr.read_aovs(tmp_path / "out" / name.replace(".exr", "-denoised.exr"), variances=False)
        single = exr.read_aovs(tmp_path / "alone" / name, variances=False)
        for layer in ("default", "diffuse", "specular"):
            np.testing.assert_array_equal(together[layer], single[layer])


def test_panels_png_is_a_row_of_tonemapped_panels(tmp_path):
    from PIL import Image

    from kpcn_keras.denoise import panels_png
    from prep.metrics import tonemap

    image = random_aovs(10, 12)["default"]
    path = panels_png(tmp_path / "p.png", [("input", image), ("denoised", image * 0.5)], title="t")
    pixels = np.asarray(Image.open(path).convert("RGB"))
    assert pixels.shape == (28 + 10, 2 * 12 + 4, 3)
    np.testing.assert_array_equal(pixels[28:, :12], np.round(tonemap(image) * 255).astype(np.uint8))


def test_plan_outputs(tmp_path):
    from kpcn_keras.denoise import plan_outputs
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
