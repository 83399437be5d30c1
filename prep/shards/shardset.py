"""The folder of one shard set, its manifest and its rounds: :class:`ShardSet` is the one owner of its layout::

    <set>/manifest.json             sources (with SHA-256), split, configuration, every round and shard (with
                                    its CRC-32)
    <set>/.lock                     held by the one process that writes the set
    <set>/round-<k>/shard-<i>.h5    up to ``patches_per_shard`` patches of one split (train or val)
    <set>/round-<k>/plan.npz        an error round's positions, drawn before its shards are cut (k >= 1)
    <set>/parts/part-<i>-of-<N>.json   round 0's shards that part i of N wrote (``prep.parts``), until the merge
    <set>/.lock-part-<i>-of-<N>     held by the process that writes part i of N
    <set>/figures/                  ``kpcn figures --set``'s PNGs (``prep.figures``): read by nothing here

A round's name is made here (:func:`round_name`), as the set's folders are. A round's entry has a ``status``;
readers take only complete rounds, so a set whose round k is being written stays usable with rounds 0..k-1.

Guarantees to readers, by construction:

- **The set knows its sources.** Every render is listed with its SHA-256; the *content key*
  (:func:`content_key`) hashes them with the configuration. A render replaced since the set was cut is
  found (:meth:`ShardSet.check_renders`).
- **Nothing half-done is taken for done.** The writers mark the manifest ``"complete"`` last. Readers
  (:meth:`ShardSet.verified_shards`) accept only a complete manifest and shards whose checksum matches it
  (``prep.shards.format.SHARD_CHECKSUMS``), and whose attributes and shapes say what the manifest says of
  them (patch size, patch count, configuration, content key): a hand-edited manifest is refused.
- **One writer per set, or per part**: :meth:`ShardSet.lock` is the set's lock (held to change the
  manifest), or a part's (held while it writes its shards).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

from prep.files import (
    atomic_path,
    atomic_write_json,
    check_writable,
    exclusive_lock,
    read_json,
    remove_temporaries,
    sha256_file,
)
from prep.inputs import FULL
from prep.parts import Part
from prep.shards.config import shard_set_dir
from prep.shards.format import (
    FORMAT,
    ShardError,
    listed_checksum,
    older_format,
    open_shard,
    rebuild_command,
    shard_intact,
)

MANIFEST = "manifest.json"
PARTS = "parts"
SPLITS = ("train", "val")
ROUND_RE = re.compile(r"^round-(\d{3,})$")
PLAN = "plan.npz"


class OlderFormatError(ShardError):
    """A set of an older ``kpcn-shard`` format: refused by readers, rebuilt by ``kpcn shards``."""


def round_name(k: int) -> str:
    """The folder (and manifest key) of sampling round ``k``: ``round-000`` is variance sampling, later rounds
    error-based. The one place a round's name is made; :func:`round_index` reads it back."""
    return f"round-{int(k):03d}"


def round_index(name: str) -> int:
    """Inverse of :func:`round_name`."""
    match = ROUND_RE.match(name)
    if not match:
        raise ShardError(f"{name!r} is not a round name (round-NNN)")
    return int(match.group(1))


def content_key(config_hash: str, sources: list[dict]) -> str:
    """The set's content key: its format, configuration and every source's identity (what, where in the
    split, with how many patches, and the render's SHA-256) hashed together."""
    identity = [{k: s[k] for k in ("scene", "spp", "role", "split", "sha256", "patches")} for s in sources]
    return hashlib.sha256(json.dumps([FORMAT, config_hash, identity], sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class ShardEntry:
    """One shard as the manifest lists it; ``path`` is resolved against the set folder."""

    path: Path
    round: str
    split: str
    patches: int
    checksum: tuple[str, str]  # (algorithm of SHARD_CHECKSUMS, hex digest)

    def intact(self) -> bool:
        """Whether the file's checksum is still the listed one."""
        return shard_intact(self.path, self.checksum)


class ShardSet:
    """The folder of one shard set: its manifest, rounds, shards, lock and source paths."""

    def __init__(self, set_dir: str | os.PathLike):
        self.dir = Path(set_dir)

    @classmethod
    def named(cls, out_root: str | os.PathLike, set_name: str, inputs: str = FULL.name) -> ShardSet:
        """The set ``set_name`` cut for ``inputs`` under ``out_root`` (:func:`~prep.shards.config.shard_set_dir`),
        so that no reader retypes where a set lives."""
        return cls(shard_set_dir(out_root, set_name, inputs))

    @property
    def manifest_path(self) -> Path:
        return self.dir / MANIFEST

    def round_dir(self, k: int) -> Path:
        return self.dir / round_name(k)

    @property
    def figures_dir(self) -> Path:
        return self.dir / "figures"

    def lock(self, part: Part = Part()):
        """The set's lock (held to change the manifest), or the lock of ``part`` (held while it writes its shards)."""
        return exclusive_lock(self.dir, "shard set" if part.whole else f"part {part} of shard set", part.lock_name)

    def part_record_path(self, part: Part) -> Path:
        """Where ``part`` of a split ``kpcn shards`` lists the shards it wrote, until the merge."""
        return self.dir / PARTS / f"{part.label}.json"

    def part_records(self) -> list[Path]:
        return sorted((self.dir / PARTS).glob("part-*-of-*.json"))

    def relative(self, path: str | os.PathLike) -> str:
        """``path`` as stored in the manifest: relative to the set folder, so the tree can move."""
        return os.path.relpath(os.path.abspath(path), os.path.abspath(self.dir))

    def resolve(self, stored: str) -> Path:
        """Inverse of :meth:`relative`."""
        return Path(os.path.normpath(self.dir / stored))

    def read_manifest(self) -> dict:
        """The manifest, whatever its status; ShardError naming it if missing, broken or foreign."""
        if not self.manifest_path.is_file():
            raise ShardError(f"{self.manifest_path}: no shard manifest (run 'kpcn shards' first)")
        manifest = read_json(self.manifest_path, "shard manifest", keys=("format", "status", "rounds", "sources"))
        if older_format(manifest["format"]):
            raise OlderFormatError(
                f"{self.manifest_path}: a shard set of format {manifest['format']!r}, this kpcn reads {FORMAT!r}; "
                f"rebuild it with {rebuild_command(manifest.get('config'))}"
            )
        if manifest["format"] != FORMAT:
            raise ShardError(
                f"{self.manifest_path}: shard set of format {manifest['format']!r}, this kpcn reads {FORMAT!r}; "
                f"remove {self.dir} and run 'kpcn shards' again"
            )
        return manifest

    def complete_manifest(self) -> dict:
        """The manifest of a finished set; ShardError if ``kpcn shards`` did not finish it."""
        manifest = self.read_manifest()
        if manifest["status"] != "complete":
            raise ShardError(
                f"{self.manifest_path}: the shard set is incomplete (status {manifest['status']!r}: 'kpcn shards' "
                "was interrupted, is still running, or has parts of a split still to run); run it again to "
                "finish the set"
            )
        return manifest

    @staticmethod
    def complete_rounds(manifest: dict) -> list[int]:
        """The rounds of ``manifest`` whose shards are all written, in order. (A round entry without a status
        was written before rounds had one: it is as complete as the set.)"""
        return sorted(round_index(name) for name, rnd in manifest["rounds"].items()
                      if rnd.get("status", manifest["status"]) == "complete")

    def entries(self, manifest: dict, split: str, rounds=None) -> list[ShardEntry]:
        """The shards of ``split`` that ``manifest`` lists in ``rounds`` (default: every complete round), in order."""
        rounds = self.complete_rounds(manifest) if rounds is None else sorted(rounds)
        names = [round_name(k) for k in rounds]
        missing = [n for n in names if n not in manifest["rounds"]]
        if missing:
            raise ShardError(f"{self.manifest_path}: the set has no {', '.join(missing)} "
                             f"(its rounds: {', '.join(sorted(manifest['rounds'])) or 'none'})")
        return [
            ShardEntry(self.resolve(s["path"]), name, s["split"], int(s["patches"]), listed_checksum(s))
            for name in names
            for s in manifest["rounds"][name]["shards"]
            if s["split"] == split
        ]

    def verified_shards(self, split: str, manifest: dict | None = None, rounds=None) -> list[ShardEntry]:
        """The shards of ``split`` in ``rounds`` (default: every complete round) of a complete set, each present
        with the checksum the manifest lists."""
        manifest = manifest or self.complete_manifest()
        entries = self.entries(manifest, split, rounds)
        for entry in entries:
            if not entry.path.is_file():
                raise ShardError(f"{entry.path}: listed in {self.manifest_path} but missing; "
                                 "run 'kpcn shards' again to rebuild it")
            if not entry.intact():
                raise ShardError(
                    f"{entry.path}: its checksum ({entry.checksum[0]}) differs from the one in {self.manifest_path} "
                    "(the file changed after it was written); run 'kpcn shards' again to rebuild it"
                )
            self._check_claims(manifest, entry)
        return entries

    def check_renders(self, manifest: dict) -> None:
        """ShardError naming the first source render that is where the manifest says but no longer has the
        SHA-256 it lists (a render replaced since the set was cut: the shards are stale). A render that is not
        there is not an error: a set can be moved or copied without its renders, and is then trusted as it
        is. Every present render is hashed, every time: for the default set's 195 MB of renders that is a second at
        most, less than ``kpcn train`` spends importing torch, and a size-and-mtime shortcut would need a record
        kept beside a set that may be read-only, or moved with new mtimes."""
        for source in manifest["sources"]:
            path = self.resolve(source["path"])
            if path.is_file() and sha256_file(path) != source["sha256"]:
                config = manifest.get("config", {})
                raise ShardError(
                    f"{path}: changed since the shard set {self.dir} was cut from it (its SHA-256 is not the one "
                    f"{self.manifest_path} lists); 'kpcn shards --set {config.get('set_name', self.dir.name)}' "
                    f"with the set's options rebuilds the set ({config.get('command') or 'kpcn shards'})"
                )

    def _check_claims(self, manifest: dict, entry: ShardEntry) -> None:
        """ShardError naming the manifest and its field unless what it says of ``entry`` (a shard whose checksum
        matched: its own attributes and shapes are what was written) is what the shard holds: the patch size,
        the shard's patch count, the configuration and its hash, the features and the content key (which
        covers the sources' patch counts and checksums, recomputed from the manifest's lists)."""
        try:
            with open_shard(entry.path) as f:
                found = {"patch_size": int(f.attrs["patch_size"]), "shape": f["diffuse/reference"].shape[1:3],
                         "patches": len(f["source"]), "config": json.loads(f.attrs["config"]),
                         "config_hash": f.attrs["config_hash"], "content_key": f.attrs["content_key"],
                         "features": json.loads(f.attrs["features"])}
        except (KeyError, OSError, ValueError) as exc:
            raise ShardError(f"{entry.path}: damaged shard attributes ({type(exc).__name__}: {exc})") from None
        config = manifest.get("config", {})
        size = manifest.get("patch_size")
        claims = [("patch_size", size, found["patch_size"]),
                  ("patch_size", (size, size), tuple(int(n) for n in found["shape"])),
                  (f"patches of {self.relative(entry.path)}", entry.patches, found["patches"]),
                  *((f"config.{k}", config.get(k), v) for k, v in found["config"].items()
                    if k not in ("command", "out_root", "render_root")),
                  ("config_hash", manifest.get("config_hash"), found["config_hash"]),
                  ("features", manifest.get("features"), found["features"]),
                  ("content_key", manifest.get("content_key"), found["content_key"])]
        try:
            key = content_key(manifest["config_hash"], manifest["sources"])
        except (KeyError, TypeError) as exc:
            key = f"none ({type(exc).__name__}: {exc})"
        claims.append(("sources (their patches and checksums)", key, found["content_key"]))
        for field_name, claimed, held in claims:
            if claimed != held:
                raise ShardError(
                    f"{self.manifest_path}: its {field_name} ({claimed!r}) is not what {entry.path.name} of "
                    f"{entry.round} holds ({held!r}): the manifest was edited; run 'kpcn shards' again to rewrite it"
                )

    def fork(self, dest: str | os.PathLike, rounds=(0,)) -> ShardSet:
        """A new set in ``dest`` holding ``rounds`` of this complete set (hard links where the file system allows,
        else copies; shard files are never written in place, so the two sets cannot change each other's) and a
        manifest listing only them, with source paths rebased; later rounds are the new set's own. A ``dest``
        that already holds a complete fork of the same set is returned as it is."""
        manifest = self.complete_manifest()
        new = ShardSet(dest)
        if new.manifest_path.is_file():
            found = new.complete_manifest()
            if found["content_key"] != manifest["content_key"]:
                raise ShardError(f"{new.dir}: holds another shard set; remove it or choose another folder")
            return new
        names = [round_name(k) for k in rounds]
        check_writable(new.dir, "shard set folder", directory=True)
        with new.lock():
            remove_temporaries(new.dir)
            forked = json.loads(json.dumps(manifest))
            forked["rounds"] = {}
            for name in names:
                if name not in manifest["rounds"]:
                    raise ShardError(f"{self.manifest_path}: has no {name} to fork")
                entry = forked["rounds"][name] = json.loads(json.dumps(manifest["rounds"][name]))
                for listed in entry["shards"] + ([entry["plan"]] if "plan" in entry else []):
                    source = self.resolve(listed["path"])
                    target = new.dir / name / source.name
                    if not target.is_file():
                        with atomic_path(target) as tmp:
                            try:
                                os.link(source, tmp)
                            except OSError:
                                shutil.copyfile(source, tmp)
                    listed["path"] = new.relative(target)
            for source in forked["sources"]:
                source["path"] = new.relative(self.resolve(source["path"]))
            atomic_write_json(new.manifest_path, forked)
        return new

    def pairs(self, manifest: dict, split: str) -> list[tuple[Path, Path]]:
        """(noisy input, reference) render paths of the scenes of ``split``."""
        refs = {s["scene"]: self.resolve(s["path"]) for s in manifest["sources"] if s["role"] == "reference"}
        return [
            (self.resolve(s["path"]), refs[s["scene"]])
            for s in manifest["sources"]
            if s["role"] == "input" and s["split"] == split
        ]


def shard_paths(set_dir: str | os.PathLike, split: str) -> list[Path]:
    """The verified shard files of ``split`` of the complete set in ``set_dir``, every round."""
    return [e.path for e in ShardSet(set_dir).verified_shards(split)]
