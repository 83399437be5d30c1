"""The ONNX export (kpcn_keras/onnx_export.py, ``kpcn export --onnx``) and the onnxruntime path
(kpcn_keras/onnx_runtime.py, ``--runtime onnx``): graphs that equal their Keras networks at any frame size."""

import json
from pathlib import Path

import keras
import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.networks import randomise
from helpers.paths import FIXTURES, REPO
from helpers.references import reference_kernel_apply
from helpers.tiny import TINY_MODEL, random_aovs

from kpcn_keras.config import ModelConfig
from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import build_branch_model, input_alignment
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from prep import exr, layouts
from prep.errors import OptionError

onnx = pytest.importorskip("onnx", reason="onnx not installed (the optional extra onnx; CI installs it: .[test])")
ort = pytest.importorskip("onnxruntime", reason="onnxruntime not installed (the optional extra onnx; CI: .[test])")

from kpcn_keras.onnx_export import MANIFEST, TOLERANCE, network_bytes  # noqa: E402
from kpcn_keras.onnx_runtime import OnnxNetwork  # noqa: E402

FLOAT32 = InferenceSettings(precision="float32")
ONNX = InferenceSettings(precision="float32", runtime="onnx")


def _features(shape, channels, seed):
    return np.random.default_rng(seed).uniform(-1.0, 3.0, (1, *shape, channels)).astype(np.float32)


def _keras(model, x):
    return keras.ops.convert_to_numpy(model.predict_on_batch(x))


@pytest.mark.parametrize("k, d", [(3, 1), (5, 1), (5, 2)])
def test_the_traced_kernel_application_equals_the_float64_reference(k, d):
    import torch

    from kpcn_keras.layers import traced_kernel_apply

    rng = np.random.default_rng(k + d)
    colour = rng.uniform(0, 4, (2, 7, 9, 3)).astype(np.float32)
    logits = rng.normal(0, 3, (2, 7, 9, k * k)).astype(np.float32)
    got = traced_kernel_apply(torch.from_numpy(colour), torch.from_numpy(logits), k, d).numpy()
    if d == 1:
        want = reference_kernel_apply(colour, logits, k)[0]
    else:  # dilated taps: the reference on the colour seen through a d-spaced grid, built by hand
        r = (k // 2) * d
        padded = np.pad(colour.astype(np.float64), ((0, 0), (r, r), (r, r), (0, 0)), mode="edge")
        z = logits.astype(np.float64)
        w = np.exp(z - z.max(-1, keepdims=True))
        w /= w.sum(-1, keepdims=True)
        want = sum(w[..., i * k + j, None] * padded[:, i * d : i * d + 7, j * d : j * d + 9]
                   for i in range(k) for j in range(k))
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("arch", [{}, {"arch": "unet", "width": 4, "depth": 1, "levels": 3}], ids=["kpcn", "unet"])
def test_an_exported_network_equals_its_keras_model_at_frame_sizes_other_than_the_traced_one(arch):
    cfg = ModelConfig(**{**TINY_MODEL, **arch})
    model = build_branch_model(cfg)
    randomise(model, seed=3, scale=0.3)  # a zero head gives box kernels, which a frozen graph could still match
    align = input_alignment(cfg)
    network = OnnxNetwork(network_bytes(model, align), align)
    for seed, shape in enumerate([(13, 29), (31, 18)]):  # neither a multiple of the unet's 4
        x = _features(shape, cfg.input_channels, seed)
        got, want = network.predict_on_batch(x), _keras(model, x)
        assert got.shape == want.shape == (1, *shape, 3)
        assert np.max(np.abs(got - want)) <= TOLERANCE
        assert np.std(got) > 0.01  # a graph that kept one frame's values would not follow the input


def _denoisers(run: Run, tile: int = 256):
    """A torch and an onnx denoiser of ``run`` on the same random weights (float32, the graphs' arithmetic)."""
    torch_denoiser = Denoiser.from_run(run, FLOAT32)
    for i, net in enumerate(torch_denoiser.networks.values()):
        randomise(net, seed=40 + i, scale=0.2)
    settings = InferenceSettings(precision="float32", runtime="onnx", tile=tile)
    return torch_denoiser, Denoiser(run, torch_denoiser.record, torch_denoiser.networks, None, settings,
                                    torch_denoiser.albedo_network)


def test_the_onnx_runtime_denoises_as_torch_does_and_its_tiles_equal_an_untiled_run(tiny_run):
    aovs = random_aovs(37, 45, seed=5)
    torch_denoiser, onnx_denoiser = _denoisers(Run(tiny_run))
    _, tiled = _denoisers(Run(tiny_run), tile=16)
    want, got, got_tiled = torch_denoiser(aovs), onnx_denoiser(aovs), tiled(aovs)
    for name in ("diffuse", "specular", "default"):
        scale = np.abs(want[name]) + 1e-2
        assert np.max(np.abs(got[name] - want[name]) / scale) < 10 * TOLERANCE, name
        np.testing.assert_allclose(got_tiled[name], got[name], rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.slow  # traces the shipped model's seven networks: about a minute
def test_the_shipped_model_through_onnx_equals_keras_on_the_fixture_for_every_input_set():
    frame = {name: layer[:48, :64] for name, layer in layouts.read(FIXTURES / "fixture-00008spp.exr").layers.items()}
    shipped = Run(REPO / "models" / "default")
    variants = [run for run in shipped.variants() if run.has_record()]
    assert len(variants) == 4  # full, no-variance, no-split, no-split-no-variance
    for run in variants:
        want = Denoiser.from_run(run, FLOAT32)(frame)
        got = Denoiser.from_run(run, ONNX)(frame)
        for name in ("diffuse", "specular", "default"):
            # the documented tolerance is of the log domain: a relative difference of the linear colour
            relative = np.abs(got[name] - want[name]) / (np.abs(want[name]) + 1e-2)
            assert relative.max() < TOLERANCE, (run.dir, name, relative.max())


@pytest.mark.slow  # trains a tiny run of every input set and traces each network
def test_kpcn_export_writes_every_network_of_every_input_set_with_its_card(tiny_run_of_every_input_set, tmp_path):
    model = Run(tiny_run_of_every_input_set)
    res = run_main("export", model.dir, "--onnx", tmp_path / "onnx", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    manifest = json.loads((tmp_path / "onnx" / MANIFEST).read_text())
    variants = [run for run in model.variants() if run.has_record()]
    want = {(str(run.dir.relative_to(model.dir)), name) for run in variants for name in run.record().components}
    assert {(str(Path(n["file"]).parent), n["network"]) for n in manifest["networks"]} == want
    card = (tmp_path / "onnx" / "CARD.md").read_text()
    for entry in manifest["networks"]:
        assert entry["file"] in card and 0 <= entry["max_difference"] <= TOLERANCE
        run = model.dir / entry["file"]
        keras_model = Run(run.parent).load_component(Run(run.parent).record(), entry["network"])
        network = OnnxNetwork((tmp_path / "onnx" / entry["file"]).read_bytes(), entry["alignment"])
        x = _features((19, 23), entry["channels"], 9)
        assert np.max(np.abs(network.predict_on_batch(x) - _keras(keras_model, x))) <= TOLERANCE
    again = run_main("export", model.dir, "--onnx", tmp_path / "onnx", cwd=tmp_path)  # an earlier export: replaced
    assert again.returncode == 0, again.stderr


def test_kpcn_export_refuses_bad_input_in_one_line(tiny_run, tmp_path):
    assert_one_line_error(run_main("export", tmp_path, "--onnx", tmp_path / "o", cwd=tmp_path), str(tmp_path),
                          "not a run folder")
    (tmp_path / "taken").mkdir()
    (tmp_path / "taken" / "keep.txt").write_text("x")
    assert_one_line_error(run_main("export", tiny_run, "--onnx", tmp_path / "taken", cwd=tmp_path), "taken",
                          "not an earlier kpcn export")
    (tmp_path / "file").write_text("x")
    assert_one_line_error(run_main("export", tiny_run, "--onnx", tmp_path / "file" / "o", cwd=tmp_path),
                          "cannot be written")
    assert (tmp_path / "taken" / "keep.txt").read_text() == "x"


def test_the_onnx_runtime_refuses_what_it_cannot_serve_in_one_line(tiny_run, tmp_path):
    with pytest.raises(OptionError, match="runtime"):
        InferenceSettings(runtime="tensorrt")
    with pytest.raises(OptionError, match="float32"):
        Denoiser.from_run(Run(tiny_run), InferenceSettings(runtime="onnx", precision="bfloat16"))
    frame = tmp_path / "f.exr"
    exr.write_aovs(frame, random_aovs(16, 16, seed=1))
    res = run_main("denoise", frame, "--run", tiny_run, "--runtime", "onnx", "--precision", "bfloat16",
                   cwd=tmp_path)
    assert_one_line_error(res, "--runtime", "float32")
