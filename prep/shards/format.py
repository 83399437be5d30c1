"""One shard file: its datasets, how they are stored, and its writing, opening, reading and checksums.

Each shard stores one patch per HDF5 chunk, uncompressed, each chunk with a Fletcher-32 checksum (the layout
:data:`SHARD_LAYOUT`; why not gzip, lzf or several patches a chunk: :data:`LAYOUTS`). Format ``kpcn-shard/4``
stores what the network features are *made of*, once, not the features: the per-pixel buffers of
``prep.features`` (``branch_buffers``: log colour, clipped normal and albedo, scaled depth, over the patch and
the next row and column, so that the forward differences at its border are the whole image's), the relative
variances, and the training targets. A reader gets the features by ``prep.features.features_from_buffers``,
the same function that makes them at render time (:func:`read_patches`). The datasets are the table
:data:`DATASETS` (N patches, P = patch size, channels last); what a reader asks for by name (:data:`VIEWS`
and every dataset read ``as is``) is float32:

====================  ===============  =======  ==========================================================
dataset               shape            dtype    content, and why this dtype
====================  ===============  =======  ==========================================================
diffuse/log_colour    (N, P+1, P+1, 3) float16  log(1 + irradiance): features 0-2 and what 3-5, 13-15 are
                                                differences of. A log value in [0, 94.5]: float16 keeps it
                                                to 2**-11 relative (at most 0.046), far below the noise
specular/log_colour   (N, P+1, P+1, 3) float16  log(1 + specular), likewise
guides                (N, P+1, P+1, 7) float16  clip(normal, -1, 1), clip(albedo, 0, 1), depth / max(depth),
                                                shared by both branches (their differences are features
                                                6-12, 16-22 of each). In [-1, 1]: 2**-11 relative
diffuse/relvar        (N, P, P, 1)     float16  feature 23 (relative colour variance), log(1 + .) in [0, 300]
specular/relvar       (N, P, P, 1)     float16  likewise
guide_relvar          (N, P, P, 3)     float16  features 24-26 (normal, albedo, depth), shared; as above
diffuse/reference     (N, P, P, 3)     float32  reference colour in the branch's log domain: the target a
                                                loss is held to, kept as it was computed
specular/reference    (N, P, P, 3)     float32  likewise
noisy                 (N, P, P, 3)     float32  noisy final colour, linear: HDR, float16 overflows at 65504
reference             (N, P, P, 3)     float32  reference final colour, linear: likewise
diffuse/ref_relse     (N, P, P, 1)     float16  relative standard error of the diffuse reference, per pixel,
                                                clipped to :data:`RELSE_MAX`: it only sets a loss weight
                                                (``kpcn_keras.losses``), which 2**-11 relative leaves as it
                                                is and which is 0 in float32 long before the clip
specular/ref_relse    (N, P, P, 1)     float16  likewise, specular (0 where the reference has no variance
                                                layer)
source                (N,) int32                index into the manifest's (and the ``sources`` attribute's)
                                                sources
position              (N, 2) int32              top-left (y, x) in the source render
round                 (N,) int32                sampling round
pdf                   (N,) float64              probability of the position under the round's PDF
====================  ===============  =======  ==========================================================

The reference diffuse colour is divided by the reference's own albedo (a clean irradiance target). The
``ref_relse`` datasets are ``prep.convergence.branch_relse`` of the reference render, each branch from its own
colour and variance layer (a relative error is unchanged by the albedo division to first order); a reference
without that variance layer (another renderer's) has 0 there, i.e. full weight in a weighted loss. At 65x65
a patch is 375 kB (:func:`patch_bytes`), 100,000 patches 38 GB; ``kpcn-shard/2`` stored the 27 features
of each branch in float32, 1.27 MB a patch (:func:`v2_patch_bytes`).

What a reader gets (:data:`VIEWS`, float32): ``{branch}/features`` (P, P, 27), recomputed;
``{branch}/noisy`` (P, P, 3), the noisy log colour (features 0-2); ``albedo`` (P, P, 3), the clipped noisy
albedo (what rebuilds the final colour: ``kpcn_keras.layers.FinalColour`` clips it anyway); and every
dataset of the table read ``as is``. Error of a recomputed feature against the float64 features of the same
render (``prep.features.reference_features``), u = 2**-11, each stored value v within u |v| (2**-25 absolute
below float16's smallest normal, 2**-14; 2u |v| in the last float16 step below its range's top, where
:func:`to_half` rounds down to stay inside the range): channels 0-2 and 23-26 within u |f| of the feature f; a
difference (3-22) of the buffer values a, b within u (|a| + |b|): at most 2u = 2**-10 for normal, albedo and
depth (values in [-1, 1]), u (2 |c| + |dc|) for colour. ``tests/test_compact_shards.py`` holds reads to it.

**Adding a dataset** is one entry of :data:`DATASETS` (name, channels, dtype, how it is read: ``as is``, served
float32 under its name, or ``features``, an input of the features that no reader asks for by name) and its
full-image array in ``prep.shards.patches.image_datasets``.

A shard is written atomically under a per-process temporary name, marked ``complete`` inside last
(:func:`write_shard`), and opened only if it is a complete shard of this :data:`FORMAT` (:func:`open_shard`;
a shard of an older ``kpcn-shard`` format is refused in one line naming the command that rebuilds its set).
Its checksum (:data:`SHARD_CHECKSUMS`), which the manifest lists (``prep.shards.shardset``), is what makes it
safe against a power cut, not an fsync. This module knows nothing of sets, rounds or renders.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
from h5py import h5s

from prep import features
from prep.errors import KpcnError
from prep.files import atomic_path, crc32_file, sha256_file
from prep.inputs import FULL

FORMAT_FAMILY = "kpcn-shard/"
FORMAT = FORMAT_FAMILY + "4"
SHARD_RE = re.compile(r"^shard-(\d{5})\.h5$")

# the largest float16: a stored relSE is clipped to it (a reference pixel that far from converged has weight 0)
RELSE_MAX = float(np.finfo(np.float16).max)

AS_IS = "as is"  # served float32 under its own name
FEATURES = "features"  # an input of the features (:data:`FEATURE_INPUTS`), not served by name


@dataclass(frozen=True)
class Dataset:
    """One per-patch dataset of a shard: (N, P + border, P + border, channels) of ``dtype``, read as ``read``
    says (:data:`AS_IS` or :data:`FEATURES`). ``border`` = 1: the patch and the next row and column, the
    neighbours that the forward differences at the patch's last row and column read."""

    name: str
    channels: int
    dtype: str
    read: str
    border: int = 0


# The module docstring's table, where each dtype is justified. An entry here is all a new dataset needs in
# this module.
DATASETS = {d.name: d for d in (
    Dataset("diffuse/log_colour", 3, "float16", FEATURES, border=1),
    Dataset("specular/log_colour", 3, "float16", FEATURES, border=1),
    Dataset("guides", 7, "float16", FEATURES, border=1),
    Dataset("diffuse/relvar", 1, "float16", FEATURES),
    Dataset("specular/relvar", 1, "float16", FEATURES),
    Dataset("guide_relvar", 3, "float16", FEATURES),
    Dataset("diffuse/reference", 3, "float32", AS_IS),
    Dataset("specular/reference", 3, "float32", AS_IS),
    Dataset("noisy", 3, "float32", AS_IS),
    Dataset("reference", 3, "float32", AS_IS),
    Dataset("diffuse/ref_relse", 1, "float16", AS_IS),
    Dataset("specular/ref_relse", 1, "float16", AS_IS),
)}
# What the features of a branch are made of (``prep.features.features_from_buffers``): the stored buffers and
# the stored relative variances, each the datasets concatenated along channels in this order.
FEATURE_INPUTS = {
    "buffers": ("{b}/log_colour", "guides"),
    "relvar": ("{b}/relvar", "guide_relvar"),
}
PROVENANCE = {"source": ((), np.int32), "position": ((2,), np.int32), "round": ((), np.int32),
              "pdf": ((), np.float64)}
assert sum(DATASETS[n.format(b="diffuse")].channels for n in FEATURE_INPUTS["buffers"]) == features.BUFFER_CHANNELS
assert sum(DATASETS[n.format(b="diffuse")].channels for n in FEATURE_INPUTS["relvar"]) == len(features.RELVARS)
# The guides' channels: features.BUFFERS after the colour. ``albedo`` (a view) is their albedo.
GUIDE_ALBEDO = slice(3, 6)


def _views() -> dict[str, tuple[str, ...]]:
    """Every name a reader may ask for, with the stored datasets it is read from."""
    out = {}
    for b in features.BRANCHES:
        out[f"{b}/features"] = tuple(n.format(b=b) for names in FEATURE_INPUTS.values() for n in names)
        out[f"{b}/noisy"] = (f"{b}/log_colour",)
    out["albedo"] = ("guides",)
    out.update({d.name: (d.name,) for d in DATASETS.values() if d.read == AS_IS})
    return out


VIEWS = _views()

# kpcn-shard/2's bytes a patch (float32, no border): the 27 features of both branches, the branch colours and
# references, the albedo and the final colours; what the compact format is measured against.
V2_CHANNELS = 2 * features.NUM_FEATURES + 4 * 3 + 3 * 3


def v2_patch_bytes(patch_size: int) -> int:
    """Bytes of one patch of ``kpcn-shard/2`` (its datasets' data, as :func:`patch_bytes` counts)."""
    return 4 * patch_size * patch_size * V2_CHANNELS


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
    a storage type overriding the table's for every float dataset (``None``: each dataset's own; readers get
    float32 whatever it is: :func:`read_patches`)."""

    name: str
    compression: str | None = None
    compression_opts: int | None = None
    shuffle: bool = False
    patches_per_chunk: int | None = 1
    fletcher32: bool = True
    dtype: str | None = None


# The layouts `kpcn_keras.studies.data_costs.shard_layout_costs` measures side by side
# (docs/results/08-shard-layouts.md has the numbers of kpcn-shard/2, all float32). gzip (what shards were written
# with before) and lzf compress slower than the uncompressed bytes are written and hashed (for the manifest), and
# a training batch reads 4-8x slower from them. Several patches per chunk make a random patch read its whole
# chunk. float16 for every dataset (the table keeps the targets and linear colours float32) overflows linear
# colours above 65504.
# Contiguous datasets (no chunks, so no Fletcher-32) read a batch ~4x faster but write slower: HDF5 spends
# ~3x the system time on them. The chunked ones keep a Fletcher-32 checksum per chunk, so a chunk damaged
# after the manifest's check is an error when read, not silent garbage: ~40 % of the HDF5 time of a write
# and 60 % of a batch read's.
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


def shard_name(i: int) -> str:
    return f"shard-{int(i):05d}.h5"


def to_half(values: np.ndarray, top: float) -> np.ndarray:
    """``values`` (>= 0, <= ``top``) in float16, each rounded to nearest, but never past the largest float16 <=
    ``top``: rounding up at the top of a feature's range (LOG_COLOUR_MAX's 94.48 is 94.5 in float16) would
    read back outside it. So a value is within u |v| (u = 2**-11), 2u |v| in its range's last float16 step."""
    top16 = np.float16(top)
    if float(top16) > top:
        top16 = np.nextafter(top16, np.float16(0))
    return np.minimum(np.asarray(values).astype(np.float16), top16)


def dataset_shape(dataset: Dataset, patch_size: int) -> tuple[int, int, int]:
    """The shape of one patch of ``dataset``."""
    side = patch_size + dataset.border
    return (side, side, dataset.channels)


def patch_bytes(patch_size: int) -> int:
    """Bytes of one patch of every dataset of the table, as stored (the data; HDF5's own is ~1 % more)."""
    return sum(int(np.prod(dataset_shape(d, patch_size))) * np.dtype(d.dtype).itemsize for d in DATASETS.values()) \
        + sum(int(np.prod(shape or (1,))) * np.dtype(dtype).itemsize for shape, dtype in PROVENANCE.values())


def empty_patches(count: int, patch_size: int) -> dict[str, np.ndarray]:
    """Uninitialised arrays of ``count`` patches of every dataset of the table, in its storage type, to cut
    patches into (``prep.shards.patches``), and of the provenance."""
    out = {d.name: np.empty((count,) + dataset_shape(d, patch_size), d.dtype) for d in DATASETS.values()}
    out.update({name: np.empty((count,) + shape, dtype) for name, (shape, dtype) in PROVENANCE.items()})
    return out


def write_shard(path: Path, patches: dict[str, np.ndarray], attrs: dict, layout: Layout = SHARD_LAYOUT) -> None:
    """Write one shard atomically: a per-process temporary name, ``complete`` attribute last, then rename.
    ``layout`` other than :data:`SHARD_LAYOUT` is for measuring (``kpcn_keras.studies.data_costs``).

    Not fsync'ed (``atomic_path(durable=False)``): waiting for the disk was most of ``kpcn shards`` (a set
    was ~1.2 MB a patch in kpcn-shard/2; this disk takes ~430 MB/s), and a shard needs no fsync to be safe, since its
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
                if layout.dtype is not None and name in DATASETS:
                    data = data.astype(layout.dtype, copy=False)
                data = np.ascontiguousarray(data)
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
    """The names a training batch of one branch reads per patch (``kpcn_keras.data``; timed by
    ``kpcn_keras.studies.data_costs``): the features and the reference, and the noisy colour for a loss that uses it
    (``noisy``: the asymmetric loss)."""
    return [f"{branch}/features", f"{branch}/reference"] + ([f"{branch}/noisy"] if noisy else [])


def stored_datasets(names) -> list[str]:
    """The stored datasets that the names ``names`` (:data:`VIEWS`) are read from, each once, in table order."""
    unknown = [n for n in names if n not in VIEWS]
    if unknown:
        raise KeyError(f"{unknown} are not datasets of a {FORMAT} shard (those read: {', '.join(VIEWS)})")
    wanted = {stored for n in names for stored in VIEWS[n]}
    return [name for name in DATASETS if name in wanted]


def read_stored(f, names, patch: int) -> dict[str, np.ndarray]:
    """Patch ``patch`` of the stored datasets ``names`` of an open shard (an h5py File, or a mapping of its
    datasets by name), as stored: one chunk read each. OSError (a chunk whose checksum fails) is the caller's
    to name."""
    return {name: f[name][patch] for name in names}


def derive(stored: dict[str, np.ndarray], names, patch_size: int) -> dict[str, np.ndarray]:
    """The names ``names`` (:data:`VIEWS`), float32, from stored datasets of one or more patches (leading axes
    alike, e.g. a batch: (B, ...)): the features recomputed by ``prep.features.features_from_buffers``, once
    for the whole batch."""
    p = patch_size
    out = {}
    for name in names:
        if name.endswith("/features"):
            b = name.split("/")[0]
            inputs = {key: np.concatenate([stored[n.format(b=b)] for n in parts], axis=-1)
                      for key, parts in FEATURE_INPUTS.items()}
            out[name] = features.features_from_buffers(inputs["buffers"], inputs["relvar"])
        elif name.endswith("/noisy") and name not in DATASETS:
            out[name] = np.asarray(stored[VIEWS[name][0]][..., :p, :p, :], np.float32)
        elif name == "albedo":
            out[name] = np.asarray(stored["guides"][..., :p, :p, GUIDE_ALBEDO], np.float32)
        else:
            out[name] = np.asarray(stored[name][..., :p, :p, :], np.float32)
    return out


def read_patches(f, names, patches, patch_size: int | None = None) -> dict[str, np.ndarray]:
    """Patches ``patches`` (a sequence of indices) of the names ``names`` of an open shard, float32, stacked
    (len(patches), P, P, C): each stored dataset read one patch (one chunk) at a time, then :func:`derive` on
    the batch. ``patch_size`` defaults to the shard's attribute (``f`` a mapping of datasets: pass it)."""
    stored = stored_datasets(names)
    if patch_size is None:
        patch_size = int(f.attrs["patch_size"])
    batch = [read_stored(f, stored, int(i)) for i in patches]
    if not batch:  # no patches: (0, ...) arrays of each name's shape
        return derive({n: np.empty((0,) + f[n].shape[1:], f[n].dtype) for n in stored}, names, patch_size)
    return derive({n: np.stack([b[n] for b in batch]) for n in stored}, names, patch_size)


def read_patch(f, names, patch: int, patch_size: int | None = None) -> dict[str, np.ndarray]:
    """Patch ``patch`` of the names ``names`` (:data:`VIEWS`) of an open shard, float32: :func:`read_patches`
    of one patch. OSError (a chunk whose checksum fails) is the caller's to name."""
    return {n: a[0] for n, a in read_patches(f, names, [patch], patch_size).items()}


def rebuild_command(config) -> str:
    """The commands that rebuild a shard set, as a refusal names them, from its configuration (a set's
    ``config``, a dict; None where it cannot be read): a set of another input set than the full one is
    rebuilt with its ``--inputs``."""
    config = config if isinstance(config, dict) else {}
    name = config.get("set_name") or "NAME"
    inputs = config.get("inputs")
    if inputs and inputs != FULL.name:
        return f"'kpcn shards --set {name} --inputs {inputs}'"
    return f"'kpcn shards --set {name}' (or 'make shards SET={name}')"


def older_format(found) -> bool:
    """Whether ``found`` (a shard's or manifest's ``format``) is another kpcn-shard format than this one: a
    set that ``kpcn shards`` rebuilds rather than refuses to touch."""
    return isinstance(found, str) and found.startswith(FORMAT_FAMILY) and found != FORMAT


def open_shard(path: str | os.PathLike) -> h5py.File:
    """Open a shard for reading; ShardError unless it is a complete shard of this format (one line naming
    the file, the format found and the command that rebuilds its set, for a shard of an older format)."""
    path = Path(path)
    if not SHARD_RE.match(path.name):
        raise ShardError(f"{path}: not a shard name (shard-NNNNN.h5); temporary files are never shards")
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise ShardError(f"{path}: not a readable HDF5 file ({exc})") from None
    try:
        found, complete = f.attrs.get("format"), bool(f.attrs.get("complete", False))
        missing = [name for name in [*DATASETS, *PROVENANCE] if name not in f]
        config = f.attrs.get("config") if older_format(found) else None
    except (OSError, RuntimeError, KeyError) as exc:
        f.close()
        raise ShardError(f"{path}: damaged HDF5 file ({exc})") from None
    if older_format(found):
        f.close()
        try:
            config = json.loads(config) if config else None
        except ValueError:
            config = None
        raise ShardError(f"{path}: a shard of format {found!r}, this kpcn reads {FORMAT!r}; rebuild the set with "
                         f"{rebuild_command(config)}")
    if found != FORMAT or not complete:
        f.close()
        raise ShardError(f"{path}: incomplete or foreign shard (format={found!r}, complete={complete}; "
                         f"expected {FORMAT!r})")
    if missing:
        f.close()
        raise ShardError(f"{path}: missing datasets {missing}")
    return f


def config_hash_of(path: Path) -> str | None:
    try:
        with open_shard(path) as f:
            return f.attrs.get("config_hash")
    except ShardError:
        return None


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
