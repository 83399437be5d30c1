"""The networks run by onnxruntime (``--runtime onnx``, ``InferenceSettings.runtime``): the optional extra ``onnx``.

:class:`OnnxNetwork` is one network's ONNX graph (``kpcn_keras.onnx_export.network_bytes``) in an onnxruntime
session, called as a Keras model is (``predict_on_batch``), so ``denoise.Denoiser`` tiles, ensembles and
recombines exactly as it does on torch: tiles still equal an untiled run. ``kpcn_keras.onnx_export.onnx_networks``
turns a run's loaded Keras networks into them (traced once, when the denoiser is made: seconds, not per frame). The
graphs are float32: a precision of bfloat16 is refused with this runtime (``auto`` is float32 here). Not served: a
multiscale run's compositor and a run with a specialisation module (``PreparedFrame`` splits its Keras model),
refused in one line naming the run.

The session runs on the threads torch has (``prep.threads``: ``--threads``), with onnxruntime's transpose
optimizer off: it moved the kernel application's layout back to channels last, where each product broadcasts
along the last axis, several times slower (measured on the shipped networks at 256 x 256).
"""

from __future__ import annotations

import numpy as np

from prep.errors import OptionError


class OnnxNetwork:
    """An ONNX graph of features (B, H, W, C) -> (B, H, W, 3) in an onnxruntime session. ``align``: the network's
    input alignment (``models.input_alignment``); a frame is edge-padded at the bottom and right up to it and
    cropped after, as the Keras network's own ``PadToMultiple`` does (replicating an edge twice is replicating it
    once), so any H and W are served."""

    def __init__(self, graph: bytes, align: int = 1, threads: int | None = None):
        import onnxruntime as ort

        options = ort.SessionOptions()
        if threads is None:
            import torch

            threads = torch.get_num_threads()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(graph, options, providers=["CPUExecutionProvider"],
                                            disabled_optimizers=["TransposeOptimizer"])
        self.input = self.session.get_inputs()[0].name
        self.align = align

    def predict_on_batch(self, x) -> np.ndarray:
        """The network's output of the batch ``x`` (B, H, W, C), float32."""
        x = np.ascontiguousarray(x, dtype=np.float32)
        h, w = x.shape[1:3]
        pad_h, pad_w = -h % self.align, -w % self.align
        if pad_h or pad_w:
            x = np.pad(x, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")
        return self.session.run(None, {self.input: x})[0][:, :h, :w]


def require_onnx() -> None:
    """KpcnError in one line where ``onnx`` or ``onnxruntime`` is not installed (the optional extra ``onnx``)."""
    import importlib.util

    from prep.errors import KpcnError

    missing = [name for name in ("onnx", "onnxruntime") if importlib.util.find_spec(name) is None]
    if missing:
        raise KpcnError(f"{' and '.join(missing)} not installed: pip install -c constraints.txt -e '.[onnx]'")


def check_servable(run_dir, *, precision: str, compositor: bool, slope_module: bool) -> None:
    """OptionError (``--runtime``) in one line where the ONNX runtime cannot serve the run at ``run_dir``: onnx or
    onnxruntime not installed, a bfloat16 ``precision``, a compositor or a specialisation module."""
    from prep.errors import KpcnError

    try:
        require_onnx()
    except KpcnError as exc:
        raise OptionError("runtime", f"onnx needs {exc}") from None
    reason = ("runs float32 networks; give --precision float32 or auto" if precision == "bfloat16" else
              "does not run a multiscale compositor" if compositor else
              "does not run a specialisation module (--slope-module)" if slope_module else None)
    if reason:
        raise OptionError("runtime", f"onnx {reason}, which {run_dir} has; use --runtime torch")


__all__ = ["OnnxNetwork", "check_servable", "require_onnx"]
