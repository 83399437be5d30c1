"""Shipping a run as a model folder (``kpcn ship``, ``shipping.ship``, ``kpcn_keras/card.py``) and the default model
of ``kpcn denoise`` without ``--run``."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main

from prep.inputs import INPUT_SETS, InputSet


@pytest.fixture(scope="module")
def evaluated_run(tiny_run_of_every_input_set, tmp_path_factory):
    """A copy of the tiny run of every input set, evaluated on its held-out frames and, as validation frames,
    on a folder of renders without a split or variance layers (served by its no-split-no-variance variant)."""
    from kpcn_keras.evaluate import evaluate, held_out_pairs, pairs_for_inputs
    from kpcn_keras.run import Run
    from prep import exr

    tmp = tmp_path_factory.mktemp("ship")
    src = Path(tiny_run_of_every_input_set)
    # beside the original, so that its records' relative shard set paths hold
    run = Run(src.with_name("evaluated"))
    if not run.dir.exists():
        shutil.copytree(src, run.dir)
    evaluate(run, baseline=True)
    frames = tmp / "frames"
    frames.mkdir()
    for noisy, ref in held_out_pairs(run, run.record())[:1]:
        for path in (noisy, ref):
            aovs = exr.read_aovs(path, variances=False)
            exr.write_aovs(frames / Path(path).name, {"default": aovs["default"], "albedo": aovs["albedo"],
                                                     "normal": aovs["normal"], "depth": aovs["depth"]})
    evaluate(run, pairs_for_inputs([str(frames)]), out_dir=run.validation_dir)
    return run


@pytest.fixture(scope="module")
def shipped(evaluated_run, tmp_path_factory):
    dest = tmp_path_factory.mktemp("models") / "tiny"
    res = run_main("ship", "--run", evaluated_run.dir, "--out", dest, "--speed-frame", "96,80",
                   cwd=evaluated_run.dir.parent)
    assert res.returncode == 0, res.stderr
    return dest


def test_a_shipped_model_holds_what_serving_needs_and_no_checkpoints(evaluated_run, shipped):
    files = {str(p.relative_to(shipped)) for p in shipped.rglob("*") if p.is_file()}
    assert not [f for f in files if "checkpoints" in f or Path(f).name.startswith(".")]
    assert "CARD.md" in files and "config.json" in files and "loss.png" in files and "log.csv" in files
    assert "eval/metrics.json" in files and not [f for f in files if f.endswith(".png") and "eval" in f]
    for name in INPUT_SETS[1:]:
        assert f"inputs/{name}/config.json" in files
    record = json.loads((shipped / "config.json").read_text())
    for entry in record["components"].values():
        assert (shipped / entry["file"]).read_bytes() == (evaluated_run.dir / entry["file"]).read_bytes()
    # its shard set is found from its own folder
    assert (shipped / record["shards"]["set_dir"]).resolve() == \
        (evaluated_run.dir / evaluated_run.record().set_dir).resolve()


def test_denoise_and_evaluate_accept_a_shipped_model(shipped, evaluated_run, fixture_noisy, tmp_path):
    from kpcn_keras.evaluate import read_rows

    res = run_main("denoise", fixture_noisy, "--run", shipped, "-o", tmp_path / "out.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "out.exr").is_file()
    res = run_main("evaluate", "--run", shipped, "--out", tmp_path / "eval", "--no-baseline", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    ours, theirs = read_rows(tmp_path / "eval"), read_rows(evaluated_run.eval_dir)
    assert [r.denoised for r in ours] == [r.denoised for r in theirs]  # the same networks, the same bits
    # its own report folders hold what its card shows: another evaluation (an ensemble, say) goes elsewhere
    before = {p: p.read_bytes() for p in shipped.rglob("eval*/*")}
    for out in ((), ("--out", shipped / "eval-validation")):
        res = run_main("evaluate", "--run", shipped, "--ensemble", "2", "--no-baseline", *out, cwd=tmp_path)
        assert_one_line_error(res, str(shipped), "a shipped model", "--out DIR")
    assert {p: p.read_bytes() for p in shipped.rglob("eval*/*")} == before


def test_denoise_without_run_uses_the_default_model(shipped, fixture_noisy, tmp_path, monkeypatch):
    monkeypatch.setenv("KPCN_MODEL", str(shipped))
    res = run_main("denoise", fixture_noisy, "-o", tmp_path / "out.exr", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert f"model {shipped}" in res.stdout


def test_the_python_api_without_run_uses_the_default_model(shipped, fixture_noisy, monkeypatch):
    import kpcn
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run

    monkeypatch.setenv("KPCN_MODEL", str(shipped))
    frame = kpcn.read(fixture_noisy)
    ours = kpcn.denoise(frame)
    theirs = Denoiser.from_run(Run(shipped).serving(frame.inputs))(frame.layers)["default"]
    np.testing.assert_array_equal(ours, theirs)


def test_denoise_without_run_and_no_model_shipped_says_how_to_train_one(fixture_noisy, tmp_path, monkeypatch):
    from kpcn_keras import config

    monkeypatch.delenv("KPCN_MODEL", raising=False)
    monkeypatch.setattr(config, "MODELS_DIR", tmp_path / "models")
    res = run_main("denoise", fixture_noisy, cwd=tmp_path)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "no model is shipped" in lines[0] and "make model" in lines[0], res.stderr
    monkeypatch.setenv("KPCN_MODEL", str(tmp_path / "nowhere"))
    res = run_main("denoise", fixture_noisy, cwd=tmp_path)
    assert res.returncode == 2 and "KPCN_MODEL" in res.stderr


def test_the_default_model_is_found_beside_the_package():
    import kpcn_keras
    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR

    assert MODELS_DIR == Path(kpcn_keras.__file__).resolve().parent.parent / "models"
    assert DEFAULT_MODEL and "/" not in DEFAULT_MODEL


def test_make_model_ships_where_denoise_looks_and_evaluates_where_the_card_reads():
    import subprocess

    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR
    from kpcn_keras.run import Run

    plan = subprocess.run(["make", "-n", "--no-print-directory", "model"], cwd=MODELS_DIR.parent, text=True,
                          capture_output=True, check=True).stdout
    ship = next(line for line in plan.splitlines() if " ship " in line)
    assert ship.endswith(f"--out models/{DEFAULT_MODEL}")
    run = Run(ship.split("--run ")[1].split()[0])
    assert f"--out {run.validation_dir} " in plan
    assert f"evaluate --run {run.dir}\n" in plan



def test_make_model_tune_ships_make_models_networks_fine_tuned_from_their_own_with_the_no_split_ones_as_they_are():
    import subprocess

    from kpcn_keras.config import DEFAULT_MODEL, MODELS_DIR
    from prep.inputs import INPUT_SETS

    def plan(target):
        return subprocess.run(["make", "-n", "--no-print-directory", target], cwd=MODELS_DIR.parent, text=True,
                              capture_output=True, check=True).stdout.replace("\\\n\t", "")

    base = plan("model")
    model_run = next(line for line in base.splitlines() if " ship " in line).split("--run ")[1].split()[0]
    model_set = next(line for line in base.splitlines() if " train " in line).split("--set ")[1].split()[0]
    held_out = base.split("--val-scenes ")[1].split()[0]
    tune = plan("model-tune")
    lines = tune.splitlines()
    trains = [line for line in lines if " train " in line]
    full = next(line for line in trains if "--inputs full" in line)
    # make model trains without synthetic fireflies (its networks' identity); the tuning adds them (the default)
    assert all("--fireflies 0" in line for line in base.splitlines() if " train " in line)
    assert f"--set {model_set} " in full and f"--init {model_run} " in full and "--fireflies 0" not in full
    cycles = next(line for line in trains if "--inputs no-variance" in line)
    assert f"--init {model_run} " in cycles and "--fireflies 0" not in cycles
    tuned, cycles_run = (line.split("--run ")[1].split()[0] for line in (full, cycles))
    shards = next(line for line in lines if " shards " in line)
    assert f"--set {cycles.split('--set ')[1].split()[0]} --inputs no-variance" in shards
    assert shards.split("--val-scenes ")[1].split()[0].startswith(held_out + ",")  # make model's and Cycles' own
    ship = next(line for line in lines if " ship " in line)
    shipped = ship.split("--run ")[1].split()[0]
    assert ship.endswith(f"--out models/{DEFAULT_MODEL}") and shipped not in (model_run, tuned, cycles_run)
    assert f"cp -al {tuned} {shipped}" in tune
    # every input set but the two tuned ones is make model's own
    untouched = [s for s in INPUT_SETS if s not in ("full", "no-variance")]
    assert f"cp -al {' '.join(f'{model_run}/inputs/{s}' for s in untouched)} {shipped}/inputs/" in tune
    assert f"cp -al {cycles_run}/inputs/no-variance {shipped}/inputs/" in tune
    assert f"evaluate --run {shipped}\n" in tune and f"--out {shipped}/eval-validation " in tune


def _means(rows, spp, method, metric):
    """The float64 mean over the rows of ``spp``; None where a row lacks the method."""
    of = [r for r in rows if r.spp == spp]
    if any(getattr(r, method) is None for r in of):
        return None
    return float(np.mean(np.asarray([getattr(r, method)[metric] for r in of], dtype=np.float64)))


def test_the_cards_tables_are_the_runs_reports(evaluated_run, shipped):
    from kpcn_keras.card import HELD_OUT_COLUMNS, VALIDATION_COLUMNS, card_tables, with_anchors
    from kpcn_keras.evaluate import read_rows
    from prep import baselines

    tables = card_tables((shipped / "CARD.md").read_text())
    rows = read_rows(evaluated_run.eval_dir)
    held = tables["Held-out frames"]
    assert held[0][:2] == ["input spp", "frames"]
    assert [int(line[0]) for line in held[1:]] == sorted({r.spp for r in rows})
    for line in held[1:]:
        spp = int(line[0])
        assert int(line[1]) == sum(r.spp == spp for r in rows)
        for cell, (_, method, metric) in zip(line[2:], with_anchors(HELD_OUT_COLUMNS, rows), strict=False):
            mean = _means(rows, spp, method, metric)
            if mean is None or not np.isfinite(mean):
                assert cell == "–"
            else:
                assert float(cell) == pytest.approx(mean, abs=5e-5)
    validation = read_rows(evaluated_run.validation_dir)
    lines = tables["Validation frames"][1:]
    assert len(lines) == len(validation) + (len(validation) > 1)
    columns = with_anchors(VALIDATION_COLUMNS, validation)
    if baselines.oidn_available():  # prefiltered OIDN beside plain, and which frames are won against the better
        assert [h for h, _, _ in columns[-2:]] == ["OIDN prefiltered relMSE", "OIDN prefiltered DSSIM"]
        assert tables["Validation frames"][0][-1] == held[0][-1] == "won"
    for line, row in zip(lines, validation):
        assert line[:3] == [row.scene, str(row.spp), "no-split-no-variance"]
        for cell, (_, method, metric) in zip(line[3:], columns, strict=False):
            value = row.score(method, metric)
            assert cell == "–" if value is None else float(cell) == pytest.approx(value, abs=5e-5)
        if baselines.oidn_available():
            best = min(row.oidn["relmse"], row.oidn_prefiltered["relmse"])
            assert line[-1] == ("yes" if row.denoised["relmse"] < best else "no")
    curve = tables["Learning curve"]
    assert {line[0] for line in curve[1:]} == set(INPUT_SETS)


def test_a_network_fine_tuned_on_other_renders_shows_its_own_data_and_its_start_on_the_card(evaluated_run, tmp_path):
    from helpers.tiny import TINY_MODEL, make_renders

    from kpcn_keras.evaluate import evaluate
    from kpcn_keras.run import Run
    from kpcn_keras.train import TrainConfig, train
    from prep import shards
    from prep.files import sha256_file

    make_renders(tmp_path / "renders" / "t", scenes=("c-000", "c-001", "d-000", "d-001"))
    cut = shards.ShardConfig(set_name="t", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                             patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5, seed=3,
                             inputs="no-variance")
    shards.build_shards(cut, progress=False)
    run = Run(evaluated_run.dir.with_name(f"tuned-{tmp_path.name}"))  # beside it: its shard paths hold
    shutil.copytree(evaluated_run.dir, run.dir)
    shutil.rmtree(run.dir / "inputs" / "no-variance")
    shutil.rmtree(run.validation_dir)
    cfg = TrainConfig.from_preset("cpu", set_name="t", shards_root=cut.out_root, model=TINY_MODEL, steps=4,
                                  steps_per_epoch=4, batch_size=2, val_batches=1, inputs="no-variance",
                                  init=str(evaluated_run.dir), fireflies=0.5)
    train(cfg, run.dir, verbose=0)
    evaluate(run, baseline=False)
    res = run_main("ship", "--run", run.dir, "--out", tmp_path / "models" / "tuned", "--speed-frame", "64,48",
                   cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    card = (tmp_path / "models" / "tuned" / "CARD.md").read_text()
    tuned = card[card.index("### no-variance"):card.index("### no-split\n")]
    sha = {b: sha256_file(evaluated_run.dir / "inputs" / "no-variance" / f"{b}.keras")[:12]
           for b in ("diffuse", "specular")}
    assert (f"- fine-tuned: its branch phases started from the networks of `{evaluated_run.dir}` as they were then "
            f"(diffuse SHA-256 {sha['diffuse']}…, specular SHA-256 {sha['specular']}…)") in tuned
    assert "fine-tuned" not in card.replace(tuned, "")  # the others were not
    assert "augmentation on, synthetic fireflies 0.5 a patch, seed 0" in tuned
    others = card.replace(tuned, "")  # trained with the default, 1 a patch
    assert "synthetic fireflies 1 a patch" in others and "fireflies 0.5" not in others
    data = card[card.index("## Training data"):card.index("## Held-out frames")]
    assert "the same renders cut for each, `s.no-split`, `s.no-split-no-variance`" in data
    own = data[data.index("The no-variance network's:"):]
    assert "- shard set `t.no-variance` (input set no-variance), cut from the render set `t`" in own
    assert "2 training scenes, 2 held out (c-001, d-001)" in own


def test_an_unfinished_or_incomplete_run_is_refused_in_one_line(tiny_run, evaluated_run, tmp_path):
    from kpcn_keras.run import Run

    # no variant for the other input sets: the line names the first missing one and how to train it
    res = run_main("ship", "--run", tiny_run, "--out", tmp_path / "m", cwd=tmp_path)
    assert res.returncode == 2
    line, = res.stderr.strip().splitlines()
    assert f"no model for the {INPUT_SETS[1]} input set" in line and "kpcn train" in line and "--inputs" in line
    assert not (tmp_path / "m").exists() and not (Path(tiny_run) / "inputs").exists()
    # an unfinished phase of a variant
    run = Run(tmp_path / "copy")
    shutil.copytree(evaluated_run.dir, run.dir)
    variant = run.for_inputs(InputSet.named(INPUT_SETS[2]))
    data = json.loads(variant.record_path.read_text())
    next(iter(data["phases"].values()))["status"] = "pending"
    variant.record_path.write_text(json.dumps(data))
    res = run_main("ship", "--run", run.dir, "--out", tmp_path / "m", cwd=tmp_path)
    assert res.returncode == 2
    line, = res.stderr.strip().splitlines()
    assert "unfinished" in line and "kpcn train" in line
    assert not (tmp_path / "m").exists()


def test_a_run_not_evaluated_or_evaluated_before_more_training_is_refused(evaluated_run, tmp_path):
    import os

    run = tmp_path / "r"
    shutil.copytree(evaluated_run.dir, run, copy_function=shutil.copy2)
    later = os.stat(run / "eval" / "metrics.json").st_mtime + 10  # trained on after it was evaluated
    os.utime(run / "diffuse.keras", (later, later))
    res = run_main("ship", "--run", run, "--out", tmp_path / "m", cwd=tmp_path)
    assert res.returncode == 2 and "evaluate again" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    os.remove(run / "eval" / "metrics.json")
    res = run_main("ship", "--run", run, "--out", tmp_path / "m", cwd=tmp_path)
    assert res.returncode == 2 and "kpcn evaluate --run" in res.stderr
    assert not (tmp_path / "m").exists()


def test_a_shipped_model_ships_again_whatever_the_times_a_checkout_gave_its_files(evaluated_run, tmp_path):
    import os

    first = tmp_path / "m"
    res = run_main("ship", "--run", evaluated_run.dir, "--out", first, "--speed-frame", "48,40", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    later = os.stat(first / "eval" / "metrics.json").st_mtime + 10  # as git may write them, in any order
    os.utime(first / "diffuse.keras", (later, later))
    res = run_main("ship", "--run", first, "--out", tmp_path / "again", "--speed-frame", "48,40", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "again" / "diffuse.keras").read_bytes() == (first / "diffuse.keras").read_bytes()
    # its card's training data is the first card's (the shard sets need not be on the machine that ships it again)
    from kpcn_keras.card import card_section

    sections = [card_section((m / "CARD.md").read_text(), "Training data") for m in (first, tmp_path / "again")]
    assert sections[0] == sections[1] and any("shard set" in line for line in sections[0])


def test_a_model_over_the_size_limit_is_refused(evaluated_run, tmp_path):
    from kpcn_keras.run import Run
    from kpcn_keras.shipping import ship

    size = sum(f.stat().st_size for f in Run(evaluated_run.dir).dir.rglob("*.keras") if "checkpoints" not in f.parts)
    with pytest.raises(Exception, match="MiB a model kept in git may have"):
        ship(Run(evaluated_run.dir), tmp_path / "m", max_bytes=size // 2)
    assert not (tmp_path / "m").exists() and not list(tmp_path.glob(".m.tmp-*"))
    # within the limit it is written, and shipping again replaces it whole
    ship(Run(evaluated_run.dir), tmp_path / "m", {"CARD.md": "one"})
    ship(Run(evaluated_run.dir), tmp_path / "m", {"CARD.md": "two"})
    assert (tmp_path / "m" / "CARD.md").read_text() == "two" and not list(tmp_path.glob(".m.tmp-*"))


def test_shipping_never_replaces_the_run_or_a_folder_that_is_not_a_shipped_model(evaluated_run, tmp_path):
    for dest in (evaluated_run.dir, evaluated_run.dir / "inputs", evaluated_run.dir.parent):
        res = run_main("ship", "--run", evaluated_run.dir, "--out", dest, cwd=tmp_path)
        assert res.returncode == 2 and "cannot be the run" in res.stderr, res.stderr
    other = tmp_path / "other"
    (other / "checkpoints").mkdir(parents=True)
    (other / "mine.txt").write_text("kept")
    res = run_main("ship", "--run", evaluated_run.dir, "--out", other, cwd=tmp_path)
    assert res.returncode == 2 and "is not a shipped model" in res.stderr
    assert (other / "mine.txt").read_text() == "kept"
    assert evaluated_run.finished_record()


def test_the_speed_frame_wraps_a_render_around_to_the_size_asked():
    from kpcn_keras.card import frame_of_size

    rng = np.random.default_rng(0)
    layers = {"default": rng.random((5, 7, 3), dtype=np.float32), "depth": rng.random((5, 7), dtype=np.float32)}
    big = frame_of_size(layers, 17, 12)
    for name, a in layers.items():
        assert big[name].shape[:2] == (12, 17) and big[name].dtype == a.dtype
        ys, xs = np.meshgrid(np.arange(12) % 5, np.arange(17) % 7, indexing="ij")
        np.testing.assert_array_equal(big[name], a[ys, xs])
    small = frame_of_size(layers, 3, 2)
    np.testing.assert_array_equal(small["default"], layers["default"][:2, :3])


@pytest.mark.parametrize("plan, shown", [
    ({"epochs": 49, "steps": 2432}, "2432"),  # trained every step, no early stopping
    ({"epochs": 240, "steps": 12000, "epochs_trained": 118, "best_epoch": 97},
     "5900 of 12000, the weights of step 4900"),
    ({"epochs": 4, "steps": 200, "epochs_trained": 4, "best_epoch": 3}, "200"),  # patience never ran out
    ({"epochs": 4, "steps": 190, "epochs_trained": 4, "best_epoch": 1}, "190, the weights of step 100"),
])
def test_the_card_shows_the_steps_a_phase_trained_and_whose_weights_it_keeps(plan, shown):
    from kpcn_keras.card import trained_steps

    assert trained_steps(plan, steps_per_epoch=50) == shown


def test_the_card_times_the_frame_asked_and_names_oidn(shipped):
    from kpcn_keras.card import card_tables

    text = (shipped / "CARD.md").read_text()
    speed = card_tables(text)["Speed"]
    assert speed[0] == ["denoiser", "seconds a 96×80 frame"]
    assert speed[1][0] == "kpcn (this model)" and float(speed[1][1]) > 0
    assert speed[2][0] == "OIDN"


def test_the_card_s_speed_figures_are_those_of_the_speed_record_shipped_beside_it(shipped):
    from kpcn_keras.card import SPEED, card_tables, speed_lines

    found = json.loads((shipped / SPEED).read_text())
    assert found["width"] == 96 and found["height"] == 80 and found["kpcn_s"] > 0
    assert card_tables((shipped / "CARD.md").read_text())["Speed"][1][1] == f"{found['kpcn_s']:.2f}"
    assert "\n".join(speed_lines(found)) in (shipped / "CARD.md").read_text()


def test_a_shipped_model_timed_again_shows_the_new_record_and_keeps_the_rest_of_its_card(shipped, tmp_path):
    import shutil

    from kpcn_keras.card import SPEED, retime, speed_lines
    from kpcn_keras.run import Run

    model = tmp_path / "tiny"
    shutil.copytree(shipped, model)
    before = (model / "CARD.md").read_text()
    noisy = Path(__file__).parent / "fixtures" / "fixture-00008spp.exr"  # kpcn's own layout, as a held-out frame
    found = retime(Run(model), noisy, "python -m kpcn_keras.studies.card_speed --frame X", frame_size=(40, 24))
    assert json.loads((model / SPEED).read_text()) == found
    assert found["frame"] == noisy.name and not found["held_out"] and (found["width"], found["height"]) == (40, 24)
    after = (model / "CARD.md").read_text()
    assert "\n".join(speed_lines(found)) in after and "measured " in after
    head, tail = before.split("## Speed\n")[0], before[before.index("## Learning curve"):]
    assert after.startswith(head) and after.endswith(tail)


def test_the_committed_model_s_card_shows_its_speed_record():
    from kpcn_keras.card import SPEED, speed_lines

    model = Path(__file__).resolve().parent.parent / "models" / "default"
    found = json.loads((model / SPEED).read_text())
    card = (model / "CARD.md").read_text()
    assert "\n".join(speed_lines(found)) in card
    assert f"| kpcn (this model) | {found['kpcn_s']:.2f} |" in card and f"| OIDN | {found['oidn_s']:.2f} |" in card


def test_shipping_on_a_full_disk_ends_in_one_line_and_leaves_nothing(evaluated_run, small_disk, tmp_path):
    from kpcn_keras.run import Run

    dest = small_disk.path / "m"
    args = ("ship", "--run", evaluated_run.dir, "--out", dest, "--speed-frame", "32,32")
    assert_one_line_error(run_main(*args, cwd=tmp_path), "cannot write (No space left on device)")
    assert list(small_disk.path.iterdir()) == []
    small_disk.grow()
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert Run(dest).finished_record() and [p.name for p in small_disk.path.iterdir()] == ["m"]


# --- the model in the repository: what `kpcn denoise FILE` uses without --run ---

FIXTURES = Path(__file__).parent / "fixtures" / "renderers"


def test_the_shipped_model_is_small_carded_and_has_a_network_for_every_input_set():
    from kpcn_keras.config import SHIPPED_MAX_BYTES
    from kpcn_keras.run import default_model

    model = default_model()
    size = sum(f.stat().st_size for f in model.dir.rglob("*") if f.is_file())
    assert size < SHIPPED_MAX_BYTES
    assert (model.dir / "CARD.md").is_file() and not (model.dir / "checkpoints").exists()
    assert [model.for_inputs(InputSet.named(n)).has_record() for n in INPUT_SETS] == [True] * len(INPUT_SETS)


@pytest.mark.parametrize("fixture, served_by", [("cycles5/studio-00016spp.exr", "no-variance"),
                                                ("mitsuba3/cornell-00016spp.exr", "no-split"),
                                                ("pbrt4/cornell-00016spp.exr", "no-split")])
def test_the_shipped_model_denoises_each_renderers_frame_with_the_network_for_what_it_has(fixture, served_by):
    """Each frame comes out finite and closer to the renderer's own high-spp render than it went in."""
    import kpcn
    from kpcn_keras.run import default_model
    from prep import exr

    frame = kpcn.read(FIXTURES / fixture)
    assert default_model().serving(frame.inputs).record().inputs.name == served_by
    out = kpcn.denoise(frame)
    scene, _ = exr.parse_render_filename(FIXTURES / fixture)
    ref_path = max((FIXTURES / fixture).parent.glob(f"{scene}-*spp.exr"), key=lambda p: exr.parse_render_filename(p)[1])
    ref = kpcn.read(ref_path).layers["default"].astype(np.float64)
    noisy = frame.layers["default"].astype(np.float64)

    def relmse(x):  # a float64 reference of the metric, as docs/method.md defines it
        return float(np.mean((x - ref) ** 2 / (ref ** 2 + 0.01)))

    assert np.isfinite(out).all() and relmse(out) < relmse(noisy)


def test_a_write_that_fails_names_the_file_shipping_could_not_write(evaluated_run, tmp_path):
    """Every write of the process limited to 4 KiB (RLIMIT_FSIZE: ``write(2)`` itself fails with EFBIG, as on a
    full disk), so the first network file copied fails: the one line names that file in the model folder, not the
    run's file it read, and leaves nothing behind."""
    from helpers.commands import kpcn

    dest = tmp_path / "models" / "m"
    res = kpcn("ship", "--run", evaluated_run.dir, "--out", dest, "--speed-frame", "32,32", cwd=tmp_path,
               file_size_limit=4096)
    assert_one_line_error(res, f"{dest}{'/'}", ".keras: cannot write (File too large)")
    assert str(evaluated_run.dir) not in res.stderr
    assert not (tmp_path / "models").exists() or list((tmp_path / "models").iterdir()) == []
