"""What a new λ map costs against a full denoise, in one process
(docs/results/11-painted-slope-map.md).

For each run (trained with ``--slope-module``, with or without ``--slope-mixture``) and each frame size (a real
render wrapped around to it: ``card.frame_of_size``): the seconds of a full denoise at a λ map
(``Denoiser.__call__``), of preparing the frame once (``Denoiser.prepare``: the trunks), of a new map applied to
the prepared frame (``PreparedFrame.__call__``) and of a brush stroke (a ``STROKE`` x ``STROKE`` region re-applied,
what ``kpcn view`` sends), each the best of ``--repeats``, the calls alternating so that each run's figures are
measured side by side; the bytes the prepared frame holds; the ratio of a new map to a full denoise against the
issue's targets (:data:`TARGET_RATIO`, :data:`TARGET_MS` at 512 x 512). Each new map is another smooth random
map (log λ bilinear between random nodes), so that nothing is cached between calls. ``busy`` lists the busiest
other processes when it starts, with the load average before and after.

Writes ``<out>.json``, ``<out>.md`` and, per run, ``<out>-<run name>.png``: the held-out frame with λ at the
low end of the range on the left half and the high end on the right, beside both uniform frames
(``figures.slope_map_figure``: Fig. 17 with a map).

  .venv/bin/python -m kpcn_keras.studies.slope_map_costs --runs runs/lambda,runs/lambda-mixture [--repeats 5]
                                              [--out reports/slope_map]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")
sys.path.insert(0, str(Path(__file__).parent))

from denoise_costs import busy  # noqa: E402 (the script beside this one)

SIZES = ((256, 256), (512, 512), (1920, 1080))  # width, height
STROKE = 64  # pixels a side of the region a brush stroke re-applies
WARM_UP = 3  # new maps applied before the timing, at each size
TARGET_RATIO, TARGET_MS, TARGET_SIZE = 0.2, 150.0, (512, 512)


def random_map(rng, shape, slope_range):
    import numpy as np

    from kpcn_keras import slope_map

    nodes = rng.uniform(*np.log(slope_range), (3, 4))
    return np.exp(slope_map.bilinear(nodes, shape)).astype(np.float32)


def measure(denoisers: dict, layers_of: dict, repeats: int, seed: int) -> dict:
    """Per run name and size: the best seconds of each call (the module docstring)."""
    import gc

    import numpy as np

    rng = np.random.default_rng(seed)
    found = {}
    for (width, height), layers in layers_of.items():
        shape = (height, width)
        y0, x0 = (height - STROKE) // 2, (width - STROKE) // 2
        region = (y0, y0 + STROKE, x0, x0 + STROKE)
        prepared, best = {}, {}
        for name, den in denoisers.items():
            slope_range = den.record.train.slope_range
            den(layers, slope=random_map(rng, shape, slope_range))  # the warm-up at this size
            start = time.perf_counter()
            prepared[name] = den.prepare(layers)
            best[name] = {"prepare_s": time.perf_counter() - start, "full_s": np.inf, "new_map_s": np.inf,
                          "stroke_s": np.inf}
            for _ in range(WARM_UP):  # torch's first calls at a shape are slower (measured: 24 against 9 ms)
                prepared[name](random_map(rng, shape, slope_range))
        for _ in range(repeats):
            for name, den in denoisers.items():
                for key in ("full_s", "new_map_s", "stroke_s"):
                    slopes = random_map(rng, shape, den.record.train.slope_range)  # drawn outside the timing
                    start = time.perf_counter()
                    if key == "full_s":
                        den(layers, slope=slopes)
                    else:
                        prepared[name](slopes, region if key == "stroke_s" else None)
                    best[name][key] = min(best[name][key], time.perf_counter() - start)
        for name in denoisers:
            row = {**best[name], "prepared_mb": prepared[name].nbytes / 2**20}
            row["ratio"] = row["new_map_s"] / row["full_s"]
            found.setdefault(name, {})[f"{width}x{height}"] = row
        del prepared
        gc.collect()
    return found


def report_md(found: dict) -> str:
    lines = [
        "# A new λ map against a full denoise",
        "",
        f"Written by `python -m kpcn_keras.studies.slope_map_costs` on {found['date']} (this machine: "
        f"{found['cpus']} CPUs, {found['threads']} torch threads, precision {found['precision']}; busiest processes "
        f"at the start: {'; '.join(found['busy'])}; load average {found['load_before'][0]:.2f} before, "
        f"{found['load_after'][0]:.2f} after). Each figure is the best of {found['repeats']}, the runs' calls "
        "alternating. *full*: a whole denoise at a λ map; *prepare*: the trunks once "
        "(`Denoiser.prepare`); *new map*: another whole map on the prepared frame; *stroke*: a "
        f"{STROKE}×{STROKE} region re-applied (what `kpcn view` sends); *held*: what the prepared frame keeps.",
        "",
        f"Targets: a new map in at most {TARGET_RATIO:g} of a full denoise, and within {TARGET_MS:g} ms "
        f"at {TARGET_SIZE[0]}×{TARGET_SIZE[1]}.",
        "",
        "| run | size | full s | prepare s | new map ms | new map / full | stroke ms | held MB | targets |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, sizes in found["runs"].items():
        for size, row in sizes.items():
            met = row["ratio"] <= TARGET_RATIO
            if size == f"{TARGET_SIZE[0]}x{TARGET_SIZE[1]}":
                met = met and row["new_map_s"] * 1000 <= TARGET_MS
            lines.append(f"| {name} ({found['describe'][name]}) | {size.replace('x', '×')} | {row['full_s']:.3f} | "
                         f"{row['prepare_s']:.3f} | {row['new_map_s'] * 1000:.0f} | {row['ratio']:.3f} | "
                         f"{row['stroke_s'] * 1000:.0f} | {row['prepared_mb']:.0f} | {'met' if met else 'missed'} |")
    lines += ["", "Figures (Fig. 17 with a map: λ at the range's low end on the left half, its high end on the "
              "right, beside both uniform frames; the captions give each half's largest difference from its "
              "uniform frame):", ""]
    lines += [f"![{name}]({Path(path).name})" for name, path in found["figures"].items()]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", default="runs/lambda,runs/lambda-mixture")
    parser.add_argument("--frame", default="tests/fixtures/fixture-00008spp.exr", help="the render timed")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="reports/slope_map")
    args = parser.parse_args()

    from prep.processes import keep_freed_memory

    keep_freed_memory()  # as every kpcn command does (kpcn_keras.cli.main)
    import torch

    from kpcn_keras.card import frame_of_size
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_pairs
    from kpcn_keras.figures import slope_map_figure
    from kpcn_keras.run import Run
    from prep import exr, layouts
    from prep.files import atomic_write_json

    found = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "busy": busy(),
             "load_before": os.getloadavg(), "frame": args.frame, "threads": torch.get_num_threads(),
             "cpus": os.cpu_count(), "repeats": args.repeats}
    runs = {Path(r).name: Run(r) for r in args.runs.split(",")}
    denoisers = {name: Denoiser.from_run(run) for name, run in runs.items()}
    found["precision"] = next(iter(denoisers.values())).precision
    found["describe"] = {name: f"--slope-module {d.model_config.slope_module}" + (
        f" --slope-mixture {d.model_config.slope_mixture}" if d.model_config.slope_mixture else "")
        for name, d in denoisers.items()}
    frame = layouts.read(args.frame).layers
    layers_of = {size: frame_of_size(frame, *size) for size in SIZES}
    found["runs"] = measure(denoisers, layers_of, args.repeats, args.seed)
    found["load_after"] = os.getloadavg()
    out = Path(args.out)
    found["figures"] = {}
    for name, den in denoisers.items():
        noisy, reference = min(held_out_pairs(den.run, den.record), key=lambda p: exr.parse_render_filename(p[0]))
        aovs, ref = exr.read_aovs(noisy), exr.read_aovs(reference, variances=False)
        path = slope_map_figure(den, aovs, ref, out.with_name(f"{out.name}-{name}.png"))
        found["figures"][name] = str(path)
        found.setdefault("figure_frames", {})[name] = str(noisy)
    atomic_write_json(out.with_suffix(".json"), found)
    out.with_suffix(".md").write_text(report_md(found))
    print(report_md(found))


if __name__ == "__main__":
    main()
