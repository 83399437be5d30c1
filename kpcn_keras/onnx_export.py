"""A model as ONNX (``kpcn export MODEL --onnx OUT``): each network of each variant and quality mode, with a card.

A network is traced whole, features (B, H, W, C) in, its log-domain colour (B, H, W, 3) out, with B, H and W
free: the kernel prediction, the softmax and the kernel application are in the graph. The kernel application's
fast paths run numba on numpy, which a trace would keep as constants (Keras's own ``Model.export(format="onnx")``
gave outputs off by the output's own size); under an ONNX export ``layers.kernel_apply`` takes
``layers.traced_kernel_apply`` instead, shifted planes cut by offsets from both ends, so the graph holds no
frame size. Outside the graph stay what is not a network: the features (``prep.features.branch_features`` and
``models.network_input``), the recombination of the branches in linear colour (``prep.colour``: ``expm1(d) *
(albedo + ALBEDO_EPS) + expm1(s)``, the albedo the albedo network's where the model has one) and the tiling.
``kpcn_keras.onnx_runtime`` runs them so, inside ``denoise.Denoiser`` (``--runtime onnx``).

Each network is checked as it is written: onnxruntime's output and the Keras model's, on the same random
features at two frame sizes (neither the traced one), may differ by at most :data:`TOLERANCE` (absolute, in the
log domain of the output, where 1e-4 is a relative 1e-4 of the linear colour); the differences found go into
the card and ``onnx.json``. Not exported: a multiscale run's compositor (its networks are exported; the
pyramid is not), refused by the runtime.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import warnings
from pathlib import Path

import keras
import numpy as np

from kpcn_keras.models import input_alignment, receptive_radius
from kpcn_keras.oidn_mix import of_record
from kpcn_keras.onnx_runtime import OnnxNetwork, require_onnx
from kpcn_keras.run import Run, RunRecord, check_architecture
from prep.errors import KpcnError

OPSET = 17
INPUT, OUTPUT = "features", "colour"
# Keras (torch) and onnxruntime add the same terms in other orders; measured on the shipped networks at 256 x 256
# the largest difference was 4e-5 (output ~4.8): a tenth of this, which leaves room for other machines' kernels
TOLERANCE = 1e-3
TRACED_SIZE = (24, 20)  # H, W of the trace: small; the check runs at two other sizes
CHECK_SIZES = ((37, 53), (70, 46))
MANIFEST = "onnx.json"
CARD = "CARD.md"
NOT_EXPORTED = ("compositor",)


class _Call:
    """A Keras model as a torch module of one tensor (the tracer's unit)."""

    def __new__(cls, model: keras.Model):
        import torch

        class Call(torch.nn.Module):
            def __init__(self):
                super().__init__()
                self.model = model

            def forward(self, x):
                return self.model(x)

        return Call()


def network_bytes(model: keras.Model, align: int = 1) -> bytes:
    """``model`` (features (B, H, W, C) -> (B, H, W, 3)) as an ONNX graph of B, H and W free, float32, traced at a
    multiple of ``align`` (a unet's pooling grid: its padding is then none, and the runtime pads as it did)."""
    import torch

    h, w = (-(-s // align) * align for s in TRACED_SIZE)
    sample = torch.from_numpy(_features((h, w), model.input_shape[-1], seed=0))
    axes = {0: "batch", 1: "height", 2: "width"}
    buffer = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        # the tracer's notes on shapes read as Python numbers: the graph runs at other sizes (checked after)
        warnings.simplefilter("ignore")
        torch.onnx.export(_Call(model), (sample,), buffer, dynamo=False, input_names=[INPUT], output_names=[OUTPUT],
                          dynamic_axes={INPUT: axes, OUTPUT: axes}, opset_version=OPSET)
    return buffer.getvalue()


def _features(shape: tuple[int, int], channels: int, seed: int) -> np.ndarray:
    """Random features (1, H, W, C) in the range of real ones (log colours and unit auxiliaries)."""
    return np.random.default_rng(seed).uniform(-1.0, 3.0, (1, *shape, channels)).astype(np.float32)


def check_network(model: keras.Model, graph: bytes, align: int, what: str) -> float:
    """The largest difference between ``graph`` run by onnxruntime and ``model`` at :data:`CHECK_SIZES` (grown to
    multiples of ``align``); KpcnError naming ``what`` where it exceeds :data:`TOLERANCE`."""
    network = OnnxNetwork(graph, align)
    worst = 0.0
    for seed, size in enumerate(CHECK_SIZES, start=1):
        x = _features(size, model.input_shape[-1], seed)
        want = keras.ops.convert_to_numpy(model.predict_on_batch(x))
        worst = max(worst, float(np.max(np.abs(network.predict_on_batch(x) - want))))
    if not worst <= TOLERANCE:
        raise KpcnError(f"{what}: the ONNX graph's output differs from the Keras network's by {worst:.3g} "
                        f"(more than {TOLERANCE:g}); not written")
    return worst


def onnx_networks(networks: dict, align: int) -> dict:
    """Each Keras network of ``networks`` (name -> model) as a ``onnx_runtime.OnnxNetwork`` of the same name."""
    return {name: OnnxNetwork(network_bytes(net, align), align) for name, net in networks.items()}


def exported_networks(model: Run) -> list[tuple[Run, RunRecord, str]]:
    """(run, record, component) of every network :func:`export` writes: each quality mode's every variant that
    has a record, each component but :data:`NOT_EXPORTED`; KpcnError naming the folder where it is not a
    finished model."""
    model.check_folder()
    found = []
    for mode in model.quality_modes():
        for run in model.for_quality(mode).variants():
            if not run.has_record():
                continue
            record = run.record().finished()
            run.check_weights(record)
            found += [(run, record, name) for name in record.components if name not in NOT_EXPORTED]
    return found


def export(model: Run, out: str | os.PathLike) -> Path:
    """Write every network of ``model`` (:func:`exported_networks`) as ONNX under ``out``, in the folders of the
    model (``inputs/<set>/``, ``quality/<mode>/``), with :data:`MANIFEST` and :data:`CARD`; checked first
    (:func:`check_network`). Written into a temporary folder renamed at the end; an ``out`` that exists is
    replaced only where it is an earlier export (it has a manifest). Returns ``out``."""
    require_onnx()
    out = Path(out)
    if out.exists() and not (out / MANIFEST).is_file():
        raise KpcnError(f"{out}: exists and is not an earlier kpcn export (no {MANIFEST}); give a new folder")
    networks = exported_networks(model)
    temporary = out.with_name(f".{out.name}.tmp-{os.getpid()}")
    try:
        temporary.mkdir(parents=True, exist_ok=False)
    except OSError as exc:
        raise KpcnError(f"{out}: cannot be written ({exc.strerror})") from None
    try:
        entries = [_write_network(model, run, record, name, temporary) for run, record, name in networks]
        manifest = {"opset": OPSET, "input": INPUT, "output": OUTPUT, "tolerance": TOLERANCE,
                    "model": str(model.dir), "networks": entries}
        (temporary / MANIFEST).write_text(json.dumps(manifest, indent=2) + "\n")
        (temporary / CARD).write_text(card_text(manifest))
        if out.exists():
            shutil.rmtree(out)
        temporary.rename(out)
    finally:
        shutil.rmtree(temporary, ignore_errors=True)
    return out


def _write_network(model: Run, run: Run, record: RunRecord, name: str, folder: Path) -> dict:
    network = run.load_component(record, name)
    if name != "compositor":
        check_architecture(network, record.model, record.component_path(name))
    align = input_alignment(record.model)
    relative = run.dir.relative_to(model.dir)
    graph = network_bytes(network, align)
    difference = check_network(network, graph, align, f"{record.component_path(name)}")
    path = folder / relative / f"{name}.onnx"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(graph)
    source = record.component_path(name)
    return {"file": str(relative / f"{name}.onnx"), "network": name, "source": str(source.relative_to(model.dir)),
            "source_sha256": hashlib.sha256(source.read_bytes()).hexdigest(),
            "sha256": hashlib.sha256(graph).hexdigest(), "inputs": record.inputs.name,
            "auxiliaries": record.auxiliaries, "channels": int(network.input_shape[-1]),
            "kernel_size": record.model.kernel_size, "alignment": align, "margin": receptive_radius(record.model),
            "max_difference": difference, "oidn_mix": _mix_entry(record)}


def _mix_entry(record: RunRecord) -> dict | None:
    """What a consumer of the graphs must do after them for a variant served mixed with OIDN's frame
    (``kpcn_keras.oidn_mix``): the weight of the networks' frame and the OIDN to mix with; None where unmixed."""
    mix = of_record(record.data, str(record.path))
    return None if mix is None else {"weight": mix.weight, "oidn_mode": mix.oidn_mode, "oidn_quality": mix.oidn_quality}


def card_text(manifest: dict) -> str:
    """The card of an export: what each file is, how it is fed and put together, how close it is to Keras."""
    rows = "\n".join(f"| `{n['file']}` | {n['network']} | {n['inputs']} | {n['channels']} | {n['kernel_size']} | "
                     f"{n['alignment']} | {n['margin']} | {n['max_difference']:.2g} |" for n in manifest["networks"])
    return f"""# ONNX export of `{manifest['model']}`

Written by `kpcn export {manifest['model']} --onnx OUT` (kpcn_keras/onnx_export.py); opset {manifest['opset']}.
Each file is one network: input `{manifest['input']}` (batch, height, width, channels) float32, any height and width
(a multiple of the alignment: pad the bottom and right by repeating the last row and column, crop after),
output `{manifest['output']}` (batch, height, width, 3), the branch's colour in the log domain. The kernel
prediction, the softmax and the per-pixel kernel application are in the graph.

Outside the graph, as `kpcn denoise --runtime onnx` does them (docs/onnx.md): the features of a frame
(`prep.features.branch_features`, `models.network_input`), tiles with a margin of the network's receptive radius,
and the recombination: `expm1(diffuse) * (clip(albedo, 0, 1) + {_albedo_eps()}) + expm1(specular)` (`prep.colour`), the
albedo the albedo network's output where the model has one, else the noisy albedo prefiltered (`prep.albedo`).

Checked when written: onnxruntime's output and the Keras network's on random features at two frame sizes differ
by at most the last column (absolute, log domain); the tolerance is {manifest['tolerance']:g}.

| file | network | input set | channels | kernel | alignment | margin (px) | max difference |
|---|---|---|---|---|---|---|---|
{rows}
"""


def _albedo_eps() -> str:
    from prep.colour import ALBEDO_EPS

    return f"{ALBEDO_EPS:g}"


__all__ = ["CARD", "MANIFEST", "TOLERANCE", "check_network", "export", "exported_networks", "network_bytes",
           "onnx_networks"]
