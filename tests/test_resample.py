"""The parts of error-based resampling (docs/method.md §8) and of its study: weighted training batches, forked
shard sets and runs, the base run's round-0-only inputs, the study's arithmetic, the study end to end through
the command line, and the command line's refusals. Each checked against an independent computation (numpy in
float64, numbers worked by hand, binomial bounds, files read with h5py and hashlib)."""

import hashlib
import json
import math
import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, kpcn, run_main
from helpers.files import checksums
from helpers.tiny import TINY_MODEL, build_tiny_shards, make_renders

from kpcn_keras.config import TrainConfig
from kpcn_keras.data import ShardPatches
from kpcn_keras.resample import round_weights
from kpcn_keras.run import Run, load_model
from kpcn_keras.studies.resample_study import at_time, cumulative_cost, frame_scores_at, frame_test, verdict
from kpcn_keras.train import check_inputs, train
from prep.errors import KpcnError
from prep.shards import ErrorRound, ShardError, ShardSet, build_error_round

ARMS = ("continue", "variance", "error")


def variance_round(set_dir, k: int = 1, patches_per_image: int = 3):
    """Error round ``k`` drawn from the variance PDF alone (error weight 0: no denoiser is run)."""
    return build_error_round(set_dir, ErrorRound(k, patches_per_image, 0.0, "smape", {}), None, progress=False)


def tiny_set(root: Path, **kw) -> ShardSet:
    cfg = build_tiny_shards(root, **kw)
    return ShardSet(cfg.set_dir)


def read_shard(path) -> dict:
    """A shard's datasets read with h5py alone."""
    with h5py.File(path, "r") as f:
        return {name: f[name][:] for name in ("diffuse/reference", "round", "source", "position")}


def manifest_of(set_dir) -> dict:
    return json.loads((Path(set_dir) / "manifest.json").read_text())


def train_shards_on_disk(set_dir) -> dict[str, list[Path]]:
    """round folder -> the training shard files in it, found from the files (their ``split`` attribute)."""
    found = {}
    for path in sorted(Path(set_dir).glob("round-*/shard-*.h5")):
        with h5py.File(path, "r") as f:
            split = f.attrs["split"]
        if (split.decode() if isinstance(split, bytes) else split) == "train":
            found.setdefault(path.parent.name, []).append(path)
    return found


# ---------------------------------------------------------------- weighted batches


@pytest.fixture(scope="module")
def two_round_set(tmp_path_factory) -> ShardSet:
    """A tiny set with its variance round 0 and one error round (error weight 0)."""
    sset = tiny_set(tmp_path_factory.mktemp("weighted"))
    variance_round(sset.dir)
    return sset


def test_weighted_batches_draw_patches_in_proportion_to_their_shards_weight(two_round_set):
    shards = train_shards_on_disk(two_round_set.dir)
    assert sorted(shards) == ["round-000", "round-001"]
    paths = shards["round-000"] + shards["round-001"]
    data = [read_shard(p) for p in paths]
    rounds = [int(np.unique(d["round"]).item()) for d in data]  # one round per shard, from the file itself
    assert rounds == [0] * len(shards["round-000"]) + [1] * len(shards["round-001"])
    weights = [1.0 if r == 0 else 4.0 for r in rounds]
    # every patch is told apart by its bytes (random renders, positions never reused across rounds)
    owner = {}
    for s, d in enumerate(data):
        for patch in d["diffuse/reference"]:
            owner[patch.astype(np.float32).tobytes()] = s
    sizes = np.array([len(d["round"]) for d in data], np.float64)
    assert len(owner) == sizes.sum()

    batch, steps = 8, 250
    ds = ShardPatches(paths, "diffuse", batch, steps, shuffle=True, seed=11, weights=weights)
    counts = np.zeros(len(paths))
    for i in range(steps):
        _, y = ds[i]
        for patch in y:
            counts[owner[patch.tobytes()]] += 1
    n = batch * steps
    assert counts.sum() == n

    w = np.array(weights, np.float64)
    expected = sizes * w / np.sum(sizes * w)  # a patch's probability is its shard's weight over the total
    late = np.array(rounds) == 1
    p1 = expected[late].sum()
    n0, n1 = sizes[~late].sum(), sizes[late].sum()
    assert p1 == pytest.approx(n1 * 4 / (n0 + 4 * n1))
    assert abs(counts[late].sum() / n - p1) < 5 * math.sqrt(p1 * (1 - p1) / n)
    for share, p in zip(counts / n, expected):  # and per shard
        assert abs(share - p) < 5 * math.sqrt(p * (1 - p) / n), (counts / n, expected)
    # without weights every patch weighs the same: round 1 far from its weighted share
    assert abs(n1 / (n0 + n1) - p1) > 10 * math.sqrt(p1 * (1 - p1) / n)


def test_weighted_batches_are_a_pure_function_of_seed_and_batch_number(two_round_set):
    paths = [e.path for e in two_round_set.verified_shards("train", rounds=[0, 1])]
    weights = np.linspace(1.0, 3.0, len(paths))

    def make(seed=5, offset=0, steps=6):
        return ShardPatches(paths, "diffuse", 4, steps, shuffle=True, seed=seed, offset=offset, weights=weights)

    a, b, later, other = make(), make(), make(offset=3, steps=3), make(seed=6)
    for i in range(6):
        xa, ya = a[i]
        xb, yb = b[i]
        np.testing.assert_array_equal(xa, xb)
        np.testing.assert_array_equal(ya, yb)
    for i in range(3):  # batch i of a stream resumed at 3 is batch 3 + i of the whole stream
        np.testing.assert_array_equal(later[i][1], a[3 + i][1])
        np.testing.assert_array_equal(later[i][0], a[3 + i][0])
    assert any(not np.array_equal(a[i][1], other[i][1]) for i in range(6))  # the seed matters
    assert any(not np.array_equal(a[0][1], a[i][1]) for i in range(1, 6))  # and the batch number


def test_round_weights_decay_with_the_age_of_each_shards_round(two_round_set):
    entries = two_round_set.verified_shards("train", rounds=[0, 1])
    ages = {"round-000": 1, "round-001": 0}  # in round 1
    assert {e.round for e in entries} == set(ages)
    assert round_weights(entries, 1, 1.0) is None  # every patch alike
    assert round_weights(entries, 1, 0.5) == pytest.approx([0.5 ** ages[e.round] for e in entries])
    assert round_weights(entries, 3, 0.5) == pytest.approx([0.5 ** (ages[e.round] + 2) for e in entries])


@pytest.mark.parametrize("bad", [
    "short", "long", [0.0], [-1.0], [float("nan")], [float("inf")],
], ids=["too-few", "too-many", "zero", "negative", "nan", "inf"])
def test_bad_shard_weights_are_refused(two_round_set, bad):
    paths = [e.path for e in two_round_set.verified_shards("train", rounds=[0, 1])]
    n = len(paths)
    weights = {"short": [1.0] * (n - 1), "long": [1.0] * (n + 1)}.get(bad) if isinstance(bad, str) \
        else [1.0] * (n - 1) + bad
    with pytest.raises(ValueError, match="weights"):
        ShardPatches(paths, "diffuse", 2, 3, shuffle=True, weights=weights)


def test_an_error_round_removes_what_a_killed_writer_left_in_the_set(tmp_path):
    sset = tiny_set(tmp_path)
    stale = sset.dir / ".manifest.json.tmp-1-deadbeef.json"  # a manifest write cut short by a kill
    stale.write_text("{")
    variance_round(sset.dir)
    assert not stale.exists()
    assert sorted(manifest_of(sset.dir)["rounds"]) == ["round-000", "round-001"]


def test_a_run_removes_what_a_killed_resample_loop_left(tiny_run, tmp_path):
    run = Run(tiny_run).fork(tmp_path / "r")
    run.resample_dir.mkdir()
    stale = run.resample_dir / ".rounds.json.tmp-1-deadbeef.json"
    stale.write_text("{")
    with run.lock():
        run.remove_temporaries()
    assert not stale.exists()


# ---------------------------------------------------------------- forked shard sets and runs


def test_a_forked_shard_set_shares_round_0_and_keeps_its_own_later_rounds(tmp_path):
    original = tiny_set(tmp_path / "a")
    before = checksums(original.dir)
    before_manifest = original.manifest_path.read_bytes()
    fork = original.fork(tmp_path / "forks" / "s")
    assert fork.dir == tmp_path / "forks" / "s"

    originals = sorted((original.dir / "round-000").glob("shard-*.h5"))
    assert originals
    for path in originals:
        copy = fork.dir / "round-000" / path.name
        assert os.path.samefile(path, copy) or copy.read_bytes() == path.read_bytes()
    forked = manifest_of(fork.dir)
    assert list(forked["rounds"]) == ["round-000"]
    listed = [fork.dir / s["path"] for s in forked["rounds"]["round-000"]["shards"]]
    assert sorted(p.resolve() for p in listed) == sorted(p.resolve() for p in fork.dir.glob("round-000/shard-*.h5"))
    for mine, theirs in zip(forked["sources"], manifest_of(original.dir)["sources"]):
        assert os.path.samefile(fork.dir / mine["path"], original.dir / theirs["path"])
    assert [e.patches for e in fork.verified_shards("train")] == [e.patches for e in original.verified_shards("train")]

    variance_round(fork.dir)
    assert sorted(manifest_of(fork.dir)["rounds"]) == ["round-000", "round-001"]
    assert (fork.dir / "round-001").is_dir()
    assert not (original.dir / "round-001").exists()
    assert original.manifest_path.read_bytes() == before_manifest
    assert checksums(original.dir) == before

    again = original.fork(fork.dir)  # an existing fork is returned as it is, its own round kept
    assert again.dir == fork.dir and sorted(manifest_of(fork.dir)["rounds"]) == ["round-000", "round-001"]

    other = tiny_set(tmp_path / "b", seed=4)  # other content: another draw of the same renders
    other_bytes = checksums(other.dir)
    with pytest.raises(ShardError, match=re.escape(str(other.dir))):
        original.fork(other.dir)
    assert checksums(other.dir) == other_bytes


def test_a_forked_run_reads_the_forked_set_and_has_the_same_models(tiny_run, tmp_path):
    base = Run(tiny_run)
    record_bytes = base.record_path.read_bytes()
    sset = base.shard_set(base.record()).fork(tmp_path / "shards" / "s")
    new = base.fork(tmp_path / "runs" / "r", sset)
    record = new.read_record()
    assert new.shard_set(new.record()).dir.resolve() == sset.dir.resolve()
    models = sorted(p.relative_to(base.dir) for p in base.dir.rglob("*.keras"))
    assert models and sorted(p.relative_to(new.dir) for p in new.dir.rglob("*.keras")) == models
    for rel in models:
        assert (new.dir / rel).read_bytes() == (base.dir / rel).read_bytes()
    for entry in record["components"].values():
        assert (new.dir / entry["file"]).is_file()
    assert base.record_path.read_bytes() == record_bytes  # the original still reads its own set

    stamp = {p: p.stat().st_mtime_ns for p in new.dir.rglob("*") if p.is_file()}
    again = base.fork(new.dir)  # returned as it is
    assert again.dir == new.dir
    assert {p: p.stat().st_mtime_ns for p in new.dir.rglob("*") if p.is_file()} == stamp
    assert new.shard_set(new.record()).dir.resolve() == sset.dir.resolve()

    other = tiny_set(tmp_path / "other", seed=4)
    with pytest.raises(KpcnError, match=re.escape(str(other.dir))):
        base.fork(tmp_path / "runs" / "r2", other)
    assert not (tmp_path / "runs" / "r2").exists()


def test_the_runs_own_phases_train_on_round_0_only(tmp_path):
    sset = tiny_set(tmp_path)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=str(sset.dir.parent), model=TINY_MODEL,
                                  batch_size=2)
    _, before = check_inputs(cfg, sset)
    variance_round(sset.dir)
    on_disk = train_shards_on_disk(sset.dir)
    assert on_disk.get("round-001"), "the error round was not written"
    _, after = check_inputs(cfg, sset)
    assert after == before
    assert sorted(Path(p).resolve() for p in after["train"]) == sorted(p.resolve() for p in on_disk["round-000"])
    for path in after["train"] + after["val"]:
        assert set(np.unique(read_shard(path)["round"])) == {0}


# ---------------------------------------------------------------- the study's arithmetic


def hand_made_loop() -> dict:
    """Rounds listed out of order, one unfinished; seconds of evaluation that must not count."""
    return {
        "before": {"relmse": 1.0, "dssim": 0.5, "steps": 10, "seconds": {"evaluation": 99.0}},
        "rounds": {
            "round-002": {"status": "done", "relmse": 0.5, "dssim": 0.2, "total_steps": 18,
                          "seconds": {"training": 4.0, "evaluation": 7.0}},
            "round-001": {"status": "done", "relmse": 0.8, "dssim": 0.4, "total_steps": 14,
                          "seconds": {"error_maps": 1.0, "shards": 0.5, "training": 2.5, "evaluation": 100.0}},
            "round-003": {"status": "training", "seconds": {"error_maps": 50.0, "shards": 1.0}},
        },
    }


def test_cumulative_cost_counts_error_maps_shards_and_training_of_finished_rounds():
    assert cumulative_cost(hand_made_loop()) == pytest.approx([0.0, 4.0, 8.0])
    assert cumulative_cost({"before": {}, "rounds": {}}) == [0.0]


@pytest.mark.parametrize("seconds, relmse, dssim", [
    (0.0, 1.0, 0.5),
    (2.0, 0.9, 0.45),      # half way to round 1 (4 s)
    (4.0, 0.8, 0.4),
    (6.0, 0.65, 0.3),      # half way from round 1 to round 2 (8 s)
    (7.0, 0.575, 0.25),
    (8.0, 0.5, 0.2),
    (8.5, math.nan, math.nan),  # past the last measured round
])
def test_scores_at_equal_time_interpolate_linearly_between_rounds(seconds, relmse, dssim):
    loop = hand_made_loop()
    for score, want in (("relmse", relmse), ("dssim", dssim)):
        got = at_time(loop, score, seconds)
        if math.isnan(want):
            assert math.isnan(got)
        else:
            assert got == pytest.approx(want, abs=1e-12)


@pytest.mark.parametrize("differences, want", [
    ([-0.1, -0.02, -3.0], "better"),
    ([0.1, 0.3], "worse"),
    ([-0.1, 0.2], "within seed noise"),
    ([0.0, 0.0], "within seed noise"),
    ([-0.1, math.nan], "not measured"),
    ([], "not measured"),
])
def test_a_difference_is_a_verdict_only_when_every_seed_agrees(differences, want):
    assert verdict(differences) == want


def test_each_frames_score_is_read_per_round_and_interpolated_in_time():
    loop = hand_made_loop()
    for row, values in ((loop["before"], (1.0, 3.0)), (loop["rounds"]["round-001"], (0.6, 3.0)),
                        (loop["rounds"]["round-002"], (0.2, 5.0))):
        row["frames"] = [{"frame": f"f{i}", "relmse": v} for i, v in enumerate(values)]
    np.testing.assert_array_equal(frame_scores_at(loop, "relmse", rounds=2), [0.2, 5.0])
    # 6 s is half way from round 1 (4 s) to round 2 (8 s)
    np.testing.assert_allclose(frame_scores_at(loop, "relmse", seconds=6.0), [0.4, 4.0], rtol=1e-12)
    assert np.isnan(frame_scores_at(loop, "relmse", seconds=9.0)).all()


def test_the_frame_test_counts_lower_frames_and_takes_the_geometric_mean_of_the_ratios():
    a = np.array([1.0, 2.0, 3.0, 4.0, 5.0, 1.0, np.nan])
    b = np.array([2.0, 4.0, 6.0, 8.0, 2.5, 1.0, 1.0])
    found = frame_test(a, b)
    # the tie (1 vs 1) and the unmeasured frame are left out: 4 of 5 lower under a
    assert (found["frames_lower"], found["frames_compared"]) == (4, 5)
    # two-sided sign test of 4 of 5: P(X <= 1) + P(X >= 4) = (1 + 5 + 5 + 1) / 32
    assert found["sign_test_p"] == pytest.approx(12 / 32)
    ratios = np.array([0.5, 0.5, 0.5, 0.5, 2.0, 1.0])
    assert found["geomean_ratio"] == pytest.approx(float(np.prod(ratios) ** (1 / 6)))


# ---------------------------------------------------------------- the study through the command line


STUDY = ("resample-study", "--set", "s", "--shards", "shards", "--runs", "runs/study", "--seeds", "0,1",
         "--base-steps", "8", "--rounds", "2", "--round-steps", "4", "--patches-per-image", "2", "--out", "reports")
BASE_STEPS, ROUNDS, ROUND_STEPS = 8, 2, 4


def shard_files_state(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_ino, p.stat().st_mtime_ns, p.stat().st_size)
            for p in sorted(root.rglob("shard-*.h5"))}


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """The study of two seeds at toy size, run twice; what the runs left, and the second run's result."""
    root = tmp_path_factory.mktemp("study")
    make_renders(root / "renders" / "s")
    # 8 patches per image: the one held-out scene fills a validation batch of the cpu preset (8)
    res = kpcn("shards", "--set", "s", "--renders", "renders", "--out", "shards", "--patch-size", "16",
               "--patches-per-image", "8", "--patches-per-shard", "8", cwd=root)
    assert res.returncode == 0, res.stderr[-3000:]
    first = run_main(*STUDY, cwd=root)
    assert first.returncode == 0, first.stderr[-3000:]
    shards_after_first = shard_files_state(root / "runs" / "study" / "shards") | shard_files_state(root / "shards")
    runs_after_first = checksums(root / "runs" / "study")
    report_json = json.loads((root / "reports" / "resample.json").read_text())
    second = run_main(*STUDY, cwd=root)
    return {"root": root, "first": first, "second": second, "shards_after_first": shards_after_first,
            "runs_after_first": runs_after_first, "record": report_json}


def arm_run(root: Path, seed: int, arm: str) -> Run:
    return Run(root / "runs" / "study" / f"s-seed{seed}" / arm)


def rounds_json(root: Path, seed: int, arm: str) -> dict:
    return json.loads((arm_run(root, seed, arm).dir / "resample" / "rounds.json").read_text())


def timings_json(root: Path, seed: int, arm: str) -> dict:
    """The arm's seconds: ``before`` and each round -> error_maps, shards, training, evaluation."""
    return json.loads((arm_run(root, seed, arm).dir / "resample" / "timings.json").read_text())


@pytest.mark.slow
def test_the_study_reports_every_arm_of_every_seed_at_equal_steps(study):
    root, record = study["root"], study["record"]
    for name in ("resample.md", "resample.json", "resample.png"):
        assert (root / "reports" / name).is_file() and (root / "reports" / name).stat().st_size > 0
    assert set(record["seeds"]) == {"0", "1"}
    for seed in (0, 1):
        for arm in ARMS:
            loop = record["seeds"][str(seed)]["loops"][arm]
            done = [e for e in loop["rounds"].values() if e.get("status") == "done"]
            assert len(done) >= ROUNDS, (seed, arm)
            for entry in done:
                assert {"relmse", "dssim", "seconds", "total_steps"} <= set(entry)
            own = rounds_json(root, seed, arm)  # the run folder's record, read independently
            assert own["rounds"]["round-002"]["total_steps"] == BASE_STEPS + ROUNDS * ROUND_STEPS
            assert own["rounds"]["round-001"]["total_steps"] == BASE_STEPS + ROUND_STEPS
            assert own["before"]["steps"] == BASE_STEPS
        base = Run(root / "runs" / "study" / f"s-seed{seed}" / "base").read_record()["train"]
        assert (base["seed"], base["steps"]) == (seed, BASE_STEPS)

    md = (root / "reports" / "resample.md").read_text()
    section = md.split("## At equal training steps")[1].split("## ")[0]
    for arm in ARMS:
        want = [rounds_json(root, seed, arm)["rounds"]["round-002"]["relmse"] for seed in (0, 1)]
        assert record["summary"]["table"][arm]["relmse"]["equal_steps"] == want
        row = next(line for line in section.splitlines() if line.startswith(f"| {arm} |"))
        assert row.split("|")[2].strip() == " / ".join(f"{v:.4f}" for v in want)
        dssim = [rounds_json(root, seed, arm)["rounds"]["round-002"]["dssim"] for seed in (0, 1)]
        assert record["summary"]["table"][arm]["dssim"]["equal_steps"] == dssim
    pair = next(p for p in record["summary"]["pairs"]
                if (p["a"], p["b"], p["score"], p["when"]) == ("error", "variance", "relmse", "equal_steps"))
    want = [rounds_json(root, s, "error")["rounds"]["round-002"]["relmse"]
            - rounds_json(root, s, "variance")["rounds"]["round-002"]["relmse"] for s in (0, 1)]
    assert pair["differences"] == pytest.approx(want, abs=1e-12)


def cost_curve(loop: dict, timings: dict) -> tuple[np.ndarray, np.ndarray]:
    """(cumulative seconds of error maps, shards and training; relMSE) before and after each finished round."""
    done = [k for k in sorted(loop["rounds"]) if loop["rounds"][k]["status"] == "done"]
    cost = np.cumsum([0.0] + [sum(timings[k].get(what, 0.0) for what in ("error_maps", "shards", "training"))
                              for k in done])
    return cost, np.array([loop["before"]["relmse"]] + [loop["rounds"][k]["relmse"] for k in done], np.float64)


@pytest.mark.slow
def test_the_study_compares_arms_at_the_costliest_arms_time(study):
    root, record = study["root"], study["record"]
    for i, seed in enumerate((0, 1)):
        curves = {arm: cost_curve(rounds_json(root, seed, arm), timings_json(root, seed, arm)) for arm in ARMS}
        budget = max(cost[ROUNDS] for cost, _ in curves.values())
        assert record["seeds"][str(seed)]["budget_seconds"] == pytest.approx(budget, abs=1e-9)
        for arm, (cost, relmse) in curves.items():
            want = np.interp(budget, cost, relmse) if budget <= cost[-1] + 1e-9 else math.nan
            got = record["summary"]["table"][arm]["relmse"]["equal_time"][i]
            assert (math.isnan(want) and math.isnan(got)) or got == pytest.approx(want, rel=1e-12), (seed, arm)
            rounds = len(cost) - 1  # an arm below the budget ran more rounds, up to 3x as many
            assert ROUNDS <= rounds <= 3 * ROUNDS
            assert cost[-1] >= budget - 1e-9 or rounds == 3 * ROUNDS, (seed, arm, cost, budget)


@pytest.mark.slow
def test_each_study_arm_adds_its_patches_to_its_own_copy_of_the_set(study):
    root = study["root"]
    original = manifest_of(root / "shards" / "s")
    assert list(original["rounds"]) == ["round-000"]  # the user's set is never resampled
    inputs = sum(1 for s in original["sources"] if s["role"] == "input" and s["split"] == "train")
    assert inputs >= 2
    sets = set()
    for seed in (0, 1):
        for arm, weight in (("continue", None), ("variance", 0.0), ("error", 0.5)):
            run = arm_run(root, seed, arm)
            set_dir = run.shard_set(run.record()).dir.resolve()
            manifest = manifest_of(set_dir)
            loop = rounds_json(root, seed, arm)
            if weight is None:
                assert set_dir == (root / "shards" / "s").resolve()
                assert "round-001" not in manifest["rounds"]
                assert all(e["patches"] == 0 for e in loop["rounds"].values())
                continue
            sets.add(set_dir)
            assert {"round-001", "round-002"} <= set(manifest["rounds"])
            for k in sorted(loop["rounds"]):
                entry = manifest["rounds"][k]
                assert entry["status"] == "complete"
                assert entry["provenance"]["error_weight"] == weight
                assert entry["provenance"]["patches_per_image"] == 2
                with_shards = [read_shard(set_dir / s["path"]) for s in entry["shards"]]
                assert sum(len(d["round"]) for d in with_shards) == loop["rounds"][k]["patches"] == 2 * inputs
                assert all(set(np.unique(d["round"])) == {int(k[6:])} for d in with_shards)
                model = entry["provenance"]["model"]
                if weight == 0:
                    assert model == {}  # no model ran
                    continue
                # the networks before the round, by the SHA-256 of their files in the arm's run
                assert set(model) == {"diffuse", "specular"}
                for name, found in model.items():
                    previous = "" if k == "round-001" else f"-round-{int(k[6:]) - 1:03d}"
                    assert found["file"] == f"{name}{previous}.keras"
                    assert found["sha256"] == hashlib.sha256((run.dir / found["file"]).read_bytes()).hexdigest()
            # no position is drawn twice from one render, in any round
            taken = [(int(src), int(y), int(x)) for path in set_dir.glob("round-*/shard-*.h5")
                     for d in [read_shard(path)] for src, (y, x) in zip(d["source"], d["position"])]
            assert len(taken) == len(set(taken))
    assert len(sets) == 4  # one copy per seed and arm that adds patches


@pytest.mark.slow
def test_running_the_study_again_reuses_everything(study):
    second = study["second"]
    assert second.returncode == 0, second.stderr[-3000:]
    root = study["root"]
    assert shard_files_state(root / "runs" / "study" / "shards") | shard_files_state(root / "shards") \
        == study["shards_after_first"]
    assert checksums(root / "runs" / "study") == study["runs_after_first"]  # no run trained or measured again
    again = json.loads((root / "reports" / "resample.json").read_text())
    assert again["summary"] == study["record"]["summary"]
    for seed, found in again["seeds"].items():
        assert found["budget_seconds"] == study["record"]["seeds"][seed]["budget_seconds"]
        for arm, loop in found["loops"].items():
            # the run's records, and the seconds from its timings file
            timings = timings_json(root, int(seed), arm)
            assert {k: {**e, "seconds": timings[k]} for k, e in rounds_json(root, int(seed), arm)["rounds"].items()} \
                == loop["rounds"]


@pytest.mark.slow
def test_running_the_study_again_reports_each_loop_as_its_run_records_it(study):
    root = study["root"]
    again = json.loads((root / "reports" / "resample.json").read_text())
    for seed, found in again["seeds"].items():
        for arm, loop in found["loops"].items():
            own = rounds_json(root, int(seed), arm)
            assert loop["config"] == own["config"], (seed, arm)
            assert loop["config"]["rounds"] == len(own["rounds"])


# ---------------------------------------------------------------- the command line's refusals


@pytest.fixture(scope="module")
def forked_run(tiny_run, tmp_path_factory) -> Path:
    """A copy of the tiny run on its own copy of the shard set (the session's set stays as it is)."""
    tmp = tmp_path_factory.mktemp("cli")
    base = Run(tiny_run)
    sset = base.shard_set(base.record()).fork(tmp / "shards" / "s")
    return base.fork(tmp / "runs" / "r", sset).dir


@pytest.mark.parametrize("args, flag", [
    (["--error-weight", "2"], "--error-weight"),
    (["--metric", "mse"], "--metric"),
    (["--rounds", "0"], "--rounds"),
    (["--round-steps", "0"], "--round-steps"),
    (["--round-decay", "0"], "--round-decay"),
])
def test_bad_resample_options_are_one_line_errors_naming_the_flag(forked_run, args, flag):
    assert_one_line_error(run_main("resample", "--run", forked_run, *args, cwd=forked_run.parent), flag)


def test_resampling_a_folder_that_is_not_a_run_names_it(tmp_path):
    (tmp_path / "empty").mkdir()
    assert_one_line_error(run_main("resample", "--run", tmp_path / "empty", cwd=tmp_path), str(tmp_path / "empty"),
                          "not a run")


@pytest.mark.slow
def test_a_round_trains_each_network_exactly_its_round_steps(tiny_run, tmp_path):
    """6 round steps at the base run's 4 per epoch: a shorter last epoch, so each network's optimizer has
    taken the base run's steps and then exactly the round's, as the record says (not two whole epochs)."""
    base = Run(tiny_run)
    record = base.read_record()
    run = base.fork(tmp_path / "runs" / "r", base.shard_set(base.record()).fork(tmp_path / "shards" / "s"))
    res = run_main("resample", "--run", run.dir, "--rounds", "1", "--round-steps", "6", "--patches-per-image", "0",
               "--error-weight", "0", cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    base_steps = record["train"]["steps"]
    assert (base_steps, record["train"]["steps_per_epoch"]) == (8, 4)
    phases = run.read_record()["phases"]
    for branch in ("diffuse", "specular"):
        name = f"{branch}-round-001"
        optimizer = load_model(run.dir / f"{name}.keras").optimizer
        assert int(optimizer.iterations.numpy()) == base_steps + 6 == base_steps + phases[name]["steps"]


@pytest.fixture(scope="module")
def resampled_run(forked_run):
    """The copy of the tiny run after one error round (error weight 0.5) through the command line."""
    res = run_main("resample", "--run", forked_run, "--rounds", "1", "--round-steps", "2", "--error-weight", "0.5",
               "--patches-per-image", "2", cwd=forked_run.parent)
    assert res.returncode == 0, res.stderr[-3000:]
    return forked_run


@pytest.mark.slow
def test_an_error_round_records_the_files_of_the_model_that_drew_it(resampled_run):
    run = Run(resampled_run)
    record = run.read_record()
    sset_dir = run.shard_set(run.record()).dir
    entry = manifest_of(sset_dir)["rounds"]["round-001"]
    model = entry["provenance"]["model"]
    assert set(model) == {"diffuse", "specular"}
    for name, found in model.items():
        # the networks of the run before the round: the files of its own phases
        assert found["file"] == f"{name}.keras"
        assert found["sha256"] == hashlib.sha256((run.dir / found["file"]).read_bytes()).hexdigest()
    assert entry["provenance"]["error_weight"] == 0.5
    loop = json.loads((run.dir / "resample" / "rounds.json").read_text())
    assert loop["rounds"]["round-001"]["status"] == "done"
    # the record's components now point at the round's phases
    assert {c["file"] for c in record["components"].values()} == {"diffuse-round-001.keras",
                                                                   "specular-round-001.keras"}


@pytest.mark.slow
def test_a_loops_seconds_are_kept_in_its_timings_file_alone(resampled_run):
    """Wall-clock seconds differ between a resumed and an uninterrupted loop: they are in the resample
    folder's timings.json (and the run's, per phase), never in the records."""
    run = Run(resampled_run)
    timings = json.loads((run.dir / "resample" / "timings.json").read_text())
    assert set(timings) == {"before", "round-001"}
    assert set(timings["before"]) == {"evaluation"}
    assert set(timings["round-001"]) == {"error_maps", "shards", "training", "evaluation"}
    assert all(s >= 0 for entry in timings.values() for s in entry.values())
    for path in (run.dir / "config.json", run.dir / "resample" / "rounds.json"):
        assert "seconds" not in path.read_text(), path
    phases = json.loads((run.dir / "timings.json").read_text())
    assert {"diffuse-round-001", "specular-round-001"} <= set(phases)


@pytest.mark.slow
def test_resample_refuses_to_continue_a_loop_with_other_settings(resampled_run):
    before = checksums(resampled_run)
    res = run_main("resample", "--run", resampled_run, "--rounds", "1", "--round-steps", "2", "--error-weight", "0.25",
               "--patches-per-image", "2", cwd=resampled_run.parent)
    assert_one_line_error(res, "other settings", "error_weight")
    assert checksums(resampled_run) == before


@pytest.mark.slow
def test_resample_refuses_a_run_with_a_compositor(tmp_path):
    shard_cfg = build_tiny_shards(tmp_path)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=shard_cfg.out_root, model=TINY_MODEL, steps=2,
                                  steps_per_epoch=2, batch_size=2, val_batches=1, compositor_steps=2,
                                  compositor={"kind": "alpha", "width": 4, "depth": 3, "kernel_size": 3})
    run_dir = train(cfg, tmp_path / "runs" / "c", verbose=0)
    manifest = manifest_of(shard_cfg.set_dir)
    assert_one_line_error(run_main("resample", "--run", run_dir, "--rounds", "1", cwd=tmp_path), "compositor")
    assert manifest_of(shard_cfg.set_dir) == manifest
    assert not (Path(run_dir) / "resample").exists()
