"""Training a denoiser from a shard set, in phases (docs/method.md §6, §7; docs/training.md).

A run trains, in this order (:meth:`TrainConfig.phases`), one command for all of them:

=================  ================================================  ==========================================
phase              trains                                            on
=================  ================================================  ==========================================
``diffuse``,       one branch network each (``--branches``)          the branch's reference, log domain
``specular``
``shared``         one network for both branches (``--shared``)      both branches' patches, each with its
                   with a one-hot branch input                       branch's reference
``joint``          both branch networks at once, fine-tuned at       the final colour (remodulated diffuse +
                   ``joint_learning_rate`` (``--joint-steps`` > 0)   specular), linear
``compositor``     the multiscale scale compositor, the branch       the final colour, through the three-level
                   networks frozen (``--compositor alpha|kernel``)   pyramid of both branches (and, with
                                                                     ``--scale-supervision``, each inner
                                                                     level's against the target taken down)
=================  ================================================  ==========================================

A run of another input set than the full one (``--inputs``, ``prep.inputs``) trains on the shard set cut for
it (``TrainConfig.set_dir``) into ``<run>/inputs/<inputs>/`` (``Run.for_inputs``); a no-split run trains the
diffuse phase alone (``TrainConfig.phases``).

Every phase has its own Adam optimizer (exponential learning-rate decay, gradient-norm clipping) and its own
checkpoint; the CSV log numbers epochs across phases, so it and ``loss.png`` show one continuous run, and the
record (``config.json``) lists every phase with its epochs and the components it produced. The run folder's
layout belongs to :class:`kpcn_keras.run.Run`. What training guarantees:

- **Inputs first, record second.** The shard set must be complete, every shard's checksum must match
  its manifest and the manifest's claims (patch size, counts, configuration) what the shards hold, every
  source render still present must have the SHA-256 the manifest lists (``ShardSet.check_renders``), the
  options must fit the data (the kernel and the receptive field within the shards' patches:
  :func:`check_fits_patches`), and the run folder must be writable, before ``config.json`` is written; a
  command refused for bad input leaves no run behind.
- **Exactly the steps asked.** A phase's epochs are ``steps_per_epoch`` steps (``Phase.epoch_steps``), the
  last one shorter where the phase's steps are not a multiple of it, so its optimizer, and with it the
  learning-rate schedule, takes exactly the steps the record gives.
- **Or as long as held-out error falls** (``patience`` > 0: :class:`~kpcn_keras.callbacks.StopOnPlateau`): a
  phase stops after ``patience`` epochs in a row without a validation loss below its best, and its model is the
  best epoch's (``checkpoints/<phase>-best.keras``, written at each new best); the record gives the epochs it
  trained and its best (``epochs_trained``, ``best_epoch``), and the next phase keeps its place in the epoch
  numbering.
- **Exact resume, at any point.** After every epoch the phase's model, its optimizer and the training state
  (phase, epochs done, the loss history) are written as one ``.keras`` file (``run.save_model``), so the
  model and its epoch count cannot disagree. A finished phase is one file, written once. Running the same
  command again continues from the first unfinished phase and ends with the same bytes as an uninterrupted
  run (the CSV log is cut back to the checkpoint's epochs; one holding fewer, emptied or cut, is refused).
- **Same run, same inputs.** Another configuration, another shard set content, or a checkpoint of
  another architecture under an existing run is an error that says which.
- **Fine-tuning starts from what it names** (``--init``, :func:`init_networks`): the branch phases start from
  another run's (or a shipped model's) finished networks of the same input set, which must have the run's
  model configuration and have been trained on its features; their SHA-256 are in the record (``init``), and
  resuming from other weights, or without them, is refused.
- **Divergence stops at the batch** (:class:`~kpcn_keras.callbacks.StopOnNonFinite`): one line names the last
  good checkpoint, which stays.
- **So does a network that can no longer learn** (:class:`~kpcn_keras.callbacks.StopOnSaturation`): a
  validation loss frozen for ``FROZEN_EPOCHS`` epochs while the training loss moves is a network whose kernels'
  softmax has saturated (each pixel takes one neighbour, and no gradient passes the softmax); one line says so
  and what to lower. A phase that starts from finished networks is judged once its validation loss has left its
  start: it may start on a plateau (:func:`starts_trained`).
- **The callbacks of a phase's fit** (:mod:`kpcn_keras.callbacks`) hold these at every batch and epoch, and
  write the checkpoint's training state.
- **One trainer per run**: the run's lock is held while training.
"""

from __future__ import annotations

import csv
import sys
import time
from contextlib import nullcontext
from pathlib import Path

import keras
import numpy as np

from kpcn_keras import distributed
from kpcn_keras.callbacks import (
    Checkpoint,
    MeanOverProcesses,
    StopOnNonFinite,
    StopOnPlateau,
    StopOnSaturation,
    best_epoch,
    checkpoint_differences,
)
from kpcn_keras.config import ALBEDO_NETWORK, UNWEIGHTED_TAU, Phase, TrainConfig
from kpcn_keras.data import ShardPatches
from kpcn_keras.layers import FinalColour
from kpcn_keras.losses import SMAPE, AsymmetricSMAPE
from kpcn_keras.models import (
    ModelConfig,
    build_albedo_training_model,
    build_branch_model,
    build_final_model,
    receptive_radius,
)
from kpcn_keras.multiscale import (
    InferenceOnly,
    ScaleSupervision,
    build_compositor,
    image_pyramid,
    multiscale_output,
)
from kpcn_keras.run import Run, check_architecture, load_model, read_state, save_model
from prep.auxiliary import RAW
from prep.errors import KpcnError, OptionError
from prep.features import BRANCHES
from prep.files import atomic_path, atomic_write_json, check_writable, pyplot, read_json, save_png, sha256_file
from prep.inputs import FULL
from prep.shards import ShardSet

# ---------------------------------------------------------------- what each phase trains


def _network_names(cfg: TrainConfig) -> dict[str, str]:
    """branch -> the component that denoises it."""
    return {b: "shared" if cfg.shared else b for b in BRANCHES}


def _build(cfg: TrainConfig, run: Run, record: dict, phase: Phase) -> keras.Model:
    """The compiled model ``phase`` starts from: the finished phase it continues, or a new model built from
    the components earlier phases finished."""
    if phase.continues:
        model = load_model(run.model_path(phase.continues))  # with its optimizer: training goes on
        run.check_model(run.parse_record(record), run.model_path(phase.continues).name, model, phase.component)
        return model
    model = _new_model(cfg, run, record, phase)
    _compile(model, cfg, phase)
    return model


def _new_model(cfg: TrainConfig, run: Run, record: dict, phase: Phase) -> keras.Model:
    model_cfg = cfg.model
    if not phase.trains_on_final_colour:
        keras.utils.set_random_seed(cfg.seed + [p.name for p in cfg.phases()].index(phase.name))
        model = build_branch_model(model_cfg, name=phase.name)
        if cfg.init is not None:
            source = _init_run(cfg)
            found = source.record()
            start = source.load_component(found, phase.component)  # checked against its record
            check_architecture(start, model_cfg, found.component_path(phase.component))
            model.set_weights(start.get_weights())
        return model
    names = _network_names(cfg)
    finished = run.parse_record(record)  # the phases done so far
    # the albedo network starts from the diffuse network alone: the trunk already tells noise from detail, and a
    # new network did not learn in as many steps what one started from it did (docs/results/20-albedo-network.md)
    wanted = ["diffuse"] if phase.name == ALBEDO_NETWORK else dict.fromkeys(names.values())
    nets = {name: run.load_component(finished, name) for name in wanted}
    for name, net in nets.items():
        check_architecture(net, model_cfg, finished.component_path(name))
    if phase.name == ALBEDO_NETWORK:
        albedo = build_branch_model(model_cfg, name=ALBEDO_NETWORK)
        albedo.set_weights(nets["diffuse"].get_weights())
        return build_albedo_training_model(albedo, model_cfg.input_channels)
    if phase.name == "joint":
        return build_final_model({b: nets[names[b]] for b in BRANCHES}, model_cfg.input_channels, name="joint")
    keras.utils.set_random_seed(cfg.seed + len(cfg.phases()))
    comp_cfg = cfg.compositor
    compositor = build_compositor(comp_cfg)
    # one graph for both branches: they share the compositor (and a shared network its frozen wrapper)
    frozen = {name: InferenceOnly(net, name=f"{name}_denoiser") for name, net in nets.items()}
    levels = {b: [] for b in BRANCHES}
    pyramids = {b: (lambda x, b=b: multiscale_output(x, frozen[names[b]], comp_cfg, compositor, prefix=f"{b}_",
                                                     levels=levels[b]))
                for b in BRANCHES}
    model = build_final_model(pyramids, model_cfg.input_channels, name="multiscale")
    if not cfg.supervises_scales(phase):
        return model
    # per-scale supervision (multiscale.py): each inner level's final colour, from its composite branch
    # colours and the albedo taken down the pyramid, against the target taken down the same way
    target = keras.Input(shape=(None, None, cfg.target_channels), name="target")
    albedos = image_pyramid(model.input["albedo"], comp_cfg, "albedo_pyramid")
    targets = image_pyramid(target, comp_cfg, "target_pyramid")
    pairs = []
    for level in range(1, comp_cfg.levels - 1):
        colour = FinalColour(name=f"final_colour{level}")(
            [levels[b][level - 1] for b in BRANCHES] + [albedos[level]])
        pairs += [targets[level], colour]
    out = ScaleSupervision(_loss(cfg, phase), comp_cfg.scale_supervision, name="scale_supervision")(
        [model.output, *pairs])
    return keras.Model({**model.input, "target": target}, out, name="multiscale")


def _check_registered(model: keras.Model) -> None:
    """RuntimeError unless every trainable weight is a torch parameter of ``model``: Keras's torch backend
    zeroes only those gradients between steps, and keys them by variable path, so two weights with one
    path would leave one accumulating its gradients for ever (``models.build_branch_model``)."""
    registered = {id(p) for p in model.parameters()}
    missing = [w.path for w in model.trainable_weights if id(w.value) not in registered]
    if missing:
        raise RuntimeError(f"model {model.name!r}: weights not registered with torch (repeated paths?): {missing[:4]}")


def _components(cfg: TrainConfig, phase: Phase) -> dict[str, dict]:
    """The record's entries of the components a finished ``phase`` holds (see ``run.Run``)."""
    file = f"{phase.name}.keras"
    if not phase.trains_on_final_colour:
        return {phase.component: {"file": file, "phase": phase.name}}
    if phase.component == "joint":
        networks = dict.fromkeys(_network_names(cfg).values())  # ordered: the record is compared byte for byte
        return {name: {"file": file, "layers": [name], "phase": phase.name} for name in networks}
    return {phase.component: {"file": file, "layers": [phase.component], "phase": phase.name}}


def _asymmetric(cfg: TrainConfig, phase: Phase) -> bool:
    """Whether ``phase`` trains with the asymmetric loss (and reads the noisy colour for it): the run's loss, but
    for the albedo network, whose target has no noisy side to lean to."""
    return cfg.loss == "asymmetric" and phase.component != ALBEDO_NETWORK


def _loss(cfg: TrainConfig, phase: Phase) -> keras.losses.Loss:
    """The training loss of ``phase`` (compiled, and per-scale supervision's at every inner level)."""
    # the final colour has no relSE in the shards: joint and compositor phases are unweighted (docs/training.md §2)
    tau = cfg.reference_tau if cfg.weights_reference(phase) else UNWEIGHTED_TAU
    if _asymmetric(cfg, phase):
        return AsymmetricSMAPE(None if cfg.slope_input else cfg.slope, reference_tau=tau)
    return SMAPE(reference_tau=tau)


def _compile(model: keras.Model, cfg: TrainConfig, phase: Phase) -> None:
    schedule = keras.optimizers.schedules.ExponentialDecay(phase.learning_rate, cfg.decay_steps, cfg.decay_rate)
    loss = _loss(cfg, phase)
    # a fixed name: Keras numbers unnamed optimizers per process (adam, adam_1, ...), and the name is
    # saved with the model and its variables, so two identical runs would otherwise differ in bytes
    model.compile(optimizer=keras.optimizers.Adam(schedule, clipnorm=cfg.clipnorm, name="adam"), loss=loss)


def _data(cfg: TrainConfig, phase: Phase, paths: dict, start: int, end: int, world: distributed.World):
    """The training and validation streams of ``phase``'s epochs ``start`` to ``end`` (excluded; the
    training stream starts ``start`` epochs in and serves exactly their steps).
    ``paths``: split -> shard paths, and optionally ``train_weights``, one per training shard. Over several
    processes the training stream is this process's slice of each batch (``cfg.batch_size`` is the global
    batch); validation is read whole by each."""
    network = phase.component
    source = network if network == ALBEDO_NETWORK else "final" if phase.trains_on_final_colour else \
        "both" if network == "shared" else network
    common = dict(source=source, batch_size=cfg.batch_size, model=cfg.model,
                  loss_target="reference+noisy" if _asymmetric(cfg, phase) else "reference",
                  slope=cfg.slope, slope_range=cfg.slope_range, reference_relse=cfg.weights_reference(phase),
                  target_input=cfg.supervises_scales(phase))
    train = ShardPatches(paths["train"], steps=sum(phase.epoch_length(i) for i in range(start, end)),
                         seed=cfg.seed, offset=start * phase.epoch_steps, augment=cfg.augment,
                         weights=paths.get("train_weights"), rank=world.rank, world=world.size,
                         firefly_rate=0.0 if phase.trains_on_final_colour else cfg.fireflies,
                         variance=cfg.input_set.variance,
                         **{**common, "batch_size": cfg.batch_size // world.size})
    val = None
    if paths["val"]:
        val = ShardPatches(paths["val"], shuffle=False, **common)
        val.steps = min(val.steps, cfg.val_batches)
    return train, val


def starts_trained(cfg: TrainConfig, phase: Phase) -> bool:
    """Whether ``phase`` starts from finished networks: joint fine-tuning (the branch networks), the albedo network
    (a copy of the diffuse one), a resample round (the phase it continues), and a branch phase of a run with
    ``--init`` (that run's network; a compositor under ``--init`` is still a new network, :func:`_new_model`)."""
    return (phase.component in ("joint", ALBEDO_NETWORK) or phase.continues is not None
            or (cfg.init is not None and not phase.trains_on_final_colour))


# ---------------------------------------------------------------- checkpoints, log, record


def check_fits_patches(model: ModelConfig, patch: int, where) -> None:
    """OptionError unless the network fits the ``patch`` x ``patch`` training patches of the shard set
    ``where``: the predicted kernel (a larger one reaches only the patch's replicated edges), and the
    receptive field (with a larger one no pixel of a patch sees the context it sees in a tiled inference,
    whose margins are real pixels: every pixel of the loss is computed from the trunk's zero padding)."""
    fits = f"the {patch}x{patch} patches of {where} (--patch-size {patch})"
    if model.arch != "dpcn" and model.kernel_size > patch:
        raise OptionError("kernel_size", f"{model.kernel_size} is larger than {fits}: use a kernel of at most "
                          f"{patch - 1 + patch % 2}, or cut the shards with a --patch-size of at least "
                          f"{model.kernel_size}")
    field = 2 * receptive_radius(model) + 1
    if field > patch:
        levels = f" and --levels {model.levels}" if model.arch == "unet" else ""
        raise OptionError("depth", f"{model.depth} with --conv-size {model.conv_size}{levels} gives a {model.arch} "
                          f"network a receptive field of {field}x{field} pixels, larger than {fits}: use a smaller "
                          f"--depth or --conv-size{' or --levels' if levels else ''}, or a --patch-size of at least "
                          f"{field}")


def check_inputs(cfg: TrainConfig, sset: ShardSet) -> tuple[dict, dict]:
    """Everything a run needs from its shard set, checked before the run folder is touched; returns the
    manifest and ``split -> shard paths`` of round 0 (the variance round: a run's own phases train on it;
    error rounds are the resample loop's)."""
    manifest = sset.complete_manifest()
    cut_for = manifest.get("config", {}).get("inputs", FULL.name)
    if cut_for != cfg.inputs:
        raise KpcnError(f"{sset.manifest_path}: the shard set was cut for the input set {cut_for}, not {cfg.inputs} "
                        f"(--inputs); cut it with 'kpcn shards --set {cfg.set_name} --inputs {cfg.inputs}'")
    cut_with = manifest.get("config", {}).get("auxiliaries", RAW)
    if cut_with != cfg.auxiliaries:  # a folder another name rule wrote, or moved by hand: not the set asked for
        raise KpcnError(f"{sset.manifest_path}: the shard set was cut with --auxiliaries {cut_with}, not "
                        f"{cfg.auxiliaries} (--auxiliaries)")
    if manifest.get("features") is not None and len(manifest["features"]) != cfg.model.in_channels:
        raise OptionError("in_channels", f"is {cfg.model.in_channels} but the shards in {sset.dir} have "
                          f"{len(manifest['features'])} feature channels")
    check_fits_patches(cfg.model, int(manifest["patch_size"]), sset.dir)
    entries = {split: sset.verified_shards(split, manifest, rounds=[0]) for split in ("train", "val")}
    sset.check_renders(manifest)
    paths = {split: [e.path for e in found] for split, found in entries.items()}
    patches = sum(e.patches for e in entries["train"])
    if patches < cfg.batch_size:
        raise OptionError("batch_size", f"{cfg.batch_size} exceeds the {patches} training patches of {sset.dir}")
    if cfg.patience and not paths["val"]:
        raise OptionError("patience", f"{cfg.patience} stops on the validation loss, and {sset.dir} holds no held-out "
                          "scenes (cut with --val-fraction 0): cut the shards with some, or train without --patience")
    return manifest, paths


def check_run_folder(run: Run, sset: ShardSet, manifest: dict) -> None:
    """KpcnError for a run folder that is, or lies in, the shard set's folder or the folder of one of its
    renders: a run's records have the names of a render set's (``config.json``, ``timings.json``), and a
    shard set's rebuild owns what is in its folder. Checked with the inputs, before the run is written."""
    where = run.dir.resolve()
    folders = [("shard set", sset.dir)] + [("render set", sset.resolve(s["path"]).parent) for s in manifest["sources"]]
    for what, folder in folders:
        folder = folder.resolve()
        if where == folder or folder in where.parents:
            raise KpcnError(f"run folder (--run) {run.dir}: is {'' if where == folder else 'inside '}the {what} "
                            f"folder {folder}, whose files a run would write over or mix with; choose another --run")


def _open_record(run: Run, cfg: TrainConfig, manifest: dict, sset: ShardSet,
                 init: dict[str, str] | None = None) -> dict:
    """The run's record: read and compared if the run exists, else created (inputs are checked by now;
    ``init``: :func:`init_networks`)."""
    if run.has_record():
        record = run.read_record()
        old = TrainConfig.recorded_identity(record["train"])
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
        _check_init(run, record, init)
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
        "phases": {p.name: _phase_plan(p) for p in cfg.phases()},
        "components": {},
        "results": {},
    }
    if init is not None:
        source = _init_run(cfg)
        record["init"] = {"run": run.relative(source.dir), "networks": init}
        started = source.finished_record().auxiliaries
        if RAW != started or RAW != cfg.auxiliaries:  # a fine-tune across methods says both; raw to raw as before
            record["init"]["auxiliaries"] = started
    run.write_record(record)
    return record


# ---------------------------------------------------------------- starting from another run's networks


def _init_run(cfg: TrainConfig) -> Run:
    """The run (or its ``inputs/`` variant) whose networks of ``cfg``'s input set ``cfg.init`` names."""
    return Run(cfg.init).for_inputs(cfg.input_set)


def init_networks(cfg: TrainConfig, manifest: dict) -> dict[str, str] | None:
    """``{network: SHA-256 of its file}`` for each branch phase of ``cfg`` to start from (``cfg.init``; None
    without it), checked before the run is written: ``cfg.init`` must be a run or a shipped model with a
    finished network of the run's input set for every branch phase, of the run's model configuration, trained
    on the features and constants of the shard set (``manifest``) the run trains on. OptionError naming
    ``--init``, the folder and what differs otherwise."""
    if cfg.init is None:
        return None
    base = Run(cfg.init)
    if not base.has_record():
        raise OptionError("init", f"{cfg.init} is not a run or model folder (no {base.record_path})")
    source = _init_run(cfg)
    if not source.has_record():
        raise OptionError("init", f"{cfg.init} has no network for frames of the input set {cfg.inputs} (no "
                          f"{source.record_path}): train one with --inputs {cfg.inputs}, or start from scratch")
    record = source.finished_record()
    theirs, ours = record.model.to_dict(), cfg.model.to_dict()
    differ = [f"{k} {theirs.get(k)!r} against {ours.get(k)!r}" for k in sorted(set(theirs) | set(ours))
              if theirs.get(k) != ours.get(k)]
    if differ:
        raise OptionError("init", f"{source.dir} holds networks of another configuration than this run's "
                          f"({'; '.join(differ)}): pass its --preset and network options")
    shards = record.data.get("shards", {})
    for what in ("features", "constants"):
        if shards.get(what) != manifest.get(what):
            raise OptionError("init", f"{source.dir} was trained on other {what} than the shard set's "
                              f"({shards.get(what)} against {manifest.get(what)})")
    names = [p.component for p in cfg.phases() if not p.trains_on_final_colour]
    missing = [n for n in names if n not in record.components]
    if missing:
        raise OptionError("init", f"{source.dir} has no {', '.join(missing)} network (it has "
                          f"{', '.join(sorted(record.components)) or 'none'})")
    return {n: sha256_file(record.component_path(n)) for n in names}


def _check_init(run: Run, record: dict, networks: dict[str, str] | None) -> None:
    """KpcnError unless the run resumes from the networks it started from (``record["init"]``)."""
    started = record.get("init", {}).get("networks")
    if started == networks:
        return
    said = (f"started from the networks of {record['init']['run']} (relative to the run)" if started else
            "started from a seeded initialisation")
    now = "other networks (their SHA-256 differ)" if started and networks else (
        "networks (--init)" if networks else "none (no --init)")
    raise KpcnError(f"{run.record_path}: this run {said}, and this command gives it {now}; resume it with the "
                    f"options it was started with, or choose another --run")


def _phase_plan(phase: Phase) -> dict:
    """A phase's entry in the record before it is trained (a continuing phase also says what it continues)."""
    plan = {"status": "pending", "first_epoch": phase.first_epoch, "epochs": phase.epochs, "steps": phase.steps,
            "learning_rate": phase.learning_rate}
    if phase.continues:
        plan.update(continues=phase.continues, rounds=phase.rounds)
    return plan


def epochs_trained(plan: dict) -> int:
    """The epochs a finished phase of the record trained: all it planned, or (``epochs_trained``, written
    only by early stopping) those before it stopped."""
    return plan.get("epochs_trained", plan["epochs"])


def logged_epochs(record: dict, phase: Phase, done: int) -> list[int]:
    """The epoch numbers the CSV log holds once ``phase`` has trained ``done`` epochs: every earlier phase's
    (all its planned epochs, or those it trained before it stopped early), then ``done`` of its own."""
    epochs = []
    for name, plan in record["phases"].items():
        if name == phase.name:
            break
        epochs += range(plan["first_epoch"], plan["first_epoch"] + epochs_trained(plan))
    return epochs + list(range(phase.first_epoch, phase.first_epoch + done))


def _check_log(run: Run, epochs: list[int]) -> None:
    """KpcnError naming the CSV log unless its first rows are the run's ``epochs`` (what the checkpoint and the
    finished phases say were trained: :func:`logged_epochs`), in order, each row whole: resuming on a log that
    was emptied, cut or torn would lose those epochs from it and from ``loss.png`` for good. Refused rather
    than rebuilt: the log is kept as Keras wrote it, and a rebuilt one could only claim to be that."""
    try:
        rows = read_log(run.log_path)
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise KpcnError(f"{run.log_path}: unreadable training log ({type(exc).__name__}: {exc})") from None
    bad = next((e for e, row in zip(epochs, rows)
                if row.get("epoch") != str(e) or None in row or any(v in (None, "") for v in row.values())), None)
    if len(rows) < len(epochs) or bad is not None:
        found = f"{len(rows)} epochs" if bad is None else f"a damaged row for epoch {bad}"
        raise KpcnError(
            f"{run.log_path}: holds {found} where the run has trained {len(epochs)} (it was emptied, cut or "
            f"edited); resuming would lose them from the log and loss.png. Restore it, or train again under "
            f"another --run"
        )


def _cut_log(path: Path, rows: int) -> None:
    """Cut the CSV log back to its header and its first ``rows`` epochs (a kill after a log row but before
    its checkpoint would otherwise leave that epoch twice); no rows, no file."""
    if not path.is_file():
        return
    if rows == 0:
        path.unlink()
        return
    lines = path.read_bytes().splitlines(keepends=True)[: 1 + rows]  # bytes: keeps CSVLogger's \r\n
    with atomic_path(path) as tmp:
        tmp.write_bytes(b"".join(lines))


def read_log(path: Path) -> list[dict]:
    """The CSV log's rows (``epoch``, ``loss``, ``val_loss``, ... as strings); [] before the first epoch."""
    if not path.is_file():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def loss_curve_png(run: Run, record: dict) -> Path:
    """``loss.png``: training and validation loss per epoch of the whole run, each phase shaded and named."""
    plt = pyplot()

    rows = read_log(run.log_path)
    fig, ax = plt.subplots(figsize=(8, 4))
    for key, style in (("loss", "-"), ("val_loss", "--")):
        points = [(int(r["epoch"]) + 1, float(r[key])) for r in rows if r.get(key) not in (None, "", "NA")]
        if points:
            ax.plot(*zip(*points), style, label=key.replace("_", " "))
    for i, (name, plan) in enumerate(record["phases"].items()):
        a = plan["first_epoch"] + 0.5
        ax.axvspan(a, a + epochs_trained(plan), color=f"C{i % 10}", alpha=0.08)
        if "best_epoch" in plan:
            ax.axvline(plan["first_epoch"] + plan["best_epoch"] + 1, color=f"C{i % 10}", lw=0.8, ls=":")
        ax.text(a + 0.1, 0.98, name, transform=ax.get_xaxis_transform(), va="top", rotation=90, fontsize=7)
    ax.set_xlabel("epoch (all phases)")
    ax.set_ylabel("loss (SMAPE; final colour in joint and compositor)")
    ax.set_yscale("log")
    ax.legend(loc="upper right")
    fig.tight_layout()
    return save_png(fig, run.loss_curve_path)


# ---------------------------------------------------------------- the loop


def train_phase(cfg: TrainConfig, run: Run, record: dict, phase: Phase, paths: dict, *, verbose="auto",
                callbacks=(), world: distributed.World = distributed.World()) -> int:
    """Train (or resume) one phase of ``run``; when it returns, ``<phase>.keras`` is written. Returns the
    steps it trained. ``callbacks``: more Keras callbacks for its ``fit`` (after the run's own). Over several
    processes (``world``) each starts from rank 0's weights, gradients are averaged, and only rank 0 writes
    (the checkpoint, the log, the model)."""
    final = run.model_path(phase.name)
    ckpt = run.checkpoint_path(phase.name)
    if final.is_file():
        if world.writer:  # what _finish_phase and loss.png read
            _check_log(run, logged_epochs(record, phase, _epochs_trained(cfg, phase, ckpt)))
        return 0  # written once, after its last epoch: the phase is done (the record may lag after a kill)
    epochs_done, history = 0, []
    if ckpt.is_file():
        state = read_state(ckpt)
        if state is None or "epochs_done" not in state:
            raise KpcnError(f"{ckpt}: a .keras file without kpcn's training state; remove it to restart the "
                            f"{phase.name} phase")
        differ = checkpoint_differences(state, cfg, phase)
        if differ:
            raise KpcnError(
                f"{ckpt}: checkpoint of another configuration ({'; '.join(differ)}). Remove the checkpoint to "
                f"restart the {phase.name} phase, or choose another --run"
            )
        model = load_model(ckpt)
        if not phase.trains_on_final_colour:
            check_architecture(model, cfg.model, ckpt)
        epochs_done, history = int(state["epochs_done"]), list(state.get("history", []))
        if world.writer:
            print(f"[{phase.name}] resuming from {ckpt} after epoch {epochs_done}")
    else:
        model = _build(cfg, run, record, phase)
    _check_registered(model)
    distributed.broadcast_weights(model, world)
    distributed.average_gradients(model, world)
    resumed_at = epochs_done
    if world.writer:
        logged = logged_epochs(record, phase, epochs_done)
        _check_log(run, logged)
        _cut_log(run.log_path, len(logged))

    best = run.best_checkpoint_path(phase.name) if cfg.patience else None
    stopper = StopOnPlateau(history, cfg.patience)
    writes = [keras.callbacks.CSVLogger(str(run.log_path), append=True),
              Checkpoint(ckpt, cfg, phase, history, best if world.writer else None)]
    callbacks = [
        MeanOverProcesses(world),
        StopOnNonFinite(phase, ckpt),  # before the writers: they never see a non-finite epoch
        *(writes if world.writer else []),
        StopOnSaturation(phase, history, started_trained=starts_trained(cfg, phase)),
        stopper,
        *callbacks,
    ]
    # Keras's fit gives every epoch the same steps: the whole epochs are one fit, a shorter last epoch
    # (what is left of the phase's steps) another, so the optimizer takes exactly ``phase.steps`` steps
    whole = phase.steps // phase.epoch_steps
    for start, end in ((epochs_done, whole), (max(epochs_done, whole), phase.epochs)):
        if start >= end or stopper.stopped:
            continue
        train, val = _data(cfg, phase, paths, start, end, world)
        # shuffle=False: the stream is already a seeded permutation, and Keras walks it in order
        # across epochs only without its own shuffling (and with one worker), which makes resume exact
        model.fit(train, epochs=phase.first_epoch + end, initial_epoch=phase.first_epoch + start,
                  steps_per_epoch=phase.epoch_length(start), validation_data=val, callbacks=callbacks,
                  verbose=verbose if world.writer else 0, shuffle=False)
    trained = len(stopper.history)
    if world.writer:
        if best is not None:
            model = load_model(best)  # the phase's model is its best epoch's
            if stopper.stopped:
                print(f"[{phase.name}] stopped after epoch {trained} of {phase.epochs}: the validation loss has "
                      f"not fallen for {cfg.patience} epochs since epoch {best_epoch(stopper.history) + 1}, whose "
                      "weights the phase keeps")
        save_model(model, final)
    return sum(phase.epoch_length(i) for i in range(resumed_at, trained))


def _epochs_trained(cfg: TrainConfig, phase: Phase, ckpt: Path) -> int:
    """Epochs a finished ``phase`` trained: all of them, or, with early stopping, what its checkpoint says."""
    if not cfg.patience:
        return phase.epochs
    state = read_state(ckpt) if ckpt.is_file() else None
    return int(state["epochs_done"]) if state and "epochs_done" in state else phase.epochs


def _finish_phase(cfg: TrainConfig, run: Run, record: dict, phase: Phase, seconds: float,
                  world: distributed.World = distributed.World()) -> None:
    """Mark ``phase`` done in the record (its components now come from its file), with its last epoch and
    the seconds this session spent on it (timings.json), after redrawing loss.png. Only rank 0 writes; the
    other processes update their copy of the record, which their next phases read."""
    record["phases"][phase.name]["status"] = "done"
    record["components"].update(_components(cfg, phase))
    if not world.writer:
        return
    # rank 0 only: another process may get here before rank 0 has written the file, and its copy of the
    # record, without the checksum, has its networks checked by their names (Run.check_model)
    run.record_model(record, run.model_path(phase.name).name, phase.component)
    if cfg.patience:  # what logged_epochs reads for the phases after it
        state = read_state(run.checkpoint_path(phase.name)) or {}
        record["phases"][phase.name].update(epochs_trained=int(state.get("epochs_done", phase.epochs)),
                                            best_epoch=best_epoch(state.get("history", [])))
    rows = [r for r in read_log(run.log_path)
            if phase.first_epoch <= int(r["epoch"]) < phase.first_epoch + phase.epochs]
    record["results"][phase.name] = {"last_epoch": rows[-1] if rows else {}}
    timings = read_json(run.timings_path, "run timings") if run.timings_path.is_file() else {}
    timings[phase.name] = round(seconds, 1)  # the session that finished it
    atomic_write_json(run.timings_path, timings)
    loss_curve_png(run, record)
    # last: the record is what says the phase is done, so a kill before it redraws loss.png on the rerun
    run.write_record(record)


def train(cfg: TrainConfig, run_dir: str | Path, *, verbose="auto", callbacks=(),
          world: distributed.World | None = None) -> Path:
    """Train every phase of ``cfg`` into the run folder ``run_dir`` (for an input set other than the full
    one, into its variant ``<run_dir>/inputs/<inputs>``: ``Run.for_inputs``); returns the folder trained.
    ``callbacks`` are passed to every phase's ``fit`` (a benchmark's step timer).

    ``world``: the processes of a data-parallel run (default: what torchrun's variables say, else this
    process alone; ``kpcn_keras.distributed``). ``cfg.batch_size`` is the global batch, split evenly
    between them; rank 0 holds the run's lock and writes everything, the others wait for it between
    phases. A killed run resumes with the same command, with any number of processes."""
    keras_backend = keras.backend.backend()
    if keras_backend != "torch":
        raise KpcnError(f"kpcn trains on the torch backend; KERAS_BACKEND selects {keras_backend!r}")
    world = distributed.from_environment() if world is None else world
    if cfg.batch_size % world.size:
        raise OptionError("batch_size", f"{cfg.batch_size} does not split evenly over {world.size} processes")
    run = Run(run_dir).for_inputs(cfg.input_set)
    sset = ShardSet(cfg.set_dir)
    manifest, paths = check_inputs(cfg, sset)
    init = init_networks(cfg, manifest)
    check_run_folder(run, sset, manifest)
    check_writable(run.dir, "run folder (--run)", directory=True)
    distributed.start(world)
    if world.distributed and world.writer:
        print(f"data-parallel: {world.size} processes ({distributed.backend()}), {cfg.batch_size // world.size} "
              f"patches each of every batch of {cfg.batch_size}")
    with run.lock() if world.writer else nullcontext():
        if world.writer:
            run.remove_temporaries()
            record = _open_record(run, cfg, manifest, sset, init)
        distributed.barrier(world)
        if not world.writer:
            record = run.read_record()
        for phase in cfg.phases():
            run_phase(cfg, run, record, phase, paths, verbose=verbose, callbacks=callbacks, world=world)
            distributed.barrier(world)  # the phase's file is written before any process builds on it
    distributed.stop(world)
    return run.dir


def run_phase(cfg: TrainConfig, run: Run, record: dict, phase: Phase, paths: dict, *, verbose="auto",
              callbacks=(), world: distributed.World = distributed.World()) -> float:
    """Train ``phase`` of ``run`` unless the record says it is done (listing it first if it is not yet
    listed), then mark it done; returns the seconds this call trained (0 for a done phase). The run's lock
    must be held."""
    if record["phases"].get(phase.name, {}).get("status") == "done" and run.model_path(phase.name).is_file():
        return 0.0
    record["phases"].setdefault(phase.name, _phase_plan(phase))
    start = time.perf_counter()
    steps = train_phase(cfg, run, record, phase, paths, verbose=verbose, callbacks=callbacks, world=world)
    seconds = time.perf_counter() - start
    if steps and world.writer:  # the throughput a user compares across machines and process counts
        print(f"[{phase.name}] {steps} steps in {seconds:.1f} s: {steps / seconds:.2f} steps/s, "
              f"{steps * cfg.batch_size / seconds:.1f} patches/s (validation and saving included)")
    _finish_phase(cfg, run, record, phase, seconds, world)
    return seconds
