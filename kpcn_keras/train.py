"""Training the diffuse and specular branch networks from a shard set (seed report §2.3).

The run folder's layout belongs to :class:`kpcn_keras.run.Run`. What training guarantees:

- **Inputs first, record second.** The shard set must be complete and every shard's SHA-256 must match
  its manifest, the options must fit the data, and the run folder must be writable, before
  ``config.json`` is written; a command refused for bad input leaves no run behind.
- **Exact resume.** After every epoch the model, its optimizer and the training state (epochs done, the
  model configuration, the loss history) are written as one ``.keras`` file (``run.save_model``), so
  the model and its epoch count cannot disagree. Running the same command again continues from it and
  ends with the same bytes as an uninterrupted run (the CSV log is cut back to the checkpoint's epochs).
- **Same run, same inputs.** Another configuration, another shard set content, or a checkpoint of
  another architecture under an existing run is an error that says which.
- **One trainer per run**: the run's lock is held while training.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import keras
import numpy as np

from kpcn_keras.data import ShardPatches
from kpcn_keras.losses import SMAPE, AsymmetricSMAPE
from kpcn_keras.models import ModelConfig, build_branch_model
from kpcn_keras.run import Run, check_architecture, load_model, read_state, save_model
from prep.errors import KpcnError, OptionError
from prep.files import atomic_path, atomic_write_json, check_writable, read_json
from prep.shards import ShardSet

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


# Fields that say where the data is, not what is trained: a run is the same run wherever it is read from.
_LOCATION_FIELDS = ("set_name", "shards_root")


@dataclass
class TrainConfig:
    """Configuration of ``kpcn train``; every field is saved in the run's config.json.

    The defaults are the "cpu" preset: a 7-layer, 32-wide vanilla KPCN with 13x13 kernels (the
    ModelConfig defaults), 1200 steps of batch 8 per branch. The run folder is not part of it
    (:class:`kpcn_keras.run.Run` owns that), so a renamed run folder resumes.
    """

    set_name: str = "default"
    shards_root: str = "shards"
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
        if not self.branches or any(b not in BRANCHES for b in self.branches):
            raise OptionError("branches", f"must be a non-empty subset of {','.join(BRANCHES)}, got {list(self.branches)}")
        if self.loss not in ("smape", "asymmetric"):
            raise OptionError("loss", f"must be 'smape' or 'asymmetric', got {self.loss!r}")
        for name in ("steps", "steps_per_epoch", "batch_size", "decay_steps", "val_batches"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise OptionError(name, f"must be an integer >= 1, got {value!r}")
        checks = {
            "learning_rate": (0 < self.learning_rate < math.inf, "> 0 and finite"),
            "clipnorm": (0 < self.clipnorm < math.inf, "> 0 and finite"),
            "decay_rate": (0 < self.decay_rate <= 1, "in (0, 1]"),
            "slope": (1 <= self.slope < math.inf, ">= 1 and finite"),
            "seed": (self.seed >= 0, ">= 0"),
        }
        for name, (ok, bound) in checks.items():
            if not ok:
                raise OptionError(name, f"must be {bound}, got {getattr(self, name)!r}")
        self.model = ModelConfig(**self.model).to_dict()  # validates and fills defaults

    @classmethod
    def from_preset(cls, preset: str | None = None, **overrides) -> "TrainConfig":
        """The preset's values (None: the default preset), then ``overrides`` (None values ignored;
        ``model`` keys merged)."""
        preset = cls.preset if preset is None else preset
        if preset not in PRESETS:
            raise OptionError("preset", f"must be one of {sorted(PRESETS)}, got {preset!r}")
        values = json.loads(json.dumps(PRESETS[preset]))
        values["model"] = {**values.get("model", {}), **(overrides.pop("model", None) or {})}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(preset=preset, **values)

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

    def identity(self) -> dict:
        """The fields that make two runs the same run (everything but where the data is read from)."""
        return {k: v for k, v in self.to_dict().items() if k not in _LOCATION_FIELDS}


class _Checkpoint(keras.callbacks.Callback):
    """After every epoch: the model, its optimizer and the training state, as one atomic .keras file."""

    def __init__(self, path: Path, cfg: TrainConfig, history: list[dict]):
        super().__init__()
        self.path, self.cfg, self.history = path, cfg, history

    def on_epoch_end(self, epoch, logs=None):
        logs = {k: float(v) for k, v in (logs or {}).items()}
        if not np.isfinite(logs.get("loss", 0.0)):
            return  # keep the last good checkpoint; train_branch reports the divergence
        self.history.append({"epoch": epoch, **logs})
        save_model(self.model, self.path, _state(self.cfg, epoch + 1, self.history))


def _state(cfg: TrainConfig, epochs_done: int, history: list[dict]) -> dict:
    return {"epochs_done": epochs_done, "model": cfg.model, "train": _identity_key(cfg), "history": history}


def _identity_key(cfg: TrainConfig) -> str:
    return hashlib.sha256(json.dumps(cfg.identity(), sort_keys=True).encode()).hexdigest()[:16]


def _compile(model: keras.Model, cfg: TrainConfig) -> None:
    schedule = keras.optimizers.schedules.ExponentialDecay(cfg.learning_rate, cfg.decay_steps, cfg.decay_rate)
    loss = AsymmetricSMAPE(cfg.slope) if cfg.loss == "asymmetric" else SMAPE()
    # a fixed name: Keras numbers unnamed optimizers per process (adam, adam_1, ...), and the name is
    # saved with the model and its variables, so two identical runs would otherwise differ in bytes
    model.compile(optimizer=keras.optimizers.Adam(schedule, clipnorm=cfg.clipnorm, name="adam"), loss=loss)


def _check_inputs(cfg: TrainConfig, sset: ShardSet) -> tuple[dict, dict]:
    """Everything a run needs from its shard set, checked before the run folder is touched; returns the
    manifest and ``split -> shard paths``."""
    manifest = sset.complete_manifest()
    if manifest.get("features") is not None and len(manifest["features"]) != cfg.model["in_channels"]:
        raise OptionError("in_channels", f"is {cfg.model['in_channels']} but the shards in {sset.dir} have "
                          f"{len(manifest['features'])} feature channels")
    paths = {split: [e.path for e in sset.verified_shards(split, manifest)] for split in ("train", "val")}
    patches = sum(s["patches"] for r in manifest["rounds"].values() for s in r["shards"] if s["split"] == "train")
    if patches < cfg.batch_size:
        raise OptionError("batch_size", f"{cfg.batch_size} exceeds the {patches} training patches of {sset.dir}")
    return manifest, paths


def _open_record(run: Run, cfg: TrainConfig, manifest: dict, sset: ShardSet) -> dict:
    """The run's record: read and compared if the run exists, else created (inputs are checked by now)."""
    if run.has_record():
        record = run.read_record()
        old = {k: v for k, v in record["train"].items() if k not in _LOCATION_FIELDS}
        diff = sorted(k for k in set(old) | set(cfg.identity()) if old.get(k) != cfg.identity().get(k))
        if diff:
            raise KpcnError(
                f"{run.record_path}: this run was made with another configuration (differs in {', '.join(diff)}); "
                f"choose another --run or remove {run.dir}"
            )
        if record["shards"].get("content_key") != manifest["content_key"]:
            raise KpcnError(
                f"{run.record_path}: the shard set {sset.dir} changed since this run started (its renders or "
                f"options differ); choose another --run or remove {run.dir}"
            )
        return record
    import torch

    record = {
        "train": cfg.to_dict(),
        "shards": {
            "set_dir": run.relative(sset.dir),
            "config_hash": manifest["config_hash"],
            "content_key": manifest["content_key"],
            "split": manifest["split"],
            "features": manifest["features"],
            "constants": manifest["constants"],
        },
        "versions": {"keras": keras.__version__, "torch": torch.__version__, "numpy": np.__version__},
        "command": " ".join(["kpcn"] + sys.argv[1:]),
        "results": {},
    }
    run.write_record(record)
    return record


def _resume_log(path: Path, epochs_done: int) -> None:
    """Cut the CSV log back to its header and the ``epochs_done`` rows the checkpoint has seen (a kill
    after the log row but before the checkpoint would otherwise leave that epoch twice)."""
    if not path.is_file():
        return
    lines = path.read_bytes().splitlines(keepends=True)[: 1 + epochs_done]  # bytes: keeps CSVLogger's \r\n
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(lines))


def train_branch(cfg: TrainConfig, run: Run, branch: str, paths: dict, *, verbose="auto") -> keras.Model:
    """Train (or resume, or reuse) one branch network of ``run``; returns the finished model."""
    model_cfg = ModelConfig.from_dict(cfg.model)
    final = run.model_path(branch)
    if final.is_file():
        model = load_model(final)
        check_architecture(model, model_cfg, final)
        return model
    ckpt = run.checkpoint_path(branch)
    initial_epoch, history = 0, []
    if ckpt.is_file():
        state = read_state(ckpt)
        if state is None or "epochs_done" not in state:
            raise KpcnError(f"{ckpt}: a .keras file without kpcn's training state; remove it to restart the {branch} branch")
        if state.get("model") != cfg.model or state.get("train") != _identity_key(cfg):
            raise KpcnError(
                f"{ckpt}: checkpoint of another configuration (model {state.get('model')}); the run asks for "
                f"{cfg.model}. Remove the checkpoint to restart the {branch} branch, or choose another --run"
            )
        model = load_model(ckpt)
        check_architecture(model, model_cfg, ckpt)
        initial_epoch, history = int(state["epochs_done"]), list(state.get("history", []))
        _resume_log(run.log_path(branch), initial_epoch)
        print(f"[{branch}] resuming from {ckpt} after epoch {initial_epoch}")
    else:
        run.log_path(branch).unlink(missing_ok=True)  # a log without a checkpoint holds no epoch we keep
        keras.utils.set_random_seed(cfg.seed + BRANCHES.index(branch))
        model = build_branch_model(model_cfg, name=branch)
        _compile(model, cfg)

    target = "reference+noisy" if cfg.loss == "asymmetric" else "reference"
    spe = cfg.epoch_steps
    train = ShardPatches(
        paths["train"], branch, cfg.batch_size, steps=(cfg.epochs - initial_epoch) * spe,
        seed=cfg.seed, offset=initial_epoch * spe, target=target,
    )
    val = None
    if paths["val"]:
        val = ShardPatches(paths["val"], branch, cfg.batch_size, shuffle=False, target=target)
        val.steps = min(val.steps, cfg.val_batches)
    callbacks = [
        keras.callbacks.CSVLogger(str(run.log_path(branch)), append=True),
        _Checkpoint(ckpt, cfg, history),
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
    save_model(model, final)
    return model


def train(cfg: TrainConfig, run_dir: str | Path, *, verbose="auto") -> Path:
    """Train every configured branch into the run folder ``run_dir``; returns it."""
    keras_backend = keras.backend.backend()
    if keras_backend != "torch":
        raise KpcnError(f"kpcn trains on the torch backend; KERAS_BACKEND selects {keras_backend!r}")
    run = Run(run_dir)
    sset = ShardSet(cfg.set_dir)
    manifest, paths = _check_inputs(cfg, sset)
    check_writable(run.dir, "run folder (--run)", directory=True)
    with run.lock():
        run.remove_temporaries()
        record = _open_record(run, cfg, manifest, sset)
        timings = read_json(run.timings_path, "run timings") if run.timings_path.is_file() else {}
        for branch in cfg.branches:
            if branch in record["results"] and run.model_path(branch).is_file():
                continue
            start = time.perf_counter()
            train_branch(cfg, run, branch, paths, verbose=verbose)
            log = _read_log(run.log_path(branch))
            record["results"][branch] = {"last_epoch": log[-1] if log else {}}
            timings[branch] = round(time.perf_counter() - start, 1)  # the session that finished it
            atomic_write_json(run.timings_path, timings)
            run.write_record(record)
    return run.dir


def _read_log(path: Path) -> list[dict]:
    import csv

    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))
