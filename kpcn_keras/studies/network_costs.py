"""What each stage of a branch network costs in time, against what it could cost, for ``kpcn bench``.

Every function returns a plain JSON-able dict (floats, ints, strings, nested dicts) and runs on the current
torch thread count; times are seconds, best (or median, where said) of several repeats, variants measured
alternately in one process so that load from other processes hits them alike.

- :func:`memory_bandwidth` -> ``{"read_bytes_per_s", "nbytes", "repeats", "seconds", "threads", "method"}``:
  the best rate of reading one large float32 tensor once (``torch.sum``).
- :func:`kernel_application_cost` -> ``{"k", "pixels", "weight_bytes", "seconds", "floor_seconds", "ratio",
  "variants", "bandwidth", "training"}``: the kernel layer as shipped (``layers.kernel_apply``, softmax +
  per-pixel k x k weighted sum) against the memory floor, the time to read every logit once
  (``weight_bytes / read_bytes_per_s``); ``ratio = seconds / floor_seconds``. ``variants`` times the
  alternatives by name (``VARIANTS``), the shipped one included. ``training=True`` times forward +
  backward (gradient of the logits, as in a branch model, where the colour is an input).
- :func:`train_step_cost` -> ``{"keras_s", "torch_s", "ratio", "patches_per_s", ...}``: the median time of
  one training step (forward, SMAPE, backward, Adam) of the Keras branch model and of the same network in
  plain torch (``plain_torch``), same starting weights, same in-memory batch; ``ratio = keras_s / torch_s``
  and ``patches_per_s`` is the Keras step's. Gradient clipping and the learning-rate schedule of
  ``train.py`` are left out of both (they cost the same on either side).
"""

from __future__ import annotations

import statistics
import time

import keras
import numpy as np
import torch
import torch.nn.functional as F

from kpcn_keras import layers
from kpcn_keras.config import ModelConfig
from kpcn_keras.losses import SMAPE, smape
from kpcn_keras.models import build_branch_model
from kpcn_keras.studies.plain_torch import torch_branch_from_keras
from prep.bounds import is_integer

__all__ = ["TRAINING_SKIPS", "VARIANTS", "kernel_application_cost", "memory_bandwidth", "train_step_cost"]

FLOAT_BYTES = 4  # float32 everywhere here
LOGIT_SCALE = 3.0  # logits ~ N(0, 3^2): peaked kernels, like a trained network's
ADAM_LEARNING_RATE = 1e-3
KERAS_ADAM_EPSILON = 1e-7  # keras.optimizers.Adam's default; torch's is 1e-8


def _check_positive_int(name, value, minimum=1):
    if not is_integer(value) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, received {value!r}")
    return value


def memory_bandwidth(nbytes: int = 512 * 2**20, repeats: int = 5) -> dict:
    """Best-of-``repeats`` rate (bytes/s) of reading a float32 tensor of ``nbytes`` once with ``torch.sum``.

    Choose ``nbytes`` well above the last-level cache, or the rate is the cache's."""
    _check_positive_int("nbytes", nbytes, FLOAT_BYTES)
    _check_positive_int("repeats", repeats)
    x = torch.ones(nbytes // FLOAT_BYTES, dtype=torch.float32)
    x.sum()  # first touch: page faults are not reads
    best = min(_timed(x.sum) for _ in range(repeats))
    size = x.numel() * FLOAT_BYTES
    return {
        "read_bytes_per_s": size / best,
        "nbytes": size,
        "repeats": repeats,
        "seconds": best,
        "threads": torch.get_num_threads(),
        "method": "torch.sum over a float32 tensor, best of repeats",
    }


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


# ---------------------------------------------------------------- kernel application variants


def _shifted_slices(colour, logits, k):
    """The layer before its fused torch path: four-op keras.ops softmax, then a loop over k*k shifted
    channels-last views."""
    return layers.apply_kernels(colour, layers._softmax_kernels_ops(logits), k)


def _fused_softmax_slices(colour, logits, k):
    """The same loop after one fused softmax: isolates what the softmax cost."""
    return layers.apply_kernels(colour, torch.softmax(logits, dim=-1), k)


def _channels_first_planes(colour, logits, k):
    """Softmax, then the weights transposed to (B, k*k, H, W) so that each tap reads one contiguous plane."""
    r = k // 2
    h, w = colour.shape[1:3]
    weights = torch.softmax(logits, dim=-1).permute(0, 3, 1, 2).contiguous()
    padded = F.pad(colour.permute(0, 3, 1, 2), (r, r, r, r), mode="replicate")
    out = None
    for i in range(k):
        for j in range(k):
            term = weights[:, i * k + j : i * k + j + 1] * padded[:, :, i : i + h, j : j + w]
            out = term if out is None else out + term
    return out.permute(0, 2, 3, 1)


def _softmax_only(colour, logits, k):
    """The shipped path's softmax and nothing else, over the same row blocks (one whole-image softmax
    would mostly time the page faults of a fresh k*k-channel output): a compute floor of any path that
    needs the weights; on a 2-core CPU the exponentials, not the memory, bound the layer."""
    b, h, w, taps = logits.shape
    step = layers._block_rows(b, w, colour.shape[-1], taps, logits.element_size())
    for y0 in range(0, h, step):
        torch.softmax(logits[:, y0 : y0 + step], dim=-1)
    return logits


def _shipped(colour, logits, k):
    return layers.kernel_apply(colour, logits, k)


VARIANTS = {
    "shipped": _shipped,
    "shifted_slices": _shifted_slices,
    "fused_softmax_slices": _fused_softmax_slices,
    "channels_first_planes": _channels_first_planes,
    "softmax_only": _softmax_only,
}

TRAINING_SKIPS = ("channels_first_planes", "softmax_only")


def kernel_application_cost(
    k: int,
    height: int = 256,
    width: int = 256,
    batch: int = 1,
    repeats: int = 5,
    training: bool = False,
    *,
    bandwidth: dict | None = None,
) -> dict:
    """Time the kernel layer at kernel size ``k`` on a (batch, height, width) image; see the module docstring.

    ``bandwidth``: a :func:`memory_bandwidth` result to reuse (measured here when None). In training mode
    ``TRAINING_SKIPS`` are left out: ``softmax_only`` is no layer, and autograd through the k*k-plane loop
    of ``channels_first_planes`` took 17 s per step at k=21 on 8 x 65 x 65 (vs 0.3 s for the baseline)."""
    k = layers.check_kernel_size(k)
    for name, value in (("height", height), ("width", width), ("batch", batch), ("repeats", repeats)):
        _check_positive_int(name, value)
    if bandwidth is None:
        bandwidth = memory_bandwidth()
    generator = torch.Generator().manual_seed(0)
    colour = torch.rand(batch, height, width, 3, generator=generator)
    logits = torch.randn(batch, height, width, k * k, generator=generator) * LOGIT_SCALE
    names = list(VARIANTS)

    def step(fn):
        if not training:
            with torch.no_grad():
                fn(colour, logits, k)
            return
        z = logits.detach().requires_grad_(True)
        out = fn(colour, z, k)
        grad = torch.ones_like(out)
        torch.autograd.grad(out, z, grad)

    if training:
        names = [name for name in names if name not in TRAINING_SKIPS]
    best = {name: float("inf") for name in names}
    for name in names:  # warm-up: first-call allocations are not the layer's cost
        step(VARIANTS[name])
    for _ in range(repeats):
        for name in names:
            best[name] = min(best[name], _timed(lambda name=name: step(VARIANTS[name])))
    weight_bytes = batch * height * width * k * k * FLOAT_BYTES
    floor = weight_bytes / bandwidth["read_bytes_per_s"]
    return {
        "k": k,
        "pixels": batch * height * width,
        "weight_bytes": weight_bytes,
        "seconds": best["shipped"],
        "floor_seconds": floor,
        "ratio": best["shipped"] / floor,
        "variants": best,
        "bandwidth": bandwidth,
        "training": bool(training),
    }


# ---------------------------------------------------------------- training step


def train_step_cost(model_config: ModelConfig, batch_size: int = 8, patch: int = 65, steps: int = 12,
                    skip: int = 2) -> dict:
    """Median seconds per training step, Keras (``train_on_batch``) against plain torch, alternating steps;
    the first ``skip`` steps of each are warm-up and not counted. See the module docstring."""
    if not isinstance(model_config, ModelConfig):
        raise TypeError(f"model_config must be a ModelConfig, received {type(model_config).__name__}")
    for name, value in (("batch_size", batch_size), ("patch", patch), ("steps", steps)):
        _check_positive_int(name, value)
    _check_positive_int("skip", skip, 0)
    model = build_branch_model(model_config)
    net = torch_branch_from_keras(model, model_config).train()
    model.compile(optimizer=keras.optimizers.Adam(ADAM_LEARNING_RATE), loss=SMAPE())
    optimizer = torch.optim.Adam(net.parameters(), lr=ADAM_LEARNING_RATE, eps=KERAS_ADAM_EPSILON)
    rng = np.random.default_rng(0)
    x = torch.from_numpy(rng.uniform(0.0, 1.0, (batch_size, patch, patch,
                                                model_config.input_channels)).astype(np.float32))
    y = torch.from_numpy(rng.uniform(0.0, 1.0, (batch_size, patch, patch, 3)).astype(np.float32))

    def torch_step():
        optimizer.zero_grad(set_to_none=True)
        smape(y, net(x)).backward()
        optimizer.step()

    times = {"keras": [], "torch": []}
    for i in range(skip + steps):
        for side, fn in (("keras", lambda: model.train_on_batch(x, y)), ("torch", torch_step)):
            seconds = _timed(fn)
            if i >= skip:
                times[side].append(seconds)
    keras_s = statistics.median(times["keras"])
    torch_s = statistics.median(times["torch"])
    return {
        "keras_s": keras_s,
        "torch_s": torch_s,
        "ratio": keras_s / torch_s,
        "patches_per_s": batch_size / keras_s,
        "batch_size": batch_size,
        "patch": patch,
        "steps": steps,
        "arch": model_config.arch,
        "threads": torch.get_num_threads(),
    }
