"""Shipping: a finished run (with a run for every input set), and a run for each other quality mode, copied into a
model folder ``models/<name>/`` (``kpcn ship``; the card is ``kpcn_keras/card.py``'s; docs/formats.md §5b).

A *shipped model* is a run folder of ``Run``'s layout holding what serving needs and nothing else: the record,
timings, the component files, the log and its curve, the reports' tables (``eval/`` and ``eval-validation/``
without their PNGs), the same for each ``inputs/<inputs>/`` (one for every input set), and its card ``CARD.md``;
no checkpoints, no locks. Those are its ``balanced`` mode (``config.DEFAULT_QUALITY``). Each other quality mode
shipped (``kpcn ship --mode fast=RUN``) is the same copy of its own run in ``quality/<mode>/``
(``Run.for_quality``), without a card. Each copied record says where it came from (:data:`SHIPPED`): the mode, the
run as named and the SHA-256 of each network, as that run's record lists them.
"""

from __future__ import annotations

import copy
import os
import shutil
from collections.abc import Mapping
from contextlib import ExitStack
from pathlib import Path

from kpcn_keras.config import DEFAULT_QUALITY, SHIPPED_MAX_BYTES
from kpcn_keras.run import CARD, RECORD, REPORT_TABLES, TIMINGS, Run, RunRecord
from prep.errors import KpcnError
from prep.files import sha256_file, write_failure
from prep.inputs import INPUT_SETS, InputSet

SHIPPED = "shipped"  # the entry of a shipped record that says which run and networks it came from


def shippable_records(run: Run) -> list[RunRecord]:
    """The finished record of every input set's run (``Run.variants``): what :func:`ship` needs. KpcnError in one
    line naming the first that is missing (and the commands that train it) or unfinished (and the command that
    resumes it)."""
    records = []
    for variant, name in zip(run.variants(), INPUT_SETS):
        if not variant.has_record():
            if variant is run:
                run.record()  # the one line that says this is not a run folder
            raise KpcnError(f"{run.dir}: no model for the {name} input set ({variant.dir} is missing), which a "
                            f"shipped model needs; train it with {run.training_commands(InputSet.named(name))}")
        records.append(variant.finished_record())
    return records


def shipped_files(run: Run, record: RunRecord) -> list[str]:
    """The files of ``run`` (not of its variants), relative to its folder, that a shipped model holds: the record,
    each component's file (what serving loads: a phase whose networks a later phase's file holds too is left
    out), the timings, the log, its curve and the reports' tables, those that exist."""
    files = [RECORD, *dict.fromkeys(entry.file for entry in record.components.values())]
    optional = [TIMINGS, run.relative(run.log_path), run.relative(run.loss_curve_path)]
    optional += [run.relative(folder / name) for folder in (run.eval_dir, run.validation_dir)
                 for name in REPORT_TABLES]
    return files + [f for f in optional if (run.dir / f).is_file()]


def is_shipped_model(run: Run) -> bool:
    """Whether ``run`` is a shipped model folder: a record and a card, no checkpoints (what :func:`ship` writes)."""
    return run.card_path.is_file() and run.has_record() and not run.checkpoint_dir.exists()


def check_ship_destination(run: Run, new: Run) -> None:
    """KpcnError unless ``new`` may be written by :func:`ship` from ``run``: neither the run, in it, nor holding it,
    and absent or an earlier shipped model (which it replaces): never a folder of anything else."""
    here, there = Path(os.path.abspath(run.dir)), Path(os.path.abspath(new.dir))
    if here == there or here in there.parents or there in here.parents:
        raise KpcnError(f"{new.dir}: the model folder (--out) cannot be the run {run.dir}, in it or hold it; "
                        "choose another, e.g. models/<name>")
    if new.dir.exists() and not is_shipped_model(new):
        raise KpcnError(f"{new.dir}: exists and is not a shipped model (no {CARD}, or a run with checkpoints), "
                        "which shipping would replace; choose another --out")


def check_modes(run: Run, dest: str | os.PathLike, modes: Mapping[str, Run]) -> dict[str, list[RunRecord]]:
    """The finished records (:func:`shippable_records`) of ``run`` as the balanced mode and of each mode's run of
    ``modes`` (mode -> run), after checking ``dest`` against each run (:func:`check_ship_destination`): every
    refusal comes before anything is written."""
    runs = {DEFAULT_QUALITY: run, **modes}
    for source in runs.values():
        check_ship_destination(source, Run(dest))
    return {mode: shippable_records(source) for mode, source in runs.items()}


def _shipped_entry(mode: str, source: Run, record: RunRecord) -> dict:
    """What a shipped record says of where it came from: the mode, the run as named, each network's SHA-256."""
    return {"mode": mode, "run": str(source.dir),
            "networks": {name: record.models[entry.file].sha256 if entry.file in record.models
                         else sha256_file(source.dir / entry.file) for name, entry in record.components.items()}}


def ship(run: Run, dest: str | os.PathLike, extra: Mapping[str, str] | None = None, *,
         modes: Mapping[str, Run] | None = None, max_bytes: int = SHIPPED_MAX_BYTES) -> Run:
    """Copy the finished ``run``, with a finished run for every input set, to ``dest`` as a shipped model (module
    docstring), and each run of ``modes`` (mode -> run, not the balanced one) to ``dest/quality/<mode>``: each
    variant's :func:`shipped_files`, each record's shard set path made relative to the copy and :data:`SHIPPED`
    added, and ``extra`` (file name -> text: the card) at its top. Refused (KpcnError, one line) for a run
    :func:`shippable_records` refuses, or a copy that would exceed ``max_bytes`` (``config.SHIPPED_MAX_BYTES``: a
    shipped model is kept in git), or a ``dest`` that :func:`check_ship_destination` refuses. Written under a
    temporary name and renamed: ``dest`` is the earlier shipped model or the new one, whole (a kill between the
    two renames that replace an earlier one leaves none, until shipped again). Every variant's lock is held while
    it is read, so no trainer writes it meanwhile."""
    new = Run(dest)
    sources = {DEFAULT_QUALITY: run, **(modes or {})}
    check_modes(run, dest, modes or {})  # before any lock: a lock would make the folder of a missing variant
    with ExitStack() as locks:
        held = set()
        for source in sources.values():
            for variant in source.variants():  # each variant has its own trainer, and lock; a run named twice once
                if variant.dir.resolve() not in held:
                    held.add(variant.dir.resolve())
                    locks.enter_context(variant.lock())
        copies = []  # (mode, its run, the variant, its record, its files, where in the model)
        for mode, source in sources.items():
            top = new.relative(new.quality_dir(mode))
            for variant, record in zip(source.variants(), shippable_records(source)):
                files = shipped_files(variant, record)
                for file in files:
                    variant.check_file(record, file)  # the copy is what training wrote
                where = os.path.normpath(os.path.join(top, os.path.relpath(variant.dir, source.dir)))
                copies.append((mode, source, variant, record, files, where))
        size = sum((c[2].dir / f).stat().st_size for c in copies for f in c[4])
        size += sum(len(text.encode()) for text in (extra or {}).values())
        if size > max_bytes:
            raise KpcnError(f"{run.dir}: a shipped model of {size / 2**20:.1f} MiB is over the "
                            f"{max_bytes / 2**20:.0f} MiB a model kept in git may have; train a smaller one")
        _write(new, copies, extra or {})
    return new


def _write(new: Run, copies: list, extra: Mapping[str, str]) -> None:
    """Write ``copies`` (:func:`ship`'s) and ``extra`` into a temporary folder beside ``new``, then rename it."""
    new.dir.parent.mkdir(parents=True, exist_ok=True)
    for stale in new.dir.parent.glob(f".{new.dir.name}.tmp-*"):  # a killed ship's
        shutil.rmtree(stale)
    tmp = Run(new.dir.with_name(f".{new.dir.name}.tmp-{os.getpid()}"))
    writing = new.dir  # what is being written, named as the model will hold it: what a failure names
    try:
        for mode, _, variant, record, files, where in copies:
            target = Run(tmp.dir / where)
            final = new.dir / where  # where the copy's record will be read from
            for file in files:
                writing = final / file
                (target.dir / file).parent.mkdir(parents=True, exist_ok=True)
                if file != RECORD:
                    shutil.copy2(variant.dir / file, target.dir / file)
            data = copy.deepcopy(dict(record.data))
            data["shards"] = {**data["shards"], "set_dir": os.path.relpath(
                os.path.abspath(variant.shard_set(record).dir), os.path.abspath(final))}
            data[SHIPPED] = _shipped_entry(mode, variant, record)
            writing = final / RECORD
            target.write_record(data)
        for name, text in extra.items():
            writing = new.dir / name
            (tmp.dir / name).write_text(text)
        writing = new.dir
        old = new.dir.with_name(f".{new.dir.name}.tmp-old-{os.getpid()}")
        if new.dir.exists():
            os.replace(new.dir, old)  # a folder is not replaced whole by one rename
        os.replace(tmp.dir, new.dir)
    except BaseException as exc:
        shutil.rmtree(tmp.dir, ignore_errors=True)
        # an OSError names the file it read as often as the one it wrote (shutil's copies name the source):
        # the line names what was being written; atomic_path's own line names the temporary copy
        cause = exc.__cause__ if isinstance(exc, KpcnError) else exc
        failure = write_failure(writing, cause) if isinstance(cause, OSError) else None
        if failure is not None:  # a full disk: one line naming the file
            raise failure from exc
        raise
    shutil.rmtree(old, ignore_errors=True)


__all__ = ["SHIPPED", "check_modes", "check_ship_destination", "ship", "shippable_records", "shipped_files"]
