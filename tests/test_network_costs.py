"""network_costs: the bench's network stage timings (contract keys, consistency), plain_torch equal to Keras."""

import math

import numpy as np
import pytest
import torch
from helpers.networks import randomise

from kpcn_keras.models import ARCHS, ModelConfig, build_branch_model
from kpcn_keras.studies.network_costs import (
    TRAINING_SKIPS,
    VARIANTS,
    kernel_application_cost,
    memory_bandwidth,
    train_step_cost,
)
from kpcn_keras.studies.plain_torch import TorchBranch, copy_keras_weights, torch_branch_from_keras
from prep.bounds import is_number

TINY_BANDWIDTH = {"read_bytes_per_s": 1e10}  # a stand-in, so that kernel tests need not stream 512 MiB


def positive(x):
    return is_number(x) and math.isfinite(x) and x > 0


def tiny(arch, **kw):
    base = dict(arch=arch, width=6, depth=2, kernel_size=5)
    base.update(kw)
    return ModelConfig(**base)


@pytest.mark.slow
@pytest.mark.parametrize("arch, kw", [(arch, {}) for arch in ARCHS] + [("kpcn", {"dilations": [3, 2]})],
                         ids=[*ARCHS, "kpcn-dilated"])
@pytest.mark.parametrize("training", [False, True])
def test_plain_torch_equals_keras(arch, kw, training):
    cfg = tiny(arch, batchnorm=True, branch_channels=True, **kw)
    model = build_branch_model(cfg, name="specular")
    randomise(model, seed=1)
    net = torch_branch_from_keras(model, cfg)
    x = torch.from_numpy(np.random.default_rng(2).normal(size=(3, 9, 7, cfg.input_channels)).astype(np.float32))
    net.train(training)
    got = net(x).detach().numpy()
    want = model(x, training=training).detach().numpy()
    assert got.shape == (3, 9, 7, 3)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


def test_copy_rejects_a_model_of_another_config():
    model = build_branch_model(tiny("kpcn"))
    with pytest.raises(ValueError, match="res00a_conv"):
        copy_keras_weights(model, TorchBranch(tiny("kpal")))
    with pytest.raises(ValueError, match="kernel shape"):
        copy_keras_weights(model, TorchBranch(tiny("kpcn", kernel_size=3)))


def test_memory_bandwidth_contract():
    result = memory_bandwidth(nbytes=4 * 2**20, repeats=2)
    assert positive(result["read_bytes_per_s"]) and positive(result["seconds"])
    assert result["nbytes"] == 4 * 2**20
    assert result["read_bytes_per_s"] == pytest.approx(result["nbytes"] / result["seconds"])
    with pytest.raises(ValueError, match="received 0"):
        memory_bandwidth(nbytes=0)


@pytest.mark.parametrize("training", [False, True])
def test_kernel_application_cost_contract(training):
    result = kernel_application_cost(3, height=6, width=5, batch=2, repeats=2, training=training,
                                     bandwidth=TINY_BANDWIDTH)
    assert result["k"] == 3 and result["pixels"] == 60 and result["weight_bytes"] == 60 * 9 * 4
    assert result["floor_seconds"] == pytest.approx(result["weight_bytes"] / 1e10)
    assert result["ratio"] == pytest.approx(result["seconds"] / result["floor_seconds"])
    want = set(VARIANTS) - (set(TRAINING_SKIPS) if training else set())
    assert set(result["variants"]) == want and "shifted_slices" in want
    assert all(positive(v) for v in result["variants"].values())
    assert result["seconds"] == result["variants"]["shipped"]
    assert result["bandwidth"] is TINY_BANDWIDTH and result["training"] is training


def test_kernel_variants_compute_the_same_layer():
    rng = np.random.default_rng(3)
    colour = torch.tensor(rng.normal(size=(1, 6, 7, 3)), dtype=torch.float64)
    logits = torch.tensor(rng.normal(size=(1, 6, 7, 25)), dtype=torch.float64)
    want = VARIANTS["shifted_slices"](colour, logits, 5).numpy()
    for name, fn in VARIANTS.items():
        if name != "softmax_only":
            np.testing.assert_allclose(fn(colour, logits, 5).numpy(), want, rtol=1e-12, atol=1e-12, err_msg=name)


def test_train_step_cost_contract():
    result = train_step_cost(tiny("kpcn"), batch_size=2, patch=9, steps=2, skip=1)
    for key in ("keras_s", "torch_s", "ratio", "patches_per_s"):
        assert positive(result[key]), (key, result[key])
    assert result["ratio"] == pytest.approx(result["keras_s"] / result["torch_s"])
    assert result["patches_per_s"] == pytest.approx(2 / result["keras_s"])
    with pytest.raises(TypeError, match="dict"):
        train_step_cost({"arch": "kpcn"})
