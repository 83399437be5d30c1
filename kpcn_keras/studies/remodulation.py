"""How much of a frame's error is the albedo its diffuse irradiance is multiplied back by
(docs/results/19-albedo-prefilter.md).

The diffuse network predicts irradiance (trained against the reference's), and the frame is that irradiance times
an albedo. For each frame, against its reference, as a ratio to OIDN's relMSE where ``pyoidn`` is installed:

- ``floor``: no network, the reference's irradiance times each albedo below, plus the reference's specular: the
  error the albedo alone leaves;
- ``kpcn``: the run's networks for what the frame has (``Run.serving``; each branch's output once), the irradiance
  times each albedo, plus the specular output.

The albedos: the input's (``noisy``), ``prep.albedo.prefilter``'s at its own setting and at each ``--setting``
r,f,k[,s], the run's albedo network's (``network``, where the network serving the frame has one: what it denoises
with then) and the reference's (``oracle``, an upper bound no renderer's frame gives). Then, per albedo, the median
floor as a fraction of the input albedo's, the frames where kpcn is below OIDN and the median ratio.

  .venv/bin/python -m kpcn_keras.studies.remodulation [--run RUN] [--setting 5,1,1.0,1 ...] [--pair-suffix -b]
      [FRAMES ...]
      # default: models/default on its held-out frames; frames of training scenes choose the settings

Writes nothing; prints markdown tables.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")


def main() -> None:
    import numpy as np

    from kpcn_keras.batch import read_frame
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_pairs, pairs_for_inputs
    from kpcn_keras.run import Run, default_model
    from kpcn_keras.studies.pair_variance import read_with_pair_variance
    from prep import albedo, baselines, colour, features, layouts, metrics

    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--run", help="a run or model folder (default: the shipped model)")
    parser.add_argument("--setting", action="append", default=[],
                        help="a prefilter setting r,f,k[,s] beyond the module's own (repeat for more)")
    parser.add_argument("--pair-suffix", help="each frame with its second render, the file named with this after "
                        "its stem: the variance from the two (studies.pair_variance)")
    parser.add_argument("frames", nargs="*", help="noisy renders (default: the run's held-out frames)")
    args = parser.parse_args()
    run = Run(args.run) if args.run else default_model()
    pairs = pairs_for_inputs(args.frames) if args.frames else held_out_pairs(run, run.record())
    settings = [(albedo.SEARCH_RADIUS, albedo.PATCH_RADIUS, albedo.STRENGTH, albedo.VARIANCE_RADIUS)]
    for setting in args.setting:
        r, f, k, *s = setting.split(",")
        settings.append((int(r), int(f), float(k), int(s[0]) if s else albedo.VARIANCE_RADIUS))
    names = ["noisy"] + [f"r{r} f{f} k{k} s{s}" for r, f, k, s in settings] + ["network", "oracle"]
    oidn = baselines.oidn_available()
    denoisers = {}
    rows, floors = [], []
    columns = [f"floor {n}" for n in names] + [f"kpcn {n}" for n in names]
    print(f"| frame | OIDN relMSE | {' | '.join(columns)} |")
    print("|---|---|" + "---|" * 2 * len(names))
    for noisy_path, ref_path in pairs:
        pair = None
        if args.pair_suffix:
            pair = Path(noisy_path).with_name(Path(noisy_path).stem + args.pair_suffix + Path(noisy_path).suffix)
        frame = read_frame(noisy_path) if pair is None else read_with_pair_variance(noisy_path, pair)
        reference = layouts.read(ref_path)
        noisy, ref = frame.layers, reference.layers
        # a reference without a split or an albedo of its own (an rgb file) has no floor and no oracle
        whole = reference.inputs.split and not any(note.startswith("no albedo") for note in reference.notes)
        served = run.serving(frame.inputs)
        if served.dir not in denoisers:
            denoisers[served.dir] = Denoiser.from_run(served)
        den = denoisers[served.dir]
        log_irradiance = den.run_branch("diffuse", noisy)
        specular = colour.specular_from_log(den.run_branch("specular", noisy))
        given = den.given(noisy)  # as the denoiser reads it: no variance layer is zeros
        learned = (den.frame_albedo(given, features.depth_scale(given["depth"]))
                   if den.albedo_network is not None else None)
        albedos = [noisy["albedo"]] + [albedo.prefilter(noisy["albedo"], given["albedoVariance"], r=r, f=f, k=k, s=s)
                                       for r, f, k, s in settings] + [learned, ref["albedo"] if whole else None]
        scale = metrics.relmse(baselines.oidn_denoise(noisy, mode="plain"), ref["default"]) if oidn else 1.0
        floor = [np.nan] * len(albedos)
        if whole:
            irradiance = colour.irradiance(ref["diffuse"], ref["albedo"])
            floor = [np.nan if a is None else metrics.relmse(
                np.float32(colour.remodulate(irradiance, a) + ref["specular"]), ref["default"])
                / scale for a in albedos]
        kpcn = [np.nan if a is None else metrics.relmse(np.float32(colour.diffuse_from_log(log_irradiance, a)
                                                                   + specular), ref["default"]) / scale
                for a in albedos]
        rows.append(kpcn)
        floors.append([x / floor[0] if whole else np.nan for x in floor])
        name = os.path.basename(noisy_path)
        print(f"| {name} | {scale:.5f} | " + " | ".join(f"{x:.4f}" for x in floor + kpcn) + " |", flush=True)
    rows, floors = np.array(rows), np.array(floors)
    print("\n| albedo | floor / the input's albedo's, median | frames where kpcn is below OIDN | median kpcn / OIDN |")
    print("|---|---|---|---|")
    for i, n in enumerate(names):
        kept = ~np.isnan(rows[:, i])
        if not kept.any():
            print(f"| {n} | – | – | – |")
            continue
        floor = f"{np.median(floors[kept, i]):.3f}" if not np.isnan(floors[kept, i]).any() else "–"
        print(f"| {n} | {floor} | {int((rows[kept, i] < 1).sum())} of {int(kept.sum())} | "
              f"{np.median(rows[kept, i]):.3f} |")
    if not oidn:
        print("(pyoidn is not installed: the figures are relMSE, not ratios to OIDN's)")


if __name__ == "__main__":
    main()
