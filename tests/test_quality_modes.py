"""Quality modes (``--quality fast|balanced|high``, ``kpcn.denoise(..., quality=...)``): a model holds a network set
per mode (``Run.for_quality``; ``kpcn ship --mode MODE=RUN`` ships one into ``<model>/quality/<mode>/``), each mode
served by its own networks, a mode the model lacks refused in one line naming those it has."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.tiny import random_aovs

TINY_UNET = {"arch": "unet", "width": 4, "depth": 1, "levels": 2, "kernel_size": 5}  # fits 16-pixel patches


@pytest.fixture(scope="module")
def mode_runs(tiny_run_of_every_input_set):
    """(balanced, fast): copies of the tiny kpcn run of every input set, the first evaluated (``kpcn ship`` needs
    its report for the card), and a tiny unet run of every input set trained on the same shard sets."""
    from kpcn_keras.evaluate import evaluate
    from kpcn_keras.run import Run
    from kpcn_keras.train import TrainConfig, train
    from prep.inputs import INPUT_SETS

    src = Path(tiny_run_of_every_input_set)
    balanced = Run(src.with_name("modes-balanced"))  # beside it: its records' relative shard set paths hold
    if not balanced.dir.exists():
        shutil.copytree(src, balanced.dir)
        evaluate(balanced, baseline=False)
    fast = Run(src.with_name("modes-fast"))
    base = balanced.record().train
    if not fast.dir.exists():
        for name in INPUT_SETS:
            cfg = TrainConfig.from_preset("cpu", set_name=base.set_name, shards_root=base.shards_root,
                                          model=TINY_UNET, steps=4, steps_per_epoch=4, batch_size=2, val_batches=1,
                                          inputs=name)
            train(cfg, fast.dir, verbose=0)
    return balanced, fast


@pytest.fixture(scope="module")
def two_mode_model(mode_runs, tmp_path_factory):
    balanced, fast = mode_runs
    dest = tmp_path_factory.mktemp("models") / "two"
    res = run_main("ship", "--run", balanced.dir, "--mode", f"fast={fast.dir}", "--out", dest, "--speed-frame",
                   "48,40", cwd=balanced.dir.parent)
    assert res.returncode == 0, res.stderr
    return dest


def test_a_model_serves_each_mode_with_its_own_networks_and_records_where_they_came_from(
        mode_runs, two_mode_model, fixture_noisy, tmp_path):
    import kpcn
    from kpcn_keras.card import card_tables
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from prep.inputs import INPUT_SETS

    balanced, fast = mode_runs
    assert Run(two_mode_model).quality_modes() == ["fast", "balanced"]
    frame = kpcn.read(fixture_noisy)
    outs = {}
    for mode, source in (("balanced", balanced), ("fast", fast)):
        outs[mode] = kpcn.denoise(frame, run=two_mode_model, quality=mode)
        direct = Denoiser.from_run(source.serving(frame.inputs))(frame.layers)["default"]
        np.testing.assert_array_equal(outs[mode], direct)  # the mode's run's own networks, bit for bit
    assert np.abs(outs["fast"] - outs["balanced"]).max() > 1e-5  # tiny networks: near their start, yet apart
    # the record of each shipped folder says which run and which networks (SHA-256) it came from
    for mode, source, folder in (("balanced", balanced, two_mode_model), ("fast", fast, two_mode_model / "quality"
                                                                            / "fast")):
        for name in INPUT_SETS:
            where = folder if name == "full" else folder / "inputs" / name
            source_dir = source.dir if name == "full" else source.dir / "inputs" / name
            record = json.loads((where / "config.json").read_text())
            theirs = json.loads((source_dir / "config.json").read_text())
            assert record["shipped"]["mode"] == mode and record["shipped"]["run"] == str(source_dir), where
            assert record["shipped"]["networks"] == {c: theirs["models"][e["file"]]["sha256"]
                                                     for c, e in theirs["components"].items()}
    # the command line serves the mode asked, and says which folder's networks it used
    res = run_main("denoise", fixture_noisy, "--run", two_mode_model, "--quality", "fast", "-o",
                   tmp_path / "fast.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert f"model {two_mode_model / 'quality' / 'fast'}" in res.stdout
    # the card has a row per mode: its architecture and where it came from
    rows = card_tables((two_mode_model / "CARD.md").read_text())["Quality modes"]
    assert [(r[0], r[1], r[3], r[4]) for r in rows[1:]] == [("balanced (default)", "kpcn", "–", f"`{balanced.dir}`"),
                                                            ("fast", "unet", "–", f"`{fast.dir}`")]
    assert all(int(r[2]) > 0 for r in rows[1:]) and rows[1][2] != rows[2][2]


@pytest.mark.parametrize("mode", ["balanced", "fast"], ids=["kpcn", "unet"])
def test_tiled_inference_equals_untiled_in_each_mode(two_mode_model, mode):
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings
    from prep.inputs import FULL

    aovs = random_aovs(45, 61, seed=4)  # odd: partial tiles
    aovs["depth"][-1, -1] = 50.0
    whole = Serving(Run(two_mode_model), InferenceSettings(tile=128, precision="float32", quality=mode))
    tiled = Serving(Run(two_mode_model), InferenceSettings(tile=16, precision="float32", quality=mode))
    assert whole.run.dir == Run(two_mode_model).quality_dir(mode)
    want, got = whole.denoiser(FULL)(aovs)["default"], tiled.denoiser(FULL)(aovs)["default"]
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-6)


def test_a_mode_the_model_lacks_is_refused_in_one_line_naming_its_modes(two_mode_model, fixture_noisy, tmp_path):
    import kpcn

    res = run_main("denoise", fixture_noisy, "--run", two_mode_model, "--quality", "high", "-o", tmp_path / "o.exr",
                   cwd=tmp_path)
    assert_one_line_error(res, f"{two_mode_model} has no quality mode 'high'", "its modes: fast, balanced")
    assert not (tmp_path / "o.exr").exists()
    with pytest.raises(kpcn.KpcnError, match="has no quality mode 'high'; its modes: fast, balanced"):
        kpcn.denoise(kpcn.read(fixture_noisy), run=two_mode_model, quality="high")


def test_an_unknown_mode_is_refused_naming_the_modes(fixture_noisy, tmp_path):
    from kpcn_keras.settings import InferenceSettings
    from prep.errors import OptionError

    for command in (("denoise", fixture_noisy), ("evaluate", "--run", tmp_path), ("view", fixture_noisy)):
        res = run_main(*command, "--quality", "ultra", cwd=tmp_path)
        last = res.stderr.strip().splitlines()[-1]
        assert res.returncode == 2 and "--quality" in last and "'ultra'" in last, res.stderr
        assert all(f"'{mode}'" in last for mode in ("fast", "balanced", "high")), last
    with pytest.raises(OptionError, match="quality must be one of fast, balanced, high, received 'ultra'"):
        InferenceSettings(quality="ultra")


def test_shipping_a_mode_whose_run_is_unfinished_is_refused_before_anything_is_written(mode_runs, two_mode_model,
                                                                                      tmp_path):
    balanced, fast = mode_runs
    unfinished = fast.dir.with_name("modes-unfinished")
    shutil.copytree(fast.dir, unfinished)
    record = json.loads((unfinished / "inputs" / "no-split" / "config.json").read_text())
    phase = next(iter(record["phases"]))
    record["phases"][phase]["status"] = "running"  # as a training killed in that phase leaves it
    (unfinished / "inputs" / "no-split" / "config.json").write_text(json.dumps(record))
    before = {p: p.read_bytes() for p in two_mode_model.rglob("*") if p.is_file()}
    for dest in (tmp_path / "m", two_mode_model):
        res = run_main("ship", "--run", balanced.dir, "--mode", f"high={unfinished}", "--out", dest,
                       cwd=tmp_path)
        assert_one_line_error(res, "phase is unfinished", "kpcn train --run")
    assert not (tmp_path / "m").exists() and not list(tmp_path.glob(".m.tmp-*"))
    assert {p: p.read_bytes() for p in two_mode_model.rglob("*") if p.is_file()} == before
    # nor a mode named twice, nor the balanced mode, whose networks are --run's
    res = run_main("ship", "--run", balanced.dir, "--mode", f"fast={fast.dir}", "--mode", f"fast={unfinished}",
                   "--out", tmp_path / "m", cwd=tmp_path)
    assert_one_line_error(res, "--mode", "fast mode twice")
    res = run_main("ship", "--run", balanced.dir, "--mode", f"balanced={fast.dir}", "--out", tmp_path / "m",
                   cwd=tmp_path)
    assert res.returncode == 2 and "the balanced mode is the networks of --run" in res.stderr
    assert not (tmp_path / "m").exists()
