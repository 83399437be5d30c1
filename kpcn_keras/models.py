"""Branch denoising networks: vanilla KPCN, residual KPAL and direct-prediction DPCN (seed report §2.2, §3.4).

A branch network (diffuse or specular) maps ``features`` (B, H, W, in_channels), channels last, any H and W,
whose channels 0..2 are the noisy branch colour in the log domain log(1 + x), to the filtered colour in the same
domain, (B, H, W, 3). Architectures (``ModelConfig.arch``):

- ``"kpcn"``: Bako et al.'s plain stack: ``depth`` convolutions (``conv_size``, ``width`` filters, ReLU), then a
  1x1 convolution to k*k logits and ``KernelApply`` on the noisy colour. The default depth 7 plus the head
  is 8 layers; the paper's vanilla network is 9 (8 hidden 5x5 layers of 100 filters + output).
- ``"kpal"``: Vogels et al.'s residual network: a stem convolution to ``width`` filters, then ``depth``
  residual blocks of two convolutions, each followed by batch norm (if enabled) and dropout, the block
  input added back before the final ReLU; then the same kernel-predicting head. The report's 28-layer
  network is ``depth=13`` (1 + 2 * 13 + 1 layers).
- ``"dpcn"``: the ``"kpcn"`` trunk with a 1x1 convolution to 3 channels that is **added to the noisy
  colour** (residual direct prediction): the network predicts a correction, not the colour itself. The sum
  is clamped to the colour feature's range [0, ``prep.features.LOG_COLOUR_MAX``], which a kernel output
  never leaves (it is a convex combination of the input colour).

Initialisation: the last 1x1 layer has zero weights and bias. An untrained KPCN/KPAL therefore predicts
all-equal logits, i.e. a uniform k x k box filter (a sensible smoother rather than noise), and an untrained
DPCN returns its input unchanged. Gradients still reach the trunk from the second step on.

Models contain only built-in Keras layers and the registered ``kpcn>`` layers, so ``model.save("x.keras")``
and ``keras.models.load_model`` work without ``custom_objects`` once ``kpcn_keras.layers`` is imported
(importing this module does that; ``load_model`` below is a convenience).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Optional

import keras

from kpcn_keras.layers import KernelApply, TakeChannels, check_kernel_size, softmax_kernels
from prep.errors import OptionError
from prep.features import LOG_COLOUR_MAX

__all__ = [
    "ARCHS",
    "COLOUR_CHANNELS",
    "ModelConfig",
    "build_branch_model",
    "build_kernel_model",
    "load_model",
    "receptive_radius",
    "trunk_radius",
]

ARCHS = ("kpcn", "kpal", "dpcn")
COLOUR_CHANNELS = 3  # features[..., :3] is the noisy branch colour (data contract)


@dataclass
class ModelConfig:
    """Architecture of one branch network. ``batchnorm=None`` means: True for kpal, False otherwise.

    ``depth`` counts trunk convolutions for kpcn/dpcn and residual blocks for kpal. ``dropout`` is the drop
    rate (the report's keep probability 0.7 is ``dropout=0.3``); it is applied after every trunk
    convolution when > 0. ``kernel_size`` is the predicted kernel's side (odd; paper 21) and is ignored by
    dpcn.
    """

    arch: str = "kpcn"
    in_channels: int = 27
    width: int = 32
    depth: int = 7
    conv_size: int = 3
    kernel_size: int = 13
    dropout: float = 0.0
    batchnorm: Optional[bool] = None

    def __post_init__(self):
        if self.arch not in ARCHS:
            raise OptionError("arch", f"must be one of {ARCHS}, received {self.arch!r}")
        for field in ("in_channels", "width", "depth", "conv_size", "kernel_size"):
            value = getattr(self, field)
            if isinstance(value, bool) or not isinstance(value, int):
                raise OptionError(field, f"must be an integer, received {value!r}")
        if self.in_channels < COLOUR_CHANNELS:
            raise OptionError(
                "in_channels", f"must be >= {COLOUR_CHANNELS} (channels 0..2 are the colour), received {self.in_channels}"
            )
        if self.width < 1:
            raise OptionError("width", f"must be >= 1, received {self.width}")
        if self.depth < 1:
            raise OptionError("depth", f"must be >= 1, received {self.depth}")
        if self.conv_size < 1 or self.conv_size % 2 == 0:
            raise OptionError("conv_size", f"must be a positive odd integer, received {self.conv_size}")
        try:
            check_kernel_size(self.kernel_size)
        except ValueError as exc:
            raise OptionError("kernel_size", str(exc).removeprefix("kernel size ")) from None
        if isinstance(self.dropout, bool) or not isinstance(self.dropout, (int, float)):
            raise OptionError("dropout", f"must be a number in [0, 1), received {self.dropout!r}")
        if not 0.0 <= float(self.dropout) < 1.0:
            raise OptionError("dropout", f"must be in [0, 1), received {self.dropout!r}")
        self.dropout = float(self.dropout)
        if self.batchnorm is None:
            self.batchnorm = self.arch == "kpal"
        elif not isinstance(self.batchnorm, bool):
            raise OptionError("batchnorm", f"must be a bool or None, received {self.batchnorm!r}")

    def to_dict(self) -> dict:
        """Plain JSON-able dict; ``batchnorm`` is resolved (never None)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ModelConfig":
        """Inverse of ``to_dict``; unknown keys are an error (a typo would otherwise be silently ignored)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise OptionError("model", f"has unknown ModelConfig keys {unknown}; known keys are {sorted(names)}")
        return cls(**d)


def trunk_radius(cfg: ModelConfig) -> int:
    """Chebyshev radius of the trunk's receptive field (pixels), i.e. of the logits' dependence on features."""
    per_conv = cfg.conv_size // 2
    n_convs = cfg.depth if cfg.arch in ("kpcn", "dpcn") else 1 + 2 * cfg.depth
    return n_convs * per_conv  # the 1x1 head adds nothing


def receptive_radius(cfg: ModelConfig) -> int:
    """Radius R such that output pixel p depends only on input pixels q with max(|qy-py|, |qx-px|) <= R.

    For kernel models the output at p combines the logits at p (trunk radius) with the colour within k//2
    of p, so R = max(trunk, k//2), not their sum. A tiled inference whose tiles overlap by at least R (and
    discard R pixels at every inner tile edge) reproduces the untiled result; the test suite checks the
    bound is exact. Batch norm must run in inference mode for this to hold (training mode mixes the batch).
    """
    t = trunk_radius(cfg)
    if cfg.arch == "dpcn":
        return t
    return max(t, cfg.kernel_size // 2)


def _conv_unit(x, cfg: ModelConfig, name: str, activate: bool):
    """Conv -> [BN] -> [ReLU] -> [Dropout]. The conv has no bias when batch norm follows (BN's beta is it)."""
    x = keras.layers.Conv2D(
        cfg.width,
        cfg.conv_size,
        padding="same",
        use_bias=not cfg.batchnorm,
        name=f"{name}_conv",
    )(x)
    if cfg.batchnorm:
        x = keras.layers.BatchNormalization(name=f"{name}_bn")(x)
    if activate:
        x = keras.layers.ReLU(name=f"{name}_relu")(x)
    if cfg.dropout > 0.0:
        x = keras.layers.Dropout(cfg.dropout, name=f"{name}_drop")(x)
    return x


def _trunk(features, cfg: ModelConfig):
    if cfg.arch in ("kpcn", "dpcn"):
        x = features
        for i in range(cfg.depth):
            x = _conv_unit(x, cfg, f"trunk{i:02d}", activate=True)
        return x
    x = _conv_unit(features, cfg, "stem", activate=True)
    for i in range(cfg.depth):
        y = _conv_unit(x, cfg, f"res{i:02d}a", activate=True)
        y = _conv_unit(y, cfg, f"res{i:02d}b", activate=False)
        x = keras.layers.Add(name=f"res{i:02d}_add")([x, y])
        x = keras.layers.ReLU(name=f"res{i:02d}_relu")(x)
    return x


def build_branch_model(cfg: ModelConfig, name: str = "diffuse") -> keras.Model:
    """Functional model: input ``features`` (None, None, cfg.in_channels) -> filtered colour (None, None, 3)."""
    if not isinstance(cfg, ModelConfig):
        raise TypeError(f"cfg must be a ModelConfig, received {type(cfg).__name__}")
    features = keras.Input(shape=(None, None, cfg.in_channels), name="features")
    colour = TakeChannels(0, COLOUR_CHANNELS, name="noisy_colour")(features)
    x = _trunk(features, cfg)
    if cfg.arch == "dpcn":
        correction = keras.layers.Conv2D(
            COLOUR_CHANNELS, 1, kernel_initializer="zeros", bias_initializer="zeros", name="correction"
        )(x)
        out = keras.layers.Add(name="colour_sum")([colour, correction])
        # a kernel output is a convex combination of the input colour and stays in its range by itself;
        # a direct prediction is clamped to it, else one extreme pixel maps back to inf (exp(c) - 1)
        out = keras.layers.ReLU(max_value=LOG_COLOUR_MAX, name="colour_out")(out)
    else:
        logits = keras.layers.Conv2D(
            cfg.kernel_size**2, 1, kernel_initializer="zeros", bias_initializer="zeros", name="kernel_logits"
        )(x)
        out = KernelApply(cfg.kernel_size, name="kernel_apply")([colour, logits])
    return keras.Model(features, out, name=name)


def build_kernel_model(model: keras.Model) -> keras.Model:
    """Model sharing ``model``'s weights that returns the softmaxed per-pixel kernels (B, H, W, k*k).

    Tap t = i*k + j is row-major with the centre at (k//2, k//2); reshape to (B, H, W, k, k) to view a
    kernel. Raises ValueError for a model without exactly one ``KernelApply`` (e.g. dpcn).
    """
    appliers = [layer for layer in model.layers if isinstance(layer, KernelApply)]
    if len(appliers) != 1:
        raise ValueError(
            f"model {model.name!r} must contain exactly one KernelApply layer to expose kernels, "
            f"found {len(appliers)} (a dpcn model predicts colour directly)"
        )
    _, logits = appliers[0].input
    kernels = softmax_kernels(logits)
    return keras.Model(model.input, kernels, name=f"{model.name}_kernels")


def load_model(path) -> keras.Model:
    """``keras.models.load_model`` with the kpcn layers registered (they are, by importing this module)."""
    return keras.models.load_model(path)
