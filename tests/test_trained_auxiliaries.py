"""A network trained on prefiltered auxiliaries (``kpcn shards --auxiliaries``, ``kpcn train --auxiliaries``) is
served them so: the shards hold ``prep.auxiliary``'s layers, the run's record says which, the denoiser gives its
networks the same layers, tiled as untiled, and a model whose prefilter cannot run here is refused in one line.
The core path runs with ``nlm`` (no optional package); the ``oidn`` cases skip without ``pyoidn``."""

import json
import shutil
import sys

import keras
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, kpcn, run_main
from helpers.references import assert_read_features_close
from helpers.tiny import build_tiny_shards, make_renders, random_aovs, tiny_train_config

from kpcn_keras.denoise import Denoiser
from kpcn_keras.evaluate import evaluate
from kpcn_keras.models import network_input
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import train
from prep import auxiliary, baselines, colour, exr, features, metrics, shards
from prep.albedo import prefilter

needs_oidn = pytest.mark.skipif(not baselines.oidn_available(), reason="pyoidn is not installed")
# a raw set's content hash as the code before the option computed it (the tiny set of build_tiny_shards)
RAW_CONTENT_HASH = "4d2cc4322cdf56a5"


@pytest.fixture(scope="module")
def nlm_set(tmp_path_factory):
    """A tiny render set cut raw and with ``nlm``-prefiltered auxiliaries, side by side; (raw, nlm) configs."""
    tmp = tmp_path_factory.mktemp("aux")
    raw = build_tiny_shards(tmp)
    nlm = shards.ShardConfig(**{**raw.to_dict(), "auxiliaries": "nlm"})
    shards.build_shards(nlm, progress=False)
    return raw, nlm


@pytest.fixture(scope="module")
def nlm_run(nlm_set, tmp_path_factory):
    """A tiny run trained on the nlm set."""
    return train(tiny_train_config(nlm_set[1], auxiliaries="nlm"), tmp_path_factory.mktemp("runs") / "nlm",
                 verbose=0)


def _check_patches_hold(cfg, method):
    """Every patch of ``cfg``'s set holds the features of ``prep.auxiliary.network_layers`` of its whole input
    (float16 rounding); returns how many differ from the raw input's features (the prefilter is seen)."""
    sset = shards.ShardSet(cfg.set_dir)
    manifest = json.loads(sset.manifest_path.read_text())
    changed = seen = 0
    given_of = {}  # each input's layers, prefiltered once
    for split in ("train", "val"):
        for path in shards.shard_paths(cfg.set_dir, split):
            with shards.open_shard(path) as f:
                for k in range(len(f["source"])):
                    src = manifest["sources"][int(f["source"][k])]
                    noisy = exr.read_aovs(sset.resolve(src["path"]))
                    if src["path"] not in given_of:  # the frame whole, then cut
                        given_of[src["path"]] = auxiliary.auxiliaries(noisy, method)
                    given = given_of[src["path"]]
                    y, x = f["position"][k]
                    win = np.s_[y:y + cfg.patch_size, x:x + cfg.patch_size]
                    got = shards.read_patch(f, list(shards.VIEWS), k)
                    for branch in features.BRANCHES:
                        assert_read_features_close(got[f"{branch}/features"],
                                                   features.branch_features(given, branch)[win], branch)
                    np.testing.assert_allclose(got["albedo"], given["albedo"][win], rtol=2.0**-11, atol=2.0**-25)
                    changed += not np.allclose(got["albedo"], noisy["albedo"][win], rtol=1e-2, atol=1e-3)
                    seen += 1
    assert seen == 4 * cfg.patches_per_image
    return changed


@pytest.mark.slow
def test_shards_cut_with_nlm_hold_its_auxiliaries_in_a_set_of_their_own(nlm_set):
    raw, nlm = nlm_set
    assert nlm.set_dir == raw.set_dir.parent / "s.aux-nlm" and raw.set_dir.name == "s"
    manifest = json.loads((nlm.set_dir / "manifest.json").read_text())
    assert manifest["config"]["auxiliaries"] == "nlm" and manifest["config_hash"] != raw.content_hash()
    assert _check_patches_hold(nlm, "nlm") > 0
    # the positions are the raw set's (drawn from the render as it is)
    for split in ("train", "val"):
        for a, b in zip(shards.shard_paths(raw.set_dir, split), shards.shard_paths(nlm.set_dir, split), strict=True):
            with shards.open_shard(a) as fa, shards.open_shard(b) as fb:
                np.testing.assert_array_equal(fa["position"][:], fb["position"][:])


@pytest.mark.slow
def test_kpcn_shards_cuts_a_prefiltered_set_in_worker_processes(tmp_path):
    """A forked worker would enter the NLM filter's parallel loops under the parent's OpenMP, which aborts it."""
    make_renders(tmp_path / "renders" / "s")
    res = kpcn("shards", "--set", "s", "--renders", tmp_path / "renders", "--out", tmp_path / "shards", "--threads",
               "2", "--patch-size", "16", "--patches-per-image", "7", "--patches-per-shard", "5", "--val-fraction",
               "0.5", "--auxiliaries", "nlm", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    cfg = shards.ShardConfig(set_name="s", render_root=str(tmp_path / "renders"), out_root=str(tmp_path / "shards"),
                             patch_size=16, patches_per_image=7, patches_per_shard=5, val_fraction=0.5,
                             auxiliaries="nlm")
    assert _check_patches_hold(cfg, "nlm") > 0


@needs_oidn
@pytest.mark.slow
def test_shards_cut_with_oidn_hold_its_auxiliaries(tmp_path):
    cfg = build_tiny_shards(tmp_path, auxiliaries="oidn")
    assert cfg.set_dir.name == "s.aux-oidn"
    assert _check_patches_hold(cfg, "oidn") > 0


@pytest.mark.slow
def test_a_raw_set_is_the_set_cut_before_the_option(tmp_path):
    raw = build_tiny_shards(tmp_path)  # as the code before the option cut it: no auxiliaries anywhere
    explicit = shards.ShardConfig(**{**raw.to_dict(), "auxiliaries": "raw"})
    assert explicit.set_dir == raw.set_dir
    assert "auxiliaries" not in explicit.to_dict() and explicit.content_hash() == RAW_CONTENT_HASH
    manifest = json.loads((raw.set_dir / "manifest.json").read_text())
    assert "auxiliaries" not in manifest["config"] and manifest["config_hash"] == RAW_CONTENT_HASH
    assert "auxiliaries" not in tiny_train_config(raw).to_dict()


def test_another_method_is_refused_in_one_line(tmp_path):
    res = run_main("shards", "--set", "s", "--renders", tmp_path, "--auxiliaries", "clean", cwd=tmp_path)
    assert res.returncode == 2
    assert_one_line_error(res, "auxiliaries")


@pytest.mark.slow
def test_a_runs_record_carries_its_auxiliaries_and_a_fine_tune_says_both(nlm_set, nlm_run, tmp_path):
    raw, nlm = nlm_set
    record = Run(nlm_run).read_record()
    assert record["train"]["auxiliaries"] == "nlm" and Run(nlm_run).record().auxiliaries == "nlm"
    assert record["shards"]["set_dir"].endswith("s.aux-nlm")
    raw_run = train(tiny_train_config(raw), tmp_path / "raw", verbose=0)
    assert "auxiliaries" not in Run(raw_run).read_record()["train"] and Run(raw_run).record().auxiliaries == "raw"
    tuned = train(tiny_train_config(nlm, auxiliaries="nlm", init=str(raw_run)), tmp_path / "tuned", verbose=0)
    record = Run(tuned).read_record()
    assert record["train"]["auxiliaries"] == "nlm" and record["init"]["auxiliaries"] == "raw"
    # the set named by --auxiliaries must say so in its manifest
    with pytest.raises(Exception, match="auxiliaries nlm, not raw"):
        moved = tmp_path / "moved"
        shutil.copytree(nlm.set_dir, moved / "s")
        train(tiny_train_config(nlm, shards_root=str(moved)), tmp_path / "wrong", verbose=0)


def _by_hand(run, frame, method="nlm"):
    """The run's networks applied by hand to the features of ``prep.auxiliary.auxiliaries(frame, method)``, the
    whole frame at once, the diffuse branch multiplied back by the prefiltered albedo (``prep.albedo``)."""
    den = Denoiser.from_run(Run(run))
    given = auxiliary.auxiliaries(frame, method)
    out = {}
    for branch in features.BRANCHES:
        feats = network_input(features.branch_features(given, branch), den.model_config, branch)
        out[branch] = keras.ops.convert_to_numpy(den.networks[branch].predict_on_batch(feats[None]))[0]
    albedo = prefilter(given["albedo"], given["albedoVariance"])
    return (colour.diffuse_from_log(out["diffuse"], albedo).astype(np.float64)
            + colour.specular_from_log(out["specular"]))


@pytest.mark.slow
def test_a_model_trained_with_nlm_denoises_as_its_networks_do_on_the_prefiltered_frame(nlm_run):
    frame = random_aovs(40, 44, seed=7)
    got = Denoiser.from_run(Run(nlm_run), InferenceSettings(tile=512))(frame)["default"]
    np.testing.assert_allclose(got, _by_hand(nlm_run, frame), rtol=1e-4, atol=1e-5)
    # not what the same networks give the raw frame
    den = Denoiser.from_run(Run(nlm_run))
    den.auxiliaries = "raw"
    assert not np.allclose(den(frame)["default"], got, rtol=1e-3)


@pytest.mark.slow
def test_tiled_equals_untiled_with_a_prefilter(nlm_run):
    frame = random_aovs(40, 44, seed=8)
    whole = Denoiser.from_run(Run(nlm_run), InferenceSettings(tile=512))(frame)
    tiled = Denoiser.from_run(Run(nlm_run), InferenceSettings(tile=8))(frame)
    for name in ("diffuse", "specular", "default"):
        np.testing.assert_allclose(tiled[name], whole[name], rtol=1e-5, atol=1e-6)


def _as_oidn(run, tmp_path):
    """A copy of ``run`` whose record says it was trained with OIDN's prefilter."""
    copy = tmp_path / "oidn-model"
    shutil.copytree(run, copy)
    path = Run(copy).record_path
    record = json.loads(path.read_text())
    record["train"]["auxiliaries"] = "oidn"
    path.write_text(json.dumps(record))
    return copy


@pytest.mark.slow
def test_a_model_needing_pyoidn_where_it_is_missing_is_refused_in_one_line(nlm_run, tmp_path, monkeypatch):
    model = _as_oidn(nlm_run, tmp_path)
    frame = tmp_path / "frame.exr"
    exr.write_aovs(frame, random_aovs(24, 24, seed=9))
    monkeypatch.setitem(sys.modules, "pyoidn", None)  # the import system finds no pyoidn
    res = run_main("denoise", frame, "--run", model, "--output", tmp_path / "out.exr", cwd=tmp_path)
    assert res.returncode == 2
    assert_one_line_error(res, str(model))
    assert "pip install 'kpcn[oidn]'" in res.stderr
    assert not (tmp_path / "out.exr").exists()


@needs_oidn
@pytest.mark.slow
def test_a_model_trained_with_oidn_is_served_oidns_auxiliaries(nlm_run, tmp_path):
    model = _as_oidn(nlm_run, tmp_path)
    frame = random_aovs(32, 32, seed=10)
    den = Denoiser.from_run(Run(model))
    assert den.auxiliaries == "oidn"
    given = den.given(frame)
    expected = auxiliary.auxiliaries(frame, "oidn")
    for name in auxiliary.AUXILIARIES:
        np.testing.assert_array_equal(given[name], expected[name])
    untiled = den(frame)["default"]
    tiled = Denoiser.from_run(Run(model), InferenceSettings(tile=8))(frame)["default"]
    np.testing.assert_allclose(tiled, untiled, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["nlm", pytest.param("oidn", marks=needs_oidn)])
def test_kpcn_evaluate_scores_a_run_with_its_prefilter(nlm_run, tmp_path, method):
    model = nlm_run if method == "nlm" else _as_oidn(nlm_run, tmp_path)
    frame, reference = random_aovs(40, 44, seed=11), random_aovs(40, 44, seed=12, variances=False)
    noisy_path, ref_path = tmp_path / exr.render_filename("x", 4), tmp_path / exr.render_filename("x", 64)
    exr.write_aovs(noisy_path, frame)
    exr.write_aovs(ref_path, reference)
    rows = evaluate(Run(model), [(str(noisy_path), str(ref_path))], out_dir=tmp_path / "eval", baseline=False)
    expected = metrics.all_metrics(_by_hand(model, frame, method).astype(np.float32), reference["default"])
    assert rows[0].denoised["relmse"] == pytest.approx(expected["relmse"], rel=1e-4)


@pytest.mark.slow
def test_the_mode_probe_times_a_modes_prefilter_apart(nlm_run, fixture_noisy, capsys):
    from kpcn_keras.studies import mode_costs

    assert mode_costs.main(["--model", str(nlm_run), "--frame", str(fixture_noisy), "--size", "40,32",
                            "--repeats", "1"]) == 0
    best = json.loads(capsys.readouterr().out)["best_s"]
    assert list(best)[:2] == ["kpcn balanced", "prefilter nlm"] and all(s > 0 for s in best.values())
