"""What a 1920 x 1080 frame costs in each quality mode of a model, beside OIDN at each of its qualities, in one
process (``make modes-report`` runs it, then ``kpcn_keras.studies.modes_plot``).

Prints one JSON object (and with ``--out`` writes it there too): the seconds to denoise a frame wrapped around to
1920 x 1080 (``card.frame_of_size``) by each quality mode the model has (``Run.quality_modes``; each mode's own
networks, ``InferenceSettings(quality=MODE)``, as ``kpcn denoise --quality MODE`` runs them), by the prefilter of a
mode's auxiliaries alone where it has one (``Denoiser.given``: that share of the mode's time), and by OIDN at
``fast``, ``balanced`` and ``high`` (``prep.baselines.oidn_denoise``), both prefiltered (as Blender runs it: the
albedo and normal each denoised first at the same quality) and plain, on the layers OIDN is given
(``baselines.oidn_inputs``). Every method is warmed up, then all are called alternately ``--repeats`` times, so
that load from other processes hits them alike; ``best`` and ``median`` seconds of each, the ratios of each kpcn
mode to OIDN's same quality (best over best), torch's threads, the load average before and after and the busiest
other processes when it starts. Run it on an otherwise idle machine: it is a timing.

  .venv/bin/python -m kpcn_keras.studies.mode_costs [--model models/default]
      [--frame tests/fixtures/fixture-00008spp.exr] [--repeats 5] [--size 1920,1080] [--out reports/mode_costs.json]
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import statistics
import sys
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")

SIZE = (1920, 1080)


def kpcn_method(mode: str) -> str:
    """The probe's name of kpcn in quality mode ``mode``."""
    return f"kpcn {mode}"


def oidn_method(mode: str, quality: str) -> str:
    """The probe's name of OIDN in ``mode`` (``prep.baselines.OIDN_MODES``) at ``quality``."""
    return f"oidn_{mode} {quality}"


def prefilter_method(method: str) -> str:
    """The probe's name of the auxiliaries prefilter ``method`` (``prep.auxiliary``) alone."""
    return f"prefilter {method}"


def methods(model: Path, frame, size: tuple[int, int]) -> dict:
    """name -> a call denoising ``frame`` (a ``prep.layouts.Frame``) wrapped to ``size`` (width, height): each
    quality mode of ``model``, the prefilter of a mode's auxiliaries alone (where it has one), then OIDN in each
    mode at each quality (none where ``pyoidn`` is missing)."""
    from kpcn_keras.card import frame_of_size
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings
    from prep import auxiliary, baselines

    layers = frame_of_size(frame.served_layers(), *size)
    calls, prefilters = {}, {}
    for mode in Run(model).quality_modes():
        denoiser = Serving(Run(model), InferenceSettings(quality=mode)).denoiser(frame.inputs)
        calls[kpcn_method(mode)] = lambda d=denoiser: d(layers)["default"]
        if denoiser.auxiliaries != auxiliary.RAW:  # the share of the mode's time its prefilter takes
            prefilters[prefilter_method(denoiser.auxiliaries)] = (
                lambda d=denoiser: d.given(layers))
    calls.update(prefilters)
    if baselines.oidn_available():
        given = frame_of_size(baselines.oidn_inputs(frame), *size)
        for quality in baselines.OIDN_QUALITIES:
            for mode in baselines.OIDN_MODES:
                calls[oidn_method(mode, quality)] = (
                    lambda m=mode, q=quality: baselines.oidn_denoise(given, mode=m, quality=q))
    return calls


def timed(calls: dict, repeats: int) -> dict[str, list[float]]:
    """Each call's seconds over ``repeats`` rounds, after one warm-up each, the calls alternating in each round
    (``denoise_costs.alternating_seconds``)."""
    from kpcn_keras.studies.denoise_costs import alternating_seconds

    for call in calls.values():
        call()  # the warm-ups: first-call allocations, OIDN's device and weights
    return alternating_seconds(calls, repeats)


def ratios(best: dict[str, float]) -> dict:
    """{kpcn mode: {OIDN mode: kpcn's best / OIDN's best at the same quality}} where both were timed."""
    from prep import baselines

    found = {}
    for quality in baselines.OIDN_QUALITIES:
        if kpcn_method(quality) in best:
            found[quality] = {mode: best[kpcn_method(quality)] / best[oidn_method(mode, quality)]
                              for mode in baselines.OIDN_MODES if oidn_method(mode, quality) in best}
    return found


def probe(model: Path, frame_path: Path, size: tuple[int, int], repeats: int, command: str) -> dict:
    from kpcn_keras.batch import torch_threads
    from kpcn_keras.studies.denoise_costs import busy
    from prep import layouts

    found = {"command": command, "model": str(model), "frame": str(frame_path), "size": list(size),
             "repeats": repeats, "busy": busy(), "load_before": os.getloadavg(), "threads": torch_threads(),
             "cpus": os.cpu_count()}
    seconds = timed(methods(model, layouts.read(frame_path), size), repeats)
    best = {name: min(s) for name, s in seconds.items()}
    found.update({"best_s": best, "median_s": {name: statistics.median(s) for name, s in seconds.items()},
                  "ratio_to_oidn_same_quality": ratios(best), "load_after": os.getloadavg()})
    return found


def _size(text: str) -> tuple[int, int]:
    width, _, height = text.partition(",")
    return int(width), int(height)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.mode_costs",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="models/default", help="the model (default: %(default)s)")
    parser.add_argument("--frame", default="tests/fixtures/fixture-00008spp.exr",
                        help="the EXR the timed frame is made of (default: %(default)s)")
    parser.add_argument("--repeats", type=int, default=5, help="timed rounds (default: %(default)s)")
    parser.add_argument("--size", type=_size, default=SIZE, help="WIDTH,HEIGHT (default: 1920,1080)")
    parser.add_argument("--out", help="also write the JSON object here")
    args = parser.parse_args(argv)
    command = shlex.join(["python", "-m", "kpcn_keras.studies.mode_costs", *(sys.argv[1:] if argv is None else argv)])
    from prep.errors import KpcnError
    from prep.files import atomic_write_json
    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as every kpcn command does (kpcn_keras.cli.main)
    try:
        found = probe(Path(args.model), Path(args.frame), args.size, args.repeats, command)
    except KpcnError as exc:
        print(f"mode-costs: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(found, indent=2))
    if args.out:
        atomic_write_json(Path(args.out), found)
    return 0


if __name__ == "__main__":
    sys.exit(main())
