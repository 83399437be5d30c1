"""Pairs of Blender Cycles renders of the validation scenes, for measuring `kpcn denoise A.exr --pair B.exr`.

For each scene of the validation set's script (shared/validation/render_blender_validation.py, which builds the
scenes) and each total spp N of its ladder (4, 16, 64): two renders of N/2 spp with different seeds,
OUT/<scene>-<N/2>spp-pair-a.exr and -pair-b.exr (catalogue.pair_names), with every pass of the validation frames
(so their mean has N spp, as the validation set's own N-spp frame), and the validation set's reference copied
beside them (OUT/<scene>-<ref>spp.exr), so `kpcn inputs-study --pairs OUT` compares, at the same samples, the
mean without variance against the mean with the variance of their difference.

A study's input, not a user's step (the pairs serve only ``kpcn inputs-study --pairs``), so it lives with the
studies. It runs in Blender's Python (the `bpy` wheel; 5.0.1 wants numpy < 2, so its own venv, the one
``kpcn render-cycles`` uses), from the repository's root, where that Python finds ``kpcn_keras`` without kpcn
installed (importing ``kpcn_keras`` and its studies' package imports nothing but the standard library):

  .venv-bpy/bin/python -m kpcn_keras.studies.render_blender_pairs OUT --validation ../shared/validation \
      [--scenes a,b] [--res 256]
"""
import argparse
import os
import shutil
import sys

SPPS = (4, 16, 64)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out")
    ap.add_argument("--validation", required=True, help="the folder of render_blender_validation.py and blender/")
    ap.add_argument("--scenes", default="kitchen,bathroom,studio")
    ap.add_argument("--res", type=int, default=256)
    a = ap.parse_args()
    sys.path.insert(0, a.validation)
    import render_blender_validation as validation  # noqa: E402  (Blender's scenes; needs bpy)

    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "prep", "render", "blender"))
    import catalogue  # noqa: E402  the pairs' names (the standard library alone: this Python has no kpcn)

    os.makedirs(a.out, exist_ok=True)
    references = sorted(f for f in os.listdir(os.path.join(a.validation, "blender")) if f.endswith("02048spp.exr"))
    for si, name in enumerate(a.scenes.split(",")):
        for li, total in enumerate(SPPS):
            half = total // 2
            names = catalogue.pair_names(name, total)
            for file, seed in zip(names, (5000 + 100 * si + 10 * li + 1, 5000 + 100 * si + 10 * li + 2)):
                path = os.path.join(a.out, file)
                seconds = validation.render(path, name=name, res=a.res, spp=half, seed=seed, denoise=False,
                                            passes=True)
                print(f"{path}: {seconds:.1f} s", flush=True)
        for ref in references:
            if ref.startswith(f"{name}-"):
                shutil.copy(os.path.join(a.validation, "blender", ref), os.path.join(a.out, ref))


if __name__ == "__main__":
    main()
