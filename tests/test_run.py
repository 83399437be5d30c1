"""A run folder: its record is written only after its inputs are checked, it can be moved, a checkpoint
holds the model and its epoch count in one file, and anything broken in it is one clear line."""

import dataclasses
import json
import shutil
import zipfile

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.files import checksums
from helpers.tiny import build_tiny_shards, random_aovs

from kpcn_keras.config import ModelConfig
from kpcn_keras.denoise import Denoiser
from kpcn_keras.evaluate import evaluate
from kpcn_keras.run import Component, ModelFile, Run, load_model, read_state
from kpcn_keras.train import TrainConfig, train
from prep import exr
from prep.errors import KpcnError
from prep.files import atomic_write_json

TINY = {"width": 4, "depth": 2, "kernel_size": 3}
TRAIN = ("train", "--set", "s", "--shards", "shards", "--width", "4", "--depth", "2", "--kernel-size", "3",
         "--steps", "4", "--batch-size", "2", "--branches", "diffuse")


def tiny_config(shard_cfg, **kw):
    values = dict(set_name=shard_cfg.set_name, shards_root=shard_cfg.out_root, model=TINY, steps=4,
                  steps_per_epoch=2, batch_size=2, val_batches=1, branches=("diffuse",))
    values.update(kw)
    return TrainConfig.from_preset("cpu", **values)


def weights(path):
    return [np.asarray(w) for w in load_model(path, compile=False).get_weights()]


@pytest.mark.slow
def test_a_first_train_that_fails_its_checks_writes_nothing_and_the_corrected_command_runs(tmp_path):
    build_tiny_shards(tmp_path)
    before = checksums(tmp_path)
    res = run_main(*TRAIN, "--run", "runs/r", "--batch-size", "100000", cwd=tmp_path)
    assert_one_line_error(res, "--batch-size", "100000")
    assert checksums(tmp_path) == before and not (tmp_path / "runs" / "r" / "config.json").exists()
    res = run_main(*TRAIN, "--run", "runs/r", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "runs" / "r" / "config.json").is_file() and (tmp_path / "runs" / "r" / "diffuse.keras").is_file()


@pytest.mark.slow
def test_a_renamed_run_folder_is_still_the_same_run(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg), tmp_path / "runs" / "r", verbose=0)
    done = checksums(run_dir)
    moved = run_dir.rename(tmp_path / "runs" / "renamed")
    again = train(tiny_config(shard_cfg), moved, verbose=0)  # finds every branch finished
    assert {k: v for k, v in checksums(again).items() if k != "timings.json"} == \
           {k: v for k, v in done.items() if k != "timings.json"}
    run = Run(moved)
    assert run.shard_set(run.record()).dir.resolve() == shard_cfg.set_dir.resolve()


@pytest.mark.slow
def test_a_checkpoint_of_another_architecture_is_refused(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    other = train(tiny_config(shard_cfg, model={**TINY, "width": 6}), tmp_path / "runs" / "wide", verbose=0)
    run_dir = tmp_path / "runs" / "r"
    shutil.copytree(other / "checkpoints", run_dir / "checkpoints")
    with pytest.raises(KpcnError, match="checkpoint of another configuration"):
        train(tiny_config(shard_cfg), run_dir, verbose=0)
    assert not (run_dir / "diffuse.keras").exists()


@pytest.mark.slow
def test_a_checkpoint_whose_weights_disagree_with_its_record_is_refused(tmp_path):
    # the state entry claims the run's model, the weights are another's: checked against the weights
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg), tmp_path / "runs" / "r", verbose=0)
    wide = train(tiny_config(shard_cfg, model={**TINY, "width": 6}), tmp_path / "runs" / "wide", verbose=0)
    ckpt = run_dir / "checkpoints" / "diffuse.keras"
    state = zipfile.ZipFile(ckpt).read("kpcn-state.json")
    with zipfile.ZipFile(wide / "checkpoints" / "diffuse.keras") as src, zipfile.ZipFile(ckpt, "w") as dst:
        for item in src.infolist():
            dst.writestr(item, state if item.filename == "kpcn-state.json" else src.read(item))
    (run_dir / "diffuse.keras").unlink()
    with pytest.raises(KpcnError, match="diffuse.keras"):
        train(tiny_config(shard_cfg), run_dir, verbose=0)


@pytest.mark.slow
def test_a_checkpoint_is_one_file_holding_the_model_and_its_epoch_count(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, steps=6), tmp_path / "runs" / "r", verbose=0)
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["diffuse.keras"]
    ckpt = run_dir / "checkpoints" / "diffuse.keras"
    state = read_state(ckpt)
    assert state["epochs_done"] == 3 and [h["epoch"] for h in state["history"]] == [0, 1, 2]
    assert state["model"] == tiny_config(shard_cfg).model.to_dict()
    for a, b in zip(weights(ckpt), weights(run_dir / "diffuse.keras")):
        np.testing.assert_array_equal(a, b)
    # the same weights give the same bytes: a model's checksum means something
    again = train(tiny_config(shard_cfg, steps=6), tmp_path / "runs" / "again", verbose=0)
    assert (again / "diffuse.keras").read_bytes() == (run_dir / "diffuse.keras").read_bytes()


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["truncated", "not json", "no train key"])
def test_a_broken_run_record_is_one_line_naming_it(tmp_path, damage):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg), tmp_path / "runs" / "r", verbose=0)
    record = run_dir / "config.json"
    text = record.read_text()
    record.write_text({"truncated": text[: len(text) // 2], "not json": "<html>", "no train key": "{}"}[damage])
    before = checksums(tmp_path)
    res = run_main(*TRAIN, "--run", "runs/r", cwd=tmp_path)
    assert_one_line_error(res, "runs/r/config.json")
    exr.write_aovs(tmp_path / "in.exr", random_aovs(8, 8))
    res = run_main("denoise", "in.exr", "--run", "runs/r", cwd=tmp_path)
    assert_one_line_error(res, "runs/r/config.json")
    assert {k: v for k, v in checksums(tmp_path).items() if k != "in.exr"} == before


@pytest.mark.slow
def test_the_record_train_wrote_reads_back_typed_with_the_model_config_it_trained(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    cfg = tiny_config(shard_cfg, branches=BOTH)
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    text = (run_dir / "config.json").read_text()
    record = Run(run_dir).record()
    assert isinstance(record.model, ModelConfig) and record.model == cfg.model
    assert record.model == ModelConfig.from_dict(json.loads(text)["train"]["model"])
    assert (record.model.width, record.model.depth, record.model.kernel_size) == (4, 2, 3)
    assert record.train == cfg and record.compositor is None and record.validation_slope is None
    sums = checksums(run_dir)
    assert dict(record.models) == {f"{b}.keras": ModelFile(b, sums[f"{b}.keras"]) for b in BOTH}
    assert dict(record.components) == {b: Component(f"{b}.keras") for b in BOTH}
    assert dict(record.phases) == {b: "done" for b in BOTH} and record.finished() is record
    assert Run(run_dir).shard_set(record).dir.resolve() == shard_cfg.set_dir.resolve()
    with pytest.raises(dataclasses.FrozenInstanceError):
        record.train = None
    atomic_write_json(tmp_path / "again.json", record.data)
    assert (tmp_path / "again.json").read_text() == text  # the file's format is the writers', untouched


@pytest.mark.parametrize("part, damage", [
    ("train", lambda r: r["train"]["model"].update(width=0)),
    ("train", lambda r: r["train"]["model"].update(widht=4)),
    ("train", lambda r: r["train"].update(steps="many")),
    ("shards", lambda r: r["shards"].pop("set_dir")),
    ("components", lambda r: r["components"]["diffuse"].pop("file")),
    ("models", lambda r: r["models"]["specular.keras"].pop("sha256")),
    ("phases", lambda r: r.update(phases=["diffuse"])),
], ids=["width 0", "unknown model key", "steps a string", "no set_dir", "component without file",
        "model without sha256", "phases a list"])
def test_a_damaged_part_of_the_record_is_one_line_naming_the_file_and_the_part(tiny_run, tmp_path, part, damage):
    record = json.loads((tiny_run / "config.json").read_text())
    damage(record)
    atomic_write_json(tmp_path / "r" / "config.json", record)
    with pytest.raises(KpcnError) as err:
        Run(tmp_path / "r").record()
    message = str(err.value)
    assert message.startswith(f"{tmp_path / 'r' / 'config.json'}: the run record is damaged in its {part} (")
    assert "\n" not in message


@pytest.mark.slow
@pytest.mark.parametrize("which", ["checkpoints/diffuse.keras", "diffuse.keras"])
def test_a_corrupt_model_file_is_one_line_naming_it_not_file_not_found(tmp_path, which):
    build_tiny_shards(tmp_path)
    assert run_main(*TRAIN, "--run", "runs/r", "--branches", "diffuse,specular", cwd=tmp_path).returncode == 0
    run_dir = tmp_path / "runs" / "r"
    victim = run_dir / which
    victim.write_bytes(victim.read_bytes()[:500])
    before = checksums(tmp_path)
    if which == "diffuse.keras":
        exr.write_aovs(tmp_path / "in.exr", random_aovs(8, 8))
        res = run_main("denoise", "in.exr", "--run", "runs/r", cwd=tmp_path)
        assert not (tmp_path / "in-denoised.exr").exists()
    else:
        (run_dir / "diffuse.keras").unlink()  # so that training goes back to the checkpoint
        before = checksums(tmp_path)
        res = run_main(*TRAIN, "--run", "runs/r", "--branches", "diffuse,specular", cwd=tmp_path)
    assert_one_line_error(res, which)
    assert "File not found" not in res.stderr
    assert {k: v for k, v in checksums(tmp_path).items() if k != "in.exr"} == before


BOTH = ("diffuse", "specular")


@pytest.mark.slow
def test_a_specular_file_that_is_a_copy_of_the_diffuse_file_is_refused_naming_the_branch(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, branches=BOTH), tmp_path / "runs" / "r", verbose=0)
    shutil.copyfile(run_dir / "diffuse.keras", run_dir / "specular.keras")
    exr.write_aovs(tmp_path / "in.exr", random_aovs(8, 8))
    before = checksums(tmp_path)
    res = run_main("denoise", "in.exr", "--run", "runs/r", cwd=tmp_path)
    assert_one_line_error(res, "runs/r/specular.keras", "holds a diffuse network", "its specular network")
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_a_model_file_replaced_by_another_runs_is_refused_by_its_checksum(tmp_path):
    # the same branch, the same architecture, other weights: only the record's SHA-256 tells them apart
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, branches=BOTH), tmp_path / "runs" / "r", verbose=0)
    other = train(tiny_config(shard_cfg, branches=BOTH, seed=5), tmp_path / "runs" / "other", verbose=0)
    assert Run(run_dir).read_record()["models"]["specular.keras"] == \
        {"network": "specular", "sha256": checksums(run_dir)["specular.keras"]}
    shutil.copyfile(other / "specular.keras", run_dir / "specular.keras")
    with pytest.raises(KpcnError, match=r"specular\.keras: not the file this run wrote \(SHA-256 "
                                        + checksums(other)["specular.keras"][:12]):
        Denoiser.from_run(Run(run_dir))


@pytest.mark.slow
def test_a_run_written_before_records_held_checksums_loads_and_is_still_checked_by_branch(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, branches=BOTH), tmp_path / "runs" / "r", verbose=0)
    run = Run(run_dir)
    record = run.read_record()
    del record["models"]
    run.write_record(record)
    aovs = random_aovs(8, 8)
    assert np.isfinite(Denoiser.from_run(Run(run_dir))(aovs)["default"]).all()
    shutil.copyfile(run_dir / "diffuse.keras", run_dir / "specular.keras")
    with pytest.raises(KpcnError, match="specular.keras: holds a diffuse network"):
        Denoiser.from_run(Run(run_dir))


@pytest.mark.slow
@pytest.mark.parametrize("status", ["running", "pending"])
def test_a_run_with_an_unfinished_phase_is_refused_by_its_readers_naming_the_phase(tmp_path, status):
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, branches=BOTH), tmp_path / "runs" / "r", verbose=0)
    run = Run(run_dir)
    record = run.read_record()
    record["phases"]["specular"]["status"] = status
    run.write_record(record)
    exr.write_aovs(tmp_path / "in.exr", random_aovs(8, 8))
    before = checksums(tmp_path)
    res = run_main("denoise", "in.exr", "--run", "runs/r", cwd=tmp_path)
    assert_one_line_error(res, "runs/r/config.json", f"specular phase is unfinished (status '{status}')",
                          "'kpcn train --run runs/r'")
    with pytest.raises(KpcnError, match="specular phase is unfinished"):
        evaluate(Run(run_dir))
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_a_diffuse_checkpoint_in_the_specular_slot_is_refused_naming_the_phase_and_nothing_that_agrees(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    cfg = tiny_config(shard_cfg, branches=BOTH)
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    (run_dir / "specular.keras").unlink()  # so that training goes back to the specular checkpoint
    shutil.copyfile(run_dir / "checkpoints" / "diffuse.keras", run_dir / "checkpoints" / "specular.keras")
    with pytest.raises(KpcnError) as err:
        train(cfg, run_dir, verbose=0)
    message = str(err.value)
    assert "checkpoints/specular.keras: checkpoint of another configuration (it is the diffuse phase's, this " \
           "is the specular phase's)" in message
    assert "model" not in message and "{" not in message, message  # no setting that agrees is printed
    assert not (run_dir / "specular.keras").exists()


@pytest.mark.slow
def test_a_checkpoint_of_another_width_is_refused_naming_only_the_width(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    other = train(tiny_config(shard_cfg, model={**TINY, "width": 6}), tmp_path / "runs" / "wide", verbose=0)
    run_dir = tmp_path / "runs" / "r"
    shutil.copytree(other / "checkpoints", run_dir / "checkpoints")
    with pytest.raises(KpcnError) as err:
        train(tiny_config(shard_cfg), run_dir, verbose=0)
    assert "(model width 6, the run's 4)" in str(err.value), str(err.value)


@pytest.mark.slow
def test_a_run_whose_resample_round_is_unfinished_is_refused_by_denoise_but_resampled_on(tmp_path):
    # a kill between a round's two branch phases leaves the diffuse network a round ahead of the specular
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = train(tiny_config(shard_cfg, branches=BOTH), tmp_path / "runs" / "r", verbose=0)
    run = Run(run_dir)
    record = run.read_record()
    record["resample"] = {"config": {}, "rounds": {"round-001": {"status": "training", "seconds": {}}}}
    run.write_record(record)
    with pytest.raises(KpcnError, match=r"resample round-001 is unfinished \(status 'training'\); "
                                        r"'kpcn resample --run .*' with the options it was started with resumes it"):
        Denoiser.from_run(Run(run_dir))
    assert Denoiser.from_run(Run(run_dir), resampling=True).record.data == record  # the loop's own use, mid-round


# --- a damaged model folder: refused the same way by every path that takes one ---


def _damaged_model(tmp_path, damage: str):
    """A copy of the shipped model (a variant for every input set) with its record removed or made unreadable, or
    its no-variance variant's diffuse network removed."""
    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR

    model = shutil.copytree(MODELS_DIR / DEFAULT_MODEL, tmp_path / "model")
    if damage == "no record":
        (model / "config.json").unlink()
    elif damage == "unreadable record":
        (model / "config.json").write_text('{"train": ')
    else:
        (model / "inputs" / "no-variance" / "diffuse.keras").unlink()
    return model


@pytest.mark.parametrize("damage, line", [
    ("no record", "{model}: not a run folder (no config.json); its inputs/ holds only the variants no-variance, "
                  "no-split, no-split-no-variance"),
    ("unreadable record", "{model}/config.json: "),
])
def test_a_damaged_model_folder_is_refused_the_same_way_by_every_path(tmp_path, fixture_noisy, monkeypatch, damage,
                                                                      line):
    """``--run`` of denoise, evaluate and view, ``KPCN_MODEL``, the API: the same one line, nothing written (a
    variant in ``inputs/`` is never taken in the place of the model the frame needs)."""
    import kpcn

    model = _damaged_model(tmp_path, damage)
    line = line.format(model=model)
    out = tmp_path / "out"
    for args in (("denoise", fixture_noisy, "--run", model, "-o", out),
                 ("evaluate", "--run", model, fixture_noisy, "--out", out, "--no-baseline"),
                 ("view", fixture_noisy, "--run", model, "--port", "0")):
        assert_one_line_error(run_main(*args, cwd=tmp_path), line)
        assert not out.exists()
    monkeypatch.setenv("KPCN_MODEL", str(model))
    assert_one_line_error(run_main("denoise", fixture_noisy, "-o", out, cwd=tmp_path), line, "KPCN_MODEL")
    assert not out.exists()
    for run in (model, None):
        with pytest.raises(KpcnError) as err:
            kpcn.denoise(kpcn.read(fixture_noisy), run=run)
        assert line in str(err.value) and "\n" not in str(err.value)


def test_a_variant_without_its_weights_is_refused_before_any_frame_is_written(tmp_path, fixture_noisy):
    """A frame of the full set and a Blender frame (no variance: served by ``inputs/no-variance``) in one command,
    that variant's diffuse network removed: refused before the first frame is denoised, naming the file."""
    from helpers.paths import FIXTURES

    model = _damaged_model(tmp_path, "weights")
    blender = shutil.copy(FIXTURES / "renderers" / "cycles5" / "studio-00016spp.exr", tmp_path / "b.exr")
    out = tmp_path / "out"
    res = run_main("denoise", fixture_noisy, blender, "--run", model, "-o", out, cwd=tmp_path)
    assert_one_line_error(res, str(model / "inputs" / "no-variance" / "diffuse.keras"))
    assert not out.exists()
