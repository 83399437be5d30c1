"""A Cycles frame's two halves as the two halves of one sample sequence (Cycles' Sample Subset), beside a folder
of `kpcn cycles-validation` frames, for measuring pairs whose mean is the one full render.

`kpcn cycles-validation` renders a frame's halves with two seeds at half the samples: independent, as
Noise2Noise wants, but their mean is noisier than Cycles' own render of all the samples, whose sampler stratifies
across all of them. Cycles can render the first and the second half of one N-sample sequence instead
(``cycles.samples = N``, ``use_sample_subset``, ``sample_offset`` 0 and N/2, ``sample_subset_length`` N/2, the
full render's seed): their mean is that render. This writes, for each scene of FOLDER that has its N-spp frame,
OUT/<scene>-<N/2>spp-pair-a.exr and -pair-b.exr rendered so (every pass, ``cycles_set.setup``), and links the
scene's recipe, its N-spp frame, Blender's denoised frame and the reference beside them, so OUT reads as a
validation folder whose pairs are subsets (``python -m kpcn_keras.studies.adapt_report FOLDER --more OUT``
compares the two kinds of pairs). A study's input, not a user's step.

It runs in Blender's Python (the venv of ``kpcn render-cycles``), from the repository's root:

  .venv-bpy/bin/python -m kpcn_keras.studies.render_subset_halves data/cycles/dev OUT [--spp 16] [--seed 1]

``--seed`` is the one FOLDER was rendered with (``kpcn cycles-validation --seed``): the full render's Cycles seed
is drawn from it as that command draws it.
"""
import argparse
import json
import os
import sys


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("folder")
    ap.add_argument("out")
    ap.add_argument("--spp", type=int, default=16, help="the full render's samples, even (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=1, help="the folder's --seed (default: %(default)s)")
    a = ap.parse_args()
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "prep", "render", "blender"))
    import bpy  # noqa: E402
    import catalogue  # noqa: E402
    import cycles_set  # noqa: E402  the scenes, their seeds and setup (needs bpy)

    os.makedirs(a.out, exist_ok=True)
    drawn = argparse.Namespace(seed=a.seed, split=catalogue.VALIDATION.name)
    for name in sorted(f[:-5] for f in os.listdir(a.folder) if f.startswith("val-") and f.endswith(".json")):
        recipe = json.load(open(os.path.join(a.folder, name + ".json")))
        full = catalogue.frame_name(name, a.spp)
        if not os.path.exists(os.path.join(a.folder, full)):
            continue
        seeds = {n: seed for n, _, seed, _, _ in cycles_set.planned_renders(drawn, recipe, recipe["frames"])}
        factor = cycles_set.exposure(recipe)
        for half, offset in zip(catalogue.pair_names(name, a.spp), (0, a.spp // 2)):
            scene = cycles_set.setup(recipe, a.spp, seeds[full], factor)
            c = scene.cycles
            c.use_sample_subset, c.sample_offset, c.sample_subset_length = True, offset, a.spp // 2
            scene.render.filepath = os.path.join(a.out, "." + half)
            bpy.ops.render.render(write_still=True)
            os.replace(scene.render.filepath, os.path.join(a.out, half))
        for f in (name + ".json", full, catalogue.denoised_name(name, a.spp),
                  catalogue.frame_name(name, recipe["frames"][-1])):
            link = os.path.join(a.out, f)
            if not os.path.lexists(link):
                os.symlink(os.path.abspath(os.path.join(a.folder, f)), link)
        print(name, "halves of one", a.spp, "sample sequence, seed", seeds[full], flush=True)


if __name__ == "__main__":
    main()
