"""kpcn's quality modes in the reports: the Blender report's column set per mode (each mode's own networks, scored
as float64 numpy scores them), the keys a report of a balanced-only model always had, the timing probe of each mode
beside OIDN's qualities, and the plot of error against seconds, whose points are the two records' numbers."""

import json

import numpy as np
import pytest
import test_quality_modes
from test_blender_report import _expected, _folder, _rgb

import kpcn
from kpcn_keras.studies import blender_report as br
from kpcn_keras.studies import mode_costs, modes_plot
from prep import baselines, exr, layouts

# the keys of a report of models with the default mode alone, as the report wrote them before quality modes
RECORD_KEYS = {"date", "command", "started", "finished", "frames_given", "models", "note", "oidn_modes", "machine",
               "frames", "summary", "panels"}
AGAINST_KEYS = {"below_blender", "with_blender", "below_oidn", "with_oidn", "median_ratio_blender"}
# the tiny model with two modes (fast: a unet; balanced: the tiny kpcn run), as tests/test_quality_modes.py makes it
mode_runs, two_mode_model = test_quality_modes.mode_runs, test_quality_modes.two_mode_model


@pytest.mark.slow
def test_a_model_with_two_modes_has_a_column_set_per_mode_each_by_its_own_networks(two_mode_model, tmp_path):
    frames, out = _folder(tmp_path / "frames"), tmp_path / "reports"
    assert br.main([str(frames), "--model", f"two={two_mode_model}", "--out", str(out)]) == 0
    record = json.loads((out / "blender.json").read_text())
    assert record["quality_modes"] == {"two": ["fast", "balanced"]}
    oidn = baselines.oidn_available()
    assert record["oidn_modes"] == ([f"oidn_{m}{q}" for q in (" fast", " balanced", "") for m in baselines.OIDN_MODES]
                                    if oidn else [])
    for row in record["frames"]:
        noisy = frames / exr.render_filename(row["scene"], row["spp"])
        ref = _rgb(frames / exr.render_filename(row["scene"], 2048))
        frame = kpcn.read(noisy)
        assert "kpcn two" not in row["scores"]
        for mode in ("fast", "balanced"):
            want = _expected(kpcn.denoise(frame, run=two_mode_model, quality=mode), ref)
            for score, value in want.items():
                assert row["scores"][f"kpcn two {mode}"][score] == pytest.approx(value, rel=1e-6, abs=1e-12)
        if oidn:  # OIDN at the fast quality, as Blender runs it, beside kpcn's fast mode
            given = baselines.oidn_inputs(layouts.read(noisy))
            want = _expected(baselines.oidn_denoise(given, mode="prefiltered", quality="fast"), ref)
            assert row["scores"]["oidn_prefiltered fast"]["relmse"] == pytest.approx(want["relmse"], rel=1e-6)
    assert row["scores"]["kpcn two fast"]["relmse"] != row["scores"]["kpcn two balanced"]["relmse"]
    four = record["summary"]["by_spp"]["4"]["models"]
    assert set(four) == {"two fast", "two balanced"}
    rows4 = [r for r in record["frames"] if r["spp"] == 4]
    for mode in ("fast", "balanced"):
        ratios = [r["scores"][f"kpcn two {mode}"]["relmse"] / r["scores"]["blender"]["relmse"] for r in rows4]
        assert four[f"two {mode}"]["median_ratio_blender"] == pytest.approx(np.median(ratios), rel=1e-12)
    md = (out / "blender.md").read_text()
    assert "kpcn two fast relMSE" in md and "kpcn two balanced below Blender's" in md


@pytest.mark.slow
def test_a_model_with_only_the_balanced_mode_writes_the_keys_it_always_had(tiny_run_of_every_input_set, tmp_path):
    frames, out = _folder(tmp_path / "frames"), tmp_path / "reports"
    assert br.main([str(frames), "--model", f"one={tiny_run_of_every_input_set}", "--out", str(out)]) == 0
    record = json.loads((out / "blender.json").read_text())
    assert set(record) == RECORD_KEYS
    oidn = ["oidn_plain", "oidn_prefiltered"] if baselines.oidn_available() else []
    assert record["oidn_modes"] == oidn  # OIDN at its default quality alone, under the names it always had
    for row in record["frames"]:
        assert set(row["scores"]) - {"blender"} == {"raw", "kpcn one", *oidn}
    for block in record["summary"]["by_spp"].values():
        assert set(block["models"]) == {"one"} and set(block["models"]["one"]) == AGAINST_KEYS
    assert "kpcn one relMSE" in (out / "blender.md").read_text()


@pytest.mark.slow
def test_the_probe_times_each_mode_and_oidn_at_each_quality(two_mode_model, fixture_noisy, tmp_path, capsys):
    assert mode_costs.main(["--model", str(two_mode_model), "--frame", str(fixture_noisy), "--size", "40,32",
                            "--repeats", "2", "--out", str(tmp_path / "c.json")]) == 0
    found = json.loads(capsys.readouterr().out)
    assert found == json.loads((tmp_path / "c.json").read_text())
    oidn = [f"oidn_{m} {q}" for q in baselines.OIDN_QUALITIES for m in baselines.OIDN_MODES] \
        if baselines.oidn_available() else []
    assert list(found["best_s"]) == ["kpcn fast", "kpcn balanced", *oidn]
    for name, best in found["best_s"].items():
        assert 0 < best <= found["median_s"][name]
    assert found["size"] == [40, 32] and found["threads"] >= 1 and len(found["load_after"]) == 3
    if oidn:
        assert found["ratio_to_oidn_same_quality"]["fast"]["prefiltered"] == pytest.approx(
            found["best_s"]["kpcn fast"] / found["best_s"]["oidn_prefiltered fast"])


def _records(tmp_path, with_blender: bool):
    """A timing and a Blender report of a model with three modes, written by hand: random scores of two scenes at 4
    and 16 spp, Blender's frame (where ``with_blender``) on all but one frame; OIDN's plain mode at ``fast`` timed
    but not scored."""
    rng = np.random.default_rng(3)
    methods = ["kpcn m fast", "kpcn m balanced", "kpcn m high", "oidn_prefiltered fast", "oidn_prefiltered balanced",
               "oidn_prefiltered", "oidn_plain"] + (["blender"] if with_blender else [])
    rows = []
    for k, (scene, spp) in enumerate([("a", 4), ("b", 4), ("c", 4), ("a", 16), ("b", 16)]):
        scores = {m: {"relmse": float(rng.uniform(0.01, 0.2))} for m in methods}
        if k == 1:
            scores.pop("blender", None)
        rows.append({"scene": scene, "spp": spp, "scores": scores})
    errors = {"models": {"m": str(tmp_path / "m")}, "quality_modes": {"m": ["fast", "balanced", "high"]},
              "frames": rows}
    timed = ["kpcn fast", "kpcn balanced", "kpcn high"] + [f"oidn_{m} {q}" for q in ("fast", "balanced", "high")
                                                           for m in ("prefiltered", "plain")]
    costs = {"model": str(tmp_path / "m"), "size": [1920, 1080], "repeats": 3,
             "best_s": {m: float(rng.uniform(0.5, 3)) for m in timed}}
    (tmp_path / "costs.json").write_text(json.dumps(costs))
    (tmp_path / "blender.json").write_text(json.dumps(errors))
    return costs, errors


@pytest.mark.parametrize("with_blender", [True, False], ids=["ratio-to-blender", "mean-relmse"])
def test_the_plots_points_are_the_timing_and_the_reports_numbers(tmp_path, with_blender):
    costs, errors = _records(tmp_path, with_blender)
    assert modes_plot.main(["--costs", str(tmp_path / "costs.json"), "--errors", str(tmp_path / "blender.json"),
                            "--out", str(tmp_path / "out")]) == 0
    record = json.loads((tmp_path / "out" / "modes.json").read_text())
    assert (tmp_path / "out" / "modes.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert record["costs"] == str(tmp_path / "costs.json") and record["errors"] == str(tmp_path / "blender.json")
    column = {"kpcn fast": "kpcn m fast", "kpcn balanced": "kpcn m balanced", "kpcn high": "kpcn m high",
              "oidn_prefiltered fast": "oidn_prefiltered fast", "oidn_prefiltered balanced": "oidn_prefiltered "
              "balanced", "oidn_prefiltered high": "oidn_prefiltered", "oidn_plain high": "oidn_plain"}
    assert {p["method"]: p["column"] for p in record["points"]} == column  # no point for a method not scored

    def want(col, spp):
        rows = [r["scores"] for r in errors["frames"] if r["spp"] == spp]
        if with_blender:
            return np.median([s[col]["relmse"] / s["blender"]["relmse"] for s in rows if "blender" in s])
        return np.mean([s[col]["relmse"] for s in rows])

    assert record["y"] == ("median relMSE ratio to Blender's" if with_blender else "mean relMSE")
    for p in record["points"]:
        assert p["seconds"] == costs["best_s"][p["method"]]
        assert p["error"] == {str(spp): pytest.approx(want(p["column"], spp), rel=1e-12) for spp in (4, 16)}
    # the figure drawn from the record read back: each family's line holds its points, in quality order
    fig = modes_plot.figure(record)
    for ax, spp in zip(fig.axes, ("4", "16")):
        drawn = {line.get_label(): line.get_xydata().tolist() for line in ax.lines}
        for family in ("kpcn", "oidn_prefiltered", "oidn_plain"):
            mine = sorted((p for p in record["points"] if p["family"] == family),
                          key=lambda p: ("fast", "balanced", "high").index(p["quality"]))
            assert drawn[family] == [[p["seconds"], p["error"][spp]] for p in mine]


def test_the_plot_refuses_a_record_that_is_not_one_in_one_line(tmp_path, capsys):
    (tmp_path / "costs.json").write_text("{not json")
    assert modes_plot.main(["--costs", str(tmp_path / "costs.json"), "--errors", str(tmp_path / "b.json"),
                            "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("modes-plot: error: ") and "costs.json: not a readable" in err and err.count("\n") == 1


@pytest.mark.slow
def test_the_card_times_each_mode_beside_oidn_at_the_same_quality(two_mode_model, fixture_noisy, tmp_path):
    import shutil

    from kpcn_keras.card import SPEED, card_tables, retime, speed_lines
    from kpcn_keras.run import Run

    model = shutil.copytree(two_mode_model, tmp_path / "two")  # retime writes the card and speed.json again
    for found in (json.loads((model / SPEED).read_text()),  # as kpcn ship --mode timed it
                  retime(Run(model), fixture_noisy, "test", frame_size=(40, 32))):
        assert list(found["modes"]) == ["fast", "balanced"]
        assert found["modes"]["balanced"]["kpcn_s"] == found["kpcn_s"]  # the model itself, timed once
        assert found["modes"]["fast"]["kpcn_s"] > 0
        if baselines.oidn_available():
            assert all(t["oidn_s"] > 0 for t in found["modes"].values())
        else:
            assert all(t["oidn_s"] is None for t in found["modes"].values())
    card = (model / "CARD.md").read_text()
    assert "\n".join(speed_lines(found)) in card
    rows = {r[0]: r for r in card_tables(card)["Speed"]}
    assert rows["fast"][1] == f"{found['modes']['fast']['kpcn_s']:.2f}"
    assert rows["balanced"][1] == f"{found['kpcn_s']:.2f}"
