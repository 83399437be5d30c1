import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, kpcn
from helpers.files import checksums
from helpers.references import assert_read_features_close, reference_importance, reference_pdf, reference_relse
from helpers.tiny import make_renders, random_aovs

from prep import exr, features, shards
from prep.files import is_temporary

REPO = Path(__file__).resolve().parents[1]


def config(tmp_path, **kw):
    values = dict(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                  patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3)
    values.update(kw)
    return shards.ShardConfig(**values)


def stored_patches(cfg, manifest):
    """Every patch of the shard set ``cfg`` cut (``manifest``, its manifest), shard by shard, as ``(split, shard,
    k, source, reference)``: the open shard file, the patch's index in it, its source's manifest record and the
    resolved path of its scene's reference."""
    sset = shards.ShardSet(cfg.set_dir)
    for split in ("train", "val"):
        for path in shards.shard_paths(cfg.set_dir, split):
            with shards.open_shard(path) as f:
                for k in range(len(f["source"])):
                    src = manifest["sources"][int(f["source"][k])]
                    ref = next(s["path"] for s in manifest["sources"]
                               if s["scene"] == src["scene"] and s["role"] == "reference")
                    yield split, f, k, src, sset.resolve(ref)


@pytest.fixture
def render_set(tmp_path):
    return make_renders(tmp_path / "renders" / "s")


@pytest.mark.slow
def test_shard_patches_equal_crops_of_the_source(tmp_path, render_set):
    cfg = config(tmp_path)
    manifest = shards.build_shards(cfg, progress=False)
    sset = shards.ShardSet(cfg.set_dir)
    seen = 0
    for split, f, k, src, ref_path in stored_patches(cfg, manifest):
        assert f.attrs["split"] == split
        assert src["role"] == "input" and src["split"] == split
        noisy = exr.read_aovs(sset.resolve(src["path"]))
        ref = exr.read_aovs(ref_path, variances=False)
        y, x = f["position"][k]
        win = np.s_[y:y + 16, x:x + 16]
        got = shards.read_patch(f, list(shards.VIEWS), k)
        for branch in features.BRANCHES:
            assert_read_features_close(got[f"{branch}/features"], features.branch_features(noisy, branch)[win],
                                       branch)
            np.testing.assert_array_equal(got[f"{branch}/reference"], features.branch_colour(ref, branch)[win])
        np.testing.assert_array_equal(got["reference"], ref["default"][win])
        np.testing.assert_allclose(got["albedo"], noisy["albedo"][win], rtol=2.0**-11, atol=2.0**-25)
        assert f["guides"].chunks == (1, 17, 17, 7)
        seen += 1
    assert seen == 4 * 7
    assert json.loads((cfg.set_dir / "manifest.json").read_text())["config_hash"] == cfg.content_hash()


@pytest.mark.slow
def test_split_is_by_scene_never_by_patch(tmp_path, render_set):
    manifest = shards.build_shards(config(tmp_path), progress=False)
    assert manifest["split"] == {"train": ["a-000", "b-000"], "val": ["a-001", "b-001"]}
    train = {s["scene"] for s in manifest["sources"] if s["split"] == "train"}
    val = {s["scene"] for s in manifest["sources"] if s["split"] == "val"}
    assert not train & val


@pytest.mark.slow
def test_same_seed_same_shards_and_a_second_run_keeps_them(tmp_path, render_set):
    a = config(tmp_path, out_root=str(tmp_path / "one"))
    b = config(tmp_path, out_root=str(tmp_path / "two"))
    shards.build_shards(a, progress=False)
    shards.build_shards(b, progress=False)
    for pa, pb in zip(shards.shard_paths(a.set_dir, "train"), shards.shard_paths(b.set_dir, "train")):
        with h5py.File(pa) as fa, h5py.File(pb) as fb:
            np.testing.assert_array_equal(fa["position"][()], fb["position"][()])
            for name in shards.DATASETS:
                np.testing.assert_array_equal(fa[name][()], fb[name][()], err_msg=name)
    first = shards.shard_paths(a.set_dir, "train")[0]
    mtime = first.stat().st_mtime_ns
    shards.build_shards(a, progress=False)
    assert first.stat().st_mtime_ns == mtime


@pytest.mark.slow
def test_other_configuration_over_existing_shards_is_refused(tmp_path, render_set):
    shards.build_shards(config(tmp_path), progress=False)
    with pytest.raises(shards.ShardError, match="another configuration"):
        shards.build_shards(config(tmp_path, seed=4), progress=False)


@pytest.mark.slow
def test_interrupted_write_leaves_nothing_a_reader_accepts(tmp_path):
    out = tmp_path / "killed"
    out.mkdir()
    # uncompressed shards are written too fast to be caught mid-write by timing alone: every dataset
    # is held back a while, so the kill lands inside the writer whatever the machine
    script = f"""
import time, h5py, numpy as np, sys
sys.path.insert(0, {str(REPO)!r})
from pathlib import Path
from prep import shards
create = h5py.Group.create_dataset
def slow_create(self, *args, **kwargs):
    out = create(self, *args, **kwargs)
    time.sleep(0.5)
    return out
h5py.Group.create_dataset = slow_create
rng = np.random.default_rng(0)
arrays = shards.empty_patches(40, 65)
for name in shards.DATASETS:
    arrays[name][...] = rng.normal(size=arrays[name].shape)
print('ready', flush=True)
shards.write_shard(Path({str(out)!r}) / 'shard-00000.h5', arrays, {{'format': shards.FORMAT}})
"""
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready"
    deadline = time.time() + 60
    while not list(out.glob(".shard-00000.h5.tmp-*")) and time.time() < deadline:
        time.sleep(0.01)
    time.sleep(0.3)  # let it write part of the file
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert not (out / "shard-00000.h5").exists(), "the writer should still have been busy when killed"
    leftovers = list(out.iterdir())
    assert leftovers, "a temporary file should remain after a kill"
    for path in leftovers:
        with pytest.raises(shards.ShardError):
            shards.open_shard(path)


def test_reader_rejects_incomplete_and_foreign_files(tmp_path):
    path = tmp_path / "shard-00000.h5"
    with h5py.File(path, "w") as f:
        f.attrs["format"] = shards.FORMAT  # never marked complete
    with pytest.raises(shards.ShardError, match="incomplete"):
        shards.open_shard(path)
    path.write_bytes(b"truncated")
    with pytest.raises(shards.ShardError, match="not a readable HDF5"):
        shards.open_shard(path)


@pytest.mark.slow
def test_rerun_after_a_kill_completes_the_set(tmp_path, render_set):
    cfg = config(tmp_path)
    manifest = shards.build_shards(cfg, progress=False)
    # a kill between shards: the last shard and the manifest are gone, a temporary file is left
    last = cfg.set_dir / manifest["rounds"]["round-000"]["shards"][-1]["path"]
    last.rename(last.with_name(f".{last.name}.tmp-123-abcd.h5"))
    (cfg.set_dir / "manifest.json").unlink()
    again = shards.build_shards(cfg, progress=False)
    assert again == manifest
    assert last.is_file() and not list(last.parent.glob(".*.tmp-*"))


@pytest.mark.slow
def test_errors_name_the_folder_and_scene(tmp_path):
    root = tmp_path / "renders" / "s"
    root.mkdir(parents=True)
    with pytest.raises(shards.ShardError, match="no '<scene>-<spp>spp.exr' renders"):
        shards.build_shards(config(tmp_path), progress=False)
    exr.write_aovs(root / "lonely-00004spp.exr", random_aovs(20, 20))
    with pytest.raises(shards.ShardError, match="'lonely' has only lonely-00004spp.exr"):
        shards.build_shards(config(tmp_path), progress=False)


@pytest.mark.slow
def test_mitsuba_fixture_is_sharded(tmp_path, fixture_noisy, fixture_reference):
    root = tmp_path / "renders" / "fx"
    root.mkdir(parents=True)
    for src in (fixture_noisy, fixture_reference):
        os.symlink(src, root / src.name)
    cfg = shards.ShardConfig(set_name="fx", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "sh"),
                             patch_size=32, patches_per_image=10, val_fraction=0.0)
    manifest = shards.build_shards(cfg, progress=False)
    assert manifest["split"] == {"train": ["fixture"], "val": []}
    with shards.open_shard(shards.shard_paths(cfg.set_dir, "train")[0]) as f:
        got = shards.read_patches(f, ["diffuse/features", "specular/features"], range(len(f["source"])))
    assert got["diffuse/features"].shape == (10, 32, 32, 27)
    assert np.isfinite(got["diffuse/features"]).all() and np.isfinite(got["specular/features"]).all()


def test_shards_are_uncompressed_one_patch_per_chunk_and_a_damaged_chunk_is_detected(tmp_path):
    rng = np.random.default_rng(1)
    arrays = shards.empty_patches(3, 8)
    for _name, data in arrays.items():
        data[...] = rng.normal(size=data.shape) if data.dtype.kind == "f" else rng.integers(0, 9, data.shape)
    path = tmp_path / "shard-00000.h5"
    shards.write_shard(path, arrays, {"format": shards.FORMAT, "patch_size": 8})
    buffers = np.concatenate([arrays["diffuse/log_colour"], arrays["guides"]], axis=-1)
    relvar = np.concatenate([arrays["diffuse/relvar"], arrays["guide_relvar"]], axis=-1)
    want = features.features_from_buffers(buffers, relvar)
    with shards.open_shard(path) as f:
        for name, dataset in shards.DATASETS.items():
            dset = f[name]
            assert dset.chunks == (1,) + shards.format.dataset_shape(dataset, 8), name
            assert dset.compression is None and dset.fletcher32, name
        np.testing.assert_array_equal(shards.read_patch(f, ["diffuse/features"], 1)["diffuse/features"], want[1])
        chunk = f["guides"].id.get_chunk_info(1)
    data = bytearray(path.read_bytes())
    data[chunk.byte_offset + 100] ^= 0xFF  # one byte of patch 1's guides, the file's size unchanged
    path.write_bytes(bytes(data))
    with shards.open_shard(path) as f:
        np.testing.assert_array_equal(shards.read_patch(f, ["diffuse/features"], 0)["diffuse/features"], want[0])
        with pytest.raises(OSError):
            shards.read_patch(f, ["diffuse/features"], 1)


def test_cut_into_a_shard_buffer_equals_cut(tmp_path):
    noisy, reference = random_aovs(30, 33, seed=5), random_aovs(30, 33, seed=6, variances=False)
    image = shards.variance_patches(noisy, reference, config(tmp_path, patch_size=8, patches_per_image=6), 4)
    out = shards.empty_patches(9, 8)
    image.cut_into(2, 6, out, 5)
    want = image.cut(2, 6)
    for name, data in want.items():
        np.testing.assert_array_equal(out[name][5:9], data, err_msg=name)
    assert (want["source"] == 4).all() and want["diffuse/log_colour"].dtype == np.float16


# --- a full disk: one line, nothing half-written, and a rerun with space finishes ---

SHARDS_ARGS = ("shards", "--set", "s", "--renders", "renders", "--patch-size", "16", "--patches-per-image", "7",
               "--patches-per-shard", "5")


def _temporaries(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if is_temporary(p)]


@pytest.mark.slow
@pytest.mark.parametrize("threads", [1, 2])
def test_shards_on_a_full_disk_end_in_one_line_and_a_rerun_with_space_finishes_the_set(tmp_path, small_disk,
                                                                                        threads):
    # 2 threads: the shards are written by worker processes, whose HDF5 errors cross back to the command
    make_renders(tmp_path / "renders" / "s")
    args = SHARDS_ARGS + ("--threads", threads)
    res = kpcn(*args, "--out", "disk", cwd=tmp_path)
    assert_one_line_error(res, "disk/s/round-000/shard-", "cannot write (No space left on device)")
    assert _temporaries(small_disk.path) == []
    small_disk.grow()
    res = kpcn(*args, "--out", "disk", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert checksums(small_disk.path / "s") == _uninterrupted(tmp_path, *args, "--out", "disk")


def _uninterrupted(tmp_path: Path, *args) -> dict[str, str]:
    """The checksums of the shard set that ``kpcn ARGS`` writes in one go, in a copy of ``tmp_path``'s renders
    (the same relative paths and command line, which the shards record)."""
    twin = tmp_path / "twin"
    shutil.copytree(tmp_path / "renders", twin / "renders")
    assert kpcn(*args, cwd=twin).returncode == 0
    return checksums(twin / args[args.index("--out") + 1] / "s")


@pytest.mark.slow
def test_shards_refused_a_write_by_the_file_system_end_in_one_line_and_resume(tmp_path):
    # the same failure injected at write(2) without a mount: files may not grow past 64 kB. The uninterrupted
    # twin first: it also writes numba's caches of the kernels (files larger than the limit), so that the limited
    # run fails at a shard, where the test means it to, in any order of tests
    make_renders(tmp_path / "renders" / "s")
    args = SHARDS_ARGS + ("--threads", 2, "--out", "out")
    want = _uninterrupted(tmp_path, *args)
    res = kpcn(*args, cwd=tmp_path, file_size_limit=64 << 10)
    assert_one_line_error(res, "out/s/round-000/shard-", "cannot write (File too large)")
    assert _temporaries(tmp_path / "out") == []
    assert kpcn(*args, cwd=tmp_path).returncode == 0
    assert checksums(tmp_path / "out" / "s") == want


@pytest.mark.parametrize("reference_variances", [True, False])
def test_shards_carry_the_reference_relse_of_each_branch(tmp_path, reference_variances):
    make_renders(tmp_path / "renders" / "s", scenes=("a-000", "b-000"), size=(20, 22),
                 reference_variances=reference_variances)
    cfg = config(tmp_path, patches_per_image=3)
    manifest = shards.build_shards(cfg, progress=False)
    seen = 0
    for _, f, k, _, ref_path in stored_patches(cfg, manifest):
        assert f.attrs["format"] == shards.FORMAT
        ref = exr.read_aovs(ref_path, variances=reference_variances)
        y, x = f["position"][k]
        win = np.s_[y:y + 16, x:x + 16]
        for branch, variance in (("diffuse", "diffuseVariance"), ("specular", "specularVariance")):
            got = f[f"{branch}/ref_relse"][k]
            assert got.shape == (16, 16, 1) and got.dtype == np.float16
            want = reference_relse(ref[branch], ref[variance])[win] if reference_variances else np.zeros((16, 16))
            # float16 rounding (2**-11 relative; 2**-25 absolute below its smallest normal)
            np.testing.assert_allclose(got[..., 0], want, rtol=2.0**-11, atol=2.0**-25)
        seen += 1
    assert seen == 2 * 3


def test_renders_without_variance_are_cut_for_a_set_without_variance_where_their_error_to_the_reference_is(tmp_path):
    """Another renderer's frames (Cycles writes no variance): a no-variance set cuts them, each patch's PDF the
    variance PDF of a float64 estimate written out here, the input's squared error to its reference averaged
    over the channels; the full set refuses them in one line naming the layer."""
    root = tmp_path / "renders" / "s"
    root.mkdir(parents=True)
    for i, scene in enumerate(("a-000", "a-001")):
        exr.write_aovs(root / exr.render_filename(scene, 4), random_aovs(40, 44, seed=10 + i, variances=False))
        exr.write_aovs(root / exr.render_filename(scene, 64), random_aovs(40, 44, seed=100 + i, variances=False))
    cfg = config(tmp_path, inputs="no-variance")
    manifest = shards.build_shards(cfg, progress=False)
    sset = shards.ShardSet(cfg.set_dir)
    seen = 0
    for _, f, k, src, ref_path in stored_patches(cfg, manifest):
        assert ref_path == root / exr.render_filename(src["scene"], 64)
        noisy = exr.read_aovs(sset.resolve(src["path"]), variances=None)
        ref = exr.read_aovs(ref_path, variances=None)
        estimate = {
            "default": noisy["default"],
            "colorVariance": ((noisy["default"].astype(np.float64) - ref["default"]) ** 2).mean(axis=-1),
            "normalVariance": ((noisy["normal"].astype(np.float64) - ref["normal"]) ** 2).mean(axis=-1),
        }
        want = reference_pdf(reference_importance(estimate), 16, cfg.uniform_mix)
        y, x = f["position"][k]
        assert f["pdf"][k] == pytest.approx(want[y, x], rel=1e-12)
        seen += 1
    assert seen == 2 * 7

    res = kpcn("shards", "--set", "s", "--renders", str(tmp_path / "renders"), "--out", str(tmp_path / "full"),
               "--patch-size", "16", "--patches-per-image", "7", cwd=tmp_path)
    assert_one_line_error(res, "a-000-00004spp.exr", "diffuseVariance")
    assert not (tmp_path / "full" / "s").exists()
