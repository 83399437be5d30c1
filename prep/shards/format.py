"""One shard file: its datasets, how they are stored, and its writing, opening, reading and checksums.

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
diffuse/ref_relse        (N, P, P, 1)     relative standard error of the diffuse reference, per pixel
specular/ref_relse       (N, P, P, 1)     likewise, specular (0 where the reference has no variance layer)
source                   (N,) int32       index into the manifest's (and the ``sources`` attribute's) sources
position                 (N, 2) int32     top-left (y, x) in the source render
round                    (N,) int32       sampling round
pdf                      (N,) float64     probability of the position under the round's PDF
=======================  ===============  ===============================================

The reference diffuse colour is divided by the reference's own albedo (a clean irradiance target). The
``ref_relse`` datasets are ``prep.convergence.branch_relse`` of the reference render, each branch from its own
colour and variance layer (a relative error is unchanged by the albedo division to first order); a reference
without that variance layer (another renderer's) has 0 there, i.e. full weight in a weighted loss.
Every per-patch dataset is a row of :data:`PATCH_DATASETS` (name -> channels) and nothing else: a new one is a
new row, cut by ``prep.shards.patches.image_datasets``.

A shard is written atomically under a per-process temporary name, marked ``complete`` inside last
(:func:`write_shard`), and opened only if it is a complete shard of this :data:`FORMAT` (:func:`open_shard`).
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

# /3 added the ref_relse datasets (issue 23); a shard or set of another format is refused with the command
# that rebuilds it (:func:`rebuild_hint`)
FORMAT = "kpcn-shard/3"
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
    "diffuse/ref_relse": 1,
    "specular/ref_relse": 1,
}
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


# The layouts `prep.studies.stage_costs.shard_layout_costs` measures side by side (docs/results.md §8 has the numbers).
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


def rebuild_hint(set_dir, set_name: str | None) -> str:
    """The command that rebuilds a shard set of another format: the folder removed, then ``kpcn shards``."""
    return f"rebuild it with 'rm -r {set_dir} && kpcn shards --set {set_name or '<set>'}'"


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


def write_shard(path: Path, patches: dict[str, np.ndarray], attrs: dict, layout: Layout = SHARD_LAYOUT) -> None:
    """Write one shard atomically: a per-process temporary name, ``complete`` attribute last, then rename.
    ``layout`` other than :data:`SHARD_LAYOUT` is for measuring (``prep.studies.stage_costs``).

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
    ``prep.studies.stage_costs``): the features and the reference, and the noisy colour for a loss that uses it
    (``noisy``: the asymmetric loss)."""
    return [f"{branch}/features", f"{branch}/reference"] + ([f"{branch}/noisy"] if noisy else [])


def read_patch(f, names, patch: int) -> dict[str, np.ndarray]:
    """Patch ``patch`` of the datasets ``names`` of an open shard (an h5py File, or a mapping of its datasets
    by name), float32 whatever the storage type: the one
    read a training batch makes per patch (``kpcn_keras.data``, timed by ``prep.studies.stage_costs``). OSError
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
    if found != FORMAT and complete and isinstance(found, str) and found.startswith(FORMAT.split("/")[0] + "/"):
        set_name = _set_name(f)
        f.close()
        raise ShardError(f"{path}: shard of format {found!r}, this kpcn reads {FORMAT!r}; "
                         f"{rebuild_hint(path.parent.parent, set_name)}")
    if found != FORMAT or not complete:
        f.close()
        raise ShardError(f"{path}: incomplete or foreign shard (format={found!r}, complete={complete}; "
                         f"expected {FORMAT!r})")
    if missing:
        f.close()
        raise ShardError(f"{path}: missing datasets {missing}")
    return f


def _set_name(f: h5py.File) -> str | None:
    """The set name a shard's ``config`` attribute records, if it can be read."""
    try:
        return json.loads(f.attrs["config"])["set_name"]
    except (KeyError, TypeError, ValueError):
        return None


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
