"""Per-pixel kernel application for kernel-predicting networks (docs/method.md §4, Bako et al. 2017).

A kernel-predicting network outputs k*k logits per pixel. They are turned into a normalised kernel by a
softmax over the taps and applied to the noisy colour of the same pixel's k x k neighbourhood:

    w[b, y, x, :] = softmax(logits[b, y, x, :])
    out[b, y, x, c] = sum_{i, j} w[b, y, x, i*k + j] * colour_padded[b, y + i, x + j, c]

where tap t = i*k + j is row-major, (i, j) = (k//2, k//2) is the centre, and the colour is padded by k//2 on
each side by edge replication (a constant image stays constant at its borders; zero padding would darken
them). Everything is written with ``keras.ops`` so the layer is backend-agnostic; the project runs it on
torch, where ``KernelApply`` takes a fused fast path (:func:`kernel_apply`, same result up to float
rounding; the tests hold both paths to the same float64 reference). No epsilon is needed: after max
subtraction the softmax denominator is >= 1.

The other layers of the networks: ``FusedConv2D`` (a convolution with its bias fused on torch),
``TakeChannels`` (a channel slice), ``FinalColour`` (the branches back to the linear colour), and the pair
that lets a network with 2x2 pooling take any H and W: ``PadToMultiple`` (edge-replicate at the bottom and
right up to a multiple) and ``CropLike`` (cut back to a reference's size), used by the U-Net trunk
(``models``) and the multiscale pyramid (``multiscale``, which re-exports them from where they were first).
"""

from __future__ import annotations

import keras
import numba
import numpy as np
from keras import ops

from kpcn_keras.config import check_kernel_size
from prep.bounds import is_integer
from prep.colour import ALBEDO_EPS, LOG_LINEAR_MAX

__all__ = [
    "CropLike",
    "FinalColour",
    "FusedConv2D",
    "KernelApply",
    "MixColours",
    "PadToMultiple",
    "TakeChannels",
    "apply_kernels",
    "check_kernel_size",
    "kernel_apply",
    "pad_edge",
    "softmax_kernels",
    "traced_kernel_apply",
]


def softmax_kernels(logits):
    """Softmax over the last axis (the k*k taps), max-subtracted so logits like +-1e4 stay finite.

    Equal logits give exactly uniform weights. The max is a constant for the gradient (the softmax is
    invariant to it), which also avoids the tie-breaking subgradient of ``max``. On torch this is
    ``ops.softmax`` (torch's fused softmax, max-subtracted internally): one pass instead of four ops over
    k*k channels (k=21, 256 x 256: 47 ms against 132 ms).
    """
    if keras.backend.backend() == "torch":
        return ops.softmax(logits, axis=-1)
    return _softmax_kernels_ops(logits)


def _softmax_kernels_ops(logits):
    """``softmax_kernels`` spelled out in ``keras.ops`` (the path of other backends; tested equal)."""
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


def _check_dilation(dilation) -> int:
    """``dilation`` if it is a positive integer (not a bool), else ValueError echoing it."""
    if not is_integer(dilation) or dilation < 1:
        raise ValueError(f"dilation must be a positive integer, received {dilation!r}")
    return dilation


def apply_kernels(colour, weights, k: int, dilation: int = 1):
    """Filter ``colour`` (B, H, W, C) with normalised per-pixel ``weights`` (B, H, W, k*k); returns (B, H, W, C).

    The weights are used as given (no softmax), so this also serves to apply hand-made kernels.
    ``dilation`` d spaces the taps d pixels apart: tap (i, j) reads colour[y + d(i - k//2), x + d(j - k//2)],
    edge-replicated (d = 2 on a nearest-upsampled image reads the coarse image at coarse offsets).
    Implementation: a loop over the k*k shifted views accumulating a weighted sum. Measured on a 2-core CPU
    (k=13, 8 x 65 x 65, forward + backward) it beat stacking the shifted views into a (B, H, W, k*k, C)
    tensor and contracting with einsum/matmul (0.11 s vs 0.13-0.17 s), and it never materialises the stack.
    The weights are split with ``unstack`` rather than sliced per tap: on torch each slice's backward
    allocates a full-size zero gradient, which made the sliced loop three times slower. ``KernelApply``
    on torch uses the faster :func:`kernel_apply` instead; this loop is the path of other backends.
    """
    k = check_kernel_size(k)
    d = _check_dilation(dilation)
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


# Bytes of colour patches gathered per row block of the torch path, so that a block's softmaxed weights
# and patches are still cached (2 MiB L2 per core, 32 MiB shared L3) when they are contracted. Measured
# (k=21, 256 x 256): 2 / 4 / 8 MiB blocks 40 / 31 / 33 ms; larger blocks fall out of cache and slow down.
KERNEL_BLOCK_BYTES = 4 * 2**20


def kernel_apply(colour, logits, k: int, dilation: int = 1):
    """``apply_kernels(colour, softmax_kernels(logits), k, dilation)``: (B, H, W, C), (B, H, W, k*k) -> (B, H, W, C).

    On the torch backend with concrete tensors on the CPU this is a fused, row-blocked torch implementation
    (``_TorchKernelApply``) with a hand-written backward, or, where no gradient is asked (inference), its forward
    alone without the patch gather (:func:`_inference_kernel_apply`); anything else (other backends, symbolic
    tensors) takes the ``keras.ops`` path. The three agree to float rounding (tested, values and gradients).

    Why this form (2-core CPU shared with other jobs, so best of several alternating repeats;
    1 x 256 x 256 inference, k=13 / k=21):

    - the ``keras.ops`` path (four-op softmax + loop over k*k shifted channels-last slices): 51 / 294 ms;
    - the same loop after one fused softmax: 44 / 147 ms (the softmax alone: 3 / ~8 ms);
    - weights transposed to channels-first planes, one contiguous plane per tap: 37 / 151 ms, and its
      autograd backward is far worse (17 s at k=21, 8 x 65 x 65);
    - ``F.unfold`` of the whole image + einsum: 292 / 697 ms (a k*k*C copy per pixel, out of cache);
    - per kernel row, a matmul against a width-unfolded view: 53 / 160 ms;
    - ``torch.compile`` (inductor, CPU) of softmax + gathered weighted sum: 60 / 204 ms, 18 s to compile;
      of softmax + the k*k shifted-tap sum over the whole image: 22 / 59 ms, 42 / 104 s to compile;
    - in the shipped row blocks, the gather of the patches alone (channels last or channels first) costs
      more than the softmax and the contraction together; einsum, broadcast multiply + sum, ``vecdot``
      and a batched matmul for the contraction: einsum wins;
    - row blocks of ``KERNEL_BLOCK_BYTES`` (softmax + gathered patches + einsum while cached): 13 / 31 ms,
      shipped. Through plain autograd its backward lost to the baseline (8 x 65 x 65 forward + backward,
      k=13: 98 vs 60 ms; k=21: 1.2 s vs 0.21 s), hence the hand-written backward.

    Re-measured with ``kpcn_keras.studies.network_costs.kernel_application_cost`` (best of 9): inference
    71 -> 13.6 ms (k=13) and 220 -> 30 ms (k=21); 8 x 65 x 65 forward + backward 73 -> 18.5 ms and 313 -> 57 ms. The
    memory floor (every logit read once: 0.6 / 1.6 ms at the 74 GB/s ``torch.sum`` reached) is out of reach on
    this CPU: the block softmax alone, the k*k exponentials, costs 4.2 / 8.9 ms.
    """
    k = check_kernel_size(k)
    d = _check_dilation(dilation)
    if keras.backend.backend() == "torch" and not _is_symbolic(colour) and not _is_symbolic(logits):
        import torch

        colour = ops.convert_to_tensor(colour)
        logits = ops.convert_to_tensor(logits, dtype=colour.dtype)
        if torch.onnx.is_in_onnx_export():  # the fast paths run numba on numpy, which a trace keeps as constants
            return traced_kernel_apply(colour, logits, k, d)
        # CPU only: on a GPU (H100, 1920 x 1080, k=13) the cache-sized row blocks are many small launches
        # and lost to the shifted-slice loop, 76 against 20 ms
        if isinstance(colour, torch.Tensor) and colour.device.type == "cpu":
            return _torch_kernel_apply(colour, logits, k, d)
    return apply_kernels(colour, softmax_kernels(logits), k, d)


def traced_kernel_apply(colour, logits, k: int, d: int):
    """:func:`kernel_apply` in torch ops a trace records whole (``kpcn_keras.onnx_export``): the k*k shifted
    planes of the edge-padded colour, each cut by offsets from both ends so that the graph holds no frame size
    (it runs at any H and W), weighted by the exponentials of the max-subtracted logits, summed, and divided by
    their sum once (the softmax's normalisation after the sum, one division per colour instead of per tap).
    Taps lead the weights' layout and channels the colour's, so each product broadcasts over a leading axis,
    which onnxruntime runs as a plain loop (measured: against a channels-first product and a softmax over the last
    axis, onnxruntime's Softmax was most of the time). Equal to the other paths to float rounding (tested)."""
    import torch
    import torch.nn.functional as F

    r = (k // 2) * d
    taps = logits.permute(3, 0, 1, 2)  # (k*k, B, H, W)
    e = torch.exp(taps - taps.amax(dim=0, keepdim=True))
    planes = F.pad(colour.permute(0, 3, 1, 2), (r, r, r, r), mode="replicate").permute(1, 0, 2, 3)  # (C, B, ., .)
    out = None
    for i in range(k):
        for j in range(k):
            rows = slice(i * d, (i * d - 2 * r) or None)
            cols = slice(j * d, (j * d - 2 * r) or None)
            term = e[i * k + j : i * k + j + 1] * planes[:, :, rows, cols]
            out = term if out is None else out + term
    return (out / e.sum(dim=0, keepdim=True)).permute(1, 2, 3, 0)


def _is_symbolic(x) -> bool:
    return isinstance(x, keras.KerasTensor)


def _torch_kernel_apply(colour, logits, k: int, d: int):
    import torch
    import torch.nn.functional as F

    if colour.ndim != 4 or logits.ndim != 4 or logits.shape[:3] != colour.shape[:3] or logits.shape[3] != k * k:
        raise ValueError(
            f"kernel_apply(k={k}) expects colour (B, H, W, C) and logits (B, H, W, {k * k}) of the same B, H, W, "
            f"received {tuple(colour.shape)} and {tuple(logits.shape)}"
        )
    r = (k // 2) * d
    # replicate padding works on the trailing dims, hence the round trip through channels first;
    # F.pad's own backward folds the border gradient back onto the edge pixels
    planes = F.pad(colour.permute(0, 3, 1, 2), (r, r, r, r), mode="replicate")
    no_gradient = not torch.is_grad_enabled() or not (colour.requires_grad or logits.requires_grad)
    if no_gradient and colour.dtype in (torch.float32, torch.float64) and logits.dtype == colour.dtype:
        return _inference_kernel_apply(planes.detach().contiguous(), logits.detach().contiguous(), k, d)
    return _TorchKernelApply.apply(planes.permute(0, 2, 3, 1).contiguous(), logits.contiguous(), k, d)


def _inference_kernel_apply(planes, logits, k: int, d: int):
    """The forward alone, where no gradient is asked (inference): per row block the logits are softmaxed by torch
    (vectorised exponentials, the block still cached) and contracted with the edge-padded colour planes
    (B, C, H + 2r, W + 2r) by :func:`_contract_rows`, which reads each tap's colour where it lies instead of
    gathering k*k-tap patches first (the gather was most of this layer's time). The autograd path
    keeps the gather: its backward needs the patches anyway."""
    import torch

    b, h, w, taps = logits.shape
    c = planes.shape[1]
    out = planes.new_empty((b, h, w, c))
    step = _block_rows(b, w, 1, taps, logits.element_size())
    planes_np, out_np = planes.numpy(), out.numpy()
    # named for torch's profiler, as the autograd path is by its Function's name
    with torch.profiler.record_function("KernelApply"):
        for y0 in range(0, h, step):
            y1 = min(h, y0 + step)
            weights = torch.softmax(logits[:, y0:y1], dim=-1)
            _contract_rows(planes_np, weights.numpy(), y0, k, d, out_np)
    return out


@numba.njit(parallel=True, fastmath={"reassoc", "contract"}, cache=True)
def _contract_rows(planes, weights, y0, k, d, out):  # pragma: no cover (compiled)
    """out[b, y0 + y, x, c] = sum_t weights[b, y, x, t] * planes[b, c, y0 + y + d i, x + d j], t = i k + j.

    Per output row the weights are transposed to one contiguous row of W per tap, so that each tap adds
    weight row x colour row along x, W pixels at a time in vector registers (a tap's colour row is the padded
    plane's row shifted by d j). The sums may be fused into multiply-adds and vectorised, float rounding as the
    einsum's; no other fast-math licence (infinities and NaN keep their IEEE meaning). Measured against
    summing each pixel's taps in turn (the taps' stride defeats vectorisation) and the training path's gather
    and einsum, 1 thread, k = 13, a 270 x 270 tile with its block softmax: 17 against 41 and 42 ms."""
    batch, rows, width, taps = weights.shape
    channels = planes.shape[1]
    for n in numba.prange(batch * rows):
        b, y = n // rows, n % rows
        by_tap = np.empty((taps, width), weights.dtype)
        for x in range(width):
            for t in range(taps):
                by_tap[t, x] = weights[b, y, x, t]
        acc = np.zeros((channels, width), out.dtype)
        for i in range(k):
            for j in range(k):
                w = by_tap[i * k + j]
                for ch in range(channels):
                    colour = planes[b, ch, y0 + y + d * i, d * j : d * j + width]
                    sums = acc[ch]
                    for x in range(width):
                        sums[x] += w[x] * colour[x]
        for ch in range(channels):
            for x in range(width):
                out[b, y0 + y, x, ch] = acc[ch, x]


def _block_rows(batch: int, width: int, channels: int, taps: int, itemsize: int) -> int:
    return max(1, KERNEL_BLOCK_BYTES // max(1, batch * width * channels * taps * itemsize))


def _patches(padded, y0: int, y1: int, k: int, d: int):
    """Colour patches of output rows [y0, y1): (B, y1 - y0, W, C, k*k), tap t = i*k + j (a copy)."""
    span = (k - 1) * d + 1
    rows = padded[:, y0 : y1 + span - 1]
    view = rows.unfold(1, span, 1)[..., ::d].unfold(2, span, 1)[..., ::d]  # (B, h, W, C, k_i, k_j)
    b, h, w, c = view.shape[:4]
    return view.reshape(b, h, w, c, k * k)


def _torch_kernel_function():
    import torch

    class TorchKernelApply(torch.autograd.Function):
        """Softmax + per-pixel weighted sum over row blocks, on edge-padded colour (B, H + 2r, W + 2r, C).

        Per block the logits are softmaxed (one fused op, channels last, so each pixel's k*k logits are
        contiguous) and contracted with the block's gathered patches by one batched matmul (einsum)
        while both are cached. The backward recomputes the block softmax instead of storing the weights:
        with q_t = g . patch_t and sum_t w_t q_t = g . out,
            dL/dlogit_t = w_t (q_t - g . out),   dL/dpatch_t = w_t g  (summed back onto the colour by fold).
        """

        @staticmethod
        def forward(ctx, padded, logits, k, d):
            b, h, w, _ = logits.shape
            c = padded.shape[-1]
            out = padded.new_empty((b, h, w, c))
            step = _block_rows(b, w, c, k * k, padded.element_size())
            for y0 in range(0, h, step):
                y1 = min(h, y0 + step)
                weights = torch.softmax(logits[:, y0:y1], dim=-1)
                out[:, y0:y1] = torch.einsum("bhwt,bhwct->bhwc", weights, _patches(padded, y0, y1, k, d))
            ctx.save_for_backward(padded, logits, out)
            ctx.kernel = (k, d)
            return out

        @staticmethod
        @torch.autograd.function.once_differentiable
        def backward(ctx, grad):
            padded, logits, out = ctx.saved_tensors
            k, d = ctx.kernel
            b, h, w, taps = logits.shape
            c = padded.shape[-1]
            grad = grad.contiguous()
            grad_logits = torch.empty_like(logits) if ctx.needs_input_grad[1] else None
            grad_padded = None
            if ctx.needs_input_grad[1]:
                g_dot_out = (grad * out).sum(-1, keepdim=True)
                step = _block_rows(b, w, c, taps, padded.element_size())
                for y0 in range(0, h, step):
                    y1 = min(h, y0 + step)
                    weights = torch.softmax(logits[:, y0:y1], dim=-1)
                    q = torch.einsum("bhwc,bhwct->bhwt", grad[:, y0:y1], _patches(padded, y0, y1, k, d))
                    grad_logits[:, y0:y1] = weights * (q - g_dot_out[:, y0:y1])
            if ctx.needs_input_grad[0]:
                # only where the colour is itself computed (the multiscale compositor); a whole-image pass
                weights = torch.softmax(logits, dim=-1)
                per_tap = grad.permute(0, 3, 1, 2)[:, :, None] * weights.permute(0, 3, 1, 2)[:, None]
                folded = torch.nn.functional.fold(
                    per_tap.reshape(b, c * taps, h * w), padded.shape[1:3], k, dilation=d
                )
                grad_padded = folded.permute(0, 2, 3, 1)
            return grad_padded, grad_logits, None, None

    return TorchKernelApply


class _LazyFunction:
    """Builds the autograd Function on first use, so importing this module does not import torch."""

    def __init__(self, factory):
        self._factory = factory
        self._function = None

    def apply(self, *args):
        if self._function is None:
            self._function = self._factory()
        return self._function.apply(*args)


_TorchKernelApply = _LazyFunction(_torch_kernel_function)


@keras.saving.register_keras_serializable(package="kpcn")
class KernelApply(keras.layers.Layer):
    """Inputs ``[colour (B, H, W, C), logits (B, H, W, k*k)]`` -> (B, H, W, C): softmax the logits over the
    taps and filter the colour with the resulting per-pixel k x k kernels (edge-replicated borders).

    ``kernel_size`` must be a positive odd integer. The layer has no weights. It runs :func:`kernel_apply`
    (on torch a fused row-blocked path with its own backward; see there for what it beat).
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
        return kernel_apply(colour, logits, self.kernel_size)

    def compute_output_shape(self, input_shape):
        colour_shape, _ = input_shape
        return tuple(colour_shape)

    def get_config(self):
        config = super().get_config()
        config["kernel_size"] = self.kernel_size
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class MixColours(keras.layers.Layer):
    """Inputs ``[colours (B, H, W, C * J), logits (B, H, W, J)]`` -> (B, H, W, C): per pixel the J colours
    (channels ``j C .. (j + 1) C - 1`` the j-th) weighted by the softmax of the J logits (max-subtracted). For
    J colours each filtered by a normalised kernel this is the colour filtered by the mixture of those kernels
    (the kernel application is linear in the kernel): a kernel-predicting network's λ mixture (``models``,
    ``ModelConfig.slope_mixture``). No weights."""

    def __init__(self, channels: int = 3, **kwargs):
        super().__init__(**kwargs)
        if not is_integer(channels) or int(channels) < 1:
            raise ValueError(f"channels must be a positive integer, received {channels!r}")
        self.channels = int(channels)

    def build(self, input_shape):
        colours_shape, logits_shape = input_shape
        mixed, parts = colours_shape[-1], logits_shape[-1]
        if mixed is not None and parts is not None and mixed != parts * self.channels:
            raise ValueError(f"MixColours(channels={self.channels}) needs {self.channels} colour channels per logit, "
                             f"received shapes {tuple(colours_shape)} and {tuple(logits_shape)}")

    def call(self, inputs):
        colours, logits = inputs
        c, parts = self.channels, logits.shape[-1]
        # the softmax spelled out over the J slices: the logits arrive as a channels-last view of the head's
        # channels-first output, along whose last axis torch's softmax is 3x slower (J = 2, a 270 x 270 tile)
        z = [logits[..., j : j + 1] for j in range(parts)]
        top = z[0]
        for zj in z[1:]:
            top = ops.maximum(top, zj)
        weights = [ops.exp(zj - top) for zj in z]  # the largest is 1, so their sum is >= 1
        out, total = weights[0] * colours[..., 0:c], weights[0]
        for j in range(1, parts):
            out = out + weights[j] * colours[..., j * c : (j + 1) * c]
            total = total + weights[j]
        return out / total

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0][:-1]) + (self.channels,)

    def get_config(self):
        config = super().get_config()
        config["channels"] = self.channels
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class FusedConv2D(keras.layers.Conv2D):
    """``keras.layers.Conv2D`` whose torch path hands the bias to the convolution itself.

    Keras adds the bias after the convolution as a separate broadcast op, a second pass over every
    activation (on the channels-last memory torch keeps them in, 2.4 ms per layer at 256 x 256 and 19 of
    the branch model's 83 ms). With ``data_format="channels_first"``, stride 1, no groups and "same" padding of
    an odd kernel (or "valid"), at any dilation, the torch backend calls ``torch.nn.functional.conv2d``
    with the bias directly: the same mkldnn kernel and bit-identical outputs, one pass less (cpu preset,
    256 x 256 frame 91 -> 65 ms; 8 x 65 x 65 training step 78 -> 68 ms). The bias gradient is then summed
    inside the convolution's backward, in another order: equal to float rounding, so a model trains like
    its ``Conv2D`` twin but not bit for bit (1.7e-8 apart in the weights after 5 Adam steps). Anything else
    (other backends, layouts, strides) runs the Keras implementation. Weights and config are Conv2D's.
    """

    def _torch_fast_path(self) -> bool:
        return (
            keras.backend.backend() == "torch"
            and self.data_format == "channels_first"
            and tuple(self.strides) == (1, 1)
            and self.groups == 1
            and (self.padding == "valid" or (self.padding == "same" and all(s % 2 == 1 for s in self.kernel_size)))
            and getattr(self, "lora_rank", None) is None  # LoRA adds to the kernel in Keras's own call
        )

    def call(self, inputs):
        if not self._torch_fast_path() or _is_symbolic(inputs):
            return super().call(inputs)
        import torch.nn.functional as F

        kernel = ops.convert_to_tensor(self.kernel).permute(3, 2, 0, 1)  # (kh, kw, in, out) -> (out, in, kh, kw)
        bias = ops.convert_to_tensor(self.bias) if self.use_bias else None
        dilation = tuple(self.dilation_rate)
        padding = tuple(d * (s // 2) for d, s in zip(dilation, self.kernel_size)) if self.padding == "same" else 0
        return self.activation(F.conv2d(ops.convert_to_tensor(inputs), kernel, bias, padding=padding,
                                        dilation=dilation))


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


@keras.saving.register_keras_serializable(package="kpcn")
class FinalColour(keras.layers.Layer):
    """Inputs ``[diffuse (B, H, W, 3), specular (B, H, W, 3), albedo (B, H, W, 3)]``, the branch colours in
    the log domain and the noisy albedo -> the final linear colour (B, H, W, 3).

    The inverse of the branch transforms of ``prep.colour`` (``diffuse_from_log`` + ``specular_from_log``, on its
    constants) written in ``keras.ops``, so a model can be supervised on the colour users see (joint fine-tuning):
    ``expm1(d) * (clip(albedo, 0, 1) + ALBEDO_EPS) + expm1(s)``, each log colour clamped to
    ``prep.colour.LOG_LINEAR_MAX``; ``tests/test_layers.py`` holds it to the numpy inverse.
    """

    def call(self, inputs):
        diffuse, specular, albedo = inputs
        albedo = ops.clip(albedo, 0.0, 1.0) + ALBEDO_EPS
        return (ops.expm1(ops.minimum(diffuse, LOG_LINEAR_MAX)) * albedo
                + ops.expm1(ops.minimum(specular, LOG_LINEAR_MAX)))

    def compute_output_shape(self, input_shape):
        return tuple(input_shape[0])


def _positive_int(name: str, value) -> int:
    if not is_integer(value) or value < 1:
        raise ValueError(f"{name} must be a positive integer, received {value!r}")
    return value


def _round_up(n, m):
    return None if n is None else -(-n // m) * m


def _ceil_div(n, m):
    return None if n is None else -(-n // m)


def _shape_str(shape) -> str:
    return str(tuple(shape))


@keras.saving.register_keras_serializable(package="kpcn")
class PadToMultiple(keras.layers.Layer):
    """(B, H, W, C) -> (B, H', W', C), H' and W' the next multiples of ``multiple``, padded at the bottom and
    right by replicating the last row / column (a constant image stays constant)."""

    def __init__(self, multiple: int, **kwargs):
        super().__init__(**kwargs)
        self.multiple = _positive_int("multiple", multiple)
        self.input_spec = keras.layers.InputSpec(ndim=4)

    def call(self, x):
        h, w = ops.shape(x)[1], ops.shape(x)[2]
        pad_h, pad_w = -h % self.multiple, -w % self.multiple
        if pad_h:
            x = ops.concatenate([x, ops.repeat(x[:, -1:], pad_h, axis=1)], axis=1)
        if pad_w:
            x = ops.concatenate([x, ops.repeat(x[:, :, -1:], pad_w, axis=2)], axis=2)
        return x

    def compute_output_shape(self, input_shape):
        b, h, w, c = input_shape
        return (b, _round_up(h, self.multiple), _round_up(w, self.multiple), c)

    def get_config(self):
        config = super().get_config()
        config["multiple"] = self.multiple
        return config


@keras.saving.register_keras_serializable(package="kpcn")
class CropLike(keras.layers.Layer):
    """Inputs ``[x (B, H', W', C), reference (B, H, W, *)]`` -> x[:, :ceil(H/factor), :ceil(W/factor)]: undoes
    ``PadToMultiple`` at the level whose pixels are ``factor`` reference pixels wide."""

    def __init__(self, factor: int = 1, **kwargs):
        super().__init__(**kwargs)
        self.factor = _positive_int("factor", factor)
        self.input_spec = [keras.layers.InputSpec(ndim=4), keras.layers.InputSpec(ndim=4)]

    def _target(self, shape):
        return _ceil_div(shape[1], self.factor), _ceil_div(shape[2], self.factor)

    def _check(self, x_shape, ref_shape):
        th, tw = self._target(ref_shape)
        for have, want in ((x_shape[1], th), (x_shape[2], tw)):
            if have is not None and want is not None and have < want:
                raise ValueError(
                    f"CropLike(factor={self.factor}) cannot crop shape {_shape_str(x_shape)} to the size of "
                    f"reference shape {_shape_str(ref_shape)}: it is too small"
                )

    def build(self, input_shape):
        self._check(*input_shape)

    def call(self, inputs):
        x, reference = inputs
        self._check(ops.shape(x), ops.shape(reference))
        th, tw = self._target(ops.shape(reference))
        return x[:, :th, :tw]

    def compute_output_shape(self, input_shape):
        x_shape, ref_shape = input_shape
        th, tw = self._target(ref_shape)
        return (x_shape[0], th, tw, x_shape[3])

    def get_config(self):
        config = super().get_config()
        config["factor"] = self.factor
        return config
