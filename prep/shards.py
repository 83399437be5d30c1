"""65x65 training patches in HDF5 shards (docs/formats.md §4).

A shard set is the folder ``<out_root>/<set>/``; :class:`ShardSet` is the one owner of its layout::

    <set>/manifest.json             sources (with SHA-256), split, configuration, every round and shard (with its CRC-32)
    <set>/.lock                     held by the one process that writes the set
    <set>/round-<k>/shard-<i>.h5    up to ``patches_per_shard`` patches of one split (train or val)
    <set>/round-<k>/plan.npz        an error round's positions, drawn before its shards are cut (k >= 1)
    <set>/parts/part-<i>-of-<N>.json   round 0's shards that part i of N wrote (``prep.parts``), until the merge
    <set>/.lock-part-<i>-of-<N>     held by the process that writes part i of N

**Rounds.** ``round-000`` is cut by ``kpcn shards`` from each input's variance PDF (:func:`build_shards`),
from every input of both splits. Round k >= 1 is an *error round* (docs/method.md §8,
:func:`build_error_round`): from every training input, positions drawn from the PDF of a model's per-pixel
error mixed with the variance PDF, never at a position an earlier round used; its manifest entry keeps
its provenance (the model's files with their SHA-256, the error metric, the mix weight). Every round goes
through the same per-image step (:func:`round_pdf` → :func:`draw` → :class:`ImagePatches` → a shard) and the
same writer. A round's entry has a ``status``; readers take only complete rounds, so a set whose round k
is being written stays usable with rounds 0..k-1. Held-out scenes are never resampled.

Each shard stores one patch per HDF5 chunk, uncompressed, each chunk with a Fletcher-32 checksum (the layout
:data:`SHARD_LAYOUT`; why not gzip, lzf or float16: :data:`LAYOUTS`), in these datasets (N patches,
P = patch size, channels last, float32):

=======================  ===============  ===============================================
dataset                  shape            content
=======================  ===============  ===============================================
diffuse/features         (N, P, P, 27)    network input of the diffuse branch
specular/features        (N, P, P, 27)    network input of the specular branch
diffuse/noisy            (N, P, P, 3)     noisy colour in the branch's log domain
diffuse/reference        (N, P, P, 3)     reference colour in the branch's log domain
specular/noisy           (N, P, P, 3)     likewise, specular
specular/reference       (N, P, P, 3)
albedo                   (N, P, P, 3)     noisy albedo (rebuilds the final colour)
noisy                    (N, P, P, 3)     noisy final colour, linear
reference                (N, P, P, 3)     reference final colour, linear
source                   (N,) int32       index into the manifest's (and the ``sources`` attribute's) sources
position                 (N, 2) int32     top-left (y, x) in the source render
round                    (N,) int32       sampling round
pdf                      (N,) float64     probability of the position under the round's PDF
=======================  ===============  ===============================================

The reference diffuse colour is divided by the reference's own albedo (a clean irradiance target).

Guarantees, by construction:

- **The set knows its sources.** Every render is listed with its SHA-256; the *content key* hashes them
  with the configuration. A rerun whose renders changed (added, removed, edited, moved between splits)
  rebuilds the set; one whose renders are the same keeps every shard whose checksum still matches.
- **Nothing half-done is taken for done.** Shards are written with ``prep.files.atomic_path`` and marked
  ``complete`` inside; the manifest is rewritten after every shard with ``status: "building"`` and marked
  ``"complete"`` last. Readers (:meth:`ShardSet.verified_shards`) accept only a complete manifest and shards
  whose checksum matches it (:data:`SHARD_CHECKSUMS`), and whose attributes and shapes say what the manifest
  says of them (patch size, patch count, configuration, content key): a hand-edited manifest is refused. That check, not an fsync, is what makes a shard safe
  against a power cut (:func:`write_shard`).
- **One writer per set, or per part.** ``build_shards`` holds the set's lock; a second one waits, then
  finds the work done. Split in parts (``build_shards(part=)``), each part holds its own lock while it
  writes its shards, and the set's lock only to open the manifest and, last, to merge the parts' lists.
- **Bad input is found before anything is written**: every render's header (layers, size) and the options
  against every image are checked first.
- **Bounded memory**: a shard is assembled from one image at a time; each worker process holds one
  shard's patches (:func:`shard_workers` of them: the thread count).
- **Parallel, and the same files**: shards are cut and written by worker processes, one shard at a time
  each; which process writes a shard, and how many there are, changes none of its bytes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import multiprocessing
import os
import re
import shutil
import sys
import time
from collections import defaultdict
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
from h5py import h5s

from prep import exr, features, sampling, threads
from prep.bounds import PATCH_COUNT, SEED, Bound, bounded, check_fields
from prep.errors import KpcnError, OptionError
from prep.files import (
    atomic_path,
    atomic_write_json,
    check_set_name,
    check_writable,
    crc32_file,
    exclusive_lock,
    read_json,
    remove_temporaries,
    sha256_file,
)
from prep.parts import Part
from prep.processes import die_with_parent
from prep.render.frame import SPP

log = logging.getLogger("kpcn")

FORMAT = "kpcn-shard/2"
MANIFEST = "manifest.json"
PARTS = "parts"
SHARD_RE = re.compile(r"^shard-(\d{5})\.h5$")
SPLITS = ("train", "val")
PATCH_DATASETS = {
    "diffuse/features": features.NUM_FEATURES,
    "specular/features": features.NUM_FEATURES,
    "diffuse/noisy": 3,
    "diffuse/reference": 3,
    "specular/noisy": 3,
    "specular/reference": 3,
    "albedo": 3,
    "noisy": 3,
    "reference": 3,
}
# A shard is assembled in memory before it is written; this bounds that memory.
MAX_SHARD_BYTES = 2 << 30
# A shard's checksum, listed in the manifest and checked by every reader and by the next run, is there to
# find a torn or damaged shard, which CRC-32 does at 6.4 GB/s here against SHA-256's 1.9 (hashing a set of
# ~2.8 GB was a quarter of `kpcn shards` once shards were uncompressed). Sources and plans keep SHA-256: it
# names what a set was made from. The first algorithm is the one written; sets written before list SHA-256,
# which still verifies.
SHARD_CHECKSUMS = {"crc32": crc32_file, "sha256": sha256_file}


@dataclass(frozen=True)
class Layout:
    """How a shard's datasets are stored: HDF5 filters, patches per chunk (``None``: no chunks, each dataset
    one contiguous block, where a patch is one contiguous run of bytes), a Fletcher-32 checksum per chunk, and
    the storage type of the patch datasets (readers get float32 whatever it is: :func:`read_patch`)."""

    name: str
    compression: str | None = None
    compression_opts: int | None = None
    shuffle: bool = False
    patches_per_chunk: int | None = 1
    fletcher32: bool = True
    dtype: str = "float32"


# The layouts `prep.stage_costs.shard_layout_costs` measures side by side (docs/results.md §8 has the numbers).
# gzip (what shards were written with before) and lzf compress slower than the uncompressed bytes are
# written and hashed (for the manifest), and a training batch reads 4-8x slower from them. Several
# patches per chunk make a random patch read its whole chunk. float16 halves the bytes but not the time
# (the conversion), rounds the features at 5e-4 relative where the tests hold shards to the float64
# features at 1e-6, and overflows linear colours above 65504. Contiguous datasets (no chunks, so no
# Fletcher-32) read a batch ~4x faster but write slower: HDF5 spends ~3x the system time on them. The
# chunked ones keep a Fletcher-32 checksum per chunk, so a chunk damaged after the manifest's check is an
# error when read, not silent garbage: ~40 % of the HDF5 time of a write and 60 % of a batch read's.
LAYOUTS = {
    "gzip": Layout("gzip", compression="gzip", compression_opts=1, shuffle=True),
    "lzf": Layout("lzf", compression="lzf", shuffle=True),
    "none": Layout("none"),
    "contiguous": Layout("contiguous", patches_per_chunk=None, fletcher32=False),
    "none-8": Layout("none-8", patches_per_chunk=8),
    "float16": Layout("float16", dtype="float16"),
}
SHARD_LAYOUT = LAYOUTS["none"]


class ShardError(KpcnError, ValueError):
    """A shard or shard set that cannot be used; the message names the file and what was found."""


ROUND_RE = re.compile(r"^round-(\d{3,})$")
PLAN = "plan.npz"


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


def shard_name(i: int) -> str:
    return f"shard-{int(i):05d}.h5"


def patch_bytes(patch_size: int) -> int:
    """Bytes of one patch of every dataset in memory (float32)."""
    return 4 * patch_size * patch_size * sum(PATCH_DATASETS.values())


def empty_patches(count: int, patch_size: int) -> dict[str, np.ndarray]:
    """Uninitialised arrays of ``count`` patches of every dataset of the shard layout, to cut patches into."""
    out = {name: np.empty((count, patch_size, patch_size, channels), np.float32)
           for name, channels in PATCH_DATASETS.items()}
    out["source"] = np.empty(count, np.int32)
    out["position"] = np.empty((count, 2), np.int32)
    out["round"] = np.empty(count, np.int32)
    out["pdf"] = np.empty(count, np.float64)
    return out


# A patch is at least the smallest kernel that filters (3x3; models.KERNEL_SIZE) and at most 512 pixels a
# side, eight times the 65 of the papers; train refuses a kernel or receptive field that the set's patches
# do not hold (kpcn_keras.train.check_inputs).
PATCH_SIZE = Bound(3, 512)


@dataclass
class ShardConfig:
    """Configuration of ``kpcn shards``; saved in the manifest and in every shard."""

    set_name: str = "default"
    render_root: str = "data/renders"
    out_root: str = "shards"
    patch_size: int = bounded(65, PATCH_SIZE)
    patches_per_image: int = bounded(32, PATCH_COUNT)  # per input render: a ladder of three inputs gives 96 per scene
    patches_per_shard: int = bounded(256, PATCH_COUNT)
    val_fraction: float = bounded(0.25, Bound(0.0, 1.0, integer=False, high_open=True))
    val_scenes: tuple[str, ...] = bounded((), distinct=True)
    input_spp: int | None = bounded(None, SPP)
    colour_weight: float = 1.0
    normal_weight: float = 1.0
    # > 0: every position can be drawn, so the plan's check of patches_per_image against the positions of
    # each image is complete (with 0, an image without variance has none)
    uniform_mix: float = bounded(0.1, Bound(0.0, 1.0, integer=False, low_open=True))
    seed: int = bounded(0, SEED)
    command: str = field(default="", compare=False)

    def __post_init__(self):
        self.val_scenes = tuple(self.val_scenes)
        check_set_name(self.set_name)
        check_fields(self)
        if self.colour_weight < 0 or self.normal_weight < 0 or self.colour_weight + self.normal_weight <= 0:
            raise OptionError("colour_weight", f"and normal_weight must be >= 0 and not both 0, got "
                              f"{self.colour_weight} and {self.normal_weight}")
        shard_bytes = self.patches_per_shard * patch_bytes(self.patch_size)
        if shard_bytes > MAX_SHARD_BYTES:
            most = MAX_SHARD_BYTES // patch_bytes(self.patch_size)
            raise OptionError(
                "patches_per_shard",
                f"{self.patches_per_shard} would hold {shard_bytes / 2**30:.1f} GiB in memory per shard; "
                f"at patch size {self.patch_size} at most {most} fit in {MAX_SHARD_BYTES >> 30} GiB",
            )

    @property
    def render_dir(self) -> Path:
        return Path(self.render_root) / self.set_name

    @property
    def set_dir(self) -> Path:
        return Path(self.out_root) / self.set_name

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def content_hash(self) -> str:
        """Hash of the options that change the shards' content (not where files are, nor the command)."""
        d = self.to_dict()
        for location in ("command", "out_root", "render_root"):
            d.pop(location)
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Source:
    scene: str
    spp: int
    path: str


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

    @property
    def manifest_path(self) -> Path:
        return self.dir / MANIFEST

    def round_dir(self, k: int) -> Path:
        return self.dir / round_name(k)

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
                    f"{entry.path}: its checksum ({entry.checksum[0]}) differs from the one in {self.manifest_path} (the file changed "
                    "after it was written); run 'kpcn shards' again to rebuild it"
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
                found = {"patch_size": int(f.attrs["patch_size"]), "shape": f["diffuse/features"].shape[1:3],
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

    def fork(self, dest: str | os.PathLike, rounds=(0,)) -> "ShardSet":
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


def discover_renders(render_dir: Path, input_spp: int | None = None) -> dict[str, dict]:
    """``scene -> {"reference": Source, "inputs": [Source, ...]}`` for a folder of renders.

    Within a scene the file with the most samples is the reference; ``input_spp`` keeps only inputs of
    that sample count. Dot-files (temporaries) are ignored. Errors name the folder or the scene.
    """
    if not render_dir.is_dir():
        raise ShardError(f"{render_dir}: no such render folder (run 'kpcn render' first)")
    by_scene: dict[str, list[Source]] = defaultdict(list)
    for path in sorted(render_dir.glob("*.exr")):
        if path.name.startswith("."):
            continue
        scene, spp = exr.parse_render_filename(path)
        by_scene[scene].append(Source(scene, spp, str(path)))
    if not by_scene:
        raise ShardError(f"{render_dir}: no '<scene>-<spp>spp.exr' renders found")
    out = {}
    for scene, sources in sorted(by_scene.items()):
        sources.sort(key=lambda s: s.spp)
        if len(sources) < 2:
            raise ShardError(
                f"{render_dir}: scene {scene!r} has only {Path(sources[0].path).name}; "
                "it needs a noisy input and a reference with more samples"
            )
        inputs = sources[:-1]
        if input_spp is not None:
            inputs = [s for s in inputs if s.spp == input_spp]
            if not inputs:
                raise ShardError(
                    f"{render_dir}: scene {scene!r} has no input at {input_spp} spp; "
                    f"found {[s.spp for s in sources]}"
                )
        out[scene] = {"reference": sources[-1], "inputs": inputs}
    return out


def split_scenes(scenes: list[str], val_fraction: float, val_scenes: tuple[str, ...] = ()) -> dict[str, list[str]]:
    """Train/validation split by scene, never by patch.

    Explicit ``val_scenes`` win. Otherwise scenes are grouped by family (the name without its trailing
    ``-<index>``) and the last ``round(val_fraction * n)`` of each sorted group are held out, at least
    one scene overall when there are two or more and val_fraction > 0.
    """
    scenes = sorted(scenes)
    if val_scenes:
        unknown = sorted(set(val_scenes) - set(scenes))
        if unknown:
            raise ShardError(f"val_scenes {unknown} are not among the renders' scenes {scenes}")
        val = sorted(set(val_scenes))
    else:
        families: dict[str, list[str]] = defaultdict(list)
        for s in scenes:
            families[re.sub(r"-\d+$", "", s)].append(s)
        val = []
        for members in families.values():
            val += members[len(members) - int(round(val_fraction * len(members))):] if val_fraction else []
        if not val and val_fraction > 0 and len(scenes) >= 2:
            val = [scenes[-1]]
    train = [s for s in scenes if s not in val]
    if not train:
        raise ShardError(f"no training scene left after holding out {val}")
    return {"train": train, "val": sorted(val)}


# ---------------------------------------------------------------- the per-image step


def image_datasets(noisy: dict, reference: dict) -> dict[str, np.ndarray]:
    """Full-image arrays of every per-patch dataset of the shard layout, for one (noisy, reference) pair."""
    return {
        "diffuse/features": features.branch_features(noisy, "diffuse"),
        "specular/features": features.branch_features(noisy, "specular"),
        "diffuse/noisy": features.branch_colour(noisy, "diffuse"),
        "diffuse/reference": features.branch_colour(reference, "diffuse"),
        "specular/noisy": features.branch_colour(noisy, "specular"),
        "specular/reference": features.branch_colour(reference, "specular"),
        "albedo": noisy["albedo"],
        "noisy": noisy["default"],
        "reference": reference["default"],
    }


@dataclass
class ImagePatches:
    """The patches that one input render gives to one round: the positions drawn for it (:func:`draw`), and
    the full-image datasets they are cut from. Every round (variance or error PDF) goes through this."""

    source_id: int
    round: int
    patch_size: int
    positions: np.ndarray  # (n, 2) int32, top-left (y, x), in drawing order
    pdf: np.ndarray  # (n,) float64, probability of each position under the round's PDF
    images: dict[str, np.ndarray]

    @classmethod
    def at(cls, noisy: dict, reference: dict, positions: np.ndarray, pdf: np.ndarray, *, source_id: int, round: int,
           patch_size: int) -> "ImagePatches":
        return cls(source_id, round, patch_size, positions, pdf, image_datasets(noisy, reference))

    def cut(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Patches ``start:stop`` (in drawing order) with their provenance datasets."""
        out = empty_patches(stop - start, self.patch_size)
        self.cut_into(start, stop, out, 0)
        return out

    def cut_into(self, start: int, stop: int, out: dict[str, np.ndarray], at: int) -> None:
        """Patches ``start:stop`` into rows ``at:`` of ``out`` (:func:`empty_patches`): a shard's arrays are
        filled in place, never stacked and concatenated (that copying was a tenth of the writer's time)."""
        p = self.patch_size
        pos = self.positions[start:stop]
        rows = slice(at, at + len(pos))
        for name, image in self.images.items():
            target = out[name]
            for k, (y, x) in enumerate(pos):
                target[at + k] = image[y : y + p, x : x + p]
        out["source"][rows] = self.source_id
        out["position"][rows] = pos
        out["round"][rows] = self.round
        out["pdf"][rows] = self.pdf[start:stop]


def round_pdf(noisy: dict, config: ShardConfig, error: np.ndarray | None = None, error_weight: float = 0.0) -> np.ndarray:
    """A round's PDF over the patch positions of one input: its variance PDF (docs/method.md §3), and in an
    error round (§3.3.2) ``error_weight`` times the PDF of the per-pixel ``error`` map (built the same way:
    window sums mixed with ``uniform_mix`` of uniform) plus the rest times the variance PDF."""
    importance = sampling.variance_importance(noisy, config.colour_weight, config.normal_weight)
    pdf = sampling.patch_pdf(importance, config.patch_size, config.uniform_mix)
    if error is None or error_weight == 0.0:
        return pdf
    return sampling.mix_pdfs(sampling.patch_pdf(error, config.patch_size, config.uniform_mix), pdf, error_weight)


def round_rng(config: ShardConfig, source_id: int, k: int) -> np.random.Generator:
    """The generator of one input's draw in round ``k``. Round 0 keeps the (seed, source) stream it has
    always had, so sets cut before rounds existed are still the sets this code cuts."""
    key = [config.seed, source_id] if k == 0 else [config.seed, source_id, k]
    return np.random.default_rng(np.random.SeedSequence(key))


def draw(pdf: np.ndarray, count: int, config: ShardConfig, source_id: int, k: int,
         used: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``count`` positions of one input for round ``k`` (without replacement, never one of ``used``: the
    positions earlier rounds took from it) and each one's probability under the round's PDF (``pdf`` with
    ``used`` removed and renormalised)."""
    if used is not None and len(used):
        pdf = sampling.exclude_positions(pdf, used)
    positions = sampling.draw_positions(pdf, count, round_rng(config, source_id, k))
    return positions, pdf[positions[:, 0], positions[:, 1]]


def variance_patches(noisy: dict, reference: dict, config: ShardConfig, source_id: int) -> ImagePatches:
    """Round 0 of one input: ``patches_per_image`` positions from its variance PDF."""
    positions, pdf = draw(round_pdf(noisy, config), config.patches_per_image, config, source_id, 0)
    return ImagePatches.at(noisy, reference, positions, pdf, source_id=source_id, round=0, patch_size=config.patch_size)


# ---------------------------------------------------------------- shard files


def write_shard(path: Path, patches: dict[str, np.ndarray], attrs: dict, layout: Layout = SHARD_LAYOUT) -> None:
    """Write one shard atomically: a per-process temporary name, ``complete`` attribute last, then rename.
    ``layout`` other than :data:`SHARD_LAYOUT` is for measuring (``prep.stage_costs``).

    Not fsync'ed (``atomic_path(durable=False)``): waiting for the disk was most of ``kpcn shards`` (a set
    is ~1.2 MB a patch; this disk takes ~430 MB/s), and a shard needs no fsync to be safe, since its
    checksum is in the manifest and checked by every reader and by the next run, which writes a torn shard
    again (the manifest itself is written durably).

    A write that fails (a full disk) is the KpcnError of ``atomic_path`` naming ``path``, and the HDF5 file
    is closed before it is raised (:func:`_abandon`): HDF5 flushes an open file again whenever one of its
    objects is freed, printing each failure, and at interpreter exit, where a failure can crash the process.
    """
    with atomic_path(path, durable=False) as tmp:
        f = h5py.File(tmp, "w")
        # every dataset is held here until the file is closed: one freed with chunks unwritten writes them
        # then, where HDF5 can only print a failure, not raise it
        datasets = []
        try:
            for name, data in patches.items():
                data = np.ascontiguousarray(data.astype(layout.dtype, copy=False) if name in PATCH_DATASETS else data)
                chunked = {} if layout.patches_per_chunk is None else dict(
                    chunks=(min(len(data), layout.patches_per_chunk if data.ndim > 1 else 1024),) + data.shape[1:],
                    compression=layout.compression, compression_opts=layout.compression_opts,
                    shuffle=layout.shuffle, fletcher32=layout.fletcher32)
                # created, then written: a write that fails leaves the dataset here to close (create_dataset's
                # data= frees it inside h5py); flushed where freeing it flushed its chunks before, so the
                # file's bytes are those that create_dataset(data=) writes
                datasets.append(f.create_dataset(name, shape=data.shape, dtype=data.dtype, **chunked))
                datasets[-1].id.write(h5s.ALL, h5s.ALL, data)
                datasets[-1].flush()
            for key, value in attrs.items():
                f.attrs[key] = value
            f.attrs["complete"] = True
            f.flush()
            datasets.clear()
            f.close()
        except BaseException:
            _abandon(f, datasets)
            raise


def _abandon(f: h5py.File, datasets: list) -> None:
    """Close an HDF5 file whose writing failed, with every object of it in ``datasets``, for good: its file
    descriptor is pointed at ``/dev/null`` first, so the flushes that closing makes succeed (the temporary
    file is removed anyway) and nothing of the file is left open for a later flush to fail on."""
    if not f.id.valid:
        datasets.clear()
        return
    null = os.open(os.devnull, os.O_RDWR)
    try:
        os.dup2(null, f.id.get_vfd_handle())
    finally:
        os.close(null)
    datasets.clear()
    f.close()


def branch_datasets(branch: str, noisy: bool = False) -> list[str]:
    """The datasets a training batch of one branch reads per patch (``kpcn_keras.data``; timed by
    ``prep.stage_costs``): the features and the reference, and the noisy colour for a loss that uses it
    (``noisy``: the asymmetric loss)."""
    return [f"{branch}/features", f"{branch}/reference"] + ([f"{branch}/noisy"] if noisy else [])


def read_patch(f, names, patch: int) -> dict[str, np.ndarray]:
    """Patch ``patch`` of the datasets ``names`` of an open shard (an h5py File, or a mapping of its datasets
    by name), float32 whatever the storage type: the one
    read a training batch makes per patch (``kpcn_keras.data``, timed by ``prep.stage_costs``). OSError
    (a chunk whose checksum fails) is the caller's to name."""
    return {name: np.asarray(f[name][patch], dtype=np.float32) for name in names}


def open_shard(path: str | os.PathLike) -> h5py.File:
    """Open a shard for reading; ShardError unless it is a complete shard of this format."""
    path = Path(path)
    if not SHARD_RE.match(path.name):
        raise ShardError(f"{path}: not a shard name (shard-NNNNN.h5); temporary files are never shards")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ShardError(f"{path}: not a readable HDF5 file ({exc})") from None
    try:
        found, complete = f.attrs.get("format"), bool(f.attrs.get("complete", False))
        missing = [name for name in PATCH_DATASETS if name not in f]
    except (OSError, RuntimeError, KeyError) as exc:
        f.close()
        raise ShardError(f"{path}: damaged HDF5 file ({exc})") from None
    if found != FORMAT or not complete:
        f.close()
        raise ShardError(f"{path}: incomplete or foreign shard (format={found!r}, complete={complete}; expected {FORMAT!r})")
    if missing:
        f.close()
        raise ShardError(f"{path}: missing datasets {missing}")
    return f


def _config_hash_of(path: Path) -> str | None:
    try:
        with open_shard(path) as f:
            return f.attrs.get("config_hash")
    except ShardError:
        return None


# ---------------------------------------------------------------- the plan of a set


@dataclass
class _ShardSpec:
    index: int
    split: str
    pieces: list[tuple[int, int, int]]  # (source id, first patch, end patch) of that source's draw order

    @property
    def patches(self) -> int:
        return sum(b - a for _, a, b in self.pieces)


def _shard_specs(streams: list[tuple[str, int, int]], per_shard: int) -> list[_ShardSpec]:
    """The shards of one round: ``streams`` lists (split, source id, patches) in order; each split's patches
    fill shards of ``per_shard`` in that order, an input spanning consecutive shards."""
    shards: list[_ShardSpec] = []
    for split_name in SPLITS:
        current: _ShardSpec | None = None
        for split, source_id, count in streams:
            if split != split_name:
                continue
            start = 0
            while start < count:
                if current is None or current.patches == per_shard:
                    current = _ShardSpec(len(shards), split_name, [])
                    shards.append(current)
                take = min(count - start, per_shard - current.patches)
                current.pieces.append((source_id, start, start + take))
                start += take
    return shards


@dataclass
class _Plan:
    """Everything ``build_shards`` will write, decided (and checked) before anything is."""

    config_hash: str
    content_key: str
    split: dict[str, list[str]]
    sources: list[dict]
    shards: list[_ShardSpec]


def _plan(config: ShardConfig, sset: ShardSet) -> _Plan:
    """Find the renders, check every header and the options against every image, fix the split, source
    ids and the shard each patch goes to. Raises (naming the file or option) before any writing."""
    renders = discover_renders(config.render_dir, config.input_spp)
    split = split_scenes(list(renders), config.val_fraction, config.val_scenes)
    p = config.patch_size
    sources: list[dict] = []
    streams: list[tuple[str, int, int]] = []
    for split_name in SPLITS:
        for scene in split[split_name]:
            ref = renders[scene]["reference"]
            ref_size = exr.read_header(ref.path, variances=False)
            sources.append(_source_record(sset, ref, "reference", split_name, 0))
            for src in renders[scene]["inputs"]:
                size = exr.read_header(src.path)
                if size != ref_size:
                    raise ShardError(
                        f"{src.path} is {size[1]}x{size[0]} but its reference {ref.path} is {ref_size[1]}x{ref_size[0]}"
                    )
                if min(size) < p:
                    smaller = (f"use --patch-size {min(size)} or less, or remove the render"
                               if min(size) >= PATCH_SIZE.low else
                               f"the smallest patch is {PATCH_SIZE.low}x{PATCH_SIZE.low}: remove the render")
                    raise ShardError(f"{src.path} is {size[1]}x{size[0]}, smaller than a {p}x{p} patch; {smaller}")
                positions = (size[0] - p + 1) * (size[1] - p + 1)
                if config.patches_per_image > positions:
                    raise OptionError(
                        "patches_per_image",
                        f"{config.patches_per_image} exceeds the {positions} distinct {p}x{p} patch positions of "
                        f"{src.path} ({size[1]}x{size[0]}); patches are drawn without replacement",
                    )
                streams.append((split_name, len(sources), config.patches_per_image))
                sources.append(_source_record(sset, src, "input", split_name, config.patches_per_image))
    config_hash = config.content_hash()
    key = content_key(config_hash, sources)
    return _Plan(config_hash, key, split, sources, _shard_specs(streams, config.patches_per_shard))


def content_key(config_hash: str, sources: list[dict]) -> str:
    """The set's content key: its format, configuration and every source's identity (what, where in the
    split, with how many patches, and the render's SHA-256) hashed together."""
    identity = [{k: s[k] for k in ("scene", "spp", "role", "split", "sha256", "patches")} for s in sources]
    return hashlib.sha256(json.dumps([FORMAT, config_hash, identity], sort_keys=True).encode()).hexdigest()[:16]


def _source_record(sset: ShardSet, src: Source, role: str, split: str, patches: int) -> dict:
    return {"scene": src.scene, "spp": src.spp, "path": sset.relative(src.path), "role": role, "split": split,
            "patches": patches, "sha256": sha256_file(src.path)}


def _source_changes(old: list[dict], new: list[dict]) -> str:
    """What differs between two source lists, for the message that explains a rebuild."""
    def index(sources):
        return {(s["scene"], s["spp"]): s for s in sources}

    a, b = index(old), index(new)
    parts = []
    for label, names in (
        ("added", sorted(set(b) - set(a))),
        ("removed", sorted(set(a) - set(b))),
        ("changed", sorted(k for k in set(a) & set(b) if (a[k]["sha256"], a[k]["split"]) != (b[k]["sha256"], b[k]["split"]))),
    ):
        if names:
            parts.append(f"{label} " + ", ".join(f"{scene} ({spp} spp)" for scene, spp in names))
    return "; ".join(parts) or "the patches per source changed"


def _previous_manifest(sset: ShardSet, config: ShardConfig, plan: _Plan) -> dict | None:
    """The manifest of an earlier run of the same configuration (None if there is none to go on);
    ShardError if the folder holds a set of another configuration or format."""
    round_dir = sset.round_dir(0)
    if sset.manifest_path.is_file():
        try:
            manifest = sset.read_manifest()
        except ShardError:
            raise  # another format: not ours to overwrite
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
        found = _config_hash_of(existing)
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
    plan = _plan(config, sset)
    with sset.lock():
        manifest = _open_manifest(sset, config, plan)
    mine = [plan.shards[i] for i in part.block(len(plan.shards))]
    with sset.lock(part):
        record = manifest if part.whole else {**manifest, "rounds": {
            **manifest["rounds"], round_name(0): {**manifest["rounds"][round_name(0)], "shards": []}}}
        record_path = sset.manifest_path if part.whole else sset.part_record_path(part)
        _write_round(sset, config, record, 0, mine, _RoundDraw(config, 0), config.command, progress, workers,
                     listed=_listed_round_zero(sset, manifest), shards_in_round=len(plan.shards),
                     record_path=record_path)
        if not part.whole:
            record["status"] = "complete"
            atomic_write_json(record_path, record)
    with sset.lock():
        return _merge_round_zero(sset, manifest, record, part, len(plan.shards))


def _open_manifest(sset: ShardSet, config: ShardConfig, plan: _Plan) -> dict:
    """The manifest this run builds round 0 into, the set's lock held: the set's error rounds and round 0's
    listed shards are kept when the renders are the same; the set is emptied when they changed. A new
    manifest is written at once (``status: "building"``), so that a part starting later finds the set as
    this one left it rather than rebuilding it again."""
    previous = _previous_manifest(sset, config, plan)
    if previous is not None and previous.get("content_key") != plan.content_key:
        log.warning("%s: renders changed since the set was written (%s); rebuilding it", sset.dir,
                    _source_changes(previous.get("sources", []), plan.sources))
        previous = None
        for old in [*sorted(sset.dir.glob("round-*")), sset.dir / PARTS]:
            if old.is_dir():
                shutil.rmtree(old)
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
        "constants": {"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS},
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


def _write_round(sset: ShardSet, config: ShardConfig, manifest: dict, k: int, specs: list[_ShardSpec],
                 draw_of: "_RoundDraw", command: str, progress: bool, workers: int | None, *,
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
                          _shard_attrs(config, manifest, command))

    def record(spec: _ShardSpec, checksum: tuple[str, str]) -> None:
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
        pool = ProcessPoolExecutor(workers, mp_context=_worker_context(), initializer=_start_worker,
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
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise OptionError("workers", f"must be an integer >= 1, got {workers!r}")
    return workers


def shard_workers() -> int:
    """How many processes cut and write shards: the thread count the user set (``prep.threads``), else 1.
    Processes, not threads: writing HDF5 holds the GIL, and the rest of a shard's work needs it too."""
    return threads.requested() or 1


@dataclass(frozen=True)
class _RoundDraw:
    """An input's positions in round ``k`` and each one's PDF value: drawn from the variance PDF in round 0
    (:func:`round_pdf`, :func:`draw`), looked up in the error round's plan (source id -> (positions, pdf))
    otherwise. A value, not a closure, so that worker processes can be given it."""

    config: ShardConfig
    k: int
    plan: dict[int, tuple[np.ndarray, np.ndarray]] | None = None

    def __call__(self, source_id: int, noisy: dict) -> tuple[np.ndarray, np.ndarray]:
        if self.plan is None:
            return draw(round_pdf(noisy, self.config), self.config.patches_per_image, self.config, source_id, self.k)
        return self.plan[source_id]


@dataclass
class _RoundWriter:
    """Cuts and writes one shard of a round at a time: what each worker process is started with.

    It keeps, between shards, the :class:`ImagePatches` of the input it cut last (an input spans at most a
    few consecutive shards) with its reference, and one shard buffer (reused: allocating it per shard
    costs its page faults each time)."""

    set_dir: str
    sources: list[dict]
    k: int
    patch_size: int
    draw_of: _RoundDraw
    attrs: dict
    _current: ImagePatches | None = field(default=None, repr=False)
    _reference: tuple[str, dict] | None = field(default=None, repr=False)
    _buffer: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def __getstate__(self):
        return {**self.__dict__, "_current": None, "_reference": None, "_buffer": None}

    def write(self, spec: _ShardSpec) -> tuple[str, str]:
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
            ref_path = _reference_of(self.sources, src)["path"]
            if self._reference is None or self._reference[0] != ref_path:
                self._reference = None
                self._reference = (ref_path, exr.read_aovs(sset.resolve(ref_path), variances=False))
            noisy = exr.read_aovs(sset.resolve(src["path"]))
            self._current = None  # free the previous image before the next is cut
            positions, pdf = self.draw_of(source_id, noisy)
            self._current = ImagePatches.at(noisy, self._reference[1], positions, pdf, source_id=source_id,
                                            round=self.k, patch_size=self.patch_size)
        return self._current


_worker: _RoundWriter | None = None


def _worker_context():
    """fork where torch is not loaded (``kpcn shards``: prep never imports it), spawn where it is (an error
    round cut by ``kpcn resample``). A forked worker starts in milliseconds with everything imported; a
    spawned one imports and loads the features kernel again (~0.6 s of CPU each, a sixth of a default set
    here), but a fork copies torch's thread pools half-made. The workers run no parallel region of numba's
    or anyone's, so the idle OpenMP threads of ``prep.threads`` that a fork leaves behind are never waited on."""
    return multiprocessing.get_context("spawn" if "torch" in sys.modules else "fork")


def _start_worker(writer: _RoundWriter, parent: int) -> None:
    global _worker
    die_with_parent(parent)  # a killed `kpcn shards` leaves no worker writing on
    _worker = writer
    threads.set_threads(1)  # one process per core already


def _write_in_worker(spec: _ShardSpec) -> tuple[str, str]:
    return _worker.write(spec)


def _entry(sset: ShardSet, path: Path, spec: _ShardSpec, checksum: tuple[str, str]) -> dict:
    algorithm, digest = checksum
    return {"path": sset.relative(path), "split": spec.split, "patches": spec.patches, algorithm: digest}


def shard_checksum(path: Path) -> tuple[str, str]:
    """(algorithm, hex digest) of a shard file, as a manifest lists it: :data:`SHARD_CHECKSUMS`'s first."""
    algorithm = next(iter(SHARD_CHECKSUMS))
    return algorithm, SHARD_CHECKSUMS[algorithm](path)


def listed_checksum(listed: dict) -> tuple[str, str]:
    """(algorithm, hex digest) of a manifest's shard entry (a set of any version of this format)."""
    for algorithm in SHARD_CHECKSUMS:
        if algorithm in listed:
            return algorithm, listed[algorithm]
    raise ShardError(f"shard entry {listed.get('path', listed)!r} lists no checksum ({', '.join(SHARD_CHECKSUMS)})")


def shard_intact(path: Path, checksum: tuple[str, str]) -> bool:
    algorithm, digest = checksum
    return SHARD_CHECKSUMS[algorithm](path) == digest


def _reference_of(sources: list[dict], src: dict) -> dict:
    return next(s for s in sources if s["scene"] == src["scene"] and s["role"] == "reference")


def _shard_attrs(config: ShardConfig, manifest: dict, command: str) -> dict:
    return {
        "format": FORMAT,
        "patch_size": config.patch_size,
        "features": json.dumps(list(features.FEATURE_NAMES)),
        "transforms": "diffuse: log1p(diffuse / (albedo + ALBEDO_EPS)); specular: log1p(max(specular, 0))",
        "constants": json.dumps({"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS}),
        "sources": json.dumps([{k: s[k] for k in ("scene", "spp", "path")} for s in manifest["sources"]]),
        "config": json.dumps(config.to_dict()),
        "config_hash": manifest["config_hash"],
        "content_key": manifest["content_key"],
        "command": command or " ".join(sys.argv),
    }


# ---------------------------------------------------------------- error rounds (docs/method.md §8)


@dataclass(frozen=True)
class ErrorRound:
    """What error round ``index`` (>= 1) of a set is drawn with; all but ``command`` is its provenance.

    ``patches_per_image`` new positions per training input, from ``error_weight`` times the PDF of the
    ``metric`` error map (``prep.sampling.ERROR_METRICS``) of ``model``'s output plus the rest times the
    variance PDF; ``model`` says what made the error maps (the caller's record: files with SHA-256). With
    ``error_weight`` 0 no model is run: the round is drawn from the variance PDF alone (a control).
    """

    index: int
    patches_per_image: int
    error_weight: float
    metric: str
    model: dict
    command: str = field(default="", compare=False)

    def __post_init__(self):
        if isinstance(self.index, bool) or not isinstance(self.index, int) or self.index < 1:
            raise OptionError("rounds", f"error rounds are numbered from 1, got {self.index!r}")
        if isinstance(self.patches_per_image, bool) or not isinstance(self.patches_per_image, int) \
                or self.patches_per_image < 1:
            raise OptionError("patches_per_image", f"must be an integer >= 1, got {self.patches_per_image!r}")
        if not 0.0 <= self.error_weight <= 1.0:
            raise OptionError("error_weight", f"must be in [0, 1], got {self.error_weight!r}")
        if self.metric not in sampling.ERROR_METRICS:
            raise OptionError("metric", f"must be one of {', '.join(sampling.ERROR_METRICS)}, got {self.metric!r}")

    def provenance(self) -> dict:
        return {"patches_per_image": self.patches_per_image, "error_weight": float(self.error_weight),
                "metric": self.metric, "model": self.model}


@dataclass
class RoundResult:
    """What :func:`build_error_round` did: the manifest after it, the patches the round holds, seconds spent
    on error maps (denoising included) and on shards in this call (0 for a round found complete), and the
    map that drove the draw on one input (``figure``: source id, the map, whether it is an error map,
    and the round's positions on that input)."""

    manifest: dict
    patches: int
    seconds: dict
    figure: dict


def training_inputs(manifest: dict) -> list[int]:
    """The source ids of the training inputs: the renders that error rounds resample."""
    return [i for i, s in enumerate(manifest["sources"]) if s["role"] == "input" and s["split"] == "train"]


def used_positions(sset: ShardSet, manifest: dict, rounds) -> dict[int, np.ndarray]:
    """source id -> (n, 2) positions that the training shards of ``rounds`` took from it."""
    found: dict[int, list[np.ndarray]] = defaultdict(list)
    for entry in sset.verified_shards("train", manifest, rounds):
        with open_shard(entry.path) as f:
            source, position = f["source"][:], f["position"][:]
        for sid in np.unique(source):
            found[int(sid)].append(position[source == sid])
    return {sid: np.concatenate(parts) for sid, parts in found.items()}


def _read_plan(path: Path) -> dict:
    with np.load(path) as z:
        return {name: z[name] for name in z.files}


def _write_plan(path: Path, plan: dict) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.savez(f, **plan)


def build_error_round(set_dir: str | os.PathLike, rnd: ErrorRound, denoise=None, *, progress: bool = True,
                      workers: int | None = None) -> RoundResult:
    """Write error round ``rnd.index`` of the complete set in ``set_dir``; returns what was done.

    ``denoise(noisy AOVs) -> (H, W, 3)`` linear colour is the model whose error is measured against each
    training input's reference (not called when ``rnd.error_weight`` is 0). Two steps, each resumable:
    the positions of every training input are drawn and written as the round's plan (``plan.npz``), then
    its shards are cut from the plan. Interrupted anywhere, the same call finishes the round: a plan whose
    provenance matches is reused, whole shards are kept. A complete round of the same provenance is never
    rebuilt; one of another provenance, or a gap in the rounds, is a ShardError.
    """
    sset = ShardSet(set_dir)
    k, name = rnd.index, round_name(rnd.index)
    with sset.lock():
        remove_temporaries(sset.dir)  # a manifest write that a kill cut short
        manifest = sset.complete_manifest()
        config = ShardConfig(**manifest["config"])
        have = set(manifest["rounds"])
        later = sorted(n for n in have if round_index(n) > k)
        if later:
            raise ShardError(f"{sset.dir}: has {', '.join(later)} beyond {name}; rounds are drawn in order")
        before = list(range(k))
        incomplete = [round_name(j) for j in before if j not in sset.complete_rounds(manifest)]
        if incomplete:
            raise ShardError(f"{sset.dir}: {name} needs every earlier round complete; {', '.join(incomplete)} "
                             "is not (run the command that writes it again)")
        entry = manifest["rounds"].get(name)
        if entry is not None and entry.get("provenance") != rnd.provenance():
            if entry.get("status") == "complete":
                raise ShardError(
                    f"{sset.round_dir(k)}: drawn with another model or settings ({_provenance_diff(entry, rnd)}); "
                    f"remove {sset.round_dir(k)} and its entry, or continue on a copy of the set"
                )
            log.warning("%s: an unfinished %s of other settings; drawing it again", sset.dir, name)
            entry = None
        if entry is None and sset.round_dir(k).exists():
            shutil.rmtree(sset.round_dir(k))
        seconds = {"error_maps": 0.0, "shards": 0.0}
        plan_path = sset.round_dir(k) / PLAN
        plan = None
        if entry is not None and plan_path.is_file() and sha256_file(plan_path) == entry["plan"]["sha256"]:
            plan = _read_plan(plan_path)
        if entry is not None and entry["status"] == "complete":
            return RoundResult(manifest, _round_patches(entry), seconds, _figure(plan))
        if plan is None:
            start = time.perf_counter()
            plan = _draw_error_round(sset, manifest, config, rnd, denoise, progress)
            seconds["error_maps"] = time.perf_counter() - start
            _write_plan(plan_path, plan)
            entry = {"kind": "error", "status": "building", "provenance": rnd.provenance(),
                     "plan": {"path": sset.relative(plan_path), "sha256": sha256_file(plan_path)}, "shards": []}
            manifest["rounds"][name] = entry
            atomic_write_json(sset.manifest_path, manifest)
        start = time.perf_counter()
        inputs = training_inputs(manifest)
        specs = _shard_specs([("train", sid, rnd.patches_per_image) for sid in inputs], config.patches_per_shard)
        rows = {int(sid): np.flatnonzero(plan["source"] == sid) for sid in inputs}
        drawn = {sid: (plan["position"][r], plan["pdf"][r]) for sid, r in rows.items()}
        _write_round(sset, config, manifest, k, specs, _RoundDraw(config, k, drawn), rnd.command, progress, workers)
        entry["status"] = "complete"
        atomic_write_json(sset.manifest_path, manifest)
        seconds["shards"] = time.perf_counter() - start
    return RoundResult(manifest, _round_patches(entry), seconds, _figure(plan))


def _draw_error_round(sset: ShardSet, manifest: dict, config: ShardConfig, rnd: ErrorRound, denoise,
                      progress: bool) -> dict:
    """The plan of an error round: every training input's positions (and PDF values), and the map that
    drove the draw on the input where it is largest on average (for the round's figure)."""
    from tqdm import tqdm

    inputs = training_inputs(manifest)
    used = used_positions(sset, manifest, range(rnd.index))
    uses_model = rnd.error_weight > 0.0
    if uses_model and denoise is None:
        raise ValueError("an error round with error_weight > 0 needs a denoise function")
    p = config.patch_size
    for sid in inputs:  # before any denoising: the positions left must hold the round
        src = manifest["sources"][sid]
        h, w = exr.read_header(sset.resolve(src["path"]))
        left = (h - p + 1) * (w - p + 1) - len(np.unique(used.get(sid, np.empty((0, 2))), axis=0))
        if rnd.patches_per_image > left:
            raise OptionError("patches_per_image", f"{rnd.patches_per_image} exceeds the {left} patch positions of "
                              f"{src['path']} that earlier rounds left unused")
    sources, positions, pdfs = [], [], []
    figure = {"figure_source": -1, "figure_mean": -np.inf}
    for sid in tqdm(inputs, desc=f"error maps {round_name(rnd.index)}", unit="image", disable=not progress):
        src = manifest["sources"][sid]
        noisy = exr.read_aovs(sset.resolve(src["path"]))
        if uses_model:
            reference = exr.read_aovs(sset.resolve(_reference_of(manifest["sources"], src)["path"]), variances=False)
            drive = sampling.error_map(np.asarray(denoise(noisy)), reference["default"], rnd.metric)
        else:
            drive = sampling.variance_importance(noisy, config.colour_weight, config.normal_weight)
        pos, pdf = draw(round_pdf(noisy, config, drive if uses_model else None, rnd.error_weight),
                        rnd.patches_per_image, config, sid, rnd.index, used.get(sid))
        sources.append(np.full(len(pos), sid, np.int32))
        positions.append(pos)
        pdfs.append(pdf)
        mean = float(np.mean(drive))
        if mean > figure["figure_mean"]:
            figure = {"figure_source": sid, "figure_mean": mean, "figure_map": drive.astype(np.float32)}
    return {"source": np.concatenate(sources), "position": np.concatenate(positions).astype(np.int32),
            "pdf": np.concatenate(pdfs), "figure_source": np.int32(figure["figure_source"]),
            "figure_map": figure["figure_map"], "figure_is_error": np.bool_(uses_model)}


def _figure(plan: dict | None) -> dict:
    if plan is None:
        return {}
    sid = int(plan["figure_source"])
    return {"source": sid, "map": plan["figure_map"], "is_error": bool(plan["figure_is_error"]),
            "positions": plan["position"][plan["source"] == sid]}


def _round_patches(entry: dict) -> int:
    return sum(s["patches"] for s in entry["shards"])


def _provenance_diff(entry: dict, rnd: ErrorRound) -> str:
    old, new = entry.get("provenance") or {}, rnd.provenance()
    return ", ".join(f"{k} {old.get(k)!r} vs {new[k]!r}" for k in new if old.get(k) != new[k]) or "unknown"


__all__ = [
    "FORMAT",
    "MANIFEST",
    "PATCH_DATASETS",
    "ErrorRound",
    "ImagePatches",
    "LAYOUTS",
    "Layout",
    "SHARD_LAYOUT",
    "RoundResult",
    "ShardConfig",
    "ShardEntry",
    "ShardError",
    "ShardSet",
    "build_error_round",
    "branch_datasets",
    "build_shards",
    "discover_renders",
    "draw",
    "empty_patches",
    "image_datasets",
    "open_shard",
    "read_patch",
    "round_index",
    "round_name",
    "round_pdf",
    "shard_name",
    "shard_paths",
    "split_scenes",
    "training_inputs",
    "used_positions",
    "variance_patches",
    "write_shard",
]
