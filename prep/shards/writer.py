"""Writing one round's shards (:func:`write_round`), for round 0 (``prep.shards.build``) and error rounds
(``prep.shards.rounds``) alike.

A round's patches are dealt into shards in order (:func:`shard_specs`); each shard is cut and written whole,
atomically, and listed in the manifest (or a part's list) with its checksum as soon as it is written, so an
interrupted round resumes: a shard whose file still has its listed checksum is kept, the others are
written again.

- **Bounded memory**: a shard is assembled from one image at a time; each worker process holds one
  shard's patches (:func:`shard_workers` of them: the thread count).
- **Parallel, and the same files**: shards are cut and written by worker processes, one shard at a time
  each; which process writes a shard, and how many there are, changes none of its bytes.
"""

from __future__ import annotations

import json
import multiprocessing
import os
import sys
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from prep import colour, exr, features, threads
from prep.auxiliary import RAW
from prep.bounds import is_integer
from prep.errors import OptionError
from prep.files import atomic_write_json, remove_temporaries
from prep.inputs import InputSet
from prep.processes import LINUX, die_with_parent
from prep.shards.config import ShardConfig
from prep.shards.format import (
    FORMAT,
    SHARD_RE,
    empty_patches,
    listed_checksum,
    shard_checksum,
    shard_intact,
    shard_name,
    write_shard,
)
from prep.shards.patches import ImagePatches, draw, noisy_variances, round_pdf, shard_layers
from prep.shards.renders import reference_of
from prep.shards.shardset import SPLITS, ShardSet, round_name


@dataclass
class ShardSpec:
    """Shard ``index`` of a round, of one split: the runs of its inputs' draws it holds, in order."""

    index: int
    split: str
    pieces: list[tuple[int, int, int]]  # (source id, first patch, end patch) of that source's draw order

    @property
    def patches(self) -> int:
        return sum(b - a for _, a, b in self.pieces)


def shard_specs(streams: list[tuple[str, int, int]], per_shard: int) -> list[ShardSpec]:
    """The shards of one round: ``streams`` lists (split, source id, patches) in order; each split's patches
    fill shards of ``per_shard`` in that order, an input spanning consecutive shards."""
    shards: list[ShardSpec] = []
    for split_name in SPLITS:
        current: ShardSpec | None = None
        for split, source_id, count in streams:
            if split != split_name:
                continue
            start = 0
            while start < count:
                if current is None or current.patches == per_shard:
                    current = ShardSpec(len(shards), split_name, [])
                    shards.append(current)
                take = min(count - start, per_shard - current.patches)
                current.pieces.append((source_id, start, start + take))
                start += take
    return shards


def write_round(sset: ShardSet, config: ShardConfig, manifest: dict, k: int, specs: list[ShardSpec],
                draw_of: RoundDraw, command: str, progress: bool, workers: int | None, *,
                listed: dict[str, tuple[str, str]] | None = None, shards_in_round: int | None = None,
                record_path: Path | None = None) -> None:
    """Write the shards of round ``k`` (``specs``) that are not already whole, the lock of their writer held.

    ``draw_of`` gives an input's positions and their PDF values (the round's draw). A shard whose checksum
    ``listed`` gives (stored path -> checksum; default: the round's manifest entry) and whose file still
    has it is kept; the others are (re)written, each atomically, and ``manifest`` is rewritten to
    ``record_path`` (default: the set's manifest) after each. Shard files numbered past the round's
    ``shards_in_round`` (default: ``len(specs)``) are removed. The shards are cut and written by
    ``workers`` processes (None: :func:`shard_workers`; 1: this one), :class:`_RoundWriter`; a shard's bytes
    do not depend on which process wrote it, nor on how many there were.
    """
    from tqdm import tqdm

    entry = manifest["rounds"][round_name(k)]
    record_path = sset.manifest_path if record_path is None else record_path
    round_dir = sset.round_dir(k)
    round_dir.mkdir(parents=True, exist_ok=True)
    shards_in_round = len(specs) if shards_in_round is None else shards_in_round
    # other parts of a split may be writing theirs
    remove_temporaries(round_dir, None if len(specs) == shards_in_round else {shard_name(s.index) for s in specs})
    if record_path.parent.is_dir():
        remove_temporaries(record_path.parent, targets={record_path.name})
    if listed is None:
        listed = {s["path"]: listed_checksum(s) for s in entry["shards"]}
    written: dict[int, dict] = {}
    todo = []
    for spec in specs:
        path = round_dir / shard_name(spec.index)
        rel = sset.relative(path)
        if rel in listed and path.is_file() and shard_intact(path, listed[rel]):
            written[spec.index] = _entry(sset, path, spec, listed[rel])
        else:
            todo.append(spec)
    for extra in round_dir.glob("shard-*.h5"):
        match = SHARD_RE.match(extra.name)
        if match and int(match.group(1)) >= shards_in_round:
            extra.unlink(missing_ok=True)  # parts of a split find the same extras
    entry["shards"] = [written[i] for i in sorted(written)]
    atomic_write_json(record_path, manifest)

    writer = _RoundWriter(str(sset.dir), manifest["sources"], k, config.patch_size, draw_of,
                          _shard_attrs(config, manifest, command), config.input_set, config.auxiliaries)

    def record(spec: ShardSpec, checksum: tuple[str, str]) -> None:
        written[spec.index] = _entry(sset, round_dir / shard_name(spec.index), spec, checksum)
        entry["shards"] = [written[i] for i in sorted(written)]
        atomic_write_json(record_path, manifest)
        bar.update(1)

    workers = min(shard_workers() if workers is None else _check_workers(workers), len(todo))
    with tqdm(total=len(todo), desc=f"shards {round_name(k)}", unit="shard", disable=not progress) as bar:
        if workers <= 1:
            for spec in todo:
                record(spec, writer.write(spec))
            return
        pool = ProcessPoolExecutor(workers, mp_context=_worker_context(writer.auxiliaries), initializer=_start_worker,
                                   initargs=(writer, os.getpid()))
        try:
            jobs = {pool.submit(_write_in_worker, spec): spec for spec in todo}
            for job in as_completed(jobs):
                record(jobs[job], job.result())
        finally:
            # on an error or an interrupt, shards not yet started are not started; the temporary file of one
            # being written is removed by its worker (atomic_path), or by the next run (remove_temporaries)
            pool.shutdown(wait=True, cancel_futures=True)


def _check_workers(workers) -> int:
    if not is_integer(workers) or workers < 1:
        raise OptionError("workers", f"must be an integer >= 1, got {workers!r}")
    return workers


def shard_workers() -> int:
    """How many processes cut and write shards: the thread count the user set (``prep.threads``), else 1.
    Processes, not threads: writing HDF5 holds the GIL, and the rest of a shard's work needs it too."""
    return threads.requested() or 1


@dataclass(frozen=True)
class RoundDraw:
    """An input's positions in round ``k`` and each one's PDF value: drawn from the variance PDF in round 0
    (:func:`round_pdf`, :func:`draw`), looked up in the error round's plan (source id -> (positions, pdf))
    otherwise. A value, not a closure, so that worker processes can be given it."""

    config: ShardConfig
    k: int
    plan: dict[int, tuple[np.ndarray, np.ndarray]] | None = None

    def __call__(self, source_id: int, noisy: dict, reference: dict) -> tuple[np.ndarray, np.ndarray]:
        if self.plan is None:
            return draw(round_pdf(noisy, self.config, reference=reference), self.config.patches_per_image,
                        self.config, source_id, self.k)
        return self.plan[source_id]


@dataclass
class _RoundWriter:
    """Cuts and writes one shard of a round at a time: what each worker process is started with.

    It keeps, between shards, the :class:`ImagePatches` of the input it cut last (an input spans at most a
    few consecutive shards) with its reference, and one shard buffer (reused: allocating it per shard
    costs its page faults each time). The positions are drawn from the render as read, the patches cut
    from the layers of the set's ``inputs`` and ``auxiliaries`` (``prep.shards.patches.shard_layers``)."""

    set_dir: str
    sources: list[dict]
    k: int
    patch_size: int
    draw_of: RoundDraw
    attrs: dict
    inputs: InputSet = InputSet()
    auxiliaries: str = RAW
    _current: ImagePatches | None = field(default=None, repr=False)
    _reference: tuple[str, dict] | None = field(default=None, repr=False)
    _buffer: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "_current": None, "_reference": None, "_buffer": None}

    def write(self, spec: ShardSpec) -> tuple[str, str]:
        """Cut shard ``spec``, write it atomically; returns its checksum (:func:`shard_checksum`)."""
        if self._buffer is None or len(self._buffer["source"]) < spec.patches:
            self._buffer = None
            self._buffer = empty_patches(spec.patches, self.patch_size)
        arrays = {name: buffer[: spec.patches] for name, buffer in self._buffer.items()}
        at = 0
        for source_id, a, b in spec.pieces:
            self._image(source_id).cut_into(a, b, arrays, at)
            at += b - a
        path = ShardSet(self.set_dir).round_dir(self.k) / shard_name(spec.index)
        write_shard(path, arrays, {**self.attrs, "split": spec.split})
        return shard_checksum(path)

    def _image(self, source_id: int) -> ImagePatches:
        if self._current is None or self._current.source_id != source_id:
            sset = ShardSet(self.set_dir)
            src = self.sources[source_id]
            ref_path = reference_of(self.sources, src)["path"]
            if self._reference is None or self._reference[0] != ref_path:
                self._reference = None
                self._reference = (ref_path, exr.read_aovs(sset.resolve(ref_path), variances=None))
            noisy = exr.read_aovs(sset.resolve(src["path"]), variances=noisy_variances(self.inputs))
            self._current = None  # free the previous image before the next is cut
            positions, pdf = self.draw_of(source_id, noisy, self._reference[1])
            layers = shard_layers(noisy, self._reference[1], self.inputs, self.auxiliaries)
            self._current = ImagePatches.at(*layers, positions, pdf,
                                            source_id=source_id, round=self.k, patch_size=self.patch_size)
        return self._current


_worker: _RoundWriter | None = None


def _worker_context(auxiliaries: str = RAW):
    """fork where torch is not loaded (``kpcn shards``: prep never imports it), spawn where it is (an error
    round cut by ``kpcn resample``). A forked worker starts in milliseconds with everything imported; a
    spawned one imports and loads the features kernel again (~0.6 s of CPU each, a sixth of a default set
    here), but a fork copies torch's thread pools half-made. The workers of a raw set run no parallel region
    of numba's or anyone's, so the idle OpenMP threads of ``prep.threads`` that a fork leaves behind are never
    waited on; those of a set with prefiltered ``auxiliaries`` do (the NLM filter's numba loops, OIDN's
    threads), and GNU OpenMP aborts a forked child that enters one: spawn, whose cost the prefilter's dwarfs.
    spawn on every system but Linux: Windows cannot fork, and macOS's system libraries are not safe across one."""
    fork = LINUX and "torch" not in sys.modules and auxiliaries == RAW
    return multiprocessing.get_context("fork" if fork else "spawn")


def _start_worker(writer: _RoundWriter, parent: int) -> None:
    global _worker
    die_with_parent(parent)  # a killed `kpcn shards` leaves no worker writing on
    _worker = writer
    threads.set_threads(1)  # one process per core already


def _write_in_worker(spec: ShardSpec) -> tuple[str, str]:
    return _worker.write(spec)


def _entry(sset: ShardSet, path: Path, spec: ShardSpec, checksum: tuple[str, str]) -> dict:
    algorithm, digest = checksum
    return {"path": sset.relative(path), "split": spec.split, "patches": spec.patches, algorithm: digest}


def _shard_attrs(config: ShardConfig, manifest: dict, command: str) -> dict:
    return {
        "format": FORMAT,
        "patch_size": config.patch_size,
        "features": json.dumps(list(features.FEATURE_NAMES)),
        "transforms": colour.DESCRIPTION,
        "constants": json.dumps(colour.CONSTANTS),
        "sources": json.dumps([{k: s[k] for k in ("scene", "spp", "path")} for s in manifest["sources"]]),
        "config": json.dumps(config.to_dict()),
        "config_hash": manifest["config_hash"],
        "content_key": manifest["content_key"],
        "command": command or " ".join(sys.argv),
    }
