"""Branch denoising networks: KPCN, residual KPAL, direct-prediction DPCN and U-Net KPCN (docs/method.md §4).

A branch network (diffuse or specular) maps its input (B, H, W, ``input_channels``), channels last, any H and W,
to the filtered colour in the log domain log(1 + x), (B, H, W, 3). The input is the ``in_channels`` features of
``prep.features`` (channels 0..2 the noisy branch colour), then the conditioning channels the configuration asks
for, appended by :func:`network_input` (the one place that knows them):

- ``branch_channels``: two one-hot channels, (1, 0) for diffuse and (0, 1) for specular, so that one shared
  network serves both branches (docs/method.md §4) and knows which it is filtering;
- ``slope_channel``: one channel holding log(λ) of the asymmetric loss slope λ >= 1, per pixel (0 for λ = 1),
  so that one network serves a range of λ chosen at inference (Vogels et al. 2018 §5.3).

Architectures (``ModelConfig.arch``):

- ``"kpcn"``: Bako et al.'s plain stack: ``depth`` convolutions (``conv_size``, ``width`` filters, ReLU), then a
  1x1 convolution to k*k logits (the kernel head) and ``KernelApply`` on the noisy colour. The default is
  8 layers: 7 convolutions of 32 3x3 filters and the kernel head; the paper's vanilla network is 9: 8
  convolutions of 100 5x5 filters and the kernel head. With ``dilations`` the i-th convolution's taps are
  ``dilations[i]`` pixels apart: the ``dilated`` preset's 1, 2, 4, 8, 4, 2, 1 reach 22 pixels each way at the
  cost of the plain stack's 7 (the low-frequency blotches it is for are 10-30 pixels across). Every offset
  within that reach is some sum of ±dilations, so no pixel of the field is skipped (the "gridding" of equal dilations).
- ``"kpal"``: Vogels et al.'s residual network: a stem convolution to ``width`` filters, then ``depth``
  residual blocks of two convolutions, each followed by batch norm (if enabled) and dropout, the block
  input added back before the final ReLU; then the same kernel-predicting head. The report's 28-layer
  network is ``depth=13`` (1 + 2 * 13 + 1 layers).
- ``"dpcn"``: the ``"kpcn"`` trunk with a 1x1 convolution to 3 channels that is **added to the noisy
  colour** (residual direct prediction): the network predicts a correction, not the colour itself. The sum
  is clamped to the colour feature's range [0, ``prep.colour.LOG_COLOUR_MAX``], which a kernel output
  never leaves beyond float32 rounding (it is a convex combination of the input colour).
- ``"unet"``: a kernel-predicting network on a U-Net trunk (the ``cpu`` stack sees 15 x 15 pixels,
  and low-frequency blotches 10-30 pixels across survive it). ``levels`` resolutions L, level l of
  ``ModelConfig.unet_widths()[l]`` filters (``width`` growing by ``width_growth`` a level, at most
  ``width_cap``). Encoder: at every level ``depth`` conv units, then (above the coarsest) 2x2 average
  pooling to the next; the coarsest level's ``depth`` units are the bottleneck. Decoder, coarsest to
  finest: 2x2 nearest upsampling of the level below, concatenated with the encoder's output at this
  level (the skip connection), then ``depth`` conv units, so the first of them is the "resize + conv" and
  reads both. Then the same zero-initialised 1x1 kernel head and ``KernelApply`` on the noisy colour at
  full resolution. Any H and W: the features are edge-padded at the bottom and right to a multiple of
  :func:`input_alignment` = 2**(L-1) (``layers.PadToMultiple``) and the logits cropped back
  (``layers.CropLike``) before the kernels are applied, so the kernel sees the frame's own border. The
  ``unet`` preset (config.PRESETS) is cpu's training with 4 levels of 32/48/72/96 filters, one convolution
  per level each way, 13x13 kernels.

  Receptive radius (exact, :func:`trunk_radius`; a = conv_size // 2, d = depth): per axis the trunk at an
  output pixel reaches d a (2**(L-1) - 1) fine pixels through the decoder convolutions of levels 0..L-2,
  d a (2**L - 1) through the bottleneck and the encoder convolutions below it, and up to 2**(L-1) - 1 more
  where the upsampling rounds a level's reach out to whole pixels of the next level (2**l at the step from
  l to l + 1; some output pixel takes every step's worst case, as its coordinate's bits choose each
  rounding), so R = (d a + 1)(2**(L-1) - 1) + d a (2**L - 1): 29 for the preset. It depends on where a
  pixel sits in the 2**(L-1) pooling grid, so tiles of a tiled inference must start on that grid
  (:func:`input_alignment`; ``denoise.Denoiser``), not only overlap by R.

λ after the trunk (``ModelConfig.slope_module``; docs/method.md §5): the slope channel bypasses the trunk and joins
its activations through N 1x1 convolutions (:func:`_slope_module`) before the kernel head; with
``slope_mixture`` J, the trunk's activations feed a head of J kernels instead, each applied to the colour, and
the module's 1x1 head gives J logits per pixel that mix the J filtered colours (:func:`_slope_mixture`).
:func:`slope_module_parts` cuts either into what runs once per frame and what runs for each λ map.

Initialisation: the last 1x1 layer has zero weights and bias (a λ mixture's J kernels start apart:
:func:`mixture_bias`). An untrained KPCN/KPAL/U-Net therefore predicts
all-equal logits, i.e. a uniform k x k box filter (a sensible smoother rather than noise), and an untrained
DPCN returns its input unchanged. Gradients still reach the trunk from the second step on.

Layout: the contract is channels last, but the convolutions run channels first inside (one ``Permute``
after the input, one after each 1x1 head). Keras's torch backend wraps every channels-last convolution in
two copies (to NCHW, then back to torch's channels-last memory format) and a transpose of its output; a
channels-first convolution on the permuted input is handed the same memory unchanged, torch keeps the
activations in channels-last memory format throughout, and the permute back at the head is free. Measured
on 2 CPU threads, cpu preset trunk: 8 x 65 x 65 forward + backward 48.6 -> 40.5 ms (plain torch 38.5),
outputs bit-identical. The convolutions are ``layers.FusedConv2D``, which on torch passes the bias to the
convolution instead of adding it in a second pass (outputs bit-identical too; frame 91 -> 65 ms). Models saved
before (channels-last Keras ``Conv2D``) load and run unchanged; ``build_branch_model(...,
data_format="channels_last")`` still builds that layout.

Models contain only built-in Keras layers and the registered ``kpcn>`` layers, so ``model.save("x.keras")``
and ``keras.models.load_model`` work without ``custom_objects`` once ``kpcn_keras.layers`` is imported
(importing this module does that; ``load_model`` below is a convenience).
"""

from __future__ import annotations

import keras
import numpy as np

from kpcn_keras.config import ALBEDO_NETWORK, ARCHS, COLOUR_CHANNELS, DILATED_ARCHS, ModelConfig
from kpcn_keras.layers import (
    CropLike,
    FinalColour,
    FusedConv2D,
    KernelApply,
    MixColours,
    PadToMultiple,
    TakeChannels,
    softmax_kernels,
)
from prep.colour import LOG_COLOUR_MAX
from prep.errors import OptionError
from prep.features import BRANCHES

__all__ = [
    "ARCHS",
    "COLOUR_CHANNELS",
    "ModelConfig",
    "albedo_input",
    "build_albedo_training_model",
    "build_branch_model",
    "build_final_model",
    "build_kernel_model",
    "input_alignment",
    "kept_of",
    "load_model",
    "mixture_bias",
    "network_input",
    "receptive_radius",
    "slope_module_parts",
    "slope_plane",
    "trunk_layers",
    "trunk_radius",
]

FINAL_INPUTS = {branch: f"{branch}_input" for branch in BRANCHES}  # input names of a final-colour model
TRUNK_FORMAT = "channels_first"  # the convolutions' layout inside a branch model (see the module docstring)
DATA_FORMATS = ("channels_first", "channels_last")  # "channels_last": the layout of models saved before
TO_CHANNELS_FIRST = (3, 1, 2)  # keras.layers.Permute dims: (H, W, C) -> (C, H, W)
TO_CHANNELS_LAST = (2, 3, 1)  # and back
# The names of a trunk's layers after the model's prefix (``diffuse_trunk03_relu``, ``specular_enc1_00_conv``,
# ``shared_skip0``): what :func:`trunk_layers` finds, and what the builders below name them
TRUNK_PARTS = ("trunk", "stem", "res", "enc", "dec", "pool", "up", "skip")


def network_input(features, cfg: ModelConfig, branch: str, slope=None) -> np.ndarray:
    """``features`` (..., H, W, in_channels) with the conditioning channels of ``cfg`` appended (float32).

    ``slope``: λ >= 1 for a network with a slope channel, a number or a per-pixel array broadcastable to
    (..., H, W); it must be None for a network without one (the network would not know it was asked).
    """
    features = np.asarray(features, np.float32)
    if features.shape[-1] != cfg.in_channels:
        raise ValueError(f"expected {cfg.in_channels} feature channels, received shape {features.shape}")
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, received {branch!r}")
    if cfg.slope_channel != (slope is not None):
        raise OptionError("slope", "is needed by a network trained with a slope input channel" if cfg.slope_channel
                          else "is only for a network trained with a slope input channel (--slope-input)")
    extra = []
    if cfg.branch_channels:
        extra += [np.float32(branch == b) for b in BRANCHES]
    if slope is not None:
        extra.append(_log_slope(slope))
    if not extra:
        return features
    spatial = features.shape[:-1]
    planes = [np.broadcast_to(np.asarray(e, np.float32), spatial)[..., None] for e in extra]
    return np.concatenate([features] + planes, axis=-1)


def albedo_input(diffuse_features, albedo) -> np.ndarray:
    """The albedo network's input: the diffuse features (..., H, W, in_channels), float32, with channels 0-2, the
    colour a kernel-predicting network filters, replaced by the noisy albedo clipped to [0, 1] (..., H, W, 3),
    in place. The network's kernels then filter the albedo, seeing what the diffuse network sees (the
    albedo's own differences and relative variance among the guides): docs/method.md §1."""
    if diffuse_features.dtype != np.float32 or diffuse_features.shape[:-1] != np.shape(albedo)[:-1]:
        raise ValueError(f"expected float32 features over the albedo's pixels {np.shape(albedo)[:-1]}, received "
                         f"{diffuse_features.dtype} {diffuse_features.shape}")
    np.clip(albedo, 0.0, 1.0, out=diffuse_features[..., :COLOUR_CHANNELS], casting="same_kind")
    return diffuse_features


def slope_plane(slope, shape: tuple[int, int]) -> np.ndarray:
    """The slope channel (1, H, W, 1) of an (H, W) = ``shape`` window at λ = ``slope`` (a number or an (H, W)
    map): what :func:`slope_module_parts`' ``module`` takes last, as :func:`network_input` writes it."""
    return np.ascontiguousarray(np.broadcast_to(_log_slope(slope), shape)[None, ..., None])


def _log_slope(slope) -> np.ndarray:
    """log λ (float32) of the slope channel; OptionError unless every λ is finite and >= 1."""
    slope = np.asarray(slope, np.float64)
    if not np.all(np.isfinite(slope)) or np.any(slope < 1.0):
        raise OptionError("slope", f"must be finite and >= 1, received {slope if slope.ndim == 0 else slope.min()}")
    return np.log(slope).astype(np.float32)


def trunk_radius(cfg: ModelConfig) -> int:
    """Chebyshev radius of the trunk's receptive field (pixels), i.e. of the logits' dependence on features.

    For a unet the largest over the positions of the pooling grid (the module docstring derives it)."""
    per_conv = cfg.conv_size // 2
    if cfg.arch == "unet":
        reach, coarsest = cfg.depth * per_conv, 2 ** (cfg.levels - 1)
        return (reach + 1) * (coarsest - 1) + reach * (2 * coarsest - 1)
    if cfg.arch in DILATED_ARCHS:
        return sum(cfg.trunk_dilations()) * per_conv  # the 1x1 head adds nothing
    return (1 + 2 * cfg.depth) * per_conv


def input_alignment(cfg: ModelConfig) -> int:
    """The multiple an input's height and width must start on for exact tiling: a tile whose window starts
    at a multiple of it pools the frame's own blocks. 1 for the single-resolution archs, 2**(levels-1) for
    a unet (which pads any input to a multiple of it itself)."""
    return 2 ** (cfg.levels - 1) if cfg.arch == "unet" else 1


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


def trunk_layers(model: keras.Model) -> list:
    """The layers of a branch model's trunk (:data:`TRUNK_PARTS`), from the features up to, not including, the
    kernel head (or a dpcn's correction): what ``kpcn_keras.precision`` may run in bfloat16."""
    prefix = f"{model.name}_"
    return [layer for layer in model.layers if layer.name.startswith(prefix)
            and layer.name[len(prefix):].startswith(TRUNK_PARTS)]


def _conv_class(data_format: str):
    """The convolution layer of a layout: ``FusedConv2D`` channels first, Keras's own for the old layout."""
    return FusedConv2D if data_format == "channels_first" else keras.layers.Conv2D


def _conv_unit(x, cfg: ModelConfig, name: str, activate: bool, data_format: str, width: int | None = None,
               dilation: int = 1):
    """Conv -> [BN] -> [ReLU] -> [Dropout] of ``width`` filters (default ``cfg.width``), taps ``dilation``
    pixels apart. The conv has no bias when batch norm follows (BN's beta is it)."""
    x = _conv_class(data_format)(
        cfg.width if width is None else width,
        cfg.conv_size,
        padding="same",
        dilation_rate=dilation,
        use_bias=not cfg.batchnorm,
        data_format=data_format,
        name=f"{name}_conv",
    )(x)
    if cfg.batchnorm:
        x = keras.layers.BatchNormalization(axis=1 if data_format == "channels_first" else -1, name=f"{name}_bn")(x)
    if activate:
        x = keras.layers.ReLU(name=f"{name}_relu")(x)
    if cfg.dropout > 0.0:
        x = keras.layers.Dropout(cfg.dropout, name=f"{name}_drop")(x)
    return x


def _unet_trunk(x, cfg: ModelConfig, prefix: str, data_format: str):
    """The U-Net of the module docstring on ``x`` (its sides multiples of ``input_alignment(cfg)``)."""
    axis = 1 if data_format == "channels_first" else -1
    widths = cfg.unet_widths()
    skips = []
    for level, width in enumerate(widths):
        if level:
            x = keras.layers.AveragePooling2D(2, data_format=data_format, name=f"{prefix}pool{level}")(x)
        for i in range(cfg.depth):
            x = _conv_unit(x, cfg, f"{prefix}enc{level}_{i:02d}", True, data_format, width)
        skips.append(x)
    for level in reversed(range(cfg.levels - 1)):
        x = keras.layers.UpSampling2D(2, data_format=data_format, interpolation="nearest",
                                      name=f"{prefix}up{level}")(x)
        x = keras.layers.Concatenate(axis=axis, name=f"{prefix}skip{level}")([x, skips[level]])
        for i in range(cfg.depth):
            x = _conv_unit(x, cfg, f"{prefix}dec{level}_{i:02d}", True, data_format, widths[level])
    return x


def _trunk(features, cfg: ModelConfig, prefix: str, data_format: str):
    if cfg.arch == "unet":
        return _unet_trunk(features, cfg, prefix, data_format)
    if cfg.arch in DILATED_ARCHS:
        x = features
        for i, dilation in enumerate(cfg.trunk_dilations()):
            x = _conv_unit(x, cfg, f"{prefix}trunk{i:02d}", activate=True, data_format=data_format, dilation=dilation)
        return x
    x = _conv_unit(features, cfg, f"{prefix}stem", activate=True, data_format=data_format)
    for i in range(cfg.depth):
        y = _conv_unit(x, cfg, f"{prefix}res{i:02d}a", activate=True, data_format=data_format)
        y = _conv_unit(y, cfg, f"{prefix}res{i:02d}b", activate=False, data_format=data_format)
        x = keras.layers.Add(name=f"{prefix}res{i:02d}_add")([x, y])
        x = keras.layers.ReLU(name=f"{prefix}res{i:02d}_relu")(x)
    return x


def _slope_module(x, slope, cfg: ModelConfig, prefix: str, data_format: str):
    """The loss-specialisation module on the trunk's activations ``x``: log λ (``slope``, the features' last
    channel, laid out as ``x``) joined (``<prefix>slope_join``, what :func:`slope_module_parts` cuts at), then
    ``cfg.slope_module`` 1x1 convolutions of ``cfg.width`` filters and ReLUs. 1x1, so that λ at a pixel sets
    that pixel's kernel alone, whose taps read colour, not λ: a map changed in a region changes the output in
    that region alone."""
    first = data_format == "channels_first"
    align = input_alignment(cfg)
    if align > 1:
        slope = PadToMultiple(align, name=f"{prefix}slope_pad")(slope)
    if first:
        slope = keras.layers.Permute(TO_CHANNELS_FIRST, name=f"{prefix}slope_first")(slope)
    x = keras.layers.Concatenate(axis=1 if first else -1, name=f"{prefix}slope_join")([x, slope])
    for i in range(cfg.slope_module):
        x = _conv_class(data_format)(cfg.width, 1, data_format=data_format, name=f"{prefix}special{i:02d}_conv")(x)
        x = keras.layers.ReLU(name=f"{prefix}special{i:02d}_relu")(x)
    return x


def slope_module_parts(model: keras.Model) -> tuple[keras.Model, keras.Model]:
    """``(trunk, module)`` of a branch model with a specialisation module, with its weights (copied): ``trunk`` maps
    the network input to what λ does not change, for one frame (run it once; :func:`kept_of` gives it as a list):
    the activations λ joins, then the noisy colour the kernels filter, or for a λ mixture its J filtered colours;
    ``module`` maps ``[*that, log λ]`` (:func:`slope_plane`) to the model's output (run it again for each λ map).
    The module reads no other feature, so a new map costs the module, the copy of λ into it and what follows.
    ValueError for a model without the module."""
    join = f"{model.name}_slope_join"
    if join not in {layer.name for layer in model.layers}:
        raise ValueError(f"model {model.name!r} has no slope module (trained without --slope-module)")
    # cut from a copy: Keras clones the graph nodes of a model whose input is an intermediate tensor, and the
    # model cut from then no longer saves ("could not find node key")
    copy = keras.models.clone_model(model)
    copy.set_weights(model.get_weights())
    names = {layer.name for layer in copy.layers}
    kept = [copy.get_layer(join).input[0],
            copy.get_layer(f"{model.name}_filtered" if f"{model.name}_filtered" in names
                           else f"{model.name}_noisy_colour").output]
    slope = copy.get_layer(f"{model.name}_slope").output
    return (keras.Model(copy.input, kept, name=f"{model.name}_trunk"),
            keras.Model([*kept, slope], copy.output, name=f"{model.name}_module"))


def kept_of(trunk: keras.Model, batch) -> list[np.ndarray]:
    """What :func:`slope_module_parts`' ``trunk`` gives for ``batch``, as the list its ``module`` takes first
    (Keras hands back a model's one output bare, not in a list)."""
    out = trunk.predict_on_batch(batch)
    return [keras.ops.convert_to_numpy(x) for x in (out if isinstance(out, (list, tuple)) else [out])]


def build_branch_model(cfg: ModelConfig, name: str = "diffuse", *, data_format: str = TRUNK_FORMAT) -> keras.Model:
    """Functional model: input ``features`` (None, None, cfg.input_channels) -> filtered colour (None, None, 3).

    Every layer's name starts with the model's (``diffuse_trunk00_conv``): Keras's torch backend registers a
    model's torch parameters by variable path, and two nested networks with equal paths (diffuse and
    specular in one joint model) would leave one network's gradients out of ``zero_grad``, so they would
    accumulate from step to step.

    ``data_format`` is the convolutions' layout inside (the input and output stay channels last):
    ``TRUNK_FORMAT`` by default, ``"channels_last"`` for the layout of models saved before the trunk ran
    channels first (same weights, same outputs; it exists to test that they still load and agree).
    """
    if not isinstance(cfg, ModelConfig):
        raise TypeError(f"cfg must be a ModelConfig, received {type(cfg).__name__}")
    if data_format not in DATA_FORMATS:
        raise ValueError(f"data_format must be one of {DATA_FORMATS}, received {data_format!r}")
    first = data_format == "channels_first"
    p = f"{name}_"
    features = keras.Input(shape=(None, None, cfg.input_channels), name="features")
    colour = TakeChannels(0, COLOUR_CHANNELS, name=f"{p}noisy_colour")(features)
    align = input_alignment(cfg)
    trunk_input = features
    if cfg.slope_module:  # λ, the last channel, bypasses the trunk
        trunk_input = TakeChannels(0, cfg.input_channels - 1, name=f"{p}features_without_slope")(features)
    x = PadToMultiple(align, name=f"{p}pad")(trunk_input) if align > 1 else trunk_input
    x = keras.layers.Permute(TO_CHANNELS_FIRST, name=f"{p}to_channels_first")(x) if first else x
    x = trunk = _trunk(x, cfg, p, data_format)
    # what the layers after the join crop to: the slope channel, so that the module reads no other feature
    like = features
    if cfg.slope_module:
        like = TakeChannels(cfg.input_channels - 1, cfg.input_channels, name=f"{p}slope")(features)
        x = _slope_module(x, like, cfg, p, data_format)
    if cfg.arch == "dpcn":
        correction = _conv_class(data_format)(
            COLOUR_CHANNELS, 1, kernel_initializer="zeros", bias_initializer="zeros", data_format=data_format,
            name=f"{p}correction",
        )(x)
        if first:
            correction = keras.layers.Permute(TO_CHANNELS_LAST, name=f"{p}correction_last")(correction)
        out = keras.layers.Add(name=f"{p}colour_sum")([colour, correction])
        # a kernel output is a convex combination of the input colour and stays in its range by itself;
        # a direct prediction is clamped to it, else one extreme pixel maps back to inf (exp(c) - 1)
        out = keras.layers.ReLU(max_value=LOG_COLOUR_MAX, name=f"{p}colour_out")(out)
    elif not cfg.slope_mixture:
        logits = _head(x, cfg.kernel_size**2, like, cfg, f"{p}kernel_logits", f"{p}logits_last", f"{p}crop",
                       data_format)
        out = KernelApply(cfg.kernel_size, name=f"{p}kernel_apply")([colour, logits])
    else:
        out = _slope_mixture(trunk, x, colour, features, like, cfg, p, data_format)
    return keras.Model(features, out, name=name)


def _head(x, channels: int, like, cfg: ModelConfig, name: str, last_name: str, crop_name: str, data_format: str,
          bias: np.ndarray | None = None):
    """A zero-initialised 1x1 convolution of ``x`` to ``channels`` (its bias ``bias`` if given), channels last
    and cropped to the size of ``like`` (the features, or a channel of them)."""
    head = _conv_class(data_format)(channels, 1, kernel_initializer="zeros", bias_initializer="zeros",
                                    data_format=data_format, name=name)
    out = head(x)
    if bias is not None:
        head.bias.assign(bias.astype(np.float32))
    if data_format == "channels_first":
        # a free view: torch already holds the logits in channels-last memory, each pixel's taps contiguous
        out = keras.layers.Permute(TO_CHANNELS_LAST, name=last_name)(out)
    if input_alignment(cfg) > 1:  # the kernels filter the frame's own colour, edge-replicated at its border
        out = CropLike(name=crop_name)([out, like])
    return out


def mixture_bias(kernel_size: int, parts: int) -> np.ndarray:
    """Starting logits of a λ mixture's ``parts`` kernels, tap t = i k + j of kernel m at channel m k² + t:
    Gaussians -d²/(2σ²) of the tap's distance d from the centre, σ geometric from k / 2 (near a box) down to
    1/2 (near the pixel itself). Kernels that start alike would get alike gradients and stay alike; these
    start as a choice between smoothing and keeping, which λ is about."""
    c = kernel_size // 2
    i, j = np.mgrid[0:kernel_size, 0:kernel_size]
    d2 = ((i - c) ** 2 + (j - c) ** 2).ravel().astype(np.float64)
    sigmas = np.geomspace(kernel_size / 2, 0.5, parts)
    return np.concatenate([-d2 / (2 * sigma**2) for sigma in sigmas])


def _slope_mixture(trunk, module, colour, features, like, cfg: ModelConfig, prefix: str, data_format: str):
    """The λ mixture (``cfg.slope_mixture`` J): J kernels from the trunk's activations, each applied to the noisy
    colour (``<prefix>filtered``: J colours, what :func:`slope_module_parts` caches), mixed per pixel by the
    softmax of J logits the specialisation module predicts from the activations and λ (``MixColours``). The
    mixture of normalised kernels is a normalised kernel, so the output stays a kernel-filtered colour."""
    k2, parts = cfg.kernel_size**2, cfg.slope_mixture
    logits = _head(trunk, parts * k2, features, cfg, f"{prefix}kernel_logits", f"{prefix}logits_last", f"{prefix}crop",
                   data_format, bias=mixture_bias(cfg.kernel_size, parts))
    filtered = [KernelApply(cfg.kernel_size, name=f"{prefix}kernel_apply{m}")(
        [colour, TakeChannels(m * k2, (m + 1) * k2, name=f"{prefix}kernel{m}_logits")(logits)]) for m in range(parts)]
    filtered = keras.layers.Concatenate(axis=-1, name=f"{prefix}filtered")(filtered)
    mix = _head(module, parts, like, cfg, f"{prefix}mixture_logits", f"{prefix}mixture_last",
                f"{prefix}mixture_crop", data_format)
    return MixColours(COLOUR_CHANNELS, name=f"{prefix}mix")([filtered, mix])


def build_final_model(networks: dict, input_channels: int, name: str = "final") -> keras.Model:
    """A model of the whole denoiser: inputs ``diffuse_input`` and ``specular_input`` (each branch's network
    input) and ``albedo`` (the noisy albedo) -> the final linear colour, ``networks[branch]`` applied to each
    branch (the same model twice for a shared network; or any callable building a symbolic graph, such as
    ``multiscale.multiscale_output``) and the branch transforms inverted (``FinalColour``).

    Joint fine-tuning trains it on the final colour (docs/method.md §6); the networks are nested models, so
    each can be taken out again by name (``model.get_layer("diffuse")``).
    """
    inputs = {b: keras.Input(shape=(None, None, input_channels), name=FINAL_INPUTS[b]) for b in BRANCHES}
    albedo = keras.Input(shape=(None, None, COLOUR_CHANNELS), name="albedo")
    colours = [networks[branch](inputs[branch]) for branch in BRANCHES]
    out = FinalColour(name="final_colour")(colours + [albedo])
    return keras.Model({**{FINAL_INPUTS[b]: inputs[b] for b in BRANCHES}, "albedo": albedo}, out, name=name)


def build_albedo_training_model(albedo: keras.Model, input_channels: int) -> keras.Model:
    """The albedo network ``albedo`` (a branch network named :data:`ALBEDO_NETWORK`, :func:`albedo_input` in,
    the filtered albedo out) trained as the denoiser uses it: inputs ``features`` (its input), ``irradiance``
    and ``specular`` (the reference's diffuse irradiance and specular colour, log domain) -> the final linear
    colour, the reference's irradiance times the network's albedo plus the reference's specular
    (``FinalColour``). Its loss is then the error the albedo leaves in the frame, where the irradiance
    makes it visible; ``model.get_layer("albedo")`` is the network again."""
    features = keras.Input(shape=(None, None, input_channels), name="features")
    irradiance = keras.Input(shape=(None, None, COLOUR_CHANNELS), name="irradiance")
    specular = keras.Input(shape=(None, None, COLOUR_CHANNELS), name="specular")
    out = FinalColour(name="final_colour")([irradiance, specular, albedo(features)])
    return keras.Model({"features": features, "irradiance": irradiance, "specular": specular}, out,
                       name=f"{ALBEDO_NETWORK}_training")


def build_kernel_model(model: keras.Model) -> keras.Model:
    """Model sharing ``model``'s weights that returns the softmaxed per-pixel kernels (B, H, W, k*k): for a λ
    mixture, the mixture of its kernels.

    Tap t = i*k + j is row-major with the centre at (k//2, k//2); reshape to (B, H, W, k, k) to view a
    kernel. Raises ValueError for a model without exactly one ``KernelApply`` (e.g. dpcn).
    """
    appliers = sorted((layer for layer in model.layers if isinstance(layer, KernelApply)), key=lambda la: la.name)
    mixers = [layer for layer in model.layers if isinstance(layer, MixColours)]
    if mixers and len(appliers) > 1:
        # a λ mixture: the kernel applied is the mixture of its kernels (the application is linear in the kernel)
        weights = softmax_kernels(mixers[0].input[1])
        kernels = weights[..., 0:1] * softmax_kernels(appliers[0].input[1])
        for m, applier in enumerate(appliers[1:], 1):
            kernels = kernels + weights[..., m : m + 1] * softmax_kernels(applier.input[1])
        return keras.Model(model.input, kernels, name=f"{model.name}_kernels")
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
