"""Branch models: shapes, config, initial behaviour, receptive field, save/load, kernels, and learning."""

import dataclasses
import json

import keras
import numpy as np
import pytest
import torch
from helpers.networks import finite_loss_and_gradients, randomise
from helpers.numerics import extreme_features

from kpcn_keras.config import (
    PRESETS,
    QUALITY_AUXILIARIES,
    QUALITY_INIT,
    QUALITY_MODES,
    QUALITY_OIDN_MIX,
    QUALITY_PRESETS,
    TrainConfig,
)
from kpcn_keras.layers import apply_kernels
from kpcn_keras.losses import SMAPE
from kpcn_keras.models import (
    ARCHS,
    ModelConfig,
    build_branch_model,
    build_kernel_model,
    input_alignment,
    receptive_radius,
    trunk_radius,
)
from prep import auxiliary, colour, exr
from prep.colour import LOG_COLOUR_MAX
from prep.errors import OptionError
from prep.features import NUM_FEATURES


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def tiny(arch, **kw):
    base = dict(arch=arch, width=6, depth=2, kernel_size=5)
    base.update(kw)
    return ModelConfig(**base)


def predict(model, x):
    return to_np(model(x, training=False))


def features(shape, seed=0):
    return np.random.default_rng(seed).normal(size=shape).astype(np.float32)


# ---------------------------------------------------------------- config


def test_config_defaults_and_round_trip():
    cfg = ModelConfig()
    assert (cfg.arch, cfg.in_channels, cfg.width, cfg.depth, cfg.kernel_size) == ("kpcn", 27, 32, 7, 13)
    assert cfg.batchnorm is False
    assert ModelConfig(arch="kpal").batchnorm is True
    assert ModelConfig(arch="kpal", batchnorm=False).batchnorm is False
    d = ModelConfig(arch="kpal", dropout=0.3).to_dict()
    assert d["batchnorm"] is True and d["dropout"] == 0.3
    assert ModelConfig.from_dict(d) == ModelConfig(arch="kpal", dropout=0.3)


@pytest.mark.parametrize(
    "kw,echo",
    [
        (dict(arch="unt"), "'unt'"),
        (dict(arch="unet", levels=7), "7"),
        (dict(arch="unet", levels=1), "1"),
        (dict(arch="unet", width_growth=0.5), "0.5"),
        (dict(arch="unet", width=32, width_cap=16), "16"),
        (dict(kernel_size=12), "12"),
        (dict(conv_size=4), "4"),
        (dict(dropout=1.0), "1.0"),
        (dict(dropout=-0.1), "-0.1"),
        (dict(in_channels=2), "2"),
        (dict(width=0), "0"),
        (dict(depth=0), "0"),
        (dict(width=3.5), "3.5"),
        (dict(batchnorm="yes"), "'yes'"),
    ],
)
def test_config_validation_echoes_value(kw, echo):
    with pytest.raises(ValueError, match=echo):
        ModelConfig(**kw)


@pytest.mark.parametrize("arch", ["kpcn", "kpal", "dpcn"])
@pytest.mark.parametrize("name, value", [("levels", 3), ("width_growth", 2.0), ("width_cap", 64)])
def test_unet_fields_are_refused_with_another_arch_and_left_out_of_its_dict(arch, name, value):
    with pytest.raises(OptionError, match=rf"^{name} is a setting of arch unet alone, received {value}"):
        ModelConfig(arch=arch, **{name: value})
    d = ModelConfig(arch=arch).to_dict()
    # the dict written before unet existed, key for key and in order: old records stay byte-identical
    assert list(d) == ["arch", "in_channels", "width", "depth", "conv_size", "kernel_size", "dropout", "batchnorm",
                       "branch_channels", "slope_channel"]
    assert ModelConfig.from_dict(d) == ModelConfig(arch=arch)


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(arch="kpal", depth=2, dilations=[1, 2]), r"^dilations dilate the convolutions of a plain stack .*"
                                                       r"received \[1, 2\] with arch kpal"),
        (dict(arch="unet", depth=2, dilations=[1, 2]), "with arch unet"),
        (dict(depth=3, dilations=[1, 2]), r"one dilation per trunk convolution, depth 3; received 2: \[1, 2\]"),
        (dict(depth=1, dilations=4), "must be a list of dilations, one per convolution, received 4"),
        (dict(depth=2, dilations=[1, 0]), "0"),
        (dict(depth=2, dilations=[1, 33]), "33"),
    ],
)
def test_dilations_are_refused_where_they_do_not_fit_and_echo_what_was_given(kw, message):
    with pytest.raises(OptionError, match=message):
        ModelConfig(**kw)


def test_dilations_round_trip_and_all_ones_is_the_plain_stack_with_its_old_record():
    cfg = ModelConfig(depth=3, dilations=[1, 4, 2])
    assert cfg.trunk_dilations() == (1, 4, 2)
    d = cfg.to_dict()
    assert d["dilations"] == [1, 4, 2]  # what JSON reads back, so a stored record equals a fresh one
    assert ModelConfig.from_dict(json.loads(json.dumps(d))) == cfg
    plain = ModelConfig(depth=3, dilations=(1, 1, 1))
    assert plain == ModelConfig(depth=3) and "dilations" not in plain.to_dict()
    assert ModelConfig(depth=3).trunk_dilations() == (1, 1, 1)
    with pytest.raises(ValueError, match="a unet network's trunk is not one stack"):
        ModelConfig(arch="unet").trunk_dilations()


def test_dilated_preset_is_cpu_with_a_dilated_trunk():
    dilated, cpu = TrainConfig.from_preset("dilated"), TrainConfig.from_preset("cpu")
    assert dilated.model.trunk_dilations() == (1, 2, 4, 8, 4, 2, 1)
    assert trunk_radius(dilated.model) == 22 == receptive_radius(dilated.model)
    assert dilated.model == dataclasses.replace(cpu.model, dilations=(1, 2, 4, 8, 4, 2, 1))
    assert {k: v for k, v in dilated.to_dict().items() if k not in ("model", "preset")} == \
        {k: v for k, v in cpu.to_dict().items() if k not in ("model", "preset")}


def test_unet_fields_resolve_and_round_trip():
    cfg = ModelConfig(arch="unet")
    assert (cfg.levels, cfg.width_growth, cfg.width_cap) == (4, 1.5, 96)
    assert cfg.unet_widths() == (32, 48, 72, 96)
    assert ModelConfig(arch="unet", width=20, levels=3, width_growth=2.0).unet_widths() == (20, 40, 60)
    assert ModelConfig(arch="unet", width=8, width_growth=1.0).unet_widths() == (8, 8, 8, 8)
    d = ModelConfig(arch="unet", levels=2, width_cap=40).to_dict()
    assert (d["levels"], d["width_growth"], d["width_cap"]) == (2, 1.5, 40)
    assert ModelConfig.from_dict(d) == ModelConfig(arch="unet", levels=2, width_cap=40)
    with pytest.raises(ValueError, match="kpcn network has no levels"):
        ModelConfig().unet_widths()


def test_unet_preset_is_cpus_training_at_a_lower_rate_with_a_four_level_unet():
    unet, cpu = TrainConfig.from_preset("unet"), TrainConfig.from_preset("cpu")
    assert unet.model.unet_widths() == (32, 48, 72, 96)
    assert (unet.model.depth, unet.model.kernel_size, unet.model.conv_size) == (1, 13, 3)
    assert unet.learning_rate == 3e-4 < cpu.learning_rate  # cpu's saturated its specular kernels (train.frozen)
    mine = ("model", "preset", "learning_rate")
    assert {k: v for k, v in unet.to_dict().items() if k not in mine} == \
        {k: v for k, v in cpu.to_dict().items() if k not in mine}
    assert set(PRESETS["unet"]) == {"model", "learning_rate"}
    with pytest.raises(OptionError, match="^levels is a setting of arch unet alone"):
        TrainConfig.from_preset("cpu", model={"levels": 3})


def test_each_quality_mode_trains_from_a_preset_and_fast_costs_a_fraction_of_balanced():
    assert set(QUALITY_PRESETS) == set(QUALITY_MODES) and set(QUALITY_PRESETS.values()) <= set(PRESETS)
    assert set(QUALITY_AUXILIARIES) == set(QUALITY_MODES)
    assert set(QUALITY_AUXILIARIES.values()) <= set(auxiliary.TRAINED)
    assert QUALITY_AUXILIARIES["balanced"] == TrainConfig().auxiliaries  # make model's networks, as trained
    # balanced is kpcn's networks alone, the default whether or not pyoidn is installed
    assert set(QUALITY_OIDN_MIX) <= set(QUALITY_MODES) and "balanced" not in QUALITY_OIDN_MIX
    fast, balanced = (TrainConfig.from_preset(QUALITY_PRESETS[m]).model for m in ("fast", "balanced"))

    def multiply_adds(cfg):  # a stack of conv_size² convolutions, then the 1x1 kernel head
        taps, w = cfg.conv_size ** 2, cfg.width
        return taps * (cfg.in_channels * w + (cfg.depth - 1) * w * w) + w * cfg.kernel_size ** 2

    assert fast.arch == balanced.arch == "kpcn" and fast.kernel_size < balanced.kernel_size
    assert multiply_adds(fast) < 0.25 * multiply_adds(balanced)
    # the count above is the network's own: its weights are the multiply-adds a pixel, less the biases
    net = build_branch_model(fast)
    assert net.count_params() - fast.depth * fast.width - fast.kernel_size ** 2 == multiply_adds(fast)


def test_a_mode_started_from_another_modes_networks_has_their_architecture():
    # make modes passes --init models/<model> for these, which refuses networks of another configuration
    assert set(QUALITY_INIT) <= set(QUALITY_MODES) and set(QUALITY_INIT.values()) <= set(QUALITY_MODES)
    for mode, source in QUALITY_INIT.items():
        assert mode != source
        ours, theirs = (TrainConfig.from_preset(QUALITY_PRESETS[m]).model for m in (mode, source))
        assert ours.to_dict() == theirs.to_dict()


def test_from_dict_rejects_unknown_keys():
    with pytest.raises(ValueError, match="kernal_size"):
        ModelConfig.from_dict({"kernal_size": 5})


# ---------------------------------------------------------------- shapes and initial behaviour


@pytest.mark.parametrize("arch", ARCHS)
def test_shapes_any_size(arch):
    model = build_branch_model(tiny(arch), name="diffuse")
    assert model.input_shape == (None, None, None, 27)
    assert model.inputs[0].name == "features"
    for shape in [(2, 20, 24, 27), (1, 7, 9, 27), (1, 33, 17, 27), (1, 3, 2, 27)]:
        out = predict(model, features(shape))
        assert out.shape == shape[:3] + (3,)
        assert np.isfinite(out).all()


def test_default_config_shapes():
    model = build_branch_model(ModelConfig(), name="specular")
    assert model.name == "specular"
    assert predict(model, features((2, 20, 24, 27))).shape == (2, 20, 24, 3)


def box_filter(colour, k):
    r = k // 2
    h, w = colour.shape[1:3]
    padded = np.pad(colour.astype(np.float64), ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
    out = np.zeros(colour.shape, np.float64)
    for i in range(k):
        for j in range(k):
            out += padded[:, i : i + h, j : j + w]
    return out / (k * k)


@pytest.mark.parametrize("arch", ["kpcn", "kpal", "unet"])
def test_untrained_kernel_model_is_box_filter(arch):
    model = build_branch_model(tiny(arch))
    x = features((2, 9, 11, 27), seed=1)  # odd: the unet pads to 16 x 16 and crops the logits back
    np.testing.assert_allclose(predict(model, x), box_filter(x[..., :3], 5), rtol=1e-5, atol=1e-5)


def test_untrained_dpcn_is_identity_on_log_colours():
    model = build_branch_model(tiny("dpcn"))
    x = features((2, 9, 11, 27), seed=1)
    x[..., :3] = np.abs(x[..., :3])  # the colour features are log(1 + x) >= 0
    np.testing.assert_array_equal(predict(model, x), x[..., :3])


# ---------------------------------------------------------------- receptive field


@pytest.mark.slow
@pytest.mark.parametrize(
    "cfg",
    [
        tiny("kpcn", depth=3, kernel_size=3),  # trunk (3) dominates
        tiny("kpcn", depth=1, kernel_size=7),  # kernel (3) dominates
        tiny("kpal", depth=1, kernel_size=3),  # 3 convs -> 3
        tiny("dpcn", depth=2, conv_size=5),  # 2 * 2 = 4
        tiny("kpcn", depth=3, kernel_size=3, dilations=[1, 3, 2]),  # 1 + 3 + 2 = 6
    ],
)
def test_receptive_radius_is_exact(cfg):
    radius = receptive_radius(cfg)
    model = build_branch_model(cfg)
    randomise(model, seed=5)
    size, c = 2 * radius + 7, radius + 3
    x = features((1, size, size, 27), seed=2)
    base = predict(model, x)[0, c, c]
    for dy, dx in [(radius + 1, 0), (0, -(radius + 1)), (radius + 1, radius + 1), (-(radius + 2), 1)]:
        y = x.copy()
        y[0, c + dy, c + dx] += 5.0
        np.testing.assert_array_equal(predict(model, y)[0, c, c], base)
    changed = 0
    for dy, dx in [(radius, 0), (0, -radius), (-radius, radius), (radius, -1)]:
        y = x.copy()
        y[0, c + dy, c + dx] += 5.0
        changed += not np.array_equal(predict(model, y)[0, c, c], base)
    assert changed >= 3  # a ReLU may mask one path; the bound must be reached, not just respected


def _probed_radius(model, cfg, seeds=(11, 12)) -> int:
    """The largest Chebyshev distance from an output pixel to an input pixel its gradient reaches, over one
    output pixel at every offset of the pooling grid (along the diagonal: each axis sees every offset), in
    a frame large enough that no border is reached; the union over a few random inputs, so that a ReLU off
    at one input does not hide a path."""
    radius, align = trunk_radius(cfg), input_alignment(cfg)
    base = radius + 2 * align
    size = 2 * base + align
    reached = 0
    for seed in seeds:
        x = torch.tensor(features((1, size, size, 27), seed=seed), requires_grad=True)
        out = model(x, training=False)
        for offset in range(align):
            c = base + offset
            (grad,) = torch.autograd.grad(out[0, c, c].sum(), x, retain_graph=True)
            ys, xs = np.nonzero(to_np(grad[0]).any(axis=-1))
            reached = max(reached, int(np.abs(ys - c).max()), int(np.abs(xs - c).max()))
    return reached


@pytest.mark.parametrize(
    "kw",
    [
        dict(levels=2, depth=1, conv_size=3),  # (1 + 1) * 1 + 1 * 3 = 5
        dict(levels=3, depth=2, conv_size=3),  # 3 * 3 + 2 * 7 = 23
        dict(levels=3, depth=1, conv_size=5),  # 3 * 3 + 2 * 7 = 23
        dict(levels=4, depth=1, conv_size=3),  # the preset's trunk: 2 * 7 + 15 = 29
    ],
)
def test_unet_receptive_radius_is_the_probed_one(kw):
    cfg = ModelConfig(arch="unet", width=8, kernel_size=3, **kw)
    model = build_branch_model(cfg)
    randomise(model, seed=5, scale=0.1)  # moderate logits: a saturated softmax would pass no gradient back
    a, coarsest = cfg.depth * (cfg.conv_size // 2), 2 ** (cfg.levels - 1)
    assert trunk_radius(cfg) == (a + 1) * (coarsest - 1) + a * (2 * coarsest - 1)
    assert _probed_radius(model, cfg) == trunk_radius(cfg) == receptive_radius(cfg)


@pytest.mark.slow
def test_the_dilated_presets_trunk_reaches_every_pixel_of_its_field_and_no_further():
    """1, 2, 4, 8, 4, 2, 1 leave no gridding holes: every input pixel within the radius moves the output pixel."""
    cfg = ModelConfig(width=8, kernel_size=3, dilations=[1, 2, 4, 8, 4, 2, 1])
    model = build_branch_model(cfg)
    randomise(model, seed=5, scale=0.1)
    radius, size = trunk_radius(cfg), 2 * trunk_radius(cfg) + 9
    c = size // 2
    reached = np.zeros((size, size), bool)
    for seed in (11, 12):
        x = torch.tensor(features((1, size, size, 27), seed=seed), requires_grad=True)
        (grad,) = torch.autograd.grad(model(x, training=False)[0, c, c].sum(), x)
        reached |= to_np(grad[0]).any(axis=-1)
    ys, xs = np.nonzero(reached)
    assert int(np.abs(ys - c).max()) == int(np.abs(xs - c).max()) == radius == 22
    assert reached[c - radius : c + radius + 1, c - radius : c + radius + 1].all()


def test_radius_formulas():
    assert trunk_radius(ModelConfig()) == 7
    assert receptive_radius(ModelConfig()) == 7
    assert receptive_radius(ModelConfig(kernel_size=21)) == 10
    assert trunk_radius(ModelConfig(arch="kpal", depth=13)) == 27
    assert receptive_radius(ModelConfig(arch="unet", depth=1)) == 29  # the unet preset
    assert receptive_radius(ModelConfig(arch="unet", depth=1, levels=2, kernel_size=21)) == 10  # the kernel's
    assert [input_alignment(ModelConfig(arch=a)) for a in ("kpcn", "kpal", "dpcn")] == [1, 1, 1]
    assert [input_alignment(ModelConfig(arch="unet", levels=n)) for n in (2, 4, 6)] == [2, 8, 32]


# ---------------------------------------------------------------- save / load, kernels


@pytest.mark.slow
@pytest.mark.parametrize("arch, kw", [(arch, {}) for arch in ARCHS] + [("kpcn", {"dilations": [2, 3]})],
                         ids=[*ARCHS, "kpcn-dilated"])
def test_save_load_round_trip(arch, kw, tmp_path):
    cfg = tiny(arch, dropout=0.2, **kw)
    model = build_branch_model(cfg, name="diffuse")
    randomise(model, seed=3)
    x = features((2, 10, 12, 27), seed=4)
    before = predict(model, x)
    path = tmp_path / "model.keras"
    model.save(path)
    loaded = keras.models.load_model(path)  # no custom_objects: the kpcn layers are registered
    np.testing.assert_array_equal(predict(loaded, x), before)
    assert loaded.name == "diffuse"
    assert [type(layer) for layer in loaded.layers] == [type(layer) for layer in model.layers]


@pytest.mark.slow
@pytest.mark.parametrize("arch", ARCHS)
def test_channels_last_saved_models_load_and_agree_with_the_channels_first_layout(arch, tmp_path):
    """A model saved with the old channels-last convolutions loads and runs as before, and the default
    (channels-first inside) model with its weights gives the same output; batch norm in training mode too."""
    cfg = tiny(arch, batchnorm=True) if arch != "kpal" else tiny(arch)
    old = build_branch_model(cfg, data_format="channels_last")
    assert all(getattr(layer, "data_format", "channels_last") == "channels_last" for layer in old.layers)
    randomise(old, seed=8)
    old.save(tmp_path / "old.keras")
    loaded = keras.models.load_model(tmp_path / "old.keras")
    new = build_branch_model(cfg)
    assert {layer.data_format for layer in new.layers if hasattr(layer, "data_format")} == {"channels_first"}
    new.set_weights(loaded.get_weights())
    x = features((2, 9, 11, 27), seed=9)
    np.testing.assert_array_equal(predict(loaded, x), predict(old, x))
    np.testing.assert_allclose(predict(new, x), predict(old, x), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(to_np(new(x, training=True)), to_np(old(x, training=True)), rtol=1e-5, atol=1e-5)


def test_bad_data_format_raises_with_value():
    with pytest.raises(ValueError, match="'nhwc'"):
        build_branch_model(tiny("kpcn"), data_format="nhwc")


@pytest.mark.parametrize("arch", ["kpcn", "kpal"])
def test_kernel_model_sums_to_one_and_reproduces_output(arch, tmp_path):
    cfg = tiny(arch)
    model = build_branch_model(cfg)
    randomise(model, seed=6, scale=1.0)
    model.save(tmp_path / "m.keras")
    model = keras.models.load_model(tmp_path / "m.keras")
    x = features((2, 8, 10, 27), seed=7)
    kernels = predict(build_kernel_model(model), x)
    assert kernels.shape == (2, 8, 10, cfg.kernel_size**2)
    assert (kernels >= 0).all()
    np.testing.assert_allclose(kernels.sum(axis=-1), 1.0, rtol=1e-5)
    assert kernels.std() > 1e-3  # not the untrained box filter
    again = to_np(apply_kernels(x[..., :3], kernels, cfg.kernel_size))
    np.testing.assert_allclose(again, predict(model, x), rtol=1e-5, atol=1e-5)


def test_kernel_model_rejects_dpcn():
    with pytest.raises(ValueError, match="KernelApply"):
        build_kernel_model(build_branch_model(tiny("dpcn")))


# ---------------------------------------------------------------- learning


def synthetic_batch(seed, n=4, size=16):
    """Piecewise-constant log colour with a vertical edge, noisy copy, and a clean edge-indicator feature."""
    rng = np.random.default_rng(seed)
    feats = np.zeros((n, size, size, 27), np.float32)
    gt = np.zeros((n, size, size, 3), np.float32)
    for b in range(n):
        edge = rng.integers(4, size - 4)
        left, right = rng.uniform(0.1, 1.0, 3), rng.uniform(1.5, 3.0, 3)
        gt[b, :, :edge] = left
        gt[b, :, edge:] = right
        feats[b, :, edge:, 3:6] = 1.0  # like an albedo/normal buffer that shows the edge noise-free
    feats[..., :3] = gt + rng.normal(scale=0.3, size=gt.shape)
    return feats, gt


@pytest.mark.slow
@pytest.mark.parametrize("arch", ARCHS)
def test_adam_steps_reduce_loss(arch):
    keras.utils.set_random_seed(1234)
    model = build_branch_model(tiny(arch, width=8))
    model.compile(optimizer=keras.optimizers.Adam(learning_rate=1e-2), loss=SMAPE())
    x, y = synthetic_batch(0)
    loss0 = float(model.evaluate(x, y, verbose=0))
    for _ in range(40):
        model.train_on_batch(x, y)
    loss1 = float(model.evaluate(x, y, verbose=0))
    assert np.isfinite(loss1)
    assert loss1 < 0.85 * loss0, (loss0, loss1)


# ---------------------------------------------------------------- hard numbers (from test_numerics)

TINY = {"width": 4, "depth": 2, "kernel_size": 3}


@pytest.mark.parametrize("content", ["constant", "extreme"])
@pytest.mark.parametrize("size", [1, 6])
def test_batch_norm_with_a_batch_of_one_keeps_loss_gradients_and_statistics_finite(size, content):
    keras.utils.set_random_seed(0)
    model = build_branch_model(ModelConfig(arch="kpal", **TINY))
    assert any(isinstance(layer, keras.layers.BatchNormalization) for layer in model.layers)
    randomise(model, seed=1, scale=0.5)
    if content == "constant":  # zero batch variance in every channel
        x = np.zeros((1, size, size, NUM_FEATURES), np.float32)
        x[..., :3] = 1.0
    else:
        x = extreme_features((1, size, size), seed=2)
    gt = np.full((1, size, size, 3), 0.5, np.float32)
    out = to_np(finite_loss_and_gradients(model, x, gt, x[..., :3]))
    assert out.min() >= 0 and out.max() <= LOG_COLOUR_MAX
    model.compile(optimizer=keras.optimizers.Adam(1e-3, clipnorm=1.0), loss=SMAPE())
    for _ in range(2):
        assert np.isfinite(float(model.train_on_batch(x, gt)))
    for w in model.weights:
        value = to_np(w.value)
        assert np.isfinite(value).all(), w.path
        if "moving_variance" in w.path:
            assert value.min() >= 0, w.path
    assert np.isfinite(to_np(model(x, training=False))).all()


def test_dpcn_output_is_clamped_to_the_log_colour_range_at_extreme_inputs():
    model = build_branch_model(ModelConfig(arch="dpcn", **TINY))
    x = extreme_features((2, 9, 9), seed=3)
    x[0, 0, 0, :3] = LOG_COLOUR_MAX
    # untrained: the identity on the colour, which maps back to float32 max, not to inf
    out = to_np(model(x, training=False))
    np.testing.assert_array_equal(out, x[..., :3])
    assert np.isfinite(exr.to_float32(colour.diffuse_from_log(out, np.zeros_like(out)))).all()
    randomise(model, seed=4, scale=1.0)  # corrections far beyond the colour range, both ways
    out = to_np(finite_loss_and_gradients(model, x, np.zeros_like(x[..., :3]), x[..., :3]))
    assert out.min() == 0.0 and out.max() == np.float32(LOG_COLOUR_MAX)
    linear = colour.diffuse_from_log(out, np.ones_like(out))  # the largest albedo multiplier
    assert np.isfinite(linear).all() and np.isfinite(exr.to_float32(linear)).all()
