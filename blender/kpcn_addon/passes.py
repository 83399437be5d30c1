"""Blender's side of the round trip: the passes kpcn reads best turned on, the Render Result written as the
multilayer EXR kpcn reads (or the frame rendered as two halves, each written so), and kpcn's output loaded back
as an image shown in the Image Editor."""

import os

import bpy
import numpy as np

from . import halves
from .exr_colour import read_colour
from .runner import AddonError

# The view layer's passes kpcn's Cycles layout reads (prep/layouts.py CYCLES_PASSES: the diffuse / specular split,
# its colour passes, Emit, Env, the normal and depth), as kpcn render-cycles turns them on for the frames the shipped
# model was trained on (prep/render/blender/cycles_set.py PASSES, which tests/test_blender_addon.py holds equal)
PASSES = ("combined", "z", "normal", "emit", "environment",
          "diffuse_direct", "diffuse_indirect", "diffuse_color",
          "glossy_direct", "glossy_indirect", "glossy_color",
          "transmission_direct", "transmission_indirect", "transmission_color")
# Cycles' own passes of the view layer: what a medium scatters (kpcn adds it to specular) and Denoising Data
CYCLES_PASSES = ("use_pass_volume_direct", "use_pass_volume_indirect", "denoising_store_passes")
# Cycles' settings a half sets (as kpcn blend-pair does) and the scene gets back after the pair
HALF_SETTINGS = ("samples", "seed", "use_animated_seed", "use_adaptive_sampling", "use_denoising", "time_limit")
# True while the halves render: the after-render handler leaves them alone (the pair operator denoises them)
RENDERING_HALVES = [False]


def use_passes(scene, on: bool) -> None:
    """Turn on every pass kpcn reads on each view layer, Blender's own denoiser off for the render (its state
    before kept, and given back when ``on`` is False; the passes stay on: they cost memory, not samples)."""
    settings = scene.kpcn
    if on:
        for vl in scene.view_layers:
            for p in PASSES:
                setattr(vl, "use_pass_" + p, True)
            for p in CYCLES_PASSES:
                setattr(vl.cycles, p, True)
        if not settings.denoiser_saved:
            settings.blender_denoiser, settings.denoiser_saved = scene.cycles.use_denoising, True
        scene.cycles.use_denoising = False
    elif settings.denoiser_saved:
        scene.cycles.use_denoising, settings.denoiser_saved = settings.blender_denoiser, False


def render_result():
    """Blender's Render Result image, None where nothing was rendered yet."""
    image = bpy.data.images.get("Render Result")
    return image if image is not None and image.type == "RENDER_RESULT" else None


def save_render_result(scene, image, path: str) -> None:
    """The Render Result with every pass as a 32-bit multilayer EXR at ``path``; the scene's output format is
    set for the write and given back after it."""
    im = scene.render.image_settings
    keys = [k for k in ("media_type", "file_format", "color_depth", "exr_codec") if hasattr(im, k)]
    before = {k: getattr(im, k) for k in keys}
    try:
        if "media_type" in before:  # Blender 5: the format list depends on the media type
            im.media_type = "MULTI_LAYER_IMAGE"
        im.file_format, im.color_depth, im.exr_codec = "OPEN_EXR_MULTILAYER", "32", "ZIP"
        image.save_render(path, scene=scene)
    finally:
        for k in keys:
            setattr(im, k, before[k])


def render_halves(scene, folder: str) -> list[str]:
    """The current frame rendered twice by Cycles, each half at half the scene's samples at every pixel (adaptive
    sampling off) with its own seed (``halves.half_seeds`` of the scene's), Blender's denoiser off, no time
    limit, the passes as the scene has them; each Render Result written as :func:`save_render_result` writes it,
    ``folder``/``halves.NAMES``: their paths. The scene's settings are given back after (:data:`HALF_SETTINGS`),
    whatever happens; the Render Result is the second half's. AddonError in one line for a scene that does not
    render with Cycles, samples that do not halve, or a render cancelled."""
    if scene.render.engine != "CYCLES":
        raise AddonError(f"a pair is rendered by Cycles (its seed): scene '{scene.name}' renders with "
                         f"{scene.render.engine}")
    c = scene.cycles
    try:
        samples = halves.half_samples(c.samples)
    except ValueError as exc:
        raise AddonError(str(exc)) from None
    before = {k: getattr(c, k) for k in HALF_SETTINGS}
    paths = [os.path.join(folder, name) for name in halves.NAMES]
    RENDERING_HALVES[0] = True
    try:
        for path, seed in zip(paths, halves.half_seeds(before["seed"])):
            c.samples, c.seed, c.time_limit = samples, seed, 0.0
            c.use_animated_seed = c.use_adaptive_sampling = c.use_denoising = False
            if "FINISHED" not in bpy.ops.render.render():
                raise AddonError("render cancelled: no pair to denoise")
            save_render_result(scene, render_result(), path)
            if not os.path.isfile(path):
                raise AddonError(f"Blender wrote no {path}")
    finally:
        RENDERING_HALVES[0] = False
        for k, v in before.items():
            setattr(c, k, v)
    return paths


def image_name(scene, frame: int, what: str = "kpcn") -> str:
    """The denoised image's name: ``<scene> frame <n> kpcn`` (``kpcn pair`` for a pair's)."""
    return f"{scene.name} frame {frame} {what}"


def load_result(path: str, name: str):
    """kpcn's denoised colour as image ``name`` (float, scene linear; one of that name before is replaced), packed
    into the .blend (the temporary file goes), and shown in every open Image Editor."""
    colour = read_colour(path)
    height, width = colour.shape[:2]
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)
    image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
    image.pixels.foreach_set(np.ascontiguousarray(colour[::-1]).ravel())  # Blender's rows run bottom to top
    image.pack()
    show(image)
    return image


def show(image) -> None:
    wm = bpy.context.window_manager
    for window in wm.windows if wm else ():
        for area in window.screen.areas:
            if area.type == "IMAGE_EDITOR":
                area.spaces.active.image = image


def denoised_path(frame_file: str) -> str:
    """Where an animation's denoised frame goes: beside the frame Blender wrote, ``<name>-kpcn.exr``."""
    stem, _ = os.path.splitext(frame_file)
    return stem + "-kpcn.exr"
