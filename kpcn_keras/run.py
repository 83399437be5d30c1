"""A run folder, and the ``.keras`` files in it (docs/formats.md §5; docs/design.md §3).

:class:`Run` is the one owner of a run folder's layout::

    <run>/config.json                 the run record: training config, shard set, versions, command, phases,
                                      components, results
    <run>/timings.json                seconds per phase (with resample/timings.json, the only files that differ
                                      between identical runs)
    <run>/<phase>.keras               what a finished training phase trained (one file per phase)
    <run>/checkpoints/<phase>.keras   the phase being trained, with its optimizer and training state
    <run>/checkpoints/<phase>-best.keras  with early stopping, the phase's best epoch so far (its model at the end)
    <run>/log.csv                     loss and validation loss per epoch, every phase in one numbering
    <run>/loss.png                    the log as a curve, phases shaded
    <run>/eval/                       ``kpcn evaluate``'s report on the held-out frames
    <run>/eval-validation/            ``kpcn evaluate --out <run>/eval-validation FRAMES``: on another
                                      renderer's validation frames (``make model``)
    <run>/figures/                    ``kpcn figures``' PNGs
    <run>/resample/rounds.json        ``kpcn resample``: one record per error round (and the run before them)
    <run>/resample/timings.json       seconds per error round (and the run before them)
    <run>/resample/round-<k>.png      the map that drove round k's draw on one training render, its new patches
    <run>/.lock                       held by the one process that trains into the run
    <run>/inputs/<inputs>/            the run's network for frames without a split or variance: a run folder of
                                      its own, of this layout, for each input set but the full one
                                      (``kpcn train --inputs``: :meth:`Run.for_inputs`)
    <run>/quality/<mode>/             the networks of another quality mode (``config.QUALITY_MODES``): a run
                                      folder of its own, of this layout (a shipped model's: ``kpcn ship --mode``)

A run folder's own networks (and its ``inputs/`` variants) are its ``balanced`` mode (``config.DEFAULT_QUALITY``),
so every run is a model of one mode; :meth:`Run.quality_modes` lists a model's modes and :meth:`Run.for_quality`
gives the run of one (refused in one line naming the modes it has). A *shipped model* (``models/<name>/``) is
``kpcn_keras/shipping.py``'s: a run folder of this layout holding what serving needs and nothing else.
``kpcn denoise`` without ``--run`` uses :func:`default_model`.

A run's record names its input set (``prep.inputs``; :attr:`RunRecord.inputs`: the full set for a record
without one), and its denoiser reads frames restricted to it. :meth:`Run.serving` picks, among a run and its
``inputs/`` variants, the finished one for a frame's input set.

A *component* is a network the denoiser is made of: ``diffuse`` and ``specular`` (or one ``shared``),
``albedo`` for a run with an albedo network, and ``compositor`` for a multiscale run. The record's ``components``
maps each to the phase file that holds its latest weights and the path of nested model names to it inside that
file (joint fine-tuning trains both branch networks as parts of one model, so its file holds both; the albedo
phase's file holds the albedo network inside the model it trained in): :meth:`Run.load_component` is how
anything reads one.

The record stores the shard set's folder relative to the run folder, and no field names the run itself,
so a run folder can be renamed or used from any working directory.

**What a reader gets is what training wrote.** The record's ``models`` maps every finished phase file to its
SHA-256 and the network it was trained as (:meth:`Run.record_model`); each network inside a file also carries its
role as its model name (``diffuse``, ``specular``, ``shared``, ``albedo``, ``compositor``:
``models.build_branch_model`` names every layer after it). Every reader of a run's networks (denoise, evaluate,
figures, compare, bench, resample) reads the record once, as a :class:`RunRecord` (:meth:`Run.record`: the JSON
parsed in this one place, the model configuration a ``ModelConfig``), refuses it while a phase or a resample
round is unfinished (:meth:`RunRecord.finished`, naming it and the command that resumes it), and reads each
network once with :meth:`Run.load_component` (refused when the file's checksum is not the recorded one, or the
network in it is another branch's), through ``denoise.Denoiser.from_run``, and passes the record and the denoiser
down. A run written before the record held checksums has no ``models``: it still loads, checked by the model
names alone. The writers (``train``, ``resample``) update the record's JSON (:meth:`Run.read_record`) and write
it whole: the file's format is theirs, and :class:`RunRecord` only reads it.

``.keras`` files are written by :func:`save_model` through ``prep.files.atomic_path`` and made canonical:
fixed zip timestamps and no save date, so the same weights give the same bytes (checksums of models mean
something), and a checkpoint carries its training state (epochs done, model configuration, history) as one
more entry of the same zip, so the model and its epoch count can never disagree after a kill.
"""

from __future__ import annotations

import copy
import importlib
import json
import os
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType

import keras

from kpcn_keras.config import DEFAULT_QUALITY, HINT_FLAGS, QUALITY_MODES, CompositorConfig, ModelConfig, TrainConfig
from kpcn_keras.models import build_branch_model
from prep.errors import KpcnError, OptionError
from prep.files import atomic_path, atomic_write_json, exclusive_lock, read_json, remove_temporaries, sha256_file
from prep.inputs import FULL, INPUT_SETS, InputSet
from prep.shards import ShardSet

RECORD = "config.json"
INPUTS = "inputs"  # the folder of a run's variants for other input sets
QUALITY = "quality"  # the folder of a model's other quality modes, one run folder each
TIMINGS = "timings.json"  # the seconds of a folder: the one file whose bytes differ between identical runs
STATE_ENTRY = "kpcn-state.json"
CARD = "CARD.md"  # a shipped model's card (kpcn_keras/card.py)
REPORT, METRICS = "report.md", "metrics.json"  # kpcn evaluate's tables in a report folder (eval/)
REPORT_TABLES = (REPORT, METRICS)  # what a shipped model keeps of a report folder: not its PNGs
_ZIP_TIME = (1980, 1, 1, 0, 0, 0)


class Run:
    """One run folder (it may not exist yet)."""

    def __init__(self, path: str | os.PathLike):
        self.dir = Path(path)

    def __repr__(self) -> str:
        return f"Run({str(self.dir)!r})"

    @property
    def record_path(self) -> Path:
        return self.dir / RECORD

    @property
    def timings_path(self) -> Path:
        return self.dir / TIMINGS

    @property
    def eval_dir(self) -> Path:
        return self.dir / "eval"

    @property
    def validation_dir(self) -> Path:
        return self.dir / "eval-validation"

    @property
    def card_path(self) -> Path:
        return self.dir / CARD

    @property
    def figures_dir(self) -> Path:
        return self.dir / "figures"

    @property
    def resample_dir(self) -> Path:
        return self.dir / "resample"

    @property
    def resample_record_path(self) -> Path:
        return self.resample_dir / "rounds.json"

    @property
    def resample_timings_path(self) -> Path:
        return self.resample_dir / TIMINGS

    def resample_png(self, round_name: str) -> Path:
        return self.resample_dir / f"{round_name}.png"

    def model_path(self, phase: str) -> Path:
        return self.dir / f"{phase}.keras"

    @property
    def checkpoint_dir(self) -> Path:
        return self.dir / "checkpoints"

    def checkpoint_path(self, phase: str) -> Path:
        return self.checkpoint_dir / f"{phase}.keras"

    def best_checkpoint_path(self, phase: str) -> Path:
        """The phase's best epoch so far (the model alone), kept under early stopping (``--patience``)."""
        return self.checkpoint_dir / f"{phase}-best.keras"

    @property
    def log_path(self) -> Path:
        return self.dir / "log.csv"

    @property
    def loss_curve_path(self) -> Path:
        return self.dir / "loss.png"

    def lock(self):
        return exclusive_lock(self.dir, "run folder")

    def for_inputs(self, inputs: InputSet) -> Run:
        """The run of ``inputs``: this run for the full set, else the run folder ``<run>/inputs/<name>``."""
        return self if inputs == FULL else Run(self.dir / INPUTS / inputs.name)

    def quality_dir(self, mode: str) -> Path:
        """Where the networks of quality mode ``mode`` are: this folder for the default mode, else
        ``<run>/quality/<mode>``."""
        return self.dir if mode == DEFAULT_QUALITY else self.dir / QUALITY / mode

    def quality_modes(self) -> list[str]:
        """The quality modes this model has, in the order of ``config.QUALITY_MODES``: the default one (its own
        networks) and each whose folder ``quality/<mode>`` exists."""
        return [mode for mode in QUALITY_MODES if mode == DEFAULT_QUALITY or self.quality_dir(mode).is_dir()]

    def for_quality(self, mode: str) -> Run:
        """The run of quality mode ``mode``: this run for the default mode, else ``quality/<mode>``, checked as a
        model folder (:meth:`check_folder`). KpcnError in one line naming this folder, the mode and the modes it
        has where it has not that one."""
        if mode == DEFAULT_QUALITY:
            return self
        self.check_folder()
        if mode not in self.quality_modes():
            raise KpcnError(f"{self.dir} has no quality mode {mode!r}; its modes: {', '.join(self.quality_modes())}")
        return Run(self.quality_dir(mode)).check_folder()

    def serving(self, frame: InputSet) -> Run:
        """The run whose networks denoise a frame that has ``frame``: this run, then its ``inputs/`` variants in
        the order of ``prep.inputs.INPUT_SETS`` (the most the frame has first), the first that is finished and
        whose input set serves the frame (``InputSet.serves``). KpcnError naming the run, what the frame lacks
        and the commands that train the model for it, if none does."""
        self.check_folder()
        runs = [run for run in self.variants() if run.has_record()]
        found = []
        for run in runs:
            record = run.record()
            try:
                record.finished()
            except KpcnError:
                if run is self and len(runs) == 1 and record.inputs.serves(frame):
                    raise  # the run alone, unfinished: its own line names the phase and the command that resumes it
                found.append(f"{record.inputs} (unfinished)")
                continue
            if record.inputs.serves(frame):
                run.check_weights(record)  # a damaged variant is refused, never passed over for a lesser one
                return run
            found.append(record.inputs.name)
        lacks = " and ".join(what for what, has in (("a diffuse/specular split", frame.split),
                                                     ("variance layers", frame.variance)) if not has)
        what = f"without {lacks}" if lacks else "with a split and variance layers"
        raise KpcnError(f"{self.dir}: no finished model for a frame {what} (the run has: "
                        f"{', '.join(found) or 'none'}); train it with {self.training_commands(frame)}")

    def training_commands(self, inputs: InputSet) -> str:
        """'kpcn shards ...' then 'kpcn train ...': what trains this run's model for ``inputs``, on the base
        run's shard set cut for that input set (the model that serves it best)."""
        base = self.record().train if self.has_record() else TrainConfig()
        root = None if base.shards_root == TrainConfig.shards_root else base.shards_root
        aux = None if base.auxiliaries == TrainConfig.auxiliaries else base.auxiliaries  # the run's, for its variants
        shards = _hint_command("shards", {"set_name": base.set_name, "out_root": root, "inputs": inputs.name,
                                          "auxiliaries": aux})
        train = _hint_command("train", {"set_name": base.set_name, "shards_root": root, "run": str(self.dir),
                                        "inputs": inputs.name, "auxiliaries": aux})
        return f"'{shards}' then '{train}'"

    def check_folder(self) -> Run:
        """This run, if its folder is a model to denoise with: its record (``config.json``) present and readable;
        KpcnError in one line naming the folder otherwise (every path that takes a model folder: ``--run``,
        ``KPCN_MODEL``, ``kpcn.denoise``, view, evaluate). A folder whose ``inputs/`` holds variants but which has
        no record of its own (``kpcn train --inputs`` into a new folder, or a model whose record was lost) is
        refused too, naming them: each is a run folder of its own, to pass instead. Taking one in its place would
        denoise a frame with more inputs by a lesser network without a word."""
        if not self.has_record():
            variants = [name for name, run in zip(INPUT_SETS[1:], self.variants()[1:]) if run.has_record()]
            where = (f"; its {INPUTS}/ holds only the variants {', '.join(variants)}, each a run folder of its own: "
                     f"pass one (e.g. {self.for_inputs(InputSet.named(variants[0])).dir}) or train the full model "
                     "into this folder with 'kpcn train'" if variants else "; train one with 'kpcn train'")
            raise KpcnError(f"{self.dir}: not a run folder (no {RECORD}){where}")
        self.record()
        return self

    def check_weights(self, record: RunRecord) -> None:
        """KpcnError naming the first model file that the record lists for a component and that is missing: found
        before a command starts its work, not when that network is first loaded."""
        for name, entry in record.components.items():
            path = self.dir / entry.file
            if not path.is_file():
                raise KpcnError(f"{path}: missing, the {name} network of the run record {self.record_path}; "
                                "restore it or train the run again")

    def variants(self) -> list[Run]:
        """The run of every input set, in the order of ``prep.inputs.INPUT_SETS`` (this run first)."""
        return [self.for_inputs(InputSet.named(name)) for name in INPUT_SETS]

    def remove_temporaries(self) -> None:
        """Remove what killed trainers and resample loops left (hold :meth:`lock`; ``eval/`` and ``figures/``
        belong to evaluate and figures, which take no lock)."""
        for folder in (self.dir, self.checkpoint_dir, self.resample_dir):
            if folder.is_dir():
                remove_temporaries(folder)

    def has_record(self) -> bool:
        return self.record_path.is_file()

    def _read_json(self) -> dict:
        if not self.record_path.is_file():
            self.check_folder()  # the one line that says what the folder is instead
        data = read_json(self.record_path, "run record", keys=("train", "shards", "results"))
        if "phases" not in data:
            raise KpcnError(f"{self.record_path}: a run made by an older kpcn (no training phases); train it again")
        return data

    def record(self) -> RunRecord:
        """The run record, read and parsed once (:class:`RunRecord`); KpcnError naming the file if the
        folder is not a run or the record is broken."""
        return self.parse_record(self._read_json())

    def read_record(self) -> dict:
        """The run record as its JSON, checked as :meth:`record` checks it: for the writers (train, resample),
        which update it and write it back (:meth:`write_record`)."""
        data = self._read_json()
        self.parse_record(data)
        return data

    def parse_record(self, data: dict) -> RunRecord:
        """``data`` (the JSON of this run's record, e.g. a writer's copy) as a :class:`RunRecord`."""
        return RunRecord.from_json(self.record_path, data)

    def finished_record(self, *, resampling: bool = False) -> RunRecord:
        """:meth:`record`, refused unless the run's networks may be used (:meth:`RunRecord.finished`)."""
        return self.record().finished(resampling=resampling)

    def read_files(self, record: RunRecord) -> list[tuple[str, Path]]:
        """What denoising with the run reads of it, ``(what, path)``: its record and each component's model
        file (for ``prep.files.check_outputs``)."""
        return [("run record", self.record_path)] + [(f"{name} model", self.dir / entry.file)
                                                     for name, entry in record.components.items()]

    def write_record(self, record: dict) -> None:
        atomic_write_json(self.record_path, record)

    def relative(self, path: str | os.PathLike) -> str:
        return os.path.relpath(os.path.abspath(path), os.path.abspath(self.dir))

    def record_model(self, record: dict, file: str, network: str) -> None:
        """Note in ``record`` the model file ``file`` (relative to the run folder) that the run wrote: its
        SHA-256 and the network it was trained as, what :meth:`load_component` checks it against."""
        record.setdefault("models", {})[file] = {"network": network, "sha256": sha256_file(self.dir / file)}

    def load_component(self, record: RunRecord, name: str, *, compile: bool = False) -> keras.Model:
        """The finished network ``name`` (``diffuse``, ``specular``, ``shared``, ``albedo``, ``compositor``) of the run,
        read from the phase file the record names; KpcnError if the run has not trained it, if the file is
        not the one the record lists (SHA-256), or if the network in it was trained for another branch."""
        entry = record.components.get(name)
        if entry is None:
            trained = ", ".join(sorted(record.components)) or "none yet"
            raise KpcnError(f"{self.dir}: the run has no finished {name} network (finished: {trained})")
        path = self.dir / entry.file
        model = load_model(path, compile=compile)
        for layer in entry.layers:
            try:
                model = model.get_layer(layer)
            except ValueError:
                raise KpcnError(f"{path}: holds no {layer} network (it holds the model {model.name!r}); "
                                f"not the file the run wrote") from None
        self.check_model(record, entry.file, model, name)
        return model

    def check_model(self, record: RunRecord, file: str, model: keras.Model, network: str) -> None:
        """KpcnError naming the run's model file ``file`` unless ``model`` (read from it) is the ``network``
        the run needs there and the file has the SHA-256 the record lists (a record without one, of a run
        written before records held them, is checked by the network's name alone)."""
        path = self.dir / file
        if model.name != network:
            raise KpcnError(f"{path}: holds a {model.name} network where the run needs its {network} network "
                            f"(a copy of another phase's file?); restore the run's own file or train it again")
        self.check_file(record, file)

    def check_file(self, record: RunRecord, file: str) -> None:
        """KpcnError naming the run's model file ``file`` unless it has the SHA-256 the record lists (none
        listed: nothing to check)."""
        listed = record.models.get(file)
        if listed is not None:
            path = self.dir / file
            found = sha256_file(path)
            if found != listed.sha256:
                raise KpcnError(f"{path}: not the file this run wrote (SHA-256 {found[:12]}…, the record "
                                f"{self.record_path} lists {listed.sha256[:12]}…); restore it or train "
                                "the run again")

    def fork(self, dest: str | os.PathLike, sset: ShardSet | None = None) -> Run:
        """A copy of this run in ``dest`` (so that two experiments can continue it apart), trained on ``sset``
        (default: the same shard set), which must hold the same content. Written under a temporary name and
        renamed, so ``dest`` is whole or absent; an existing ``dest`` is returned as it is."""
        import shutil

        new = Run(dest)
        if new.has_record():
            return new
        record = self.record()
        if sset is not None:
            if sset.complete_manifest()["content_key"] != record.content_key:
                raise KpcnError(f"{sset.dir}: not the shard set {self.dir} was trained on")
        else:
            sset = self.shard_set(record)
        data = copy.deepcopy(record.data)  # the copy's record: the same but for where its shard set is
        for stale in new.dir.parent.glob(f".{new.dir.name}.tmp-*"):  # a killed fork's
            shutil.rmtree(stale)
        tmp = new.dir.with_name(f".{new.dir.name}.tmp-{os.getpid()}")
        # not the variants of other input sets (inputs/) nor other quality modes (quality/): runs of their own
        shutil.copytree(self.dir, tmp, ignore=lambda folder, names: [
            n for n in names if n.startswith(".") or (n in (INPUTS, QUALITY) and Path(folder) == self.dir)])
        data["shards"]["set_dir"] = os.path.relpath(os.path.abspath(sset.dir), os.path.abspath(new.dir))
        Run(tmp).write_record(data)
        os.replace(tmp, new.dir)
        return new

    def shard_set(self, record: RunRecord) -> ShardSet:
        """The shard set the run was trained on (stored relative to the run folder)."""
        return ShardSet(os.path.normpath(self.dir / record.set_dir))


def _hint_command(command: str, values: dict) -> str:
    """``kpcn <command>`` with ``values`` (option -> value; None left out) under the flags ``config.HINT_FLAGS``
    gives them."""
    flags = HINT_FLAGS[command]
    return " ".join(["kpcn", command] + [f"{flags[k]} {v}" for k, v in values.items() if v is not None])


def default_model() -> Run:
    """The model ``kpcn denoise`` uses without ``--run``: the folder the environment variable
    ``config.MODEL_ENV`` names, else the shipped ``models/<config.DEFAULT_MODEL>`` beside the package. KpcnError
    in one line, saying how to train one, if it holds no model."""
    from kpcn_keras import config  # read when called: a test points it elsewhere

    chosen = os.environ.get(config.MODEL_ENV)
    run = Run(chosen or config.MODELS_DIR / config.DEFAULT_MODEL)
    named = f" (named by {config.MODEL_ENV})" if chosen else ""
    if not run.dir.exists():
        raise KpcnError(f"no model is shipped at {run.dir}{named}: train one with 'make model', or with 'make train' "
                        "and pass --run runs/default")
    try:
        return run.check_folder()
    except KpcnError as exc:  # refused as --run refuses it, saying where the folder came from
        raise KpcnError(f"{exc}{named}") from None


@dataclass(frozen=True)
class Component:
    """A network of the run (see the module docstring): the phase file, relative to the run folder, that
    holds its latest weights, and the path of nested model names to it inside that file."""

    file: str
    layers: tuple[str, ...] = ()


@dataclass(frozen=True)
class ModelFile:
    """A finished phase file as training wrote it: the network it was trained as and its SHA-256."""

    network: str
    sha256: str


@dataclass(frozen=True)
class RunRecord:
    """A run's ``config.json``, read once and parsed once (:meth:`Run.record`), for the readers of a run.

    ``train`` is the run's :class:`TrainConfig`, its ``model`` a :class:`ModelConfig` (and ``compositor``
    a :class:`CompositorConfig` or None): the one parse of the model configuration. ``set_dir`` is the
    shard set's folder relative to the run folder; ``components`` and ``models`` are the record's entries
    (``models`` is empty for a run written before records held checksums); ``phases`` and ``rounds`` each
    phase's and resample round's status. ``data`` is the JSON as read, for what no field names (results,
    versions, the resample loop's entries); the writers (train, resample) update their own dict
    (:meth:`Run.read_record`) and write it back, so the file format is theirs.
    """

    path: Path
    train: TrainConfig
    set_dir: str
    content_key: str | None
    components: Mapping[str, Component]
    models: Mapping[str, ModelFile]
    phases: Mapping[str, str | None]
    rounds: Mapping[str, str | None]
    command: str | None
    data: Mapping = field(repr=False)

    @classmethod
    def from_json(cls, path: Path, data: dict) -> RunRecord:
        """The record of the JSON ``data`` read from ``path``; KpcnError naming the file and the part of the
        record that is damaged (missing, of the wrong type, or a configuration out of its bounds)."""
        part = "train"
        try:
            train = TrainConfig.from_record(data["train"])
            part = "shards"
            set_dir, content_key = data["shards"]["set_dir"], data["shards"].get("content_key")
            part = "components"
            components = {name: Component(entry["file"], tuple(entry.get("layers", ())))
                          for name, entry in data["components"].items()}
            part = "models"
            models = {file: ModelFile(entry["network"], entry["sha256"])
                      for file, entry in data.get("models", {}).items()}
            part = "phases"
            phases = {name: plan.get("status") for name, plan in data["phases"].items()}
            part = "resample"
            rounds = {name: entry.get("status") for name, entry in data.get("resample", {}).get("rounds", {}).items()}
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise KpcnError(f"{path}: the run record is damaged in its {part} ({type(exc).__name__}: {exc})") from None
        return cls(Path(path), train, set_dir, content_key, MappingProxyType(components), MappingProxyType(models),
                   MappingProxyType(phases), MappingProxyType(rounds), data.get("command"), data)

    @property
    def dir(self) -> Path:
        return self.path.parent

    @property
    def model(self) -> ModelConfig:
        return self.train.model

    @property
    def compositor(self) -> CompositorConfig | None:
        return self.train.compositor

    @property
    def inputs(self) -> InputSet:
        """The input set the run was trained for (the full set for a record written before input sets)."""
        return self.train.input_set

    @property
    def auxiliaries(self) -> str:
        """How the albedo, normal and depth the run's networks see are prefiltered (``prep.auxiliary.TRAINED``):
        what its shard set was cut with, and what its denoiser gives it (raw for a record written before)."""
        return self.train.auxiliaries

    @property
    def branches(self) -> tuple[str, ...]:
        """The branches its denoiser runs (``TrainConfig.denoised_branches``)."""
        return self.train.denoised_branches

    @property
    def validation_slope(self) -> float | None:
        """λ of the run's validation for a run trained with λ as an input (``kpcn figures``' frame), else None."""
        return self.train.slope if self.model.slope_channel else None

    def check_slope(self, slope: float | None) -> None:
        """OptionError unless the networks get the λ they need: a run trained with λ as an input needs one
        (``models.network_input`` refuses one given to a network without that input)."""
        if self.model.slope_channel and slope is None:
            raise OptionError("slope", f"is needed: {self.dir} was trained with λ as an input, for λ in "
                              f"{list(self.train.slope_range)}")

    def component_path(self, name: str) -> Path:
        return self.dir / self.components[name].file

    def finished(self, *, resampling: bool = False) -> RunRecord:
        """This record, if the run's networks may be used: KpcnError naming the first phase that is not done
        (its status, and that ``kpcn train`` resumes it), or the first unfinished resample round (a kill
        between its two branch phases leaves one network a round ahead), unless ``resampling`` (the loop's
        own use, between the phases of the round it is training)."""
        for name, status in self.phases.items():
            if status != "done":
                raise KpcnError(
                    f"{self.path}: the {name} phase is unfinished (status {status!r}); "
                    f"'kpcn train --run {self.dir}' with the options it was started with resumes it "
                    f"({self.command or 'kpcn train'})")
        for name, status in self.rounds.items() if not resampling else ():
            if status != "done":
                raise KpcnError(
                    f"{self.path}: resample {name} is unfinished (status {status!r}); "
                    f"'kpcn resample --run {self.dir}' with the options it was started with resumes it")
        return self


# ---------------------------------------------------------------- .keras files


def save_model(model: keras.Model, path: str | os.PathLike, state: dict | None = None) -> Path:
    """Save ``model`` (with its optimizer, if compiled) atomically and canonically; ``state`` is stored
    inside the same file (see :func:`read_state`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        model.save(tmp)
        _canonicalise(tmp, state)
    return path


def _canonicalise(path: Path, state: dict | None) -> None:
    """Rewrite the zip Keras wrote: entries in name order, fixed timestamps, no save date, no shared-object
    ids, plus ``state``."""
    with zipfile.ZipFile(path) as src:
        entries = {info.filename: src.read(info.filename) for info in src.infolist()}
    metadata = json.loads(entries["metadata.json"])
    metadata.pop("date_saved", None)
    entries["metadata.json"] = json.dumps(metadata, sort_keys=True).encode()
    # Keras marks objects that several layers share (a dtype policy) with their id(), a per-process memory
    # address, and a model read back from a file shares nothing: without the marks, the same weights give
    # the same bytes whether the model was built in this process or loaded
    entries["config.json"] = json.dumps(_without_shared_ids(json.loads(entries["config.json"]))).encode()
    if state is not None:
        entries[STATE_ENTRY] = json.dumps(state, sort_keys=True, indent=1).encode()
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as dst:
        for name in sorted(entries):
            dst.writestr(zipfile.ZipInfo(name, date_time=_ZIP_TIME), entries[name])


def _without_shared_ids(value):
    if isinstance(value, dict):
        return {k: _without_shared_ids(v) for k, v in value.items() if k != "shared_object_id"}
    if isinstance(value, list):
        return [_without_shared_ids(v) for v in value]
    return value


def read_state(path: str | os.PathLike) -> dict | None:
    """The training state stored in a ``.keras`` file by :func:`save_model` (None if it has none)."""
    path = Path(path)
    try:
        with zipfile.ZipFile(path) as z:
            if STATE_ENTRY not in z.namelist():
                return None
            return json.loads(z.read(STATE_ENTRY))
    except (zipfile.BadZipFile, OSError, ValueError) as exc:
        raise KpcnError(f"{path}: not a readable .keras file ({type(exc).__name__}: {exc})") from None


# the modules whose registered layers and losses a run's .keras files name: loading needs them imported
_REGISTERING = ("kpcn_keras.layers", "kpcn_keras.losses", "kpcn_keras.multiscale")


def load_model(path: str | os.PathLike, *, compile: bool = True) -> keras.Model:
    """``keras.models.load_model`` with errors that name the file: missing, or damaged (and how)."""
    for module in _REGISTERING:
        importlib.import_module(module)
    path = Path(path)
    if not path.is_file():
        raise KpcnError(f"{path}: no such model file")
    if not zipfile.is_zipfile(path):
        raise KpcnError(f"{path}: damaged model file (not a .keras zip archive)")
    try:
        return keras.models.load_model(path, compile=compile)
    except Exception as exc:  # Keras reports every failure as ValueError("File not found") or worse
        raise KpcnError(f"{path}: damaged model file ({type(exc).__name__}: {exc})") from exc


def weight_signature(model: keras.Model) -> list[tuple[str, tuple[int, ...]]]:
    """(path, shape) of every weight: what must agree for two models to be the same architecture."""
    return [(w.path, tuple(int(d) for d in w.shape)) for w in model.weights]


def check_architecture(model: keras.Model, config: ModelConfig, path: str | os.PathLike) -> None:
    """KpcnError naming ``path`` unless ``model`` has the weights a model built from ``config`` has.

    Tiled inference derives its overlap from the configuration, so a model of another architecture would
    give wrong (tile-size dependent) output rather than fail.
    """
    expected = weight_signature(build_branch_model(config, name=model.name))
    found = weight_signature(model)
    if found != expected:
        first = next((f"{a} vs {b}" for a, b in zip(found, expected) if a != b),
                     f"{len(found)} weights vs {len(expected)}")
        raise KpcnError(
            f"{path}: the model's architecture differs from the run's configuration "
            f"({config.arch}, width {config.width}, depth {config.depth}, conv {config.conv_size}, "
            f"kernel {config.kernel_size}); first difference: {first}"
        )
