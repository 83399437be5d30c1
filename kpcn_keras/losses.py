"""SMAPE and asymmetric SMAPE training losses (docs/method.md §5).

    smape(gt, out)      = mean(|out - gt| / (|out| + |gt| + SMAPE_EPS))      over pixels and channels
    asymmetric (slope λ) = smape elementwise * (1 + (λ - 1) * H((out - gt) * (gt - noisy)))

H(x) = 1 for x > 0, else 0: an element is weighted by λ when the output over-shoots the reference on the
side *away* from the noisy input, i.e. when out and noisy lie on opposite sides of gt; (out - gt) and
(gt - noisy) then have the same sign. Ties (out == gt or noisy == gt) get factor 1. λ >= 1 penalises moving
past the reference more than staying on the noisy side, so the network prefers keeping some noise (detail)
over blurring.

Keras use: ``SMAPE()`` is a ``keras.losses.Loss`` for ``model.compile(loss=...)``. ``AsymmetricSMAPE(slope)``
needs the noisy colour too, so its ``y_true`` has 6 channels, ``concatenate([gt, noisy], axis=-1)``
(gt first); a data pipeline yields ``(features, concatenate([gt, features[..., :3]], -1))`` and the model
output stays 3 channels. ``AsymmetricSMAPE(slope=None)`` takes λ per element from a seventh channel of
``y_true`` instead (``concatenate([gt, noisy, λ], -1)``): the training of a network whose input carries λ
(``models.network_input``), where each patch has its own λ. Both losses are registered for ``.keras`` saving. All
inputs are in the domain the network is trained in (log(1 + x) branch colour, or the final colour for joint
fine-tuning).

**Reference weighting** (docs/training.md §2). Where a reference is itself noisy (caustics,
fireflies), a network trained on it learns its speckles as signal. With ``reference_tau`` τ > 0 either loss
takes one more channel, the **last** of ``y_true``: the reference's relative standard error per pixel
(``prep.convergence``, the shards' ``<branch>/ref_relse``), and weighs each pixel by

    w = 1 / (1 + (relSE / τ)^2)          (no gradient: it depends on the data alone)

as a weighted mean per sample: ``loss = Σ_pixels,channels w e / (C Σ_pixels w)`` (C colour channels, e the
elementwise loss). With every w = 1 this is the plain mean; a pixel's gradient is its unweighted one times
``w P / Σ w`` (P pixels), so a pixel whose relSE is large (w -> 0) has none, and the others keep their relative
sizes. ``Σ w`` is floored at :data:`WEIGHT_FLOOR` (a patch whose every pixel is unconverged still has a
finite loss). τ = 0 (the default of the loss classes; a loss saved before weighting existed) is the unweighted
loss, the same operations as before.
"""

from __future__ import annotations

import keras
from keras import ops

from prep.bounds import is_number

__all__ = [
    "SMAPE_EPS",
    "AsymmetricSMAPE",
    "SMAPE",
    "asymmetric_smape",
    "asymmetric_weight",
    "reference_weight",
    "smape",
    "smape_elementwise",
]

SMAPE_EPS = 0.01  # the report's constant; keeps the ratio finite where out and gt are both ~0
WEIGHT_FLOOR = 1e-12  # the least Σ w of a weighted sample: a sum of weights that each underflowed stays finite


def _check_slope(slope) -> float:
    if not isinstance(slope, (int, float)) and ops.is_tensor(slope):
        return slope  # a per-element map, from the data: checked where it is drawn
    if not is_number(slope) or not slope >= 1.0:
        raise ValueError(f"asymmetric SMAPE slope must be a number >= 1, received {slope!r}")
    return float(slope)


def smape_elementwise(gt, out):
    """|out - gt| / (|out| + |gt| + SMAPE_EPS), same shape as the inputs."""
    gt = ops.convert_to_tensor(gt)
    out = ops.convert_to_tensor(out, dtype=gt.dtype)
    return ops.abs(out - gt) / (ops.abs(out) + ops.abs(gt) + SMAPE_EPS)


def smape(gt, out):
    """Scalar SMAPE, mean over every element. Argument order matches Keras losses: (y_true, y_pred)."""
    return ops.mean(smape_elementwise(gt, out))


def asymmetric_weight(noisy, gt, out, slope):
    """Per-element factor 1 + (slope - 1) * H((out - gt) * (gt - noisy)); piecewise constant, no gradient."""
    slope = _check_slope(slope)
    gt = ops.convert_to_tensor(gt)
    out = ops.convert_to_tensor(out, dtype=gt.dtype)
    noisy = ops.convert_to_tensor(noisy, dtype=gt.dtype)
    side = ops.stop_gradient((out - gt) * (gt - noisy))
    return 1.0 + (slope - 1.0) * ops.cast(side > 0, gt.dtype)


def asymmetric_smape(noisy, gt, out, slope):
    """Scalar asymmetric SMAPE (mean over every element); equals ``smape(gt, out)`` for slope 1."""
    return ops.mean(smape_elementwise(gt, out) * asymmetric_weight(noisy, gt, out, slope))


def _per_sample_mean(values):
    # Keras convention: a loss returns one value per sample, so sample_weight of shape (B,) applies.
    return ops.mean(ops.reshape(values, (ops.shape(values)[0], -1)), axis=-1)


def _check_tau(tau) -> float:
    if not is_number(tau) or not tau >= 0.0 or tau == float("inf"):
        raise ValueError(f"reference_tau must be a finite number >= 0, received {tau!r}")
    return float(tau)


def reference_weight(relse, tau: float):
    """Per-pixel weight 1 / (1 + (relSE / τ)^2) of the module docstring, without gradient; τ > 0."""
    relse = ops.stop_gradient(ops.convert_to_tensor(relse))
    return 1.0 / (1.0 + ops.square(relse / tau))


def _weighted_per_sample_mean(values, weight):
    """Σ w e / (C Σ w) per sample (module docstring): ``values`` (B, H, W, C), ``weight`` (B, H, W, 1)."""
    batch = ops.shape(values)[0]
    channels = values.shape[-1]
    total = ops.sum(ops.reshape(values * weight, (batch, -1)), axis=-1)
    weights = ops.sum(ops.reshape(weight, (batch, -1)), axis=-1)
    return total / (channels * ops.maximum(weights, WEIGHT_FLOOR))


def _split_relse(loss, y_true, expected: int):
    """``(y_true without its relSE channel, relSE or None)``, ValueError unless it has ``expected`` channels
    (the loss's own, and one more with reference weighting)."""
    weighted = loss.reference_tau > 0.0
    channels = y_true.shape[-1]
    if channels != expected + weighted:
        raise ValueError(
            f"{type(loss).__name__}({loss.describe()}) expects y_true with {expected + weighted} channels "
            f"({loss.channel_names}{', reference relSE' if weighted else ''}), received shape {tuple(y_true.shape)}"
        )
    if not weighted:
        return y_true, None
    return y_true[..., :expected], y_true[..., expected:]


def _reduce(loss, values, relse):
    if relse is None:
        return _per_sample_mean(values)
    return _weighted_per_sample_mean(values, reference_weight(relse, loss.reference_tau))


@keras.saving.register_keras_serializable(package="kpcn")
class SMAPE(keras.losses.Loss):
    """SMAPE as a Keras loss: ``call(y_true, y_pred)`` returns the per-sample mean, reduced over the batch.
    With ``reference_tau`` > 0, ``y_true`` is (B, H, W, 4), the reference relSE last, and the mean is
    weighted (module docstring)."""

    channel_names = "gt"

    def __init__(self, name: str = "smape", reduction: str = "sum_over_batch_size", dtype=None,
                 reference_tau: float = 0.0):
        super().__init__(name=name, reduction=reduction, dtype=dtype)
        self.reference_tau = _check_tau(reference_tau)

    def describe(self) -> str:
        return f"reference_tau={self.reference_tau}"

    def call(self, y_true, y_pred):
        if self.reference_tau == 0.0:
            return _per_sample_mean(smape_elementwise(y_true, y_pred))
        gt, relse = _split_relse(self, y_true, 3)
        return _reduce(self, smape_elementwise(gt, y_pred), relse)

    def get_config(self):
        config = super().get_config()
        config["reference_tau"] = self.reference_tau
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class AsymmetricSMAPE(keras.losses.Loss):
    """Asymmetric SMAPE with slope λ >= 1. ``y_true`` is (B, H, W, 6): gt in channels 0..2, noisy in 3..5;
    with ``slope=None`` it is (B, H, W, 7) and channel 6 is λ per element. ``y_pred`` is (B, H, W, 3).
    With ``reference_tau`` > 0 the reference relSE is one more channel, the last, and the mean is weighted
    (module docstring)."""

    def __init__(self, slope: float | None = 2.0, name: str = "asymmetric_smape",
                 reduction: str = "sum_over_batch_size", dtype=None, reference_tau: float = 0.0):
        super().__init__(name=name, reduction=reduction, dtype=dtype)
        self.slope = None if slope is None else _check_slope(slope)
        self.reference_tau = _check_tau(reference_tau)

    @property
    def channel_names(self) -> str:
        return "gt, noisy" + ("" if self.slope is not None else ", slope")

    def describe(self) -> str:
        return f"slope={self.slope}" + (f", reference_tau={self.reference_tau}" if self.reference_tau else "")

    def call(self, y_true, y_pred):
        y_true, relse = _split_relse(self, y_true, 6 if self.slope is not None else 7)
        gt = y_true[..., :3]
        noisy = y_true[..., 3:6]
        slope = self.slope if self.slope is not None else y_true[..., 6:7]
        values = smape_elementwise(gt, y_pred) * asymmetric_weight(noisy, gt, y_pred, slope)
        return _reduce(self, values, relse)

    def get_config(self):
        config = super().get_config()
        config["slope"] = self.slope
        config["reference_tau"] = self.reference_tau
        return config
