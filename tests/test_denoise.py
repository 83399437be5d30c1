import numpy as np

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
