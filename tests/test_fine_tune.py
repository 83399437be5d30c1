"""Fine-tuning: ``kpcn train --init RUN`` starts the branch phases from another run's finished networks."""

import json

import keras
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.tiny import TINY_TRAIN_MODEL, build_tiny_shards, tiny_train_config

from kpcn_keras.run import Run
from kpcn_keras.train import TrainConfig, train
from prep import shards
from prep.errors import KpcnError, OptionError
from prep.files import sha256_file


class FirstWeights(keras.callbacks.Callback):
    """Each network's weights when its phase's first fit begins, by the network's name."""

    def __init__(self):
        super().__init__()
        self.seen = {}

    def on_train_begin(self, logs=None):
        self.seen.setdefault(self.model.name, [np.array(w) for w in self.model.get_weights()])


def component_weights(run_dir, name):
    run = Run(run_dir)
    return [np.asarray(w) for w in run.load_component(run.record(), name).get_weights()]


@pytest.mark.slow
def test_each_branch_phase_starts_from_the_named_runs_network_and_the_record_keeps_its_checksum(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    source = train(tiny_train_config(shard_cfg), tmp_path / "source", verbose=0)
    started, scratch = FirstWeights(), FirstWeights()
    tuned = train(tiny_train_config(shard_cfg, init=str(source), learning_rate=1e-4), tmp_path / "tuned", verbose=0,
                  callbacks=[started])
    train(tiny_train_config(shard_cfg, learning_rate=1e-4), tmp_path / "scratch", verbose=0, callbacks=[scratch])
    for branch in ("diffuse", "specular"):
        want = component_weights(source, branch)
        assert all(np.array_equal(a, b) for a, b in zip(started.seen[branch], want, strict=True)), branch
        # a seeded initialisation is another start: the comparison above can fail
        assert not all(np.array_equal(a, b) for a, b in zip(scratch.seen[branch], want, strict=True)), branch
        # and it trains from there
        assert not all(np.array_equal(a, b) for a, b in zip(component_weights(tuned, branch), want, strict=True))
    record = json.loads((tuned / "config.json").read_text())
    assert record["init"] == {"run": "../source", "networks": {b: sha256_file(source / f"{b}.keras")
                                                              for b in ("diffuse", "specular")}}
    assert "init" not in json.loads((tmp_path / "scratch" / "config.json").read_text())
    assert "init" not in TrainConfig().to_dict()  # the runs from before --init keep their identity


@pytest.mark.slow
def test_networks_that_do_not_fit_the_run_are_refused_in_one_line_before_the_run_is_written(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    source = train(tiny_train_config(shard_cfg, branches=("diffuse",)), tmp_path / "source", verbose=0)
    shards.build_shards(shards.ShardConfig(**{**shard_cfg.to_dict(), "inputs": "no-variance"}), progress=False)
    cases = [
        (dict(model={**TINY_TRAIN_MODEL, "width": 6}), OptionError, r"init.*another configuration.*width 4 against 6"),
        (dict(), OptionError, r"init.*has no specular network \(it has diffuse\)"),
        (dict(inputs="no-variance"), OptionError, r"init.*no network for frames of the input set no-variance"),
        (dict(init=str(tmp_path / "nowhere")), OptionError, r"init.*nowhere is not a run or model folder"),
    ]
    for i, (kw, error, message) in enumerate(cases):
        with pytest.raises(error, match=message):
            train(tiny_train_config(shard_cfg, **{"init": str(source), **kw}), tmp_path / f"r{i}", verbose=0)
        assert not (tmp_path / f"r{i}").exists()
    res = run_main("train", "--set", "s", "--shards", shard_cfg.out_root, "--run", tmp_path / "cli", "--width", "6",
                   "--depth", "2", "--kernel-size", "3", "--init", source, cwd=tmp_path)
    assert_one_line_error(res, "--init", str(source), "width 4 against 6")
    assert not (tmp_path / "cli").exists()


@pytest.mark.slow
def test_a_fine_tuned_run_resumes_only_from_the_networks_it_started_from(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    one = train(tiny_train_config(shard_cfg, branches=("diffuse",)), tmp_path / "one", verbose=0)
    other = train(tiny_train_config(shard_cfg, branches=("diffuse",), seed=1), tmp_path / "other", verbose=0)
    tuned = train(tiny_train_config(shard_cfg, branches=("diffuse",), init=str(one)), tmp_path / "tuned", verbose=0)
    before = sha256_file(tuned / "diffuse.keras")
    train(tiny_train_config(shard_cfg, branches=("diffuse",), init=str(one)), tuned, verbose=0)  # the same: done
    assert sha256_file(tuned / "diffuse.keras") == before
    with pytest.raises(KpcnError, match=r"started from the networks of \.\./one.*gives it other networks"):
        train(tiny_train_config(shard_cfg, branches=("diffuse",), init=str(other)), tuned, verbose=0)
    with pytest.raises(KpcnError, match=r"started from the networks of .*gives it none \(no --init\)"):
        train(tiny_train_config(shard_cfg, branches=("diffuse",)), tuned, verbose=0)
    with pytest.raises(KpcnError, match=r"started from a seeded initialisation.*gives it networks \(--init\)"):
        train(tiny_train_config(shard_cfg, branches=("diffuse",), init=str(other)), one, verbose=0)
