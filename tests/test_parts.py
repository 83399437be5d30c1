"""Offline stages split over processes: ``kpcn render`` and ``kpcn shards`` in parts, by
``--part i/N`` or by torchrun's rank, write the same files as one process, whichever part ends last."""

import fcntl
import hashlib
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

import pytest
from helpers.commands import launcher_free_env, torchrun
from helpers.paths import REPO

from kpcn_keras.cli import main
from prep.errors import OptionError
from prep.parts import LaunchError, Part
from prep.shards import ShardError, ShardSet

RENDER = ("render", "--set", "t", "--families", "cornell,caustics", "--per-family", "2", "--width", "32",
          "--height", "32", "--input-spp", "2,4", "--reference-spp", "8", "--out", "data/renders")
SHARDS = ("shards", "--set", "t", "--renders", "data/renders", "--out", "data/shards", "--patch-size", "12",
          "--patches-per-image", "10", "--patches-per-shard", "15", "--seed", "3")


def _files(folder: Path, *, leave_out=("timings.json",)) -> dict[str, str]:
    """Every file a reader sees under ``folder`` (dot-files are locks and temporaries), with its SHA-256;
    ``timings.json`` holds seconds, the one file that differs between any two runs."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and not p.name.startswith(".")
            and p.name not in leave_out}


def _kpcn(cwd: Path, monkeypatch, *args) -> None:
    monkeypatch.chdir(cwd)
    assert main(["-q", *args]) == 0


def test_part_is_read_from_the_option_else_from_the_launcher():
    assert Part.parse("1/2") == Part(0, 2) and Part.parse(" 3 / 3 ") == Part(2, 3)
    assert Part.chosen(None, {}) == Part() and Part().whole
    assert Part.chosen(None, {"RANK": "1", "WORLD_SIZE": "4"}) == Part(1, 4)
    assert Part.chosen("4/4", {"RANK": "1", "WORLD_SIZE": "4"}) == Part(3, 4)  # the option wins
    assert str(Part(1, 4)) == "2/4" and Part(1, 4).label == "part-2-of-4"
    assert Part(1, 4).lock_name == ".lock-part-2-of-4" and Part().lock_name == ".lock"


@pytest.mark.parametrize("text", ["0/2", "3/2", "1/0", "a/b", "1", "-1/2"])
def test_a_malformed_part_is_refused_echoing_it(text):
    with pytest.raises(OptionError) as err:
        Part.parse(text)
    assert err.value.option == "part" and repr(text) in str(err.value)


@pytest.mark.parametrize("environ,needle", [
    ({"RANK": "0"}, "WORLD_SIZE not set while RANK is"),
    ({"RANK": "x", "WORLD_SIZE": "2"}, "RANK must be an integer, got 'x'"),
    ({"RANK": "2", "WORLD_SIZE": "2"}, "RANK=2 and WORLD_SIZE=2 name no process"),
])
def test_a_malformed_launcher_environment_is_refused_naming_the_variable(environ, needle):
    with pytest.raises(LaunchError) as err:
        Part.from_environment(environ)
    assert needle in str(err.value)


@pytest.mark.parametrize("n,count", [(0, 3), (5, 1), (7, 3), (64, 5), (3, 8)])
def test_blocks_of_the_parts_cover_every_item_once_in_order(n, count):
    blocks = [list(Part(i, count).block(n)) for i in range(count)]
    assert sum(blocks, []) == list(range(n))
    assert max(map(len, blocks)) - min(map(len, blocks)) <= 1


def test_balanced_shares_cover_every_item_once_and_stay_within_one_item_of_each_other():
    costs = [2, 4, 512, 2, 4, 2048, 2, 4, 512, 8, 8, 8, 16, 16, 1024]
    for count in (1, 2, 3, 4):
        shares = [Part(i, count).balanced(costs) for i in range(count)]
        assert sorted(sum(shares, [])) == list(range(len(costs)))
        loads = [sum(costs[i] for i in share) for share in shares]
        # the greedy bound: no part exceeds the least loaded by more than the dearest item
        assert max(loads) - min(loads) <= max(costs)
    assert Part(0, 2).balanced(costs) == Part(0, 2).balanced(list(costs))  # every part computes the same


@pytest.mark.slow
def test_render_and_shards_in_two_parts_write_the_files_of_one_process(tmp_path, monkeypatch):
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    _kpcn(one, monkeypatch, *RENDER)
    # the second part first: whichever part ends last writes the record
    _kpcn(two, monkeypatch, *RENDER, "--part", "2/2")
    assert not (two / "data/renders/t/contact-sheet.png").exists()
    assert (two / "data/renders/t/timings.part-2-of-2.json").is_file()
    _kpcn(two, monkeypatch, *RENDER, "--part", "1/2")
    renders = _files(one / "data/renders/t")
    assert len([n for n in renders if n.endswith(".exr")]) == 12 and "contact-sheet.png" in renders
    assert _files(two / "data/renders/t") == renders
    assert not list((two / "data/renders/t").glob("timings.part-*"))
    timings = (two / "data/renders/t/timings.json").read_text()
    assert all(name in timings for name in renders if name.endswith(".exr"))  # both parts' seconds kept

    _kpcn(one, monkeypatch, *SHARDS, "--threads", "2")
    _kpcn(two, monkeypatch, *SHARDS, "--part", "2/2", "--threads", "1")
    with pytest.raises(ShardError, match="not complete|status"):
        ShardSet(two / "data/shards/t").complete_manifest()  # no reader takes half a set
    _kpcn(two, monkeypatch, "--quiet", *SHARDS, "--part=1/2")
    shards = _files(one / "data/shards/t")
    assert len([n for n in shards if n.endswith(".h5")]) >= 4
    assert _files(two / "data/shards/t") == shards
    assert not (two / "data/shards/t/parts").exists()
    manifest = ShardSet(two / "data/shards/t").complete_manifest()
    assert manifest["config"]["command"] == "kpcn " + " ".join(SHARDS)  # no --part, --threads or -q


def _whole_set_and_a_third_of_one(tmp_path: Path, monkeypatch) -> tuple[Path, Path]:
    """Two trees with the same renders: ``one`` with the whole shard set, ``two`` with part 1/3 of it."""
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir()
    _kpcn(one, monkeypatch, *RENDER)
    shutil.copytree(one, two)
    _kpcn(one, monkeypatch, *SHARDS)
    _kpcn(two, monkeypatch, *SHARDS, "--part", "1/3")
    return one, two


@pytest.mark.slow
def test_a_rerun_in_any_split_keeps_the_shards_a_part_listed_and_rewrites_a_damaged_one(tmp_path, monkeypatch):
    one, two = _whole_set_and_a_third_of_one(tmp_path, monkeypatch)
    sset = ShardSet(two / "data/shards/t")
    mine = sorted(sset.round_dir(0).glob("shard-*.h5"))
    assert len(mine) >= 2 and (sset.dir / "parts/part-1-of-3.json").is_file()
    kept, damaged = mine[0], mine[-1]
    stamp = kept.stat().st_mtime_ns
    data = bytearray(damaged.read_bytes())
    data[len(data) // 2] ^= 0xFF
    damaged.write_bytes(bytes(data))
    _kpcn(two, monkeypatch, *SHARDS)  # one process finishes what a third of a 3-way split began
    assert kept.stat().st_mtime_ns == stamp  # taken from the part's list, not cut again
    assert _files(sset.dir) == _files(one / "data/shards/t")


@pytest.mark.slow
def test_torchrun_splits_render_and_shards_over_its_processes(tmp_path, monkeypatch):
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    _kpcn(one, monkeypatch, *RENDER)
    _kpcn(one, monkeypatch, *SHARDS)
    env = launcher_free_env(PYTHONPATH=str(REPO))
    out = {}
    for args in (RENDER, SHARDS):
        res = subprocess.run(torchrun("-q", *args), cwd=two, env=env, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr[-3000:]
        out[args[0]] = res.stdout
    assert "(part 1/2)" in out["render"] and "(part 2/2)" in out["render"]  # each process took its rank's part
    assert "manifest: data/shards/t/manifest.json" in out["shards"]  # printed by the part that merged
    assert _files(two / "data") == _files(one / "data")


@pytest.mark.slow
def test_a_damaged_part_list_is_left_out_and_blocks_no_merge(tmp_path, monkeypatch):
    one, two = _whole_set_and_a_third_of_one(tmp_path, monkeypatch)
    stale = two / "data/shards/t/parts/part-1-of-3.json"
    stale.write_text("{")  # a list of an earlier split, torn
    _kpcn(two, monkeypatch, *SHARDS, "--part", "1/2")
    _kpcn(two, monkeypatch, *SHARDS, "--part", "2/2")
    assert _files(two / "data/shards/t") == _files(one / "data/shards/t")


# a few seconds of work after start-up, so that a kill lands in the middle of it
RENDER_SLOW = (*RENDER[:-4], "--reference-spp", "256", "--out", "data/renders")
SHARDS_MANY = (*SHARDS[:-4], "--patches-per-shard", "1", "--seed", "3")


def _lock_free(path: Path) -> bool:
    fd = os.open(path, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        return True
    except OSError:
        return False
    finally:
        os.close(fd)


@pytest.mark.slow
def test_a_killed_split_render_and_shards_resume_with_the_same_launch_line(tmp_path, monkeypatch):
    """torchrun and both its processes killed at once (a cancelled job) once the first files are written:
    no part goes on writing, and the same launch line again gives the files of one uninterrupted process."""
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir(), two.mkdir()
    _kpcn(one, monkeypatch, *RENDER_SLOW)
    _kpcn(one, monkeypatch, *SHARDS_MANY)
    env = launcher_free_env(PYTHONPATH=str(REPO))
    for args, folder, written in ((RENDER_SLOW, "data/renders/t", "*.exr"),
                                  (SHARDS_MANY, "data/shards/t", "round-000/shard-*.h5")):
        proc = subprocess.Popen(torchrun("-q", *args), cwd=two, env=env, start_new_session=True,
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 300
        while len(list((two / folder).glob(written))) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert proc.poll() is None, f"{args[0]} ended before the kill: nothing was killed"
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=60)
        locks = [two / folder / f".lock-part-{i}-of-2" for i in (1, 2)]
        deadline = time.monotonic() + 10  # the kernel ends them at once (PR_SET_PDEATHSIG)
        while not all(_lock_free(lock) for lock in locks if lock.exists()) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert all(_lock_free(lock) for lock in locks if lock.exists()), "a part outlived its launcher"
        assert len(list((two / folder).glob(written))) < len(list((one / folder).glob(written)))
        res = subprocess.run(torchrun("-q", *args), cwd=two, env=env, capture_output=True, text=True, timeout=300)
        assert res.returncode == 0, res.stderr[-3000:]
    assert not [p for p in (two / "data").rglob("*") if ".tmp-" in p.name]
    assert _files(two / "data") == _files(one / "data")


def test_a_command_that_does_not_split_refuses_to_run_as_one_of_several_processes(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.chdir(tmp_path)
    assert main(["resample", "--run-dir", "runs/r"]) == 2
    err = capsys.readouterr().err
    assert "kpcn resample runs as one process, not as part 2/2" in err and "Traceback" not in err
    assert not (tmp_path / "runs").exists()
    assert main(["render", "--scene", str(REPO / "scenes/example.toml"), "--out", str(tmp_path / "x.exr")]) == 2
    assert "renders one file, as one process, not as part 2/2" in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()
