"""A command killed at a random point of ``kpcn render``, ``kpcn shards`` or ``kpcn train`` is
finished by running the same command again, and then every file it wrote is byte-identical (SHA-256) to
an uninterrupted run's; nothing that was complete is lost, redone or duplicated, no temporary file is left.

Each stage runs the real command line in a process of its own (``helpers.commands.start_kpcn``: ``python -m
kpcn_keras.cli`` for render and shards, forked from an interpreter that has imported the stack for train),
at toy size, with the working directory set to its own tmp tree and the same relative arguments, so that the
recorded commands and relative paths of the reference and the killed runs agree. Kill points are drawn from
a seeded ``random.Random``: a time after the command took its folder's lock (the lock file then holds the
command's pid, so imports and input checks are not counted), as a fraction of the reference run's time
from that point to its exit (a command that finishes before its kill point, on a machine less loaded than
during the reference run, is compared as an uninterrupted run and started afresh with the point halved).
The last kill point of each stage kills the rerun a second time before the third run completes it. Where
each kill landed is printed (``pytest -s``); the test does not depend on it.

Compared: every file of the tree (inputs included, so they must be left alone) but dot-files (``.lock``,
temporaries) and ``timings.json`` (seconds differ by design).
"""

from __future__ import annotations

import hashlib
import json
import random
import shutil
import signal
import subprocess
import time
import zipfile
from pathlib import Path

import pytest
from helpers.commands import start_kpcn
from helpers.files import checksums_but_timings

SEED = 5
# kill points per stage, the last of which kills twice: a kill once and a kill of a resumed run, each at a point
# drawn anew (render and shards write one file after another, so a third point meets the same code: what was
# whole is kept, the rest is written again)
KILLS = {"render": 2, "shards": 2, "train": 2}
TIMEOUT = 300

# toy sizes, chosen so that the work after the lock takes one to a few seconds on a 2-core CPU
RENDER = ["render", "--set", "t", "--out", "renders", "--families", "cornell,spheres,boxes", "--per-family", "2",
          "--width", "48", "--height", "48", "--input-spp", "4", "--reference-spp", "512"]
SHARDS = ["shards", "--set", "t", "--renders", "renders", "--out", "shards", "--patch-size", "16",
          "--patches-per-image", "48", "--patches-per-shard", "1", "--val-fraction", "0.5"]
# 80 steps of 50 per epoch: 2 checkpoints per branch, the last after a shorter epoch of 30 steps (the CLI
# has no --steps-per-epoch)
TRAIN = ["train", "--set", "t", "--shards", "shards", "--run", "runs/r", "--steps", "80", "--batch-size", "2",
         "--width", "4", "--depth", "2", "--kernel-size", "3"]

STAGES = {
    # args, the folder the command locks, the files that are never rewritten once they exist
    "render": (RENDER, "renders/t", ("*.exr",)),
    "shards": (SHARDS, "shards/t", ("round-*/shard-*.h5",)),
    "train": (TRAIN, "runs/r", ("diffuse.keras", "specular.keras")),
}


def _wait_for_lock(proc: subprocess.Popen, lock: Path) -> float | None:
    """The time at which ``proc`` holds ``lock`` (its pid is in it), or None if it ended first."""
    deadline = time.monotonic() + TIMEOUT
    while time.monotonic() < deadline:
        try:
            if lock.read_text().strip() == str(proc.pid):
                return time.monotonic()
        except (FileNotFoundError, UnicodeDecodeError):
            pass
        if proc.poll() is not None:
            return None
        time.sleep(0.005)
    proc.kill()
    pytest.fail(f"{proc.args} did not take {lock} within {TIMEOUT} s")


def _finish(proc: subprocess.Popen) -> str:
    try:
        out, _ = proc.communicate(timeout=TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"{proc.args} ran past {TIMEOUT} s:\n{out}")
    return out


def run_to_completion(args: list[str], root: Path, lock: Path) -> float:
    """Run the command; returns the seconds from taking the lock to exit."""
    proc = start_kpcn(args, root)
    locked = _wait_for_lock(proc, lock)
    out = _finish(proc)
    end = time.monotonic()
    assert proc.returncode == 0, f"kpcn {' '.join(args)} in {root} failed ({proc.returncode}):\n{out}"
    assert "Traceback" not in out, out
    return end - locked if locked is not None else 0.0


def run_and_kill(args: list[str], root: Path, lock: Path, delay: float) -> bool:
    """Start the command and SIGKILL it ``delay`` s after it took the lock; False if it ended first."""
    proc = start_kpcn(args, root)
    locked = _wait_for_lock(proc, lock)
    if locked is not None:
        while proc.poll() is None and time.monotonic() < locked + delay:
            time.sleep(0.002)
    killed = proc.poll() is None
    if killed:
        proc.send_signal(signal.SIGKILL)
    out = _finish(proc)
    if not killed:
        assert proc.returncode == 0, f"kpcn {' '.join(args)} in {root} failed ({proc.returncode}):\n{out}"
    return killed


# ---------------------------------------------------------------- what is on disk


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def dot_files(root: Path) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in root.rglob(".*") if p.is_file())


def temporaries(root: Path) -> list[str]:
    return [p for p in dot_files(root) if Path(p).name != ".lock"]


def explain(a: Path, b: Path) -> str:
    """How two files of the same name differ: the entries of a .keras zip, the first line of a text."""
    if zipfile.is_zipfile(a) and zipfile.is_zipfile(b):
        with zipfile.ZipFile(a) as za, zipfile.ZipFile(b) as zb:
            names = sorted(set(za.namelist()) | set(zb.namelist()))
            return "zip entries differ: " + ", ".join(
                n for n in names if n not in za.namelist() or n not in zb.namelist() or za.read(n) != zb.read(n))
    try:
        la, lb = a.read_bytes().splitlines(keepends=True), b.read_bytes().splitlines(keepends=True)
    except OSError as exc:
        return str(exc)
    for i, (x, y) in enumerate(zip(la, lb)):
        if x != y:
            return f"line {i + 1}: {x[:160]!r} vs {y[:160]!r}"
    return f"{len(la)} vs {len(lb)} lines, {a.stat().st_size} vs {b.stat().st_size} bytes"


def assert_same_tree(reference: Path, root: Path) -> None:
    want, got = checksums_but_timings(reference), checksums_but_timings(root)
    missing, extra = sorted(set(want) - set(got)), sorted(set(got) - set(want))
    differ = sorted(k for k in set(want) & set(got) if want[k] != got[k])
    details = "\n".join(f"  {k}: {explain(reference / k, root / k)}" for k in differ)
    assert not (missing or extra or differ), (
        f"{root} after the rerun vs the uninterrupted run {reference}:\n"
        f"missing {missing}\nextra {extra}\ndiffering {differ}\n{details}"
    )


def kept_files(folder: Path, patterns: tuple[str, ...]) -> dict[str, tuple[int, int]]:
    """(inode, mtime) of the files that are final once they exist, to see that a rerun keeps them."""
    return {
        p.relative_to(folder).as_posix(): (p.stat().st_ino, p.stat().st_mtime_ns)
        for pattern in patterns
        for p in sorted(folder.glob(pattern))
        if not p.name.startswith(".")
    }


def progress(stage: str, folder: Path) -> str:
    """Where a kill landed, from what the killed command left in its folder."""
    temps = [Path(t).name for t in temporaries(folder)]
    tail = f"; temporaries {temps}" if temps else ""
    if stage == "render":
        exrs = sorted(folder.glob("*.exr"))
        return f"{len(exrs)}/12 renders written" + tail
    if stage == "shards":
        done = len(list(folder.glob("round-*/shard-*.h5")))
        try:
            manifest = json.loads((folder / "manifest.json").read_text())
            listed = sum(len(r["shards"]) for r in manifest["rounds"].values())
            state = f"manifest {manifest['status']} with {listed} shards"
        except FileNotFoundError:
            state = "no manifest"
        return f"{done}/288 shard files, {state}" + tail
    parts = [] if (folder / "config.json").is_file() else ["no run record"]
    for branch in ("diffuse", "specular"):
        if (folder / f"{branch}.keras").is_file():
            parts.append(f"{branch} finished")
            continue
        ckpt = folder / "checkpoints" / f"{branch}.keras"
        if ckpt.is_file():
            with zipfile.ZipFile(ckpt) as z:
                epochs = json.loads(z.read("kpcn-state.json"))["epochs_done"]
            parts.append(f"{branch} checkpoint after epoch {epochs}/2")
    record = folder / "config.json"
    if record.is_file():
        results = sorted(json.loads(record.read_text())["results"])
        parts.append(f"record results {results}")
    return ", ".join(parts or ["nothing written"]) + tail


def check_after_kill(stage: str, root: Path, reference: Path, folder: str, patterns) -> None:
    """What a kill may leave: final files only whole (the reference's bytes), records only valid JSON."""
    for name in kept_files(root / folder, patterns):
        rel = f"{folder}/{name}"
        assert sha256(root / rel) == sha256(reference / rel), f"{stage}: {rel} left by the kill is not the final file"
    for path in (root / folder).rglob("*.json"):
        if not path.name.startswith("."):
            json.loads(path.read_text())  # atomic: never half-written


# ---------------------------------------------------------------- the stages


def copy_inputs(reference: Path, root: Path, *folders: str) -> None:
    for name in folders:
        shutil.copytree(reference / name, root / name, ignore=shutil.ignore_patterns(".*"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """(root, stage): one tree holding an uninterrupted run of every stage asked for so far (and of the
    stages before it); ``stage(name)`` runs them if needed and returns the seconds from lock to exit."""
    root = tmp_path_factory.mktemp("reference")
    done = {}

    def stage(name: str) -> float:
        for before in list(STAGES)[: list(STAGES).index(name) + 1]:
            if before not in done:
                args, folder, _ = STAGES[before]
                done[before] = run_to_completion(args, root, root / folder / ".lock")
        return done[name]

    return root, stage


def interrupt_and_resume(stage: str, reference, tmp_path: Path, inputs: tuple[str, ...]) -> list[str]:
    ref_root, durations = reference
    duration = durations(stage)
    args, folder, patterns = STAGES[stage]
    rng = random.Random(f"{SEED}-{stage}")
    landed = []
    for k in range(KILLS[stage]):
        root = tmp_path / f"kill-{k}"
        root.mkdir()
        copy_inputs(ref_root, root, *inputs)
        lock = root / folder / ".lock"
        kills = 2 if k == KILLS[stage] - 1 else 1
        for attempt in range(kills):
            delay = rng.uniform(0.02, 0.9) * duration
            for _retry in range(3):
                killed = run_and_kill(args, root, lock, delay)
                where = progress(stage, root / folder) if killed else "after the command had finished"
                landed.append(f"{stage} kill {k}.{attempt} at {delay:.2f} s of {duration:.2f} s: {where}")
                print(landed[-1])
                if killed or attempt > 0:
                    break
                # the machine was faster than during the reference run: an uninterrupted run, which must
                # give the reference's bytes too; start afresh with the kill point twice as early
                assert_same_tree(ref_root, root)
                shutil.rmtree(root)
                root.mkdir()
                copy_inputs(ref_root, root, *inputs)
                delay /= 2
            if killed:
                check_after_kill(stage, root, ref_root, folder, patterns)
        kept = kept_files(root / folder, patterns)
        if stage == "shards":  # a shard renamed but not yet listed is rewritten by design; listed ones are kept
            listed = set()
            if (root / folder / "manifest.json").is_file():
                manifest = json.loads((root / folder / "manifest.json").read_text())
                listed = {s["path"] for r in manifest["rounds"].values() for s in r["shards"]}
            kept = {name: ident for name, ident in kept.items() if name in listed}
        run_to_completion(args, root, lock)
        assert temporaries(root) == [], f"{stage}: temporaries left after the rerun: {temporaries(root)}"
        after = kept_files(root / folder, patterns)
        redone = sorted(name for name, ident in kept.items() if after.get(name) != ident)
        assert not redone, f"{stage}: files complete before the kill were rewritten or lost: {redone}"
        assert_same_tree(ref_root, root)
    return landed


@pytest.mark.slow
def test_killed_render_resumes_to_identical_files(reference, tmp_path):
    interrupt_and_resume("render", reference, tmp_path, inputs=())


@pytest.mark.slow
def test_killed_shards_resume_to_identical_files(reference, tmp_path):
    interrupt_and_resume("shards", reference, tmp_path, inputs=("renders",))


@pytest.mark.slow
def test_killed_training_resumes_to_identical_files(reference, tmp_path):
    interrupt_and_resume("train", reference, tmp_path, inputs=("renders", "shards"))
