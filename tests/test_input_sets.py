"""A network per input set: the shard set cut for a set (``prep.inputs.restrict`` of the render and
its reference, ``ShardConfig.inputs``), the run trained on it (``<run>/inputs/<set>``, ``TrainConfig.inputs``),
the denoiser that restricts a frame to its run's set, and ``Run.serving``, which finds the run for a frame.

Each figure is checked against what the module docstring of ``prep.inputs`` says the set holds, computed here
(the total colour as the diffuse layer, float64 features of ``prep.features.reference_features``), or against
the full set's shards and renders as written."""

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.references import assert_read_features_close, reference_features, reference_log_colour
from helpers.tiny import TINY_MODEL, build_tiny_shards, random_aovs

from prep import colour, exr, metrics, shards
from prep.albedo import prefilter
from prep.errors import KpcnError, OptionError
from prep.exr import VARIANCE_LAYERS
from prep.features import BRANCHES
from prep.inputs import FULL, INPUT_SETS, InputSet, restrict

NO_SPLIT, NO_VARIANCE, NEITHER = (InputSet.named(n) for n in ("no-split", "no-variance", "no-split-no-variance"))
RELVAR = slice(23, 27)  # the relative-variance channels of prep/features.py's table


def total_colour_frame(aovs: dict) -> dict:
    """A frame as the docstring of prep.inputs says a no-split model reads it, written out here."""
    zeros3, zeros = np.zeros_like(aovs["default"]), np.zeros_like(aovs["depth"])
    return {**aovs, "diffuse": aovs["default"], "specular": zeros3, "diffuseVariance": aovs["colorVariance"],
            "specularVariance": zeros}


# ---------------------------------------------------------------- restrict


@pytest.mark.parametrize("name", INPUT_SETS)
def test_restrict_fills_each_missing_layer_as_the_table_of_the_module_says(name):
    inputs = InputSet.named(name)
    aovs = random_aovs(5, 7, seed=4)
    out = restrict(aovs, inputs)
    assert set(out) == set(aovs)
    for kept in ("default", "albedo", "normal", "depth"):
        assert out[kept] is aovs[kept]  # kept, not copied
    if inputs.split:
        assert out["diffuse"] is aovs["diffuse"] and out["specular"] is aovs["specular"]
    else:
        assert out["diffuse"] is aovs["default"]
        np.testing.assert_array_equal(out["specular"], np.zeros((5, 7, 3)))
    for layer in VARIANCE_LAYERS:
        assert out[layer].shape == (5, 7) and out[layer].dtype == np.float32, layer
        if not inputs.variance:
            assert not out[layer].any(), layer
        elif not inputs.split and layer == "diffuseVariance":
            assert out[layer] is aovs["colorVariance"]
        elif not inputs.split and layer == "specularVariance":
            assert not out[layer].any()
        else:
            assert out[layer] is aovs[layer], layer


# ---------------------------------------------------------------- shard sets


def test_a_full_shard_config_keeps_the_folder_and_the_hash_of_the_sets_cut_before_input_sets():
    cfg = shards.ShardConfig()
    assert cfg.set_dir == Path("shards/default") and cfg.input_set == FULL
    before = {k: v for k, v in dataclasses.asdict(cfg).items()  # inputs and auxiliaries: added since
              if k not in ("inputs", "auxiliaries", "command", "out_root", "render_root")}
    assert cfg.content_hash() == hashlib.sha256(json.dumps(before, sort_keys=True).encode()).hexdigest()[:16]
    assert "inputs" not in cfg.to_dict()
    other = shards.ShardConfig(inputs="no-split")
    assert other.set_dir == Path("shards/default.no-split") and other.render_dir == cfg.render_dir
    assert other.to_dict()["inputs"] == "no-split" and other.content_hash() != cfg.content_hash()
    with pytest.raises(OptionError, match="must be one of full, no-variance, no-split, no-split-no-variance"):
        shards.ShardConfig(inputs="rgb")


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    """The tiny renders cut for the full set, for no-split (in this process) and for no-variance (by
    ``kpcn shards --inputs``)."""
    tmp = tmp_path_factory.mktemp("inputs")
    full = build_tiny_shards(tmp)
    no_split = shards.ShardConfig(**{**full.to_dict(), "inputs": "no-split"})
    shards.build_shards(no_split, progress=False)
    res = run_main("shards", "--set", "s", "--renders", full.render_root, "--out", full.out_root, "--patch-size", 16,
                   "--patches-per-image", 7, "--patches-per-shard", 5, "--val-fraction", 0.5, "--seed", 3,
                   "--inputs", "no-variance", cwd=tmp)
    assert res.returncode == 0, res.stderr
    no_variance = shards.ShardConfig(**{**full.to_dict(), "inputs": "no-variance"})
    assert f"manifest: {no_variance.set_dir}/manifest.json" in res.stdout
    return tmp, {"full": full, "no-split": no_split, "no-variance": no_variance}


class Read:
    """An open shard's names (``prep.shards.VIEWS``, the features recomputed) and provenance, every patch."""

    def __init__(self, f):
        self.f = f

    def __getitem__(self, name):
        if name not in shards.VIEWS:
            return self.f[name]
        return shards.read_patches(self.f, [name], range(len(self.f["source"])))[name]


def shard_pairs(full, other):
    """(full set's shard, the other set's) of every round-0 shard, both splits, read as :class:`Read`."""
    for split in ("train", "val"):
        a, b = shards.shard_paths(full.set_dir, split), shards.shard_paths(other.set_dir, split)
        assert [p.name for p in a] == [p.name for p in b] and a
        for pa, pb in zip(a, b):
            with shards.open_shard(pa) as fa, shards.open_shard(pb) as fb:
                yield Read(fa), Read(fb)


def test_a_no_split_set_holds_the_features_of_the_total_colour_and_no_specular(sets):
    _, configs = sets
    cfg = configs["no-split"]
    assert cfg.set_dir.name == "s.no-split"
    sset = shards.ShardSet(cfg.set_dir)
    manifest = sset.complete_manifest()
    assert manifest["config"]["inputs"] == "no-split"
    sources = manifest["sources"]
    seen = 0
    for full, f in shard_pairs(configs["full"], cfg):
        # the same positions as the full set's: drawn from the render as it is
        np.testing.assert_array_equal(f["source"][:], full["source"][:])
        np.testing.assert_array_equal(f["position"][:], full["position"][:])
        for k in range(len(f["source"])):
            src = sources[int(f["source"][k])]
            noisy = exr.read_aovs(sset.resolve(src["path"]))
            ref_path = next(s["path"] for s in sources if s["scene"] == src["scene"] and s["role"] == "reference")
            ref = exr.read_aovs(sset.resolve(ref_path), variances=False)
            y, x = f["position"][k]
            win = np.s_[y:y + 16, x:x + 16]
            want = reference_features(total_colour_frame(noisy), "diffuse")[win]
            assert_read_features_close(f["diffuse/features"][k], want)
            np.testing.assert_allclose(f["diffuse/reference"][k],
                                       reference_log_colour(ref["default"], ref["albedo"])[win], rtol=1e-6, atol=1e-6)
            for name in ("specular/noisy", "specular/reference"):
                assert not f[name][k].any(), name
            assert not f["specular/features"][k][..., :3].any()
            np.testing.assert_array_equal(f["noisy"][k], noisy["default"][win])  # the total colour, as it is
            np.testing.assert_array_equal(f["reference"][k], ref["default"][win])
            seen += 1
    assert seen == 4 * 7


def test_a_no_variance_set_has_zero_relative_variances_and_the_full_sets_other_channels(sets):
    _, configs = sets
    seen = 0
    for full, f in shard_pairs(configs["full"], configs["no-variance"]):
        np.testing.assert_array_equal(f["position"][:], full["position"][:])
        for branch in BRANCHES:
            got, whole = f[f"{branch}/features"][:], full[f"{branch}/features"][:]
            assert not got[..., RELVAR].any() and whole[..., RELVAR].any(), branch
            np.testing.assert_array_equal(got[..., :RELVAR.start], whole[..., :RELVAR.start])
            for name in (f"{branch}/noisy", f"{branch}/reference"):
                np.testing.assert_array_equal(f[name][:], full[name][:])
        seen += len(f["source"])
    assert seen == 4 * 7


def test_an_error_round_of_a_no_split_set_is_cut_from_the_total_colour(sets):
    tmp, configs = sets
    copy = tmp / "shards" / "copy.no-split"  # beside the set: its sources' relative paths still resolve
    shutil.copytree(configs["no-split"].set_dir, copy)
    shards.build_error_round(copy, shards.ErrorRound(1, 3, 0.0, "smape", {}), None, progress=False)
    sset = shards.ShardSet(copy)
    sources = sset.complete_manifest()["sources"]
    paths = [p for p in shards.shard_paths(copy, "train") if p.parent.name == "round-001"]
    seen = 0
    for path in paths:
        with shards.open_shard(path) as opened:
            f = Read(opened)
            for k in range(len(f["source"])):
                noisy = exr.read_aovs(sset.resolve(sources[int(f["source"][k])]["path"]))
                y, x = f["position"][k]
                want = reference_features(total_colour_frame(noisy), "diffuse")[y:y + 16, x:x + 16]
                assert_read_features_close(f["diffuse/features"][k], want)
                assert not f["specular/noisy"][k].any() and not f["specular/reference"][k].any()
                seen += 1
    assert seen == 2 * 3  # two training inputs


def test_kpcn_shards_refuses_an_unknown_input_set_in_one_line(tmp_path):
    res = run_main("shards", "--set", "s", "--inputs", "rgb", cwd=tmp_path)
    assert_one_line_error(res, "--inputs must be one of full, no-variance, no-split, no-split-no-variance, got 'rgb'")


# ---------------------------------------------------------------- training


def test_a_no_split_configuration_trains_no_specular_or_joint_phase_and_refuses_two_branch_networks():
    from kpcn_keras.config import TrainConfig

    assert [p.name for p in TrainConfig(inputs="no-split", joint_steps=5).phases()] == ["diffuse"]
    assert [p.name for p in TrainConfig.from_preset("kpcn-paper", inputs="no-split").phases()] == ["diffuse"]
    assert [p.name for p in TrainConfig(inputs="no-variance", joint_steps=5).phases()] == ["diffuse", "specular",
                                                                                          "joint"]
    assert TrainConfig(inputs="no-split-no-variance").set_dir == Path("shards/default.no-split-no-variance")
    for given, option in (({"shared": True}, "shared"), ({"compositor": {"kind": "alpha"}}, "compositor"),
                          ({"branches": ("specular",)}, "branches")):
        with pytest.raises(OptionError, match="has the diffuse branch alone") as err:
            TrainConfig(inputs="no-split", **given)
        assert err.value.option == option
    full = TrainConfig()
    assert "inputs" not in full.to_dict() and "inputs" not in full.identity()  # runs trained before: the same runs
    assert TrainConfig(inputs="no-variance").identity()["inputs"] == "no-variance"


@pytest.fixture(scope="module")
def runs(sets):
    """A full run of the tiny set, and its no-split variant trained by ``kpcn train --inputs no-split``."""
    from kpcn_keras.config import TrainConfig
    from kpcn_keras.train import train

    tmp, configs = sets
    root = configs["full"].out_root
    cfg = TrainConfig.from_preset("cpu", set_name="s", shards_root=root, model=TINY_MODEL, steps=4,
                                  steps_per_epoch=4, batch_size=2, val_batches=1)
    base = train(cfg, tmp / "runs" / "r", verbose=0)
    res = run_main("train", "--set", "s", "--shards", root, "--run", base, "--inputs", "no-split", "--width", 6,
                   "--depth", 3, "--kernel-size", 5, "--steps", 4, "--batch-size", 2, cwd=tmp)
    assert res.returncode == 0, res.stderr[-3000:]
    variant = base / "inputs" / "no-split"
    assert f"run: {variant}" in res.stdout
    return tmp, base, variant


def test_a_no_split_run_trains_the_diffuse_phase_alone_into_the_runs_inputs_folder(runs, sets):
    from kpcn_keras.run import Run

    _, base, variant = runs
    record = Run(variant).finished_record()
    assert record.inputs == NO_SPLIT and record.branches == ("diffuse",)
    assert record.data["train"]["inputs"] == "no-split"
    assert list(record.phases) == ["diffuse"] and set(record.components) == {"diffuse"}
    assert sorted(p.name for p in variant.glob("*.keras")) == ["diffuse.keras"]
    assert Run(variant).shard_set(record).dir.resolve() == sets[1]["no-split"].set_dir.resolve()
    assert list(Run(base).record().phases) == ["diffuse", "specular"]  # the run itself is untouched


def test_a_no_split_denoiser_runs_the_diffuse_network_on_the_total_colour_and_gives_no_specular(runs):
    import keras

    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings

    _, _, variant = runs
    den = Denoiser.from_run(Run(variant), InferenceSettings(tile=4096))
    assert set(den.networks) == {"diffuse"} and set(den.models) == {"diffuse"}
    aovs = random_aovs(20, 24, seed=7)
    out = den(aovs)
    assert not out["specular"].any()
    np.testing.assert_array_equal(out["default"], out["diffuse"])
    # the network on float64 features of the total colour, recombined here with the prefiltered albedo
    feats = reference_features(total_colour_frame(aovs), "diffuse").astype(np.float32)
    log = keras.ops.convert_to_numpy(den.networks["diffuse"].predict_on_batch(feats[None]))[0]
    want = colour.diffuse_from_log(log, prefilter(aovs["albedo"], aovs["albedoVariance"]))
    np.testing.assert_allclose(out["diffuse"], want, rtol=1e-4, atol=1e-5)
    # what the frame holds beyond its total colour is never read: a frame without a split gives the same
    other = {**aovs, "diffuse": random_aovs(20, 24, seed=8)["diffuse"], "specularVariance": aovs["depth"]}
    for name, layer in den(other).items():
        np.testing.assert_array_equal(layer, out[name], err_msg=name)
    np.testing.assert_array_equal(den.run_branch("specular", aovs), np.zeros((20, 24, 3)))
    den.warm_up()


def test_serving_picks_the_first_finished_run_whose_input_set_serves_the_frame(runs):
    from kpcn_keras.run import Run

    tmp, base, variant = runs
    run = Run(base)
    assert run.serving(FULL).dir == base
    assert run.serving(NO_SPLIT).dir == variant
    root = Path(tmp / "shards")
    for frame, lacks, name in ((NEITHER, "a diffuse/specular split and variance layers", "no-split-no-variance"),
                               (NO_VARIANCE, "variance layers", "no-variance")):
        with pytest.raises(KpcnError) as err:
            run.serving(frame)
        message = str(err.value)
        assert message.startswith(f"{base}: no finished model for a frame without {lacks} (the run has: full, "
                                  "no-split)"), message
        assert (f"'kpcn shards --set s --out {root} --inputs {name}' then "
                f"'kpcn train --set s --shards {root} --run-dir {base} --inputs {name}'") in message, message
        assert "\n" not in message


def test_serving_passes_over_an_unfinished_variant(runs, tmp_path):
    from kpcn_keras.run import Run

    _, base, variant = runs
    other = Run(base).fork(tmp_path / "other").dir  # the full run, without its variants
    copy = other / "inputs" / "no-split"
    shutil.copytree(variant, copy)
    record = json.loads((copy / "config.json").read_text())
    record["phases"]["diffuse"]["status"] = "running"
    (copy / "config.json").write_text(json.dumps(record))
    with pytest.raises(KpcnError, match=r"\(the run has: full, no-split \(unfinished\)\); train it with "
                       r"'kpcn shards --set s .*--inputs no-split' then "):
        Run(other).serving(NO_SPLIT)


def test_a_folder_of_variants_alone_is_refused_naming_them_and_each_serves_as_a_run_of_its_own(runs, tmp_path):
    """What ``kpcn train --inputs no-split --run NEW`` makes (``NEW/inputs/no-split``, no record of its own) is not
    a model: which network serves would be a guess. The line names the variant, which serves when passed."""
    from kpcn_keras.run import Run

    _, _, variant = runs
    folder = tmp_path / "new"
    shutil.copytree(variant, folder / "inputs" / "no-split")
    with pytest.raises(KpcnError) as err:
        Run(folder).serving(NO_SPLIT)
    assert str(err.value) == (f"{folder}: not a run folder (no config.json); its inputs/ holds only the variants "
                              f"no-split, each a run folder of its own: pass one (e.g. {folder}/inputs/no-split) or "
                              "train the full model into this folder with 'kpcn train'")
    assert Run(folder / "inputs" / "no-split").serving(NO_SPLIT).dir == folder / "inputs" / "no-split"


def test_a_record_without_an_input_set_reads_as_full(runs):
    from kpcn_keras.run import Run, RunRecord

    _, base, variant = runs
    assert "inputs" not in json.loads(Run(base).record_path.read_text())["train"]  # a full record, as before
    assert Run(base).record().inputs == FULL and Run(base).record().branches == BRANCHES
    data = json.loads(Run(variant).record_path.read_text())
    del data["train"]["inputs"]
    old = RunRecord.from_json(Run(variant).record_path, data)
    assert old.inputs == FULL and old.branches == BRANCHES


def test_train_refuses_a_shard_set_cut_for_another_input_set(runs, tmp_path):
    from kpcn_keras.config import TrainConfig
    from kpcn_keras.train import train

    tmp, _, _ = runs
    shutil.copytree(tmp / "shards" / "s.no-split", tmp_path / "shards" / "s.no-variance")
    cfg = TrainConfig(set_name="s", shards_root=str(tmp_path / "shards"), model=TINY_MODEL, steps=1, batch_size=2,
                      inputs="no-variance")
    with pytest.raises(KpcnError, match="cut for the input set no-split, not no-variance"):
        train(cfg, tmp_path / "runs" / "r", verbose=0)
    assert not (tmp_path / "runs").exists()


def test_kpcn_evaluate_of_a_no_split_run_denoises_restricted_frames_against_the_full_input(runs):
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_pairs, read_rows
    from kpcn_keras.run import Run

    tmp, _, variant = runs
    res = run_main("evaluate", "--run", variant, "--no-baseline", cwd=tmp)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = read_rows(variant / "eval")
    run = Run(variant)
    pairs = held_out_pairs(run, run.record())
    assert len(rows) == len(pairs) == 2
    den = Denoiser.from_run(run)
    for row, (noisy_path, ref_path) in zip(rows, pairs):
        noisy, ref = exr.read_aovs(noisy_path), exr.read_aovs(ref_path, variances=False)["default"]
        assert row.raw == metrics.all_metrics(noisy["default"], ref)
        assert row.denoised == metrics.all_metrics(den(total_colour_frame(noisy))["default"], ref)


def test_kpcn_figures_of_a_no_split_run_draws_the_diffuse_kernels(runs):
    tmp, _, variant = runs
    res = run_main("figures", "--run", variant, cwd=tmp)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (variant / "figures" / "kernels.png").is_file()
