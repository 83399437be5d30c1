"""`kpcn evaluate`'s table: every scene gets relMSE, relSE p99.9 and DSSIM of the raw input, the network and
NLM; the mean row averages the scenes' values."""

import json

import numpy as np
import pytest

from kpcn_keras.cli import main
from kpcn_keras.evaluate import COLUMNS, EvaluatedFrame, format_table, held_out_pairs, read_rows
from kpcn_keras.run import Run
from prep import exr, metrics

P999 = ("raw relSE p99.9", "denoised relSE p99.9", "NLM relSE p99.9")


def _parse(table: str) -> tuple[list[str], list[list[str]]]:
    lines = table.strip().splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    assert lines[1] == "|" + "---|" * len(header)
    rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines[2:]]
    assert all(len(r) == len(header) for r in rows)
    return header, rows


def _scores(relmse, relse_p999, dssim):
    return {"relmse": relmse, "relse_p999": relse_p999, "dssim": dssim}


def _row(scene, raw, den, nlm=None, seconds=0.5):
    return EvaluatedFrame(scene, 8, raw=_scores(*raw), denoised=_scores(*den), seconds=seconds,
                          nlm=None if nlm is None else _scores(*nlm), png=f"{scene}.png")


def test_table_shows_the_p999_columns_beside_relmse_and_their_mean():
    rows = [_row("a-003", (0.01, 2.5, 0.1), (0.002, 0.25, 0.01), (0.004, 1.5, 0.02), 0.9),
            _row("b-003", (0.03, 7.5, 0.2), (0.004, 0.75, 0.03), (0.006, 2.5, 0.04), 0.3)]
    header, cells = _parse(format_table(rows))
    assert header == [name for name, _, _ in COLUMNS]
    assert header[2:6] == ["raw relMSE", "denoised relMSE", "raw relSE p99.9", "denoised relSE p99.9"]
    assert header.index("NLM relSE p99.9") == header.index("NLM relMSE") + 1
    col = {name: header.index(name) for name in header}
    assert [c[0] for c in cells] == ["a-003", "b-003", "**mean**"]
    for row, line in zip(rows, cells):
        assert line[col["raw relSE p99.9"]] == f"{row.raw['relse_p999']:.4f}"
        assert line[col["denoised relSE p99.9"]] == f"{row.denoised['relse_p999']:.4f}"
        assert line[col["NLM relSE p99.9"]] == f"{row.nlm['relse_p999']:.4f}"
        assert line[col["denoised relMSE"]] == f"{row.denoised['relmse']:.4f}"
    mean = cells[-1]
    assert (mean[col["raw relSE p99.9"]], mean[col["denoised relSE p99.9"]], mean[col["NLM relSE p99.9"]]) \
        == ("5.0000", "0.5000", "2.0000")
    assert (mean[col["raw relMSE"]], mean[col["denoised DSSIM"]], mean[col["s/frame"]]) == ("0.0200", "0.0200", "0.60")


def test_table_without_the_baseline_leaves_the_nlm_columns_nan():
    rows = [_row("a-003", (0.01, 2.5, 0.1), (0.002, 0.25, 0.01)), _row("b-003", (0.03, 7.5, 0.2), (0.004, 0.75, 0.03))]
    header, cells = _parse(format_table(rows))
    for line in cells:
        assert line[header.index("NLM relMSE")] == line[header.index("NLM relSE p99.9")] == "nan"
    assert cells[-1][header.index("raw relSE p99.9")] == "5.0000"


def test_a_row_reads_back_as_it_was_written():
    row = _row("a-003", (0.01, 2.5, 0.1), (0.002, 0.25, 0.01), (0.004, 1.5, 0.02))
    assert EvaluatedFrame.from_json(row.to_json()) == row
    assert list(row.to_json()) == ["scene", "input spp", "raw", "denoised", "seconds", "nlm", "png"]
    full = EvaluatedFrame("b-000", 4, {"relmse": 1.0}, {"relmse": 0.5}, 0.25, layout="kpcn", inputs="full",
                          model="runs/m", precision="float32", ensemble=4, nlm={"relmse": 0.75}, nlm_seconds=0.5,
                          oidn={"relmse": 0.6}, oidn_seconds=0.125, png="b.png")
    assert EvaluatedFrame.from_json(json.loads(json.dumps(full.to_json()))) == full
    assert list(full.to_json()) == ["scene", "input spp", "layout", "inputs", "model", "precision", "ensemble",
                                    "raw", "denoised", "seconds", "nlm_seconds", "nlm", "oidn_seconds", "oidn", "png"]


@pytest.mark.parametrize("folder", ["eval", "eval-validation"])
def test_the_shipped_models_reports_read_and_write_back_to_the_same_bytes(folder):
    from helpers.paths import REPO

    path = REPO / "models" / "default" / folder / "metrics.json"
    rows = read_rows(path.parent)
    assert json.dumps([r.to_json() for r in rows], indent=2) == path.read_text()
    assert format_table(rows) in (path.parent / "report.md").read_text()  # the printed table, byte for byte


@pytest.mark.parametrize("text", ['{"scene": "a"}', '[{"scene": "a", "input spp": 4}]', '[[1, 2]]'])
def test_a_metrics_file_that_is_not_a_report_is_one_line_naming_it(tmp_path, text):
    from prep.errors import KpcnError

    (tmp_path / "metrics.json").write_text(text)
    with pytest.raises(KpcnError, match=f"^{tmp_path}/metrics.json: not an evaluation report of kpcn evaluate"):
        read_rows(tmp_path)


@pytest.mark.slow
def test_kpcn_evaluate_prints_the_p999_column_for_every_scene(tiny_run, tmp_path, capsys):
    out = tmp_path / "eval"
    assert main(["-q", "evaluate", "--run", str(tiny_run), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    table = "\n".join(line for line in printed.splitlines() if line.startswith("|"))
    assert table in (out / "report.md").read_text()
    header, cells = _parse(table)
    rows = read_rows(out)
    assert len(rows) == 2 and [c[0] for c in cells] == [r.scene for r in rows] + ["**mean**"]
    for (noisy, ref), row, line in zip(held_out_pairs(Run(tiny_run), Run(tiny_run).record()), rows, cells):
        raw = metrics.relse_p999(exr.read_aovs(noisy)["default"], exr.read_aovs(ref, variances=False)["default"])
        assert row.raw["relse_p999"] == raw
        assert set(row.raw) == set(row.denoised) == set(row.nlm) == set(metrics.METRICS)
        for name, key in zip(P999, ("raw", "denoised", "nlm")):
            value = row.score(key, "relse_p999")
            assert np.isfinite(value) and value >= 0
            assert line[header.index(name)] == f"{value:.4f}"
    for name, key in zip(P999, ("raw", "denoised", "nlm")):
        assert cells[-1][header.index(name)] == f"{np.mean([r.score(key, 'relse_p999') for r in rows]):.4f}"


def test_evaluate_checks_every_file_it_writes_against_every_file_it_reads(tiny_run, tmp_path, capsys):
    import os

    from helpers.files import checksums
    from helpers.tiny import random_aovs

    for folder in ("a", "b"):
        exr.write_aovs(tmp_path / folder / "x-00004spp.exr", random_aovs(16, 16))
        exr.write_aovs(tmp_path / folder / "x-00064spp.exr", random_aovs(16, 16, variances=False))
    (tmp_path / "linked").mkdir()
    os.link(tmp_path / "a" / "x-00064spp.exr", tmp_path / "linked" / "metrics.json")
    before = checksums(tmp_path)
    a, b = (str(tmp_path / f / "x-00004spp.exr") for f in ("a", "b"))
    # two renders of one name would write one PNG, the second over the first
    assert main(["-q", "evaluate", "--run", str(tiny_run), a, b, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and f"the PNG of {b} {tmp_path}/out/x-00004spp.png and the PNG of {a} " \
        f"{tmp_path}/out/x-00004spp.png are the same file" in err[0], err
    # a report file that is a hard link of the reference
    assert main(["-q", "evaluate", "--run", str(tiny_run), a, "--out", str(tmp_path / "linked")]) == 2
    assert f"metrics {tmp_path}/linked/metrics.json is the reference file {tmp_path}/a/x-00064spp.exr itself" \
        in capsys.readouterr().err
    assert checksums(tmp_path) == before


@pytest.mark.slow
def test_evaluate_and_figures_of_one_input_ignore_the_other_files_in_its_folder(tiny_run, tmp_path, capsys):
    import shutil

    from helpers.tiny import make_renders, random_aovs

    folder = make_renders(tmp_path / "renders", scenes=("a-000",), size=(24, 20))
    noisy, ref = folder / exr.render_filename("a-000", 4), folder / exr.render_filename("a-000", 64)
    exr.write_aovs(folder / exr.render_filename("lonely-000", 4), random_aovs(24, 20))  # a scene without a reference
    (folder / "notes.exr").write_bytes(b"not a render")  # not named <scene>-<spp>spp.exr
    (folder / exr.render_filename("a-000-x", 999)).write_bytes(b"torn")  # another scene, with more samples
    run = shutil.copytree(tiny_run, tmp_path / "run")  # figures are written into the run
    assert main(["-q", "evaluate", "--run", str(run), "--out", str(tmp_path / "eval"), "--no-baseline",
                 str(noisy)]) == 0
    [row] = read_rows(tmp_path / "eval")
    assert (row.scene, row.spp) == ("a-000", 4)
    want = metrics.relmse(exr.read_aovs(noisy)["default"], exr.read_aovs(ref, variances=False)["default"])
    assert row.raw["relmse"] == want
    assert main(["-q", "figures", "--run", str(run), str(noisy)]) == 0
    assert (run / "figures" / "kernels.png").is_file()
    capsys.readouterr()


@pytest.mark.slow
def test_a_slope_input_run_is_evaluated_at_the_slope_given_and_refused_without_one(tmp_path):
    from helpers.commands import assert_one_line_error, run_main
    from helpers.tiny import TINY_MODEL, build_tiny_shards

    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.train import TrainConfig, train

    shard_cfg = build_tiny_shards(tmp_path)
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=shard_cfg.out_root, model=TINY_MODEL, steps=2,
                                  steps_per_epoch=2, batch_size=2, val_batches=1, loss="asymmetric", slope_input=True)
    run = Run(train(cfg, tmp_path / "r", verbose=0))
    res = run_main("evaluate", "--run", run.dir, "--out", tmp_path / "none", "--no-baseline", cwd=tmp_path)
    assert_one_line_error(res, "--slope is needed", "trained with λ as an input, for λ in [1.0, 8.0]")
    assert not (tmp_path / "none").exists()
    res = run_main("evaluate", "--run", run.dir, "--out", tmp_path / "eval", "--no-baseline", "--slope", "3",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "at λ = 3 " in (tmp_path / "eval" / "report.md").read_text().splitlines()[0]
    rows = read_rows(tmp_path / "eval")
    denoiser = Denoiser.from_run(run)
    for (noisy, ref), row in zip(held_out_pairs(run, run.record()), rows, strict=True):
        want = denoiser(exr.read_aovs(noisy), slope=3.0)["default"]
        assert row.denoised == metrics.all_metrics(want, exr.read_aovs(ref, variances=False)["default"])


# --- a reference of another size: refused before any work, in one line naming both files ---


def _cut(src, dest, height, width):
    """The render ``src`` cut to its top-left ``height`` x ``width`` pixels, written to ``dest``."""
    layers = exr.read_aovs(src, variances=None)
    exr.write_aovs(dest, {name: image[:height, :width] for name, image in layers.items()})
    return dest


@pytest.mark.parametrize("size", [(32, 48), (1, 1)])
def test_evaluate_refuses_a_reference_of_another_size_before_any_work(fixture_noisy, fixture_reference, tmp_path,
                                                                      size):
    """A reference cut to another size beside the frame (a 1x1 test render of the scene too): the frame and the
    render it is scored against are named, with their sizes; no report folder is made."""
    import shutil

    from helpers.commands import assert_one_line_error, run_main

    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR

    frames = tmp_path / "frames"
    frames.mkdir()
    noisy = shutil.copy(fixture_noisy, frames / fixture_noisy.name)
    ref = _cut(fixture_reference, frames / fixture_reference.name, *size)
    out = tmp_path / "eval"
    for given in (noisy, frames):  # the frame, and the folder that holds it
        res = run_main("evaluate", "--run", MODELS_DIR / DEFAULT_MODEL, given, "--out", out, "--no-baseline",
                       cwd=tmp_path)
        assert_one_line_error(res, str(ref), str(noisy), f"{size[1]}x{size[0]}", "64x64")
        assert not out.exists()
    # kpcn denoise --reference refuses the same pair with the same line
    res = run_main("denoise", noisy, "--reference", ref, "--run", MODELS_DIR / DEFAULT_MODEL, "-o", out, cwd=tmp_path)
    assert_one_line_error(res, f"the reference {ref} is {size[1]}x{size[0]} but {noisy} is 64x64")
    assert not out.exists()


def test_a_frame_is_won_only_below_the_strongest_anchor_and_old_reports_print_as_before():
    def row(scene, den, oidn=None, pre=None, blender=None):
        def s(v):
            return None if v is None else _scores(v, 1.0, 0.1)

        return EvaluatedFrame(scene, 8, raw=_scores(0.5, 9.0, 0.3), denoised=_scores(den, 0.5, 0.02), seconds=0.5,
                              oidn=s(oidn), oidn_prefiltered=s(pre), blender=s(blender), png=f"{scene}.png")

    rows = [row("a-000", 0.010, oidn=0.020, pre=0.015),  # below both modes: won
            row("b-000", 0.010, oidn=0.020, pre=0.008),  # below plain, above prefiltered: lost
            row("c-000", 0.010, oidn=0.020, pre=0.015, blender=0.009),  # above Blender's own: lost
            row("d-000", 0.010, oidn=0.020, pre=0.015, blender=0.011)]  # below all three: won
    assert [r.won for r in rows] == ["yes", "no", "no", "yes"]
    header, cells = _parse(format_table(rows))
    assert header[header.index("OIDN relSE p99.9") + 1:] == ["OIDN prefiltered relMSE", "OIDN prefiltered relSE p99.9",
                                                             "Blender relMSE", "Blender relSE p99.9", "won", "s/frame"]
    assert [c[header.index("won")] for c in cells] == ["yes", "no", "no", "yes", "2 of 4"]
    assert [c[header.index("Blender relMSE")] for c in cells] == ["nan", "nan", "0.0090", "0.0110", "nan"]
    assert cells[-1][header.index("OIDN prefiltered relMSE")] == f"{np.mean([0.015, 0.008, 0.015, 0.015]):.4f}"
    for r in rows:
        assert EvaluatedFrame.from_json(json.loads(json.dumps(r.to_json()))) == r
    # a report with plain OIDN alone (every report before the prefiltered mode) has the columns it always had
    old = [row("a-000", 0.010, oidn=0.020), row("b-000", 0.030, oidn=0.020)]
    assert _parse(format_table(old))[0] == [name for name, _, _ in COLUMNS]
    assert [r.won for r in old] == ["yes", "no"]


def test_evaluate_scores_both_oidn_modes_and_blenders_own_frame_beside_the_render(tiny_run, tmp_path, capsys):
    from helpers.tiny import random_aovs

    from prep import baselines, layouts

    for scene, seed in (("x", 0), ("y", 1)):
        exr.write_aovs(tmp_path / f"{scene}-00004spp.exr", random_aovs(16, 16, seed=seed))
        exr.write_aovs(tmp_path / f"{scene}-00064spp.exr", random_aovs(16, 16, seed=seed + 10, variances=False))
    blender = random_aovs(16, 16, seed=7, variances=False)
    exr.write_aovs(tmp_path / "x-00004spp-blender-oidn.exr", blender)  # y has none: its Blender cell is NaN
    out = tmp_path / "out"
    assert main(["-q", "evaluate", "--run", str(tiny_run), str(tmp_path), "--out", str(out)]) == 0
    rows = {r.scene: r for r in read_rows(out)}
    assert set(rows) == {"x", "y"}
    ref = exr.read_aovs(tmp_path / "x-00064spp.exr", variances=False)["default"]
    assert rows["x"].blender == metrics.all_metrics(layouts.read(tmp_path / "x-00004spp-blender-oidn.exr")
                                                    .layers["default"], ref)
    assert rows["y"].blender is None
    if baselines.oidn_available():
        layers = layouts.read(tmp_path / "x-00004spp.exr").layers
        for mode, key in baselines.OIDN_KEYS.items():
            assert getattr(rows["x"], key) == metrics.all_metrics(baselines.oidn_denoise(layers, mode=mode), ref)
    strongest = min(v["relmse"] for v in (rows["x"].oidn, rows["x"].oidn_prefiltered, rows["x"].blender) if v)
    assert rows["x"].won == ("yes" if rows["x"].denoised["relmse"] < strongest else "no")
    header, cells = _parse("\n".join(ln for ln in (out / "report.md").read_text().splitlines() if ln.startswith("|")))
    assert cells[0][header.index("Blender relMSE")] == f"{rows['x'].blender['relmse']:.4f}"

    # Blender's frame of another size: one line naming it, before any work
    exr.write_aovs(tmp_path / "y-00004spp-blender-oidn.exr", random_aovs(8, 8, seed=3, variances=False))
    capsys.readouterr()
    assert main(["-q", "evaluate", "--run", str(tiny_run), str(tmp_path), "--out", str(tmp_path / "o2")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "y-00004spp-blender-oidn.exr is 8x8" in err[0] and "denoised frame of Blender" in err[0]
    assert not (tmp_path / "o2" / "metrics.json").exists()
