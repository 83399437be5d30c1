"""What the multiscale tests share: a tiny compositor's configuration, running a model or layer on numpy
arrays, and the float64 numpy references of the pyramid's operations (U, D, Keys' cubic, the bicubic 2x
filter), written from their definitions rather than from kpcn_keras.multiscale."""

import numpy as np
import torch

from kpcn_keras.multiscale import CompositorConfig


def tiny_compositor(kind="alpha", **kw):
    return CompositorConfig(**{"kind": kind, "width": 4, "depth": 3, "kernel_size": 3, **kw})


def to_np(x):
    """Tensor -> numpy without keras.ops.convert_to_numpy, whose np.array(torch_tensor) warns on numpy 2."""
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def run(model_or_layer, *inputs, **kw):
    args = [np.asarray(x, np.float32) for x in inputs]
    out = model_or_layer(args if len(args) > 1 else args[0], **kw)
    return [to_np(o) for o in out] if isinstance(out, (list, tuple)) else to_np(out)


def up(c):
    return c.repeat(2, axis=1).repeat(2, axis=2)


def down(f):
    b, h, w, c = f.shape
    return f.reshape(b, h // 2, 2, w // 2, 2, c).mean(axis=(2, 4))


def keys(x, a=-0.5):
    """Keys' cubic convolution kernel, float64, written from the paper's formula."""
    x = np.abs(x)
    return np.where(x <= 1, (a + 2) * x**3 - (a + 3) * x**2 + 1,
                    np.where(x < 2, a * x**3 - 5 * a * x**2 + 8 * a * x - 4 * a, 0.0))


def bicubic_weights():
    """The antialiased bicubic 2x filter: fine pixel 2Y + k, k = -3 .. 4, weighs keys((k - 1/2) / 2) / 2."""
    k = np.arange(-3, 5)
    return k, keys((k - 0.5) / 2.0) / 2.0


def bicubic_down(f, square=False):
    """float64 loops: coarse (Y, X) = Σ_ij w_i w_j f[2Y + i, 2X + j], coordinates clamped (``square``: the
    weights squared, the variance of the filtered noise)."""
    offsets, w = bicubic_weights()
    w = w**2 if square else w
    b, h, wd, c = f.shape
    out = np.zeros((b, h // 2, wd // 2, c))
    for yy in range(h // 2):
        for xx in range(wd // 2):
            for i, wi in zip(offsets, w):
                for j, wj in zip(offsets, w):
                    sy, sx = min(max(2 * yy + i, 0), h - 1), min(max(2 * xx + j, 0), wd - 1)
                    out[:, yy, xx] += wi * wj * f[:, sy, sx]
    return out
