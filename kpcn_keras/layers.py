"""Per-pixel kernel application for kernel-predicting networks (seed report §2.2, Bako et al. 2017).

A kernel-predicting network outputs k*k logits per pixel. They are turned into a normalised kernel by a
softmax over the taps and applied to the noisy colour of the same pixel's k x k neighbourhood:

    w[b, y, x, :] = softmax(logits[b, y, x, :])
    out[b, y, x, c] = sum_{i, j} w[b, y, x, i*k + j] * colour_padded[b, y + i, x + j, c]

where tap t = i*k + j is row-major, (i, j) = (k//2, k//2) is the centre, and the colour is padded by k//2 on
each side by edge replication (a constant image stays constant at its borders; zero padding would darken
them). Everything is written with ``keras.ops`` so the layer is backend-agnostic; the project runs it on
torch. No epsilon is needed: after max subtraction the softmax denominator is >= 1.
"""

from __future__ import annotations

import keras
import numpy as np
from keras import ops

from kpcn_keras.config import check_kernel_size
from prep.features import ALBEDO_EPS

__all__ = [
    "FinalColour",
    "KernelApply",
    "TakeChannels",
    "apply_kernels",
    "check_kernel_size",
    "pad_edge",
    "softmax_kernels",
]


def softmax_kernels(logits):
    """Softmax over the last axis (the k*k taps), max-subtracted so logits like +-1e4 stay finite.

    Equal logits give exactly uniform weights. The max is a constant for the gradient (the softmax is
    invariant to it), which also avoids the tie-breaking subgradient of ``max``.
    """
    # ops.* rather than operators, so numpy arrays and symbolic KerasTensors are accepted too
    shifted = ops.subtract(logits, ops.stop_gradient(ops.max(logits, axis=-1, keepdims=True)))
    e = ops.exp(shifted)
    return ops.divide(e, ops.sum(e, axis=-1, keepdims=True))


def pad_edge(x, r: int):
    """Pad axes 1 and 2 of a (B, H, W, C) tensor by ``r`` on each side, replicating the edge pixels.

    Built from slices and ``concatenate`` because ``keras.ops.pad`` has no edge mode that works on the
    torch backend for this layout (its "symmetric" is mapped to torch "replicate", which is a different
    rule for r > 1, and torch only replicate-pads the trailing dimensions).
    """
    if r == 0:
        return x
    top = ops.repeat(x[:, :1], r, axis=1)
    bottom = ops.repeat(x[:, -1:], r, axis=1)
    x = ops.concatenate([top, x, bottom], axis=1)
    left = ops.repeat(x[:, :, :1], r, axis=2)
    right = ops.repeat(x[:, :, -1:], r, axis=2)
    return ops.concatenate([left, x, right], axis=2)


def apply_kernels(colour, weights, k: int, dilation: int = 1):
    """Filter ``colour`` (B, H, W, C) with normalised per-pixel ``weights`` (B, H, W, k*k); returns (B, H, W, C).

    The weights are used as given (no softmax), so this also serves to apply hand-made kernels.
    ``dilation`` d spaces the taps d pixels apart: tap (i, j) reads colour[y + d(i - k//2), x + d(j - k//2)],
    edge-replicated (d = 2 on a nearest-upsampled image reads the coarse image at coarse offsets).
    Implementation: a loop over the k*k shifted views accumulating a weighted sum. Measured on a 2-core CPU
    (k=13, 8 x 65 x 65, forward + backward) it beat stacking the shifted views into a (B, H, W, k*k, C)
    tensor and contracting with einsum/matmul (0.11 s vs 0.13-0.17 s), and it never materialises the stack.
    The weights are split with ``unstack`` rather than sliced per tap: on torch each slice's backward
    allocates a full-size zero gradient, which made the sliced loop three times slower.
    """
    k = check_kernel_size(k)
    d = dilation if isinstance(dilation, int) and not isinstance(dilation, bool) else 0
    if d < 1:
        raise ValueError(f"dilation must be a positive integer, received {dilation!r}")
    r = k // 2
    h = ops.shape(colour)[1]
    w = ops.shape(colour)[2]
    colour = ops.convert_to_tensor(colour)
    weights = ops.convert_to_tensor(weights, dtype=colour.dtype)
    padded = pad_edge(colour, r * d)
    taps = ops.unstack(weights, num=k * k, axis=-1)
    out = None
    for i in range(k):
        for j in range(k):
            term = ops.expand_dims(taps[i * k + j], -1) * padded[:, i * d : i * d + h, j * d : j * d + w, :]
            out = term if out is None else out + term
    return out


@keras.saving.register_keras_serializable(package="kpcn")
class KernelApply(keras.layers.Layer):
    """Inputs ``[colour (B, H, W, C), logits (B, H, W, k*k)]`` -> (B, H, W, C): softmax the logits over the
    taps and filter the colour with the resulting per-pixel k x k kernels (edge-replicated borders).

    ``kernel_size`` must be a positive odd integer. The layer has no weights.
    """

    def __init__(self, kernel_size: int, **kwargs):
        super().__init__(**kwargs)
        self.kernel_size = check_kernel_size(kernel_size)

    def _check_shapes(self, colour_shape, logits_shape):
        taps = self.kernel_size**2
        if logits_shape[-1] is not None and logits_shape[-1] != taps:
            raise ValueError(
                f"KernelApply(kernel_size={self.kernel_size}) expects {taps} logit channels, "
                f"received logits of shape {tuple(logits_shape)}"
            )
        if len(colour_shape) != 4 or len(logits_shape) != 4:
            raise ValueError(
                "KernelApply expects rank-4 colour and logits, received shapes "
                f"{tuple(colour_shape)} and {tuple(logits_shape)}"
            )

    def build(self, input_shape):
        colour_shape, logits_shape = input_shape
        self._check_shapes(colour_shape, logits_shape)

    def call(self, inputs):
        colour, logits = inputs
        return apply_kernels(colour, softmax_kernels(logits), self.kernel_size)

    def compute_output_shape(self, input_shape):
        colour_shape, _ = input_shape
        return tuple(colour_shape)

    def get_config(self):
        config = super().get_config()
        config["kernel_size"] = self.kernel_size
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class TakeChannels(keras.layers.Layer):
    """Channels ``[start, stop)`` of a channels-last tensor, as a serialisable layer (no Lambda needed)."""

    def __init__(self, start: int, stop: int, **kwargs):
        super().__init__(**kwargs)
        if not (0 <= int(start) < int(stop)):
            raise ValueError(f"need 0 <= start < stop, received start={start!r}, stop={stop!r}")
        self.start = int(start)
        self.stop = int(stop)

    def build(self, input_shape):
        channels = input_shape[-1]
        if channels is not None and channels < self.stop:
            raise ValueError(
                f"TakeChannels({self.start}, {self.stop}) needs at least {self.stop} channels, "
                f"received shape {tuple(input_shape)}"
            )

    def call(self, x):
        return x[..., self.start : self.stop]

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[:-1]) + (self.stop - self.start,)

    def get_config(self):
        config = super().get_config()
        config.update(start=self.start, stop=self.stop)
        return config


# exp() of a log colour above this would overflow float32 once remodulated and summed; a kernel output
# never gets there on real data, but a clamp keeps a wild early training step finite
LOG_LINEAR_MAX = float(np.log(np.finfo(np.float32).max / 4))


@keras.saving.register_keras_serializable(package="kpcn")
class FinalColour(keras.layers.Layer):
    """Inputs ``[diffuse (B, H, W, 3), specular (B, H, W, 3), albedo (B, H, W, 3)]``, the branch colours in
    the log domain and the noisy albedo -> the final linear colour (B, H, W, 3).

    The inverse of the branch transforms of ``prep.features`` (``diffuse_from_log``, ``specular_from_log``)
    written in ``keras.ops``, so a model can be supervised on the colour users see (joint fine-tuning):
    ``expm1(d) * (clip(albedo, 0, 1) + ALBEDO_EPS) + expm1(s)``, each log colour clamped to LOG_LINEAR_MAX.
    """

    def call(self, inputs):
        diffuse, specular, albedo = inputs
        albedo = ops.clip(albedo, 0.0, 1.0) + ALBEDO_EPS
        return (ops.expm1(ops.minimum(diffuse, LOG_LINEAR_MAX)) * albedo
                + ops.expm1(ops.minimum(specular, LOG_LINEAR_MAX)))

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0])
