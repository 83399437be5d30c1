"""The whole pipeline at toy size, through the command line's entry point: render, shards, 20 training
steps, denoise (our render and the Mitsuba fixture), evaluate."""

import json

import numpy as np
import pytest

from kpcn_keras.cli import main
from prep import exr


@pytest.mark.slow
def test_render_shard_train_denoise_evaluate(tmp_path, monkeypatch, fixture_noisy, fixture_reference, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["-q", "render", "--set", "toy", "--families", "cornell,caustics,outdoor", "--per-family", "2",
                 "--width", "48", "--height", "40", "--input-spp", "4,8", "--reference-spp", "32"]) == 0
    renders = sorted((tmp_path / "data/renders/toy").glob("*.exr"))
    assert len(renders) == 3 * 2 * 3  # families x scenes x (two inputs and the reference)

    assert main(["-q", "shards", "--set", "toy", "--patch-size", "24", "--patches-per-image", "6",
                 "--val-fraction", "0.5"]) == 0
    manifest = json.loads((tmp_path / "shards/toy/manifest.json").read_text())
    assert len(manifest["split"]["val"]) == 3 and not set(manifest["split"]["val"]) & set(manifest["split"]["train"])

    assert main(["-q", "train", "--set", "toy", "--run", "runs/toy", "--steps", "20", "--batch-size", "4",
                 "--width", "8", "--depth", "3", "--kernel-size", "5"]) == 0
    record = json.loads((tmp_path / "runs/toy/config.json").read_text())
    assert record["train"]["steps"] == 20 and set(record["results"]) == {"diffuse", "specular"}

    noisy = next(p for p in renders if p.name.endswith("00004spp.exr"))
    assert main(["-q", "denoise", str(noisy), "--run", "runs/toy", "-o", "out/ours.exr", "--tile", "16"]) == 0
    assert main(["-q", "denoise", str(fixture_noisy), "--run", "runs/toy", "-o", "out/mitsuba.exr",
                 "--reference", str(fixture_reference)]) == 0
    for name, shape in (("ours", (40, 48, 3)), ("mitsuba", (64, 64, 3))):
        out = exr.read_aovs(tmp_path / f"out/{name}.exr", variances=False)
        assert out["default"].shape == shape and np.isfinite(out["default"]).all()
        assert (tmp_path / f"out/{name}.png").stat().st_size > 0
    assert "relmse" in capsys.readouterr().out

    assert main(["-q", "evaluate", "--run", "runs/toy"]) == 0
    rows = json.loads((tmp_path / "runs/toy/eval/metrics.json").read_text())
    assert sorted((r["scene"], r["input spp"]) for r in rows) == sorted((s, n) for s in manifest["split"]["val"] for n in (4, 8))
    assert all(np.isfinite(r["denoised"]["relmse"]) and np.isfinite(r["nlm"]["relmse"]) for r in rows)
    assert all(np.isfinite(r[k]["relse_p999"]) for r in rows for k in ("raw", "denoised", "nlm"))
    report = (tmp_path / "runs/toy/eval/report.md").read_text()
    assert "| scene | input spp | raw relMSE | denoised relMSE | raw relSE p99.9 | denoised relSE p99.9 |" in report
    assert "| NLM relMSE | NLM relSE p99.9 |" in report
