"""The arithmetic of a trained network's trunk at inference: float32, or bfloat16 where the CPU has it.

Contract: :func:`apply` sets the Keras dtype policy of a branch network's trunk (``models.trunk_layers``: its
convolutions, activations, pooling, upsampling, skips and residual sums) to ``mixed_bfloat16`` (weights kept in
float32 and cast when used, activations in bfloat16) or back to ``float32``. Everything after the trunk stays
float32: the 1x1 kernel head reads the trunk's last activations cast back to float32, so the logits, their
softmax and the kernel application are what they were, and a denoised pixel is still a convex combination of
its neighbours' noisy colours (a bfloat16 trunk changes which kernel a pixel gets, slightly, never whether it
is normalised). A dpcn's correction and clamp stay float32 likewise.

``"auto"`` (:data:`kpcn_keras.config.DEFAULT_PRECISION`) is bfloat16 where the CPU multiplies it natively
(AVX-512 BF16 or AMX, as oneDNN reports it: :func:`native_bfloat16`; on a CUDA device, where torch says the
device has it) and float32 elsewhere, where bfloat16 is emulated and slower than float32. So the same command
gives the same file on the same machine, and a machine without native bfloat16 gives what float32 gives.

Only inference uses it: ``denoise.Denoiser`` sets it on the networks it loaded. Training, checkpoints and the
saved models are float32 throughout. What it buys and costs (time of a 1920x1080 frame, relMSE of the held-out
and validation frames against float32) is measured in docs/results/10-quality-levers.md §10c; the tests bound
the difference of a real model's output (``tests/test_precision.py``).
"""

from __future__ import annotations

import functools

import keras

from kpcn_keras.config import DEFAULT_PRECISION
from kpcn_keras.settings import check_precision

TRUNK_POLICY = {"float32": "float32", "bfloat16": "mixed_bfloat16"}  # a precision -> the trunk's dtype policy


@functools.cache
def native_bfloat16() -> bool:
    """Whether this process's torch device multiplies bfloat16 natively (CPU: oneDNN's bf16 check, which asks for
    AVX-512 BF16 or AMX; CUDA: ``torch.cuda.is_bf16_supported``)."""
    import torch

    if keras.backend.backend() != "torch":
        return False
    if torch.cuda.is_available():
        return bool(torch.cuda.is_bf16_supported())
    try:
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    except (AttributeError, RuntimeError):  # a torch without the check: assume emulation
        return False


def resolve(precision: str | None = None) -> str:
    """``"float32"`` or ``"bfloat16"``: ``precision`` (default :data:`DEFAULT_PRECISION`) with ``"auto"`` decided
    for this machine; OptionError echoing anything else."""
    precision = check_precision(DEFAULT_PRECISION if precision is None else precision)
    if precision == "auto":
        return "bfloat16" if native_bfloat16() else "float32"
    return precision


def apply(model: keras.Model, precision: str | None = None) -> str:
    """Set ``model``'s trunk to ``precision`` (resolved: :func:`resolve`) and return what it resolved to."""
    from kpcn_keras.models import trunk_layers

    resolved = resolve(precision)
    for layer in trunk_layers(model):
        layer.dtype_policy = TRUNK_POLICY[resolved]
    return resolved
