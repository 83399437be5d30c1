"""Multiscale module's models, against float64 numpy: the α regulariser and the per-scale supervision in the
loss, the whole model (save/load, odd sizes, frozen denoiser, a shared compositor), its receptive radius and
tiling."""

import warnings

import keras
import numpy as np
import pytest
import torch
from helpers.multiscale import bicubic_down, down, run, tiny_compositor, to_np
from helpers.networks import randomise

from kpcn_keras.losses import SMAPE
from kpcn_keras.models import ModelConfig, build_branch_model, receptive_radius
from kpcn_keras.multiscale import (
    AlphaRegulariser,
    CompositorConfig,
    InferenceOnly,
    ScaleBlend,
    ScaleSupervision,
    alignment,
    alpha_maps,
    build_alpha_model,
    build_compositor,
    build_multiscale_model,
    compositor_of,
    denoiser_of,
    image_pyramid,
    multiscale_output,
    multiscale_radius,
)

TINY_DENOISER = ModelConfig(width=6, depth=2, kernel_size=3)


def features(shape, seed=0, channels=27):
    """Plausible feature values: everything in [0, 2] (log colours and relvars are >= 0)."""
    return np.random.default_rng(seed).uniform(0.0, 2.0, size=tuple(shape) + (channels,)).astype(np.float32)


def multiscale(kind="alpha", seed=3, dropout=0.0, **kw):
    denoiser = build_branch_model(ModelConfig(width=6, depth=2, kernel_size=3, dropout=dropout))
    model = build_multiscale_model(denoiser, tiny_compositor(kind, **kw))
    randomise(model, seed=seed)
    return model



# ---------------------------------------------------------------- α regulariser


@pytest.mark.parametrize("mean", [0.3, 0.7])
def test_alpha_regulariser_value_and_gradient(mean):
    gamma = 0.25
    rng = np.random.default_rng(8)
    values = rng.uniform(-0.2, 0.2, size=(2, 4, 5, 1))
    values += mean - values.mean()
    alpha = torch.tensor(values, dtype=torch.float32, requires_grad=True)
    layer = AlphaRegulariser(gamma)
    out = layer(alpha)
    assert out is alpha or torch.equal(out, alpha)
    (loss,) = layer.losses
    np.testing.assert_allclose(float(loss.detach()), gamma * max(0.5 - mean, 0.0), rtol=1e-5, atol=1e-7)
    loss.backward()
    want = -gamma / values.size if mean < 0.5 else 0.0
    np.testing.assert_allclose(to_np(alpha.grad), want, rtol=1e-6, atol=0)


def test_alpha_regulariser_is_part_of_the_fit_loss():
    gamma, lr, bias = 0.5, 1.0, -1.0
    x = keras.Input(shape=(None, None, 1))
    head = keras.layers.Conv2D(1, 1, activation="sigmoid", kernel_initializer="zeros",
                               bias_initializer=keras.initializers.Constant(bias), name="alpha")
    model = keras.Model(x, AlphaRegulariser(gamma)(head(x)))
    model.compile(optimizer=keras.optimizers.SGD(lr), loss=lambda y_true, y_pred: keras.ops.mean(y_pred) * 0.0)
    zeros = np.zeros((2, 3, 4, 1), np.float32)
    s = 1.0 / (1.0 + np.exp(-bias))
    loss = model.train_on_batch(zeros, zeros)
    np.testing.assert_allclose(loss, gamma * (0.5 - s), rtol=1e-5)
    # d loss / d bias = -gamma * s (1 - s): SGD moves the bias up by lr times that
    np.testing.assert_allclose(to_np(head.bias.value), [bias + lr * gamma * s * (1 - s)], rtol=1e-5)


@pytest.mark.slow
@pytest.mark.parametrize("levels", [2, 3])
def test_multiscale_loss_is_smape_plus_one_term_per_compositor_application(levels):
    gamma, bias = 0.5, -1.0
    model = multiscale("alpha", levels=levels, gamma=gamma)
    head = compositor_of(model).get_layer("compositor_alpha")
    head.kernel.assign(np.zeros(head.kernel.shape, np.float32))
    head.bias.assign(np.full(head.bias.shape, bias, np.float32))
    x = features((2, 12, 12))
    y = np.random.default_rng(9).uniform(0, 2, size=(2, 12, 12, 3)).astype(np.float32)
    model.compile(optimizer="sgd", loss=SMAPE())
    pred = run(model, x).astype(np.float64)
    assert len(model.losses) == levels - 1
    smape = np.mean(np.abs(pred - y) / (np.abs(pred) + np.abs(y) + 0.01))
    s = 1.0 / (1.0 + np.exp(-bias))
    want = smape + (levels - 1) * gamma * (0.5 - s)
    np.testing.assert_allclose(model.evaluate(x, y, verbose=0), want, rtol=1e-5)


# ---------------------------------------------------------------- per-scale supervision


def smape64(gt, out):
    return np.mean(np.abs(out - gt) / (np.abs(out) + np.abs(gt) + 0.01))


@pytest.mark.parametrize("downsample", ["average", "bicubic"])
def test_per_scale_supervision_adds_the_weighted_loss_of_every_inner_level(downsample):
    """4 levels: the inner levels 1 and 2 each compared with the target padded (to 8) and taken down the same
    pyramid, weight w each; numpy float64 computes the terms; the output passes unchanged."""
    weight = 0.7
    cfg = CompositorConfig(levels=4, downsample=downsample, scale_supervision=weight)
    rng = np.random.default_rng(18)
    target = rng.uniform(0, 2, size=(2, 13, 11, 3))  # odd: padded at the bottom and right by edge replication
    colours = [rng.uniform(0, 2, size=(2, 16 >> level, 16 >> level, 3)) for level in (1, 2)]
    inputs = [keras.Input(shape=(None, None, 3)) for _ in range(4)]
    output, target_in, *colour_in = inputs
    targets = image_pyramid(target_in, cfg, "target_pyramid")
    layer = ScaleSupervision(SMAPE(), cfg.scale_supervision)
    pairs = [t for level in (1, 2) for t in (targets[level], colour_in[level - 1])]
    model = keras.Model(inputs, layer([output, *pairs]))
    fine = rng.uniform(0, 2, size=(2, 13, 11, 3)).astype(np.float32)
    got = run(model, fine, target, *colours)
    np.testing.assert_array_equal(got, fine)
    taken = np.pad(target, ((0, 0), (0, 3), (0, 5), (0, 0)), mode="edge")
    want = 0.0
    for colour in colours:
        taken = down(taken) if downsample == "average" else bicubic_down(taken)
        want += weight * smape64(taken, colour)
    (loss,) = model.losses
    np.testing.assert_allclose(float(to_np(loss)), want, rtol=1e-5)
    # in fit's loss: the compiled loss on the output plus the terms
    model.compile(optimizer="sgd", loss=SMAPE())
    y = rng.uniform(0, 2, size=(2, 13, 11, 3)).astype(np.float32)
    evaluated = model.evaluate([fine, target.astype(np.float32), *(c.astype(np.float32) for c in colours)], y,
                               verbose=0)
    np.testing.assert_allclose(evaluated, smape64(y, fine) + want, rtol=1e-5)


def test_multiscale_output_gives_the_composite_outputs_of_the_inner_levels():
    cfg = tiny_compositor("kernel", levels=4)
    compositor = build_compositor(cfg)
    features_in = keras.Input(shape=(None, None, 27))
    levels = []
    out = multiscale_output(features_in, build_branch_model(TINY_DENOISER), cfg, compositor, levels=levels)
    model = keras.Model(features_in, [out, *levels])
    randomise(model, seed=19)
    got = run(model, features((1, 21, 19), seed=20))
    assert [g.shape for g in got] == [(1, 21, 19, 3), (1, 12, 12, 3), (1, 6, 6, 3)]  # padded to 24, halved
    blends = [layer.output for layer in model.layers if isinstance(layer, ScaleBlend)]  # coarsest first
    want = run(keras.Model(features_in, blends[:2]), features((1, 21, 19), seed=20))
    for g, w in zip(got[1:], reversed(want)):
        np.testing.assert_array_equal(g, w)


# ---------------------------------------------------------------- the whole model


@pytest.mark.slow
@pytest.mark.parametrize("kind,extra", [("alpha", {}), ("kernel", {}), ("alpha", dict(downsample="bicubic")),
                                        ("kernel", dict(kernel_size=21, downsample="bicubic"))])
def test_multiscale_model_save_load_identical(kind, extra, tmp_path):
    model = multiscale(kind, **extra)
    x = features((2, 13, 10), seed=1)
    before = run(model, x)
    model.save(tmp_path / "ms.keras")
    loaded = keras.models.load_model(tmp_path / "ms.keras")
    np.testing.assert_array_equal(run(loaded, x), before)
    assert [type(la) for la in loaded.layers] == [type(la) for la in model.layers]
    assert len(loaded.trainable_weights) == len(compositor_of(model).weights)
    assert not denoiser_of(loaded).trainable
    pair = before[:, :4, :4], before[:, 4:8, 4:8]  # the compositor alone, as a run's component is used
    for got, want in zip(run(compositor_of(loaded), *pair), run(compositor_of(model), *pair)):
        np.testing.assert_array_equal(got, want)


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["alpha", "kernel"])
def test_odd_sizes_come_back_full_size_with_alpha_maps_per_level(kind):
    model = multiscale(kind)
    x = features((1, 65, 65), seed=2)
    out = run(model, x)
    assert out.shape == (1, 65, 65, 3) and np.isfinite(out).all()
    maps = [to_np(a) for a in build_alpha_model(model)(x)]
    assert [a.shape for a in maps] == [(1, 65, 65, 1), (1, 33, 33, 1)]
    assert all(((a >= 0) & (a <= 1)).all() and a.std() > 1e-3 for a in maps)


def test_alpha_model_is_finest_first_and_shares_weights():
    model = multiscale("kernel", levels=3)
    head = compositor_of(model).get_layer("compositor_alpha")
    head.kernel.assign(np.zeros(head.kernel.shape, np.float32))
    head.bias.assign(np.array([0.8], np.float32))
    maps = [to_np(a) for a in build_alpha_model(model)(features((2, 17, 9)))]
    assert [a.shape for a in maps] == [(2, 17, 9, 1), (2, 9, 5, 1)]
    np.testing.assert_allclose(np.concatenate([a.ravel() for a in maps]), 1 / (1 + np.exp(-0.8)), rtol=1e-6)


@pytest.mark.parametrize("levels, shapes", [(2, [(2, 17, 9, 1)]), (3, [(2, 17, 9, 1), (2, 9, 5, 1)])])
def test_alpha_maps_are_a_list_finest_first_at_every_level_count(levels, shapes):
    # with 2 levels the α model has one output, which Keras returns bare: kpcn figures iterated over its batch
    maps = alpha_maps(multiscale("kernel", levels=levels), features((2, 17, 9)))
    assert isinstance(maps, list) and [m.shape for m in maps] == shapes
    assert all(isinstance(m, np.ndarray) and ((m >= 0) & (m <= 1)).all() for m in maps)


def test_alpha_zero_returns_the_single_scale_denoiser_exactly():
    model = multiscale("alpha")
    head = compositor_of(model).get_layer("compositor_alpha")
    head.kernel.assign(np.zeros(head.kernel.shape, np.float32))
    head.bias.assign(np.array([-200.0], np.float32))  # sigmoid underflows to exactly 0
    x = features((2, 24, 16), seed=4)  # multiples of the alignment: no padding
    np.testing.assert_array_equal(run(model, x), run(denoiser_of(model), x))


@pytest.mark.slow
def test_training_the_compositor_leaves_the_denoiser_bit_identical():
    model = multiscale("kernel", seed=5)
    denoiser, compositor = denoiser_of(model), compositor_of(model)
    assert not denoiser.trainable
    frozen = [to_np(v.value).copy() for v in denoiser.weights]
    comp_before = [to_np(v.value).copy() for v in compositor.weights]
    assert {id(v) for v in model.trainable_weights} == {id(v) for v in compositor.trainable_weights}
    model.compile(optimizer=keras.optimizers.Adam(1e-2), loss=SMAPE())
    x = features((4, 16, 16), seed=6)
    y = np.random.default_rng(7).uniform(0, 2, size=(4, 16, 16, 3)).astype(np.float32)
    model.fit(x, y, batch_size=2, epochs=2, verbose=0)
    for before, v in zip(frozen, denoiser.weights):
        np.testing.assert_array_equal(to_np(v.value), before)
    changed = [not np.array_equal(b, to_np(v.value)) for b, v in zip(comp_before, compositor.weights)]
    assert all(changed), changed


def test_denoiser_runs_in_inference_mode_while_training():
    model = multiscale("alpha", dropout=0.5)
    x = features((1, 16, 16), seed=8)
    a, b = run(model, x, training=True), run(model, x, training=True)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, run(model, x))
    # without the wrapper a nested model inherits fit's training=True and its dropout is live
    inp = keras.Input(shape=(None, None, 27))
    raw = keras.Model(inp, denoiser_of(model)(inp))
    assert not np.array_equal(run(raw, x, training=True), run(raw, x, training=True))


def test_compositor_can_be_shared_and_must_fit_the_config():
    cfg = tiny_compositor("kernel")
    shared = build_compositor(cfg)
    den = build_branch_model(TINY_DENOISER)
    a = build_multiscale_model(den, cfg, name="a", compositor=shared)
    b = build_multiscale_model(den, cfg, name="b", compositor=shared)
    assert compositor_of(a) is compositor_of(b) is shared
    with pytest.raises(ValueError, match="'alpha'"):
        build_multiscale_model(den, tiny_compositor("alpha"), compositor=shared)
    with pytest.raises(ValueError, match=r"\(None, None, None, 4\)"):
        build_multiscale_model(build_branch_model(ModelConfig(in_channels=4)), cfg)


@pytest.mark.slow
def test_flat_two_branch_model_sharing_compositor_and_denoiser_reloads(tmp_path):
    cfg = tiny_compositor("kernel")
    compositor = build_compositor(cfg)
    shared = InferenceOnly(build_branch_model(TINY_DENOISER), name="shared")
    inputs = [keras.Input(shape=(None, None, 27), name=n) for n in ("d", "s")]
    outs = [multiscale_output(i, shared, cfg, compositor, prefix=f"{i.name}_") for i in inputs]
    model = keras.Model(inputs, keras.layers.Add()(outs))
    randomise(model, seed=9)
    x = [features((1, 13, 10), seed=s) for s in (10, 11)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # Keras only warns when it skips weights it cannot place
        model.save(tmp_path / "flat.keras")
        loaded = keras.models.load_model(tmp_path / "flat.keras")
    np.testing.assert_array_equal(run(loaded, *x), run(model, *x))
    assert len(loaded.weights) == len(model.weights)


# ---------------------------------------------------------------- receptive radius and tiling


@pytest.mark.slow
@pytest.mark.parametrize(
    "kind,levels,extra",
    [("alpha", 2, {}), ("kernel", 3, {}), ("kernel", 2, dict(depth=2, kernel_size=5)), ("alpha", 3, dict(depth=1)),
     ("kernel", 2, dict(kernel_size=21))],
)
def test_radius_bound_holds_and_is_reached(kind, levels, extra):
    model = multiscale(kind, seed=11, levels=levels, **extra)
    cfg = tiny_compositor(kind, levels=levels, **extra)
    radius = multiscale_radius(receptive_radius(TINY_DENOISER), cfg)
    a = alignment(cfg)
    size = 2 * radius + 2 * a + 4
    x = features((1, size, size), seed=12)
    base = run(model, x)[0]
    reached = 0
    for offset in range(a):  # every phase of the centre relative to the pyramid blocks
        c = radius + 2 + offset
        for dy, dx in [(radius + 1, 0), (0, -(radius + 1)), (-(radius + 1), radius + 1), (radius + 1, -3)]:
            y = x.copy()
            y[0, c + dy, c + dx] += 3.0
            np.testing.assert_array_equal(run(model, y)[0, c, c], base[c, c])
        for dy, dx in [(radius, 0), (-radius, 0), (0, radius), (0, -radius)]:
            y = x.copy()
            y[0, c + dy, c + dx] += 3.0
            reached += not np.array_equal(run(model, y)[0, c, c], base[c, c])
    assert reached >= 2  # the bound is exact for some centre phase, not merely respected


@pytest.mark.slow
@pytest.mark.parametrize("kind,extra", [("alpha", {}), ("alpha", dict(downsample="bicubic")),
                                        ("kernel", dict(kernel_size=21, downsample="bicubic"))])
def test_radius_bound_is_the_reach_of_the_gradient(kind, extra):
    """The support of d out[c, c] / d input, over every centre phase: within R, and R for some. (The bicubic
    pyramid reaches its last pixels through its outer taps' products, (3/256)² a step: a perturbation there
    moves the output by less than float32 resolves, so the perturbation test above cannot see them.)"""
    model = multiscale(kind, seed=11, **extra)
    cfg = tiny_compositor(kind, **extra)
    radius = multiscale_radius(receptive_radius(TINY_DENOISER), cfg)
    a = alignment(cfg)
    size = 2 * radius + 2 * a + 8
    reach = []
    for offset in range(a):
        c = radius + 4 + offset
        x = torch.tensor(features((1, size, size), seed=12), requires_grad=True)
        model(x)[0, c, c].sum().backward()
        rows, cols = (np.nonzero(to_np(x.grad[0]).any(axis=(2, axis)))[0] - c for axis in (1, 0))
        reach += [-rows.min(), rows.max(), -cols.min(), cols.max()]
    assert max(reach) == radius, reach


def tiled(model, x, tile, margin, align):
    """Tiles starting at multiples of ``align``, each read with ``margin`` pixels of context (start rounded
    down to the alignment); only the tile's own pixels are kept."""
    _, h, w, _ = x.shape
    out = np.zeros(x.shape[:3] + (3,), np.float32)
    for y0 in range(0, h, tile):
        for x0 in range(0, w, tile):
            y1, x1 = min(y0 + tile, h), min(x0 + tile, w)
            ya, xa = max(0, (y0 - margin) // align * align), max(0, (x0 - margin) // align * align)
            yb, xb = min(h, y1 + margin), min(w, x1 + margin)
            pred = run(model, x[:, ya:yb, xa:xb])
            out[:, y0:y1, x0:x1] = pred[:, y0 - ya : y1 - ya, x0 - xa : x1 - xa]
    return out


@pytest.mark.slow
@pytest.mark.parametrize("kind,extra", [("alpha", {}), ("kernel", {}), ("alpha", dict(downsample="bicubic"))])
def test_aligned_tiles_with_radius_margins_reproduce_the_untiled_output(kind, extra):
    cfg = tiny_compositor(kind, **extra)
    model = multiscale(kind, seed=13, **extra)
    radius = multiscale_radius(receptive_radius(TINY_DENOISER), cfg)
    x = features((1, 45 + 2 * radius - 20, 38 + 2 * radius - 20), seed=14)
    whole = run(model, x)
    np.testing.assert_allclose(tiled(model, x, 8, radius, alignment(cfg)), whole, rtol=1e-5, atol=1e-5)
    # the alignment matters: the same margins from unaligned starts pool other 2x2 blocks
    assert np.abs(tiled(model, x, 8, radius + 1, 1) - whole).max() > 1e-3


@pytest.mark.slow
@pytest.mark.parametrize("downsample", ["average", "bicubic"])
def test_tiles_of_the_21x21_compositor_reproduce_the_untiled_output(downsample):
    """R = 4 r + (21 + b) 3 (63 past the denoiser's own reach, 72 with bicubic): tiles whose inputs are smaller
    than the image, read with margins R, give the untiled output; margins short of R do not."""
    cfg = tiny_compositor("kernel", kernel_size=21, downsample=downsample)
    model = multiscale("kernel", seed=21, kernel_size=21, downsample=downsample)
    radius = multiscale_radius(receptive_radius(TINY_DENOISER), cfg)
    assert radius == 4 * receptive_radius(TINY_DENOISER) + (21 + 3 * (downsample == "bicubic")) * 3
    size, tile = 2 * radius + 40, 24
    x = features((1, size, size - 6), seed=22)
    whole = run(model, x)
    np.testing.assert_allclose(tiled(model, x, tile, radius, alignment(cfg)), whole, rtol=1e-5, atol=1e-5)
    assert tile + 2 * radius < size - 6  # a middle tile's input is smaller than the image
    assert np.abs(tiled(model, x, tile, radius // 2 // 4 * 4, alignment(cfg)) - whole).max() > 1e-4
