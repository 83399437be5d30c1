"""The phases of a run (branches or one shared network, joint fine-tuning, the multiscale compositor
with frozen denoisers), the presets, the conditioning channels (branch one-hot, λ) and the batches of
every phase, each checked against an independent computation."""

import json
import signal
import time
from pathlib import Path

import keras
import numpy as np
import pytest
from helpers.commands import WarmProcess, assert_one_line_error, command_env, run_main
from helpers.networks import randomise
from helpers.tiny import TINY_TRAIN_MODEL, build_tiny_shards, random_aovs, tiny_train_config

from kpcn_keras import augment
from kpcn_keras.config import PRESETS, CompositorConfig, ModelConfig, TrainConfig
from kpcn_keras.data import ShardPatches
from kpcn_keras.denoise import Denoiser
from kpcn_keras.layers import FinalColour
from kpcn_keras.losses import AsymmetricSMAPE
from kpcn_keras.models import build_branch_model, build_final_model, network_input
from kpcn_keras.multiscale import InferenceOnly, build_compositor, multiscale_output
from kpcn_keras.run import Run, read_state
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.train import train
from prep import colour, exr
from prep.errors import KpcnError, OptionError
from prep.shards import VIEWS, ShardSet, open_shard, read_patches, shard_paths

TINY_COMPOSITOR = {"width": 4, "depth": 3, "kernel_size": 3}


def predict(model, x):
    return np.asarray(keras.ops.convert_to_numpy(model.predict_on_batch(x)))


def conv_layers(model):
    return [layer for layer in model.layers if isinstance(layer, keras.layers.Conv2D)]


# ---------------------------------------------------------------- presets and conditioning


def test_presets_reach_the_papers_architectures():
    kpcn_paper = build_branch_model(TrainConfig.from_preset("kpcn-paper").model)
    convs = conv_layers(kpcn_paper)
    # Bako et al.: 9 layers, 8 hidden 5x5 convolutions of 100 filters and the 21x21 kernel head
    assert len(convs) == 9 and all(c.kernel_size == (5, 5) and c.filters == 100 for c in convs[:-1])
    assert convs[-1].filters == 21 * 21
    kpal = TrainConfig.from_preset("kpal-paper")
    kpal_paper = build_branch_model(kpal.model)
    convs = conv_layers(kpal_paper)
    # the report's 28-layer residual network, batch norm after every convolution, keep probability 0.7
    assert len(convs) == 28 and convs[-1].filters == 21 * 21
    assert sum(isinstance(layer, keras.layers.BatchNormalization) for layer in kpal_paper.layers) == 27
    assert {layer.rate for layer in kpal_paper.layers if isinstance(layer, keras.layers.Dropout)} == {0.3}
    assert kpal.batch_size == 12 and kpal.learning_rate == 1e-4 and kpal.joint_learning_rate == 1e-6
    assert TrainConfig().preset == "cpu"
    assert set(PRESETS) == {"cpu", "unet", "dilated", "fast", "kpcn-paper", "kpal-paper"}
    # flags override the preset
    assert TrainConfig.from_preset("kpcn-paper", model={"conv_size": 3, "dropout": 0.1}).model.conv_size == 3


def test_network_input_appends_the_branch_one_hot_and_log_slope():
    feats = np.random.default_rng(0).normal(size=(2, 5, 6, 27)).astype(np.float32)
    cfg = ModelConfig(branch_channels=True, slope_channel=True)
    assert cfg.input_channels == 30
    slope = np.array([1.0, 4.0])[:, None, None]
    x = network_input(feats, cfg, "specular", slope)
    np.testing.assert_array_equal(x[..., :27], feats)
    np.testing.assert_array_equal(x[..., 27], 0.0)
    np.testing.assert_array_equal(x[..., 28], 1.0)
    np.testing.assert_allclose(x[0, ..., 29], 0.0)
    np.testing.assert_allclose(x[1, ..., 29], np.log(4.0), rtol=1e-7)
    assert network_input(feats, ModelConfig(), "diffuse") is not None
    with pytest.raises(OptionError, match="slope"):
        network_input(feats, cfg, "diffuse")  # the network needs λ
    with pytest.raises(OptionError, match="slope"):
        network_input(feats, ModelConfig(), "diffuse", 2.0)  # the network would ignore it
    with pytest.raises(OptionError, match="0.5"):
        network_input(feats, cfg, "diffuse", 0.5)


@pytest.mark.parametrize("bad, option", [
    (dict(slope_input=True), "slope_input"),  # λ as input needs the asymmetric loss
    (dict(shared=True, branches=("diffuse",)), "shared"),
    (dict(joint_steps=3, branches=("diffuse",)), "joint_steps"),
    (dict(compositor={"kind": "pyramid"}), "compositor"),
    (dict(slope_range=(2.0, 1.0), loss="asymmetric", slope_input=True), "slope_range"),
    (dict(joint_steps=-1), "joint_steps"),
])
def test_inconsistent_phase_options_are_refused_naming_the_option(bad, option):
    with pytest.raises(OptionError) as err:
        TrainConfig.from_preset("cpu", **bad)
    assert err.value.option == option


def test_the_conditioning_channels_follow_the_training_options_not_the_model_dict():
    cfg = TrainConfig.from_preset("cpu", shared=True, loss="asymmetric", slope_input=True,
                                  model={"branch_channels": False})
    assert cfg.model.branch_channels and cfg.model.slope_channel
    assert [p.name for p in cfg.phases()] == ["shared"]
    cfg = TrainConfig.from_preset("cpu", joint_steps=5, compositor={"kind": "alpha"}, steps=120)
    assert [(p.name, p.first_epoch, p.epochs) for p in cfg.phases()] == \
        [("diffuse", 0, 3), ("specular", 3, 3), ("joint", 6, 1), ("compositor", 7, 12)]


# ---------------------------------------------------------------- the layers and models of the phases


def test_final_colour_inverts_the_branch_transforms():
    rng = np.random.default_rng(1)
    d, s = rng.uniform(0, 5, (2, 6, 7, 3)), rng.uniform(0, 3, (2, 6, 7, 3))
    albedo = rng.uniform(-0.2, 1.2, (2, 6, 7, 3))  # clipped to [0, 1], as the inverse transform does
    want = colour.diffuse_from_log(d, albedo) + colour.specular_from_log(s)  # float64 numpy
    ins = [keras.Input((None, None, 3)) for _ in range(3)]
    layer = FinalColour(name="final_colour")
    model = keras.Model(ins, layer(ins))
    got = predict(model, [x.astype(np.float32) for x in (d, s, albedo)])
    np.testing.assert_allclose(got, want, rtol=2e-5)
    assert layer.compute_output_shape([(2, 6, 7, 3)] * 3) == (2, 6, 7, 3)  # the Keras contract: test_layers
    huge = predict(model, [np.full((1, 2, 2, 3), 94.0, np.float32)] * 2 + [np.ones((1, 2, 2, 3), np.float32)])
    assert np.all(np.isfinite(huge))  # the clamp: exp(94) overflows float32


def _final_inputs(cfg: ModelConfig, seed=0):
    rng = np.random.default_rng(seed)
    x = {f"{b}_input": network_input(rng.uniform(0, 2, (2, 12, 10, 27)), cfg, b) for b in ("diffuse", "specular")}
    x["albedo"] = rng.uniform(0, 1, (2, 12, 10, 3)).astype(np.float32)
    return x


@pytest.mark.slow
@pytest.mark.parametrize("kind", [None, "alpha", "kernel"])
@pytest.mark.parametrize("shared", [False, True])
def test_final_colour_models_survive_save_and_load_and_train_a_step(kind, shared, tmp_path):
    cfg = ModelConfig(**TINY_TRAIN_MODEL, branch_channels=shared)
    names = {b: "shared" if shared else b for b in ("diffuse", "specular")}
    nets = {n: build_branch_model(cfg, name=n) for n in set(names.values())}
    for i, net in enumerate(nets.values()):
        randomise(net, seed=i)
    if kind is None:
        model = build_final_model({b: nets[names[b]] for b in names}, cfg.input_channels, name="joint")
    else:
        comp_cfg = CompositorConfig(kind=kind, **TINY_COMPOSITOR)
        compositor = build_compositor(comp_cfg)
        frozen = {n: InferenceOnly(net, name=f"{n}_denoiser") for n, net in nets.items()}
        model = build_final_model(
            {b: (lambda x, b=b: multiscale_output(x, frozen[names[b]], comp_cfg, compositor, prefix=f"{b}_"))
             for b in names}, cfg.input_channels, name="multiscale")
    registered = {id(p) for p in model.parameters()}
    assert all(id(w.value) in registered for w in model.trainable_weights)  # else their gradients accumulate
    x = _final_inputs(cfg)
    before = predict(model, x)
    assert before.shape == (2, 12, 10, 3)
    path = tmp_path / "m.keras"
    model.save(path)
    loaded = keras.models.load_model(path)
    np.testing.assert_array_equal(predict(loaded, x), before)
    denoisers = [w.numpy().copy() for n in nets
                 for w in loaded.get_layer(n if kind is None else f"{n}_denoiser").weights]
    loaded.compile(optimizer=keras.optimizers.Adam(1e-2), loss="mae")
    loaded.fit(x, before + 0.5, epochs=1, verbose=0)
    after = [w.numpy() for n in nets for w in loaded.get_layer(n if kind is None else f"{n}_denoiser").weights]
    moved = any(not np.array_equal(a, b) for a, b in zip(denoisers, after))
    assert moved == (kind is None)  # joint fine-tuning trains the networks; the compositor phase does not


# ---------------------------------------------------------------- batches


@pytest.fixture(scope="module")
def shards(tmp_path_factory):
    return build_tiny_shards(tmp_path_factory.mktemp("shards"))


def _train_paths(shard_cfg):
    return [e.path for e in ShardSet(shard_cfg.set_dir).verified_shards("train")]


def _patches(paths, name):
    """Every patch of ``name`` (a name a reader asks for, the features recomputed, or provenance)."""
    out = []
    for p in paths:
        with open_shard(p) as f:
            out.append(read_patches(f, [name], range(len(f["source"])))[name] if name in VIEWS else f[name][:])
    return np.concatenate(out)


def test_a_shared_network_sees_each_patch_once_per_branch_with_its_one_hot(shards):
    paths = _train_paths(shards)
    cfg = ModelConfig(branch_channels=True)
    stream = ShardPatches(paths, "both", 4, model=cfg, shuffle=False)
    xs, ys = zip(*(stream[i] for i in range(len(stream))))
    x, y = np.concatenate(xs), np.concatenate(ys)
    n = len(_patches(paths, "source"))
    assert len(x) == 2 * n
    for k, branch in enumerate(("diffuse", "specular")):
        part = slice(k * n, (k + 1) * n)
        np.testing.assert_array_equal(x[part, ..., :27], _patches(paths, f"{branch}/features"))
        np.testing.assert_array_equal(x[part, ..., 27 + k], 1.0)
        np.testing.assert_array_equal(x[part, ..., 28 - k], 0.0)
        np.testing.assert_array_equal(y[part], _patches(paths, f"{branch}/reference"))


def test_final_colour_batches_carry_both_branches_the_albedo_and_the_linear_target(shards):
    paths = _train_paths(shards)
    stream = ShardPatches(paths, "final", 3, shuffle=False, loss_target="reference+noisy")
    x, y = stream[0]
    assert sorted(x) == ["albedo", "diffuse_input", "specular_input"]
    np.testing.assert_array_equal(x["specular_input"], _patches(paths, "specular/features")[:3])
    np.testing.assert_array_equal(y[..., :3], _patches(paths, "reference")[:3])
    np.testing.assert_array_equal(y[..., 3:], _patches(paths, "noisy")[:3])


def test_slope_input_batches_pair_each_patch_with_one_lambda_in_input_and_target(shards):
    cfg = ModelConfig(slope_channel=True)
    stream = ShardPatches(_train_paths(shards), "diffuse", 6, model=cfg, seed=3,
                          loss_target="reference+noisy", slope_range=(1.0, 8.0))
    x, y = stream[1]
    assert y.shape[-1] == 7
    lam_in = np.exp(x[..., 27].astype(np.float64))
    np.testing.assert_allclose(lam_in, y[..., 6], rtol=1e-6)
    per_patch = y[:, 0, 0, 6]
    assert np.all((per_patch >= 1.0) & (per_patch <= 8.0)) and len(np.unique(per_patch)) == 6
    np.testing.assert_array_equal(y[..., 6], per_patch[:, None, None] * np.ones_like(y[..., 6]))


def test_augmented_batches_are_the_patches_under_the_symmetries_drawn_for_them(shards):
    paths = _train_paths(shards)
    plain = ShardPatches(paths, "specular", 4, seed=7, loss_target="reference+noisy")
    aug = ShardPatches(paths, "specular", 4, seed=7, loss_target="reference+noisy", augment=True)
    differs = 0
    for i in range(3):
        (x0, y0), (x1, y1) = plain[i], aug[i]
        # the stream's documented draw: one generator per batch number, one augmentation per patch in order
        rng = np.random.default_rng([7, i, 1])
        for j in range(4):
            a = augment.draw(rng)
            np.testing.assert_array_equal(augment.augment_features(x1[j], a.inverse()), x0[j])
            np.testing.assert_array_equal(augment.augment_colour(y1[j, ..., :3], a.inverse()), y0[j, ..., :3])
            np.testing.assert_array_equal(augment.augment_colour(y1[j, ..., 3:], a.inverse()), y0[j, ..., 3:])
            differs += a != augment.IDENTITY
    assert differs > 0
    assert TrainConfig().augment  # on by default


@pytest.mark.slow
def test_a_slope_input_network_keeps_more_of_the_noisy_input_at_a_higher_slope():
    """Documented direction (docs/training.md §2, ``kpcn denoise --slope``): a higher λ punishes overshooting the
    reference away from the input more, so the output stays nearer the noisy input. Synthetic case: a flat
    reference under Gaussian noise; one tiny network trained for λ = 1 and λ = 16 alike."""
    keras.utils.set_random_seed(0)
    rng = np.random.default_rng(0)
    n, p = 64, 12
    gt = np.ones((n, p, p, 3), np.float32)
    noisy = np.clip(gt + rng.normal(0, 0.3, gt.shape), 0, None).astype(np.float32)
    feats = np.zeros((n, p, p, 27), np.float32)
    feats[..., :3] = noisy
    cfg = ModelConfig(width=8, depth=2, kernel_size=3, slope_channel=True)
    model = build_branch_model(cfg)
    model.compile(optimizer=keras.optimizers.Adam(1e-2), loss=AsymmetricSMAPE(None))
    slopes = np.where(np.arange(n) % 2 == 0, 1.0, 16.0)[:, None, None]
    y = np.concatenate([gt, noisy, np.broadcast_to(slopes[..., None], (n, p, p, 1))], -1).astype(np.float32)
    model.fit(network_input(feats, cfg, "diffuse", slopes), y, batch_size=16, epochs=30, verbose=0, shuffle=False)
    distance = {lam: np.abs(predict(model, network_input(feats, cfg, "diffuse", lam)) - noisy).mean()
                for lam in (1.0, 16.0)}
    assert distance[16.0] < 0.7 * distance[1.0], distance


# ---------------------------------------------------------------- whole runs


def _weights(model):
    return [np.asarray(w) for w in model.get_weights()]


@pytest.fixture(scope="module")
def full_run(shards, tmp_path_factory):
    """Separate branches, joint fine-tuning and the alpha compositor."""
    cfg = tiny_train_config(shards, joint_steps=4, compositor={"kind": "alpha", **TINY_COMPOSITOR}, compositor_steps=4)
    return train(cfg, tmp_path_factory.mktemp("runs") / "full", verbose=0)


@pytest.mark.slow
def test_a_run_trains_its_phases_in_order_into_one_log_and_one_record(full_run):
    record = json.loads((full_run / "config.json").read_text())
    assert [(n, p["first_epoch"], p["epochs"], p["status"]) for n, p in record["phases"].items()] == [
        ("diffuse", 0, 2, "done"), ("specular", 2, 2, "done"), ("joint", 4, 2, "done"), ("compositor", 6, 2, "done")]
    assert record["components"] == {
        "diffuse": {"file": "joint.keras", "layers": ["diffuse"], "phase": "joint"},
        "specular": {"file": "joint.keras", "layers": ["specular"], "phase": "joint"},
        "compositor": {"file": "compositor.keras", "layers": ["compositor"], "phase": "compositor"},
    }
    assert record["phases"]["joint"]["learning_rate"] == TrainConfig().joint_learning_rate
    rows = (full_run / "log.csv").read_text().splitlines()
    assert [int(r.split(",")[0]) for r in rows[1:]] == list(range(8))
    assert json.loads((full_run / "timings.json").read_text()).keys() == record["phases"].keys()
    assert sorted(p.name for p in full_run.glob("*.keras")) == \
        ["compositor.keras", "diffuse.keras", "joint.keras", "specular.keras"]


@pytest.mark.slow
def test_joint_fine_tuning_moves_the_branch_networks_and_the_compositor_phase_does_not(full_run):
    run = Run(full_run)
    record = run.record()
    branch = keras.models.load_model(full_run / "diffuse.keras", compile=False)
    joint = run.load_component(record, "diffuse")
    assert any(not np.array_equal(a, b) for a, b in zip(_weights(branch), _weights(joint)))
    frozen = keras.models.load_model(full_run / "compositor.keras", compile=False).get_layer("diffuse_denoiser").layer
    for a, b in zip(_weights(joint), _weights(frozen)):
        np.testing.assert_array_equal(a, b)
    compositor = run.load_component(record, "compositor")
    assert np.any(_weights(compositor)[-1] != 0) or np.any(_weights(compositor)[-2] != 0)  # the α head trained


@pytest.mark.slow
def test_a_multiscale_run_denoises_in_tiles_as_it_does_whole(full_run):
    aovs = random_aovs(37, 53, seed=5)
    whole = Denoiser.from_run(Run(full_run), InferenceSettings(tile=512))(aovs)["default"]
    tiled = Denoiser.from_run(Run(full_run), InferenceSettings(tile=8))(aovs)["default"]
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-6)
    plain = Denoiser.from_run(Run(full_run), multiscale=False)(aovs)["default"]
    assert not np.allclose(plain, whole)  # the compositor does something
    # the same networks without their compositor, nothing loaded again
    tile8 = InferenceSettings(tile=8)
    np.testing.assert_array_equal(Denoiser.from_run(Run(full_run), tile8).without_compositor()(aovs)["default"],
                                  Denoiser.from_run(Run(full_run), tile8, multiscale=False)(aovs)["default"])


@pytest.mark.slow
def test_a_compositor_of_21x21_kernels_on_a_bicubic_pyramid_with_every_scale_supervised_trains_and_tiles(
        shards, tmp_path):
    comp = {**TINY_COMPOSITOR, "kind": "kernel", "kernel_size": 21, "downsample": "bicubic", "scale_supervision": 0.5}
    cfg = tiny_train_config(shards, compositor=comp, compositor_steps=2, loss="asymmetric")
    run_dir = train(cfg, tmp_path / "r", verbose=0)
    record = json.loads((run_dir / "config.json").read_text())
    assert {k: record["train"]["compositor"][k] for k in comp} == comp
    phase = keras.models.load_model(run_dir / "compositor.keras", compile=False)  # the checkpoint's layers load
    supervision = phase.get_layer("scale_supervision")
    assert isinstance(supervision.loss_fn, AsymmetricSMAPE) and supervision.weight == 0.5
    assert sorted(i.name for i in phase.inputs) == ["albedo", "diffuse_input", "specular_input", "target"]
    x = _final_inputs(cfg.model)
    phase({**x, "target": np.concatenate([x["albedo"], x["albedo"]], axis=-1)})
    assert len(phase.losses) == 2 * 2 + 1  # an α term per pair and branch, and the per-scale terms
    aovs = random_aovs(37, 53, seed=5)
    whole = Denoiser.from_run(Run(run_dir), InferenceSettings(tile=512))(aovs)["default"]
    tiled = Denoiser.from_run(Run(run_dir), InferenceSettings(tile=8))(aovs)["default"]
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
def test_a_killed_phase_resumes_at_its_phase_and_step(shards, tmp_path):
    cfg = tiny_train_config(shards, joint_steps=40, steps_per_epoch=4)
    reference = train(cfg, tmp_path / "ref", verbose=0)
    run_dir = tmp_path / "killed"
    proc = WarmProcess(train, (cfg, str(run_dir)), {"verbose": 0}, cwd=tmp_path, env=command_env())
    ckpt = run_dir / "checkpoints" / "joint.keras"
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        if ckpt.is_file() and 1 <= read_state(ckpt)["epochs_done"] < 9:
            break
        time.sleep(0.02)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    state = read_state(ckpt)
    assert state["phase"] == "joint" and 1 <= state["epochs_done"] < 9, state["epochs_done"]
    record = json.loads((run_dir / "config.json").read_text())
    assert record["phases"]["specular"]["status"] == "done" and record["phases"]["joint"]["status"] == "pending"
    train(cfg, run_dir, verbose=0)
    for name in ("joint.keras", "log.csv", "diffuse.keras", "specular.keras"):
        assert (run_dir / name).read_bytes() == (reference / name).read_bytes(), name
    records = [json.loads((d / "config.json").read_text()) for d in (run_dir, reference)]
    for r in records:
        del r["command"]  # the processes had other command lines
    assert json.dumps(records[0]) == json.dumps(records[1])  # in the same order too: the bytes of the rest


@pytest.mark.slow
def test_the_command_line_trains_shared_slope_input_multiscale_and_draws_every_figure(shards, tmp_path):
    root = Path(shards.out_root).parent
    args = ("train", "--set", shards.set_name, "--shards", shards.out_root, "--run", str(tmp_path / "r"),
            "--width", "4", "--depth", "2", "--kernel-size", "3", "--steps", "2", "--batch-size", "2",
            "--shared", "--joint-steps", "2", "--compositor", "kernel", "--compositor-steps", "2",
            "--loss", "asymmetric", "--slope-input", "--slope-range", "1,4")
    res = run_main(*args, cwd=root)
    assert res.returncode == 0, res.stderr[-3000:]
    record = json.loads((tmp_path / "r" / "config.json").read_text())
    assert sorted(record["components"]) == ["compositor", "shared"] and record["train"]["slope_range"] == [1.0, 4.0]
    noisy = tmp_path / "renders" / "x-00004spp.exr"
    exr.write_aovs(noisy, random_aovs(24, 28, seed=9))
    res = run_main("denoise", noisy, "--run", tmp_path / "r", cwd=root)
    assert_one_line_error(res, "--slope")
    res = run_main("denoise", noisy, "--run", tmp_path / "r", "--slope", "3", "-o", tmp_path / "out.exr", cwd=root)
    assert res.returncode == 0, res.stderr[-3000:]
    exr.write_aovs(tmp_path / "renders" / "x-00064spp.exr", random_aovs(24, 28, seed=10))
    res = run_main("figures", noisy, "--run", tmp_path / "r", "--slopes", "1,4", cwd=root)
    assert res.returncode == 0, res.stderr[-3000:]
    for name in ("kernels", "multiscale", "alpha", "slopes"):
        assert (tmp_path / "r" / "figures" / f"{name}.png").read_bytes().startswith(b"\x89PNG"), name
    res = run_main(*args[:3], "--gamma", "0.1", cwd=root)
    assert_one_line_error(res, "--gamma", "--compositor")


@pytest.mark.slow
def test_a_record_of_an_older_kpcn_is_one_clear_error(shards, tmp_path):
    run_dir = train(tiny_train_config(shards, branches=("diffuse",)), tmp_path / "r", verbose=0)
    record = json.loads((run_dir / "config.json").read_text())
    del record["phases"]
    (run_dir / "config.json").write_text(json.dumps(record))
    with pytest.raises(KpcnError, match="older kpcn"):
        Run(run_dir).read_record()


# ---------------------------------------------------------------- reference weighting


def test_reference_tau_weighs_the_branch_phases_only_and_an_older_record_reads_as_unweighted():
    # off by default: it has not yet won (docs/results/10-quality-levers.md §10a)
    assert TrainConfig().reference_tau == 0.0
    cfg = TrainConfig.from_preset("cpu", joint_steps=2, compositor={"kind": "alpha"}, reference_tau=0.1)
    assert cfg.reference_tau == 0.1 and cfg.to_dict()["reference_tau"] == 0.1
    weighted = {p.name: cfg.weights_reference(p) for p in cfg.phases()}
    assert weighted == {"diffuse": True, "specular": True, "joint": False, "compositor": False}
    off = TrainConfig.from_preset("cpu")
    assert "reference_tau" not in off.to_dict() and not any(off.weights_reference(p) for p in off.phases())
    record = cfg.to_dict()
    del record["reference_tau"]  # a run trained before the weighting existed
    assert TrainConfig.from_record(record).reference_tau == 0.0
    assert TrainConfig.from_record(record).to_dict() == record  # read back, it is the record it was
    for bad in (-0.1, 101.0, float("nan"), "x"):
        with pytest.raises(OptionError, match="reference_tau"):
            TrainConfig(reference_tau=bad)
    res = run_main("train", "--reference-tau", "-1", "--set", "none", cwd=Path.cwd())
    assert_one_line_error(res, "--reference-tau", "-1")


def test_the_branch_phases_compile_the_weighted_loss_and_read_the_relse_the_final_colour_phases_do_not(tmp_path):
    from kpcn_keras import distributed
    from kpcn_keras.train import _compile, _data

    shard_cfg = build_tiny_shards(tmp_path, reference_variances=True)
    cfg = tiny_train_config(shard_cfg, loss="asymmetric", joint_steps=2, reference_tau=0.2)
    paths = {split: shard_paths(shard_cfg.set_dir, split) for split in ("train", "val")}
    model = build_branch_model(cfg.model)
    for phase in cfg.phases():
        if phase.trains_on_final_colour:
            _compile(model, cfg, phase)
            assert model.loss.reference_tau == 0.0
            continue
        _compile(model, cfg, phase)
        assert isinstance(model.loss, AsymmetricSMAPE) and model.loss.reference_tau == 0.2
        train_data, val = _data(cfg, phase, paths, 0, 1, distributed.World())
        for data in (train_data, val):
            x, y = data[0]
            assert y.shape[-1] == 7  # gt, noisy, relSE
            assert np.isfinite(float(model.loss(y, predict(model, x))))
