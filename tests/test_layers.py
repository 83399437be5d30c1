"""KernelApply against an independent float64 numpy reference, plus its numerical edge cases; every layer of
``kpcn_keras.layers`` against the Keras layer contract (``helpers.networks.check_keras_layer``)."""

import keras
import numpy as np
import pytest
import torch
from helpers.networks import check_keras_layer
from helpers.numerics import F32_EPS, F32_MAX, F32_TINY, PROPERTY, float32_images
from helpers.references import reference_kernel_apply as float64_kernel_apply
from hypothesis import given, settings
from hypothesis import strategies as st

from kpcn_keras import layers as layers_module
from kpcn_keras.layers import (
    CropLike,
    FinalColour,
    FusedConv2D,
    KernelApply,
    MixColours,
    PadToMultiple,
    TakeChannels,
    _softmax_kernels_ops,
    apply_kernels,
    kernel_apply,
    pad_edge,
    softmax_kernels,
)
from kpcn_keras.losses import smape
from prep import colour
from prep.colour import LOG_COLOUR_MAX


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def reference_kernel_apply(colour, logits, k):
    """Direct float64 loops: softmax per pixel, edge-replicated neighbourhood, weighted sum."""
    colour = np.asarray(colour, np.float64)
    logits = np.asarray(logits, np.float64)
    b_n, h_n, w_n, c_n = colour.shape
    r = k // 2
    out = np.zeros_like(colour)
    for b in range(b_n):
        for y in range(h_n):
            for x in range(w_n):
                z = logits[b, y, x] - logits[b, y, x].max()
                wts = np.exp(z) / np.exp(z).sum()
                for i in range(k):
                    for j in range(k):
                        # edge replication: clamp the source coordinate into the image
                        sy = min(max(y + i - r, 0), h_n - 1)
                        sx = min(max(x + j - r, 0), w_n - 1)
                        for c in range(c_n):
                            out[b, y, x, c] += wts[i * k + j] * colour[b, sy, sx, c]
    return out


def _run(layer, colour, logits):
    return to_np(layer([colour.astype(np.float32), logits.astype(np.float32)]))


@pytest.mark.parametrize("k,h,w", [(3, 5, 7), (5, 6, 4), (5, 3, 2)])
def test_matches_numpy_loops(k, h, w):
    rng = np.random.default_rng(k * 100 + h)
    colour = rng.normal(size=(2, h, w, 3)) * 2.0
    logits = rng.normal(size=(2, h, w, k * k)) * 3.0
    got = _run(KernelApply(k), colour, logits)
    want = reference_kernel_apply(colour, logits, k)
    assert got.shape == (2, h, w, 3)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_tap_order_is_row_major():
    # all weight on tap (i=0, j=1): out[y, x] = colour[y-1, x] (clamped); a transposed tap order would
    # read colour[y, x-1] instead
    k = 3
    colour = np.arange(4 * 5, dtype=np.float32).reshape(1, 4, 5, 1).repeat(3, axis=-1)
    logits = np.full((1, 4, 5, k * k), -1e4, np.float32)
    logits[..., 0 * k + 1] = 0.0
    got = _run(KernelApply(k), colour, logits)
    want = colour[:, np.clip(np.arange(4) - 1, 0, 3)]
    np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("r", [1, 2, 4])
def test_pad_edge_is_edge_replication(r):
    x = np.random.default_rng(r).normal(size=(2, 3, 4, 3)).astype(np.float32)
    got = to_np(pad_edge(x, r))
    np.testing.assert_array_equal(got, np.pad(x, ((0, 0), (r, r), (r, r), (0, 0)), mode="edge"))


def test_one_hot_centre_kernel_is_identity():
    k = 5
    rng = np.random.default_rng(1)
    colour = rng.normal(size=(2, 6, 9, 3)).astype(np.float32)
    logits = rng.normal(size=(2, 6, 9, k * k)).astype(np.float32)
    logits[..., (k // 2) * k + k // 2] = 1e4
    got = _run(KernelApply(k), colour, logits)
    np.testing.assert_allclose(got, colour, rtol=1e-6, atol=0)


def test_equal_logits_keep_constant_image_constant_at_borders():
    k = 5
    colour = np.full((1, 7, 6, 3), 2.5, np.float32)
    colour[..., 1] = 0.75
    # equal within each pixel, different across pixels, including large values
    level = np.random.default_rng(2).normal(size=(1, 7, 6, 1)) * 50.0
    logits = np.repeat(level, k * k, axis=-1)
    got = _run(KernelApply(k), colour, logits)
    np.testing.assert_allclose(got, colour, rtol=1e-6)
    weights = to_np(softmax_kernels(logits.astype(np.float32)))
    np.testing.assert_allclose(weights, 1.0 / (k * k), rtol=1e-6)


def test_extreme_logits_finite_values_and_gradients():
    k = 3
    rng = np.random.default_rng(3)
    colour = torch.tensor(rng.normal(size=(2, 4, 5, 3)), dtype=torch.float32, requires_grad=True)
    signs = rng.choice([-1.0, 1.0], size=(2, 4, 5, k * k))
    logits = torch.tensor(signs * 1e4, dtype=torch.float32, requires_grad=True)
    out = KernelApply(k)([colour, logits])
    assert torch.isfinite(out).all()
    # a convex combination stays within the colour range
    assert out.min() >= colour.min() - 1e-5 and out.max() <= colour.max() + 1e-5
    (out**2).sum().backward()
    assert torch.isfinite(logits.grad).all()
    assert torch.isfinite(colour.grad).all()


@pytest.mark.slow
def test_gradient_matches_finite_differences():
    k = 3
    rng = np.random.default_rng(4)
    colour = torch.tensor(rng.normal(size=(1, 3, 4, 3)), dtype=torch.float64, requires_grad=True)
    logits = torch.tensor(rng.normal(size=(1, 3, 4, k * k)), dtype=torch.float64, requires_grad=True)
    layer = KernelApply(k, dtype="float64")
    assert torch.autograd.gradcheck(lambda c, z: layer([c, z]), (colour, logits))


@pytest.mark.parametrize("k", [4, 0, -3, 2.0, "5"])
def test_bad_kernel_size_raises_with_value(k):
    with pytest.raises(ValueError, match=repr(k) if isinstance(k, str) else str(k)):
        KernelApply(k)
    with pytest.raises(ValueError, match="kernel size"):
        apply_kernels(np.zeros((1, 2, 2, 3), np.float32), np.zeros((1, 2, 2, 16), np.float32), k)


def test_wrong_logit_count_raises():
    with pytest.raises(ValueError, match="9 logit channels"):
        KernelApply(3)([np.zeros((1, 4, 4, 3), np.float32), np.zeros((1, 4, 4, 25), np.float32)])


# name -> (factory, input shapes without the batch); every custom layer of kpcn_keras/layers.py
LAYER_CASES = {
    "KernelApply": (lambda: KernelApply(3, name="ka"), [(8, 6, 3), (8, 6, 9)]),
    "TakeChannels": (lambda: TakeChannels(0, 3, name="tc"), [(8, 6, 5)]),
    "FusedConv2D": (lambda: FusedConv2D(4, 3, padding="same"), [(8, 6, 3)]),
    "FinalColour": (lambda: FinalColour(), [(8, 6, 3), (8, 6, 3), (8, 6, 3)]),
    "PadToMultiple": (lambda: PadToMultiple(4), [(7, 5, 5)]),
    "CropLike": (lambda: CropLike(2), [(11, 8, 4), (8, 6, 1)]),
    "MixColours": (lambda: MixColours(3, name="mix"), [(8, 6, 9), (8, 6, 3)]),
}


def test_final_colour_is_the_numpy_inverse_to_float32_rounding():
    """FinalColour (keras.ops) against prep.colour's inverses in float64 on the same float32 inputs: log colours
    from 0 to past its clamp at LOG_LINEAR_MAX, albedos on both sides of [0, 1]."""
    rng = np.random.default_rng(11)
    shape = (2, 9, 7, 3)
    d, s = (np.concatenate([rng.uniform(0, 5, shape), rng.uniform(0, colour.LOG_LINEAR_MAX, shape)]).astype(np.float32)
            for _ in range(2))
    ends = [0.0, 1e-30, 1e-7, colour.LOG_LINEAR_MAX, colour.LOG_LINEAR_MAX + 1.0, LOG_COLOUR_MAX]
    d.flat[: len(ends)], s.flat[: len(ends)] = ends, ends[::-1]
    albedo = rng.uniform(-0.5, 1.5, d.shape).astype(np.float32)
    albedo.flat[:4] = [0.0, 1.0, -0.5, 1.5]
    top = np.float32(colour.LOG_LINEAR_MAX)
    want = (colour.diffuse_from_log(np.minimum(d, top), albedo)  # the albedo term in float32, as the layer's
            + colour.specular_from_log(np.minimum(s, top)))
    got = to_np(FinalColour()([d, s, albedo]))
    assert np.isfinite(got).all()
    # expm1, the product and the sum each round once in float32 (both terms >= 0: no cancellation)
    np.testing.assert_allclose(got, want, rtol=4 * F32_EPS, atol=0)


def test_mix_colours_weighs_each_colour_by_the_softmax_of_its_logit_as_float64_does():
    rng = np.random.default_rng(7)
    colours = rng.normal(size=(2, 5, 4, 3 * 4)).astype(np.float32)
    logits = (rng.normal(size=(2, 5, 4, 4)) * 30).astype(np.float32)  # far apart: the max subtraction matters
    z = logits.astype(np.float64) - logits.max(axis=-1, keepdims=True)
    w = np.exp(z) / np.exp(z).sum(axis=-1, keepdims=True)
    want = np.einsum("bhwj,bhwjc->bhwc", w, colours.astype(np.float64).reshape(2, 5, 4, 4, 3))
    np.testing.assert_allclose(to_np(MixColours(3)([colours, logits])), want, rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match="3 colour channels per logit"):
        MixColours(3)([colours, logits[..., :3]])
    with pytest.raises(ValueError, match="positive integer.*0"):
        MixColours(0)


@pytest.mark.parametrize("name", sorted(LAYER_CASES))
def test_layer_keeps_the_keras_layer_contract(name, tmp_path):
    factory, shapes = LAYER_CASES[name]
    check_keras_layer(factory, shapes, tmp_path)


@pytest.mark.parametrize("h, w, m", [(7, 5, 4), (1, 1, 8), (8, 9, 8), (3, 6, 1)])
def test_pad_to_multiple_replicates_the_edges_and_crop_like_undoes_it(h, w, m):
    x = np.random.default_rng(h * w).normal(size=(2, h, w, 3)).astype(np.float32)
    padded = to_np(PadToMultiple(m)(x))
    want = np.pad(x, ((0, 0), (0, -h % m), (0, -w % m), (0, 0)), mode="edge")
    np.testing.assert_array_equal(padded, want)
    np.testing.assert_array_equal(to_np(CropLike()([padded, x[..., :1]])), x)


def test_pad_and_crop_are_the_multiscale_modules_and_load_from_files_that_name_it(tmp_path):
    """Moved from multiscale.py: the same classes there, and a layer serialised under its old module loads."""
    from kpcn_keras import multiscale

    assert multiscale.PadToMultiple is PadToMultiple and multiscale.CropLike is CropLike
    config = keras.saving.serialize_keras_object(PadToMultiple(4, name="pad"))
    config["module"] = "kpcn_keras.multiscale"  # what a .keras file saved before the move holds
    layer = keras.saving.deserialize_keras_object(config)
    assert type(layer) is PadToMultiple and layer.multiple == 4


def test_take_channels_validates():
    x = np.arange(2 * 2 * 5, dtype=np.float32).reshape(1, 2, 2, 5)
    np.testing.assert_array_equal(to_np(TakeChannels(1, 4)(x)), x[..., 1:4])
    with pytest.raises(ValueError, match="start=3, stop=3"):
        TakeChannels(3, 3)
    with pytest.raises(ValueError, match="at least 6 channels"):
        TakeChannels(0, 6)(x)


# ---------------------------------------------------------------- torch fast path: the same values as keras.ops


@pytest.mark.parametrize("k,d,h,w", [(3, 1, 5, 7), (5, 2, 6, 9), (13, 1, 9, 4), (5, 1, 3, 2)])
def test_torch_path_equals_keras_ops_path_with_gradients(k, d, h, w):
    """The fused torch path and the keras.ops path (other backends') agree, values and both gradients."""
    rng = np.random.default_rng(k + d + h)
    colour = torch.tensor(rng.normal(size=(2, h, w, 3)), dtype=torch.float64, requires_grad=True)
    logits = torch.tensor(rng.normal(size=(2, h, w, k * k)) * 3.0, dtype=torch.float64, requires_grad=True)
    fast = kernel_apply(colour, logits, k, d)
    generic = apply_kernels(colour, _softmax_kernels_ops(logits), k, d)
    np.testing.assert_allclose(to_np(fast), to_np(generic), rtol=1e-12, atol=1e-12)
    g = torch.tensor(rng.normal(size=(2, h, w, 3)), dtype=torch.float64, device=fast.device)  # Keras's device
    for a, b in zip(torch.autograd.grad(fast, (colour, logits), g), torch.autograd.grad(generic, (colour, logits), g)):
        np.testing.assert_allclose(to_np(a), to_np(b), rtol=1e-10, atol=1e-12)


@pytest.mark.slow
def test_torch_path_is_taken_and_gradchecks_with_dilation(monkeypatch):
    calls = []
    original = layers_module._torch_kernel_apply
    monkeypatch.setattr(layers_module, "_torch_kernel_apply", lambda *a: calls.append(a[2:]) or original(*a))
    rng = np.random.default_rng(5)
    colour = torch.tensor(rng.normal(size=(1, 4, 5, 3)), dtype=torch.float64, requires_grad=True)
    logits = torch.tensor(rng.normal(size=(1, 4, 5, 9)), dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda c, z: kernel_apply(c, z, 3, 2), (colour, logits))
    KernelApply(3)([colour.detach().float(), logits.detach().float()])
    assert calls and calls[0] == (3, 2) and calls[-1] == (3, 1)


@pytest.mark.parametrize("k,d,h,w", [(13, 1, 9, 4), (5, 2, 6, 9), (3, 1, 1, 6)])
def test_inference_takes_the_forward_alone_and_equals_the_training_path(monkeypatch, k, d, h, w):
    calls = []
    original = layers_module._inference_kernel_apply
    monkeypatch.setattr(layers_module, "_inference_kernel_apply", lambda *a: calls.append(a[2:]) or original(*a))
    monkeypatch.setattr(layers_module, "KERNEL_BLOCK_BYTES", 1)  # a block a row: the blocks' offsets matter
    rng = np.random.default_rng(k + d)
    colour = torch.tensor(rng.uniform(0, 5, size=(2, h, w, 3)), dtype=torch.float32)
    logits = torch.tensor(rng.normal(size=(2, h, w, k * k)) * 3.0, dtype=torch.float32)
    trained = kernel_apply(colour, logits.clone().requires_grad_(True), k, d)
    assert not calls  # a gradient asked for: the autograd path
    with torch.no_grad():
        inferred = kernel_apply(colour, logits, k, d)
    assert calls == [(k, d)]
    np.testing.assert_allclose(to_np(inferred), to_np(trained), rtol=1e-6, atol=1e-6)
    want = apply_kernels(colour.double(), _softmax_kernels_ops(logits.double()), k, d)
    np.testing.assert_allclose(to_np(inferred), to_np(want), rtol=1e-5, atol=1e-5)


def test_softmax_kernels_equals_ops_formulation_and_survives_extremes():
    logits = np.random.default_rng(6).normal(size=(2, 3, 4, 25)).astype(np.float32) * 1e4
    np.testing.assert_allclose(to_np(softmax_kernels(logits)), to_np(_softmax_kernels_ops(logits)), atol=1e-6)
    assert np.isfinite(to_np(softmax_kernels(logits))).all()


def test_row_blocks_do_not_change_the_result(monkeypatch):
    """One row per block and the whole image in one block give the same output and logit gradient."""
    rng = np.random.default_rng(7)
    colour = torch.tensor(rng.normal(size=(2, 7, 6, 3)), dtype=torch.float32)
    logits = torch.tensor(rng.normal(size=(2, 7, 6, 25)), dtype=torch.float32)
    results = []
    for budget in (1, 2**40):
        monkeypatch.setattr(layers_module, "KERNEL_BLOCK_BYTES", budget)
        z = logits.clone().requires_grad_(True)
        out = kernel_apply(colour, z, 5)
        results.append((to_np(out), to_np(torch.autograd.grad(out.square().sum(), z)[0])))
    for a, b in zip(*results):
        np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-6)


def test_kernel_apply_rejects_mismatched_shapes_and_dilation():
    with pytest.raises(ValueError, match=r"\(1, 4, 4, 25\)"):
        kernel_apply(torch.zeros(1, 4, 4, 3), torch.zeros(1, 4, 4, 25), 3)
    with pytest.raises(ValueError, match="0"):
        kernel_apply(torch.zeros(1, 4, 4, 3), torch.zeros(1, 4, 4, 9), 3, 0)


@pytest.mark.parametrize("kw", [dict(kernel_size=3, padding="same"), dict(kernel_size=1, padding="same"),
                                dict(kernel_size=3, padding="valid", use_bias=False),
                                dict(kernel_size=3, padding="same", dilation_rate=2),
                                dict(kernel_size=3, padding="same", dilation_rate=(3, 1)),
                                dict(kernel_size=2, padding="same"), dict(kernel_size=3, strides=2)])
def test_fused_conv_equals_keras_conv_values_and_gradients(kw):
    """FusedConv2D's torch path (odd "same", "valid", dilated) and its fallbacks (even "same", strides) match
    Conv2D."""
    rng = np.random.default_rng(8)
    ours = FusedConv2D(4, data_format="channels_first", **kw)
    theirs = keras.layers.Conv2D(4, data_format="channels_first", **kw)
    x = torch.tensor(rng.normal(size=(2, 3, 7, 6)), dtype=torch.float32, requires_grad=True)
    ours.build(x.shape)
    theirs.build(x.shape)
    assert ours._torch_fast_path() == (kw["kernel_size"] % 2 == 1 and "strides" not in kw)
    weights = [rng.normal(size=tuple(w.shape)).astype(np.float32) for w in theirs.weights]
    ours.set_weights(weights)
    theirs.set_weights(weights)
    a, b = ours(x), theirs(x)
    np.testing.assert_allclose(to_np(a), to_np(b), rtol=1e-5, atol=1e-5)
    params = lambda layer: [x] + [w.value for w in layer.trainable_weights]  # noqa: E731
    for ga, gb in zip(torch.autograd.grad(a.square().sum(), params(ours)),
                      torch.autograd.grad(b.square().sum(), params(theirs))):
        np.testing.assert_allclose(to_np(ga), to_np(gb), rtol=1e-4, atol=1e-4)


# ---------------------------------------------------------------- hard numbers (from test_numerics)


@pytest.mark.parametrize("colour_level", [0.0, 1.0, LOG_COLOUR_MAX])
def test_softmax_kernels_at_logits_of_plus_minus_1e4_are_exact_averages_with_finite_gradients(colour_level):
    k = 3
    rng = np.random.default_rng(6)
    signs = rng.choice([-1.0, 1.0], size=(2, 5, 4, k * k))
    signs[0, 0, 0] = 1.0  # every tap tied at the maximum
    signs[0, 0, 1] = -1.0  # every tap tied at the minimum
    colour = (rng.uniform(0, 1, (2, 5, 4, 3)) * colour_level).astype(np.float32)
    logits_np = (signs * 1e4).astype(np.float32)
    # analytic: exp(-2e4) is 0, so the weights are 1/m on the m taps at the maximum
    top = logits_np == logits_np.max(axis=-1, keepdims=True)
    want_weights = top / top.sum(axis=-1, keepdims=True)
    np.testing.assert_allclose(to_np(softmax_kernels(logits_np)), want_weights, rtol=1e-6, atol=0)
    want, _ = float64_kernel_apply(colour, logits_np, k)
    colour_t = torch.tensor(colour, requires_grad=True)
    logits = torch.tensor(logits_np, requires_grad=True)
    out = KernelApply(k)([colour_t, logits])
    np.testing.assert_allclose(to_np(out), want, rtol=1e-6, atol=1e-6 * max(colour_level, 1.0))
    smape(torch.zeros_like(out), out).backward()
    assert torch.isfinite(colour_t.grad).all() and torch.isfinite(logits.grad).all()


@st.composite
def kernel_inputs(draw):
    k = draw(st.sampled_from([1, 3, 5]))
    shape = (draw(st.integers(1, 2)), draw(st.integers(1, 8)), draw(st.integers(1, 8)))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    domain = draw(st.sampled_from(["log-colour", "signed", "non-negative"]))
    if domain == "log-colour":  # what the networks filter: [0, LOG_COLOUR_MAX], ends included
        colour = rng.uniform(0, LOG_COLOUR_MAX, shape + (3,))
        colour[rng.uniform(size=colour.shape) < 0.2] = 0.0
        colour[rng.uniform(size=colour.shape) < 0.2] = LOG_COLOUR_MAX
    else:
        # magnitudes up to 1e37: a convex combination within k*k rounding errors of float32 max may round to inf
        colour = draw(float32_images(shape + (3,), signed=domain == "signed")).astype(np.float64)
        colour = np.clip(colour, -1e37, 1e37)
    scale = draw(st.sampled_from([0.0, 1.0, 30.0, 1e4, 1e30, F32_MAX / 8]))
    logits = rng.normal(size=shape + (k * k,)) * scale
    if draw(st.booleans()):
        logits = np.sign(logits) * scale  # saturated: ties at +-scale
    return colour.astype(np.float32), np.clip(logits, -F32_MAX, F32_MAX).astype(np.float32), k


@settings(max_examples=80, **PROPERTY)
@given(case=kernel_inputs())
def test_kernel_application_matches_float64_and_stays_inside_each_window(case):
    colour, logits, k = case
    colour_t = torch.tensor(colour, requires_grad=True)
    logits_t = torch.tensor(logits, requires_grad=True)
    out = KernelApply(k)([colour_t, logits_t])
    got = to_np(out).astype(np.float64)
    want, windows = float64_kernel_apply(colour, logits, k)
    # float32 error: the shifted logits' rounding through exp (|z| <= ~104 before exp underflows), the
    # normalisation and the k*k-term sum, relative to the window's largest magnitude
    scale = np.abs(windows).max(axis=3)
    tol = (128 + 2 * k * k) * F32_EPS * scale + k * k * F32_TINY
    assert np.isfinite(got).all()
    assert (np.abs(got - want) <= tol).all()
    # a convex combination: inside [min, max] of the window, per channel
    assert (got >= windows.min(axis=3) - tol).all() and (got <= windows.max(axis=3) + tol).all()
    (out * out.detach().sign()).sum().backward()
    assert torch.isfinite(colour_t.grad).all() and torch.isfinite(logits_t.grad).all()
    with torch.no_grad():  # inference: the forward alone, on the colour planes (layers._inference_kernel_apply)
        inferred = to_np(KernelApply(k)([colour_t, logits_t])).astype(np.float64)
    assert np.isfinite(inferred).all() and (np.abs(inferred - want) <= tol).all()
