"""The compact shard format (prep.shards.format, kpcn-shard/4): what a reader gets back, the features
recomputed from the stored half-float buffers, against float64 features computed directly from the same
render, within the bound the format documents; its bytes per patch; and the refusal of an older set."""

import json

import h5py
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.tiny import build_tiny_shards, random_aovs

from prep import colour, exr, features, shards
from prep.inputs import FULL
from prep.shards.patches import shard_layers

U = 2.0**-11  # float16's unit roundoff: a stored value v is within U |v|
TINY = 2.0**-25  # half float16's smallest subnormal step: the absolute error below its smallest normal
F32 = 2.0**-23  # float32 rounding of a read value, twice over


def _buffers64(aovs: dict, branch: str) -> np.ndarray:
    """The float64 per-pixel buffers (log colour, clipped normal and albedo, scaled depth) of the whole image,
    from the formulas of prep.features' table, independently of it."""
    a = np.clip(aovs["albedo"].astype(np.float64), 0.0, 1.0)
    x = aovs[branch].astype(np.float64)
    if branch == "diffuse":
        x = x / (a + colour.ALBEDO_EPS)
    depth = np.maximum(aovs["depth"].astype(np.float64), 0.0)
    return np.concatenate([np.log1p(np.maximum(x, 0.0)), np.clip(aovs["normal"].astype(np.float64), -1.0, 1.0), a,
                           (depth / depth.max())[..., None]], axis=-1)


def _bound(aovs: dict, branch: str, y: int, x: int, p: int) -> np.ndarray:
    """The documented error bound of each recomputed feature of the patch at (y, x) (docs/formats.md §4):
    U |f| for a value (0-2, 23-26), U (|a| + |b|) for a difference of the buffer values a, b (3-22)."""
    want = features.reference_features(aovs, branch)[y:y + p, x:x + p]
    buf = _buffers64(aovs, branch)
    h, w = buf.shape[:2]
    here = buf[y:y + p, x:x + p]
    right = buf[y:y + p, np.minimum(np.arange(x, x + p) + 1, w - 1)]
    below = buf[np.minimum(np.arange(y, y + p) + 1, h - 1), x:x + p]
    out = np.empty_like(want)
    out[..., 0:3] = U * np.abs(want[..., 0:3]) + TINY
    out[..., 3:13] = U * (np.abs(here) + np.abs(right)) + 2 * TINY
    out[..., 13:23] = U * (np.abs(here) + np.abs(below)) + 2 * TINY
    out[..., 23:27] = U * np.abs(want[..., 23:27]) + TINY
    return out + F32 * np.abs(want), want


@pytest.fixture
def compact_shard(tmp_path, fixture_noisy, fixture_reference):
    """One shard of 16x16 patches of the fixture render, at its corners (the last row and column, where
    the differences are 0) and inside (where a patch's border differences are the image's)."""
    # as the writer reads them: a reference without variance layers is given zeros (ref_relse 0)
    noisy, reference = shard_layers(exr.read_aovs(fixture_noisy), exr.read_aovs(fixture_reference, variances=None),
                                    FULL)
    h, w = noisy["depth"].shape
    p = 16
    positions = np.array([(0, 0), (h - p, w - p), (h - p, 5), (7, w - p), (20, 31)], np.int32)
    image = shards.ImagePatches.at(noisy, reference, positions, np.full(len(positions), 0.1), source_id=0, round=0,
                                   patch_size=p)
    path = tmp_path / shards.shard_name(0)
    shards.write_shard(path, image.cut(0, len(positions)), {"format": shards.FORMAT, "patch_size": p})
    return path, noisy, reference, positions, p


def test_a_compact_shard_reads_back_the_full_precision_features_within_the_documented_bound(compact_shard):
    path, noisy, reference, positions, p = compact_shard
    with shards.open_shard(path) as f:
        got = shards.read_patches(f, list(shards.VIEWS), range(len(positions)))
    worst = 0.0
    for k, (y, x) in enumerate(positions):
        win = np.s_[y:y + p, x:x + p]
        for branch in features.BRANCHES:
            bound, want = _bound(noisy, branch, y, x, p)
            err = np.abs(got[f"{branch}/features"][k] - want)
            assert (err <= bound).all(), (branch, k, np.argwhere(err > bound)[:5], (err / bound).max())
            worst = max(worst, float((err / bound).max()))
            colour = want[..., 0:3]
            assert (np.abs(got[f"{branch}/noisy"][k] - colour) <= U * np.abs(colour) + TINY + F32 * colour).all()
            # the targets are stored float32 as computed: exact
            np.testing.assert_array_equal(got[f"{branch}/reference"][k],
                                          features.branch_colour(reference, branch)[win])
        albedo = np.clip(noisy["albedo"][win].astype(np.float64), 0.0, 1.0)
        assert (np.abs(got["albedo"][k] - albedo) <= U * albedo + TINY).all()
        np.testing.assert_array_equal(got["noisy"][k], noisy["default"][win])
        np.testing.assert_array_equal(got["reference"][k], reference["default"][win])
    # the bound is met with little to spare: the buffers really are float16 (float32 would use ~1e-4 of it)
    assert worst > 0.1


def test_the_border_carries_the_true_differences_of_an_inner_patch(compact_shard):
    # guards the bound above: features computed from the patch alone (the differences 0 on its last row and
    # column) are far outside it, so the test would see a shard without the border
    path, noisy, _, positions, p = compact_shard
    k = 4
    y, x = positions[k]
    with shards.open_shard(path) as f:
        got = shards.read_patch(f, ["diffuse/features"], k)["diffuse/features"]
    alone = features.branch_features({n: a[y:y + p, x:x + p] for n, a in noisy.items()}, "diffuse",
                                     scale=features.depth_scale(noisy["depth"]))
    bound, want = _bound(noisy, "diffuse", y, x, p)
    assert (np.abs(alone - want) > bound).any()
    assert not (np.abs(got[-1, :, 13:23]) == 0).all()  # the image's differences at the patch's last row


def test_features_from_float64_buffers_are_the_render_time_features_bit_for_bit():
    # one function makes the features at render time and at read time (prep.features.features_from_buffers)
    aovs = random_aovs(23, 31, seed=4)
    for branch in features.BRANCHES:
        buffers, relvar = features.branch_buffers(aovs, branch)
        np.testing.assert_array_equal(features.features_from_buffers(buffers, relvar),
                                      features.branch_features(aovs, branch))
        np.testing.assert_allclose(features.features_from_buffers(buffers, relvar),
                                   features.reference_features(aovs, branch), rtol=1e-6, atol=1e-6)
        # batched: one call for a stack of patches equals each patch's own
        stack = features.features_from_buffers(np.stack([buffers, buffers[::-1].copy()]),
                                               np.stack([relvar, relvar]))
        np.testing.assert_array_equal(stack[0], features.features_from_buffers(buffers, relvar))


def test_a_patch_of_the_default_size_fits_100000_in_40_GB(tmp_path):
    p = shards.ShardConfig().patch_size  # the default, 65
    noisy, reference = random_aovs(p + 9, p + 7, seed=1), random_aovs(p + 9, p + 7, seed=2)
    n = 6
    rng = np.random.default_rng(0)
    positions = np.stack([rng.integers(0, 10, n), rng.integers(0, 8, n)], axis=1).astype(np.int32)
    image = shards.ImagePatches.at(noisy, reference, positions, np.ones(n), source_id=0, round=0, patch_size=p)
    path = tmp_path / shards.shard_name(0)
    shards.write_shard(path, image.cut(0, n), {"format": shards.FORMAT, "patch_size": p})
    on_disk = path.stat().st_size / n  # the data, HDF5's chunk index and headers shared by only n patches
    assert shards.patch_bytes(p) <= on_disk < 400_000
    assert on_disk * 100_000 <= 40e9
    assert shards.v2_patch_bytes(p) == 4 * p * p * 75 and shards.v2_patch_bytes(p) > 3 * shards.patch_bytes(p)
    with h5py.File(path) as f:  # one patch per chunk, each with its checksum, as before
        for name, dataset in shards.DATASETS.items():
            assert f[name].chunks == (1,) + shards.format.dataset_shape(dataset, p) and f[name].fletcher32, name
            assert f[name].dtype == np.dtype(dataset.dtype), name


def _make_old(set_dir):
    """The set in ``set_dir`` made as kpcn-shard/2 left it: the format in its manifest and in its shards."""
    manifest_path = set_dir / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    manifest["format"] = "kpcn-shard/2"
    manifest_path.write_text(json.dumps(manifest))
    old = next(set_dir.glob("round-000/shard-*.h5"))
    with h5py.File(old, "a") as f:
        f.attrs["format"] = "kpcn-shard/2"
    return manifest_path, old


def test_an_older_set_is_refused_in_one_line_naming_the_rebuild_and_kpcn_shards_rebuilds_it(tmp_path):
    cfg = build_tiny_shards(tmp_path)
    manifest_path, old_shard = _make_old(cfg.set_dir)
    with pytest.raises(shards.ShardError) as exc:
        shards.open_shard(old_shard)
    for needle in (str(old_shard), "'kpcn-shard/2'", "kpcn shards --set s", "make shards SET=s"):
        assert needle in str(exc.value)
    res = run_main("train", "--set", "s", "--shards", cfg.out_root, "--run", tmp_path / "runs" / "r", cwd=tmp_path)
    assert_one_line_error(res, str(manifest_path), "'kpcn-shard/2'", "kpcn shards --set s")
    assert not (tmp_path / "runs" / "r").exists()
    res = run_main("shards", "--set", "s", "--renders", cfg.render_root, "--out", cfg.out_root,
                   "--patch-size", 16, "--patches-per-image", 7, "--patches-per-shard", 5, "--val-fraction", 0.5,
                   "--seed", 3, cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-2000:]
    assert json.loads(manifest_path.read_text())["format"] == shards.FORMAT
    assert shards.ShardSet(cfg.set_dir).verified_shards("train")


def test_the_format_benchmark_counts_the_table_and_the_files_and_times_both_reads(tmp_path):
    from kpcn_keras.studies import bench_stages

    cfg = build_tiny_shards(tmp_path)
    paths = shards.shard_paths(cfg.set_dir, "train")
    got = bench_stages.shard_bytes(paths, 16)
    assert got[shards.FORMAT] == shards.patch_bytes(16) <= got["file"] and got["kpcn-shard/2"] == 4 * 16 * 16 * 75
    assert got["patches_in_40GB"] == int(40e9 // got["file"])
    times = bench_stages.read_only_costs(paths[0], batch_size=2)
    assert times["compact_s"] > 0 and times["v2_s"] > 0
    assert not list(paths[0].parent.glob(".v2-*"))  # its copy in the old layout is removed


def test_the_rebuild_named_for_a_set_of_another_input_set_carries_its_inputs():
    assert shards.format.rebuild_command({"set_name": "d", "inputs": "no-split"}) == \
        "'kpcn shards --set d --inputs no-split'"
    assert "'kpcn shards --set d'" in shards.format.rebuild_command({"set_name": "d"})
    assert "'kpcn shards --set NAME'" in shards.format.rebuild_command(None)
