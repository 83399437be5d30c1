"""``python -m kpcn_keras.studies.adapt_report``: the adaptation report on a tiny validation folder written here; its
figures against float64 numpy of the metric definitions on the files themselves and on the model's own output."""

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers.exr_layouts import cycles_channels, parts_of, write_channels
from skimage.metrics import structural_similarity

import kpcn
from kpcn_keras.studies import adapt_report as ar
from prep import baselines
from prep.colour import tonemap

H, W = 40, 48
SCENES = (("val-studio-000", ["fog"], ["media"]), ("val-room-001", ["fine_tiles"], ["texture"]))


def _combined(channels) -> np.ndarray:
    return np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1).astype(np.float64)


def _write_rgb(path: Path, rgb: np.ndarray) -> Path:
    return write_channels(path, {f"ViewLayer.Combined.{c}": rgb[..., i].astype(np.float32)
                                 for i, c in enumerate("RGB")})


def _folder(root: Path) -> Path:
    """Two validation scenes at 16 spp as ``kpcn cycles-validation`` lays them out: the frame, Blender's frame (a
    stand-in: the reference mixed with the noisy frame), the two halves of 8 spp (two other noise seeds), the
    2048-spp reference and the recipe; a third scene without its halves (still rendering: left out)."""
    root.mkdir()
    for k, (scene, effects, groups) in enumerate((*SCENES, ("val-hall-002", ["hair"], ["hair"]))):
        recipe = {"split": "validation", "seed": 0, "index": k, "name": scene, "effects": effects, "groups": groups,
                  "frames": [16, 2048]}
        (root / f"{scene}.json").write_text(json.dumps(recipe))
        ref = cycles_channels(H, W, seed=k)
        write_channels(root / f"{scene}-02048spp.exr", ref, parts_of(ref))
        noisy = cycles_channels(H, W, seed=k, noise_seed=10 * k)
        write_channels(root / f"{scene}-00016spp.exr", noisy, parts_of(noisy))
        _write_rgb(root / f"{scene}-00016spp-blender-oidn.exr", 0.7 * _combined(ref) + 0.3 * _combined(noisy))
        if scene != "val-hall-002":
            for j, half in enumerate("ab"):
                ch = cycles_channels(H, W, seed=k, noise_seed=10 * k + 1 + j)
                write_channels(root / f"{scene}-00008spp-pair-{half}.exr", ch, parts_of(ch))
    return root


def _project_folder(root: Path) -> Path:
    """One scene of kpcn's own renders as ``kpcn render --pair`` lays them out: no recipe, no Blender frame; the
    frame of 16 spp, its two halves and the 512-spp reference (in the Cycles layout here: what is read is the same)."""
    root.mkdir()
    ref = cycles_channels(H, W, seed=7)
    write_channels(root / "cornell-000-00512spp.exr", ref, parts_of(ref))
    for name, noise in (("cornell-000-00016spp.exr", 70), ("cornell-000-00008spp-pair-a.exr", 71),
                        ("cornell-000-00008spp-pair-b.exr", 72)):
        ch = cycles_channels(H, W, seed=7, noise_seed=noise)
        write_channels(root / name, ch, parts_of(ch))
    return root


def _relmse(x, r) -> float:
    x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
    return float(np.mean((x - r) ** 2 / (r * r + 0.01)))


def _dssim(x, r) -> float:
    x, r = np.asarray(x, np.float64), np.asarray(r, np.float64)
    return (1 - structural_similarity(tonemap(x), tonemap(r), channel_axis=-1, data_range=1.0, win_size=7)) / 2


def _mean_frame(a_path: Path, b_path: Path):
    """The two halves as one frame: every layer their float64 mean (the Cycles layout has no variance layers)."""
    a, b = kpcn.read(a_path), kpcn.read(b_path)
    layers = {k: ((np.asarray(a.layers[k], np.float64) + b.layers[k]) / 2).astype(np.float32) for k in a.layers}
    return dataclasses.replace(a, layers=layers)


@pytest.mark.slow
def test_the_report_scores_each_frame_and_states_the_targets_as_numpy_does(tiny_run_of_every_input_set, tmp_path):
    run, frames = tiny_run_of_every_input_set, _folder(tmp_path / "frames")
    project = _project_folder(tmp_path / "project")
    out, cache = tmp_path / "reports", tmp_path / "cache"
    args = [str(frames), "--model", str(run), "--spp", "16", "--marks", "0.001,0.002", "--steps", "3", "--out",
            str(out), "--cache", str(cache), "--costs-size", "64,48", "--costs-steps", "12", "--more", str(project)]
    assert ar.main(args) == 0
    record = json.loads((out / "adapt.json").read_text())
    assert (out / "adapt.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    _check_project_row(record, project)
    rows = {r["scene"]: r for r in record["frames"] if r["set"] == "frames"}
    assert sorted(rows) == sorted(s for s, _, _ in SCENES)  # the scene without its halves is left out
    assert record["panels"] == ["val-studio-000", "val-room-001"]  # participating media first
    for scene, row in rows.items():
        f = {k: Path(v) for k, v in row["files"].items()}
        ref = np.asarray(kpcn.read(f["reference"]).layers["default"], np.float64)
        mean = _mean_frame(f["a"], f["b"])
        unadapted = kpcn.denoise(mean, run=run)
        expected = {"input": mean.layers["default"], "kpcn pair": unadapted,
                    "blender": kpcn.read(f["blender"]).layers["default"],
                    "kpcn single": kpcn.denoise(kpcn.read(f["single"]), run=run),
                    "input single": kpcn.read(f["single"]).layers["default"]}
        for method, image in expected.items():
            assert row["scores"][method]["relmse"] == pytest.approx(_relmse(image, ref), rel=1e-4, abs=1e-7), method
            assert row["scores"][method]["dssim"] == pytest.approx(_dssim(image, ref), rel=1e-3, abs=1e-6), method
        with np.load(cache / f"{scene}-00016spp.npz") as images:  # what the panels show, scored again
            for name, method in (("input", "input"), ("kpcn pair", "kpcn pair"), ("adapted", "kpcn adapted 0.002 s"),
                                 ("blender", "blender")):
                assert row["scores"][method]["relmse"] == pytest.approx(_relmse(images[name], ref), rel=1e-6)
            np.testing.assert_allclose(images["kpcn pair"], unadapted, atol=1e-4)
        for mark in ("0.001", "0.002"):  # 3 steps: no held-out check yet, so the guard keeps the model's output
            assert row["guard"][mark]["kept"] is False and row["guard"][mark]["steps"] == 3
            assert row["scores"][f"kpcn adapted {mark} s"] == row["scores"]["kpcn pair"]
        assert row["scores"]["kpcn unguarded"] == row["scores"]["kpcn pair"]  # no checkpoint yet: nothing forgone
    _check_summary(record, list(rows.values()))
    md = (out / "adapt.md").read_text()
    assert "Below Blender's own denoiser at equal samples (relMSE) on at least half the validation frames" in md
    assert "at least 25% lower than the unadapted pair's" in md and "No frame more than 2% worse" in md
    assert "## `project`: medians per spp (not in the targets)" in md
    t = record["targets"]
    for key in ("below_blender", "median_ratio", "worst_change"):
        assert t[key]["holds"] in (True, False)
    assert f"All three hold: **{'yes' if t['held'] else 'no'}**" in md
    import hashlib

    from kpcn_keras import adapt

    assert record["code"]["adapt_py_sha256"] == hashlib.sha256(Path(adapt.__file__).read_bytes()).hexdigest()
    costs = record["costs"]
    assert costs["64x48"]["size"] == [64, 48] and costs["validation"]["size"] == [W, H]
    for size in ("64x48", "validation"):  # 12 steps: one held-out check, after the 10th
        assert costs[size]["step_s"] > 0 and costs[size]["check_s"] is not None and costs[size]["prepare_s"] > 0
        assert costs[size]["seconds_per_step"] >= costs[size]["step_s"] * 0.5
    assert costs["64x48"]["crops"] == 2 and costs["validation"]["crops"] == 2  # one crop of 128 a side per half
    # run again with the same settings: every frame is kept, none computed again
    assert ar.main(args) == 0
    again = json.loads((out / "adapt.json").read_text())
    assert again["resumed"] == 3 and again["frames"] == record["frames"] and again["costs"] == costs
    (out / "adapt.md").unlink()
    assert ar.main(["--report-only", "--out", str(out), "--cache", str(cache)]) == 0  # the md again, from the json
    assert f"All three hold: **{'yes' if t['held'] else 'no'}**" in (out / "adapt.md").read_text()
    rewritten = json.loads((out / "adapt.json").read_text())
    assert rewritten["frames"] == record["frames"] and rewritten["targets"] == record["targets"]
    assert rewritten["command"] == again["command"] and rewritten["started"] == again["started"]  # its run's own


def _check_project_row(record: dict, project: Path) -> None:
    """A folder without Blender's frames: its row judged against the better OIDN mode on the one render, by relMSE
    against its reference; its own summary, out of the targets."""
    (row,) = [r for r in record["frames"] if r["set"] == "project"]
    assert row["scene"] == "cornell-000" and row["groups"] == ["cornell"]
    single, ref = kpcn.read(project / "cornell-000-00016spp.exr"), kpcn.read(project / "cornell-000-00512spp.exr")
    ref = np.asarray(ref.layers["default"], np.float64)
    modes = {f"oidn_{m}": _relmse(baselines.oidn_denoise(single.layers, mode=m), ref) for m in baselines.OIDN_MODES}
    assert row["anchor"] == min(modes, key=modes.get)
    assert row["scores"]["blender"]["relmse"] == pytest.approx(min(modes.values()), rel=1e-4)
    assert record["more_summary"]["project"]["16"]["frames"] == 1
    assert record["targets"]["frames"] == 2 and "cornell-000" not in record["panels"]


def _check_summary(record: dict, rows: list[dict]) -> None:
    """The medians, the ratios to Blender's, the counts and the targets, from the rows in float64 numpy."""
    block = record["summary"]["16"]
    assert block["frames"] == len(rows)
    for method, s in block["methods"].items():
        rel = np.array([r["scores"][method]["relmse"] for r in rows])
        blender = np.array([r["scores"]["blender"]["relmse"] for r in rows])
        assert s["median_relmse"] == pytest.approx(np.median(rel))
        assert s["median_ratio_blender"] == pytest.approx(np.median(rel / blender))
        assert s["below_blender"] == int(np.sum(rel < blender))
    for mark in ("0.001", "0.002"):
        chosen = [step for r in rows for step in r["guard"][mark]["best_steps"]]
        assert block["median_chosen_step"][mark] == np.median(chosen)
    target, last = f"{record['target_mark']:g}", "0.002"
    same = sum(r["guard"][last]["best_steps"] == r["guard"][target]["best_steps"] for r in rows)
    assert block["same_choice_at_last_mark"] == same
    t = record["targets"]
    adapted = np.array([r["scores"]["kpcn adapted 0.002 s"]["relmse"] for r in rows])
    plain = np.array([r["scores"]["kpcn pair"]["relmse"] for r in rows])
    blender = np.array([r["scores"]["blender"]["relmse"] for r in rows])
    assert t["mark"] == 0.002 and t["below_blender"]["frames"] == int(np.sum(adapted < blender))
    assert t["below_blender"]["holds"] == (np.sum(adapted < blender) >= np.ceil(len(rows) / 2))
    assert t["median_ratio"]["holds"] == (np.median(adapted / blender) <= 0.75 * np.median(plain / blender))
    assert t["worst_change"]["holds"] == (np.max(adapted / plain - 1) <= 0.02)
    # the most a guard could give: per frame the better of the unadapted output and the correction
    unguarded = np.array([r["scores"]["kpcn unguarded"]["relmse"] for r in rows])
    best = np.minimum(plain, unguarded)
    assert t["any_guard"]["below_blender"] == int(np.sum(best < blender))
    assert t["any_guard"]["median_ratio"] == pytest.approx(np.median(best / blender))
    assert t["any_guard"]["gain"] == pytest.approx(1 - np.median(best / blender) / np.median(plain / blender))


def test_a_folder_without_a_complete_frame_is_one_line_and_status_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    assert ar.main([str(tmp_path / "empty"), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no complete frame at 16, 4, 64 spp" in err[0]


def test_report_only_without_a_record_is_one_line_and_status_2(tmp_path, capsys):
    assert ar.main(["--report-only", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "adapt.json: no adaptation report to write again" in err[0]
