"""Where a frame's error is: in its brightest errors or spread over the frame: what closes the gap to OIDN.

relMSE is a mean over pixels, so a gap to OIDN can be a few pixels far off (a highlight or firefly kept or lost)
or most pixels a little off (low-frequency blotches). For each frame, kpcn (the run's network for what the frame
has, ``Run.serving``), OIDN and, where the folder has it, the renderer's own denoised frame: relMSE, the share of
it in the 0.1 % and the 1 % of pixels with the largest error, and the relMSE of the other 99 % (the body).
Pixels are ranked by their relSE averaged over R, G, B (``prep.metrics.relse_pixels``, as relSE p99.9 ranks them).

  .venv/bin/python -m kpcn_keras.studies.error_tail [--run RUN] [--spp 16] [FRAMES ...]
      # default: models/default, Blender's

Writes nothing; prints one markdown table.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")

SHARES = (0.001, 0.01)  # the brightest-error fractions of the pixels reported; the body is what the last leaves


def split(x, reference) -> dict:
    """relMSE of ``x``, the share of it in each of :data:`SHARES` of its worst pixels, and the rest's relMSE."""
    import numpy as np

    from prep import metrics

    errors = np.sort(metrics.relse_pixels(x, reference).ravel())[::-1]
    total = errors.sum()
    cut = [max(1, int(len(errors) * share)) for share in SHARES]
    return {"relmse": metrics.relmse(x, reference), "shares": [errors[:n].sum() / total for n in cut],
            "body": float(errors[cut[-1]:].mean())}


def main() -> None:
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run, default_model
    from kpcn_keras.studies.config import VALIDATION_FRAMES
    from kpcn_keras.studies.frames import beside, renderer_pairs
    from prep import exr, layouts

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("frames", nargs="*", default=[VALIDATION_FRAMES[0]], help="files or folders of frames, "
                        "each with its reference beside it (default: %(default)s)")
    parser.add_argument("--run", help="run or model folder (default: the model kpcn denoise uses without --run)")
    parser.add_argument("--spp", type=int, default=16, help="input spp of the frames measured (default: %(default)s)")
    args = parser.parse_args()

    run, denoisers = Run(args.run) if args.run else default_model(), {}
    header = ["frame", "method", "relMSE"] + [f"share in the worst {100 * s:g} %" for s in SHARES] + [
        f"relMSE of the other {100 * (1 - SHARES[-1]):g} %"]
    print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for noisy, ref in renderer_pairs(args.frames):
        scene, spp = exr.parse_render_filename(noisy)
        if spp != args.spp:
            continue
        frame, reference = layouts.read(noisy), layouts.read(ref).layers["default"]
        variant = run.serving(frame.inputs)
        if variant.dir not in denoisers:
            denoisers[variant.dir] = Denoiser.from_run(variant)
        methods = {"kpcn": denoisers[variant.dir](frame.layers)["default"], **beside(Path(noisy), frame)}
        for name, image in methods.items():
            got = split(image, reference)
            print(f"| {scene} {spp} spp | {name} | {got['relmse']:.5f} | "
                  + " | ".join(f"{s:.2f}" for s in got["shares"]) + f" | {got['body']:.5f} |", flush=True)


if __name__ == "__main__":
    main()
