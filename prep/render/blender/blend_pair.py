"""A user's .blend frame as two halves for ``kpcn denoise A --pair B``: the frame rendered twice by Cycles at half
the samples with two seeds (catalogue.half_seeds of the scene's own seed), every pass kpcn reads on each view
layer (cycles_set.use_passes), one 32-bit multilayer EXR each, OUT/<blend stem>-<spp/2>spp-pair-a.exr and -pair-b.exr
(catalogue.pair_names), Cycles writing each half's samples in its header.

Runs under bpy, started by ``kpcn blend-pair`` (``prep.render.blendpair``, which checks the options and the
Python), so it imports nothing of kpcn, only the standard library, bpy and the files beside it:
  kpcn blend-pair FILE.blend --spp N [--frame F] [--out DIR] [--blender-python .venv-bpy/bin/python]
What the file sets is kept (resolution, camera, motion blur, bounces, light paths) but what a half must differ
in: Cycles (whatever engine the file names), N/2 samples at every pixel (adaptive sampling off), the seed not
animated, Blender's denoiser off, no time limit. A half already there is kept, so a killed run resumes.
"""
import argparse
import os
import sys
import time

import bpy

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))  # as when run as a script, for a reader's import
import catalogue  # noqa: E402  beside this file: the pair's names and seeds
import cycles_set  # noqa: E402  beside this file: the passes kpcn reads, the EXR settings


def arguments(argv):
    ap = argparse.ArgumentParser()
    ap.add_argument("blend")
    ap.add_argument("out")
    ap.add_argument("--spp", type=int, required=True, help="the whole frame's samples: each half renders half")
    ap.add_argument("--frame", type=int, help="the frame to render (default: the file's current frame)")
    return ap.parse_args(argv)


def prepare(scene, spp, seed):
    """``scene`` set to render a half: ``spp`` samples at every pixel with Cycles' ``seed``, every pass."""
    if scene.render.engine != "CYCLES":
        print(f"{scene.name}: renders with {scene.render.engine}; the halves are rendered with Cycles", flush=True)
        scene.render.engine = "CYCLES"
    c = scene.cycles
    c.samples, c.seed, c.use_animated_seed = spp, seed, False
    c.use_adaptive_sampling, c.use_denoising, c.time_limit = False, False, 0.0
    for vl in scene.view_layers:
        cycles_set.use_passes(vl)
    cycles_set.multilayer_exr(scene)


def main():
    a = arguments(sys.argv[sys.argv.index("--") + 1:] if "--" in sys.argv else sys.argv[1:])
    bpy.ops.wm.open_mainfile(filepath=a.blend)
    scene = bpy.context.scene
    if a.frame is not None:
        scene.frame_set(a.frame)
    os.makedirs(a.out, exist_ok=True)
    stem = os.path.splitext(os.path.basename(a.blend))[0]
    own = scene.cycles.seed
    for name, seed in zip(catalogue.pair_names(stem, a.spp), catalogue.half_seeds(own)):
        path = os.path.join(a.out, name)
        if os.path.exists(path):
            print(f"{path}: there, kept", flush=True)
            continue
        t = time.perf_counter()
        prepare(scene, a.spp // 2, seed)
        scene.render.filepath = os.path.join(a.out, "." + name)
        bpy.ops.render.render(write_still=True)
        os.replace(scene.render.filepath, path)
        print(f"{path}: {a.spp // 2} spp, Cycles seed {seed}, {time.perf_counter() - t:.1f} s", flush=True)


if __name__ == "__main__":
    main()
