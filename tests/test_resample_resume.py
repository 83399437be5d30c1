"""``kpcn resample`` killed during a round's error maps, its training or its shards, then run again with the
same command, ends where an uninterrupted loop ends: the same patches (count and (source, position) sets of
every round, no position twice), byte-identical networks (weights and optimizer state), and every file of
the tree byte-identical but the timings files (``timings.json``, one per folder that has seconds).

Each command runs as a user runs it (in a process of its own, ``helpers.commands.start_kpcn``; relative paths, its own
tree), on random renders at toy size. The kill is a SIGKILL sent when the command has reached the stage under
test, seen from the files it leaves: the round's plan and some of its shard files, or the first checkpoint of
a round's training phase.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import signal
import time
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.commands import start_kpcn
from helpers.files import checksums_but_timings
from helpers.tiny import make_renders

SHARDS = ["shards", "--set", "t", "--renders", "renders", "--out", "shards", "--patch-size", "16",
          "--patches-per-image", "6", "--patches-per-shard", "1", "--val-fraction", "0.5"]
TRAIN = ["train", "--set", "t", "--shards", "shards", "--run", "runs/r", "--steps", "40", "--batch-size", "2",
         "--width", "4", "--depth", "2", "--kernel-size", "3"]
# 60 steps per round at 50 per epoch: a checkpoint to kill after, then a shorter epoch; one shard file per patch
RESAMPLE = ["resample", "--run", "runs/r", "--rounds", "2", "--round-steps", "60", "--patches-per-image", "40"]
TIMEOUT = 300


def _run(args, cwd) -> str:
    proc = start_kpcn(args, cwd)
    out, _ = proc.communicate(timeout=TIMEOUT)
    assert proc.returncode == 0, f"kpcn {' '.join(args)} failed ({proc.returncode}):\n{out}"
    assert "Traceback" not in out, out
    return out


def _kill_when(args, cwd, reached, what: str) -> str:
    """Start the command and SIGKILL it as soon as ``reached()`` holds; what it printed until then. Fails if it
    ended first."""
    proc = start_kpcn(args, cwd)
    deadline = time.monotonic() + TIMEOUT
    while not reached():
        if proc.poll() is not None:
            out, _ = proc.communicate()
            pytest.fail(f"kpcn {' '.join(args)} ended before {what}:\n{out}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"kpcn {' '.join(args)} did not reach {what} in {TIMEOUT} s")
        time.sleep(0.002)
    proc.send_signal(signal.SIGKILL)
    out, _ = proc.communicate()
    print(f"killed during {what}")
    return out


def patches(set_dir: Path) -> dict[str, list[tuple[int, int, int]]]:
    """round name -> sorted (source, y, x) of every patch of that round's shard files, read with h5py."""
    out: dict[str, list] = {}
    for round_dir in sorted(set_dir.glob("round-*")):
        found = []
        for path in sorted(round_dir.glob("shard-*.h5")):
            with h5py.File(path, "r") as f:
                found += [(int(s), int(y), int(x)) for s, (y, x) in zip(f["source"][:], f["position"][:])]
        out[round_dir.name] = sorted(found)
    return out


def networks(run_dir: Path) -> dict[str, str]:
    """SHA-256 of every finished phase's .keras file (canonical bytes: weights and optimizer state)."""
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(run_dir.glob("*.keras"))}


@pytest.fixture(scope="module")
def trees(tmp_path_factory):
    """(a tree with a trained run, before any round; a copy of it after an uninterrupted loop)."""
    base = tmp_path_factory.mktemp("base")
    make_renders(base / "renders" / "t")
    _run(SHARDS, base)
    _run(TRAIN, base)
    reference = tmp_path_factory.mktemp("reference") / "tree"
    shutil.copytree(base, reference, ignore=shutil.ignore_patterns(".lock"))
    _run(RESAMPLE, reference)
    return base, reference


def _fresh_copy(base: Path, tmp_path: Path) -> Path:
    root = tmp_path / "tree"
    shutil.copytree(base, root, ignore=shutil.ignore_patterns(".lock"))
    return root


def _assert_same_end(reference: Path, root: Path) -> None:
    want, got = patches(reference / "shards" / "t"), patches(root / "shards" / "t")
    assert sorted(got) == sorted(want) == ["round-000", "round-001", "round-002"]
    for name in want:
        assert len(got[name]) == len(want[name]), (name, len(got[name]), len(want[name]))
        assert got[name] == want[name], f"{name}: other patches after the resume"
    # no (source, position) twice, in a round or across rounds
    every = [p for name in got for p in got[name]]
    assert len(set(every)) == len(every)
    assert networks(root / "runs" / "r") == networks(reference / "runs" / "r")
    record = json.loads((root / "runs" / "r" / "config.json").read_text())
    assert [record["resample"]["rounds"][k]["status"] for k in ("round-001", "round-002")] == ["done", "done"]
    leftovers = [p for p in root.rglob(".*") if p.is_file() and p.name != ".lock"]
    assert leftovers == []
    want, got = checksums_but_timings(reference), checksums_but_timings(root)
    differ = sorted(k for k in set(want) | set(got) if want.get(k) != got.get(k))
    assert not differ, f"files that differ from an uninterrupted loop's (or exist in one tree only): {differ}"
    # the seconds are kept apart: the run's per phase, the loop's per round (a kill between a record and its
    # seconds loses those, as a kill during the work does: the rounds here were finished after the kill)
    for tree, kept in ((reference, {"before"}), (root, set())):
        loop = json.loads((tree / "runs" / "r" / "resample" / "timings.json").read_text())
        assert kept | {"round-001", "round-002"} <= set(loop) <= {"before", "round-001", "round-002"}
        assert "specular-round-002" in json.loads((tree / "runs" / "r" / "timings.json").read_text())


@pytest.mark.slow
def test_kills_during_error_maps_training_and_shards_each_resume_to_the_end_of_an_uninterrupted_loop(trees, tmp_path):
    """One tree killed three times, at each stage of a round, each run resuming what the one before left: during
    round-001's error maps (the round is drawn again), during round-001's training (after the specular
    network's first checkpoint: it resumes from there) and during round-002's shards (a part of its files
    written: none lost or written twice); the last run then ends with the uninterrupted loop's files, weights,
    optimizer state and log. A resume that went wrong at any of the three shows in that end (and each kill's
    own checks say which stage left what), at the cost of one loop rather than one per kill point."""
    base, reference = trees
    root = _fresh_copy(base, tmp_path)
    run, set_dir = root / "runs" / "r", root / "shards" / "t"

    # the run before the rounds is measured; round 1's error maps come next
    _kill_when(RESAMPLE, root, (run / "resample" / "rounds.json").is_file, "round-001's error maps")
    assert not (set_dir / "round-001" / "plan.npz").is_file()

    ckpt = run / "checkpoints" / "specular-round-001.keras"
    _kill_when(RESAMPLE, root, ckpt.is_file, "round-001's training (specular, after its first epoch)")
    assert not (run / "specular-round-001.keras").is_file()
    assert (run / "diffuse-round-001.keras").is_file()

    round_dir = set_dir / "round-002"
    total = len(list((reference / "shards" / "t" / "round-002").glob("shard-*.h5")))

    def in_shards():  # the plan is written and a part of the round's shard files
        return (round_dir / "plan.npz").is_file() and len(list(round_dir.glob("shard-*.h5"))) >= total // 4

    out = _kill_when(RESAMPLE, root, in_shards, "round-002's shards")
    assert "[specular-round-001] resuming from" in out  # its training went on from the checkpoint
    assert (run / "specular-round-001.keras").is_file()
    manifest = json.loads((set_dir / "manifest.json").read_text())
    assert manifest["rounds"]["round-002"]["status"] == "building"
    written = len(list(round_dir.glob("shard-*.h5")))
    assert 0 < written < total, (written, total)

    _run(RESAMPLE, root)
    _assert_same_end(reference, root)
    assert (run / "log.csv").read_bytes() == (reference / "runs" / "r" / "log.csv").read_bytes()


@pytest.mark.slow
def test_every_round_patch_is_the_crop_of_its_source_at_its_position(trees):
    """The shards of the error rounds hold what they say: each patch's reference colour is the crop of its
    source's reference render at its stored position (checked against the EXR, read independently)."""
    _, reference = trees
    from prep import exr

    manifest = json.loads((reference / "shards" / "t" / "manifest.json").read_text())
    set_dir = reference / "shards" / "t"
    refs = {}
    for name in ("round-001", "round-002"):
        for path in sorted((set_dir / name).glob("shard-*.h5"))[:10]:
            with h5py.File(path, "r") as f:
                for i in range(len(f["source"])):
                    src = manifest["sources"][int(f["source"][i])]
                    ref = next(s for s in manifest["sources"]
                               if s["scene"] == src["scene"] and s["role"] == "reference")
                    if ref["path"] not in refs:
                        refs[ref["path"]] = exr.read_aovs(set_dir / ref["path"], variances=False)["default"]
                    y, x = f["position"][i]
                    np.testing.assert_array_equal(f["reference"][i], refs[ref["path"]][y:y + 16, x:x + 16])
                    assert f["round"][i] == int(name.split("-")[1])
