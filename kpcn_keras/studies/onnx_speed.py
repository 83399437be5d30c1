"""The ONNX runtime's speed beside torch's and OIDN's: reports/onnx_speed.{json,md} (docs/onnx.md).

A model's full denoise (features, every branch, the albedo network, recombination; tiles of the default size) of a
frame wrapped around to each size (``card.frame_of_size``) by torch in float32, by torch in the precision
``auto`` picks on this machine, and by onnxruntime (``--runtime onnx``, float32), and OIDN's (``pyoidn``, where
installed) on the same layers: called in turn ``--repeats`` times after a warm-up each
(``denoise_costs.alternating_seconds``, so that a slow spell of a shared machine hits them alike), the best of
each. Also the largest relative difference of the onnx output from torch's float32 one (the tolerance of
``kpcn_keras.onnx_export``). The record keeps the busiest other processes when it starts and the load average
before and after: on a shared machine that is what the times were measured beside.

  .venv/bin/python -m kpcn_keras.studies.onnx_speed [--run models/default]
      [--frame tests/fixtures/fixture-00008spp.exr] [--repeats 3] [--out reports]
"""

from __future__ import annotations

import argparse
import os
import sys

os.environ.setdefault("KERAS_BACKEND", "torch")

SIZES = ((256, 256), (1920, 1080))  # width, height


def measure(run_dir: str, frame: str, repeats: int) -> dict:
    """Per size, each denoiser's best seconds and the onnx output's largest relative difference from torch's."""
    import numpy as np

    from kpcn_keras.card import frame_of_size
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.precision import resolve
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings
    from kpcn_keras.studies.denoise_costs import alternating_seconds
    from prep import baselines, layouts

    settings = {"torch float32": InferenceSettings(precision="float32"),
                f"torch auto ({resolve('auto')})": InferenceSettings(precision="auto"),
                "onnx float32": InferenceSettings(precision="float32", runtime="onnx")}
    denoisers = {name: Denoiser.from_run(Run(run_dir), s) for name, s in settings.items()}
    source = layouts.read(frame).layers
    rows = []
    for width, height in SIZES:
        layers = frame_of_size(source, width, height)
        calls = {name: (lambda d=d, layers=layers: d(layers)["default"]) for name, d in denoisers.items()}
        if baselines.oidn_available():
            calls["oidn"] = lambda layers=layers: baselines.oidn_denoise(layers, mode="plain")
        outputs = {name: call() for name, call in calls.items()}  # the warm-ups
        seconds = alternating_seconds(calls, repeats)
        want = outputs["torch float32"].astype(np.float64)
        difference = np.abs(outputs["onnx float32"] - want) / (np.abs(want) + 0.01)
        rows.append({"width": width, "height": height, "seconds": {n: min(s) for n, s in seconds.items()},
                     "all_seconds": seconds, "onnx_largest_relative_difference": float(difference.max())})
    return {"denoisers": list(calls), "sizes": rows}


def markdown(record: dict) -> str:
    """The speed table and what was running beside it."""
    names = record["denoisers"]
    head = "| frame | " + " | ".join(f"{n} (s)" for n in names) + " | onnx / torch float32 | onnx vs torch (rel.) |"
    lines = [head, "|" + "---|" * (len(names) + 3)]
    for row in record["sizes"]:
        s = row["seconds"]
        cells = " | ".join(f"{s[n]:.3f}" for n in names)
        lines.append(f"| {row['width']}x{row['height']} | {cells} | {s['onnx float32'] / s['torch float32']:.2f} | "
                     f"{row['onnx_largest_relative_difference']:.1e} |")
    m = record["machine"]
    busy = "; ".join(record["busy"])
    return f"""# The ONNX runtime beside torch and OIDN

`{record['command']}` ({record['date']}, {record['started']} to {record['finished']}). Model `{record['run']}`, frame
`{record['frame']}` wrapped around to each size; each denoiser called in turn {record['repeats']} times after a
warm-up, the best time of each (all of them in onnx_speed.json). torch ran on {m['torch_threads']} threads,
onnxruntime {m['onnxruntime']} on as many.

{chr(10).join(lines)}

The last column: the largest difference of onnxruntime's output from torch's float32 one, relative to the pixel
(+0.01); docs/onnx.md states the tolerance.

**Not an idle machine.** {m['cpus']} CPUs, load average {m['load_average_before'][0]:.1f} before and
{m['load_average_after'][0]:.1f} after, this study at niceness {m['niceness']}; the busiest other processes when it
started (%CPU command): {busy}. The training that shares this machine takes cores from every denoiser alike
(alternating calls), so the ratios carry more than the seconds.
"""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="models/default")
    parser.add_argument("--frame", default="tests/fixtures/fixture-00008spp.exr")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", default="reports")
    args = parser.parse_args(argv)

    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as every kpcn command does (kpcn_keras.cli.main)
    import onnxruntime
    import torch

    from kpcn_keras.studies.denoise_costs import busy
    from kpcn_keras.studies.report import Report

    report = Report(args.out, "onnx_speed", png=False)
    report.check_writable()
    session = report.begin()
    others = busy()
    found = measure(args.run, args.frame, args.repeats)
    record = {**session.envelope(" ".join(["python -m kpcn_keras.studies.onnx_speed", *sys.argv[1:]])),
              "run": args.run, "frame": args.frame, "repeats": args.repeats, "busy": others, **found}
    record["machine"] = session.machine(torch_threads=torch.get_num_threads(), onnxruntime=onnxruntime.__version__,
                                        niceness=os.nice(0))
    report.write(record, markdown(record))
    print(markdown(record))
    return 0


if __name__ == "__main__":
    sys.exit(main())
