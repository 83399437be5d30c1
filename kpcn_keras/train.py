"""Training the diffuse and specular branch networks from a shard set (seed report §2.3).

A run folder ``<runs_root>/<run>/`` records how it was made and resumes by itself:

- ``config.json``: this TrainConfig, the model config, the shard set's manifest hash and split,
  library versions, the command line, and per-branch results once finished;
- ``<branch>.keras``: the finished model of each branch;
- ``checkpoints/<branch>.keras`` + ``checkpoints/<branch>.json``: the model with its optimizer state
  and the number of epochs done, written atomically after every epoch;
- ``log-<branch>.csv``: loss and validation loss per epoch.

Running the same command again continues an interrupted run where its last checkpoint left off; a
different configuration under an existing run name is an error.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import keras
import numpy as np

from kpcn_keras.data import ShardPatches
from kpcn_keras.losses import SMAPE, AsymmetricSMAPE
from kpcn_keras.models import ModelConfig, build_branch_model, load_model
from prep.errors import KpcnError
from prep.files import atomic_write_text
from prep.shards import load_manifest, shard_paths

BRANCHES = ("diffuse", "specular")

# "cpu" (the TrainConfig defaults) trains a useful model on a 2-core CPU in minutes; "paper" is the
# report's setting for a GPU (28-layer residual KPAL trunk, 21x21 kernels, batch 12, lr 1e-4, keep 0.7).
PRESETS = {
    "cpu": {},
    "paper": {
        "model": {"arch": "kpal", "width": 100, "depth": 13, "kernel_size": 21, "dropout": 0.3},
        "batch_size": 12,
        "steps": 60000,
        "steps_per_epoch": 1000,
        "learning_rate": 1e-4,
        "decay_steps": 60000,
        "decay_rate": 0.1,
    },
}


@dataclass
class TrainConfig:
    """Configuration of ``kpcn train``; every field is saved in the run's config.json.

    The defaults are the "cpu" preset: a 7-layer, 32-wide vanilla KPCN with 13x13 kernels (the
    ModelConfig defaults), 1200 steps of batch 8 per branch.
    """

    set_name: str = "default"
    shards_root: str = "shards"
    run: str = "default"
    runs_root: str = "runs"
    preset: str = "cpu"
    model: dict = field(default_factory=dict)
    branches: tuple[str, ...] = BRANCHES
    steps: int = 1200
    steps_per_epoch: int = 50
    batch_size: int = 8
    learning_rate: float = 1e-3
    decay_steps: int = 1200
    decay_rate: float = 0.3
    clipnorm: float = 1.0
    loss: str = "smape"
    slope: float = 2.0
    val_batches: int = 8
    seed: int = 0

    def __post_init__(self):
        self.branches = tuple(self.branches)
        bad = [b for b in self.branches if b not in BRANCHES] or (not self.branches and ["(none)"])
        if bad:
            raise ValueError(f"branches must be a non-empty subset of {BRANCHES}, got {list(self.branches)}")
        if self.loss not in ("smape", "asymmetric"):
            raise ValueError(f"loss must be 'smape' or 'asymmetric', got {self.loss!r}")
        for name in ("steps", "steps_per_epoch", "batch_size", "decay_steps", "val_batches"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)!r}")
        if not self.learning_rate > 0 or not self.clipnorm > 0 or not 0 < self.decay_rate <= 1:
            raise ValueError(
                f"need learning_rate > 0, clipnorm > 0, 0 < decay_rate <= 1; got "
                f"{self.learning_rate}, {self.clipnorm}, {self.decay_rate}"
            )
        self.model = ModelConfig(**self.model).to_dict()  # validates and fills defaults

    @classmethod
    def from_preset(cls, preset: str, **overrides) -> "TrainConfig":
        """The preset's values, then ``overrides`` (None values ignored; ``model`` keys merged)."""
        if preset not in PRESETS:
            raise ValueError(f"preset must be one of {sorted(PRESETS)}, got {preset!r}")
        values = json.loads(json.dumps(PRESETS[preset]))
        values["model"] = {**values.get("model", {}), **(overrides.pop("model", None) or {})}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(preset=preset, **values)

    @property
    def run_dir(self) -> Path:
        return Path(self.runs_root) / self.run

    @property
    def set_dir(self) -> Path:
        return Path(self.shards_root) / self.set_name

    @property
    def epoch_steps(self) -> int:
        """Steps per epoch (one checkpoint each): steps_per_epoch, or all steps if fewer."""
        return min(self.steps_per_epoch, self.steps)

    @property
    def epochs(self) -> int:
        return math.ceil(self.steps / self.epoch_steps)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["branches"] = list(self.branches)
        return d


def _atomic_save(model: keras.Model, path: Path) -> None:
    tmp = path.with_name(f".tmp-{path.name}")  # keras wants the .keras suffix
    model.save(tmp)
    os.replace(tmp, path)


class _Checkpoint(keras.callbacks.Callback):
    """Saves the model (with optimizer state) and the epochs done after every epoch, atomically."""

    def __init__(self, path: Path):
        super().__init__()
        self.path = path

    def on_epoch_end(self, epoch, logs=None):
        if not np.isfinite((logs or {}).get("loss", 0.0)):
            return  # keep the last good checkpoint; train_branch reports the divergence
        _atomic_save(self.model, self.path)
        atomic_write_text(self.path.with_suffix(".json"), json.dumps({"epochs_done": epoch + 1, "logs": logs or {}}))


def _compile(model: keras.Model, cfg: TrainConfig) -> None:
    schedule = keras.optimizers.schedules.ExponentialDecay(cfg.learning_rate, cfg.decay_steps, cfg.decay_rate)
    loss = AsymmetricSMAPE(cfg.slope) if cfg.loss == "asymmetric" else SMAPE()
    model.compile(optimizer=keras.optimizers.Adam(schedule, clipnorm=cfg.clipnorm), loss=loss)


def _prepare_run(cfg: TrainConfig, manifest: dict) -> dict:
    """Create or reopen the run folder; returns the record written to config.json."""
    run_dir = cfg.run_dir
    record_path = run_dir / "config.json"
    if record_path.is_file():
        record = json.loads(record_path.read_text())
        if record.get("train") != cfg.to_dict() or record.get("shards", {}).get("config_hash") != manifest["config_hash"]:
            old = record.get("train", {})
            diff = sorted(k for k in set(old) | set(cfg.to_dict()) if old.get(k) != cfg.to_dict().get(k))
            raise KpcnError(
                f"{record_path}: run {cfg.run!r} was made with another configuration "
                f"(differs in {diff or ['shard set']}); choose another --run or remove {run_dir}"
            )
        return record
    import torch

    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    record = {
        "train": cfg.to_dict(),
        "shards": {
            "set_dir": str(cfg.set_dir),
            "config_hash": manifest["config_hash"],
            "split": manifest["split"],
            "features": manifest["features"],
            "constants": manifest["constants"],
        },
        "versions": {"keras": keras.__version__, "torch": torch.__version__, "numpy": np.__version__},
        "command": " ".join(sys.argv),
        "results": {},
    }
    atomic_write_text(record_path, json.dumps(record, indent=2))
    return record


def train_branch(cfg: TrainConfig, branch: str, *, verbose="auto") -> keras.Model:
    """Train (or resume, or reuse) one branch network; returns the finished model."""
    run_dir = cfg.run_dir
    final = run_dir / f"{branch}.keras"
    if final.is_file():
        return load_model(final)
    ckpt = run_dir / "checkpoints" / f"{branch}.keras"
    state = ckpt.with_suffix(".json")
    initial_epoch = 0
    if ckpt.is_file() and state.is_file():
        model = load_model(ckpt)
        initial_epoch = int(json.loads(state.read_text())["epochs_done"])
        print(f"[{branch}] resuming from {ckpt} after epoch {initial_epoch}")
    else:
        keras.utils.set_random_seed(cfg.seed + BRANCHES.index(branch))
        model = build_branch_model(ModelConfig.from_dict(cfg.model), name=branch)
        _compile(model, cfg)

    target = "reference+noisy" if cfg.loss == "asymmetric" else "reference"
    spe = cfg.epoch_steps
    train = ShardPatches(
        shard_paths(cfg.set_dir, "train"), branch, cfg.batch_size, steps=(cfg.epochs - initial_epoch) * spe,
        seed=cfg.seed, offset=initial_epoch * spe, target=target,
    )
    val_paths = shard_paths(cfg.set_dir, "val")
    val = None
    if val_paths:
        val = ShardPatches(val_paths, branch, cfg.batch_size, shuffle=False, target=target)
        val.steps = min(val.steps, cfg.val_batches)
    callbacks = [
        keras.callbacks.CSVLogger(str(run_dir / f"log-{branch}.csv"), append=True),
        _Checkpoint(ckpt),
        keras.callbacks.TerminateOnNaN(),
    ]
    if initial_epoch < cfg.epochs:
        # shuffle=False: the stream is already a seeded permutation, and Keras walks it in order
        # across epochs only without its own shuffling (and with one worker), which makes resume exact
        model.fit(train, epochs=cfg.epochs, initial_epoch=initial_epoch, steps_per_epoch=spe,
                  validation_data=val, callbacks=callbacks, verbose=verbose, shuffle=False)
        if model.stop_training:  # only TerminateOnNaN stops a run early
            raise KpcnError(
                f"training the {branch} branch diverged (non-finite loss); the last good checkpoint is {ckpt}. "
                "Lower the learning rate (--lr) under a new --run, or resume this one as it is."
            )
    _atomic_save(model, final)
    return model


def train(cfg: TrainConfig, *, verbose="auto") -> Path:
    """Train every configured branch into ``cfg.run_dir``; returns the run folder."""
    keras_backend = keras.backend.backend()
    if keras_backend != "torch":
        raise KpcnError(f"kpcn trains on the torch backend; KERAS_BACKEND selects {keras_backend!r}")
    manifest = load_manifest(cfg.set_dir)
    record = _prepare_run(cfg, manifest)
    for branch in cfg.branches:
        if branch in record["results"]:
            continue
        start = time.perf_counter()
        train_branch(cfg, branch, verbose=verbose)
        log = _read_log(cfg.run_dir / f"log-{branch}.csv")
        record["results"][branch] = {"seconds": round(time.perf_counter() - start, 1), "last_epoch": log[-1] if log else {}}
        atomic_write_text(cfg.run_dir / "config.json", json.dumps(record, indent=2))
    return cfg.run_dir


def _read_log(path: Path) -> list[dict]:
    import csv

    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
