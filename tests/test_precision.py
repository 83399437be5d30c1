"""The trunks' arithmetic at inference (``kpcn_keras.precision``): float32, or bfloat16 where the CPU has it."""

import keras
import numpy as np
import pytest
from helpers.networks import randomise
from helpers.paths import FIXTURES, REPO
from helpers.tiny import TINY_MODEL

from kpcn_keras import precision
from kpcn_keras.config import ModelConfig
from kpcn_keras.layers import KernelApply
from kpcn_keras.models import build_branch_model, trunk_layers
from prep import layouts, metrics
from prep.errors import OptionError

ARCH_MODELS = {
    "kpcn": {},
    "kpal": {"arch": "kpal", "depth": 2, "batchnorm": True, "dropout": 0.1},
    "dpcn": {"arch": "dpcn"},
    "unet": {"arch": "unet", "depth": 1, "levels": 3},
}


def _model(arch: str, seed: int = 0) -> keras.Model:
    model = build_branch_model(ModelConfig(**{**TINY_MODEL, **ARCH_MODELS[arch]}), "diffuse")
    randomise(model, seed=seed, scale=0.5)  # kernels far from the box filter the zero head gives
    return model


@pytest.mark.parametrize("native, want", [(True, "bfloat16"), (False, "float32")])
def test_auto_is_bfloat16_only_where_the_cpu_multiplies_it_natively(monkeypatch, native, want):
    monkeypatch.setattr(precision, "native_bfloat16", lambda: native)
    assert precision.resolve("auto") == precision.resolve() == want
    assert precision.resolve("float32") == "float32" and precision.resolve("bfloat16") == "bfloat16"


def test_an_unknown_precision_is_refused_echoing_it():
    with pytest.raises(OptionError, match=r"precision must be one of auto, float32, bfloat16, received 'half'"):
        precision.resolve("half")


@pytest.mark.parametrize("arch", ARCH_MODELS)
def test_bfloat16_runs_the_trunk_alone_and_float32_puts_it_back(arch):
    model = _model(arch)
    feats = np.random.default_rng(1).normal(size=(1, 24, 20, model.input_shape[-1])).astype(np.float32)
    want = keras.ops.convert_to_numpy(model.predict_on_batch(feats))
    trunk = trunk_layers(model)
    convs = [layer for layer in model.layers if isinstance(layer, keras.layers.Conv2D)]
    assert set(convs) - set(trunk) and set(convs) & set(trunk)  # the head is a convolution outside the trunk
    assert precision.apply(model, "bfloat16") == "bfloat16"
    for layer in model.layers:
        assert layer.compute_dtype == ("bfloat16" if layer in trunk else "float32"), layer.name
    assert all(w.dtype == "float32" for w in model.weights)  # the weights themselves are never cast
    got = keras.ops.convert_to_numpy(model.predict_on_batch(feats))
    assert got.dtype == np.float32 and np.all(np.isfinite(got))
    assert np.abs(got - want).max() > 0  # bfloat16 did run
    precision.apply(model, "float32")
    np.testing.assert_array_equal(keras.ops.convert_to_numpy(model.predict_on_batch(feats)), want)


@pytest.mark.parametrize("arch", ["kpcn", "unet"])
def test_a_bfloat16_trunk_still_gives_each_pixel_a_convex_combination_of_its_window(arch):
    # the softmax and the kernel application stay float32: whatever the trunk's rounding, a denoised log colour
    # lies between the least and the greatest noisy value of its k x k window (edge-replicated), per channel
    model = _model(arch, seed=3)
    precision.apply(model, "bfloat16")
    feats = np.random.default_rng(2).normal(size=(1, 21, 26, model.input_shape[-1])).astype(np.float32)
    feats[..., :3] = np.abs(feats[..., :3]) * 3
    out = keras.ops.convert_to_numpy(model.predict_on_batch(feats))[0].astype(np.float64)
    k = next(layer for layer in model.layers if isinstance(layer, KernelApply)).kernel_size
    r = k // 2
    padded = np.pad(feats[0, ..., :3].astype(np.float64), ((r, r), (r, r), (0, 0)), mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, (k, k), axis=(0, 1))  # (H, W, 3, k, k)
    low, high = windows.min(axis=(-2, -1)), windows.max(axis=(-2, -1))
    slack = 4 * np.finfo(np.float32).eps * np.maximum(np.abs(low), np.abs(high))
    assert np.all(out >= low - slack) and np.all(out <= high + slack)


def test_the_shipped_model_in_bfloat16_denoises_as_well_as_in_float32():
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings

    frame = layouts.read(FIXTURES / "fixture-00008spp.exr").layers
    reference = layouts.read(FIXTURES / "fixture-01024spp.exr").layers["default"]
    shipped = Run(REPO / "models" / "default")
    out = {p: Denoiser.from_run(shipped, InferenceSettings(precision=p))(frame)["default"].astype(np.float64)
           for p in ("float32", "bfloat16")}
    # bfloat16 keeps 8 bits of each activation: a pixel moves by well under 2 % of its value
    relative = np.abs(out["bfloat16"] - out["float32"]) / (np.abs(out["float32"]) + metrics.RELMSE_EPS)
    assert 0 < relative.max() < 0.02
    errors = {p: metrics.relmse(image, reference) for p, image in out.items()}
    assert errors["bfloat16"] == pytest.approx(errors["float32"], rel=0.01)
