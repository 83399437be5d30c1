"""65x65 training patches in HDF5 shards (docs/formats.md §4): what ``kpcn shards`` and the error rounds of
``kpcn resample`` write, and what training reads.

A shard set is the folder ``<out_root>/<set>/`` (``<out_root>/<set>.<inputs>/`` for an input set other than
the full one: ``config.shard_set_dir``; :class:`ShardSet` owns its layout). ``round-000`` is cut by
``kpcn shards`` from each input's variance PDF (:func:`build_shards`); round k >= 1 is an error round
(:func:`build_error_round`), drawn from a model's error. Every round goes through the same per-image step
(:func:`round_pdf` → :func:`draw` → :class:`ImagePatches` → a shard) and the same writer.

One job per module, each stating its contract in its docstring; each imports only modules above it in
this table (never the package itself, whose names are the interface for the rest of kpcn):

===============  =========================================================================================
module           job
===============  =========================================================================================
``format``       one shard file: its dataset table, storage layouts, writing, opening, reading, checksums
``config``       :class:`ShardConfig`: the options of ``kpcn shards``, checked, and their content hash
``shardset``     :class:`ShardSet`: the set's folder, manifest and round names; the shards a reader may take
``renders``      the set's sources: finding the renders, the split, checking them against the options
``patches``      the per-image step: a round's PDF over an input's positions, the draw, the cut patches
``writer``       writing one round's shards in worker processes, resumably, the same bytes for any number
``build``        round 0 (``kpcn shards``), whole or in parts, and the merge of the parts' lists
``rounds``       error rounds (``kpcn resample``): their plan, drawn first, then their shards
===============  =========================================================================================
"""

from prep.shards.build import build_shards
from prep.shards.config import PATCH_SIZE, ShardConfig, shard_set_dir
from prep.shards.format import (
    DATASETS,
    FORMAT,
    LAYOUTS,
    SHARD_LAYOUT,
    VIEWS,
    Dataset,
    Layout,
    ShardError,
    branch_datasets,
    derive,
    empty_patches,
    open_shard,
    patch_bytes,
    read_patch,
    read_patches,
    read_stored,
    shard_checksum,
    shard_name,
    stored_datasets,
    v2_patch_bytes,
    write_shard,
)
from prep.shards.patches import ImagePatches, draw, image_datasets, round_pdf, shard_layers, variance_patches
from prep.shards.renders import discover_renders, split_scenes
from prep.shards.rounds import ErrorRound, RoundResult, build_error_round, training_inputs, used_positions
from prep.shards.shardset import MANIFEST, ShardEntry, ShardSet, round_index, round_name, shard_paths

__all__ = [
    "DATASETS",
    "FORMAT",
    "MANIFEST",
    "PATCH_SIZE",
    "ErrorRound",
    "ImagePatches",
    "LAYOUTS",
    "Layout",
    "SHARD_LAYOUT",
    "VIEWS",
    "Dataset",
    "RoundResult",
    "ShardConfig",
    "ShardEntry",
    "ShardError",
    "ShardSet",
    "build_error_round",
    "branch_datasets",
    "build_shards",
    "discover_renders",
    "derive",
    "draw",
    "empty_patches",
    "image_datasets",
    "open_shard",
    "patch_bytes",
    "read_patch",
    "read_patches",
    "read_stored",
    "round_index",
    "round_name",
    "round_pdf",
    "shard_checksum",
    "shard_name",
    "shard_layers",
    "shard_paths",
    "shard_set_dir",
    "split_scenes",
    "stored_datasets",
    "training_inputs",
    "used_positions",
    "v2_patch_bytes",
    "variance_patches",
    "write_shard",
]
