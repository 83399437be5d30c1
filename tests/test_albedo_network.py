"""The albedo network (``--albedo-steps``), a copy of the diffuse network trained to filter the albedo the
diffuse irradiance is multiplied by: its options, its batches, its training model and the denoiser that uses it,
each against an independent computation."""

import keras
import numpy as np
import pytest
from helpers.tiny import build_tiny_shards, tiny_train_config

from kpcn_keras import augment
from kpcn_keras.config import ALBEDO_NETWORK, TrainConfig
from kpcn_keras.data import ShardPatches
from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import albedo_input, build_albedo_training_model, build_branch_model
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import train
from prep import colour, exr, features
from prep.albedo import prefilter
from prep.errors import OptionError
from prep.inputs import restrict
from prep.shards import open_shard, read_patches, shard_paths


def predict(model, x):
    return np.asarray(keras.ops.convert_to_numpy(model.predict_on_batch(x)))


@pytest.fixture(scope="module")
def albedo_run(tmp_path_factory):
    """A tiny run with an albedo network, and its shard set's configuration."""
    tmp = tmp_path_factory.mktemp("albedo")
    shard_cfg = build_tiny_shards(tmp)
    run_dir = train(tiny_train_config(shard_cfg, albedo_steps=4), tmp / "runs" / "r", verbose=0)
    return Run(run_dir), shard_cfg


# ---------------------------------------------------------------- options


@pytest.mark.parametrize("bad", [
    dict(shared=True),
    dict(loss="asymmetric", slope_input=True),
    dict(branches=("diffuse",)),  # the loss is on the final colour, which needs the specular branch
])
def test_albedo_steps_are_refused_without_a_diffuse_network_of_its_own(bad):
    with pytest.raises(OptionError) as err:
        TrainConfig.from_preset("cpu", albedo_steps=10, **bad)
    assert err.value.option == "albedo_steps"


def test_the_albedo_phase_follows_the_branches_and_a_run_without_it_keeps_its_record():
    cfg = TrainConfig.from_preset("cpu", albedo_steps=120, joint_steps=50, steps=100)
    assert [(p.name, p.steps, p.learning_rate) for p in cfg.phases()] == [
        ("diffuse", 100, cfg.learning_rate), ("specular", 100, cfg.learning_rate),
        ("albedo", 120, cfg.albedo_learning_rate), ("joint", 50, cfg.joint_learning_rate)]
    # its own: make train's rate saturates it (docs/results/20-albedo-network.md)
    assert cfg.albedo_learning_rate != cfg.learning_rate
    assert (cfg.to_dict()["albedo_steps"], cfg.to_dict()["albedo_learning_rate"]) == (120, cfg.albedo_learning_rate)
    # a run without one writes no key, and a record without the key is a run without one
    plain = TrainConfig.from_preset("cpu")
    assert not {"albedo_steps", "albedo_learning_rate"} & set(plain.to_dict())
    assert TrainConfig.from_record(plain.to_dict()).albedo_steps == 0
    assert [p.name for p in TrainConfig(inputs="no-variance", albedo_steps=3).phases()] == \
        ["diffuse", "specular", "albedo"]
    # a no-split run's one network filters the total colour: no irradiance to multiply, passed over as joint is
    assert [p.name for p in TrainConfig(inputs="no-split", albedo_steps=3, joint_steps=3).phases()] == ["diffuse"]


# ---------------------------------------------------------------- batches and the training model


def test_albedo_batches_are_the_diffuse_features_around_the_albedo_with_the_references(tmp_path):
    cfg = build_tiny_shards(tmp_path)
    paths = shard_paths(cfg.set_dir, "train")
    stream = ShardPatches(paths, "albedo", batch_size=3, shuffle=False)
    x, y = stream[0]
    with open_shard(paths[0]) as f:
        want = read_patches(f, ["diffuse/features", "albedo", "diffuse/reference", "specular/reference",
                                "reference"], range(3))
    np.testing.assert_array_equal(x["features"][..., :3], np.clip(want["albedo"], 0, 1))
    np.testing.assert_array_equal(x["features"][..., 3:], want["diffuse/features"][..., 3:])
    np.testing.assert_array_equal(x["irradiance"], want["diffuse/reference"])
    np.testing.assert_array_equal(x["specular"], want["specular/reference"])
    np.testing.assert_array_equal(y, want["reference"])
    # augmented: the albedo moves and permutes with the features it replaces (the same as augmenting the input)
    aug = augment.Augmentation(5, (2, 0, 1))
    moved = albedo_input(augment.augment_features(want["diffuse/features"][0], aug),
                         augment.augment_colour(want["albedo"][0], aug))
    np.testing.assert_array_equal(
        moved, augment.augment_features(albedo_input(want["diffuse/features"][0].copy(), want["albedo"][0]), aug))
    with pytest.raises(ValueError, match="reference alone"):
        ShardPatches(paths, "albedo", batch_size=3, loss_target="reference+noisy")


def test_the_training_model_is_the_reference_irradiance_times_the_networks_albedo_plus_the_specular():
    cfg = TrainConfig.from_preset("cpu", model={"width": 4, "depth": 2, "kernel_size": 3}).model
    net = build_branch_model(cfg, name=ALBEDO_NETWORK)
    rng = np.random.default_rng(2)
    net.set_weights([rng.normal(0, 0.3, w.shape).astype(np.float32) for w in net.get_weights()])
    model = build_albedo_training_model(net, cfg.input_channels)
    feats = rng.uniform(-1, 1, (2, 9, 11, 27)).astype(np.float32)
    feats[..., :3] = rng.uniform(0, 1, (2, 9, 11, 3))
    irr, spec = rng.uniform(0, 4, (2, 2, 9, 11, 3)).astype(np.float32)
    got = predict(model, {"features": feats, "irradiance": irr, "specular": spec})
    albedo = predict(net, feats).astype(np.float64)
    want = np.expm1(irr.astype(np.float64)) * (np.clip(albedo, 0, 1) + colour.ALBEDO_EPS) + np.expm1(spec)
    np.testing.assert_allclose(got, want, rtol=2e-5)
    assert model.get_layer(ALBEDO_NETWORK) is net


# ---------------------------------------------------------------- the run and its denoiser


def test_the_albedo_network_starts_as_the_diffuse_network_and_is_trained_apart(albedo_run):
    run, _ = albedo_run
    record = run.record()
    assert record.components[ALBEDO_NETWORK].file == "albedo.keras"
    diffuse = run.load_component(record, "diffuse")
    albedo = run.load_component(record, ALBEDO_NETWORK)
    assert albedo.name == ALBEDO_NETWORK
    assert [w.shape for w in albedo.get_weights()] == [w.shape for w in diffuse.get_weights()]
    # trained: its weights left the diffuse network's, where it started
    assert any(not np.array_equal(a, d) for a, d in zip(albedo.get_weights(), diffuse.get_weights()))


def test_the_denoiser_multiplies_the_irradiance_by_the_networks_albedo_and_tiles_equal_the_whole(albedo_run):
    run, shard_cfg = albedo_run
    noisy = sorted((shard_cfg.set_dir.parent.parent / "renders" / "s").glob("*.exr"))
    aovs = exr.read_aovs(noisy[0])
    h, w = aovs["depth"].shape
    whole = Denoiser.from_run(run, InferenceSettings(tile=max(h, w)))
    assert whole.albedo_network is not None
    out = whole(aovs)
    # independently: the network on the whole frame's albedo input, the diffuse branch's output times it
    given = restrict(aovs, whole.inputs)
    feats = albedo_input(features.branch_features(given, "diffuse"), given["albedo"])
    albedo = predict(whole.albedo_network, feats[None])[0]
    want = colour.diffuse_from_log(whole.run_branch("diffuse", aovs), albedo)
    np.testing.assert_allclose(out["diffuse"], want, rtol=1e-6, atol=1e-7)
    # and not the prefilter's albedo: the network is what serves
    assert not np.allclose(albedo, prefilter(given["albedo"], given["albedoVariance"]), atol=1e-4)
    tiled = Denoiser.from_run(run, InferenceSettings(tile=8))(aovs)
    for name in ("diffuse", "specular", "default"):
        np.testing.assert_allclose(tiled[name], out[name], rtol=1e-5, atol=1e-6)
