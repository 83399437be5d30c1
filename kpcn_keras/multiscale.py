"""Multiscale denoising: a trained branch denoiser applied to an image pyramid, blended by a learned scale
compositor (docs/method.md §7; Vogels et al. 2018).

The denoiser is any single-frame branch model (``models.build_branch_model``): features (B, H, W, C),
C >= 27 in the ``prep.features`` layout (channels 0..2 the noisy log colour, then conditioning channels),
to log colour (B, H, W, 3), any H and W. :func:`build_multiscale_model` wraps it into a model with the same
input and output:

1. **Padding.** The features are padded at the bottom and right by edge replication to a multiple of
   ``alignment(cfg)`` = 2**(levels-1), and the output is cropped back, so any H and W work (65 x 65 patches).
2. **Pyramid** (``FeatureDownsample``, once per level): every channel halved by ``cfg.downsample``, then
   the channels adjusted so that a level's features approximate those computed from downsampled buffers.
   The downsampling is a separable stride-2 filter w, coarse pixel Y = Σ_k w_k x[2Y + k] per axis:

   - "average": 2x2 average pooling, w = (1/2, 1/2) at k = 0, 1 (the block of the coarse pixel);
   - "bicubic": Keys' cubic (a = -0.5) stretched by 2, as an image resizer downsamples by 2 with
     antialiasing: w = (-3, -9, 29, 111, 111, 29, -9, -3) / 256 at k = -3 .. 4, edges replicated
     (``BICUBIC_TAPS``). It passes less noise (Σ w² = 0.404 a axis against 1/2, a noise variance of 0.164
     against 1/4 in 2-D: Choi et al. downsample so "for increased noise reduction", report §3.1.1), keeps
     constants and linear ramps (w is symmetric about the block's centre, Σ w = 1), and rings: its negative
     lobes can take a non-negative channel slightly below 0 beside a bright edge.

   The adjustments, for either filter:

   - gradients (``dx_*``, ``dy_*``) x 2: a forward difference across a coarse pixel spans two fine pixels
     (exact for a linear ramp, away from the last row and column where a gradient is 0 by convention, and,
     for "bicubic", from the replicated edges);
   - relative variances (``relvar_*``, f = log(1 + v)): the variance of Σ w_k x_k over independent pixels
     is Σ w_k² v_k, so f -> log1p(Σ w_k² expm1(f_k)) with the 2-D weights w_i w_j, taken in the variance
     domain and evaluated stably for f up to the features' 300. For "average" this is the report's division
     by 4, f -> log1p(mean(expm1(f)) / 4) over the 2x2 block; for "bicubic" the report's "divided by 4"
     would overstate the variance 1.5-fold (0.164 v against v / 4), and the squared weights, all positive,
     keep it >= 0 where the filter's negative lobes would not;
   - colour and conditioning channels (index >= 27: branch one-hot, λ map): filtered as they are.

   Channel roles come from ``prep.features.FEATURE_NAMES``.
3. **Denoising.** The same denoiser object (shared weights) filters every level. It is wrapped in
   ``InferenceOnly``: frozen (``trainable = False``; the report trains the compositor alone, §2.2.1) and
   always run with ``training=False``, so its dropout stays off and its batch norm uses moving statistics
   while the compositor trains.
4. **Composition**, coarsest to finest, ONE compositor network (shared weights) for every adjacent pair:
   o_{L-1} = d_{L-1}; o_l = blend(d_l, o_{l+1}); the output is o_0. The compositor (``build_compositor``, a
   nested functional model named ``"compositor"``) sees concat(d_l, U o_{l+1}) (6 channels), runs
   ``depth - 1`` conv + ReLU layers of ``width`` filters and a 1x1 head α = sigmoid(.) in [0, 1]:

       o = f + α (U c - U D f)                          kind "alpha"   (ScaleBlend)
       o = f + α (U'c - U D f),  U'c[p] = Σ_j w_p[j] c[floor(p/2) + j]   kind "kernel"

   with f = d_l, c = o_{l+1}, U the 2x2 nearest upsampling, D the 2x2 average pooling, all in the log
   colour domain; D is the average whatever the pyramid's filter, since D U = 1 makes α = 1 an exact
   replacement of each 2x2 block's mean by the coarse pixel. The kernel compositor has a second 1x1 head of
   kernel_size² logits; w_p is their softmax (``layers.softmax_kernels``) and j runs over the kernel's
   offsets in coarse pixels, edge replicated: tap (i, j) of a k x k kernel (row-major) reads the coarse
   pixel (i - k//2, j - k//2) coarse pixels from floor(p/2). Since (U c)[p + 2j] = c[floor(p/2) + j], U'c
   is a dilation-2 kernel application on U c (``DilatedKernelApply``). Both heads start at zero: α = 0.5
   and box kernels.
5. **α regulariser** (§3.1): γ · max(0.5 - mean(α), 0) per application of the compositor (levels - 1
   terms), mean over the whole α batch at its (padded) level resolution. ``AlphaRegulariser`` adds it
   with ``add_loss``, so ``model.fit`` minimises the compiled loss plus these terms; it does not change α.
6. **Per-scale supervision** (``cfg.scale_supervision`` w > 0; report §3.1.1, after Choi et al.): the
   composite outputs o_l of the levels 0 < l < levels - 1 (``multiscale_output(levels=...)``) are each
   compared, by the training loss, with the target taken down the same pyramid (``image_pyramid``: padded,
   then ``Downsample2x`` with ``cfg.downsample``, l times), and w times each term is added to the losses
   (``ScaleSupervision``, an identity on the model's output). The coarsest level is left out: its output is
   the frozen denoiser's, which no trained weight moves, so its term would be a constant.

Tiled inference: :func:`multiscale_radius` bounds the receptive radius R in fine pixels. A tile's input
must start at a multiple of ``alignment(cfg)`` (so that it downsamples on the image's own 2x2 grid), times the
denoiser's own alignment for a unet denoiser (:func:`tile_alignment`), and reach at
least R pixels past the kept region on every inner side; the kept pixels then equal an untiled run up to
float rounding (the end of a tile's input needs no alignment).

Every layer here uses ``keras.ops`` only and is registered (package ``kpcn``), so ``.keras`` files load
without ``custom_objects`` once this module is imported. One compositor shared by two branches must live in
one functional graph (:func:`multiscale_output`), not in two nested multiscale models: Keras 3.15 saves a
layer shared by two nested models once and then cannot load the file.
"""

from __future__ import annotations

import itertools
import math

import keras
from keras import ops

from kpcn_keras.config import DOWNSAMPLES, CompositorConfig

# PadToMultiple and CropLike live in layers.py (the U-Net pads too); imported here, where they were first
from kpcn_keras.layers import (
    CropLike,
    KernelApply,
    PadToMultiple,
    _ceil_div,
    _positive_int,
    _shape_str,
    kernel_apply,
    pad_edge,
)
from prep.bounds import is_integer, is_number
from prep.features import FEATURE_NAMES, NUM_FEATURES

__all__ = [
    "ALIGN",
    "AlphaRegulariser",
    "BICUBIC_TAPS",
    "CompositorConfig",
    "CropLike",
    "DilatedKernelApply",
    "Downsample2x",
    "FeatureDownsample",
    "InferenceOnly",
    "PadToMultiple",
    "ScaleBlend",
    "ScaleSupervision",
    "Upsample2x",
    "alignment",
    "alpha_maps",
    "build_alpha_model",
    "build_compositor",
    "build_multiscale_model",
    "compositor_of",
    "compositor_trunk_radius",
    "denoiser_of",
    "feature_runs",
    "image_pyramid",
    "multiscale_output",
    "multiscale_radius",
    "pyramid_reach",
    "tile_alignment",
]

COLOUR_CHANNELS = 3  # the denoiser's output, and the compositor's colour inputs
ALPHA_TARGET = 0.5  # the report's threshold of the α regulariser (§3.1)
# relvar pooling: up to here the direct log1p/expm1 form is used (it keeps small values accurate, where the
# max-shifted form cancels); expm1 overflows float32 near 88.7, so larger values take the shifted form
_RELVAR_DIRECT_MAX = 20.0


def _keys_cubic(x: float, a: float = -0.5) -> float:
    """Keys' cubic convolution kernel (1981); a = -0.5 is the one that reproduces quadratics, the usual
    "bicubic" of image resizers."""
    x = abs(x)
    if x <= 1.0:
        return (a + 2.0) * x**3 - (a + 3.0) * x**2 + 1.0
    if x < 2.0:
        return a * x**3 - 5.0 * a * x**2 + 8.0 * a * x - 4.0 * a
    return 0.0


# The bicubic downsampling filter per axis, tap k reading x[2Y + k]: the cubic stretched by the factor 2 about
# the coarse pixel's centre 2Y + 1/2, (-3, -9, 29, 111, 111, 29, -9, -3) / 256, exact in float32 and summing to 1
BICUBIC_START = -3
BICUBIC_TAPS = tuple(_keys_cubic((k - 0.5) / 2.0) / 2.0 for k in range(BICUBIC_START, 1 - BICUBIC_START + 1))
# how far a downsampling step reads past the two pixels of its block, in pixels of the finer level
DOWNSAMPLE_REACH = {"average": 0, "bicubic": -BICUBIC_START}


# ---------------------------------------------------------------- configuration (CompositorConfig: kpcn_keras.config)


def alignment(cfg: CompositorConfig) -> int:
    """2**(levels - 1): the pyramid's coarsest pixel in fine pixels. Tiles must start at multiples of it."""
    return 2 ** (cfg.levels - 1)


ALIGN = alignment(CompositorConfig())


def tile_alignment(cfg: CompositorConfig, denoiser_alignment: int = 1) -> int:
    """What a tile's input must start at a multiple of for exact tiling: ``alignment(cfg)`` times the
    denoiser's own (``models.input_alignment``, a unet's pooling grid), since the denoiser runs on level
    l's image, whose pixel (y, x) is fine pixel (2**l y, 2**l x), for every l < levels."""
    return alignment(cfg) * _positive_int("denoiser_alignment", denoiser_alignment)


def compositor_trunk_radius(cfg: CompositorConfig) -> int:
    """Chebyshev radius of the compositor's heads on its inputs, in pixels of the pair's fine level."""
    return (cfg.depth - 1) * (cfg.conv_size // 2)


def pyramid_reach(cfg: CompositorConfig, level: int) -> int:
    """How far, in fine pixels, a level-``level`` pixel of the pyramid reads past its own 2**level fine pixels:
    b (2**level - 1), b = ``DOWNSAMPLE_REACH`` of the filter (each step reads b pixels of the finer level past
    the block, whose pixels each reach the finer level's own reach further)."""
    return DOWNSAMPLE_REACH[cfg.downsample] * (2**level - 1)


def multiscale_radius(denoiser_radius: int, cfg: CompositorConfig) -> int:
    """A bound R (fine pixels) on the receptive radius of ``build_multiscale_model(denoiser, cfg)`` given the
    denoiser's radius r (``models.receptive_radius``): output pixel p depends only on input pixels q with
    max(|qy - py|, |qx - px|) <= R.

    Per axis, let e_l bound how far the fine pixels that o_l[P] depends on reach past the 2**l fine pixels
    of level-l pixel P, and p_l = :func:`pyramid_reach` how far a level-l feature pixel reads past them
    (0 for "average" pooling, 3 (2**l - 1) for "bicubic"). The top level is the denoiser alone:
    e_{L-1} = r 2**(L-1) + p_{L-1}. At the pair (l, l+1), with t the compositor trunk radius and
    r_k = kernel_size // 2 (0 for "alpha"):

    - the fine path (compositor and U D on d_l, each d_l on features within r): (max(t, 1) + r) 2**l + p_l;
    - the coarse path: the coarse pixels read, floor(Q/2) for |Q - P| <= t (U c into the compositor) and
      floor(P/2) + j for |j| <= r_k (the kernel), cover level-l pixels within max(t + 1, 2 r_k + 1) of P,
      and each reaches e_{l+1} further: max(t + 1, 2 r_k + 1) 2**l + e_{l+1}.

    e_l is the larger of the two and R = e_0. The coarse path always dominates (p_{l+1} >= p_l), so
    R = r 2**(L-1) + (max(t + 1, 2 r_k + 1) + b) (2**(L-1) - 1), b = 3 for "bicubic" and 0 for "average": a
    21 x 21 kernel compositor (r_k = 10) over 3 levels reads 21 x 3 = 63 fine pixels past the denoiser's own
    4 r. Bottom/right edge padding adds nothing (a padded pixel copies one nearer to p). The test suite
    checks that the bound holds and is reached, and that tiles aligned to ``alignment(cfg)`` with margins R
    reproduce an untiled run.
    """
    if not is_integer(denoiser_radius) or denoiser_radius < 0:
        raise ValueError(f"denoiser_radius must be an integer >= 0, received {denoiser_radius!r}")
    t = compositor_trunk_radius(cfg)
    r_k = cfg.kernel_size // 2 if cfg.kind == "kernel" else 0
    coarse = max(t + 1, 2 * r_k + 1)
    reach = denoiser_radius * 2 ** (cfg.levels - 1) + pyramid_reach(cfg, cfg.levels - 1)
    for level in reversed(range(cfg.levels - 1)):
        scale = 2**level
        reach = max((max(t, 1) + denoiser_radius) * scale + pyramid_reach(cfg, level), coarse * scale + reach)
    return reach


# ---------------------------------------------------------------- feature layout


def _role(name: str) -> str:
    if name.startswith("relvar"):
        return "relvar"
    if name.startswith(("dx_", "dy_")):
        return "gradient"
    return "plain"


def feature_runs(channels: int) -> tuple[tuple[int, int, str], ...]:
    """The (start, stop, role) runs of ``channels`` input channels, role "plain", "gradient" or "relvar"
    from ``prep.features.FEATURE_NAMES``; channels past the 27 features (conditioning) are "plain"."""
    if channels < NUM_FEATURES:
        raise ValueError(f"the feature pyramid needs >= {NUM_FEATURES} channels, received {channels}")
    roles = [_role(name) for name in FEATURE_NAMES] + ["plain"] * (channels - NUM_FEATURES)
    runs, start = [], 0
    for role, group in itertools.groupby(roles):
        stop = start + len(list(group))
        runs.append((start, stop, role))
        start = stop
    return tuple(runs)


# ---------------------------------------------------------------- ops


def _check_even(layer, shape) -> None:
    """Static dims may be None (unknown); runtime dims are ints on torch."""
    h, w = shape[1], shape[2]
    if (h is not None and h % 2) or (w is not None and w % 2):
        raise ValueError(
            f"{type(layer).__name__} {layer.name!r} needs an even height and width, received shape "
            f"{_shape_str(shape)}"
        )


def _quads(x):
    """The four pixels of every 2x2 block, (B, H/2, W/2, C) each: top-left, top-right, bottom-left, bottom-right."""
    return x[:, 0::2, 0::2], x[:, 0::2, 1::2], x[:, 1::2, 0::2], x[:, 1::2, 1::2]


def _mean4(a, b, c, d):
    # one fixed summation order; four equal values average to exactly their value, so D(U c) == c bit for bit
    return ((a + b) + (c + d)) * 0.25


def _downsample(x):
    return _mean4(*_quads(x))


def _upsample(x):
    return ops.repeat(ops.repeat(x, 2, axis=1), 2, axis=2)


def _check_method(method) -> str:
    if method not in DOWNSAMPLES:
        raise ValueError(f"downsample method must be one of {DOWNSAMPLES}, received {method!r}")
    return method


def _bicubic_taps(padded, axis: int):
    """The 8 strided views of ``padded`` (edge-padded by 3 on axis 1 and 2) along ``axis``: view k holds, at
    coarse Y, the pixel 2Y + k + BICUBIC_START of the unpadded image (other axis untouched)."""
    n = ops.shape(padded)[axis] + 2 * BICUBIC_START  # the unpadded length
    if axis == 1:
        return [padded[:, k : k + n : 2] for k in range(len(BICUBIC_TAPS))]
    return [padded[:, :, k : k + n : 2] for k in range(len(BICUBIC_TAPS))]


def _bicubic(x):
    """The bicubic 2x downsampling of (B, H, W, C), H and W even: separable, edges replicated."""
    x = pad_edge(x, -BICUBIC_START)
    for axis in (1, 2):
        taps = _bicubic_taps(x, axis)
        x = sum((w * t for w, t in zip(BICUBIC_TAPS[1:], taps[1:])), BICUBIC_TAPS[0] * taps[0])
    return x


def _downsample_by(x, method: str):
    return _downsample(x) if method == "average" else _bicubic(x)


# the variance gain of the 2-D bicubic filter, Σ_ij (w_i w_j)² = (Σ w²)²: what it leaves of white noise
_BICUBIC_VARIANCE_GAIN = sum(w * w for w in BICUBIC_TAPS) ** 2


def _bicubic_relvar(f):
    """log1p(Σ_ij (w_i w_j)² expm1(f_ij)) over each coarse pixel's 8 x 8 footprint (edges replicated), finite
    with finite gradients for any finite f: directly up to _RELVAR_DIRECT_MAX, else as the separable
    log-sum-exp log(Σ w² e^f + 1 - Σ w²), each axis shifted by its own (constant for the gradient) max."""
    padded = pad_edge(f, -BICUBIC_START)
    squares = [w * w for w in BICUBIC_TAPS]
    direct = ops.expm1(ops.minimum(padded, _RELVAR_DIRECT_MAX))
    shifted, biggest = padded, padded
    for axis in (1, 2):
        taps = _bicubic_taps(direct, axis)
        direct = sum((s * t for s, t in zip(squares[1:], taps[1:])), squares[0] * taps[0])
        taps = _bicubic_taps(shifted, axis)
        m = ops.stop_gradient(_max_of(taps))
        shifted = m + ops.log(sum((s * ops.exp(t - m) for s, t in zip(squares[1:], taps[1:])),
                                  squares[0] * ops.exp(taps[0] - m)))
        biggest = _max_of(_bicubic_taps(biggest, axis))
    # log(e^h + c), c = 1 - Σ w² > 0, shifted by the larger of the two
    c = math.log(1.0 - _BICUBIC_VARIANCE_GAIN)
    top = ops.stop_gradient(ops.maximum(shifted, c))
    shifted = top + ops.log(ops.exp(shifted - top) + ops.exp(c - top))
    return ops.where(biggest > _RELVAR_DIRECT_MAX, shifted, ops.log1p(direct))


def _max_of(tensors):
    out = tensors[0]
    for t in tensors[1:]:
        out = ops.maximum(out, t)
    return out


def _pool_relvar(a, b, c, d):
    """log1p(mean(expm1(f)) / 4) over the four quads, finite with finite gradients for any finite f."""
    capped = [ops.expm1(ops.minimum(q, _RELVAR_DIRECT_MAX)) for q in (a, b, c, d)]
    direct = ops.log1p(((capped[0] + capped[1]) + (capped[2] + capped[3])) * 0.0625)
    # log(mean(e^f)/4 + 3/4) with e^m factored out; m >= 0 keeps exp(-m) <= 1, and the max is a constant
    # for the gradient (the expression does not depend on it)
    m = ops.stop_gradient(ops.maximum(ops.maximum(ops.maximum(a, b), ops.maximum(c, d)), 0.0))
    shifted_sum = (ops.exp(a - m) + ops.exp(b - m)) + (ops.exp(c - m) + ops.exp(d - m))
    shifted = m + ops.log(shifted_sum * 0.0625 + 0.75 * ops.exp(-m))
    return ops.where(m > _RELVAR_DIRECT_MAX, shifted, direct)




# ---------------------------------------------------------------- layers


@keras.saving.register_keras_serializable(package="kpcn")
class Upsample2x(keras.layers.Layer):
    """U: 2x2 nearest-neighbour upsampling, (B, H, W, C) -> (B, 2H, 2W, C)."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.input_spec = keras.layers.InputSpec(ndim=4)

    def call(self, x):
        return _upsample(x)

    def compute_output_shape(self, input_shape):
        b, h, w, c = input_shape
        return (b, None if h is None else 2 * h, None if w is None else 2 * w, c)


@keras.saving.register_keras_serializable(package="kpcn")
class Downsample2x(keras.layers.Layer):
    """D: (B, H, W, C) -> (B, H/2, W/2, C) by ``method`` (module docstring): "average", 2x2 average pooling
    (the default, and the D of the blend), or "bicubic". H and W must be even."""

    def __init__(self, method: str = "average", **kwargs):
        super().__init__(**kwargs)
        self.method = _check_method(method)
        self.input_spec = keras.layers.InputSpec(ndim=4)

    def build(self, input_shape):
        _check_even(self, input_shape)

    def call(self, x):
        _check_even(self, ops.shape(x))
        return _downsample_by(x, self.method)

    def get_config(self):
        config = super().get_config()
        config["method"] = self.method
        return config

    def compute_output_shape(self, input_shape):
        _check_even(self, input_shape)
        b, h, w, c = input_shape
        return (b, _ceil_div(h, 2), _ceil_div(w, 2), c)


@keras.saving.register_keras_serializable(package="kpcn")
class FeatureDownsample(Downsample2x):
    """One pyramid step of a feature image (B, H, W, C >= 27) -> (B, H/2, W/2, C): ``method`` ("average" 2x2
    pooling or "bicubic") with the per-role adjustments of the module docstring (gradients x 2, relative
    variances filtered by the squared weights in the variance domain, everything else filtered as it is).
    H and W must be even."""

    def build(self, input_shape):
        super().build(input_shape)
        channels = input_shape[-1]
        if channels is None or channels < NUM_FEATURES:
            raise ValueError(
                f"FeatureDownsample {self.name!r} needs >= {NUM_FEATURES} feature channels (prep.features "
                f"layout), received shape {_shape_str(input_shape)}"
            )
        self._runs = feature_runs(channels)
        self.input_spec = keras.layers.InputSpec(ndim=4, axes={-1: channels})

    def call(self, x):
        _check_even(self, ops.shape(x))
        if self.method == "average":
            quads = _quads(x)
            mean = _mean4(*quads)

            def relvar(start, stop):
                return _pool_relvar(*(q[..., start:stop] for q in quads))
        else:
            mean = _bicubic(x)

            def relvar(start, stop):
                return _bicubic_relvar(x[..., start:stop])
        parts = []
        for start, stop, role in self._runs:
            if role == "relvar":
                parts.append(relvar(start, stop))
            elif role == "gradient":
                parts.append(mean[..., start:stop] * 2.0)
            else:
                parts.append(mean[..., start:stop])
        return ops.concatenate(parts, axis=-1)


@keras.saving.register_keras_serializable(package="kpcn")
class ScaleBlend(keras.layers.Layer):
    """Inputs ``[fine f (B, H, W, C), coarse_up (B, H, W, C), alpha (B, H, W, 1 or C)]`` ->
    f + alpha (coarse_up - U D f): the fine image's 2x2 block means replaced, by the fraction alpha, with the
    upsampled coarse image (U c for Vogels' compositor, U'c for the kernel one). H and W must be even.
    alpha = 0 returns f exactly; alpha = 1 gives D(out) = c for coarse_up = U c."""

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        self.input_spec = [keras.layers.InputSpec(ndim=4)] * 3

    def build(self, input_shape):
        if len(input_shape) != 3:
            raise ValueError(f"ScaleBlend expects [fine, coarse_up, alpha], received {len(input_shape)} inputs")
        fine, coarse_up, alpha = input_shape
        _check_even(self, fine)
        if tuple(fine[1:]) != tuple(coarse_up[1:]) or alpha[-1] not in (1, fine[-1], None):
            raise ValueError(
                "ScaleBlend expects fine and coarse_up of one shape and alpha with 1 or their channels, received "
                f"shapes {_shape_str(fine)}, {_shape_str(coarse_up)}, {_shape_str(alpha)}"
            )

    def call(self, inputs):
        fine, coarse_up, alpha = inputs
        _check_even(self, ops.shape(fine))
        return fine + alpha * (coarse_up - _upsample(_downsample(fine)))

    def compute_output_shape(self, input_shape):
        _check_even(self, input_shape[0])
        return tuple(input_shape[0])


@keras.saving.register_keras_serializable(package="kpcn")
class DilatedKernelApply(KernelApply):
    """Inputs ``[colour (B, H, W, C), logits (B, H, W, k*k)]`` -> (B, H, W, C): like ``KernelApply`` with the
    taps ``dilation`` pixels apart (edge-replicated). On colour = U c with dilation 2 this is the kernel
    compositor's upsampling U'c[p] = Σ_j w_p[j] c[floor(p/2) + j]."""

    def __init__(self, kernel_size: int, dilation: int = 2, **kwargs):
        super().__init__(kernel_size, **kwargs)
        self.dilation = _positive_int("dilation", dilation)

    def call(self, inputs):
        colour, logits = inputs
        return kernel_apply(colour, logits, self.kernel_size, self.dilation)

    def get_config(self):
        config = super().get_config()
        config["dilation"] = self.dilation
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class AlphaRegulariser(keras.layers.Layer):
    """Identity on an α map (B, H, W, 1) that adds ``gamma * max(0.5 - mean(α), 0)`` to the model's losses
    (report §3.1: it keeps α from collapsing to 0, i.e. to the fine image alone). The gradient is -gamma / N
    on each of the N α values while their mean is below 0.5, and 0 above."""

    def __init__(self, gamma: float, **kwargs):
        super().__init__(**kwargs)
        if not is_number(gamma) or not 0.0 <= gamma < math.inf:
            raise ValueError(f"gamma must be a finite number >= 0, received {gamma!r}")
        self.gamma = float(gamma)
        self.input_spec = keras.layers.InputSpec(ndim=4, axes={-1: 1})

    def call(self, alpha):
        self.add_loss(self.gamma * ops.relu(ALPHA_TARGET - ops.mean(alpha)))
        return alpha

    def compute_output_shape(self, input_shape):
        return tuple(input_shape)

    def get_config(self):
        config = super().get_config()
        config["gamma"] = self.gamma
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class ScaleSupervision(keras.layers.Layer):
    """Inputs ``[output, target_1, colour_1, target_2, colour_2, ...]`` -> ``output`` unchanged, adding
    ``weight * Σ_l loss(target_l, colour_l)`` to the model's losses: per-scale supervision (module docstring),
    each level's composite colour against the target taken down the pyramid to its size. ``loss`` is the
    phase's training loss (a ``keras.losses.Loss``, saved with the layer), so each term is what that loss
    would be at the finest level; any target channels it reads besides the reference (the noisy colour, λ)
    are taken down with it."""

    def __init__(self, loss, weight: float, **kwargs):
        super().__init__(**kwargs)
        if isinstance(loss, dict):
            loss = keras.saving.deserialize_keras_object(loss)
        if not isinstance(loss, keras.losses.Loss):
            raise ValueError(f"loss must be a keras.losses.Loss, received {loss!r}")
        if not is_number(weight) or not 0.0 <= weight < math.inf:
            raise ValueError(f"weight must be a finite number >= 0, received {weight!r}")
        self.loss_fn, self.weight = loss, float(weight)

    def build(self, input_shape):
        if len(input_shape) < 3 or len(input_shape) % 2 == 0:
            raise ValueError(f"ScaleSupervision expects [output, target, colour, ...] with target and colour in "
                             f"pairs, received {len(input_shape)} inputs")

    def call(self, inputs):
        output, *pairs = inputs
        terms = [self.loss_fn(pairs[i], pairs[i + 1]) for i in range(0, len(pairs), 2)]
        self.add_loss(self.weight * sum(terms[1:], terms[0]))
        return output

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0])

    def get_config(self):
        config = super().get_config()
        config.update(loss=keras.saving.serialize_keras_object(self.loss_fn), weight=self.weight)
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class InferenceOnly(keras.layers.Wrapper):
    """Applies the wrapped layer (a trained denoiser) with ``training=False`` whatever mode the caller runs
    in, so its dropout is off and its batch norm uses moving statistics while another part trains; a
    Functional model would otherwise pass ``fit``'s ``training=True`` down to it. Not trainable unless
    ``trainable=True`` is given; the flag is set on the wrapped layer too (it is the same object)."""

    def __init__(self, layer, trainable: bool = False, **kwargs):
        super().__init__(layer, trainable=trainable, **kwargs)
        self.trainable = trainable  # again, now that the wrapped layer is tracked, so the flag reaches it

    def call(self, inputs):
        return self.layer(inputs, training=False)

    def compute_output_shape(self, input_shape):
        return self.layer.compute_output_shape(input_shape)


# ---------------------------------------------------------------- models


def build_compositor(cfg: CompositorConfig) -> keras.Model:
    """The scale compositor network, named "compositor": inputs ``fine`` and ``coarse_up`` (None, None, 3)
    -> α (None, None, 1) for kind "alpha", [α, kernel logits (None, None, kernel_size²)] for "kernel".

    Its layer names start with ``compositor_``, unlike any branch network's (``models.build_branch_model``
    says why names must not repeat within one trained model)."""
    if not isinstance(cfg, CompositorConfig):
        raise TypeError(f"cfg must be a CompositorConfig, received {type(cfg).__name__}")
    p = "compositor_"
    fine = keras.Input(shape=(None, None, COLOUR_CHANNELS), name=f"{p}fine")
    coarse_up = keras.Input(shape=(None, None, COLOUR_CHANNELS), name=f"{p}coarse_up")
    x = keras.layers.Concatenate(name=f"{p}stack")([fine, coarse_up])
    for i in range(cfg.depth - 1):
        x = keras.layers.Conv2D(cfg.width, cfg.conv_size, padding="same", activation="relu", name=f"{p}conv{i}")(x)
    # zero heads: α = 0.5 (the regulariser's threshold, an even blend) and box kernels at the start
    alpha = keras.layers.Conv2D(
        1, 1, activation="sigmoid", kernel_initializer="zeros", bias_initializer="zeros", name=f"{p}alpha"
    )(x)
    outputs = alpha
    if cfg.kind == "kernel":
        logits = keras.layers.Conv2D(
            cfg.kernel_size**2, 1, kernel_initializer="zeros", bias_initializer="zeros", name=f"{p}kernel_logits"
        )(x)
        outputs = [alpha, logits]
    return keras.Model([fine, coarse_up], outputs, name="compositor")


def _check_compositor(compositor, cfg: CompositorConfig) -> None:
    if not isinstance(compositor, keras.Model) or compositor.name != "compositor":
        raise ValueError(f"compositor must be a keras.Model named 'compositor', received {compositor!r}")
    want = [(None, None, None, 1)] + ([(None, None, None, cfg.kernel_size**2)] if cfg.kind == "kernel" else [])
    have = [tuple(t.shape) for t in compositor.outputs]
    if have != want:
        raise ValueError(
            f"compositor outputs {have} do not fit a {cfg.kind!r} compositor with kernel_size "
            f"{cfg.kernel_size}: expected {want}"
        )


def _check_denoiser(denoiser) -> int:
    """The denoiser's input channel count, after checking its input and output shapes."""
    if not isinstance(denoiser, keras.Model):
        raise TypeError(f"denoiser must be a keras.Model, received {type(denoiser).__name__}")
    in_shape, out_shape = denoiser.input_shape, denoiser.output_shape
    if not (isinstance(in_shape, tuple) and len(in_shape) == 4 and in_shape[-1] and in_shape[-1] >= NUM_FEATURES):
        raise ValueError(
            f"denoiser {denoiser.name!r} must take one (B, H, W, C >= {NUM_FEATURES}) feature input, "
            f"received input shape {in_shape}"
        )
    if not (isinstance(out_shape, tuple) and len(out_shape) == 4 and out_shape[-1] == COLOUR_CHANNELS):
        raise ValueError(
            f"denoiser {denoiser.name!r} must output (B, H, W, {COLOUR_CHANNELS}) colour, received output "
            f"shape {out_shape}"
        )
    return in_shape[-1]


def image_pyramid(x, cfg: CompositorConfig, prefix: str) -> list:
    """The pyramid of an image (a symbolic (B, H, W, C)) that the features' pyramid is taken on, finest first:
    padded as they are to ``alignment(cfg)``, then halved by ``Downsample2x(cfg.downsample)`` with no channel
    adjustment (a colour, an albedo, a training target). Layer names start with ``prefix``."""
    levels = [PadToMultiple(alignment(cfg), name=f"{prefix}pad")(x)]
    for level in range(1, cfg.levels):
        levels.append(Downsample2x(cfg.downsample, name=f"{prefix}{level}")(levels[-1]))
    return levels


def multiscale_output(features, denoiser, cfg: CompositorConfig, compositor: keras.Model, prefix: str = "",
                      levels: list | None = None):
    """The multiscale graph on a symbolic ``features`` tensor (B, H, W, C) -> symbolic log colour (B, H, W, 3),
    for building one functional model in which several branches share a compositor (and possibly a
    denoiser). ``denoiser``: a model (wrapped here in a new ``InferenceOnly`` named ``prefix + "denoiser"``)
    or an ``InferenceOnly`` to share. Layer names start with ``prefix``. ``levels``: a list to which the
    composite outputs o_l of the levels 1 .. levels - 2 are appended, finest first, each at its padded level
    size (per-scale supervision, module docstring).

    Why not nest two multiscale models that share a compositor: Keras 3 (3.15) writes a layer shared by two
    nested models once and then cannot load the .keras file; layers shared within one functional graph
    load fine.
    """
    if not isinstance(cfg, CompositorConfig):
        raise TypeError(f"cfg must be a CompositorConfig, received {type(cfg).__name__}")
    frozen = denoiser if isinstance(denoiser, InferenceOnly) else None
    channels = _check_denoiser(frozen.layer if frozen else denoiser)
    if features.shape[-1] != channels:
        raise ValueError(f"denoiser takes {channels} channels, received features of shape {tuple(features.shape)}")
    _check_compositor(compositor, cfg)
    if frozen is None:
        frozen = InferenceOnly(denoiser, name=f"{prefix}denoiser")

    level_features = [PadToMultiple(alignment(cfg), name=f"{prefix}pad")(features)]
    for level in range(1, cfg.levels):
        level_features.append(
            FeatureDownsample(cfg.downsample, name=f"{prefix}pyramid{level}")(level_features[-1]))
    denoised = [frozen(x) for x in level_features]

    out, composites = denoised[-1], []
    for level in reversed(range(cfg.levels - 1)):
        coarse_up = Upsample2x(name=f"{prefix}upsample{level}")(out)
        heads = compositor([denoised[level], coarse_up])
        if cfg.kind == "kernel":
            alpha, logits = heads
            coarse_up = DilatedKernelApply(cfg.kernel_size, 2, name=f"{prefix}coarse_kernels{level}")(
                [coarse_up, logits]
            )
        else:
            alpha = heads
        alpha = AlphaRegulariser(cfg.gamma, name=f"{prefix}alpha_reg{level}")(alpha)
        out = ScaleBlend(name=f"{prefix}blend{level}")([denoised[level], coarse_up, alpha])
        composites.append(out)
    if levels is not None:
        levels.extend(reversed(composites[:-1]))  # built coarsest first; the last is o_0
    return CropLike(name=f"{prefix}crop")([out, features])


def build_multiscale_model(
    denoiser: keras.Model,
    cfg: CompositorConfig,
    name: str = "multiscale",
    *,
    compositor: keras.Model | None = None,
) -> keras.Model:
    """Functional model: input ``features`` (None, None, C), C the denoiser's input channels (>= 27) ->
    log colour (None, None, 3), through the pyramid, the denoiser at every level and the compositor.

    ``compositor``: an existing compositor (``build_compositor``, or one loaded from a run); a new one by
    default. To share one between branches inside a larger model, build that model with
    :func:`multiscale_output` instead of nesting two of these (see there). The denoiser is frozen
    (``denoiser.trainable`` becomes False) and always runs in inference mode (``InferenceOnly``).
    """
    channels = _check_denoiser(denoiser)
    if not isinstance(cfg, CompositorConfig):
        raise TypeError(f"cfg must be a CompositorConfig, received {type(cfg).__name__}")
    if compositor is None:
        compositor = build_compositor(cfg)
    features = keras.Input(shape=(None, None, channels), name="features")
    out = multiscale_output(features, denoiser, cfg, compositor)
    return keras.Model(features, out, name=name)


def compositor_of(model: keras.Model) -> keras.Model:
    """The nested compositor of a multiscale model (its weights can be saved or inspected alone)."""
    try:
        layer = model.get_layer("compositor")
    except ValueError:
        raise ValueError(f"model {model.name!r} has no layer named 'compositor' (not a multiscale model)") from None
    return layer


def denoiser_of(model: keras.Model) -> keras.Model:
    """The denoiser a multiscale model wraps (the same object that was passed in, or its loaded copy)."""
    try:
        wrapper = model.get_layer("denoiser")
    except ValueError:
        wrapper = None
    if not isinstance(wrapper, InferenceOnly):
        raise ValueError(f"model {model.name!r} has no InferenceOnly layer named 'denoiser' (not a multiscale model)")
    return wrapper.layer


def build_alpha_model(model: keras.Model) -> keras.Model:
    """Model sharing ``model``'s weights that returns the α maps, finest first: α_l (B, ceil(H/2**l),
    ceil(W/2**l), 1) for l = 0 .. levels-2, the blend weight of level l with level l+1 (for figures)."""
    regs = [layer for layer in model.layers if isinstance(layer, AlphaRegulariser)]
    if not regs:
        raise ValueError(f"model {model.name!r} has no AlphaRegulariser layers (not a multiscale model)")
    # model.layers is in graph order and each finer pair reads the coarser pair's output: coarsest first
    maps = [CropLike(2**level)([reg.output, model.input]) for level, reg in enumerate(reversed(regs))]
    return keras.Model(model.input, maps, name=f"{model.name}_alpha")


def alpha_maps(model: keras.Model, features) -> list:
    """The α maps (numpy arrays) of :func:`build_alpha_model` on a batch of ``features``, finest first, always a
    list: Keras returns a model's lone output bare, so with 2 levels the α model gives one array, not a list."""
    maps = build_alpha_model(model).predict_on_batch(features)
    return [keras.ops.convert_to_numpy(m) for m in (maps if isinstance(maps, (list, tuple)) else [maps])]
