"""Round 0 of a shard set: ``kpcn shards`` cuts ``round-000`` from each input's variance PDF, from every input
of both splits (:func:`build_shards`), whole or split in parts (``prep.parts``), and merges the parts.

- **The set knows its sources.** A rerun whose renders changed (added, removed, edited, moved between
  splits) rebuilds the set; one whose renders are the same keeps every shard whose checksum still matches,
  and the set's error rounds.
- **Nothing half-done is taken for done.** The manifest is rewritten after every shard with
  ``status: "building"`` and marked ``"complete"`` last.
- **One writer per set, or per part.** ``build_shards`` holds the set's lock; a second one waits, then
  finds the work done. Split in parts (``build_shards(part=)``), each part holds its own lock while it
  writes its shards, and the set's lock only to open the manifest and, last, to merge the parts' lists;
  the merged manifest is byte for byte the one a single process writes.
- **Bad input is found before anything is written** (``prep.shards.renders.find_sources``).
"""

from __future__ import annotations

import logging
import shutil
from dataclasses import dataclass

from prep import colour, features
from prep.auxiliary import check_method
from prep.errors import KpcnError
from prep.files import atomic_write_json, check_writable, read_json, remove_temporaries
from prep.parts import Part
from prep.shards.config import ShardConfig
from prep.shards.format import FORMAT, ShardError, config_hash_of, listed_checksum
from prep.shards.renders import find_sources, source_changes
from prep.shards.shardset import PARTS, OlderFormatError, ShardSet, content_key, round_name
from prep.shards.writer import RoundDraw, ShardSpec, shard_specs, write_round

log = logging.getLogger("kpcn")


@dataclass
class _Plan:
    """Everything ``build_shards`` will write, decided (and checked) before anything is."""

    config_hash: str
    content_key: str
    split: dict[str, list[str]]
    sources: list[dict]
    shards: list[ShardSpec]


def _plan(config: ShardConfig, sset: ShardSet) -> _Plan:
    """The sources found and checked (``find_sources``), the hashes that name the set, and the shard each
    patch goes to. Raises (naming the file or option) before any writing."""
    split, sources, streams = find_sources(config, sset)
    config_hash = config.content_hash()
    key = content_key(config_hash, sources)
    return _Plan(config_hash, key, split, sources, shard_specs(streams, config.patches_per_shard))


def _previous_manifest(sset: ShardSet, config: ShardConfig, plan: _Plan) -> dict | None:
    """The manifest of an earlier run of the same configuration (None if there is none to go on);
    ShardError if the folder holds a set of another configuration or format."""
    round_dir = sset.round_dir(0)
    if sset.manifest_path.is_file():
        try:
            manifest = sset.read_manifest()
        except OlderFormatError as exc:  # ours, of an older format: derived data, rebuilt in this one
            log.warning("%s; rebuilding the set", str(exc).split(";")[0])
            _empty_set(sset)
            return None
        except ShardError:
            raise  # a foreign format: not ours to overwrite
        except KpcnError as exc:  # a damaged manifest is derived data: rebuild rather than stop
            log.warning("%s; rebuilding the set", exc)
            manifest = None
        if manifest is not None and manifest.get("config_hash") != plan.config_hash:
            old, new = manifest.get("config", {}), config.to_dict()
            differ = [k for k in new if k not in ("command", "out_root", "render_root") and old.get(k) != new[k]]
            raise ShardError(
                f"{sset.manifest_path}: the set was made with another configuration (differs in "
                f"{', '.join(differ) or 'its options'}); remove {sset.dir} or choose another --set"
            )
        if manifest is not None:
            return manifest
    for existing in sorted(round_dir.glob("shard-*.h5")) if round_dir.is_dir() else ():
        found = config_hash_of(existing)
        if found is not None and found != plan.config_hash:
            raise ShardError(
                f"{existing}: written with another configuration; remove {sset.dir} or choose another --set"
            )
    return None


def build_shards(config: ShardConfig, *, progress: bool = True, workers: int | None = None,
                 part: Part = Part()) -> dict:
    """Cut round 0 of a shard set from a folder of renders; returns the manifest.

    ``workers``: processes that cut and write the shards (default :func:`shard_workers`); the set's files
    are the same for any number.

    ``part``: write only this part's share of the shards (``prep.parts``; a contiguous run of them), under
    the part's own lock, listing them in ``parts/<part>.json``; the part that finishes last (each checks,
    under the set's lock) merges the lists into the manifest, which is then byte for byte the one a single
    process writes. Until then the returned manifest has ``status: "building"``.

    Deterministic for a given config and renders. A rerun with the same renders keeps every shard that is
    whole (checksum as listed in the manifest or in any part's list) and writes the rest, so an interrupted
    run resumes, with any split, and keeps the set's error rounds; a rerun after the renders changed
    rebuilds the set (error rounds included); another configuration over an existing set is an error.
    """
    sset = ShardSet(config.set_dir)
    check_writable(sset.dir, "shard set folder (--out)", directory=True)
    check_method(config.auxiliaries, "--auxiliaries")
    plan = _plan(config, sset)
    with sset.lock():
        manifest = _open_manifest(sset, config, plan)
    mine = [plan.shards[i] for i in part.block(len(plan.shards))]
    with sset.lock(part):
        record = manifest if part.whole else {**manifest, "rounds": {
            **manifest["rounds"], round_name(0): {**manifest["rounds"][round_name(0)], "shards": []}}}
        record_path = sset.manifest_path if part.whole else sset.part_record_path(part)
        write_round(sset, config, record, 0, mine, RoundDraw(config, 0), config.command, progress, workers,
                    listed=_listed_round_zero(sset, manifest), shards_in_round=len(plan.shards),
                    record_path=record_path)
        if not part.whole:
            record["status"] = "complete"
            atomic_write_json(record_path, record)
    with sset.lock():
        return _merge_round_zero(sset, manifest, record, part, len(plan.shards))


def _empty_set(sset: ShardSet) -> None:
    """Remove every round and part list of a set whose shards are not to be kept (the manifest is rewritten)."""
    for old in [*sorted(sset.dir.glob("round-*")), sset.dir / PARTS]:
        if old.is_dir():
            shutil.rmtree(old)


def _open_manifest(sset: ShardSet, config: ShardConfig, plan: _Plan) -> dict:
    """The manifest this run builds round 0 into, the set's lock held: the set's error rounds and round 0's
    listed shards are kept when the renders are the same; the set is emptied when they changed. A new
    manifest is written at once (``status: "building"``), so that a part starting later finds the set as
    this one left it rather than rebuilding it again."""
    previous = _previous_manifest(sset, config, plan)
    if previous is not None and previous.get("content_key") != plan.content_key:
        log.warning("%s: renders changed since the set was written (%s); rebuilding it", sset.dir,
                    source_changes(previous.get("sources", []), plan.sources))
        previous = None
        _empty_set(sset)
    remove_temporaries(sset.dir)
    first = round_name(0)
    rounds = dict((previous or {}).get("rounds", {}))
    listed = rounds.pop(first, {}).get("shards", [])
    manifest = {
        "format": FORMAT,
        "status": "building",
        "set": config.set_name,
        "config": config.to_dict(),
        "config_hash": plan.config_hash,
        "content_key": plan.content_key,
        "features": list(features.FEATURE_NAMES),
        "constants": dict(colour.CONSTANTS),
        "patch_size": config.patch_size,
        "split": plan.split,
        "sources": plan.sources,
        "rounds": {first: {"kind": "variance", "status": "building", "patches_per_image": config.patches_per_image,
                           "shards": listed}, **rounds},
    }
    if previous is None:
        atomic_write_json(sset.manifest_path, manifest)
    return manifest


def _part_lists(sset: ShardSet, content_key: str) -> dict[str, dict]:
    """The parts' lists in the set (file name -> list) made from the same renders and options. A list that
    cannot be read is derived data: it is left out with a warning, and its shards are checked or written
    again."""
    lists = {}
    for path in sset.part_records():
        try:
            other = read_json(path, "shard part list", keys=("content_key", "rounds", "status"))
        except KpcnError as exc:
            log.warning("%s; ignoring it", exc)
            continue
        if other["content_key"] == content_key:
            lists[path.name] = other
    return lists


def _round_zero_shards(listing: dict) -> list[dict]:
    return listing["rounds"].get(round_name(0), {}).get("shards", [])


def _listed_round_zero(sset: ShardSet, manifest: dict) -> dict[str, tuple[str, str]]:
    """Round 0's shards that the manifest or any part's list (of any split of the work, with the same
    renders and options) gives a checksum for: stored path -> checksum. Each is kept only if the file still
    has it, so a list left by a killed or stale part is safe to take."""
    entries = _round_zero_shards(manifest)
    for other in _part_lists(sset, manifest["content_key"]).values():
        entries = entries + _round_zero_shards(other)
    return {s["path"]: listed_checksum(s) for s in entries}


def _merge_round_zero(sset: ShardSet, manifest: dict, record: dict, part: Part, count: int) -> dict:
    """Finish round 0, the set's lock held, once every part of the split of ``part`` has listed its shards
    (at once for the whole work): the manifest lists them all, in order, and is marked complete, and the
    parts' lists are removed. Returns the manifest, still ``building`` while parts are missing."""
    first = round_name(0)
    if part.whole:
        shards = record["rounds"][first]["shards"]
    else:
        done = {name: _round_zero_shards(other) for name, other in _part_lists(sset, manifest["content_key"]).items()
                if other["status"] == "complete"}
        labels = [Part(i, part.count).label for i in range(part.count)]
        missing = [str(Part(i, part.count)) for i, label in enumerate(labels) if f"{label}.json" not in done]
        current = sset.read_manifest() if sset.manifest_path.is_file() else manifest
        if current.get("content_key") != manifest["content_key"]:
            current = manifest  # rebuilt from other renders meanwhile: nothing of it is this set's
        if missing and current["status"] == "complete":
            sset.part_record_path(part).unlink(missing_ok=True)
            return current  # a part run again on a finished set: it found its shards whole
        if missing:
            log.info("%s: part %s written; the set is complete once part%s %s %s", sset.dir, part,
                     "s" if len(missing) > 1 else "", ", ".join(missing), "are" if len(missing) > 1 else "is")
            return manifest
        shards = [s for label in labels for s in done[f"{label}.json"]]
        # the set's error rounds as the manifest lists them now, round 0 as the parts wrote it
        manifest = {**manifest, "rounds": {**current["rounds"], first: manifest["rounds"][first]}}
    if len(shards) != count:
        raise ShardError(f"{sset.dir}: the parts list {len(shards)} shards of round 0, the set has {count}")
    manifest["rounds"][first] = {**manifest["rounds"][first], "shards": shards, "status": "complete"}
    manifest["status"] = "complete"
    atomic_write_json(sset.manifest_path, manifest)
    if (sset.dir / PARTS).is_dir():
        shutil.rmtree(sset.dir / PARTS)
    return manifest
