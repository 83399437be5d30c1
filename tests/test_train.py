import json
import signal
import time
from pathlib import Path

import keras
import numpy as np
import pytest
from helpers.commands import WarmProcess, command_env
from helpers.files import checksums
from helpers.tiny import build_tiny_shards, tiny_train_config

from kpcn_keras.callbacks import FROZEN_EPOCHS, frozen
from kpcn_keras.run import load_model, read_state
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import TrainConfig, starts_trained, train
from prep.errors import KpcnError, OptionError


def tiny_config(shard_cfg, **kw):
    return tiny_train_config(shard_cfg, **{"steps": 6, **kw})


def weights(run_dir: Path, branch: str):
    model = keras.models.load_model(run_dir / f"{branch}.keras", compile=False)
    return [np.asarray(w) for w in model.get_weights()]


@pytest.mark.slow
def test_run_folder_records_how_it_was_made(tmp_path):
    cfg = tiny_config(build_tiny_shards(tmp_path))
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    record = json.loads((run_dir / "config.json").read_text())
    assert record["train"] == cfg.to_dict()
    assert record["shards"]["set_dir"] == "../../shards/s"  # relative to the run: the tree can move
    assert set(record["results"]) == {"diffuse", "specular"}
    assert record["shards"]["split"]["val"] == ["a-001", "b-001"]
    assert {name: (p["first_epoch"], p["epochs"], p["status"]) for name, p in record["phases"].items()} == \
        {"diffuse": (0, 3, "done"), "specular": (3, 3, "done")}
    assert record["components"] == {b: {"file": f"{b}.keras", "phase": b} for b in ("diffuse", "specular")}
    log = (run_dir / "log.csv").read_text().splitlines()
    assert log[0].startswith("epoch") and [int(row.split(",")[0]) for row in log[1:]] == list(range(6))
    assert np.isfinite(float(log[-1].split(",")[1]))
    assert (run_dir / "loss.png").read_bytes().startswith(b"\x89PNG")


@pytest.mark.slow
def test_every_phase_trains_exactly_the_steps_asked(tmp_path):
    """Steps that are not a multiple of the epoch's: the last epoch is shorter, so each phase's optimizer
    counts exactly the steps asked (the record's), not whole epochs; the log has one row per epoch."""
    cfg = tiny_config(build_tiny_shards(tmp_path), steps=6, steps_per_epoch=4, joint_steps=5, compositor_steps=3,
                      compositor={"kind": "alpha", "width": 4, "depth": 3, "kernel_size": 3})
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    record = json.loads((run_dir / "config.json").read_text())
    asked = {"diffuse": 6, "specular": 6, "joint": 5, "compositor": 3}
    iterations = {name: int(load_model(run_dir / f"{name}.keras").optimizer.iterations.numpy()) for name in asked}
    assert iterations == asked
    assert {name: p["steps"] for name, p in record["phases"].items()} == asked
    rows = (run_dir / "log.csv").read_text().splitlines()[1:]
    assert len(rows) == 2 + 2 + 2 + 1  # 4 + 2, 4 + 2, 4 + 1 and 3 steps


@pytest.mark.slow
def test_asymmetric_loss_trains_on_reference_and_noisy_targets(tmp_path):
    cfg = tiny_config(build_tiny_shards(tmp_path), branches=("specular",), loss="asymmetric", slope=4.0, steps=4)
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    model = keras.models.load_model(run_dir / "checkpoints" / "specular.keras")
    assert model.loss.slope == 4.0
    losses = [float(line.split(",")[1]) for line in (run_dir / "log.csv").read_text().splitlines()[1:]]
    assert losses and all(np.isfinite(losses))


@pytest.mark.slow
def test_divergence_stops_with_a_clear_error_and_no_finished_model(tmp_path):
    # the kernel softmax saturates rather than overflows at any finite weight, so only a step
    # that takes the weights past float32 max (Adam's step is about the learning rate) diverges: set
    # past the options' bounds (--lr at most 1), which the config checks when it is made
    cfg = tiny_config(build_tiny_shards(tmp_path), branches=("diffuse",))
    cfg.learning_rate, cfg.clipnorm = 3e38, 1e38
    with pytest.raises(KpcnError, match=r"diverged \(loss (nan|-?inf) at batch \d+\); the last good checkpoint is .*"
                                        r"checkpoints/diffuse\.keras"):
        train(cfg, tmp_path / "runs" / "r", verbose=0)
    assert not (tmp_path / "runs" / "r" / "diffuse.keras").exists()


def test_a_still_validation_loss_beside_a_moving_training_loss_is_frozen():
    def history(val, loss):
        return [{"val_loss": v, "loss": t} for v, t in zip(val, loss)]

    moving = [0.044, 0.038, 0.037]
    # the unet specular phase of the quality study, as logged: float32 rounding apart, one validation loss
    assert frozen(history([0.09126332402229309, 0.09126333892345428, 0.09126332402229309], moving))
    assert frozen(history([0.5, 0.0912633, 0.0912633, 0.0912633], [0.1] + moving))  # the last epochs decide
    assert not frozen(history([0.0913, 0.0912, 0.0911], moving))  # learning, slowly
    assert not frozen(history([0.0913] * 3, [0.04] * 3))  # nothing moves: no evidence either way
    assert not frozen(history([0.0913] * (FROZEN_EPOCHS - 1), moving))
    assert not frozen(history([0.0913, float("nan"), 0.0913], moving))  # no validation
    # a phase that starts from finished networks, on the plateau it started on (make train's albedo phase, seed 1,
    # as logged: it left it a score of epochs later): not judged until its validation loss has left its start
    plateau = [0.002476734109222889, 0.0024767383001744747, 0.002476738067343831, 0.0024767373688519]
    assert frozen(history(plateau, [0.0118, 0.0083] + moving[1:]))
    assert not frozen(history(plateau, [0.0118, 0.0083] + moving[1:]), started_trained=True)
    left = [0.0025, 0.0024, 0.0021, 0.00210000001, 0.0021]  # then frozen after leaving it: judged as any phase
    assert frozen(history(left, [0.01, 0.009] + moving), started_trained=True)
    assert not frozen(history([0.0025 * (1 + 9e-4), 0.0025, 0.0025, 0.0025], [0.01] + moving), started_trained=True)


def test_the_phases_that_start_from_finished_networks_are_those_built_from_them():
    def started(**kw):
        cfg = TrainConfig.from_preset("cpu", **kw)
        return {phase.name: starts_trained(cfg, phase) for phase in cfg.phases()}

    assert started() == {"diffuse": False, "specular": False}
    assert started(joint_steps=5, albedo_steps=5) == {"diffuse": False, "specular": False, "joint": True,
                                                      "albedo": True}
    # --init starts the branch networks from another run's; a compositor is a new network all the same
    assert started(init="runs/other", compositor={"kind": "kernel"}) == {"diffuse": True, "specular": True,
                                                                         "compositor": False}


class _SaturateKernels(keras.callbacks.Callback):
    """Puts one tap's logit far above the rest in every pixel: a softmax that has saturated, as the unet preset's
    specular network's did at lr 0.001 (no gradient passes it, so it stays)."""

    def on_train_begin(self, logs=None):
        head = next(layer for layer in self.model.layers if layer.name.endswith("kernel_logits"))
        kernel, bias = head.get_weights()
        bias[:] = 0.0
        bias[0] = 1e4
        head.set_weights([kernel, bias])


@pytest.mark.slow
def test_saturated_kernels_stop_the_phase_with_a_clear_error(tmp_path):
    cfg = tiny_config(build_tiny_shards(tmp_path), branches=("diffuse",), steps=12)
    with pytest.raises(KpcnError, match=rf"training the diffuse phase stalled: its validation loss stayed \S+ for "
                                        rf"{FROZEN_EPOCHS} epochs while its training loss went .* lower learning rate "
                                        r"\(--lr; this run's is 0.001\)"):
        train(cfg, tmp_path / "r", verbose=0, callbacks=[_SaturateKernels()])
    assert not (tmp_path / "r" / "diffuse.keras").exists()
    assert len((tmp_path / "r" / "log.csv").read_text().splitlines()) == 1 + FROZEN_EPOCHS


@pytest.mark.slow
def test_same_seed_same_model_on_cpu(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    a = train(tiny_config(shard_cfg, branches=("diffuse",)), tmp_path / "a", verbose=0)
    b = train(tiny_config(shard_cfg, branches=("diffuse",)), tmp_path / "b", verbose=0)
    for wa, wb in zip(weights(a, "diffuse"), weights(b, "diffuse")):
        np.testing.assert_array_equal(wa, wb)


@pytest.mark.slow
def test_another_configuration_under_the_same_run_is_refused(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    train(tiny_config(shard_cfg, branches=("diffuse",)), tmp_path / "r", verbose=0)
    with pytest.raises(KpcnError, match="differs in.*learning_rate"):
        train(tiny_config(shard_cfg, branches=("diffuse",), learning_rate=0.5), tmp_path / "r", verbose=0)


@pytest.mark.slow
def test_killed_run_resumes_to_the_uninterrupted_result(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    steps = dict(steps=38, steps_per_epoch=4)  # 9 epochs of 4 steps and a last one of 2
    reference = train(tiny_config(shard_cfg, branches=("diffuse",), **steps), tmp_path / "ref", verbose=0)

    # the library call that `kpcn train` makes, with a short epoch so that a kill lands mid-run
    cfg = tiny_config(shard_cfg, branches=("diffuse",), **steps)
    run_dir = tmp_path / "killed" / "r"
    checkpoint = run_dir / "checkpoints" / "diffuse.keras"
    proc = WarmProcess(train, (cfg, str(run_dir)), {"verbose": 0}, cwd=tmp_path, env=command_env())
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if checkpoint.is_file() and 1 <= read_state(checkpoint)["epochs_done"] < 10:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    done = read_state(checkpoint)["epochs_done"]
    assert 1 <= done < 10, f"the run should have been killed mid-way, it had done {done} epochs"
    assert not (run_dir / "diffuse.keras").exists()

    train(cfg, run_dir, verbose=0)  # the same command again resumes
    for wa, wb in zip(weights(reference, "diffuse"), weights(run_dir, "diffuse")):
        np.testing.assert_array_equal(wa, wb)


@pytest.mark.slow
@pytest.mark.parametrize("damage", ["emptied", "cut to its first epochs", "torn in its last row"])
def test_a_damaged_log_is_refused_on_resume_rather_than_losing_its_epochs(tmp_path, damage):
    cfg = tiny_config(build_tiny_shards(tmp_path))
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    (run_dir / "specular.keras").unlink()  # a kill after the specular phase's last checkpoint: it resumes
    log = run_dir / "log.csv"
    text = log.read_bytes()
    log.write_bytes({"emptied": b"", "cut to its first epochs": b"".join(text.splitlines(keepends=True)[:3]),
                     "torn in its last row": text[: text.rindex(b",")]}[damage])
    before = checksums(run_dir)
    with pytest.raises(KpcnError, match=r"log\.csv: holds .* where the run has trained 6"):
        train(cfg, run_dir, verbose=0)
    assert checksums(run_dir) == before


# --- as long as held-out error falls: early stopping ---

def _val_losses(run_dir: Path, plan: dict) -> list[float]:
    rows = (run_dir / "log.csv").read_text().splitlines()
    header = rows[0].split(",")
    epochs = range(plan["first_epoch"], plan["first_epoch"] + plan["epochs"])
    return [float(dict(zip(header, r.split(",")))["val_loss"]) for r in rows[1:] if int(r.split(",")[0]) in epochs]


@pytest.mark.slow
def test_patience_stops_a_phase_once_validation_loss_stops_falling_and_keeps_its_best_epoch(tmp_path):
    from kpcn_keras import distributed
    from kpcn_keras.train import _data, check_inputs
    from prep.shards import ShardSet

    patience = 2
    cfg = tiny_config(build_tiny_shards(tmp_path), steps=120, steps_per_epoch=2, decay_steps=120,
                      learning_rate=0.05, patience=patience)
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    record = json.loads((run_dir / "config.json").read_text())
    for branch in ("diffuse", "specular"):
        plan = record["phases"][branch]
        val = _val_losses(run_dir, plan)
        # the stopping rule, recomputed from the log: the first epoch `patience` after the best so far
        best = int(np.argmin(val))
        stop = next((e for e in range(len(val)) if e - int(np.argmin(val[: e + 1])) >= patience), None)
        assert stop is not None and len(val) == stop + 1 < plan["epochs"] == 60, (branch, val)
        assert (plan["epochs_trained"], plan["best_epoch"]) == (len(val), best)
        # the phase's model is the best epoch's: its validation loss, measured again, is the logged best
        phase = next(p for p in cfg.phases() if p.name == branch)
        _, paths = check_inputs(cfg, ShardSet(cfg.set_dir))
        _, stream = _data(cfg, phase, paths, 0, 1, distributed.World())
        measured = load_model(run_dir / f"{branch}.keras").evaluate(stream, verbose=0)
        measured = measured[0] if isinstance(measured, list) else measured
        assert measured == pytest.approx(val[best], rel=1e-5)
        assert measured < val[-1]
    # the next phase kept its place in the numbering: the log has a gap where diffuse stopped
    assert record["phases"]["specular"]["first_epoch"] == 60


@pytest.mark.slow
def test_a_stopped_run_resumes_after_a_kill_to_the_same_files(tmp_path):
    """A kill after a stopped phase's last checkpoint but before its model (the record says pending): the
    rerun trains nothing, accepts the log with its gap, and writes the same model."""
    cfg = tiny_config(build_tiny_shards(tmp_path), steps=120, steps_per_epoch=2, decay_steps=120,
                      learning_rate=0.05, patience=2)
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    model = (run_dir / "specular.keras").read_bytes()
    (run_dir / "specular.keras").unlink()
    record = json.loads((run_dir / "config.json").read_text())
    record["phases"]["specular"].update(status="pending")
    del record["phases"]["specular"]["epochs_trained"], record["phases"]["specular"]["best_epoch"]
    (run_dir / "config.json").write_text(json.dumps(record))
    log = (run_dir / "log.csv").read_bytes()
    train(cfg, run_dir, verbose=0)
    assert (run_dir / "specular.keras").read_bytes() == model
    assert (run_dir / "log.csv").read_bytes() == log


@pytest.mark.slow
def test_patience_without_held_out_scenes_is_refused_before_the_run_is_written(tmp_path):
    cfg = tiny_config(build_tiny_shards(tmp_path, val_fraction=0.0), patience=2)
    with pytest.raises(OptionError, match=r"patience.*2 stops on the validation loss.*no held-out scenes"):
        train(cfg, tmp_path / "runs" / "r", verbose=0)
    assert not (tmp_path / "runs" / "r").exists()


def test_a_run_without_early_stopping_keeps_the_identity_it_had_before_patience_existed():
    cfg = TrainConfig()
    assert "patience" not in cfg.to_dict() and TrainConfig.from_record(cfg.to_dict()) == cfg
    assert TrainConfig(patience=3).to_dict()["patience"] == 3
    with pytest.raises(OptionError, match="patience"):
        TrainConfig(patience=-1)


@pytest.mark.slow
def test_a_run_recorded_without_a_lambda_module_resumes_whether_its_record_names_the_module_or_not(tmp_path):
    cfg = tiny_config(build_tiny_shards(tmp_path))
    run_dir = train(cfg, tmp_path / "runs" / "r", verbose=0)
    path = run_dir / "config.json"
    record = json.loads(path.read_text())
    # as written before --slope-module existed: the study plans and runs of then keep their identity
    assert not {"slope_module", "slope_mixture"} & set(record["train"]["model"])
    record["train"]["model"].update(slope_module=0, slope_mixture=0)  # as a run record of 2026-12-03 wrote it
    path.write_text(json.dumps(record))
    train(cfg, run_dir, verbose=0)  # the same run: finished, nothing to do, no error
    record["train"]["model"].update(slope_channel=True, slope_module=2)
    record["train"].update(loss="asymmetric", slope_input=True)
    path.write_text(json.dumps(record))
    with pytest.raises(KpcnError, match=r"another configuration \(differs in loss, model, slope_input\)"):
        train(cfg, run_dir, verbose=0)


# --- what training takes must fit what the shards hold, and its seed range is the project's ---

@pytest.mark.slow
def test_a_seed_beyond_the_projects_range_is_refused_in_one_line_and_leaves_no_run(tmp_path):
    from helpers.commands import assert_one_line_error, run_main

    shard_cfg = build_tiny_shards(tmp_path)
    res = run_main("train", "--set", "s", "--shards", shard_cfg.out_root, "--run", "runs/r", "--seed", str(2**32),
               "--steps", "2", cwd=tmp_path)
    assert_one_line_error(res, "--seed must be an integer in [0, 4294967295], got 4294967296")
    assert not (tmp_path / "runs").exists()


def test_the_projects_seed_range_is_the_one_training_seeds_take():
    from prep.bounds import SEED

    keras.utils.set_random_seed(SEED.high)  # the largest seed trains (numpy's legacy seeding takes it)
    np.random.seed(SEED.high)
    with pytest.raises(ValueError):
        np.random.seed(SEED.high + 1)  # the first one refused: what a seed >= 2**32 met in training


@pytest.mark.slow
@pytest.mark.parametrize("model, option, needles", [
    ({"width": 4, "depth": 1, "kernel_size": 17}, "kernel_size", ["17 is larger than the 16x16 patches", "at most 15"]),
    ({"width": 4, "depth": 8, "kernel_size": 5}, "depth", ["receptive field of 17x17 pixels", "16x16 patches"]),
    ({"arch": "kpal", "width": 4, "depth": 4, "kernel_size": 5}, "depth", ["kpal", "19x19", "16x16 patches"]),
    ({"arch": "unet", "width": 4, "depth": 1, "levels": 3, "kernel_size": 5}, "depth",
     ["unet", "--levels 3", "27x27", "16x16 patches", "or --levels"]),
])
def test_a_network_larger_than_the_shard_patches_is_refused_naming_both_before_the_run_is_written(
        tmp_path, model, option, needles):
    shard_cfg = build_tiny_shards(tmp_path)  # 16x16 patches
    with pytest.raises(OptionError) as err:
        train(tiny_config(shard_cfg, model=model), tmp_path / "runs" / "r", verbose=0)
    assert err.value.option == option and all(n in str(err.value) for n in needles), str(err.value)
    assert not (tmp_path / "runs").exists()


@pytest.mark.slow
def test_the_unet_preset_trains_and_denoises(tmp_path):
    """The preset as it is (4 levels, 32/48/72/96 filters, batch 8), 2 steps a branch on 65x65 patches (its
    receptive field is 59 pixels), then a frame of odd size denoised by the finished run."""
    from helpers.tiny import make_renders, random_aovs

    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from prep import shards

    make_renders(tmp_path / "renders" / "s", size=(72, 70))
    shard_cfg = shards.ShardConfig(set_name="s", render_root=str(tmp_path / "renders"),
                                   out_root=str(tmp_path / "shards"), patches_per_image=8, patches_per_shard=8,
                                   val_fraction=0.5, seed=3)
    shards.build_shards(shard_cfg, progress=False)
    cfg = TrainConfig.from_preset("unet", set_name="s", shards_root=shard_cfg.out_root, steps=2, val_batches=1)
    assert (cfg.batch_size, cfg.model.unet_widths(), shard_cfg.patch_size) == (8, (32, 48, 72, 96), 65)
    run_dir = train(cfg, tmp_path / "runs" / "u", verbose=0)
    moved = [w for w in weights(run_dir, "diffuse") if w.ndim == 4 and w.shape[-1] == 13 * 13]
    assert len(moved) == 1 and np.abs(moved[0]).max() > 0  # the zero-initialised kernel head trained
    out = Denoiser.from_run(Run(run_dir), InferenceSettings(tile=32))(random_aovs(37, 29, seed=1))["default"]
    assert out.shape == (37, 29, 3) and np.isfinite(out).all()


def test_the_largest_network_that_fits_the_patches_is_accepted():
    from kpcn_keras.models import ModelConfig, receptive_radius
    from kpcn_keras.train import check_fits_patches

    # 7 convolutions of 3x3 see 15x15 pixels: both fit a 15-pixel patch, one convolution or kernel side more does not
    fits = ModelConfig(width=4, depth=7, kernel_size=15)
    assert 2 * receptive_radius(fits) + 1 == 15
    check_fits_patches(fits, 15, "s")
    for bigger in (ModelConfig(width=4, depth=8, kernel_size=15), ModelConfig(width=4, depth=7, kernel_size=17)):
        with pytest.raises(OptionError):
            check_fits_patches(bigger, 15, "s")
    check_fits_patches(ModelConfig(arch="dpcn", width=4, depth=7, kernel_size=41), 15, "s")  # dpcn has no kernel


@pytest.mark.slow
def test_a_kernel_beyond_its_bound_is_refused_before_any_memory_is_taken(tmp_path):
    from helpers.commands import assert_one_line_error, run_main

    res = run_main("train", "--kernel-size", "1001", "--run", "runs/r", cwd=tmp_path)
    assert_one_line_error(res, "--kernel-size must be an odd integer in [3, 41], got 1001")
    assert not any(tmp_path.iterdir())


@pytest.mark.slow
@pytest.mark.parametrize("where", ["the render set", "inside the shard set"])
def test_a_run_folder_in_a_render_or_shard_set_is_refused_before_it_is_written(tmp_path, where):
    # the render set's config.json and timings.json have the names of a run's records
    shard_cfg = build_tiny_shards(tmp_path)
    run_dir = {"the render set": tmp_path / "renders" / "s",
               "inside the shard set": tmp_path / "shards" / "s" / "r"}[where]
    before = checksums(tmp_path)
    with pytest.raises(KpcnError, match=rf"run folder \(--run\) {run_dir}: is .*the (render|shard) set folder"):
        train(tiny_config(shard_cfg), run_dir, verbose=0)
    assert checksums(tmp_path) == before
