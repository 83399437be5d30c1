"""Multiscale module's layers, against float64 numpy: the configuration, alignment and radius formula, dilated
kernel application, every layer's Keras contract, U, D, padding, the blend, kernel upsampling (the 21x21
compositor's offsets), and the feature pyramid (2x2 pooling and the bicubic filter)."""

import keras
import numpy as np
import pytest
import torch
from helpers.multiscale import bicubic_down, bicubic_weights, down, run, tiny_compositor, to_np, up
from helpers.networks import check_keras_layer

from kpcn_keras.config import TrainConfig
from kpcn_keras.layers import apply_kernels
from kpcn_keras.losses import SMAPE, AsymmetricSMAPE
from kpcn_keras.multiscale import (
    ALIGN,
    BICUBIC_TAPS,
    AlphaRegulariser,
    CompositorConfig,
    CropLike,
    DilatedKernelApply,
    Downsample2x,
    FeatureDownsample,
    InferenceOnly,
    PadToMultiple,
    ScaleBlend,
    ScaleSupervision,
    Upsample2x,
    alignment,
    build_compositor,
    feature_runs,
    multiscale_radius,
)
from prep.features import FEATURE_NAMES

GRADIENT = [i for i, n in enumerate(FEATURE_NAMES) if n.startswith(("dx_", "dy_"))]
RELVAR = [i for i, n in enumerate(FEATURE_NAMES) if n.startswith("relvar")]
PLAIN = [i for i, n in enumerate(FEATURE_NAMES) if i not in GRADIENT and i not in RELVAR]


# ---------------------------------------------------------------- config, alignment, radius formula


def test_config_defaults_and_round_trip():
    cfg = CompositorConfig()
    assert (cfg.kind, cfg.levels, cfg.width, cfg.depth, cfg.conv_size, cfg.kernel_size, cfg.gamma) == (
        "alpha", 3, 32, 6, 3, 5, 0.01)
    assert (cfg.downsample, cfg.scale_supervision) == ("average", 0.0)  # 2x2 pooling, no per-scale terms
    d = CompositorConfig(kind="kernel", levels=4, gamma=0).to_dict()
    assert d["gamma"] == 0.0 and isinstance(d["gamma"], float)
    assert CompositorConfig.from_dict(d) == CompositorConfig(kind="kernel", levels=4, gamma=0.0)
    # the fields added since the first runs are written only where they are not their defaults, so a record
    # of an earlier run (which lacks them) is the same run
    assert "downsample" not in d and "scale_supervision" not in d
    new = CompositorConfig(kind="kernel", kernel_size=21, downsample="bicubic", scale_supervision=1)
    assert new.to_dict()["downsample"] == "bicubic" and new.to_dict()["scale_supervision"] == 1.0
    assert CompositorConfig.from_dict(new.to_dict()) == new
    assert TrainConfig(compositor=new).to_dict()["compositor"] == new.to_dict()
    assert "downsample" not in TrainConfig(compositor={"kind": "alpha"}).to_dict()["compositor"]


def test_per_scale_supervision_is_off_by_default_and_on_in_the_compositor_phase_alone():
    off = TrainConfig(compositor={"kind": "kernel"})
    assert not any(off.supervises_scales(p) for p in off.phases())
    on = TrainConfig(compositor={"kind": "kernel", "scale_supervision": 0.5}, joint_steps=2)
    assert {p.name: on.supervises_scales(p) for p in on.phases()} == {
        "diffuse": False, "specular": False, "joint": False, "compositor": True}
    assert (on.target_channels, TrainConfig(loss="asymmetric", slope_input=True).target_channels) == (3, 7)


@pytest.mark.parametrize(
    "kw,echo",
    [
        (dict(kind="vogels"), "'vogels'"),
        (dict(levels=1), "1"),
        (dict(levels=2.0), "2.0"),
        (dict(width=0), "0"),
        (dict(depth=0), "0"),
        (dict(conv_size=4), "4"),
        (dict(kernel_size=6), "6"),
        (dict(gamma=-0.5), "-0.5"),
        (dict(gamma=float("inf")), "inf"),
        (dict(gamma="0.1"), "'0.1'"),
        (dict(kernel_size=43), "43"),
        (dict(downsample="lanczos"), "'lanczos'"),
        (dict(scale_supervision=-1.0), "-1.0"),
        (dict(scale_supervision=1.0, levels=2), "levels >= 3"),
    ],
)
def test_config_validation_echoes_value(kw, echo):
    with pytest.raises(ValueError, match=echo):
        CompositorConfig(**kw)


def test_from_dict_rejects_unknown_keys():
    with pytest.raises(ValueError, match="gama"):
        CompositorConfig.from_dict({"gama": 0.1})


def test_alignment_and_radius_formula():
    assert ALIGN == alignment(CompositorConfig()) == 4
    assert alignment(CompositorConfig(levels=2)) == 2
    # R = r 2**(L-1) + max(t + 1, 2 r_k + 1)(2**(L-1) - 1); defaults t = 5, r_k = 2 (kernel)
    assert multiscale_radius(7, CompositorConfig()) == 7 * 4 + 6 * 3
    assert multiscale_radius(7, CompositorConfig(kind="kernel", kernel_size=21)) == 7 * 4 + 21 * 3
    assert multiscale_radius(0, CompositorConfig(levels=2, depth=1)) == 1
    # bicubic reads 3 finer pixels past each 2x2 block: + 3 (2**(L-1) - 1)
    assert multiscale_radius(7, CompositorConfig(downsample="bicubic")) == 7 * 4 + (6 + 3) * 3
    assert multiscale_radius(7, CompositorConfig(kind="kernel", kernel_size=21, downsample="bicubic")) == \
        7 * 4 + (21 + 3) * 3
    with pytest.raises(ValueError, match="-1"):
        multiscale_radius(-1, CompositorConfig())


def test_feature_runs_follow_feature_names():
    assert feature_runs(27) == ((0, 3, "plain"), (3, 23, "gradient"), (23, 27, "relvar"))
    assert feature_runs(30)[-1] == (27, 30, "plain")
    with pytest.raises(ValueError, match="26"):
        feature_runs(26)


# ---------------------------------------------------------------- apply_kernels(dilation=...) (layers.py)


def reference_dilated(colour, weights, k, d):
    """float64 loops: tap (i, j) reads colour at (y + d(i - r), x + d(j - r)), coordinates clamped."""
    b_n, h_n, w_n, c_n = colour.shape
    r = k // 2
    out = np.zeros(colour.shape, np.float64)
    for b in range(b_n):
        for y in range(h_n):
            for x in range(w_n):
                for i in range(k):
                    for j in range(k):
                        sy = min(max(y + d * (i - r), 0), h_n - 1)
                        sx = min(max(x + d * (j - r), 0), w_n - 1)
                        out[b, y, x] += weights[b, y, x, i * k + j] * colour[b, sy, sx]
    return out


@pytest.mark.parametrize("k,d", [(3, 1), (3, 2), (5, 2), (3, 3)])
def test_apply_kernels_dilation_matches_numpy_loops(k, d):
    rng = np.random.default_rng(10 * k + d)
    colour = rng.normal(size=(2, 7, 6, 3))
    weights = rng.dirichlet(np.ones(k * k), size=(2, 7, 6))
    got = to_np(apply_kernels(colour.astype(np.float32), weights.astype(np.float32), k, dilation=d))
    np.testing.assert_allclose(got, reference_dilated(colour, weights, k, d), rtol=1e-5, atol=1e-5)
    if d == 1:  # the default is the undilated filter, bit for bit
        np.testing.assert_array_equal(got, to_np(apply_kernels(colour.astype(np.float32),
                                                               weights.astype(np.float32), k)))


@pytest.mark.parametrize("d", [0, -2, 1.5, True])
def test_apply_kernels_rejects_bad_dilation(d):
    with pytest.raises(ValueError, match="dilation"):
        apply_kernels(np.zeros((1, 3, 3, 3), np.float32), np.zeros((1, 3, 3, 9), np.float32), 3, dilation=d)


# ---------------------------------------------------------------- every layer: the Keras contract


def tiny_wrapped_model():
    x = keras.Input(shape=(None, None, 4))
    y = keras.layers.Conv2D(3, 3, padding="same", name="conv")(x)
    y = keras.layers.Dropout(0.5, name="drop")(y)
    return keras.Model(x, y, name="tiny")


# name -> (factory, input shapes (without batch) for an image of h x w, whether odd sizes are refused)
LAYER_CASES = {
    "PadToMultiple": (lambda: PadToMultiple(4), lambda h, w: [(h, w, 5)], False),
    "CropLike": (lambda: CropLike(2), lambda h, w: [(h + 3, w + 2, 4), (h, w, 1)], False),
    "Upsample2x": (lambda: Upsample2x(), lambda h, w: [(h, w, 3)], False),
    "Downsample2x": (lambda: Downsample2x(), lambda h, w: [(h, w, 3)], True),
    "Downsample2x-bicubic": (lambda: Downsample2x("bicubic"), lambda h, w: [(h, w, 3)], True),
    "FeatureDownsample": (lambda: FeatureDownsample(), lambda h, w: [(h, w, 29)], True),
    "FeatureDownsample-bicubic": (lambda: FeatureDownsample("bicubic"), lambda h, w: [(h, w, 29)], True),
    "ScaleBlend": (lambda: ScaleBlend(), lambda h, w: [(h, w, 3), (h, w, 3), (h, w, 1)], True),
    "DilatedKernelApply": (lambda: DilatedKernelApply(3, 2), lambda h, w: [(h, w, 3), (h, w, 9)], False),
    "AlphaRegulariser": (lambda: AlphaRegulariser(0.1), lambda h, w: [(h, w, 1)], False),
    "ScaleSupervision": (lambda: ScaleSupervision(AsymmetricSMAPE(2.0), 0.5),
                         lambda h, w: [(h, w, 3), (h, w, 6), (h, w, 3)], False),
    "InferenceOnly": (lambda: InferenceOnly(tiny_wrapped_model()), lambda h, w: [(h, w, 4)], False),
}


def layer_inputs(name, h, w, batch=2, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.uniform(0.0, 1.0, size=(batch,) + s).astype(np.float32) for s in LAYER_CASES[name][1](h, w)]


@pytest.mark.parametrize("name", sorted(LAYER_CASES))
def test_layer_keeps_the_keras_layer_contract(name, tmp_path):
    factory, shapes, _ = LAYER_CASES[name]
    check_keras_layer(factory, shapes(8, 6), tmp_path)


@pytest.mark.parametrize("name", sorted(LAYER_CASES))
@pytest.mark.parametrize("h,w", [(7, 9)])  # even sizes: in the contract above
def test_layer_output_shape_inference_at_odd_sizes(name, h, w):
    factory, _, even_only = LAYER_CASES[name]
    layer = factory()
    x = layer_inputs(name, h, w)
    shapes = [a.shape for a in x]
    if even_only and h % 2:
        with pytest.raises(ValueError, match=r"\(2, 7, 9, "):
            layer(x if len(x) > 1 else x[0])
        with pytest.raises(ValueError, match=r"\(2, 7, 9, "):
            layer.compute_output_shape(shapes if len(x) > 1 else shapes[0])
        return
    got = run(layer, *x)
    assert tuple(layer.compute_output_shape(shapes if len(x) > 1 else shapes[0])) == got.shape
    # symbolic: unknown sizes stay unknown, channels are inferred
    symbolic = [keras.KerasTensor((None, None, None, s[-1])) for s in shapes]
    out = LAYER_CASES[name][0]()(symbolic if len(x) > 1 else symbolic[0])
    assert tuple(out.shape) == (None, None, None, got.shape[-1])


def test_layers_refuse_bad_arguments_and_shapes():
    with pytest.raises(ValueError, match="0"):
        PadToMultiple(0)
    with pytest.raises(ValueError, match="-1"):
        AlphaRegulariser(-1.0)
    with pytest.raises(ValueError, match="'nearest'"):
        Downsample2x("nearest")
    with pytest.raises(ValueError, match="-0.5"):
        ScaleSupervision(SMAPE(), -0.5)
    with pytest.raises(ValueError, match="2 inputs"):
        ScaleSupervision(SMAPE(), 1.0)([np.zeros((1, 2, 2, 3), np.float32)] * 2)
    with pytest.raises(ValueError, match=r"\(1, 4, 4, 26\)"):
        FeatureDownsample()(np.zeros((1, 4, 4, 26), np.float32))
    with pytest.raises(ValueError, match=r"\(1, 4, 4, 3\).*\(1, 4, 6, 3\)"):
        ScaleBlend()([np.zeros((1, 4, 4, 3), np.float32), np.zeros((1, 4, 6, 3), np.float32),
                      np.zeros((1, 4, 4, 1), np.float32)])
    with pytest.raises(ValueError, match=r"\(1, 2, 2, 3\)"):
        CropLike(1)([np.zeros((1, 2, 2, 3), np.float32), np.zeros((1, 3, 2, 1), np.float32)])


# ---------------------------------------------------------------- U, D, padding, blend, kernel upsampling


def test_up_down_pad_and_crop_match_numpy():
    rng = np.random.default_rng(2)
    c = rng.normal(size=(2, 3, 5, 3)).astype(np.float32)
    np.testing.assert_array_equal(run(Upsample2x(), c), up(c))
    f = rng.normal(size=(2, 6, 4, 3))
    np.testing.assert_allclose(run(Downsample2x(), f), down(f), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(run(Downsample2x(), up(c)), c)  # D U c = c, bit for bit
    x = rng.normal(size=(1, 5, 7, 2)).astype(np.float32)
    padded = run(PadToMultiple(4), x)
    np.testing.assert_array_equal(padded, np.pad(x, ((0, 0), (0, 3), (0, 1), (0, 0)), mode="edge"))
    np.testing.assert_array_equal(run(CropLike(1), padded, x[..., :1]), x)
    np.testing.assert_array_equal(run(CropLike(2), padded[:, ::2, ::2], x[..., :1]), padded[:, :6:2, :8:2])


def test_scale_blend_matches_float64_reference():
    rng = np.random.default_rng(3)
    f, c = rng.normal(size=(2, 6, 8, 3)), rng.normal(size=(2, 3, 4, 3))
    alpha = rng.uniform(size=(2, 6, 8, 1))
    want = f + alpha * (up(c) - up(down(f)))
    np.testing.assert_allclose(run(ScaleBlend(), f, up(c), alpha), want, rtol=1e-5, atol=1e-5)


def test_scale_blend_alpha_zero_is_fine_and_alpha_one_takes_coarse_low_frequencies():
    rng = np.random.default_rng(4)
    f = rng.normal(size=(2, 8, 6, 3)).astype(np.float32)
    c = rng.normal(size=(2, 4, 3, 3)).astype(np.float32)
    zeros, ones = np.zeros((2, 8, 6, 1), np.float32), np.ones((2, 8, 6, 1), np.float32)
    np.testing.assert_array_equal(run(ScaleBlend(), f, up(c), zeros), f)
    out = run(ScaleBlend(), f, up(c), ones)
    np.testing.assert_allclose(down(out.astype(np.float64)), c, rtol=0, atol=1e-6)  # D U c = c, D(f - U D f) = 0
    assert np.abs(out - up(c)).max() > 0.1  # ... while the fine detail f - U D f is kept


def test_kernel_upsampling_reads_coarse_pixels_at_coarse_offsets():
    """U'c[p] = Σ_j w_p[j] c[floor(p/2) + j] (clamped), computed on the coarse image directly."""
    k = 3
    r = k // 2
    rng = np.random.default_rng(5)
    c = rng.normal(size=(1, 3, 4, 3))
    logits = rng.normal(size=(1, 6, 8, k * k)) * 2.0
    w = np.exp(logits - logits.max(-1, keepdims=True))
    w /= w.sum(-1, keepdims=True)
    want = np.zeros((1, 6, 8, 3))
    for y in range(6):
        for x in range(8):
            for i in range(k):
                for j in range(k):
                    cy = min(max(y // 2 + i - r, 0), 2)
                    cx = min(max(x // 2 + j - r, 0), 3)
                    want[0, y, x] += w[0, y, x, i * k + j] * c[0, cy, cx]
    got = run(DilatedKernelApply(k, 2), up(c), logits)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("tap", [(10, 10), (0, 0), (20, 20), (3, 17), (20, 0)])
def test_21x21_compositor_kernels_read_coarse_pixels_at_the_reports_offsets(tap):
    """Report §3.1.1: U'c[k] = Σ_j f[j] c[k/2 + j]. The compositor's kernel head with all the weight on tap
    (i, j) (row-major, centre (10, 10)) makes U'c the coarse image shifted by (i - 10, j - 10) coarse pixels,
    clamped at its edges: checked against float64 numpy through the compositor's own head and softmax."""
    k, (i, j) = 21, tap
    r = k // 2
    cfg = tiny_compositor("kernel", kernel_size=k)
    compositor = build_compositor(cfg)
    head = compositor.get_layer("compositor_kernel_logits")
    head.kernel.assign(np.zeros(head.kernel.shape, np.float32))
    bias = np.zeros(k * k, np.float32)
    bias[i * k + j] = 1e4  # the others' weight, exp(-1e4) after the max subtraction, is exactly 0
    head.bias.assign(bias)
    rng = np.random.default_rng(15)
    c = rng.normal(size=(1, 26, 24, 3))  # wider than the kernel's 21 coarse pixels: a shift is more than a clamp
    fine = rng.normal(size=(1, 52, 48, 3))
    _, logits = run(compositor, fine, up(c))
    got = run(DilatedKernelApply(k, 2), up(c), logits)
    ys = np.clip(np.arange(52)[:, None] // 2 + (i - r), 0, 25)
    xs = np.clip(np.arange(48)[None, :] // 2 + (j - r), 0, 23)
    want = c[0][ys, xs][None]
    np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)
    if (i, j) != (r, r):
        assert np.abs(got - up(c)).max() > 0.1  # a shift, not the identity


# ---------------------------------------------------------------- the feature pyramid


def pool_relvar(f):
    """float64: log1p(mean over the 2x2 block of expm1(f)) / 4)."""
    return np.log1p(down(np.expm1(f)) / 4.0)


def test_pyramid_of_constant_image():
    relvar = [0.0, 0.5, 5.0, 150.0]
    extra = [1.0, 0.0, 0.7]  # conditioning: one-hot branch, log λ
    x = np.zeros((1, 16, 12, 30), np.float32)
    x[..., :3] = [1.3, 0.2, 2.0]
    x[..., RELVAR] = relvar
    x[..., 27:] = extra
    level1 = run(FeatureDownsample(), x)
    level2 = run(FeatureDownsample(), level1)
    for level, got in ((1, level1), (2, level2)):
        assert got.shape == (1, 16 >> level, 12 >> level, 30)
        np.testing.assert_array_equal(got[..., :3], x[:, : got.shape[1], : got.shape[2], :3])
        np.testing.assert_array_equal(got[..., 27:], x[:, : got.shape[1], : got.shape[2], 27:])
        np.testing.assert_array_equal(got[..., GRADIENT], 0.0)
        want = np.asarray(relvar, np.float64)
        for _ in range(level):
            want = np.log1p(np.expm1(want) / 4.0)
        np.testing.assert_allclose(got[..., RELVAR], np.broadcast_to(want, got[..., RELVAR].shape), rtol=1e-6)


def forward_differences(buffer):
    """The feature rule: c[y, x+1] - c[y, x] and c[y+1, x] - c[y, x], 0 in the last column / row."""
    dx, dy = np.zeros_like(buffer), np.zeros_like(buffer)
    dx[:, :, :-1] = buffer[:, :, 1:] - buffer[:, :, :-1]
    dy[:, :-1] = buffer[:, 1:] - buffer[:, :-1]
    return dx, dy


def test_pyramid_gradient_of_linear_ramp_is_the_coarse_ramps_gradient():
    h, w = 16, 24
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # one ramp per gradient source (colour RGB, normal RGB, albedo RGB, depth), different slopes
    slopes = np.random.default_rng(6).uniform(-0.2, 0.2, size=(10, 2))
    buffers = np.stack([a * xx + b * yy for a, b in slopes], axis=-1)[None]
    dx, dy = forward_differences(buffers)
    x = np.zeros((1, h, w, 27))
    x[..., GRADIENT] = np.concatenate([dx, dy], axis=-1)
    level = run(FeatureDownsample(), x.astype(np.float32))
    level2 = run(FeatureDownsample(), level)
    for factor, got in ((2, level), (4, level2)):
        coarse = buffers
        for _ in range(factor // 2):
            coarse = down(coarse)
        cdx, cdy = forward_differences(coarse)
        want = np.concatenate([cdx, cdy], axis=-1)
        # interior: the last coarse column / row pools the fine rule's zero there
        np.testing.assert_allclose(got[:, :-1, :-1, GRADIENT], want[:, :-1, :-1], rtol=1e-5, atol=1e-6)
        np.testing.assert_allclose(got[:, :-1, :-1, GRADIENT[:10]],
                                   np.broadcast_to(factor * slopes[:, 0], (1, h // factor - 1, w // factor - 1, 10)),
                                   rtol=1e-5, atol=1e-6)


def test_pyramid_relvar_pools_variances_and_stays_finite():
    rng = np.random.default_rng(7)
    x = np.zeros((2, 8, 6, 27))
    # tiny, moderate, and up to the features' 300 (expm1 overflows float32 past ~88.7)
    x[..., RELVAR] = (rng.choice([1e-4, 0.3, 4.0, 19.0, 25.0, 90.0, 300.0], size=(2, 8, 6, 4))
                      * rng.uniform(0.5, 1.0, size=(2, 8, 6, 4)))
    x[..., PLAIN] = rng.uniform(0, 3, size=(2, 8, 6, len(PLAIN)))
    got = run(FeatureDownsample(), x.astype(np.float32))
    np.testing.assert_allclose(got[..., RELVAR], pool_relvar(x[..., RELVAR]), rtol=2e-6, atol=1e-7)
    np.testing.assert_allclose(got[..., PLAIN], down(x[..., PLAIN]), rtol=1e-6)
    t = torch.tensor(x, dtype=torch.float32, requires_grad=True)
    FeatureDownsample()(t).sum().backward()
    assert torch.isfinite(t.grad).all()


def test_bicubic_taps_are_keys_cubic_stretched_by_two():
    _, w = bicubic_weights()
    np.testing.assert_array_equal(np.asarray(BICUBIC_TAPS), w)
    np.testing.assert_array_equal(w * 256, [-3, -9, 29, 111, 111, 29, -9, -3])  # sums to 1, exact in float32


def test_bicubic_downsampling_matches_float64_numpy():
    f = np.random.default_rng(16).normal(size=(2, 10, 14, 3))
    np.testing.assert_allclose(run(Downsample2x("bicubic"), f), bicubic_down(f), rtol=1e-5, atol=1e-6)


def test_bicubic_downsampling_keeps_constants_and_linear_ramps():
    h, w = 16, 20
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    image = np.stack([np.full((h, w), 1.7), 0.3 * xx, -0.2 * yy + 0.1 * xx + 2.0], axis=-1)[None]
    got = run(Downsample2x("bicubic"), image)
    np.testing.assert_allclose(got[..., 0], 1.7, rtol=1e-6)  # everywhere: edge replication keeps a constant
    # a ramp comes back at the coarse pixel's centre, 2Y + 1/2, as 2x2 pooling gives it, where the 8 taps
    # (2Y - 3 .. 2Y + 4) stay inside the image
    inner = np.s_[:, 2:-2, 2:-2]
    np.testing.assert_allclose(got[inner], down(image)[inner], rtol=1e-5, atol=1e-5)
    assert np.abs(got[:, 0, 0, 1:] - down(image)[:, 0, 0, 1:]).max() > 1e-3  # the clamped edge does not


def test_bicubic_pyramid_adjusts_gradients_and_relative_variances_like_pooling():
    rng = np.random.default_rng(17)
    x = np.zeros((2, 12, 10, 30))
    x[..., PLAIN] = rng.uniform(0, 3, size=(2, 12, 10, len(PLAIN)))
    x[..., 27:] = rng.uniform(0, 1, size=(2, 12, 10, 3))
    x[..., GRADIENT] = rng.normal(size=(2, 12, 10, len(GRADIENT)))
    # tiny, moderate, past the direct form's 20 and up to the features' 300
    x[..., RELVAR] = (rng.choice([1e-4, 0.3, 4.0, 19.0, 25.0, 90.0, 300.0], size=(2, 12, 10, 4))
                      * rng.uniform(0.5, 1.0, size=(2, 12, 10, 4)))
    got = run(FeatureDownsample("bicubic"), x.astype(np.float32))
    filtered = bicubic_down(x)
    plain = PLAIN + [27, 28, 29]
    np.testing.assert_allclose(got[..., plain], filtered[..., plain], rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(got[..., GRADIENT], 2 * filtered[..., GRADIENT], rtol=1e-5, atol=1e-5)
    # the variance of Σ w x over independent pixels is Σ w² v: log1p of it, in float64 (expm1(300) fits)
    relvar = np.log1p(bicubic_down(np.expm1(x[..., RELVAR]), square=True))
    np.testing.assert_allclose(got[..., RELVAR], relvar, rtol=2e-6, atol=1e-7)
    t = torch.tensor(x, dtype=torch.float32, requires_grad=True)
    FeatureDownsample("bicubic")(t).sum().backward()
    assert torch.isfinite(t.grad).all()
    # a constant relative variance v comes down to 0.164 v (2x2 pooling: v / 4)
    const = np.zeros((1, 8, 8, 27), np.float32)
    const[..., RELVAR] = np.log1p(2.0)
    gain = sum(w * w for w in BICUBIC_TAPS) ** 2
    np.testing.assert_allclose(np.expm1(run(FeatureDownsample("bicubic"), const)[..., RELVAR]), 2.0 * gain, rtol=1e-5)
