"""The command line of ONNX: ``kpcn export``'s options and command, and ``--runtime``.

Kept apart from ``parser`` and ``cli`` (each near its size limit) and as light as the parser: building the options
imports no keras, torch nor onnx; the command imports ``kpcn_keras.onnx_export`` when it runs.
"""

from __future__ import annotations

from kpcn_keras.config import DEFAULT_RUNTIME, RUNTIMES


def runtime_option(parser) -> None:
    """``--runtime``, ``InferenceSettings.runtime``: of every command that takes ``--precision``."""
    parser.add_argument("--runtime", choices=RUNTIMES, help="what runs the networks: torch, or onnxruntime on their "
                        "ONNX graphs (the optional extra onnx; float32, no compositor nor specialisation module; "
                        f"docs/onnx.md) (default: {DEFAULT_RUNTIME})")


def export_options(add) -> None:
    """The options of ``kpcn export``."""
    e = add("export", help="write a model's networks (each input set's, each quality mode's) as ONNX graphs that run "
            "at any frame size, with a card (CARD.md) and a manifest (onnx.json), each checked against Keras")
    e.add_argument("model", help="a finished run folder or shipped model (e.g. models/default)")
    e.add_argument("--onnx", required=True, metavar="OUT", help="the folder to write (an earlier export there is "
                   "replaced; any other existing path is refused)")


def cmd_export(args) -> int:
    from kpcn_keras.onnx_export import MANIFEST, export
    from kpcn_keras.run import Run

    out = export(Run(args.model), args.onnx)
    print(f"exported {args.model} to {out}: {MANIFEST} and CARD.md beside the graphs")
    return 0


__all__ = ["cmd_export", "export_options", "runtime_option"]
