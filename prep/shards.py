"""65x65 training patches in HDF5 shards (design.md "Shards").

A shard set is the folder ``<out_root>/<set>/``; :class:`ShardSet` is the one owner of its layout::

    <set>/manifest.json             sources (with SHA-256), split, configuration, every shard (with SHA-256)
    <set>/.lock                     held by the one process that writes the set
    <set>/round-<k>/shard-<i>.h5    up to ``patches_per_shard`` patches of one split (train or val)

Each shard stores one patch per chunk (gzip + shuffle + Fletcher-32 checksums), in these datasets
(N patches, P = patch size, channels last, float32):

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
  whose SHA-256 matches it.
- **One writer per set.** ``build_shards`` holds the set's lock; a second one waits, then finds the work
  done.
- **Bad input is found before anything is written**: every render's header (layers, size) and the options
  against every image are checked first.
- **Bounded memory**: a shard is assembled from one image at a time; no more than one shard's patches
  are held.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from prep import exr, features, sampling
from prep.errors import KpcnError, OptionError
from prep.files import (
    atomic_path,
    atomic_write_json,
    check_writable,
    exclusive_lock,
    read_json,
    remove_temporaries,
    sha256_file,
)

log = logging.getLogger("kpcn")

FORMAT = "kpcn-shard/2"
MANIFEST = "manifest.json"
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


class ShardError(KpcnError, ValueError):
    """A shard or shard set that cannot be used; the message names the file and what was found."""


def round_name(k: int) -> str:
    """The folder of sampling round ``k``: ``round-000`` is variance sampling, later rounds error-based."""
    return f"round-{int(k):03d}"


def shard_name(i: int) -> str:
    return f"shard-{int(i):05d}.h5"


def patch_bytes(patch_size: int) -> int:
    """Bytes of one patch of every dataset in memory (float32)."""
    return 4 * patch_size * patch_size * sum(PATCH_DATASETS.values())


@dataclass
class ShardConfig:
    """Configuration of ``kpcn shards``; saved in the manifest and in every shard."""

    set_name: str = "default"
    render_root: str = "data/renders"
    out_root: str = "shards"
    patch_size: int = 65
    patches_per_image: int = 32  # per input render: a ladder of three inputs gives 96 per scene
    patches_per_shard: int = 256
    val_fraction: float = 0.25
    val_scenes: tuple[str, ...] = ()
    input_spp: int | None = None
    colour_weight: float = 1.0
    normal_weight: float = 1.0
    uniform_mix: float = 0.1
    seed: int = 0
    command: str = field(default="", compare=False)

    def __post_init__(self):
        self.val_scenes = tuple(self.val_scenes)
        if not self.set_name or "/" in self.set_name or self.set_name in (".", ".."):
            raise OptionError("set_name", f"must be a plain folder name, got {self.set_name!r}")
        checks = {
            "patch_size": (self.patch_size >= 1, ">= 1"),
            "patches_per_image": (self.patches_per_image >= 1, ">= 1"),
            "patches_per_shard": (self.patches_per_shard >= 1, ">= 1"),
            "val_fraction": (0.0 <= self.val_fraction < 1.0, "in [0, 1)"),
            # > 0: every position can be drawn, so the plan's check of patches_per_image against the
            # positions of each image is complete (with 0, an image without variance has none)
            "uniform_mix": (0.0 < self.uniform_mix <= 1.0, "in (0, 1]"),
            "seed": (self.seed >= 0, ">= 0"),
            "input_spp": (self.input_spp is None or self.input_spp >= 1, ">= 1"),
        }
        for name, (ok, bound) in checks.items():
            if not ok:
                raise OptionError(name, f"must be {bound}, got {getattr(self, name)!r}")
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
    sha256: str


class ShardSet:
    """The folder of one shard set: its manifest, rounds, shards, lock and source paths."""

    def __init__(self, set_dir: str | os.PathLike):
        self.dir = Path(set_dir)

    @property
    def manifest_path(self) -> Path:
        return self.dir / MANIFEST

    def round_dir(self, k: int) -> Path:
        return self.dir / round_name(k)

    def lock(self):
        return exclusive_lock(self.dir, "shard set")

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
                "was interrupted or is still running); run it again to finish the set"
            )
        return manifest

    def entries(self, manifest: dict, split: str) -> list[ShardEntry]:
        """The shards of ``split`` that ``manifest`` lists, every round, in order."""
        return [
            ShardEntry(self.resolve(s["path"]), name, s["split"], int(s["patches"]), s["sha256"])
            for name, rnd in sorted(manifest["rounds"].items())
            for s in rnd["shards"]
            if s["split"] == split
        ]

    def verified_shards(self, split: str, manifest: dict | None = None) -> list[ShardEntry]:
        """The shards of ``split`` of a complete set, each present with the SHA-256 the manifest lists."""
        manifest = manifest or self.complete_manifest()
        entries = self.entries(manifest, split)
        for entry in entries:
            if not entry.path.is_file():
                raise ShardError(f"{entry.path}: listed in {self.manifest_path} but missing; "
                                 "run 'kpcn shards' again to rebuild it")
            if sha256_file(entry.path) != entry.sha256:
                raise ShardError(
                    f"{entry.path}: its SHA-256 differs from the one in {self.manifest_path} (the file changed "
                    "after it was written); run 'kpcn shards' again to rebuild it"
                )
        return entries

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
    """The patches that one input render gives to one round: positions drawn from a PDF, and the
    full-image datasets they are cut from. Every round (variance or error PDF) goes through this."""

    source_id: int
    round: int
    patch_size: int
    positions: np.ndarray  # (n, 2) int32, top-left (y, x), in drawing order
    pdf: np.ndarray  # (n,) float64, probability of each position under the round's PDF
    images: dict[str, np.ndarray]

    @classmethod
    def draw(cls, noisy: dict, reference: dict, pdf: np.ndarray, count: int, rng: np.random.Generator, *,
             source_id: int, round: int, patch_size: int) -> "ImagePatches":
        positions = sampling.draw_positions(pdf, count, rng)
        return cls(source_id, round, patch_size, positions, pdf[positions[:, 0], positions[:, 1]],
                   image_datasets(noisy, reference))

    def cut(self, start: int, stop: int) -> dict[str, np.ndarray]:
        """Patches ``start:stop`` (in drawing order) with their provenance datasets."""
        p = self.patch_size
        pos = self.positions[start:stop]
        out = {name: np.stack([image[y : y + p, x : x + p] for y, x in pos]).astype(np.float32)
               for name, image in self.images.items()}
        out["source"] = np.full(len(pos), self.source_id, dtype=np.int32)
        out["position"] = pos.astype(np.int32)
        out["round"] = np.full(len(pos), self.round, dtype=np.int32)
        out["pdf"] = self.pdf[start:stop].astype(np.float64)
        return out


def variance_patches(noisy: dict, reference: dict, config: ShardConfig, source_id: int) -> ImagePatches:
    """Round 0 of one input: ``patches_per_image`` positions from its variance PDF (seed report §2.1)."""
    pdf = sampling.patch_pdf(
        sampling.variance_importance(noisy, config.colour_weight, config.normal_weight),
        config.patch_size,
        config.uniform_mix,
    )
    rng = np.random.default_rng(np.random.SeedSequence([config.seed, source_id]))
    return ImagePatches.draw(noisy, reference, pdf, config.patches_per_image, rng, source_id=source_id, round=0,
                             patch_size=config.patch_size)


# ---------------------------------------------------------------- shard files


def write_shard(path: Path, patches: dict[str, np.ndarray], attrs: dict) -> None:
    """Write one shard atomically: a per-process temporary name, ``complete`` attribute last, then rename."""
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            for name, data in patches.items():
                chunks = (1,) + data.shape[1:] if data.ndim > 1 else (min(len(data), 1024),)
                f.create_dataset(name, data=data, chunks=chunks, compression="gzip", compression_opts=1,
                                 shuffle=True, fletcher32=True)
            for key, value in attrs.items():
                f.attrs[key] = value
            f.attrs["complete"] = True


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
    streams: dict[str, list[tuple[int, int]]] = {s: [] for s in SPLITS}
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
                    raise ShardError(
                        f"{src.path} is {size[1]}x{size[0]}, smaller than a {p}x{p} patch; "
                        f"use --patch-size {min(size)} or less, or remove the render"
                    )
                positions = (size[0] - p + 1) * (size[1] - p + 1)
                if config.patches_per_image > positions:
                    raise OptionError(
                        "patches_per_image",
                        f"{config.patches_per_image} exceeds the {positions} distinct {p}x{p} patch positions of "
                        f"{src.path} ({size[1]}x{size[0]}); patches are drawn without replacement",
                    )
                streams[split_name].append((len(sources), config.patches_per_image))
                sources.append(_source_record(sset, src, "input", split_name, config.patches_per_image))
    shards: list[_ShardSpec] = []
    per = config.patches_per_shard
    for split_name in SPLITS:
        current: _ShardSpec | None = None
        for source_id, count in streams[split_name]:
            start = 0
            while start < count:
                if current is None or current.patches == per:
                    current = _ShardSpec(len(shards), split_name, [])
                    shards.append(current)
                take = min(count - start, per - current.patches)
                current.pieces.append((source_id, start, start + take))
                start += take
    config_hash = config.content_hash()
    identity = [{k: s[k] for k in ("scene", "spp", "role", "split", "sha256", "patches")} for s in sources]
    key = hashlib.sha256(json.dumps([FORMAT, config_hash, identity], sort_keys=True).encode()).hexdigest()[:16]
    return _Plan(config_hash, key, split, sources, shards)


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


def build_shards(config: ShardConfig, *, progress: bool = True) -> dict:
    """Cut round 0 of a shard set from a folder of renders; returns the manifest.

    Deterministic for a given config and renders. A rerun with the same renders keeps every shard that is
    whole (SHA-256 as listed) and writes the rest, so an interrupted run resumes; a rerun after the
    renders changed rebuilds the set; another configuration over an existing set is an error.
    """
    from tqdm import tqdm

    sset = ShardSet(config.set_dir)
    check_writable(sset.dir, "shard set folder (--out)", directory=True)
    plan = _plan(config, sset)
    with sset.lock():
        previous = _previous_manifest(sset, config, plan)
        if previous is not None and previous.get("content_key") != plan.content_key:
            log.warning("%s: renders changed since the set was written (%s); rebuilding it", sset.dir,
                        _source_changes(previous.get("sources", []), plan.sources))
            previous = None
            for old_round in sorted(sset.dir.glob("round-*")):
                shutil.rmtree(old_round)
        round_dir = sset.round_dir(0)
        round_dir.mkdir(parents=True, exist_ok=True)
        remove_temporaries(sset.dir)
        remove_temporaries(round_dir)
        listed = {s["path"]: s["sha256"] for s in (previous or {}).get("rounds", {}).get(round_name(0), {}).get("shards", [])}

        entries: dict[int, dict] = {}
        todo = []
        for spec in plan.shards:
            path = round_dir / shard_name(spec.index)
            rel = sset.relative(path)
            if rel in listed and path.is_file() and sha256_file(path) == listed[rel]:
                entries[spec.index] = _entry(sset, path, spec, listed[rel])
            else:
                todo.append(spec)
        for extra in round_dir.glob("shard-*.h5"):
            match = SHARD_RE.match(extra.name)
            if match and int(match.group(1)) >= len(plan.shards):
                extra.unlink()

        def manifest(status: str) -> dict:
            return {
                "format": FORMAT,
                "status": status,
                "set": config.set_name,
                "config": config.to_dict(),
                "config_hash": plan.config_hash,
                "content_key": plan.content_key,
                "features": list(features.FEATURE_NAMES),
                "constants": {"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS},
                "patch_size": config.patch_size,
                "split": plan.split,
                "sources": plan.sources,
                "rounds": {round_name(0): {"shards": [entries[i] for i in sorted(entries)]}},
            }

        attrs = _shard_attrs(config, plan)
        images = _ImageCache(sset, config, plan.sources)
        with tqdm(total=len(todo), desc="shards", unit="shard", disable=not progress) as bar:
            for spec in todo:
                patches = [images.get(source_id).cut(a, b) for source_id, a, b in spec.pieces]
                arrays = {name: np.concatenate([p[name] for p in patches]) for name in patches[0]}
                path = round_dir / shard_name(spec.index)
                write_shard(path, arrays, {**attrs, "split": spec.split})
                entries[spec.index] = _entry(sset, path, spec, sha256_file(path))
                atomic_write_json(sset.manifest_path, manifest("building"))
                bar.update(1)
        final = manifest("complete")
        atomic_write_json(sset.manifest_path, final)
    return final


def _entry(sset: ShardSet, path: Path, spec: _ShardSpec, sha256: str) -> dict:
    return {"path": sset.relative(path), "split": spec.split, "patches": spec.patches, "sha256": sha256}


class _ImageCache:
    """The :class:`ImagePatches` of the input being cut (an input spans at most a few consecutive shards),
    and the reference it was read with."""

    def __init__(self, sset: ShardSet, config: ShardConfig, sources: list[dict]):
        self.sset, self.config, self.sources = sset, config, sources
        self.current: ImagePatches | None = None
        self.reference: tuple[str, dict] | None = None

    def get(self, source_id: int) -> ImagePatches:
        if self.current is None or self.current.source_id != source_id:
            src = self.sources[source_id]
            ref_src = next(s for s in self.sources if s["scene"] == src["scene"] and s["role"] == "reference")
            if self.reference is None or self.reference[0] != ref_src["path"]:
                self.reference = (ref_src["path"], exr.read_aovs(self.sset.resolve(ref_src["path"]), variances=False))
            noisy = exr.read_aovs(self.sset.resolve(src["path"]))
            self.current = None  # free the previous image before the next is cut
            self.current = variance_patches(noisy, self.reference[1], self.config, source_id)
        return self.current


def _shard_attrs(config: ShardConfig, plan: _Plan) -> dict:
    return {
        "format": FORMAT,
        "patch_size": config.patch_size,
        "features": json.dumps(list(features.FEATURE_NAMES)),
        "transforms": "diffuse: log1p(diffuse / (albedo + ALBEDO_EPS)); specular: log1p(max(specular, 0))",
        "constants": json.dumps({"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS}),
        "sources": json.dumps([{k: s[k] for k in ("scene", "spp", "path")} for s in plan.sources]),
        "config": json.dumps(config.to_dict()),
        "config_hash": plan.config_hash,
        "content_key": plan.content_key,
        "command": config.command or " ".join(sys.argv),
    }


__all__ = [
    "FORMAT",
    "MANIFEST",
    "PATCH_DATASETS",
    "ImagePatches",
    "ShardConfig",
    "ShardEntry",
    "ShardError",
    "ShardSet",
    "build_shards",
    "discover_renders",
    "image_datasets",
    "open_shard",
    "round_name",
    "shard_name",
    "shard_paths",
    "split_scenes",
    "variance_patches",
    "write_shard",
]
