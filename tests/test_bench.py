"""``kpcn bench``: the equal-error spp of a known error law and of hand-made ladders, the schema of the
record, and the whole bench on a tiny rendered set, whose figures a float64 recomputation reproduces."""

import json
import math

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.tiny import TINY_MODEL, build_tiny_shards

from kpcn_keras.studies import bench, bench_stages
from kpcn_keras.studies.config import BenchConfig
from prep.errors import OptionError

LADDER = (2, 4, 8, 16, 32, 64, 128)


@pytest.mark.parametrize("n_star", [3.0, 5.5, 24.0, 100.0])
def test_equal_error_spp_inside_the_ladder_of_an_inverse_law_is_exact(n_star):
    # e = c / n is a straight line in log-log, so interpolation between neighbours is exact
    c = 0.37
    got = bench.equal_error_spp(LADDER, [c / n for n in LADDER], c / n_star)
    assert got["how"] == "interpolated"
    assert got["spp"] == pytest.approx(n_star, rel=1e-12)


@pytest.mark.parametrize("n_star", [1.0, 1000.0, 40000.0])
def test_equal_error_spp_outside_the_ladder_follows_the_fitted_law(n_star):
    c = 0.37
    got = bench.equal_error_spp(LADDER, [c / n for n in LADDER], c / n_star)
    assert got["how"] == "extrapolated"
    assert got["spp"] == pytest.approx(n_star, rel=1e-9)


def test_a_reference_noise_floor_is_fitted_and_errors_under_it_are_never_reached():
    a, b = 0.5, 0.002  # e(n) = a/n + b: b is what the reference's own noise adds to every error
    errors = [a / n + b for n in LADDER]
    assert bench.fit_inverse_law(LADDER, errors) == pytest.approx((a, b), rel=1e-9)
    assert bench.equal_error_spp(LADDER, errors, a / 1000 + b) == {"spp": pytest.approx(1000, rel=1e-9),
                                                                   "how": "extrapolated"}
    assert bench.equal_error_spp(LADDER, errors, 0.5 * b) == {"spp": math.inf, "how": "below the floor"}


def test_equal_error_spp_interpolates_in_log_log_between_the_bracketing_points():
    # halfway in log error between 4 and 16 spp is 8 spp, whatever the rest of the curve does
    got = bench.equal_error_spp((2, 4, 16, 64), (0.5, 0.1, 0.01, 0.008), math.sqrt(0.1 * 0.01))
    assert got == {"spp": pytest.approx(8.0, rel=1e-12), "how": "interpolated"}
    # a noisy ladder that rises again: the first bracketing pair (from the lowest spp) is taken
    got = bench.equal_error_spp((2, 4, 8), (0.2, 0.05, 0.1), 0.1)
    assert got["how"] == "interpolated" and 2 < got["spp"] < 4
    assert bench.equal_error_spp((2, 4, 8), (0.2, 0.1, 0.05), 0.01, extrapolate=False)["how"] == "beyond the ladder"
    with pytest.raises(ValueError, match="ascending"):
        bench.equal_error_spp((4, 2), (0.1, 0.2), 0.1)


def test_render_time_at_an_spp_is_the_line_through_the_ladder():
    spp = (2, 4, 8, 16)
    assert bench.render_seconds_at(spp, [0.1 + 0.02 * n for n in spp], 100) == pytest.approx(2.1)
    assert bench.render_seconds_at(spp, [1, 2, 3, 4], math.inf) == math.inf


def test_missing_figures_names_each_absent_path():
    assert set(bench.missing_figures({})) == set(bench.SCHEMA)
    record = {"methods": [{"name": "a", "kind": "raw", "points": [{"spp": 2}]}]}
    missing = bench.missing_figures(record)
    assert "methods.0.points.0.seconds" in missing and "methods.0.name" not in missing


def test_plain_json_keeps_the_report_readable_by_any_json_reader():
    value = {"a": [np.float32(1.5), math.inf, math.nan, -math.inf], "b": np.int64(3)}
    text = json.dumps(bench.plain_json(value), allow_nan=False)
    assert json.loads(text) == {"a": [1.5, "inf", None, "-inf"], "b": 3}


def test_bench_config_takes_its_ladder_and_names_a_bad_option():
    assert BenchConfig().raw_spp == (2, 4, 8, 16, 32, 64, 128)
    assert BenchConfig(full=True).budget > BenchConfig().budget
    cfg = BenchConfig(budget=90, budget_fractions=(1 / 3, 1.0))
    assert cfg.budgets() == (30.0, 90.0)
    for bad, option in (({"raw_spp": (2,)}, "raw_spp"), ({"input_spp": (1, 4)}, "input_spp"),
                        ({"configurations": ("cpu", "nope")}, "configurations"), ({"budget": 0}, "budget"),
                        ({"large_frame": (0, 10)}, "large_frame")):
        with pytest.raises(OptionError) as err:
            BenchConfig(**bad)
        assert err.value.option == option


@pytest.mark.slow
def test_bench_command_refuses_options_of_the_other_bench_and_a_set_without_a_render_record(tmp_path):
    res = run_main("bench", "render", "--budget", "3", cwd=tmp_path)
    assert_one_line_error(res, "--budget", "kpcn bench render")
    res = run_main("bench", "--spp", "3", cwd=tmp_path)
    assert_one_line_error(res, "--spp", "kpcn bench render")
    res = run_main("bench", "--large-frame", "3", cwd=tmp_path)
    assert_one_line_error(res, "--large-frame", "WIDTH,HEIGHT")
    shard_cfg = build_tiny_shards(tmp_path)  # random renders: no scene descriptions to render again
    res = run_main("bench", "--set", "s", "--shards", shard_cfg.out_root, "--out", "rep", cwd=tmp_path)
    assert_one_line_error(res, "config.json", "kpcn render")
    assert not (tmp_path / "rep").exists()


def _relmse64(x, r):
    x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
    return float(np.mean((x - r) ** 2 / (r * r + 1e-2)))


@pytest.mark.slow
def test_bench_on_a_tiny_rendered_set_writes_every_figure(tmp_path, monkeypatch):
    from kpcn_keras.cli import main
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from prep import exr
    from prep.render.frame import render
    from prep.render.scene import Scene

    monkeypatch.chdir(tmp_path)
    assert main(["-q", "render", "--set", "b", "--families", "cornell,spheres", "--per-family", "2", "--width", "24",
                 "--height", "20", "--input-spp", "4", "--reference-spp", "64"]) == 0
    assert main(["-q", "shards", "--set", "b", "--patch-size", "16", "--patches-per-image", "4",
                 "--val-fraction", "0.5"]) == 0
    cfg = BenchConfig(set_name="b", runs_root="runs/bench", out_dir="rep", raw_spp=(2, 4, 8), input_spp=(4,),
                      budget=2.0, budget_fractions=(0.5, 1.0), configurations=("cpu", "multiscale-alpha"),
                      presets=("cpu",), large_frame=(40, 30), repeats=1)
    record = bench.bench(cfg, overrides={"model": TINY_MODEL, "batch_size": 2, "val_batches": 1},
                         command="test", verbose=0, progress=False, log=lambda line: None)

    assert bench.missing_figures(record) == []
    text = (tmp_path / "rep/accuracy_time.json").read_text()
    on_disk = json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the JSON"))
    assert bench.missing_figures(on_disk) == []
    assert (tmp_path / "rep/accuracy_time.png").stat().st_size > 10_000
    md = (tmp_path / "rep/accuracy_time.md").read_text()
    names = [m["name"] for m in record["methods"]]
    assert names[0] == "raw Monte Carlo" and {"cpu", "multiscale-alpha", "multiscale-alpha (compositor off)",
                                              "NLM"} <= set(names)
    assert all(f"| {name} |" in md for name in names)
    assert [(r["preset"], r["budget"]) for r in record["training"]] == [("cpu", 1.0), ("cpu", 2.0)]
    from prep import baselines, metrics

    if baselines.oidn_available():  # both OIDN modes, each a curve of its own, scored on the same inputs
        modes = {m["name"]: m for m in record["methods"] if m["name"].startswith("OIDN")}
        assert set(modes) == {"OIDN", "OIDN prefiltered"}
        assert {r["method"] for r in record["equal_error"] if r["method"].startswith("OIDN")} == set(modes)
        first = modes["OIDN"]["points"][0]["frames"][0]["scene"]
        s = next(s for s in json.loads((tmp_path / "data/renders/b/config.json").read_text())["scenes"]
                 if s["name"] == first)
        noisy = render(Scene.from_dict(s["scene"]), 4, int(s["seeds"]["4"]), 24, 20)
        ref = exr.read_aovs(tmp_path / "data/renders/b" / s["files"][max(s["files"], key=int)], variances=False)
        for name, mode in (("OIDN", "plain"), ("OIDN prefiltered", "prefiltered")):
            frame = next(f for f in modes[name]["points"][0]["frames"] if f["scene"] == first)
            assert frame["relmse"] == pytest.approx(
                metrics.relmse(baselines.oidn_denoise(noisy, mode=mode), ref["default"]), rel=1e-5)

    # the cpu row's figures, recomputed in float64 from a fresh render and the run's own denoiser
    meta = json.loads((tmp_path / "data/renders/b/config.json").read_text())
    scenes = {s["name"]: s for s in meta["scenes"]}
    cpu = next(m for m in record["methods"] if m["name"] == "cpu")
    denoiser = Denoiser.from_run(Run(cpu["run"]))
    relmse = []
    for frame in cpu["points"][0]["frames"]:
        s = scenes[frame["scene"]]
        aovs = render(Scene.from_dict(s["scene"]), 4, int(s["seeds"]["4"]), 24, 20)
        ref_path = tmp_path / "data/renders/b" / s["files"][max(s["files"], key=int)]
        ref = exr.read_aovs(ref_path, variances=False)["default"]
        relmse.append(_relmse64(denoiser(aovs)["default"], ref))
        assert frame["relmse"] == pytest.approx(relmse[-1], rel=1e-5)
    assert cpu["points"][0]["relmse"] == pytest.approx(math.exp(np.mean(np.log(relmse))), rel=1e-5)
    assert cpu["points"][0]["mean_relmse"] == pytest.approx(np.mean(relmse), rel=1e-5)

    # the headline: each scene's equal-error spp from the raw ladder, the median over scenes
    raw = record["methods"][0]
    row = next(r for r in record["equal_error"] if r["method"] == "cpu")
    for i, scene in enumerate(row["scenes"]):
        ladder = [p["frames"][i]["relmse"] for p in raw["points"]]
        assert scene["equal_spp"] == bench.equal_error_spp(cfg.raw_spp, ladder,
                                                           cpu["points"][0]["frames"][i]["relmse"])["spp"]
    finite = [s["equal_spp"] for s in row["scenes"] if not math.isnan(s["equal_spp"])]
    assert row["median_equal_spp"] == pytest.approx(float(np.median(finite)))

    st = record["stages"]
    assert st["shard_read"]["ratio"] == pytest.approx(st["shard_read"]["batch_s"] / st["train_step"]["keras_s"])
    assert [k["k"] for k in st["kernel_application"]] == list(bench_stages.KERNEL_SIZES)
    assert st["inference"]["large"]["frame"] == [40, 30]
