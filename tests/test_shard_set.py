"""A shard set knows its sources, has one writer at a time, and is never taken for whole when it is not
(issue 5, defects 1, 2, 5 and 7)."""

import json
import subprocess
import sys
import tracemalloc

import h5py
import numpy as np
import pytest

from conftest import REPO, assert_one_line_error, checksums, kpcn, make_renders, random_aovs
from prep import exr, shards
from prep.errors import KpcnError

SHARD_ARGS = ("--set", "s", "--renders", "renders", "--out", "shards", "--patch-size", "8",
              "--patches-per-image", "12", "--patches-per-shard", "2", "--val-fraction", "0.5", "--seed", "5")


def config(tmp_path, **kw):
    values = dict(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                  patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3)
    values.update(kw)
    return shards.ShardConfig(**values)


def scenes_in_shards(set_dir) -> dict[str, set[str]]:
    """split -> the scenes whose patches the listed shards of that split hold, read from the shards."""
    manifest = json.loads((set_dir / "manifest.json").read_text())
    found: dict[str, set[str]] = {"train": set(), "val": set()}
    for round_ in manifest["rounds"].values():
        for entry in round_["shards"]:
            with h5py.File(set_dir / entry["path"], "r") as f:
                names = [s["scene"] for s in json.loads(f.attrs["sources"])]
                found[entry["split"]] |= {names[i] for i in f["source"][:]}
    return found


def patch_counts(set_dir) -> dict[str, int]:
    manifest = json.loads((set_dir / "manifest.json").read_text())
    counts = {"train": 0, "val": 0}
    for round_ in manifest["rounds"].values():
        for entry in round_["shards"]:
            with h5py.File(set_dir / entry["path"], "r") as f:
                counts[entry["split"]] += len(f["source"])
    return counts


def test_renders_added_to_the_set_rebuild_it_without_leaking_held_out_scenes(tmp_path):
    root = make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path)
    shards.build_shards(cfg, progress=False)
    make_renders(root, scenes=("a-002", "b-002", "c-000", "c-001"))
    manifest = shards.build_shards(cfg, progress=False)
    split = manifest["split"]
    assert sorted(split["train"] + split["val"]) == ["a-000", "a-001", "a-002", "b-000", "b-001", "b-002",
                                                     "c-000", "c-001"]
    found = scenes_in_shards(cfg.set_dir)
    assert found["train"] == set(split["train"]) and found["val"] == set(split["val"])
    assert not found["train"] & set(split["val"])
    assert patch_counts(cfg.set_dir) == {k: len(v) * cfg.patches_per_image for k, v in split.items()}
    # and the rebuilt set is the set a first build over the new renders writes
    rebuilt = checksums(cfg.set_dir)
    cfg.set_dir.rename(tmp_path / "rebuilt")
    assert shards.build_shards(cfg, progress=False) == manifest
    assert checksums(cfg.set_dir) == rebuilt


def test_a_render_edited_in_place_rebuilds_the_shards_that_hold_it(tmp_path, caplog):
    root = make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path)
    before = shards.build_shards(cfg, progress=False)
    exr.write_aovs(root / "a-000-00004spp.exr", random_aovs(40, 44, seed=999))
    after = shards.build_shards(cfg, progress=False)
    assert after["content_key"] != before["content_key"]
    assert "changed a-000 (4 spp)" in caplog.text and "rebuilding" in caplog.text
    edited = next(s for s in after["sources"] if s["path"].endswith("a-000-00004spp.exr"))
    with h5py.File(cfg.set_dir / after["rounds"]["round-000"]["shards"][0]["path"], "r") as f:
        ids = f["source"][:]
        assert (ids == after["sources"].index(edited)).any()
        at = f["position"][int(np.argmax(ids == after["sources"].index(edited)))]
    # the shard now holds the new pixels
    noisy = exr.read_aovs(root / "a-000-00004spp.exr")
    with h5py.File(cfg.set_dir / after["rounds"]["round-000"]["shards"][0]["path"], "r") as f:
        i = int(np.argmax(f["source"][:] == after["sources"].index(edited)))
        p = cfg.patch_size
        np.testing.assert_allclose(f["noisy"][i], noisy["default"][at[0]:at[0] + p, at[1]:at[1] + p], rtol=1e-6)


def test_two_shard_commands_on_one_set_at_once_give_the_set_one_command_gives(tmp_path):
    for folder in ("together", "alone"):
        make_renders(tmp_path / folder / "renders" / "s")
    alone = kpcn("shards", *SHARD_ARGS, cwd=tmp_path / "alone")
    assert alone.returncode == 0, alone.stderr
    env = {"PYTHONPATH": str(REPO), "PATH": "/usr/bin:/bin"}
    cmd = [sys.executable, "-m", "kpcn_keras.cli", "-q", "shards", *SHARD_ARGS]
    procs = [subprocess.Popen(cmd, cwd=tmp_path / "together", env=env, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True) for _ in range(2)]
    results = [(p.wait(timeout=300), *p.communicate()) for p in procs]
    for rc, out, err in results:
        assert rc == 0 and "Traceback" not in err, err
    got = checksums(tmp_path / "together" / "shards")
    assert got == checksums(tmp_path / "alone" / "shards")
    assert not list((tmp_path / "together" / "shards").rglob("*.tmp-*"))
    assert len(shards.shard_paths(tmp_path / "together" / "shards" / "s", "train")) == 12


def test_a_shard_corrupted_at_the_same_size_is_refused_by_train_and_rebuilt_by_shards(tmp_path):
    make_renders(tmp_path / "renders" / "s")
    assert kpcn("shards", *SHARD_ARGS, cwd=tmp_path).returncode == 0
    whole = checksums(tmp_path / "shards")
    victim = tmp_path / "shards" / "s" / "round-000" / "shard-00003.h5"
    data = bytearray(victim.read_bytes())
    middle = len(data) // 2
    data[middle:middle + 64] = bytes(b ^ 0xFF for b in data[middle:middle + 64])
    victim.write_bytes(bytes(data))
    corrupted = checksums(tmp_path)

    res = kpcn("train", "--set", "s", "--shards", "shards", "--run", "runs/r", "--width", "4", "--depth", "2",
               "--kernel-size", "3", "--steps", "2", "--batch-size", "2", cwd=tmp_path)
    assert_one_line_error(res, "shard-00003.h5", "SHA-256")
    assert checksums(tmp_path) == corrupted  # nothing written, not even a run record

    res = kpcn("shards", *SHARD_ARGS, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert checksums(tmp_path / "shards") == whole


def test_patches_per_image_beyond_the_patch_positions_is_refused_before_writing(tmp_path):
    make_renders(tmp_path / "renders" / "s")  # 40x44: 33 x 37 = 1221 positions of an 8x8 patch
    before = checksums(tmp_path)
    args = list(SHARD_ARGS)
    args[args.index("--patches-per-image") + 1] = "100000000"
    res = kpcn("shards", *args, cwd=tmp_path)
    assert_one_line_error(res, "--patches-per-image", "100000000", "1221")
    assert checksums(tmp_path) == before


def test_shards_are_cut_in_memory_bounded_by_one_shard_not_by_the_patch_count(tmp_path):
    make_renders(tmp_path / "renders" / "s", scenes=("a-000", "b-000"))
    peaks, total = {}, {}
    for i, ppi in enumerate((100, 100, 1200)):  # the first build pays for imports and compilation
        cfg = config(tmp_path, out_root=str(tmp_path / f"shards-{i}"), patch_size=8,
                     patches_per_image=ppi, patches_per_shard=20, val_fraction=0.0)
        tracemalloc.start()
        shards.build_shards(cfg, progress=False)
        peaks[ppi] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        total[ppi] = 2 * ppi * shards.patch_bytes(8)
    # twelve times the patches: the peak stays that of one image and one shard
    assert peaks[1200] < 1.5 * peaks[100] + 2**20
    assert peaks[1200] < total[1200] / 4


@pytest.mark.parametrize("status", ["building", None])
def test_a_set_whose_manifest_is_not_complete_is_refused_by_readers(tmp_path, status):
    make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path)
    manifest = shards.build_shards(cfg, progress=False)
    if status is None:
        del manifest["status"]
    else:
        manifest["status"] = status
    (cfg.set_dir / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(KpcnError, match="status|not complete"):
        shards.shard_paths(cfg.set_dir, "train")
