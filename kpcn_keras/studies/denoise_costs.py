"""What a 1920 x 1080 denoise costs in each precision, beside OIDN, in one process
(docs/results/10-quality-levers.md §10c).

Prints one JSON object: the seconds of a model's full denoise (features, both branches, recombination; tiles of
the default size) of a frame wrapped around to 1920 x 1080 (``card.frame_of_size``), in float32 and in bfloat16
(``kpcn_keras.precision``), and OIDN's (``pyoidn``) on the same layers, called alternately ``--repeats`` times
after a warm-up each, the best of each and its ratio to OIDN's; with ``--profile``, where each precision's time
goes (torch's profiler: the convolutions, the kernel application, the ReLUs, everything else), and the
largest relative difference of the two precisions' outputs. ``--ensembles 2,8`` also times self-ensembles of
that many members (``kpcn denoise --ensemble``, in bfloat16 where the CPU has it: ``auto``). ``busy`` lists the
busiest other processes when it starts, the load average before and after.

  .venv/bin/python -m kpcn_keras.studies.denoise_costs [--run models/default]
      [--frame tests/fixtures/fixture-00008spp.exr] [--repeats 2] [--profile] [--ensembles 2,4,8]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import time

os.environ.setdefault("KERAS_BACKEND", "torch")

PRECISIONS = ("float32", "bfloat16")
SIZE = (1920, 1080)
# torch profiler op names -> the part of the denoise they are (the rest is features, recombination, glue)
KERNEL_APPLICATION = ("TorchKernelApply", "KernelApply")  # the autograd path's Function, the inference path's label
PARTS = {"aten::mkldnn_convolution": "convolutions", **dict.fromkeys(KERNEL_APPLICATION, "kernel application"),
         "aten::clamp_min": "ReLU", "aten::relu": "ReLU"}


def busy() -> list[str]:
    """The four busiest processes but this one and ps, as "%CPU command"."""
    ps = subprocess.run(["ps", "-eo", "pid,ppid,pcpu,comm", "--sort=-pcpu"], capture_output=True, text=True).stdout
    rows = [line.split(None, 2) for line in ps.splitlines()[1:]]
    return [rest.strip() for pid, ppid, rest in rows if os.getpid() not in (int(pid), int(ppid))][:4]


def alternating_seconds(calls: dict, repeats: int) -> dict[str, list[float]]:
    """Each of ``calls``' seconds (name -> a call of no arguments) over ``repeats`` rounds, the calls in turn in
    each round, so that a slow spell of a shared machine hits them alike. Warm each up first: a first call's
    allocations are not its cost."""
    seconds = {name: [] for name in calls}
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            seconds[name].append(time.perf_counter() - start)
    return seconds


def profile(call) -> dict[str, float]:
    """Seconds of one ``call`` by part (:data:`PARTS`), from torch's profiler (its own overhead included)."""
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    start = time.perf_counter()
    with torch_profile(activities=[ProfilerActivity.CPU]) as prof:
        call()
    total = time.perf_counter() - start
    parts = dict.fromkeys(dict.fromkeys(PARTS.values()), 0.0)
    for event in prof.key_averages():
        if event.key in PARTS:
            # the kernel application's own ops run inside it: its total, not its self time
            seconds = event.cpu_time_total if event.key in KERNEL_APPLICATION else event.self_cpu_time_total
            parts[PARTS[event.key]] += seconds / 1e6
    parts["the rest"] = total - sum(parts.values())
    return {"profiled_s": total, **parts}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", default="models/default")
    parser.add_argument("--frame", default="tests/fixtures/fixture-00008spp.exr")
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--ensembles", type=lambda text: [int(n) for n in text.split(",")], default=[])
    args = parser.parse_args()

    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as every kpcn command does (kpcn_keras.cli.main)
    import numpy as np
    import torch

    from kpcn_keras.card import frame_of_size
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings
    from prep import baselines, layouts

    found = {"busy": busy(), "load_before": os.getloadavg(), "run": args.run, "frame": args.frame,
             "size": SIZE, "threads": torch.get_num_threads(), "cpus": os.cpu_count()}
    layers = frame_of_size(layouts.read(args.frame).layers, *SIZE)
    denoisers = {p: Denoiser.from_run(Run(args.run), InferenceSettings(precision=p)) for p in PRECISIONS}
    denoisers.update({f"ensemble {n}": Denoiser.from_run(Run(args.run), InferenceSettings(ensemble=n))
                      for n in args.ensembles})
    calls = {p: (lambda d=d: d(layers)["default"]) for p, d in denoisers.items()}
    if baselines.oidn_available():
        calls["oidn"] = lambda: baselines.oidn_denoise(layers, mode="plain")
    outputs = {name: call() for name, call in calls.items()}  # the warm-ups
    best = {name: min(seconds) for name, seconds in alternating_seconds(calls, args.repeats).items()}
    found["seconds"] = best
    if "oidn" in best:
        found["ratio_to_oidn"] = {p: best[p] / best["oidn"] for p in denoisers}
    a, b = (outputs[p].astype(np.float64) for p in PRECISIONS)
    found["largest_relative_difference"] = float(np.max(np.abs(b - a) / (np.abs(a) + 0.01)))
    if args.profile:
        found["profile"] = {p: profile(calls[p]) for p in PRECISIONS}
    found["load_after"] = os.getloadavg()
    print(json.dumps(found, indent=2))


if __name__ == "__main__":
    main()
