"""A shard set knows its sources, has one writer at a time, and is never taken for whole when it is
not."""

import json
import pickle
import re
import shutil
import subprocess
import sys
import tracemalloc

import h5py
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, kpcn, run_main
from helpers.files import checksums
from helpers.paths import REPO
from helpers.tiny import make_renders, random_aovs

from prep import exr, shards
from prep.errors import KpcnError, OptionError
from prep.files import sha256_file

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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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
    for rc, _out, err in results:
        assert rc == 0 and "Traceback" not in err, err
    got = checksums(tmp_path / "together" / "shards")
    assert got == checksums(tmp_path / "alone" / "shards")
    assert not list((tmp_path / "together" / "shards").rglob("*.tmp-*"))
    assert len(shards.shard_paths(tmp_path / "together" / "shards" / "s", "train")) == 12


@pytest.mark.slow
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

    res = run_main("train", "--set", "s", "--shards", "shards", "--run", "runs/r", "--width", "4", "--depth", "2",
               "--kernel-size", "3", "--steps", "2", "--batch-size", "2", cwd=tmp_path)
    assert_one_line_error(res, "shard-00003.h5", "checksum (crc32) differs")
    assert checksums(tmp_path) == corrupted  # nothing written, not even a run record

    res = kpcn("shards", *SHARD_ARGS, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert checksums(tmp_path / "shards") == whole


# Cut by one process, then again by two: forked from a process without torch (as `kpcn shards` is) and
# spawned from one with it (as an error round of `kpcn resample` is). 9 patches an image in shards of 4:
# most inputs straddle shards, so both workers read some of the same renders.
WORKER_BUILD = """
import sys
from prep import shards
cfg = shards.ShardConfig(**{config!r})
shards.build_shards(cfg, progress=False, workers=2)
assert ("torch" in sys.modules) == {torch}, "the start method under test is not the one used"
"""


@pytest.mark.slow
@pytest.mark.parametrize("start", ["fork", "spawn"])
def test_a_set_cut_by_two_worker_processes_is_byte_for_byte_the_set_one_process_cuts(tmp_path, start):
    make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path, patches_per_image=9, patches_per_shard=4, command="kpcn shards")
    shards.build_shards(cfg, progress=False, workers=1)
    alone = checksums(cfg.set_dir)
    assert len([p for p in alone if p.endswith(".h5")]) == 10
    shutil.rmtree(cfg.set_dir)
    code = WORKER_BUILD.format(config=cfg.to_dict(), torch=start == "spawn")
    if start == "spawn":
        code = "import torch\n" + code
    res = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert checksums(cfg.set_dir) == alone


@pytest.mark.slow
def test_a_render_that_fails_to_decode_in_a_worker_stops_the_command_with_one_line_naming_it(tmp_path):
    root = make_renders(tmp_path / "renders" / "s")
    victim = root / exr.render_filename("a-000", 4)
    data = victim.read_bytes()
    victim.write_bytes(data[: len(data) * 6 // 10])  # the header reads (the plan's check); the pixels do not
    res = kpcn("shards", *SHARD_ARGS, cwd=tmp_path)
    assert_one_line_error(res, str(victim.relative_to(tmp_path)), "not a readable OpenEXR file")
    assert not list((tmp_path / "shards").rglob(".*tmp*"))


def test_an_option_error_raised_in_a_worker_reaches_the_caller_whole():
    got = pickle.loads(pickle.dumps(OptionError("patches_per_image", "must be >= 1, got 0")))
    assert (type(got), got.option, got.detail, str(got)) == (
        OptionError, "patches_per_image", "must be >= 1, got 0", "patches_per_image must be >= 1, got 0")


@pytest.mark.slow
def test_a_set_listing_sha256_as_sets_did_before_still_verifies_and_is_kept(tmp_path):
    make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path)
    manifest = shards.build_shards(cfg, progress=False)
    for entry in manifest["rounds"]["round-000"]["shards"]:
        del entry["crc32"]
        entry["sha256"] = sha256_file(cfg.set_dir / entry["path"])
    (cfg.set_dir / "manifest.json").write_text(json.dumps(manifest))
    before = checksums(cfg.set_dir)
    sset = shards.ShardSet(cfg.set_dir)
    assert {e.checksum[0] for e in sset.verified_shards("train")} == {"sha256"}
    rerun = shards.build_shards(cfg, progress=False)
    after = checksums(cfg.set_dir)
    assert ({k: v for k, v in after.items() if k.endswith(".h5")}
            == {k: v for k, v in before.items() if k.endswith(".h5")})
    assert all("sha256" in e for e in rerun["rounds"]["round-000"]["shards"])  # kept, not rewritten
    victim = sset.verified_shards("train")[0].path
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    with pytest.raises(shards.ShardError, match=r"checksum \(sha256\) differs"):
        sset.verified_shards("train")


@pytest.mark.slow
def test_patches_per_image_beyond_the_patch_positions_is_refused_before_writing(tmp_path):
    make_renders(tmp_path / "renders" / "s")  # 40x44: 33 x 37 = 1221 positions of an 8x8 patch
    before = checksums(tmp_path)
    args = list(SHARD_ARGS)
    args[args.index("--patches-per-image") + 1] = "5000"
    res = kpcn("shards", *args, cwd=tmp_path)
    assert_one_line_error(res, "--patches-per-image", "5000", "1221")
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_shards_are_cut_in_memory_bounded_by_one_shard_not_by_the_patch_count(tmp_path):
    make_renders(tmp_path / "renders" / "s", scenes=("a-000", "b-000"))
    peaks, total = {}, {}
    # the first build pays for imports and compilation; each size is built twice and its smaller peak kept, so
    # that a one-time cost of the process (a lazy import, a cache a test before this one left to fill) is not
    # taken for memory that grows with the patch count, which every build of that size would show
    for i, ppi in enumerate((100, 100, 100, 1200, 1200)):
        cfg = config(tmp_path, out_root=str(tmp_path / f"shards-{i}"), patch_size=8,
                     patches_per_image=ppi, patches_per_shard=20, val_fraction=0.0)
        tracemalloc.start()
        shards.build_shards(cfg, progress=False, workers=1)  # this process's memory is the one traced
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        peaks[ppi] = min(peaks.get(ppi, peak), peak)
        total[ppi] = 2 * ppi * shards.patch_bytes(8)
    # twelve times the patches: the peak stays that of one image and one shard (kpcn-shard/4's patch is a
    # third of kpcn-shard/2's, so the set's bytes are fewer against the same peak than they were)
    assert peaks[1200] < 1.5 * peaks[100] + 2**20
    assert peaks[1200] < total[1200] / 2


@pytest.mark.slow
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


def tiny_train(cfg, **kw):
    from kpcn_keras.train import TrainConfig

    values = dict(set_name=cfg.set_name, shards_root=cfg.out_root, model={"width": 4, "depth": 2, "kernel_size": 3},
                  steps=2, steps_per_epoch=2, batch_size=2, val_batches=1, branches=("diffuse",))
    return TrainConfig.from_preset("cpu", **{**values, **kw})


def edit_manifest(set_dir, edit):
    path = set_dir / "manifest.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest, indent=2))


MANIFEST_EDITS = {
    "patch_size": lambda m: m.update(patch_size=6),
    "patches of round-000/shard-00001.h5": lambda m: m["rounds"]["round-000"]["shards"][1].update(patches=3),
    "config.patches_per_image": lambda m: m["config"].update(patches_per_image=10),
    "sources (their patches and checksums)": lambda m: m["sources"][1].update(patches=11),
}


@pytest.mark.slow
@pytest.mark.parametrize("field", MANIFEST_EDITS)
def test_a_hand_edited_manifest_is_refused_by_train_naming_the_field(tmp_path, field):
    from kpcn_keras.train import train

    make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path, patch_size=8, patches_per_image=12, patches_per_shard=2)
    shards.build_shards(cfg, progress=False)
    edit_manifest(cfg.set_dir, MANIFEST_EDITS[field])
    before = checksums(tmp_path)
    with pytest.raises(shards.ShardError, match=rf"manifest\.json: its {re.escape(field)} \("):
        train(tiny_train(cfg), tmp_path / "runs" / "r", verbose=0)
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_a_manifest_edited_by_hand_is_one_line_and_kpcn_shards_rewrites_it(tmp_path):
    make_renders(tmp_path / "renders" / "s")
    assert kpcn("shards", *SHARD_ARGS, cwd=tmp_path).returncode == 0
    whole = checksums(tmp_path / "shards")
    edit_manifest(tmp_path / "shards" / "s", MANIFEST_EDITS["patch_size"])
    res = run_main("train", "--set", "s", "--shards", "shards", "--run", "runs/r", "--width", "4", "--depth", "2",
               "--kernel-size", "3", "--steps", "2", "--batch-size", "2", cwd=tmp_path)
    assert_one_line_error(res, "shards/s/manifest.json: its patch_size (6) is not what shard-00000.h5")
    assert not (tmp_path / "runs").exists()
    assert kpcn("shards", *SHARD_ARGS, cwd=tmp_path).returncode == 0
    assert checksums(tmp_path / "shards") == whole


@pytest.mark.slow
def test_a_render_replaced_since_the_set_was_cut_is_refused_by_train_and_a_set_without_renders_trains(tmp_path):
    from kpcn_keras.train import train

    root = make_renders(tmp_path / "renders" / "s")
    cfg = config(tmp_path)
    shards.build_shards(cfg, progress=False)
    exr.write_aovs(root / "a-000-00004spp.exr", random_aovs(40, 44, seed=999))
    before = checksums(tmp_path)
    with pytest.raises(shards.ShardError) as err:
        train(tiny_train(cfg), tmp_path / "runs" / "r", verbose=0)
    assert "renders/s/a-000-00004spp.exr: changed since the shard set" in str(err.value)
    assert "'kpcn shards --set s' with the set's options rebuilds the set" in str(err.value)
    assert checksums(tmp_path) == before
    shutil.move(tmp_path / "renders", tmp_path / "elsewhere")  # a set moved without its renders trains
    run_dir = train(tiny_train(cfg), tmp_path / "runs" / "r", verbose=0)
    assert (run_dir / "diffuse.keras").is_file()
