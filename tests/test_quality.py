"""``kpcn quality``: the lever table and its combination, the frames each lever beats OIDN on counted against
a hand-built per-frame table, the report written again from its record, a bad lever a one-line error, a larger
render set reusing the renders it shares, and (slow) a tiny study whose raw scores a float64 computation from
the EXRs reproduces."""

import dataclasses
import datetime
import json
import math
import shutil
import statistics
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, process_state_kept, run_main
from helpers.tiny import TINY_MODEL, build_tiny_shards

from kpcn_keras.studies import compare as cmp
from kpcn_keras.studies import quality as qs
from kpcn_keras.studies import quality_report as qr
from kpcn_keras.studies.config import QUALITY_LEVERS, QualityConfig, combine
from prep import exr, layouts
from prep.errors import KpcnError, OptionError

RENDERERS = Path(__file__).parent / "fixtures" / "renderers"
OVERRIDES = {"model": TINY_MODEL, "batch_size": 2, "val_batches": 1}


def test_every_lever_is_an_entry_and_the_combination_merges_them():
    for what, preset, overrides, renders in QUALITY_LEVERS.values():
        assert what and preset and isinstance(overrides, dict) and (renders is None or renders)
    levers = {"a": ("a", "cpu", {"model": {"depth": 3}, "compositor": {"kind": "kernel"}}, None),
              "b": ("b", "unet", {"model": {"width": 8}, "reference_tau": 0.1}, {"per_family": 5}),
              "c": ("c", "kpcn-paper", {}, None)}
    what, preset, overrides, renders = combine("a", "b", levers=levers)
    assert preset == "unet" and renders == {"per_family": 5}
    assert overrides == {"model": {"depth": 3, "width": 8}, "compositor": {"kind": "kernel"}, "reference_tau": 0.1}
    assert "a, b" in what
    with pytest.raises(ValueError, match="different presets"):
        combine("b", "c", levers=levers)
    # dilated and unet are two trunks: the combination takes the unet's
    others = [n for n in QUALITY_LEVERS if n not in ("cpu", "dilated", "combination")]
    assert QUALITY_LEVERS["combination"][2:] == combine(*others)[2:]
    with pytest.raises(ValueError, match="different presets"):
        combine("unet", "dilated")
    cfg = QualityConfig()
    assert qs.lever_set(cfg, "cpu") == qs.lever_set(cfg, "multiscale-kernel") == "default"
    # the data lever and the combination render the same larger set once
    assert qs.lever_set(cfg, "data") == qs.lever_set(cfg, "combination") != "default"


def test_a_bad_lever_is_one_line_naming_it_and_the_known_ones(tmp_path):
    with pytest.raises(OptionError, match="levers has unknown 'bogus'"):
        QualityConfig(levers=("cpu", "bogus"))
    for bad in ({"budget": 0}, {"levers": ()}, {"frames": ()}, {"levers": ("cpu", "cpu")}):
        with pytest.raises(OptionError):
            QualityConfig(**bad)
    res = run_main("quality", "--levers", "cpu,bogus", "--out", str(tmp_path / "reports"), cwd=tmp_path)
    assert_one_line_error(res, "--levers", "'bogus'", *QUALITY_LEVERS)
    assert not any(tmp_path.iterdir())
    res = run_main("quality", "--frames", str(tmp_path / "nowhere"), "--out", str(tmp_path / "reports"), cwd=tmp_path)
    assert_one_line_error(res, "--frames", "nowhere", "no such file or folder")


# relMSE per frame: (kind, spp, raw, cpu, data, OIDN, Blender's own or None)
TABLE = [
    ("held-out", 4, 0.50, 0.010, 0.020, 0.015, None),
    ("held-out", 4, 0.40, 0.030, 0.010, 0.020, None),
    ("held-out", 16, 0.20, 0.004, 0.006, 0.005, None),
    ("held-out", 16, 0.10, 0.009, 0.002, 0.003, None),
    ("held-out", 64, 0.05, 0.002, 0.001, 0.001, None),  # data ties OIDN: not below
    # Blender's own above OIDN's here, so that OIDN is each frame's anchor (the anchor test below lowers it)
    ("validation", 4, 0.30, 0.020, 0.010, 0.005, 0.006),
    ("validation", 16, 0.08, 0.006, 0.003, 0.004, 0.005),
    ("validation", 64, 0.02, 0.001, 0.002, 0.003, 0.004),
]
LEVERS = ("cpu", "data")


def _scores(relmse):
    return {"relmse": relmse, "dssim": relmse / 2, "relse_p999": relmse * 10}


def hand_record(oidn=True) -> dict:
    frames = []
    for i, (kind, spp, raw, cpu, data, o, blender) in enumerate(TABLE):
        row = {"kind": kind, "frame": f"s{i} {spp} spp", "scene": f"s{i}", "spp": spp, "raw": _scores(raw),
               "levers": {"cpu": {**_scores(cpu), "model": "full"}, "data": {**_scores(data), "model": "full"}}}
        if oidn:
            row["oidn"] = _scores(o)
        if kind == "validation":
            row.update(path=f"v/s{i}-{spp:05d}spp.exr", reference_path="v/ref.exr", renderer="v", layout="cycles",
                       inputs="no-variance")
            for entry in row["levers"].values():
                entry["set"] = "default"
            row["blender"] = _scores(blender)
        frames.append(row)
    network = {"phase_steps": {"diffuse": 3, "specular": 3}, "trained_s": 4.0}
    return {
        "date": "2026-12-02", "command": "kpcn quality --budget 10", "started": "s", "finished": "f",
        "config": {**dataclasses.asdict(QualityConfig(levers=LEVERS, budget=10)), "levers": list(LEVERS),
                   "frames": ["v"]},
        "levers": {n: {"what": QUALITY_LEVERS[n][0]} for n in LEVERS},
        "overrides": {}, "input_sets": ["full", "no-variance"], "rules": {"seconds_per_network": 5.0},
        "oidn": oidn,
        "machine": {"cpus": 2, "platform": "p", "python": "3.11", "torch": "t", "keras": "k", "torch_threads": 2,
                    "load_average_before": [0.0] * 3, "load_average_after": [0.0] * 3},
        "plans": {n: {"set": "default", "run": f"runs/{n}", "networks": {"full": network, "no-variance": network}}
                  for n in LEVERS},
        "frames": frames, "panels": [],
    }


def _anchor(t) -> float:
    """A frame's anchor, by hand: the lower relMSE of OIDN's and Blender's own where the frame has it."""
    return min(t[5], t[6]) if t[6] is not None else t[5]


def _expected(column: int, kinds=("held-out", "validation"), spp=None):
    """(frames where the lever's relMSE is strictly below the anchor's, frames, median of the ratio), by hand."""
    rows = [t for t in TABLE if t[0] in kinds and (spp is None or t[1] == spp)]
    ratios = sorted(t[column] / _anchor(t) for t in rows)
    n = len(ratios)
    median = ratios[n // 2] if n % 2 else (ratios[n // 2 - 1] + ratios[n // 2]) / 2
    return sum(t[column] < _anchor(t) for t in rows), n, median


def _tables(md: str) -> list[list[list[str]]]:
    tables, current = [], []
    for line in md.splitlines() + [""]:
        if line.startswith("|"):
            current.append([c.strip() for c in line.strip("|").split("|")])
        elif current:
            tables.append(current[2:])
            current = []
    return tables


def test_frames_below_oidn_are_counted_as_a_hand_count_of_the_table():
    record = hand_record()
    md = qr.format_report(record)
    levers, held, val, each, target = _tables(md)
    for lever, column in (("cpu", 3), ("data", 4)):
        row = next(r for r in levers if r[0] == f"`{lever}`")
        for cell, kinds in ((row[4], ("held-out",)), (row[5], ("validation",)), (row[6], KINDS_ALL)):
            lower, n, _ = _expected(column, kinds)
            assert cell == f"{lower} of {n}"
        assert row[7] == f"{_expected(column)[2]:.2f}×"
        for table, kind in ((held, "held-out"), (val, "validation")):
            for spp in (4, 16, 64):
                cells = next(r for r in table if r[0] == str(spp) and r[1] == f"`{lever}`")
                lower, n, median = _expected(column, (kind,), spp)
                values = [t[column] for t in TABLE if t[0] == kind and t[1] == spp]
                assert cells[2] == str(n) and cells[3] == f"{np.mean(values):.4f}"
                assert cells[4] == f"{np.mean(values) / 2:.4f}" and cells[5] == f"{np.mean(values) * 10:.4f}"
                assert cells[6] == f"{lower} of {n}" and cells[7] == f"{median:.2f}×"
    # Blender's own appears beside the validation frames only
    assert any(r[1] == "Blender's own" for r in val) and not any(r[1] == "Blender's own" for r in held)
    blender64 = next(r for r in val if r[0] == "64" and r[1] == "Blender's own")
    assert blender64[3] == "0.0040"
    assert [r[0] for r in each] == [f"s{i} {t[1]} spp" for i, t in enumerate(TABLE) if t[0] == "validation"]
    # the headline: data has the lower mean held-out relMSE, and is below OIDN on 4 of 8 frames: level
    assert qr.best(record) == "data"
    lower, n, median = _expected(4)
    assert (lower, n) == (4, 8)
    headline = next(line for line in md.splitlines() if line.startswith("**Best"))
    assert f"lower relMSE on {lower} of {n} frames (2 of 5 held-out frames; 2 of 3 validation frames)" in headline
    assert f"{median:.2f}×" in headline and "level with OIDN" in headline


KINDS_ALL = ("held-out", "validation")


def test_the_defaults_target_is_judged_by_the_frame_that_decides_half_the_validation_frames_at_16_spp():
    record = hand_record()
    # one validation frame at 16 spp (TABLE): cpu 0.006 against OIDN's 0.004, data 0.003
    target = _tables(qr.format_report(record))[4]
    assert target == [["`cpu`", "0 of 1", "1", "1.500×", "out by 50%", "default"],
                      ["`data`", "1 of 1", "1", "0.750×", "met", "default"]]
    # three: half is two, so the second lowest ratio decides
    first = next(r for r in record["frames"] if r["kind"] == "validation" and r["spp"] == 16)
    for cpu, data in ((0.0036, 0.0060), (0.0050, 0.0042)):  # against OIDN's 0.004: cpu 0.90, 1.25; data 1.50, 1.05
        extra = json.loads(json.dumps(first))
        extra["levers"]["cpu"]["relmse"], extra["levers"]["data"]["relmse"] = cpu, data
        record["frames"].append(extra)
    got = {lever: qr.default_target(record, lever) for lever in LEVERS}
    assert got["cpu"] == {"lower": 1, "frames": 3, "needed": 2, "deciding": pytest.approx(1.25)}
    assert got["data"] == {"lower": 1, "frames": 3, "needed": 2, "deciding": pytest.approx(1.05)}
    rows = _tables(qr.format_report(record))[4]
    assert [r[-2] for r in rows] == ["out by 25%", "out by 5%"]
    assert "The default's target" not in qr.format_report(hand_record(oidn=False))


# the measured model's relMSE on TABLE's frames, in order: below OIDN on frames 0, 2, 3, 5 and 7; equal on 4
MODEL_RELMSE = (0.012, 0.024, 0.004, 0.002, 0.001, 0.004, 0.005, 0.002)


def test_the_shipped_models_targets_are_judged_on_the_studys_frames_as_a_hand_count():
    record = hand_record()
    for row, relmse in zip(record["frames"], MODEL_RELMSE, strict=True):
        row[qr.MODEL] = {**_scores(relmse), "model": "full", **({"set": "other"} if "path" in row else {})}
    record[qr.MODEL] = {"run": "models/default", "set": "default-r1", "shipped": True}
    md = qr.format_report(record)
    ratios = sorted(m / t[5] for m, t in zip(MODEL_RELMSE, TABLE))
    lower = sum(m < t[5] for m, t in zip(MODEL_RELMSE, TABLE))
    assert lower == 5 and math.ceil(8 * 2 / 3) == 6
    # a model is no lever: the best lever is judged as before, though the model is below OIDN on more frames
    assert qr.best(record) == "data"
    tables = _tables(md)
    targets, default = tables[5], tables[4]
    # the sixth lowest ratio decides: frame 4, level with OIDN, and a tie is not below
    assert qr.MODEL not in QUALITY_LEVERS
    assert ratios[5] == 1.0 and targets[0][1:] == ["5 of 8", "6 frames", "1.000× (the deciding frame)", "out by 0.0%"]
    for row, spp in zip(targets[1:3], (16, 64)):  # DSSIM is relMSE / 2 in TABLE: the ratio is of the relMSE means
        model = np.mean([m for m, t in zip(MODEL_RELMSE, TABLE) if t[1] == spp])
        oidn = np.mean([t[5] for t in TABLE if t[1] == spp])
        assert row[1:4] == [f"{model / 2:.4f}", f"{oidn / 2:.4f}", f"{model / oidn:.2f}×"]
        assert row[4] == ("met" if model < oidn else f"out by {model / oidn - 1:.0%}")
    assert len(targets) == 3
    # the default's target, the model beside the levers: one validation frame at 16 spp, 0.005 against OIDN's 0.004
    assert default[-1] == ["shipped model `default`", "0 of 1", "1", "1.250×", "out by 25%", "other"]
    levers, held, val, each = tables[:4]
    label = "shipped model `default`"
    assert levers[-1][0] == label and levers[-1][4:] == ["3 of 5", "2 of 3", "5 of 8",
                                                          f"{statistics.median(ratios):.2f}×"]
    cells = next(r for r in held if r[0] == "16" and r[1] == label)
    assert cells[3] == f"{np.mean(MODEL_RELMSE[2:4]):.4f}" and cells[6] == "2 of 2"
    assert [r[-3] for r in each] == [f"{m:.4f}" for m, t in zip(MODEL_RELMSE, TABLE) if t[0] == "validation"]
    headline = next(line for line in md.splitlines() if line.startswith(f"**The {label}**"))
    assert f"on 5 of 8 frames, the median ratio {statistics.median(ratios):.2f}×" in headline
    # below OIDN on 6 of the 8: met, decided by the sixth lowest ratio
    record["frames"][1][qr.MODEL]["relmse"] = 0.019
    met = _tables(qr.format_report(record))[5][0]
    assert met[1] == "6 of 8" and met[4] == "met"


def test_a_frame_counts_against_its_strongest_anchor_prefiltered_oidn_or_blenders_own():
    record = hand_record()
    frames = record["frames"]
    frames[0]["oidn_prefiltered"] = _scores(0.005)  # held-out 4 spp: cpu 0.010 was below OIDN's 0.015, not this
    frames[1]["oidn_prefiltered"] = _scores(0.040)  # above OIDN's 0.020: plain stays the anchor
    frames[6]["blender"] = _scores(0.002)  # validation 16 spp: data 0.003 was below OIDN's 0.004, not Blender's
    anchors = [min(f[k]["relmse"] for k in ("oidn", "oidn_prefiltered", "blender") if k in f) for f in frames]
    levers = _tables(qr.format_report(record))[0]
    for lever, before in (("cpu", 3), ("data", 4)):
        lower = sum(f["levers"][lever]["relmse"] < a for f, a in zip(frames, anchors))
        assert next(r for r in levers if r[0] == f"`{lever}`")[6] == f"{lower} of 8"
        assert lower == _expected(before)[0] - 1  # each lost the one frame its new anchor took
    held = _tables(qr.format_report(record))[1]
    assert next(r for r in held if r[0] == "4" and r[1] == "OIDN prefiltered")[3] == f"{(0.005 + 0.040) / 2:.4f}"


def test_the_best_lever_is_the_one_below_oidn_on_most_frames_not_the_one_a_single_frame_makes_best_by_mean():
    record = hand_record()
    held = [r for r in record["frames"] if r["kind"] == "held-out"]
    held[0]["levers"]["data"]["relmse"] = 1.0  # one frame with a speckled reference, far off for data alone
    means = {lever: np.mean([r["levers"][lever]["relmse"] for r in held]) for lever in LEVERS}
    assert means["cpu"] < means["data"]  # by its mean, cpu would be the best
    assert (_expected(3)[0], _expected(4)[0]) == (3, 4)  # by frames below OIDN, data is (unchanged: it was above)
    assert qr.best(record) == "data"
    headline = next(line for line in qr.format_report(record).splitlines() if line.startswith("**Best"))
    assert headline.startswith("**Best lever by frames: `data`** (mean held-out relMSE "
                               f"{means['data']:.4f})")
    without = hand_record(oidn=False)  # nothing to count: the lowest mean
    without["frames"][0]["levers"]["data"]["relmse"] = 1.0
    assert qr.best(without) == "cpu"
    # a tie in frames is broken by the lower median ratio to OIDN's, before the mean
    record["frames"][1]["levers"]["cpu"]["relmse"] = 0.019  # now below OIDN's 0.020: 4 of 8, as data
    ratio = {lever: statistics.median(r["levers"][lever]["relmse"] / r["oidn"]["relmse"] for r in record["frames"])
             for lever in LEVERS}
    assert ratio["data"] < ratio["cpu"] and qr.best(record) == "data"


def test_without_oidn_the_report_says_so_and_counts_nothing():
    md = qr.format_report(hand_record(oidn=False))
    assert "OIDN, the denoiser to beat, is not installed here" in md
    levers = _tables(md)[0]
    assert all(set(r[4:]) == {"—"} for r in levers)
    assert "not installed (pip install '.[oidn]')" in md


def test_report_only_rewrites_the_reports_from_the_record_alone(tmp_path):
    record = hand_record()
    record["config"]["panel_spp"] = 2  # no validation frame at 2 spp: no panel to denoise with a run
    (tmp_path / "quality.json").write_text(json.dumps(record, indent=2) + "\n")
    (tmp_path / "quality.md").write_text("an older report\n")
    before = datetime.date.today()
    res = run_main("quality", "--report-only", "--out", str(tmp_path), cwd=tmp_path)
    assert res.returncode == 0, res.stderr[-3000:]
    md = (tmp_path / "quality.md").read_text()
    days = [f"`kpcn quality --report-only` on {d.isoformat()}" for d in {before, datetime.date.today()}]
    assert any(md == qr.format_report({**record, "rewritten": day}) for day in days)
    assert (tmp_path / "quality.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads((tmp_path / "quality.json").read_text()) == record
    res = run_main("quality", "--report-only", "--out", str(tmp_path / "empty"), cwd=tmp_path)
    assert_one_line_error(res, str(tmp_path / "empty" / "quality.json"))


def test_a_larger_render_set_links_the_renders_it_shares_with_the_same_seed(tmp_path):
    from prep.render.renderset import RenderConfig, _renders, render_seed, reuse_renders

    small = RenderConfig(set_name="small", families=("cornell",), per_family=1, width=8, height=8,
                         input_spp=(4,), reference_spp=8, out_root=str(tmp_path))
    folder = tmp_path / "small"
    folder.mkdir()
    scenes = {}
    for r in _renders(small):
        (folder / r.name).write_bytes(r.name.encode())
        scene = scenes.setdefault(r.index, {"family": r.family, "index": r.index, "seeds": {}, "files": {}})
        scene["seeds"][str(r.spp)], scene["files"][str(r.spp)] = r.seed, r.name
    record = {"config": {**dataclasses.asdict(small), "families": ["cornell"], "input_spp": [4]},
              "scenes": list(scenes.values())}
    (folder / "config.json").write_text(json.dumps(record))
    large = dataclasses.replace(small, set_name="large", per_family=2, input_spp=(2, 4))
    linked = reuse_renders(large, folder)
    assert sorted(linked) == sorted(r.name for r in _renders(small))
    assert all((tmp_path / "large" / n).read_bytes() == n.encode() for n in linked)
    assert reuse_renders(large, folder) == []  # already there
    # another seed renders other pixels: nothing is shared
    assert reuse_renders(dataclasses.replace(large, set_name="other", seed=1), folder) == []
    # a record whose seed for a file is not the one this set gives it: that file is rendered, not linked
    scenes[0]["seeds"]["4"] = render_seed(0, "cornell", 0, 4) + 1
    (folder / "config.json").write_text(json.dumps(record))
    assert "cornell-000-00004spp.exr" not in reuse_renders(dataclasses.replace(large, set_name="third"), folder)


def _fake_probe(base, scratch):
    return {p.name: [1.0] * cmp.PROBE_SKIP + [0.05] * (cmp.PROBE_STEPS - cmp.PROBE_SKIP) for p in base.phases()}


def _relmse64(x, r) -> float:
    x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
    return float(np.mean((x - r) ** 2 / (r * r + 0.01)))


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory) -> tuple[QualityConfig, dict, object]:
    """A tiny study of two levers on the tiny shard set and the Cycles and Mitsuba validation frames, with a
    stand-in for Blender's own denoised frame (the reference itself, so its relMSE is 0), steps planned from a
    fixed probe: (its configuration, its record, the shard configuration)."""
    tmp = tmp_path_factory.mktemp("quality")
    full = build_tiny_shards(tmp)
    frames = tmp / "frames"
    shutil.copytree(RENDERERS / "cycles5", frames / "cycles5")
    shutil.copytree(RENDERERS / "mitsuba3", frames / "mitsuba3")
    shutil.copy(frames / "cycles5" / "studio-00256spp.exr", frames / "cycles5" / "studio-00016spp-blender-oidn.exr")
    cfg = QualityConfig(set_name="s", render_root=full.render_root, shards_root=full.out_root,
                        runs_root=str(tmp / "runs"), out_dir=str(tmp / "reports"), budget=3.0,
                        levers=("cpu", "multiscale-kernel"), frames=(str(frames),))
    with process_state_kept(), pytest.MonkeyPatch.context() as patch:
        patch.setattr(cmp, "probe_configuration", _fake_probe)
        record = qs.quality(cfg, overrides=OVERRIDES, verbose=0, log=lambda *_: None)
    return cfg, record, full


def _studio(cfg: QualityConfig, spp: int) -> Path:
    return Path(cfg.frames[0]) / "cycles5" / f"studio-{spp:05d}spp.exr"


@pytest.mark.slow
def test_a_tiny_study_trains_each_lever_for_every_layout_and_writes_the_reports(tiny_study):
    cfg, record, _ = tiny_study
    out = Path(cfg.out_dir)
    assert json.loads((out / "quality.json").read_text()) == json.loads(json.dumps(record))
    assert (out / "quality.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert record["input_sets"] == ["full", "no-variance", "no-split"]
    # 3 s over three networks, 1 s each, at 0.05 s per step of every phase: the two branches together get all
    # of it (80 % beside a compositor, which gets the rest); a no-split network trains its diffuse branch alone
    expected = {"cpu": {"full": {"diffuse": 10, "specular": 10}, "no-split": {"diffuse": 20}},
                "multiscale-kernel": {"full": {"diffuse": 8, "specular": 8, "compositor": 4}}}
    for lever in cfg.levers:
        networks = record["plans"][lever]["networks"]
        assert list(networks) == record["input_sets"]
        assert all(n["seconds"] == 1.0 for n in networks.values())
        for inputs, steps in expected[lever].items():
            assert networks[inputs]["phase_steps"] == steps
    served = {r["frame"]: r["levers"]["cpu"]["model"] for r in record["frames"] if r["kind"] == "validation"}
    assert served == {"cycles5/studio 16 spp": "no-variance", "mitsuba3/cornell 16 spp": "no-split"}
    md = (out / "quality.md").read_text()
    assert "**Best lever by " in md and "| 16 | Blender's own | 1 | 0.0000 |" in md
    assert [p["title"].split(" (")[0] for p in record["panels"]] == ["cycles5/studio 16 spp", "mitsuba3/cornell 16 spp"]


@pytest.mark.slow
def test_a_tiny_studys_scores_are_a_float64_computation_from_the_exrs(tiny_study):
    from prep import baselines

    cfg, record, full = tiny_study
    studio = next(r for r in record["frames"] if r["frame"] == "cycles5/studio 16 spp")
    ref = layouts.read(_studio(cfg, 256)).layers["default"]
    assert studio["raw"]["relmse"] == pytest.approx(_relmse64(layouts.read(_studio(cfg, 16)).layers["default"], ref),
                                                    rel=1e-9)
    assert studio["blender"]["relmse"] == 0.0
    assert studio["levers"]["cpu"]["set"] == "s"  # the render set its no-variance network trained on
    if baselines.oidn_available():
        frame = layouts.read(_studio(cfg, 16))
        # OIDN as Blender runs it: the Denoising Albedo and Normal the file holds, not the network's layers
        given = {**frame.layers, "albedo": frame.alternatives["albedo"], "normal": frame.alternatives["normal"]}
        for mode, key in baselines.OIDN_KEYS.items():
            assert studio[key]["relmse"] == pytest.approx(
                _relmse64(baselines.oidn_denoise(given, mode=mode), ref), rel=1e-9)
        # won only below the strongest anchor: here Blender's stand-in, the reference itself, wins every frame it has
        wins = sum(r["levers"]["cpu"]["relmse"] < min(r[k]["relmse"] for k in baselines.ANCHORS if k in r)
                   for r in record["frames"])
        md = (Path(cfg.out_dir) / "quality.md").read_text()
        row = next(line for line in md.splitlines() if line.startswith("| `cpu` |"))
        assert f"| {wins} of {len(record['frames'])} |" in row
    held = [r for r in record["frames"] if r["kind"] == "held-out"]
    assert [r["frame"] for r in held] == ["a-001 4 spp", "b-001 4 spp"]  # the tiny set's validation scenes
    assert all(set(r["levers"]) == set(cfg.levers) for r in held)
    for r in held:
        noisy = exr.read_aovs(Path(full.render_root) / "s" / f"{r['scene']}-00004spp.exr")["default"]
        reference = exr.read_aovs(Path(full.render_root) / "s" / f"{r['scene']}-00064spp.exr", variances=False)
        assert r["raw"]["relmse"] == pytest.approx(_relmse64(noisy, reference["default"]), rel=1e-9)


@pytest.mark.slow
def test_the_same_study_again_reuses_its_runs_and_its_report_is_written_again_from_the_record(tiny_study,
                                                                                               monkeypatch):
    cfg, record, _ = tiny_study
    monkeypatch.setattr(cmp, "probe_configuration", _fake_probe)
    again_cfg = dataclasses.replace(cfg, out_dir=str(Path(cfg.out_dir).parent / "again"))
    again = qs.quality(again_cfg, overrides=OVERRIDES, verbose=0, log=lambda *_: None)
    assert [r["levers"] for r in again["frames"]] == [r["levers"] for r in record["frames"]]
    rewritten = qr.rewrite_reports(again_cfg.out_dir)
    assert (Path(again_cfg.out_dir) / "quality.md").read_text() == qr.format_report(rewritten)


@pytest.mark.slow
def test_a_self_ensemble_of_2_is_served_by_the_same_runs_and_scores_that_ensembles_denoise(tiny_study, monkeypatch):
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings

    cfg, record, full = tiny_study
    monkeypatch.setattr(cmp, "probe_configuration", _fake_probe)
    ens_dir = Path(cfg.out_dir).parent / "ens"
    ens = qs.quality(dataclasses.replace(cfg, ensemble=2, out_dir=str(ens_dir)), overrides=OVERRIDES,
                     verbose=0, log=lambda *_: None)
    assert [ens["plans"][lv]["run"] for lv in cfg.levers] == [record["plans"][lv]["run"] for lv in cfg.levers]
    noisy = exr.read_aovs(Path(full.render_root) / "s" / "a-001-00004spp.exr")
    reference = exr.read_aovs(Path(full.render_root) / "s" / "a-001-00064spp.exr", variances=False)["default"]
    two = Denoiser.from_run(Run(record["plans"]["cpu"]["run"]), InferenceSettings(ensemble=2))(noisy)["default"]
    assert ens["frames"][0]["frame"] == "a-001 4 spp"
    assert ens["frames"][0]["levers"]["cpu"]["relmse"] == pytest.approx(_relmse64(two, reference), rel=1e-9)
    assert ens["frames"][0]["levers"]["cpu"]["relmse"] != record["frames"][0]["levers"]["cpu"]["relmse"]
    assert "a self-ensemble of 2 members" in (ens_dir / "quality.md").read_text()


@pytest.mark.slow
def test_the_shipped_model_is_measured_beside_the_levers_each_frame_served_by_its_network(tiny_study):
    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run

    cfg, record, _ = tiny_study
    shipped = record[qr.MODEL]
    assert Path(shipped["run"]).resolve() == MODELS_DIR / DEFAULT_MODEL and shipped["shipped"]
    frame = layouts.read(_studio(cfg, 16))
    denoised = Denoiser.from_run(Run(shipped["run"]).serving(frame.inputs))(frame.layers)["default"]
    studio = next(r for r in record["frames"] if r["frame"] == "cycles5/studio 16 spp")
    ref = layouts.read(_studio(cfg, 256)).layers["default"]
    assert studio[qr.MODEL]["relmse"] == pytest.approx(_relmse64(denoised, ref), rel=1e-9)
    assert "## The shipped model `default`" in (Path(cfg.out_dir) / "quality.md").read_text()


@pytest.mark.slow
def test_measure_model_puts_another_model_in_the_record_and_refuses_one_that_cannot_be_judged(tiny_study, tmp_path):
    study, record, _ = tiny_study
    out = tmp_path / "reports"  # a copy: the record the other tests read stays as the study wrote it
    shutil.copytree(study.out_dir, out)
    cfg, lines = dataclasses.replace(study, out_dir=str(out)), []
    # nothing trained: the cpu lever's run scores as the lever
    qs.add_model(dataclasses.replace(cfg, model=record["plans"]["cpu"]["run"]), log=lines.append)
    kept = out / "quality.json"
    measured = json.loads(kept.read_text())
    assert all(r[qr.MODEL] == r["levers"]["cpu"] for r in measured["frames"])
    assert measured["plans"] == record["plans"] and measured[qr.MODEL]["set"] == "s"
    # a model that trained on a scene the study holds out is refused before anything is measured
    seen = tmp_path / "seen"
    shutil.copytree(record["plans"]["cpu"]["run"], seen)
    data = json.loads((seen / "config.json").read_text())
    data["shards"]["split"]["train"].append("a-001")
    (seen / "config.json").write_text(json.dumps(data))
    res = run_main("quality", "--measure-model", "--model", seen, "--out", out, cwd=tmp_path)
    assert_one_line_error(res, f"--model {seen}", "a-001", "holds out")
    assert json.loads(kept.read_text()) == measured
    # frames that are no longer the record's: refused, naming the first that differs
    measured["frames"][0]["frame"] = "z-009 4 spp"
    kept.write_text(json.dumps(measured))
    with pytest.raises(KpcnError, match="found 'a-001 4 spp' where it has 'z-009 4 spp'"):
        qs.add_model(cfg, log=lines.append)


@pytest.mark.slow
def test_the_data_lever_renders_a_larger_set_sharing_the_renders_and_the_held_out_scenes(tmp_path, monkeypatch):
    from prep import shards
    from prep.render.renderset import RenderConfig, render_set

    base = RenderConfig(set_name="b", families=("cornell", "spheres"), per_family=2, width=24, height=24,
                        input_spp=(4,), reference_spp=8, out_root=str(tmp_path / "renders"))
    render_set(base, progress=False)
    shards.build_shards(shards.ShardConfig(set_name="b", render_root=base.out_root, out_root=str(tmp_path / "shards"),
                                           patch_size=16, patches_per_image=2, patches_per_shard=8, val_fraction=0.5),
                        progress=False)
    monkeypatch.setitem(QUALITY_LEVERS, "data", ("more scenes, a longer ladder", "cpu", {},
                                                 {"per_family": 3, "input_spp": (2, 4)}))
    monkeypatch.setattr(cmp, "probe_configuration", _fake_probe)
    cfg = QualityConfig(set_name="b", render_root=base.out_root, shards_root=str(tmp_path / "shards"),
                        runs_root=str(tmp_path / "runs"), out_dir=str(tmp_path / "reports"), budget=2.0,
                        levers=("cpu", "data"), frames=(str(RENDERERS / "cycles5"),))
    record = qs.quality(cfg, overrides=OVERRIDES, verbose=0, log=lambda *_: None)
    larger = qs.lever_set(cfg, "data")
    assert record["plans"]["data"]["set"] == larger != "b" and record["plans"]["cpu"]["set"] == "b"
    made = tmp_path / "renders" / larger
    names = sorted(p.name for p in made.glob("*.exr"))
    assert len(names) == 2 * 3 * 3  # two families, three scenes each, at 2 and 4 spp and the reference
    shared = sorted(p.name for p in (tmp_path / "renders" / "b").glob("*.exr"))
    assert set(shared) <= set(names)
    assert all((made / n).samefile(tmp_path / "renders" / "b" / n) for n in shared)  # linked, not rendered again
    for inputs in record["input_sets"]:
        sset = shards.ShardSet(shards.shard_set_dir(cfg.shards_root, larger, inputs))
        manifest = sset.complete_manifest()
        val = sorted({s["scene"] for s in manifest["sources"] if s["split"] == "val"})
        train = sorted({s["scene"] for s in manifest["sources"] if s["split"] == "train"})
        assert val == ["cornell-001", "spheres-001"] == qs.held_out_scenes(cfg)
        assert train == ["cornell-000", "cornell-002", "spheres-000", "spheres-002"]
    held = [r["frame"] for r in record["frames"] if r["kind"] == "held-out"]
    assert held == ["cornell-001 4 spp", "spheres-001 4 spp"]  # the study set's, for both levers


def _make_variable(name: str) -> str:
    text = (Path(__file__).parent.parent / "Makefile").read_text()
    return next(line.split("?=", 1)[1].strip() for line in text.splitlines()
                if line.startswith(f"{name} ") and "?=" in line)


def test_make_model_trains_on_the_data_levers_set_as_make_quality_names_and_renders_it():
    """The Makefile writes the data lever's set out for make model; this keeps it the study's."""
    options = QUALITY_LEVERS["data"][3]
    assert _make_variable("MODEL_SET") == "$(SET)" + qs.lever_set(QualityConfig(), "data")[len("default"):]
    assert _make_variable("MODEL_RENDER_ARGS") == (f"--per-family {options['per_family']} --input-spp "
                                                   f"{','.join(map(str, options['input_spp']))}")
