"""The branch networks of ``models.build_branch_model`` as plain ``torch.nn.Module``s, to measure Keras's overhead.

Contract: ``TorchBranch(cfg)`` for any ``ModelConfig`` (arch "kpcn", "kpal", "dpcn" or "unet") takes the same input as
the Keras model, features (B, H, W, ``cfg.input_channels``) channels last, and returns its output, log colour
(B, H, W, 3). :func:`copy_keras_weights` copies a Keras branch model's weights (matched by layer name, the
branch prefix removed) into it; the two then agree to float rounding (tested). Nothing in training or
inference uses this module: it exists so that ``stage_costs`` can time the same network without Keras.

Layout as in the Keras model: one permute to channels first at the input (the convolutions then run on
torch's channels-last memory format, no copies), the kernel application channels last. Keras layer
defaults are reproduced where torch's differ: "same" padding of an odd kernel is d * (k // 2) on each side
at dilation d;
a unet's input is edge-padded at the bottom and right to its alignment and its logits cropped back, the
pooling is 2x2 average pooling, the upsampling 2x2 nearest, the skip concatenated after the upsampled
level (the Keras ``Concatenate`` order);
batch norm eps 1e-3 and momentum 0.01 (Keras's 0.99 counts the other way). The kernel layer is the same
torch function Keras's ``KernelApply`` runs (``layers.kernel_apply``), so a difference in time between the
two is the rest of Keras.
"""

from __future__ import annotations

import keras
import numpy as np
import torch
from torch import nn

from kpcn_keras.config import COLOUR_CHANNELS, DILATED_ARCHS, ModelConfig
from kpcn_keras.layers import kernel_apply
from kpcn_keras.models import input_alignment
from prep.colour import LOG_COLOUR_MAX

__all__ = ["TorchBranch", "copy_keras_weights", "torch_branch_from_keras"]

KERAS_BN_EPSILON = 1e-3  # keras.layers.BatchNormalization defaults
KERAS_BN_MOMENTUM = 0.01  # torch's momentum is 1 - Keras's 0.99


class _ConvUnit(nn.Module):
    """Conv -> [BN] -> [ReLU] -> [Dropout], as ``models._conv_unit``."""

    def __init__(self, cin: int, cfg: ModelConfig, activate: bool, width: int | None = None, dilation: int = 1):
        super().__init__()
        width = cfg.width if width is None else width
        self.conv = nn.Conv2d(cin, width, cfg.conv_size, padding=dilation * (cfg.conv_size // 2), dilation=dilation,
                              bias=not cfg.batchnorm)
        self.bn = nn.BatchNorm2d(width, eps=KERAS_BN_EPSILON, momentum=KERAS_BN_MOMENTUM) if cfg.batchnorm else None
        self.activate = activate
        self.drop = nn.Dropout(cfg.dropout) if cfg.dropout > 0.0 else None

    def forward(self, x):
        x = self.conv(x)
        if self.bn is not None:
            x = self.bn(x)
        if self.activate:
            x = torch.relu(x)
        if self.drop is not None:
            x = self.drop(x)
        return x


class TorchBranch(nn.Module):
    """A branch network, features (B, H, W, C) -> log colour (B, H, W, 3); see the module docstring.

    ``units`` maps the Keras layer names without the branch prefix (``trunk00``, ``stem``, ``res03a``,
    ``enc1_00``, ``dec0_00``) to conv units; ``head`` is the 1x1 layer (``kernel_logits`` or ``correction``).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        if not isinstance(cfg, ModelConfig):
            raise TypeError(f"cfg must be a ModelConfig, received {type(cfg).__name__}")
        self.cfg = cfg
        units = {}
        head_in = cfg.width
        if cfg.arch == "unet":
            widths = cfg.unet_widths()
            cin = cfg.input_channels
            for level, width in enumerate(widths):
                for i in range(cfg.depth):
                    units[f"enc{level}_{i:02d}"] = _ConvUnit(cin, cfg, True, width)
                    cin = width
            for level in reversed(range(cfg.levels - 1)):
                cin = widths[level + 1] + widths[level]
                for i in range(cfg.depth):
                    units[f"dec{level}_{i:02d}"] = _ConvUnit(cin, cfg, True, widths[level])
                    cin = widths[level]
            head_in = widths[0]
        elif cfg.arch in DILATED_ARCHS:
            cin = cfg.input_channels
            for i, dilation in enumerate(cfg.trunk_dilations()):
                units[f"trunk{i:02d}"] = _ConvUnit(cin, cfg, activate=True, dilation=dilation)
                cin = cfg.width
        else:
            units["stem"] = _ConvUnit(cfg.input_channels, cfg, activate=True)
            for i in range(cfg.depth):
                units[f"res{i:02d}a"] = _ConvUnit(cfg.width, cfg, activate=True)
                units[f"res{i:02d}b"] = _ConvUnit(cfg.width, cfg, activate=False)
        self.units = nn.ModuleDict(units)
        head_channels = COLOUR_CHANNELS if cfg.arch == "dpcn" else cfg.kernel_size**2
        self.head = nn.Conv2d(head_in, head_channels, 1)
        self.head_name = "correction" if cfg.arch == "dpcn" else "kernel_logits"

    def _unet(self, x):
        cfg, skips = self.cfg, []
        for level in range(cfg.levels):
            if level:
                x = nn.functional.avg_pool2d(x, 2)
            for i in range(cfg.depth):
                x = self.units[f"enc{level}_{i:02d}"](x)
            skips.append(x)
        for level in reversed(range(cfg.levels - 1)):
            x = torch.cat([nn.functional.interpolate(x, scale_factor=2, mode="nearest"), skips[level]], dim=1)
            for i in range(cfg.depth):
                x = self.units[f"dec{level}_{i:02d}"](x)
        return x

    def forward(self, features):
        colour = features[..., :COLOUR_CHANNELS]
        x = features.permute(0, 3, 1, 2)
        h, w = x.shape[2:]
        if self.cfg.arch == "unet":
            align = input_alignment(self.cfg)
            x = nn.functional.pad(x, (0, -w % align, 0, -h % align), mode="replicate")
            x = self._unet(x)
        elif self.cfg.arch in DILATED_ARCHS:
            for unit in self.units.values():
                x = unit(x)
        else:
            x = self.units["stem"](x)
            for i in range(self.cfg.depth):
                y = self.units[f"res{i:02d}b"](self.units[f"res{i:02d}a"](x))
                x = torch.relu(x + y)
        head = self.head(x)[:, :, :h, :w].permute(0, 2, 3, 1)
        if self.cfg.arch == "dpcn":
            return torch.clamp(colour + head, 0.0, LOG_COLOUR_MAX)
        return kernel_apply(colour, head, self.cfg.kernel_size)


def _tensor(variable) -> torch.Tensor:
    return torch.from_numpy(np.array(keras.ops.convert_to_numpy(variable), dtype=np.float32))


def _copy_conv(layer, conv: nn.Conv2d) -> None:
    kernel = _tensor(layer.kernel)  # Keras (kh, kw, in, out) in either data format
    expected = tuple(conv.weight.shape[2:]) + (conv.weight.shape[1], conv.weight.shape[0])
    if tuple(kernel.shape) != expected:
        raise ValueError(f"layer {layer.name!r}: kernel shape {tuple(kernel.shape)}, expected {expected}")
    conv.weight.copy_(kernel.permute(3, 2, 0, 1))
    if conv.bias is not None:
        conv.bias.copy_(_tensor(layer.bias))


def _copy_bn(layer, bn: nn.BatchNorm2d) -> None:
    bn.weight.copy_(_tensor(layer.gamma))
    bn.bias.copy_(_tensor(layer.beta))
    bn.running_mean.copy_(_tensor(layer.moving_mean))
    bn.running_var.copy_(_tensor(layer.moving_variance))


def copy_keras_weights(model: keras.Model, net: TorchBranch) -> TorchBranch:
    """Copy the weights of Keras branch ``model`` (built by ``build_branch_model`` from the same config, in
    either layout, or loaded from a run) into ``net``; returns ``net``. Raises ValueError for a layer missing
    on either side or a shape that does not fit."""
    prefix = f"{model.name}_"
    layers = {layer.name[len(prefix):]: layer for layer in model.layers if layer.name.startswith(prefix)}
    pairs = [(f"{name}_conv", unit.conv) for name, unit in net.units.items()] + [(net.head_name, net.head)]
    pairs += [(f"{name}_bn", unit.bn) for name, unit in net.units.items() if unit.bn is not None]
    missing = [name for name, _ in pairs if name not in layers]
    if missing:
        raise ValueError(f"Keras model {model.name!r} has no layers {missing} (layers: {sorted(layers)})")
    with torch.no_grad():
        for name, module in pairs:
            (_copy_bn if isinstance(module, nn.BatchNorm2d) else _copy_conv)(layers[name], module)
    return net


def torch_branch_from_keras(model: keras.Model, cfg: ModelConfig) -> TorchBranch:
    """A new ``TorchBranch(cfg)`` holding ``model``'s weights, in inference mode (``eval()``)."""
    return copy_keras_weights(model, TorchBranch(cfg)).eval()
