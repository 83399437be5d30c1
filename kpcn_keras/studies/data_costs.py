"""What the offline stage's choices cost in time, as numbers for ``kpcn bench``.

No torch, no keras: only ``prep``. Every function returns a plain JSON-able dict (floats, ints, strings,
bools, lists and dicts of them). Times are seconds of wall clock in this process; each variant is measured
alternately with the others, ``repeats`` times, and the *best* repeat is reported for work that other
processes can only slow down (decoding, features, writing), the *median* for reads (their spread is the
point). Compilation is never timed: the features kernel is run once before any clock starts.

=====================================  ==================================================================
function                               measures
=====================================  ==================================================================
:func:`feature_costs`                  one render: EXR decode, the numba features (both branches) and
                                       the float64 numpy reference of the same formulas
                                       (``prep.features.reference_features``)
:func:`shard_layout_costs`             patches cut once from (noisy, reference) pairs, then written in
                                       every layout of ``prep.shards.LAYOUTS`` (write + checksum, as
                                       ``kpcn shards`` does per shard), their bytes, the read of a
                                       training batch, and that each reads back what was written
=====================================  ==================================================================

``kpcn shards`` end to end is timed as a command by ``kpcn_keras.studies.bench.shards_command_cost``.

Scratch: :func:`shard_layout_costs` writes only inside a fresh folder under
``out_dir`` (created if missing, not its parents) and remove it, and ``out_dir`` itself if they created it, also
when they fail. Nothing else is written. Reads are of files just written, so from the page cache: what training
sees on a machine whose memory holds the set.
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from prep import exr, features, shards
from prep.bounds import is_integer

# Batches read per repeat by shard_layout_costs: one batch is a handful of reads, too few to time alone.
BATCHES_PER_REPEAT = 4
# The training source whose batch read is timed (the cpu preset's first phase, SMAPE: no noisy colour).
READ_BRANCH = "diffuse"
# max_rel_error divides by max(|value|, this): the smallest normal float16, below which float16 keeps an
# absolute (not relative) precision, so rounding to float16 is within 2**-11 on this scale everywhere.
REL_ERROR_FLOOR = 2.0**-14


def _best(times: list[float]) -> float:
    return float(min(times))


def _check_repeats(repeats: int) -> None:
    if not is_integer(repeats) or repeats < 1:
        raise ValueError(f"repeats must be an integer >= 1, got {repeats!r}")


def _warm_features() -> None:
    """Compile (or load from numba's cache) the features kernel for float32 renders, outside any clock."""
    tiny = {name: np.zeros((2, 2, 3) if name in exr.RGB_LAYERS else (2, 2), np.float32)
            for name in exr.RGB_LAYERS + exr.SCALAR_LAYERS}
    for branch in features.BRANCHES:
        features.branch_features(tiny, branch)


@contextmanager
def _scratch(out_dir):
    """A fresh folder under ``out_dir``, removed afterwards with ``out_dir`` too if this made it."""
    out = Path(out_dir)
    created = not out.exists()
    out.mkdir(exist_ok=True)  # not its parents: nothing is written outside out_dir
    folder = Path(tempfile.mkdtemp(prefix=".stage-costs-", dir=out))
    try:
        yield folder
    finally:
        shutil.rmtree(folder, ignore_errors=True)
        if created:
            try:
                out.rmdir()
            except OSError:  # something else was put there meanwhile: not ours to remove
                pass


def feature_costs(render_path, repeats: int = 3) -> dict:
    """Decode of the render at ``render_path`` (a noisy input: variance layers needed) against its
    features, both branches, by the numba kernel and by the float64 numpy reference.

    Keys: ``render``, ``pixels``, ``repeats``, ``exr_decode_s``, ``numba_s``, ``numpy_s`` (best of
    ``repeats``), ``numba_pixels_per_s`` (pixels of one branch's features per second: both branches' pixels
    over ``numba_s``), ``numpy_over_numba`` and ``numba_over_decode`` (ratios of those times).
    """
    _check_repeats(repeats)
    _warm_features()
    aovs = exr.read_aovs(render_path)
    h, w = aovs["depth"].shape
    clocks = {"exr_decode_s": [], "numba_s": [], "numpy_s": []}
    work = {
        "exr_decode_s": lambda: exr.read_aovs(render_path),
        "numba_s": lambda: [features.branch_features(aovs, b) for b in features.BRANCHES],
        "numpy_s": lambda: [features.reference_features(aovs, b) for b in features.BRANCHES],
    }
    for _ in range(repeats):
        for key, fn in work.items():
            start = time.perf_counter()
            fn()
            clocks[key].append(time.perf_counter() - start)
    best = {key: _best(times) for key, times in clocks.items()}
    return {
        "render": str(render_path),
        "pixels": int(h * w),
        "repeats": repeats,
        **best,
        "numba_pixels_per_s": len(features.BRANCHES) * h * w / best["numba_s"],
        "numpy_over_numba": best["numpy_s"] / best["numba_s"],
        "numba_over_decode": best["numba_s"] / best["exr_decode_s"],
    }


def _cut_patches(render_pairs, patches_per_image: int, patch_size: int, seed: int) -> dict[str, np.ndarray]:
    """Round-0 patches of every pair, as ``kpcn shards`` cuts them (variance PDF, ``seed``), in one array
    per dataset."""
    config = shards.ShardConfig(patch_size=patch_size, patches_per_image=patches_per_image, seed=seed)
    out = shards.empty_patches(len(render_pairs) * patches_per_image, patch_size)
    for source_id, (noisy_path, reference_path) in enumerate(render_pairs):
        noisy = exr.read_aovs(noisy_path)
        reference = exr.read_aovs(reference_path, variances=None)  # its relSE, as kpcn shards cuts it
        size = noisy["depth"].shape
        if min(size) < patch_size:
            raise ValueError(f"{noisy_path} is {size[1]}x{size[0]}, smaller than a {patch_size}x{patch_size} "
                             "patch; pass a smaller patch_size")
        image = shards.variance_patches(noisy, reference, config, source_id)
        image.cut_into(0, patches_per_image, out, source_id * patches_per_image)
    return out


def shard_layout_costs(render_pairs: list[tuple[str, str]], out_dir, patches_per_image: int = 16,
                       batch_size: int = 8, repeats: int = 3, seed: int = 0, *, patch_size: int = 65,
                       layouts=None) -> dict:
    """Every layout of ``prep.shards.LAYOUTS`` (or the names in ``layouts``) on the same patches: one shard of
    ``patches_per_image`` patches from each (noisy, reference) render pair.

    Returns ``{"default": name of prep.shards.SHARD_LAYOUT, "patches": N, "patch_size", "batch_size",
    "repeats", "layouts": {name: {...}}}``, per layout: ``write_patches_per_s`` (``write_shard`` then the
    file's checksum, as ``kpcn shards`` does per shard; best of ``repeats``), ``bytes_per_patch`` (file size
    over N), ``read_batch_s`` (``batch_size`` random patches of the ``diffuse`` datasets, read one patch and
    at a time by ``prep.shards.read_patch``, the features recomputed, from files opened once: the training
    read; median over ``repeats`` x BATCHES_PER_REPEAT batches), ``dtype`` (``"table"``: each dataset's own,
    ``prep.shards.DATASETS``), ``compression``, ``patches_per_chunk``, ``max_abs_error`` and
    ``max_rel_error`` (every stored dataset read back against what was cut, in the table's dtypes, relative
    to max(|value|, REL_ERROR_FLOOR): 0 but where a layout overrides the dtype with float16, <= 2**-11 there)
    and ``exact``.
    """
    _check_repeats(repeats)
    if not render_pairs:
        raise ValueError("render_pairs is empty: give at least one (noisy, reference) render pair")
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    names = list(shards.LAYOUTS) if layouts is None else list(layouts)
    unknown = [n for n in names if n not in shards.LAYOUTS]
    if unknown:
        raise ValueError(f"layouts {unknown} are not among prep.shards.LAYOUTS ({', '.join(shards.LAYOUTS)})")
    _warm_features()
    patches = _cut_patches(render_pairs, patches_per_image, patch_size, seed)
    n = len(patches["source"])
    attrs = {"format": shards.FORMAT, "patch_size": patch_size}
    rng = np.random.default_rng(seed)
    write_s = {name: [] for name in names}
    read_s = {name: [] for name in names}
    result = {}
    with _scratch(out_dir) as scratch:
        paths = {name: scratch / name / shards.shard_name(0) for name in names}
        for path in paths.values():
            path.parent.mkdir()
        for _ in range(repeats):
            for name in names:
                path = paths[name]
                path.unlink(missing_ok=True)
                start = time.perf_counter()
                with np.errstate(over="ignore"):  # float16 overflow is measured below, not warned about
                    shards.write_shard(path, patches, attrs, shards.LAYOUTS[name])
                shards.shard_checksum(path)
                write_s[name].append(time.perf_counter() - start)
                with shards.open_shard(path) as f:
                    for _ in range(BATCHES_PER_REPEAT):
                        ids = rng.integers(0, n, batch_size)
                        start = time.perf_counter()
                        for i in ids:
                            shards.read_patch(f, shards.branch_datasets(READ_BRANCH), int(i))
                        read_s[name].append(time.perf_counter() - start)
        for name in names:
            layout = shards.LAYOUTS[name]
            with shards.open_shard(paths[name]) as f:
                abs_err, rel_err = 0.0, 0.0
                for dataset in shards.DATASETS:
                    got = f[dataset][()].astype(np.float64)
                    want = patches[dataset].astype(np.float64)
                    with np.errstate(invalid="ignore", over="ignore"):
                        diff = np.abs(got - want)
                        abs_err = max(abs_err, float(np.max(diff)))
                        rel_err = max(rel_err, float(np.max(diff / np.maximum(np.abs(want), REL_ERROR_FLOOR))))
                provenance_equal = all(np.array_equal(f[k][()], patches[k])
                                       for k in ("source", "position", "round", "pdf"))
            result[name] = {
                "write_patches_per_s": n / _best(write_s[name]),
                "bytes_per_patch": paths[name].stat().st_size / n,
                "read_batch_s": float(statistics.median(read_s[name])),
                "dtype": layout.dtype or "table",
                "compression": layout.compression or "none",
                "patches_per_chunk": layout.patches_per_chunk,
                "max_abs_error": abs_err,
                "max_rel_error": rel_err,
                "exact": abs_err == 0.0 and provenance_equal,
            }
    return {"default": shards.SHARD_LAYOUT.name, "patches": n, "patch_size": patch_size, "batch_size": batch_size,
            "repeats": repeats, "layouts": result}


__all__ = ["BATCHES_PER_REPEAT", "READ_BRANCH", "REL_ERROR_FLOOR", "feature_costs", "shard_layout_costs"]
