"""Run by bpy's Python (tests/test_blender_addon.py): the kpcn add-on installed from its zip and driven as a
user drives it, headless. ``python blender_side.py ZIP KPCN OUT {checks,round_trip,pair} [STEPS SEED_A SEED_B]``
writes ``OUT/result.json`` (and, for round_trip and pair, ``OUT/loaded.npy``: the loaded image's RGBA pixels, top
row first as kpcn writes them; for pair, ``OUT/seed-<seed>.exr``: the frame rendered here at half the samples with
each of the seeds the caller expects the halves to have).

Blender's own settings, extensions included, go where BLENDER_USER_RESOURCES points (the caller's temporary
folder), never into the user's."""

import json
import os
import sys

import bpy
import numpy as np

ADDON = "bl_ext.user_default.kpcn"


def install(zip_path):
    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    return bpy.context.preferences.addons[ADDON].preferences


def tiny_scene():
    """The start-up scene (a cube, a lamp, a camera) in Cycles at 32 x 32, 4 samples, Blender's denoiser on as
    a user leaves it."""
    s = bpy.context.scene
    s.render.engine = "CYCLES"
    s.cycles.device, s.cycles.samples, s.cycles.use_denoising = "CPU", 4, True
    s.cycles.use_adaptive_sampling = False
    s.render.resolution_x = s.render.resolution_y = 32
    s.render.resolution_percentage = 100
    return s


def report_of(operator) -> dict:
    """What an operator reports when run from a script: its result, or the report line Blender raises."""
    try:
        return {"result": sorted(operator()), "report": ""}
    except RuntimeError as exc:
        return {"result": ["RuntimeError"], "report": str(exc)}


def checks(prefs, out):
    s = tiny_scene()
    vl = s.view_layers[0]
    got = {"before": [vl.use_pass_diffuse_color, vl.cycles.denoising_store_passes, s.cycles.use_denoising]}
    s.kpcn.use_passes = True  # the panel's checkbox
    from bl_ext.user_default.kpcn import passes
    got["on"] = {p: getattr(vl, "use_pass_" + p) for p in passes.PASSES}
    got["on_cycles"] = {p: getattr(vl.cycles, p) for p in passes.CYCLES_PASSES}
    got["denoiser_on"] = s.cycles.use_denoising
    s.kpcn.use_passes = False
    got["denoiser_off_again"] = s.cycles.use_denoising
    got["no_render"] = report_of(bpy.ops.kpcn.denoise_render)
    bpy.ops.render.render()
    prefs.kpcn_path = os.path.join(out, "no-such-kpcn")
    got["wrong_path"] = report_of(bpy.ops.kpcn.denoise_render)
    got["wrong_path_check"] = report_of(bpy.ops.kpcn.check)
    return got


def loaded(name, out):
    """Image ``name``'s pixels saved as ``OUT/loaded.npy``; whether it is packed into the .blend."""
    image = bpy.data.images[name]
    pixels = np.empty(image.size[0] * image.size[1] * 4, np.float32)
    image.pixels.foreach_get(pixels)
    # Blender's rows run bottom to top
    np.save(os.path.join(out, "loaded.npy"), pixels.reshape(image.size[1], image.size[0], 4)[::-1])
    return image.packed_file is not None


def round_trip(prefs, kpcn, out):
    s = tiny_scene()
    s.kpcn.use_passes = True
    bpy.ops.render.render()
    prefs.kpcn_path = kpcn
    got = {"denoise": report_of(bpy.ops.kpcn.denoise_render), "check": report_of(bpy.ops.kpcn.check),
           "found": prefs.found, "images": sorted(i.name for i in bpy.data.images)}
    got["packed"] = loaded(f"{s.name} frame {s.frame_current} kpcn", out)
    return got


PAIR_SETTINGS = ("samples", "seed", "use_animated_seed", "use_adaptive_sampling", "use_denoising", "time_limit")


def pair(prefs, kpcn, out, steps, seeds):
    """The pair button on the tiny scene as a user leaves it (seed 7 animated, adaptive sampling, Blender's
    denoiser and a time limit on), then the frame rendered here with each expected half's seed, 2 spp, no
    denoiser, written as the add-on writes a half."""
    s = tiny_scene()
    s.kpcn.use_passes = True
    c = s.cycles
    c.seed, c.use_animated_seed, c.use_adaptive_sampling, c.use_denoising, c.time_limit = 7, True, True, True, 60.0
    prefs.kpcn_path = kpcn
    before = {k: getattr(c, k) for k in PAIR_SETTINGS}
    got = {"pair": report_of(lambda: bpy.ops.kpcn.denoise_pair(adapt_steps=int(steps))),
           "message": prefs.last_message, "before": before, "after": {k: getattr(c, k) for k in PAIR_SETTINGS},
           "images": sorted(i.name for i in bpy.data.images)}
    got["packed"] = loaded(f"{s.name} frame {s.frame_current} kpcn pair", out)
    c.samples = 5
    got["odd"] = report_of(lambda: bpy.ops.kpcn.denoise_pair(adapt_steps=int(steps)))
    from bl_ext.user_default.kpcn import passes
    c.samples, c.use_animated_seed, c.use_adaptive_sampling, c.use_denoising, c.time_limit = 2, False, False, False, 0
    for seed in seeds:
        c.seed = int(seed)
        bpy.ops.render.render()
        passes.save_render_result(s, passes.render_result(), os.path.join(out, f"seed-{seed}.exr"))
    return got


def main(zip_path, kpcn, out, mode, *pair_args):
    prefs = install(zip_path)
    if mode == "checks":
        got = checks(prefs, out)
    elif mode == "pair":
        got = pair(prefs, kpcn, out, pair_args[0], pair_args[1:])
    else:
        got = round_trip(prefs, kpcn, out)
    with open(os.path.join(out, "result.json"), "w") as f:
        json.dump(got, f)


if __name__ == "__main__":
    main(*sys.argv[1:])
