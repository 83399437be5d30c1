"""The callbacks of a phase's ``fit`` (:func:`kpcn_keras.train.train_phase`) and the training state its
checkpoints hold: what :mod:`kpcn_keras.train`'s guarantees rest on at every batch and epoch.

- :class:`MeanOverProcesses`: an epoch's training logs as their mean over the processes;
- :class:`StopOnNonFinite`: divergence stops at the batch, naming the last good checkpoint;
- :class:`Checkpoint`: after every epoch the model, its optimizer and the training state in one file (and the
  best epoch's model, with early stopping); :func:`checkpoint_differences` says what a checkpoint's state says
  that the run does not;
- :class:`StopOnSaturation`: a network that no longer learns (:func:`frozen`) stops with one line;
- :class:`StopOnPlateau`: early stopping (``patience``: :func:`plateaued`, :func:`best_epoch`).
"""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import keras

from kpcn_keras import distributed
from kpcn_keras.config import ALBEDO_NETWORK, Phase, TrainConfig
from kpcn_keras.run import save_model
from prep.errors import KpcnError


class MeanOverProcesses(keras.callbacks.Callback):
    """First of all the callbacks: an epoch's training logs become their mean over the processes, what one
    process on the global batches would have logged (validation, read whole by each, is the same in all)."""

    def __init__(self, world: distributed.World):
        super().__init__()
        self.world = world

    def on_epoch_end(self, epoch, logs=None):
        if logs is None:
            return
        train = {k: float(v) for k, v in logs.items() if not k.startswith("val_")}
        logs.update(distributed.mean_over_processes(train, self.world))


class StopOnNonFinite(keras.callbacks.Callback):
    """Divergence stops at the batch: a training loss that is not finite raises, at once, the one-line
    error naming the last good checkpoint, before any writer sees the epoch. Ours, not Keras's
    ``TerminateOnNaN(raise_error=True)``: that argument came long after the oldest Keras pyproject.toml
    allows."""

    def __init__(self, phase: Phase, checkpoint: Path):
        super().__init__()
        self.phase, self.checkpoint = phase, checkpoint

    def on_train_batch_end(self, batch, logs=None):
        loss = (logs or {}).get("loss")
        if loss is not None and not math.isfinite(float(loss)):
            raise KpcnError(
                f"training the {self.phase.name} phase diverged (loss {float(loss)} at batch {batch}); the last good "
                f"checkpoint is {self.checkpoint}. Lower the learning rate (--lr) under a new --run, or resume this "
                "one as it is."
            )


# A validation loss that stays within FROZEN_TOLERANCE (relative) for FROZEN_EPOCHS epochs while the training
# loss moves by more than FROZEN_TRAINING_MOVE has stopped learning: the training loss moves with its batches
# alone. Seen in the quality study (docs/results/10-quality-levers.md §10d): the unet preset at lr 0.001 saturated a
# specular network's kernels in its first epoch, and its validation loss then moved by float rounding alone.
FROZEN_EPOCHS = 3
FROZEN_TOLERANCE = 1e-6
FROZEN_TRAINING_MOVE = 1e-3
# A phase that starts from finished networks (train.starts_trained) can start on a plateau: its validation loss as flat
# as a saturated network's for a score of epochs, then falling (make train's albedo phase, seed 1,
# docs/results/21-quality-report-shipped-model.md). Such a phase is judged only once its validation loss has left its
# first epoch's by more than FROZEN_TRAINING_MOVE (relative): until then it has shown no training to have saturated it.
# A phase from random weights is judged from its first epochs (the unet case).


def frozen(history: list[dict], *, started_trained: bool = False) -> bool:
    """Whether the last :data:`FROZEN_EPOCHS` epochs of ``history`` (dicts with ``loss`` and ``val_loss``) have
    one validation loss, to :data:`FROZEN_TOLERANCE`, while their training loss moved (the comment above); for a
    phase ``started_trained``, only once its validation loss has left its first epoch's
    (:func:`kpcn_keras.train.starts_trained`)."""
    last = history[-FROZEN_EPOCHS:]
    if len(last) < FROZEN_EPOCHS:
        return False
    val = [h.get("val_loss", math.nan) for h in last]
    train = [h.get("loss", math.nan) for h in last]
    if not all(math.isfinite(v) for v in val + train):
        return False
    if started_trained:
        first = history[0].get("val_loss", math.nan)
        if all(abs(h.get("val_loss", math.nan) - first) <= FROZEN_TRAINING_MOVE * abs(first) for h in history):
            return False  # still on the plateau it started on
    return (max(val) - min(val) <= FROZEN_TOLERANCE * max(map(abs, val))
            and max(train) - min(train) > FROZEN_TRAINING_MOVE * max(map(abs, train)))


# the option that sets a phase's learning rate, for the line that asks for a lower one (the branch phases': --lr)
LEARNING_RATE_OPTIONS = {"joint": "--joint-lr", "compositor": "--compositor-lr", ALBEDO_NETWORK: "--albedo-lr"}


class StopOnSaturation(keras.callbacks.Callback):
    """A phase whose network no longer learns (:func:`frozen`) stops with one line saying why and what to do;
    its checkpoints stay. Judged on the checkpoint's history too, so a resumed phase stops as it did."""

    def __init__(self, phase: Phase, history: list[dict], *, started_trained: bool):
        super().__init__()
        self.phase, self.started_trained = phase, started_trained
        self.history = [{k: h.get(k, math.nan) for k in ("loss", "val_loss")} for h in history]

    def on_epoch_end(self, epoch, logs=None):
        logs = logs or {}
        self.history.append({k: float(logs.get(k, math.nan)) for k in ("loss", "val_loss")})
        if frozen(self.history, started_trained=self.started_trained):
            first, last = self.history[-FROZEN_EPOCHS], self.history[-1]
            raise KpcnError(
                f"training the {self.phase.name} phase stalled: its validation loss stayed {last['val_loss']:.6g} "
                f"for {FROZEN_EPOCHS} epochs while its training loss went {first['loss']:.4g} -> {last['loss']:.4g}, "
                "the mark of a network that no longer learns (of a kernel-predicting one, saturated kernels: each "
                "pixel's softmax on one neighbour, no gradient through it). "
                "Train under a new --run with a lower learning rate "
                f"({LEARNING_RATE_OPTIONS.get(self.phase.component, '--lr')}; this run's is "
                f"{self.phase.learning_rate:g})."
            )


class Checkpoint(keras.callbacks.Callback):
    """After every epoch: the model, its optimizer and the training state, as one atomic .keras file; with
    ``best`` (early stopping), before it, the model alone whenever the epoch is the phase's best so far (a kill
    between the two repeats the epoch, which writes the same best again)."""

    def __init__(self, path: Path, cfg: TrainConfig, phase: Phase, history: list[dict], best: Path | None = None):
        super().__init__()
        self.path, self.cfg, self.phase, self.history, self.best = path, cfg, phase, history, best

    def on_epoch_end(self, epoch, logs=None):
        self.history.append({"epoch": epoch, **{k: float(v) for k, v in (logs or {}).items()}})
        if self.best is not None and best_epoch(self.history) == len(self.history) - 1:
            save_model(self.model, self.best)
        done = epoch + 1 - self.phase.first_epoch
        save_model(self.model, self.path, checkpoint_state(self.cfg, self.phase, done, self.history))


def best_epoch(history: list[dict]) -> int | None:
    """Index (within the phase) of the first epoch with the lowest validation loss; None without one."""
    losses = [(h["val_loss"], i) for i, h in enumerate(history) if math.isfinite(h.get("val_loss", math.nan))]
    return min(losses)[1] if losses else None


def plateaued(history: list[dict], patience: int) -> bool:
    """Whether the last ``patience`` epochs of ``history`` all came after its best (0: never)."""
    best = best_epoch(history)
    return patience > 0 and best is not None and len(history) - 1 - best >= patience


class StopOnPlateau(keras.callbacks.Callback):
    """Early stopping on the phase's validation losses, from the checkpoint's history on (so a resumed phase
    stops where an uninterrupted one would). Every process keeps its own copy and stops at the same epoch:
    validation, read whole by each, gives them the same loss."""

    def __init__(self, history: list[dict], patience: int):
        super().__init__()
        self.history, self.patience = [{"val_loss": h.get("val_loss", math.nan)} for h in history], patience

    @property
    def stopped(self) -> bool:
        return plateaued(self.history, self.patience)

    def on_epoch_end(self, epoch, logs=None):
        self.history.append({"val_loss": float((logs or {}).get("val_loss", math.nan))})
        self.model.stop_training = self.stopped


def checkpoint_state(cfg: TrainConfig, phase: Phase, epochs_done: int, history: list[dict]) -> dict:
    return {"phase": phase.name, "epochs_done": epochs_done, "model": cfg.model.to_dict(), "train": _identity_key(cfg),
            "history": history}


def checkpoint_differences(state: dict, cfg: TrainConfig, phase: Phase) -> list[str]:
    """What a checkpoint's training state says that ``phase`` of the run ``cfg`` does not, one item per
    difference, each with both values: the phase, each model setting, and else the training options (a
    checkpoint stores their hash, which covers the model)."""
    differ = []
    if state.get("phase", phase.name) != phase.name:
        differ.append(f"it is the {state['phase']} phase's, this is the {phase.name} phase's")
    model = state.get("model") if isinstance(state.get("model"), dict) else {}
    own = cfg.model.to_dict()
    differ += [f"model {k} {model.get(k)!r}, the run's {own.get(k)!r}"
               for k in sorted(set(model) | set(own)) if model.get(k) != own.get(k)]
    if not differ and state.get("train") != _identity_key(cfg):  # the hash covers the model too
        differ.append(f"training options of hash {state.get('train')}, the run's {_identity_key(cfg)} (a "
                      "checkpoint of another run)")
    return differ


def _identity_key(cfg: TrainConfig) -> str:
    return hashlib.sha256(json.dumps(cfg.identity(), sort_keys=True).encode()).hexdigest()[:16]

