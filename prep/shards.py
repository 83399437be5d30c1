"""65x65 training patches in HDF5 shards (design.md "Shards").

Layout: ``<out_root>/<set>/round-<k>/shard-<i>.h5`` plus ``<out_root>/<set>/manifest.json``.
Each shard holds up to ``patches_per_shard`` patches of one split (train or val), one patch per
chunk (gzip + shuffle), in these datasets (N patches, P = patch size, channels last, float32):

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
source                   (N,) int32       index into the ``sources`` attribute
position                 (N, 2) int32     top-left (y, x) in the source render
round                    (N,) int32       sampling round
pdf                      (N,) float64     probability of the position under the round's PDF
=======================  ===============  ===============================================

The reference diffuse colour is divided by the reference's own albedo (a clean irradiance target).
A shard is written under a temporary name, marked ``complete`` and renamed; the manifest is written
last. :func:`open_shard` accepts only complete shards with a shard file name.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import sys
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from prep import exr, features, sampling
from prep.errors import KpcnError
from prep.files import atomic_write_text

log = logging.getLogger("kpcn")

FORMAT = "kpcn-shard/1"
MANIFEST = "manifest.json"
SHARD_RE = re.compile(r"^shard-(\d{5})\.h5$")
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


class ShardError(KpcnError, ValueError):
    """A shard or shard set that cannot be used; the message names the file and what was found."""


@dataclass
class ShardConfig:
    """Configuration of ``kpcn shards``; saved in the manifest and in every shard."""

    set_name: str = "default"
    render_root: str = "data/renders"
    out_root: str = "shards"
    patch_size: int = 65
    patches_per_image: int = 100
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
        checks = {
            "patch_size": self.patch_size >= 1,
            "patches_per_image": self.patches_per_image >= 1,
            "patches_per_shard": self.patches_per_shard >= 1,
            "val_fraction": 0.0 <= self.val_fraction < 1.0,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"ShardConfig.{name} is out of range: got {getattr(self, name)!r}")

    @property
    def render_dir(self) -> Path:
        return Path(self.render_root) / self.set_name

    @property
    def set_dir(self) -> Path:
        return Path(self.out_root) / self.set_name

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def content_hash(self) -> str:
        """Hash of everything that changes the shards' content (not the command line)."""
        d = self.to_dict()
        d.pop("command")
        d.pop("out_root")
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Source:
    scene: str
    spp: int
    path: str


def sha256_file(path: str | os.PathLike) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def discover_renders(render_dir: Path, input_spp: int | None = None) -> dict[str, dict]:
    """``scene -> {"reference": Source, "inputs": [Source, ...]}`` for a folder of renders.

    Within a scene the file with the most samples is the reference; ``input_spp`` keeps only inputs of
    that sample count. Errors name the folder or the scene.
    """
    if not render_dir.is_dir():
        raise ShardError(f"{render_dir}: no such render folder (run 'kpcn render' first)")
    by_scene: dict[str, list[Source]] = defaultdict(list)
    for path in sorted(render_dir.glob("*.exr")):
        if path.name.startswith("."):
            continue  # a renderer's temporary file
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


def cut_patches(noisy: dict, reference: dict, positions: np.ndarray, patch_size: int) -> dict[str, np.ndarray]:
    """Crop every per-patch dataset of the shard layout at ``positions`` (top-left y, x)."""
    full = {
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
    p = patch_size
    return {
        name: np.stack([image[y : y + p, x : x + p] for y, x in positions]).astype(np.float32)
        for name, image in full.items()
    }


def write_shard(path: Path, patches: dict[str, np.ndarray], attrs: dict) -> None:
    """Write one shard atomically: temporary name, ``complete`` attribute last, then rename."""
    tmp = path.with_name(f".{path.name}.tmp")
    try:
        with h5py.File(tmp, "w") as f:
            for name, data in patches.items():
                chunks = (1,) + data.shape[1:] if data.ndim > 1 else (min(len(data), 1024),)
                f.create_dataset(name, data=data, chunks=chunks, compression="gzip", compression_opts=1, shuffle=True)
            for key, value in attrs.items():
                f.attrs[key] = value
            f.attrs["complete"] = True
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def open_shard(path: str | os.PathLike) -> h5py.File:
    """Open a shard for reading; ShardError unless it is a complete shard of this format."""
    path = Path(path)
    if not SHARD_RE.match(path.name):
        raise ShardError(f"{path}: not a shard name (shard-NNNNN.h5); temporary files are never shards")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ShardError(f"{path}: not a readable HDF5 file ({exc})") from None
    found, complete = f.attrs.get("format"), bool(f.attrs.get("complete", False))
    if found != FORMAT or not complete:
        f.close()
        raise ShardError(f"{path}: incomplete or foreign shard (format={found!r}, complete={complete}; expected {FORMAT!r})")
    missing = [name for name in PATCH_DATASETS if name not in f]
    if missing:
        f.close()
        raise ShardError(f"{path}: missing datasets {missing}")
    return f


def _existing_shard_ok(path: Path, config_hash: str) -> bool:
    try:
        with open_shard(path) as f:
            return f.attrs.get("config_hash") == config_hash
    except ShardError:
        return False


def load_manifest(set_dir: str | os.PathLike) -> dict:
    path = Path(set_dir) / MANIFEST
    if not path.is_file():
        raise ShardError(f"{path}: no manifest (run 'kpcn shards' first)")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ShardError(f"{path}: unreadable manifest ({exc})") from None


def shard_paths(set_dir: str | os.PathLike, split: str) -> list[Path]:
    """The complete shards of ``split`` listed in the manifest of ``set_dir``, every round."""
    set_dir = Path(set_dir)
    manifest = load_manifest(set_dir)
    paths = [set_dir / s["path"] for r in manifest["rounds"].values() for s in r["shards"] if s["split"] == split]
    for p in paths:
        if not p.is_file():
            raise ShardError(f"{p}: listed in {set_dir / MANIFEST} but missing")
    return paths


def build_shards(config: ShardConfig, *, progress: bool = True) -> dict:
    """Cut round 0 of a shard set from a folder of renders; returns the manifest.

    Deterministic for a given config. Complete shards already written with the same configuration are
    kept, so an interrupted run resumes; shards of a different configuration are an error.
    """
    from tqdm import tqdm

    renders = discover_renders(config.render_dir, config.input_spp)
    split = split_scenes(list(renders), config.val_fraction, config.val_scenes)
    round_dir = config.set_dir / "round-000"
    round_dir.mkdir(parents=True, exist_ok=True)
    for stale in round_dir.glob(".shard-*.tmp"):
        stale.unlink()
    config_hash = config.content_hash()
    for existing in sorted(round_dir.glob("shard-*.h5")):
        if not _existing_shard_ok(existing, config_hash):
            raise ShardError(
                f"{existing}: written with another configuration or incomplete; "
                f"remove {round_dir} (or choose another --set) to rebuild"
            )

    sources: list[dict] = []
    sink = _ShardSink(round_dir, config, config_hash, sources)
    bar = tqdm(total=sum(len(renders[s]["inputs"]) for s in renders), desc="shards", unit="render",
               disable=not progress)
    for split_name in ("train", "val"):
        for scene in split[split_name]:
            ref_src = renders[scene]["reference"]
            reference = exr.read_aovs(ref_src.path, variances=False)
            sources.append(_source_record(ref_src, "reference", split_name))
            for src in renders[scene]["inputs"]:
                noisy = exr.read_aovs(src.path)
                if noisy["depth"].shape != reference["depth"].shape:
                    raise ShardError(
                        f"{src.path} is {noisy['depth'].shape[::-1]} but its reference {ref_src.path} is "
                        f"{reference['depth'].shape[::-1]}"
                    )
                source_id = len(sources)
                sources.append(_source_record(src, "input", split_name))
                rng = np.random.default_rng(np.random.SeedSequence([config.seed, source_id]))
                pdf = sampling.patch_pdf(
                    sampling.variance_importance(noisy, config.colour_weight, config.normal_weight),
                    config.patch_size,
                    config.uniform_mix,
                )
                count = min(config.patches_per_image, pdf.size)
                positions = sampling.draw_positions(pdf, count, rng)
                patches = cut_patches(noisy, reference, positions, config.patch_size)
                patches["source"] = np.full(count, source_id, dtype=np.int32)
                patches["position"] = positions
                patches["round"] = np.zeros(count, dtype=np.int32)
                patches["pdf"] = pdf[positions[:, 0], positions[:, 1]]
                sink.add(split_name, patches)
                bar.update(1)
        sink.flush()
    bar.close()
    shard_entries = sink.entries

    manifest = {
        "format": FORMAT,
        "set": config.set_name,
        "config": config.to_dict(),
        "config_hash": config_hash,
        "features": list(features.FEATURE_NAMES),
        "constants": {"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS},
        "patch_size": config.patch_size,
        "split": split,
        "sources": sources,
        "rounds": {"round-000": {"shards": shard_entries}},
    }
    atomic_write_text(config.set_dir / MANIFEST, json.dumps(manifest, indent=2))
    return manifest


class _ShardSink:
    """Collects patches of one split at a time into shards of ``patches_per_shard``, numbered in order.

    A shard that already exists (complete, same configuration: checked before any work) is kept as it
    is, which is what makes a rerun resume.
    """

    def __init__(self, round_dir: Path, config: ShardConfig, config_hash: str, sources: list[dict]):
        self.round_dir, self.config, self.config_hash, self.sources = round_dir, config, config_hash, sources
        self.entries: list[dict] = []
        self.split = ""
        self.pending: dict[str, list[np.ndarray]] = defaultdict(list)
        self.count = 0

    def add(self, split: str, patches: dict[str, np.ndarray]) -> None:
        if split != self.split:
            self.flush()
            self.split = split
        n, start = len(patches["source"]), 0
        while start < n:
            take = min(n - start, self.config.patches_per_shard - self.count)
            for name, values in patches.items():
                self.pending[name].append(values[start : start + take])
            self.count += take
            start += take
            if self.count == self.config.patches_per_shard:
                self.flush()

    def flush(self) -> None:
        if not self.count:
            return
        path = self.round_dir / f"shard-{len(self.entries):05d}.h5"
        if not path.exists():
            arrays = {name: np.concatenate(parts) for name, parts in self.pending.items()}
            write_shard(path, arrays, _shard_attrs(self.config, self.config_hash, self.split, self.sources))
        self.entries.append({"path": str(path.relative_to(self.config.set_dir)), "split": self.split,
                             "patches": self.count})
        self.pending, self.count = defaultdict(list), 0


def _source_record(src: Source, role: str, split: str) -> dict:
    return {"scene": src.scene, "spp": src.spp, "path": src.path, "role": role, "split": split, "sha256": sha256_file(src.path)}


def _shard_attrs(config: ShardConfig, config_hash: str, split: str, sources: list[dict]) -> dict:
    return {
        "format": FORMAT,
        "split": split,
        "patch_size": config.patch_size,
        "features": json.dumps(list(features.FEATURE_NAMES)),
        "transforms": "diffuse: log1p(diffuse / (albedo + ALBEDO_EPS)); specular: log1p(max(specular, 0))",
        "constants": json.dumps({"ALBEDO_EPS": features.ALBEDO_EPS, "REL_EPS": features.REL_EPS}),
        "sources": json.dumps([{k: s[k] for k in ("scene", "spp", "path")} for s in sources]),
        "config": json.dumps(config.to_dict()),
        "config_hash": config_hash,
        "command": config.command or " ".join(sys.argv),
    }
