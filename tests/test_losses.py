"""SMAPE and asymmetric SMAPE against float64 numpy references and hand-built cases."""

import keras
import numpy as np
import pytest
import torch
from helpers.numerics import F32_MAX, F32_TINY

from kpcn_keras.losses import (
    SMAPE,
    SMAPE_EPS,
    AsymmetricSMAPE,
    asymmetric_smape,
    asymmetric_weight,
    smape,
    smape_elementwise,
)
from kpcn_keras.models import ModelConfig, build_branch_model
from prep.colour import LOG_COLOUR_MAX


def np_smape(gt, out):
    gt, out = np.float64(gt), np.float64(out)
    return np.mean(np.abs(out - gt) / (np.abs(out) + np.abs(gt) + 0.01))


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def random_triplet(seed, shape=(3, 5, 4, 3)):
    rng = np.random.default_rng(seed)
    gt = rng.normal(size=shape).astype(np.float32)
    out = (gt + rng.normal(scale=0.5, size=shape)).astype(np.float32)
    noisy = (gt + rng.normal(scale=0.5, size=shape)).astype(np.float32)
    gt.flat[:5] = 0.0  # zeros exercise the epsilon
    out.flat[:3] = 0.0
    return noisy, gt, out


def test_eps_is_the_reports_constant():
    assert SMAPE_EPS == 0.01
    assert float(to_np(smape(np.float32([0.0]), np.float32([0.01])))) == pytest.approx(0.5, rel=1e-6)


def test_smape_matches_numpy():
    _, gt, out = random_triplet(0)
    want = np_smape(gt, out)
    assert float(to_np(smape(gt, out))) == pytest.approx(want, rel=1e-6)
    assert float(to_np(SMAPE()(gt, out))) == pytest.approx(want, rel=1e-6)
    assert to_np(smape_elementwise(gt, out)).shape == gt.shape


def test_smape_loss_honours_sample_weight():
    _, gt, out = random_triplet(1)
    got = float(to_np(SMAPE()(gt, out, sample_weight=np.float32([1.0, 0.0, 2.0]))))
    want = (np_smape(gt[0], out[0]) + 2.0 * np_smape(gt[2], out[2])) / 3.0
    assert got == pytest.approx(want, rel=1e-6)


def test_slope_one_equals_smape():
    noisy, gt, out = random_triplet(2)
    assert float(to_np(asymmetric_smape(noisy, gt, out, 1.0))) == pytest.approx(float(to_np(smape(gt, out))), rel=1e-7)
    packed = np.concatenate([gt, noisy], axis=-1)
    assert float(to_np(AsymmetricSMAPE(1.0)(packed, out))) == pytest.approx(np_smape(gt, out), rel=1e-6)


def hand_case():
    #            opposite  same  opposite  same  out==gt  noisy==gt
    gt = np.float32([1.0, 1.0, 1.0, 1.0, 1.0, 1.0])
    noisy = np.float32([0.0, 0.0, 2.0, 2.0, 0.0, 1.0])
    out = np.float32([2.0, 0.5, 0.0, 1.5, 1.0, 3.0])
    return noisy, gt, out


@pytest.mark.parametrize("slope", [2.0, 8.0])
def test_slope_multiplies_exactly_the_overshooting_elements(slope):
    # H((out - gt)(gt - noisy)) > 0 when out and noisy lie on OPPOSITE sides of gt (out overshoots past
    # the reference, away from the input); ties get factor 1
    noisy, gt, out = hand_case()
    expected = np.float64([slope, 1.0, slope, 1.0, 1.0, 1.0])
    np.testing.assert_array_equal(to_np(asymmetric_weight(noisy, gt, out, slope)), expected)
    per_element = np.abs(np.float64(out) - gt) / (np.abs(np.float64(out)) + np.abs(gt) + 0.01)
    want = np.mean(per_element * expected)
    assert float(to_np(asymmetric_smape(noisy, gt, out, slope))) == pytest.approx(want, rel=1e-6)
    # the same six elements as 2 pixels x 3 channels, y_true packed as (gt | noisy)
    packed = np.concatenate([gt.reshape(1, 1, 2, 3), noisy.reshape(1, 1, 2, 3)], axis=-1)
    got = float(to_np(AsymmetricSMAPE(slope)(packed, out.reshape(1, 1, 2, 3))))
    assert got == pytest.approx(want, rel=1e-6)


def test_asymmetric_matches_numpy_on_random_data():
    noisy, gt, out = random_triplet(3)
    g, o, n = (np.float64(a) for a in (gt, out, noisy))
    weight = 1.0 + 2.0 * ((o - g) * (g - n) > 0)
    want = np.mean(np.abs(o - g) / (np.abs(o) + np.abs(g) + 0.01) * weight)
    assert float(to_np(asymmetric_smape(noisy, gt, out, 3.0))) == pytest.approx(want, rel=1e-6)


@pytest.mark.parametrize("slope", [0.5, -1.0, float("nan"), "2"])
def test_bad_slope_raises_with_value(slope):
    with pytest.raises(ValueError, match="received"):
        AsymmetricSMAPE(slope)
    noisy, gt, out = hand_case()
    with pytest.raises(ValueError, match=repr(slope) if isinstance(slope, str) else str(slope)):
        asymmetric_smape(noisy, gt, out, slope)


def test_asymmetric_loss_needs_six_channels():
    x = np.zeros((1, 2, 2, 3), np.float32)
    with pytest.raises(ValueError, match="6 channels"):
        AsymmetricSMAPE(2.0)(x, x)


def test_gradient_finite_at_zero():
    out = torch.zeros((1, 2, 2, 3), requires_grad=True)
    gt = torch.zeros((1, 2, 2, 3))
    loss = smape(gt, out) + asymmetric_smape(gt, gt, out, 4.0)
    loss.backward()
    assert float(loss.detach()) == 0.0
    assert torch.isfinite(out.grad).all()


def test_gradient_matches_numpy_derivative():
    # for o > g > 0: d/do (o - g) / (o + g + eps) = (2g + eps) / (o + g + eps)^2
    g, o = 0.5, 0.8
    out = torch.tensor([o], requires_grad=True)
    smape(torch.tensor([g]), out).backward()
    assert float(out.grad) == pytest.approx((2 * g + 0.01) / (o + g + 0.01) ** 2, rel=1e-5)


def test_losses_serialise_and_train_a_model(tmp_path):
    for loss in (SMAPE(), AsymmetricSMAPE(2.5)):
        clone = keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(loss))
        assert type(clone) is type(loss) and clone.get_config() == loss.get_config()
    keras.utils.set_random_seed(0)
    model = build_branch_model(ModelConfig(width=4, depth=1, kernel_size=3))
    model.compile(optimizer="adam", loss=AsymmetricSMAPE(2.0))
    rng = np.random.default_rng(0)
    x = rng.normal(size=(2, 6, 6, 27)).astype(np.float32)
    y = np.concatenate([x[..., :3] * 0.5, x[..., :3]], axis=-1)  # gt | noisy
    assert np.isfinite(float(model.train_on_batch(x, y)))
    model.save(tmp_path / "m.keras")
    loaded = keras.models.load_model(tmp_path / "m.keras")
    assert isinstance(loaded.loss, AsymmetricSMAPE) and loaded.loss.slope == 2.0


# ---------------------------------------------------------------- hard numbers (from test_numerics)


def test_smape_at_zero_is_zero_with_finite_bounded_gradient():
    out = torch.zeros((2, 3, 3, 3), requires_grad=True)
    gt = torch.zeros((2, 3, 3, 3))
    for loss in (smape(gt, out), SMAPE()(gt, out)):
        assert float(loss.detach()) == 0.0
        (grad,) = torch.autograd.grad(loss, out)
        # one-sided derivatives at out = gt = 0 are +-1 / SMAPE_EPS per element (over the mean's count)
        assert torch.isfinite(grad).all() and float(grad.abs().max()) <= 1.0 / SMAPE_EPS / out.numel()


@pytest.mark.parametrize("gt_level", [0.0, 1e-6, 1.0, LOG_COLOUR_MAX])
@pytest.mark.parametrize("slope", [1.0, 2.0, 8.0])
def test_asymmetric_smape_at_out_equal_gt_is_zero_with_finite_bounded_gradient(gt_level, slope):
    rng = np.random.default_rng(8)
    gt = torch.tensor(rng.uniform(0, 1, (2, 4, 4, 3)) * gt_level, dtype=torch.float32)
    noisy = gt + torch.tensor(rng.normal(size=(2, 4, 4, 3)), dtype=torch.float32)
    out = gt.clone().requires_grad_(True)
    for loss in (asymmetric_smape(noisy, gt, out, slope), AsymmetricSMAPE(slope)(torch.cat([gt, noisy], -1), out)):
        assert float(loss.detach()) == 0.0
        (grad,) = torch.autograd.grad(loss, out)
        # one-sided derivative bound at out = gt: slope / (2|gt| + SMAPE_EPS), over the mean's count
        bound = slope / (2 * gt.abs() + SMAPE_EPS) / out.numel()
        assert torch.isfinite(grad).all() and bool((grad.abs() <= bound * (1 + 1e-6)).all())


@pytest.mark.parametrize("out_value,gt_value", [(0.0, LOG_COLOUR_MAX), (LOG_COLOUR_MAX, 0.0), (F32_MAX, 0.0),
                                                (F32_MAX, F32_MAX), (F32_TINY, 0.0), (0.0, F32_TINY)])
def test_smape_over_the_colour_range_matches_float64_with_finite_gradient(out_value, gt_value):
    out = torch.tensor([out_value], dtype=torch.float32, requires_grad=True)
    gt = torch.tensor([gt_value], dtype=torch.float32)
    loss = smape(gt, out)
    o, g = float(np.float32(out_value)), float(np.float32(gt_value))
    want = abs(o - g) / (abs(o) + abs(g) + SMAPE_EPS)
    value = float(loss.detach())
    assert value == pytest.approx(want, rel=1e-6, abs=1e-12) and 0.0 <= value <= 1.0
    loss.backward()
    assert torch.isfinite(out.grad).all()


# ---------------------------------------------------------------- reference weighting


def np_smape_grad(gt, out):
    """d/d out of |out - gt| / (|out| + |gt| + eps), float64, elementwise (out != gt, out != 0)."""
    d = np.abs(out) + np.abs(gt) + 0.01
    return np.sign(out - gt) / d - np.abs(out - gt) * np.sign(out) / d**2


def weighted_case(seed=11, shape=(2, 4, 5, 3)):
    rng = np.random.default_rng(seed)
    gt = rng.uniform(0.1, 2.0, shape)
    out = gt + rng.choice([-1.0, 1.0], shape) * rng.uniform(0.05, 0.5, shape)
    relse = np.zeros(shape[:-1] + (1,))
    relse[0, 1, 2] = 1e3  # a speckle of the reference: weight ~1e-8
    relse[1, 3, 0] = 5.0
    relse[1, 0, 4] = 0.1  # τ itself: weight 1/2
    return gt, out, relse


@pytest.mark.parametrize("loss_kind", ["smape", "asymmetric"])
def test_reference_weighting_removes_a_speckled_pixel_and_rescales_the_others_exactly(loss_kind):
    tau = 0.1
    gt, out, relse = weighted_case()
    b, h, w, c = gt.shape
    weight = 1.0 / (1.0 + (relse / tau) ** 2)
    if loss_kind == "smape":
        loss, y = SMAPE(reference_tau=tau), np.concatenate([gt, relse], -1)
        factor = np.ones_like(gt)
    else:
        noisy = gt - 0.3 * (out - gt)  # the far side: every element's factor is the slope
        loss, y = AsymmetricSMAPE(3.0, reference_tau=tau), np.concatenate([gt, noisy, relse], -1)
        factor = np.full_like(gt, 3.0)
    out_t = torch.tensor(out, dtype=torch.float32, requires_grad=True)
    value = loss(torch.tensor(y, dtype=torch.float32), out_t)
    (grad,) = torch.autograd.grad(value, out_t)
    grad = grad.numpy().astype(np.float64)
    # float64: loss = mean over samples of Σ w e / (C Σ w); unweighted: the plain mean
    e = np.abs(out - gt) / (np.abs(out) + np.abs(gt) + 0.01) * factor
    sums = weight.reshape(b, -1).sum(1)
    want = np.mean((e * weight).reshape(b, -1).sum(1) / (c * sums))
    assert float(value.detach()) == pytest.approx(want, rel=1e-6)
    unweighted = np_smape_grad(gt, out) * factor / (b * h * w * c)
    # the normalisation: a pixel's gradient is its unweighted one times w P / Σ w of its sample
    scale = weight * (h * w) / sums[:, None, None, None]
    np.testing.assert_allclose(grad, unweighted * scale, rtol=2e-5, atol=0)
    assert np.abs(grad[0, 1, 2]).max() < 1e-7 * np.abs(unweighted[0, 1, 2]).min()
    clean = relse[..., 0] == 0
    np.testing.assert_allclose(grad[clean], (unweighted * (h * w) / sums[:, None, None, None])[clean], rtol=2e-5)


def test_tau_zero_is_exactly_the_unweighted_loss():
    _, gt, out = random_triplet(4)
    noisy = random_triplet(5)[0]
    # the loss before weighting existed: the per-sample mean of the elementwise loss, over the batch
    old = to_np(keras.ops.mean(keras.ops.mean(keras.ops.reshape(smape_elementwise(gt, out), (3, -1)), axis=-1)))
    assert to_np(SMAPE(reference_tau=0.0)(gt, out)) == old
    assert float(old) == pytest.approx(np_smape(gt, out), rel=1e-6)
    packed = np.concatenate([gt, noisy], -1)
    assert to_np(AsymmetricSMAPE(2.0, reference_tau=0.0)(packed, out)) == to_np(AsymmetricSMAPE(2.0)(packed, out))
    with pytest.raises(ValueError, match="6 channels"):
        AsymmetricSMAPE(2.0, reference_tau=0.0)(np.concatenate([packed, gt[..., :1]], -1), out)
    # τ > 0 with every relSE 0 weighs every pixel 1: the same value
    zero = np.zeros(gt.shape[:-1] + (1,), np.float32)
    assert float(to_np(SMAPE(reference_tau=0.1)(np.concatenate([gt, zero], -1), out))) == pytest.approx(
        float(old), rel=1e-6)


def test_weighted_losses_check_their_channels_and_tau_and_serialise():
    x = np.zeros((1, 2, 2, 3), np.float32)
    with pytest.raises(ValueError, match="4 channels"):
        SMAPE(reference_tau=0.1)(x, x)
    with pytest.raises(ValueError, match="8 channels"):
        AsymmetricSMAPE(None, reference_tau=0.1)(np.zeros((1, 2, 2, 7), np.float32), x)
    for bad in (-0.1, float("nan"), float("inf"), "0.1", True):
        with pytest.raises(ValueError, match="reference_tau"):
            SMAPE(reference_tau=bad)
    for loss in (SMAPE(reference_tau=0.2), AsymmetricSMAPE(2.5, reference_tau=0.3)):
        clone = keras.saving.deserialize_keras_object(keras.saving.serialize_keras_object(loss))
        assert clone.get_config() == loss.get_config() and clone.reference_tau == loss.reference_tau
    # a loss saved before weighting existed has no reference_tau: unweighted
    config = keras.saving.serialize_keras_object(SMAPE())
    config["config"].pop("reference_tau")
    assert keras.saving.deserialize_keras_object(config).reference_tau == 0.0
