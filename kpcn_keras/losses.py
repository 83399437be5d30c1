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
    "smape",
    "smape_elementwise",
]

SMAPE_EPS = 0.01  # the report's constant; keeps the ratio finite where out and gt are both ~0


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


@keras.saving.register_keras_serializable(package="kpcn")
class SMAPE(keras.losses.Loss):
    """SMAPE as a Keras loss: ``call(y_true, y_pred)`` returns the per-sample mean, reduced over the batch."""

    def __init__(self, name: str = "smape", reduction: str = "sum_over_batch_size", dtype=None):
        super().__init__(name=name, reduction=reduction, dtype=dtype)

    def call(self, y_true, y_pred):
        return _per_sample_mean(smape_elementwise(y_true, y_pred))


@keras.saving.register_keras_serializable(package="kpcn")
class AsymmetricSMAPE(keras.losses.Loss):
    """Asymmetric SMAPE with slope λ >= 1. ``y_true`` is (B, H, W, 6): gt in channels 0..2, noisy in 3..5;
    with ``slope=None`` it is (B, H, W, 7) and channel 6 is λ per element. ``y_pred`` is (B, H, W, 3)."""

    def __init__(self, slope: float | None = 2.0, name: str = "asymmetric_smape",
                 reduction: str = "sum_over_batch_size", dtype=None):
        super().__init__(name=name, reduction=reduction, dtype=dtype)
        self.slope = None if slope is None else _check_slope(slope)

    def call(self, y_true, y_pred):
        channels = y_true.shape[-1]
        expected = 6 if self.slope is not None else 7
        if channels != expected:
            raise ValueError(
                f"AsymmetricSMAPE(slope={self.slope}) expects y_true with {expected} channels (gt, noisy"
                f"{'' if self.slope is not None else ', slope'}), received shape {tuple(y_true.shape)}"
            )
        gt = y_true[..., :3]
        noisy = y_true[..., 3:6]
        slope = self.slope if self.slope is not None else y_true[..., 6:7]
        values = smape_elementwise(gt, y_pred) * asymmetric_weight(noisy, gt, y_pred, slope)
        return _per_sample_mean(values)

    def get_config(self):
        config = super().get_config()
        config["slope"] = self.slope
        return config
