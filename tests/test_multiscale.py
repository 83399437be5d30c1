"""Multiscale module: config, pyramid, blend, kernel upsampling, α regulariser, every layer's Keras contract,
the whole model (save/load, odd sizes, frozen denoiser, receptive radius, tiling), against float64 numpy."""

import warnings

import keras
import numpy as np
import pytest
import torch
from helpers.networks import check_keras_layer, randomise

from kpcn_keras.config import TrainConfig
from kpcn_keras.layers import apply_kernels
from kpcn_keras.losses import SMAPE, AsymmetricSMAPE
from kpcn_keras.models import ModelConfig, build_branch_model, receptive_radius
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
    alpha_maps,
    build_alpha_model,
    build_compositor,
    build_multiscale_model,
    compositor_of,
    denoiser_of,
    feature_runs,
    image_pyramid,
    multiscale_output,
    multiscale_radius,
)
from prep.features import FEATURE_NAMES

GRADIENT = [i for i, n in enumerate(FEATURE_NAMES) if n.startswith(("dx_", "dy_"))]
RELVAR = [i for i, n in enumerate(FEATURE_NAMES) if n.startswith("relvar")]
PLAIN = [i for i, n in enumerate(FEATURE_NAMES) if i not in GRADIENT and i not in RELVAR]
TINY_DENOISER = ModelConfig(width=6, depth=2, kernel_size=3)


def tiny_compositor(kind="alpha", **kw):
    return CompositorConfig(**{"kind": kind, "width": 4, "depth": 3, "kernel_size": 3, **kw})


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def run(model_or_layer, *inputs, **kw):
    args = [np.asarray(x, np.float32) for x in inputs]
    out = model_or_layer(args if len(args) > 1 else args[0], **kw)
    return [to_np(o) for o in out] if isinstance(out, (list, tuple)) else to_np(out)


def features(shape, seed=0, channels=27):
    """Plausible feature values: everything in [0, 2] (log colours and relvars are >= 0)."""
    return np.random.default_rng(seed).uniform(0.0, 2.0, size=tuple(shape) + (channels,)).astype(np.float32)


def multiscale(kind="alpha", seed=3, dropout=0.0, **kw):
    denoiser = build_branch_model(ModelConfig(width=6, depth=2, kernel_size=3, dropout=dropout))
    model = build_multiscale_model(denoiser, tiny_compositor(kind, **kw))
    randomise(model, seed=seed)
    return model


def up(c):
    return c.repeat(2, axis=1).repeat(2, axis=2)


def down(f):
    b, h, w, c = f.shape
    return f.reshape(b, h // 2, 2, w // 2, 2, c).mean(axis=(2, 4))


def keys(x, a=-0.5):
    """Keys' cubic convolution kernel, float64, written from the paper's formula."""
    x = np.abs(x)
    return np.where(x <= 1, (a + 2) * x**3 - (a + 3) * x**2 + 1,
                    np.where(x < 2, a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a, 0.0))


def bicubic_weights():
    """The antialiased bicubic 2x filter: fine pixel 2Y + k, k = -3 .. 4, weighs keys((k - 1/2) / 2) / 2."""
    k = np.arange(-3, 5)
    return k, keys((k - 0.5) / 2.0) / 2.0


def bicubic_down(f, square=False):
    """float64 loops: coarse (Y, X) = Σ_ij w_i w_j f[2Y + i, 2X + j], coordinates clamped (``square``: the
    weights squared, the variance of the filtered noise)."""
    offsets, w = bicubic_weights()
    w = w**2 if square else w
    b, h, wd, c = f.shape
    out = np.zeros((b, h // 2, wd // 2, c))
    for yy in range(h // 2):
        for xx in range(wd // 2):
            for i, wi in zip(offsets, w):
                for j, wj in zip(offsets, w):
                    sy, sx = min(max(2 * yy + i, 0), h - 1), min(max(2 * xx + j, 0), wd - 1)
                    out[:, yy, xx] += wi * wj * f[:, sy, sx]
    return out


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
