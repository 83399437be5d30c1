"""prep.convergence (a reference's relative standard error from its own variance layers) and ``kpcn
references``, against float64 numpy computations from the variance layers of tiny renders."""

from __future__ import annotations

import json

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.references import reference_relse
from helpers.tiny import random_aovs

from prep import convergence, exr
from prep.render import RenderConfig, make_scene, render, render_set
from prep.render.renderset import CONVERGENCE_REPORT, reference_spp


def np_summary(relse: np.ndarray, spp: int) -> dict:
    r = relse.ravel()
    p99 = np.percentile(r, 99.0)
    return {"median": np.median(r), "p99": p99, "converged": np.mean(r <= 0.05),
            "spp_needed": int(np.ceil(spp * (p99 / 0.05) ** 2))}


@pytest.mark.slow
def test_relse_of_a_tiny_render_equals_a_float64_computation_from_its_variance_layers(tmp_path):
    spp = 16
    path = exr.write_aovs(tmp_path / exr.render_filename("caustics-000", spp),
                          render(make_scene("caustics", 0, 0), spp, 7, 12, 10))
    layers = exr.read_aovs(path, variances=None)
    for branch, (colour, variance) in {"diffuse": ("diffuse", "diffuseVariance"),
                                       "specular": ("specular", "specularVariance"),
                                       "default": ("default", "colorVariance")}.items():
        want = reference_relse(layers[colour], layers[variance])
        got = convergence.branch_relse(layers, branch, path)
        assert got.shape == (10, 12) and got.dtype == np.float32 and want.max() > 0.05
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=0)
        summary, expected = convergence.frame_summary(got, spp), np_summary(want, spp)
        assert summary["spp"] == spp and summary["spp_needed"] == expected.pop("spp_needed")
        for key, value in expected.items():
            assert summary[key] == pytest.approx(value, rel=1e-6)


@pytest.mark.slow
def test_the_variance_layer_is_of_the_pixel_mean_so_relse_is_a_standard_error():
    # the spread of the pixel means over independent seeds is what the variance layer claims for each:
    # a per-sample variance would be spp (8) times too large
    scene, spp, seeds = make_scene("cornell", 0, 0), 8, 24
    renders = [render(scene, spp, seed, 8, 8) for seed in range(seeds)]
    means = np.stack([r["default"] for r in renders]).astype(np.float64)
    spread = means.var(axis=0, ddof=1).mean(axis=-1)  # per pixel, over the seeds, mean over R G B
    claimed = np.mean([r["colorVariance"] for r in renders], axis=0, dtype=np.float64)
    lit = claimed > 0
    ratio = spread[lit].sum() / claimed[lit].sum()
    assert 0.75 < ratio < 1.33, ratio


def test_a_reference_without_variance_layers_reads_and_its_relse_names_the_file(tmp_path):
    full = exr.write_aovs(tmp_path / "a-00064spp.exr", random_aovs(4, 5))
    bare = exr.write_aovs(tmp_path / "b-00064spp.exr", random_aovs(4, 5, variances=False))
    assert set(exr.VARIANCE_LAYERS) <= set(exr.read_aovs(full, variances=None))
    assert not set(exr.VARIANCE_LAYERS) & set(exr.read_aovs(bare, variances=None))
    assert not set(exr.VARIANCE_LAYERS) & set(exr.read_aovs(full, variances=False))
    with pytest.raises(exr.AOVError) as err:
        convergence.branch_relse(exr.read_aovs(bare, variances=None), "specular", bare)
    assert str(bare) in str(err.value) and "specularVariance" in str(err.value) and "\n" not in str(err.value)


def test_relse_floors_negative_variance_and_colour():
    colour = np.float32([[[-1.0, -1.0, -1.0], [0.3, 0.6, 0.9]]])
    variance = np.float32([[0.04, -0.5]])
    np.testing.assert_allclose(convergence.relative_standard_error(colour, variance),
                               [[0.2 / 0.01, 0.0]], rtol=1e-6)


@pytest.mark.slow
def test_kpcn_references_writes_its_three_files_and_an_unknown_set_is_one_line(tmp_path):
    cfg = RenderConfig(set_name="t", families=("cornell", "fireflies"), per_family=1, width=8, height=8,
                       input_spp=(2,), reference_spp=4, out_root=str(tmp_path / "renders"))
    render_set(cfg, progress=False)
    res = run_main("references", "--set", "t", "--out", str(tmp_path / "renders"), cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    folder = tmp_path / "renders" / "t"
    assert all((folder / name).is_file() for name in CONVERGENCE_REPORT)
    report = json.loads((folder / "convergence.json").read_text())
    assert [f["scene"] for f in report["frames"]] == ["cornell-000", "fireflies-000"]
    for frame in report["frames"]:
        assert frame["spp"] == reference_spp(cfg, frame["family"])
        layers = exr.read_aovs(folder / frame["file"])
        want = np_summary(reference_relse(layers["default"], layers["colorVariance"]), frame["spp"])
        assert frame["default"]["p99"] == pytest.approx(want["p99"], rel=1e-5)
        assert frame["default"]["converged"] == pytest.approx(want["converged"])
        assert f"| {frame['scene']} | {frame['spp']} |" in (folder / "convergence.md").read_text()
    assert set(report["families"]) == {"cornell", "fireflies"}
    assert (folder / "convergence.png").read_bytes()[:4] == b"\x89PNG"
    assert "convergence.md" in res.stdout
    assert_one_line_error(run_main("references", "--set", "nope", "--out", str(tmp_path / "renders"),
                                   cwd=tmp_path), "renders/nope", "no render set")
