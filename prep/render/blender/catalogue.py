"""The Cycles scene catalogue: which effects a training scene may draw (:data:`EFFECTS`), and a scene drawn as a
recipe, a JSON-able dict of everything the scene is (its kind, resolution, surfaces, objects and their materials,
lights, world, camera, media, hair, text and the effects it drew), from a seed and a scene index alone.

Why a recipe apart from the build: what a scene holds can be read, tested and recorded without Blender
(``OUT/<scene>.json`` beside its frames, counted by ``manifest.py``), and the same (seed, index, resolutions)
draws the same recipe on any machine (``random.Random`` seeded with a string hashes it with SHA-512, not with
Python's per-process hash). ``cycles_set.py`` builds a recipe in bpy; this file imports only the standard library,
as it runs in Blender's Python, where kpcn is not installed.

The manifest of a folder of these renders (``OUT/manifest.json``, :func:`write_manifest`): scenes per effect and
per effect group, frames done against frames planned, and the CPU hours spent, counted from what the folder holds
(the recipes ``OUT/<scene>.json`` and ``OUT/render_log.json``), so it is the same whoever counts it: the Blender
side after each scene, kpcn's command at the end, a test on a folder of fake files. CPU time is the process CPU
time of Blender's Python over each frame (``time.process_time``: every render thread, the scene's build and its
exposure probe), as ``render_log.json`` records it under ``cpu``; a frame logged without it counts its wall
seconds times the log's ``threads``.
"""
import colorsys
import hashlib
import json
import math
import os
import random
import re
from collections import namedtuple

Effect = namedtuple("Effect", "name group weight builds")

# one table: the effects a scene draws from (by weight), their groups (a validation set draws >= 2 per group)
EFFECTS = (
    Effect("fog", "media", 3, "a homogeneous scattering medium filling the scene's box (Principled Volume)"),
    Effect("smoke", "media", 2, "a heterogeneous medium: a box whose density is a noise texture through a ramp"),
    Effect("shafts", "media", 2, "a room with a window opening, a sun or spot outside shining through it into fog"),
    Effect("glass_medium", "media", 1, "glass objects whose inside scatters and absorbs (a volume in the glass)"),
    Effect("subsurface", "subsurface", 3, "objects of skin, wax or marble: Principled subsurface scattering"),
    Effect("brick_far", "texture", 2, "a large brick wall across the scene, its bricks a few pixels wide"),
    Effect("fine_tiles", "texture", 2, "a finely tiled floor seen at a grazing angle from a low camera"),
    Effect("text", "texture", 1, "lines of text (Blender text objects) on a sign or on the floor"),
    Effect("dof", "camera", 2, "depth of field: a wide aperture focused on one object"),
    Effect("motion_blur", "camera", 2, "objects moving during the shutter (motion blur)"),
    Effect("hair", "hair", 2, "particle hair (Cycles curves) grown on an object"),
    Effect("sun_sky", "lighting", 2, "a physical sky (Blender's single/multiple scattering sky) and a sun lamp"),
    Effect("hdri", "lighting", 2, "an HDRI-like environment: procedural bright patches and a small hot spot"),
    Effect("window", "lighting", 2, "an interior closed but for a window, lit by the sun and sky through it"),
    Effect("emissive_mesh", "emission", 2, "glowing objects (emission shaders on meshes) lighting the scene"),
    Effect("glass_caustics", "caustics", 2, "clear glass objects under a small light: caustics on the floor"),
    Effect("water_caustics", "caustics", 1, "a wavy water surface over a floor lit from above: caustics below"),
    Effect("coat", "layered", 2, "clear coats over coloured and textured bases, tinted and rough"),
    Effect("sheen", "layered", 2, "cloth-like sheen over rough bases"),
)
BY_NAME = {e.name: e for e in EFFECTS}
GROUPS = tuple(dict.fromkeys(e.group for e in EFFECTS))
KINDS = ("room", "studio", "ground")
PRIMITIVES = ("cube", "uv_sphere", "ico_sphere", "cylinder", "torus", "monkey", "cone")
RECIPE_VERSION = 1  # a change to what a (seed, index) draws bumps it: a folder's recorded recipes then differ
SAMPLE_TEXT = ("THE QUICK BROWN FOX", "Exit 12", "kpcn 0123456789", "Ristorante", "OPEN 24H", "lorem ipsum dolor",
               "HOTEL", "No parking", "Cycles", "Departures")


Split = namedtuple("Split", "name stream prefix azimuths textures texts")

# A split partitions the draws: no training recipe can equal a validation one, whatever the seeds and indices.
# Each split has its own random streams (the string that seeds them), its own camera azimuths (every scene has a
# camera: the guarantee), and its own texture kinds and lines of text where a scene has them. Validation scenes
# also carry two effect groups each, by a schedule that covers every group twice in any 9 consecutive indices
# (forced_effects), brick walls of other proportions, and cameras inside their rooms. The training split is what
# the catalogue drew before splits existed, to the bit (RECIPE_VERSION unchanged: folders rendered keep resuming).
TRAIN = Split("train", "kpcn-cycles", "", ((-2.2, -0.9),), ("checker", "brick", "noise", "wave", "voronoi"),
              SAMPLE_TEXT)
VALIDATION = Split("validation", "kpcn-cycles-validation", "val-", ((-2.6, -2.25), (-0.85, -0.5)),
                   ("magic", "gabor"), ("Way Out", "Bakery & Cafe", "Platform 9", "Zimmer frei", "42 Elm Street",
                                        "CLOSED", "Fresh Fish", "Gate B7", "Quiet please", "Bus Stop"))
SPLITS = {s.name: s for s in (TRAIN, VALIDATION)}
PAIR_STEP = 4  # validation scene i carries groups i and i + PAIR_STEP (mod 9): a bijection, so 9 scenes cover 2x


def scene_rng(seed: int, index: int, split=TRAIN) -> random.Random:
    return random.Random(f"{split.stream}:{seed}:{index}")


def scene_res(seed: int, index: int, resolutions, split=TRAIN) -> int:
    """The frame side of scene ``index``: one of ``resolutions``, drawn from a stream of its own so that the rest
    of a scene does not depend on the list."""
    resolutions = list(resolutions)
    return resolutions[random.Random(f"{split.stream}-res:{seed}:{index}").randrange(len(resolutions))]


def camera_split(recipe) -> str:
    """The split whose camera azimuths hold the recipe's camera (its direction from the origin, seen from above)."""
    x, y = recipe["camera"]["location"][:2]
    theta = math.atan2(y, x)
    return next(s.name for s in SPLITS.values() if any(lo <= theta <= hi for lo, hi in s.azimuths))


def rgb(rng, sat=(0.0, 0.9), val=(0.1, 0.95)):
    return [round(c, 6) for c in colorsys.hsv_to_rgb(rng.random(), rng.uniform(*sat), rng.uniform(*val))]


def warm(rng):
    return [round(c, 6) for c in colorsys.hsv_to_rgb(rng.uniform(0.0, 0.17), rng.uniform(0.0, 0.5), 1.0)]


CLASHES = {frozenset(("shafts", "hdri"))}  # shafts need the sun of a sky; the HDRI-like world has none


def clash(a, b) -> bool:
    return (a.group == b.group == "lighting") or frozenset((a.name, b.name)) in CLASHES


def draw_effects(rng) -> list:
    """One to three distinct effects, drawn by weight; at most one lighting effect (each sets the world), none
    that :data:`CLASHES` with another."""
    count = rng.choices((1, 2, 3), weights=(3, 4, 3))[0]
    pool, chosen = list(EFFECTS), []
    while len(chosen) < count and pool:
        e = rng.choices(pool, weights=[p.weight for p in pool])[0]
        chosen.append(e.name)
        pool = [p for p in pool if p is not e and not clash(e, p)]
    return sorted(chosen, key=list(BY_NAME).index)


def forced_effects(rng, index: int) -> list:
    """Validation scene ``index``'s effects: one of group ``index`` and one of group ``index + PAIR_STEP`` (mod 9,
    each by weight, none clashing with the other), and one time in three a third from the whole catalogue."""
    chosen = []
    for group in (GROUPS[index % len(GROUPS)], GROUPS[(index + PAIR_STEP) % len(GROUPS)]):
        pool = [e for e in EFFECTS if e.group == group and not any(clash(e, BY_NAME[c]) for c in chosen)]
        chosen.append(rng.choices(pool, weights=[p.weight for p in pool])[0].name)
    if rng.random() < 1 / 3:
        pool = [e for e in EFFECTS if e.name not in chosen and not any(clash(e, BY_NAME[c]) for c in chosen)]
        chosen.append(rng.choices(pool, weights=[p.weight for p in pool])[0].name)
    return sorted(chosen, key=list(BY_NAME).index)


def texture(rng, kind=None, scale=None, split=TRAIN):
    kind = kind or rng.choice(split.textures)
    t = {"kind": kind, "c1": rgb(rng), "c2": rgb(rng), "scale": scale or rng.uniform(2.0, 25.0)}
    if kind == "brick":
        t["mortar"] = rgb(rng, val=(0.5, 0.9))
        if split is VALIDATION:  # other proportions than Blender's default 0.5 x 0.25 that training bricks keep
            t.update(brick_width=rng.uniform(0.2, 0.4), row_height=rng.uniform(0.1, 0.2))
    return t


def material(rng, effects, floor=False, split=TRAIN):
    """A Principled material: diffuse, plastic, metal, glass or coated, with the layers the effects ask for."""
    kind = rng.choices(("diffuse", "plastic", "metal", "glass", "coated"), weights=(3, 3, 2, 0 if floor else 1, 2))[0]
    m = {"kind": kind, "base": rgb(rng), "roughness": {
        "diffuse": rng.uniform(0.6, 1.0), "plastic": rng.uniform(0.05, 0.6), "metal": rng.uniform(0.0, 0.5),
        "glass": rng.uniform(0.0, 0.15), "coated": rng.uniform(0.2, 0.8)}[kind]}
    if kind == "metal":
        m.update(metallic=1.0, base=rgb(rng, sat=(0.0, 0.4), val=(0.6, 1.0)))
    if kind == "glass":
        m.update(transmission=1.0, ior=rng.uniform(1.3, 1.6), base=rgb(rng, sat=(0.0, 0.3), val=(0.85, 1.0)))
    if kind == "coated" or ("coat" in effects and kind != "glass" and rng.random() < 0.6):
        m.update(coat=rng.uniform(0.3, 1.0), coat_roughness=rng.uniform(0.0, 0.3), coat_tint=rgb(rng, sat=(0, 0.5),
                                                                                                 val=(0.7, 1.0)))
    if "sheen" in effects and kind in ("diffuse", "plastic") and rng.random() < 0.7:
        m.update(sheen=rng.uniform(0.5, 1.0), sheen_roughness=rng.uniform(0.2, 0.8), sheen_tint=rgb(rng, val=(0.7, 1)))
    if "subsurface" in effects and not floor and kind in ("diffuse", "plastic", "coated") and rng.random() < 0.7:
        m.update(subsurface=1.0, sss_radius=[rng.uniform(0.5, 1.0), rng.uniform(0.2, 0.6), rng.uniform(0.05, 0.3)],
                 sss_scale=rng.uniform(0.05, 0.4), base=rgb(rng, sat=(0.1, 0.6), val=(0.6, 0.95)))
    if kind != "glass" and rng.random() < (0.6 if floor else 0.35):
        m["texture"] = texture(rng, split=split)
    return m


LAYERS = {"subsurface": lambda rng: {"subsurface": 1.0, "sss_scale": rng.uniform(0.05, 0.4), "sss_radius": [
              rng.uniform(0.5, 1.0), rng.uniform(0.2, 0.6), rng.uniform(0.05, 0.3)]},
          "coat": lambda rng: {"coat": rng.uniform(0.5, 1.0), "coat_roughness": rng.uniform(0.0, 0.3),
                               "coat_tint": rgb(rng, sat=(0, 0.5), val=(0.7, 1.0))},
          "sheen": lambda rng: {"sheen": rng.uniform(0.5, 1.0), "sheen_roughness": rng.uniform(0.2, 0.8),
                                "sheen_tint": rgb(rng, val=(0.7, 1))}}


def ensure_layers(rng, objs, effects):
    """Each layer effect (subsurface, coat, sheen) on at least one object: materials draw them by chance."""
    for effect, layer in LAYERS.items():
        if effect not in effects or any(o["material"].get(effect, 0) > 0 for o in objs):
            continue
        plain = [o for o in objs if o["material"]["kind"] in ("diffuse", "plastic", "coated")]
        if not plain:  # glass and glowing objects keep what their own effects made them
            s = rng.uniform(0.2, 0.5)
            plain = [primitive(rng, {"kind": "diffuse", "base": rgb(rng), "roughness": rng.uniform(0.6, 1.0)},
                               (rng.uniform(-1.3, 1.3), rng.uniform(-1.0, 1.5), s), s)]
            objs.append(plain[0])
        rng.choice(plain)["material"].update(layer(rng))


def glass(rng, ior=None):
    return {"kind": "glass", "base": rgb(rng, sat=(0.0, 0.15), val=(0.9, 1.0)), "roughness": rng.uniform(0.0, 0.05),
            "transmission": 1.0, "ior": ior or rng.uniform(1.4, 1.6)}


def quad(location, rotation, size, mat, **extra):
    return {"shape": "quad", "location": list(location), "rotation": list(rotation), "size": list(size),
            "material": mat, **extra}


def room_walls(rng, effects, size, h, window, split=TRAIN):
    """Floor-less walls and ceiling of a room; with ``window``, the +x wall is closed around an opening and the
    room has a ceiling (light comes in through the window alone)."""
    walls = material(rng, effects, floor=True, split=split)
    out = [quad((0, size / 2, h / 2), (math.pi / 2, 0, 0), (size, h), walls),
           quad((-size / 2, 0, h / 2), (0, math.pi / 2, 0), (size, h), walls)]
    if window:
        w, wh, z0 = rng.uniform(0.6, 1.6), rng.uniform(0.6, 1.3), rng.uniform(0.4, 1.0)
        y0 = rng.uniform(-size / 2 + w / 2 + 0.2, size / 2 - w / 2 - 0.2)
        x, rot = size / 2, (0, -math.pi / 2, 0)
        y_lo, y_hi = (-size / 2 + y0 - w / 2) / 2, (size / 2 + y0 + w / 2) / 2  # centres of the side pieces
        out += [quad((x, y_lo, h / 2), rot, (h, y0 - w / 2 + size / 2), walls),
                quad((x, y_hi, h / 2), rot, (h, size / 2 - y0 - w / 2), walls),
                quad((x, y0, z0 / 2), rot, (z0, w), walls),
                quad((x, y0, (z0 + wh + h) / 2), rot, (h - z0 - wh, w), walls),
                quad((0, -size / 2, h / 2), (-math.pi / 2, 0, 0), (size, h), walls),
                quad((0, 0, h), (math.pi, 0, 0), (size, size), walls)]
        return out, {"centre": [x, y0, z0 + wh / 2], "width": w, "height": wh}
    if rng.random() < 0.5:
        out.append(quad((size / 2, 0, h / 2), (0, -math.pi / 2, 0), (size, h), walls))
    if rng.random() < 0.6:
        out.append(quad((0, 0, h), (math.pi, 0, 0), (size, size), walls))
    return out, None


def primitive(rng, mat, location, size):
    kind = rng.choice(PRIMITIVES)
    o = {"shape": kind, "location": list(location), "size": size, "material": mat,
         "rotation": ([rng.uniform(0, math.pi) for _ in range(3)] if kind != "uv_sphere" else [0, 0, 0])}
    if kind == "torus":
        o["minor"] = size * rng.uniform(0.15, 0.4)
    if kind == "ico_sphere":
        o["subdivisions"] = rng.choice((1, 4))
    if kind in ("cylinder", "cone"):
        o["depth"] = size * rng.uniform(1.0, 3.0)
    o["smooth"] = kind in ("uv_sphere", "cylinder", "torus", "monkey", "cone") or (
        kind == "ico_sphere" and rng.random() < 0.5)
    return o


def objects(rng, effects, split=TRAIN):
    out = []
    for _ in range(rng.randint(3, 7)):
        s = rng.uniform(0.15, 0.6)
        loc = (rng.uniform(-1.3, 1.3), rng.uniform(-1.0, 1.5), s * rng.uniform(0.6, 2.5))
        out.append(primitive(rng, material(rng, effects, split=split), loc, s))
    if "glass_caustics" in effects or "glass_medium" in effects:
        for o in rng.sample(out, rng.randint(1, 2)):
            o["material"] = glass(rng)
            o["location"][2] = o["size"] * 1.05  # on the floor, so its caustic lands there
            if "glass_medium" in effects:
                o["material"]["volume"] = {"density": rng.uniform(0.5, 8.0), "colour": rgb(rng, sat=(0.2, 0.9),
                                                                                           val=(0.5, 1.0)),
                                           "absorption": rgb(rng, sat=(0.2, 0.9), val=(0.3, 1.0))}
    if "emissive_mesh" in effects:
        opaque = [o for o in out if o["material"]["kind"] != "glass"]  # glass keeps its caustics
        for o in rng.sample(opaque, min(len(opaque), rng.randint(1, 2))):
            o["material"] = {"kind": "emission", "emission": warm(rng) if rng.random() < 0.5 else rgb(rng, (0.5, 1),
                                                                                                       (1, 1)),
                             "strength": rng.uniform(2.0, 30.0)}
    if "motion_blur" in effects:
        for o in rng.sample(out, rng.randint(1, min(3, len(out)))):
            o["motion"] = [rng.uniform(-0.4, 0.4), rng.uniform(-0.4, 0.4), rng.uniform(-0.1, 0.1)]
            o["spin"] = rng.uniform(-0.8, 0.8)
    ensure_layers(rng, out, effects)
    if "hair" in effects:
        o = rng.choice([o for o in out if o["material"]["kind"] not in ("glass", "emission")] or out)
        o["hair"] = {"count": rng.randint(300, 1500), "length": rng.uniform(0.05, 0.3) * (1 + o["size"]),
                     "colour": rgb(rng, sat=(0.2, 0.8), val=(0.1, 0.8)), "roughness": rng.uniform(0.2, 0.6),
                     "seed": rng.randrange(1000)}
    return out


def lights(rng, kind, window):
    out = []
    for _ in range(rng.randint(1, 3)):
        pick = rng.choices(("area", "point", "strip", "spot"), weights=(4, 3, 2, 1))[0]
        theta, r = rng.uniform(0, 2 * math.pi), rng.uniform(1.5, 3.5)
        li = {"type": pick, "location": [r * math.cos(theta), r * math.sin(theta), rng.uniform(1.5, 3.2)],
              "target": [0.0, 0.0, 0.5], "rgb": warm(rng)}
        li.update({"strip": lambda: {"size": [rng.uniform(0.05, 0.3), rng.uniform(0.5, 2.0)],
                                     "energy": rng.uniform(5, 60)},
                   "area": lambda: {"size": rng.uniform(0.2, 1.5), "energy": rng.uniform(50, 400)},
                   "point": lambda: {"size": rng.choice((rng.uniform(0.01, 0.05), rng.uniform(0.1, 0.5))),
                                     "energy": rng.uniform(30, 300)},
                   "spot": lambda: {"energy": rng.uniform(200, 1000), "spot_size": rng.uniform(0.4, 1.2),
                                    "size": rng.uniform(0.02, 0.3)}}[pick]())
        out.append(li)
    if window:  # a room lit through its window keeps a dim lamp at most
        out = [dict(li, energy=li["energy"] * 0.1) for li in out[:1]]
    return out


def world(rng, kind, effects):
    if "sun_sky" in effects or "window" in effects or "shafts" in effects or (kind == "ground" and "hdri" not in
                                                                             effects):
        return {"type": "sky", "sky": rng.choice(("SINGLE_SCATTERING", "MULTIPLE_SCATTERING")),
                "elevation": rng.uniform(5, 60), "rotation": rng.uniform(0, 2 * math.pi),
                "strength": rng.uniform(0.2, 1.0)}
    if "hdri" in effects:
        return {"type": "hdri", "low": rgb(rng, sat=(0, 0.4), val=(0.05, 0.4)), "high": rgb(rng, sat=(0, 0.3),
                                                                                             val=(0.8, 1.0)),
                "scale": rng.uniform(1.0, 6.0), "spot": rng.uniform(20.0, 200.0), "spot_size": rng.uniform(0.02, 0.1),
                "spot_direction": [rng.uniform(0, 2 * math.pi), rng.uniform(0.2, 1.2)], "strength": rng.uniform(0.3, 2)}
    return {"type": "flat", "rgb": rgb(rng, sat=(0, 0.3), val=(0.0, 0.1)), "strength": rng.uniform(0.0, 1.0)}


def sun_for(rng, world_, window, effects):
    """A sun lamp along the sky's sun, or a spot outside the window aimed through it (light shafts)."""
    if world_["type"] != "sky":
        return []
    el, rot = math.radians(world_["elevation"]), world_["rotation"]
    if window:  # the sun must come in through the window: it shines along -x, down at the sky's elevation
        el, rot = max(el, math.radians(15)), rng.uniform(-0.5, 0.5)
        if "shafts" in effects and "sun_sky" not in effects and rng.random() < 0.4:
            c = window["centre"]
            loc = [c[0] + 3.0, c[1] + rng.uniform(-0.5, 0.5), c[2] + rng.uniform(0.5, 2.0)]
            return [{"type": "spot", "location": loc, "target": [0.0, c[1] * 0.5, 0.3], "rgb": warm(rng),
                     "energy": rng.uniform(2000, 8000), "spot_size": rng.uniform(0.5, 1.0), "size": 0.05}]
    direction = [-math.cos(el) * math.cos(rot), -math.cos(el) * math.sin(rot), -math.sin(el)]
    return [{"type": "sun", "direction": direction, "rgb": warm(rng), "energy": rng.uniform(2.0, 6.0),
             "angle": math.radians(rng.uniform(0.5, 3.0))}]


def media(rng, effects, extent):
    out = []
    if "fog" in effects or "shafts" in effects:
        out.append({"location": [0, 0, extent[2] / 2], "size": list(extent), "density": rng.uniform(0.02, 0.25),
                    "colour": rgb(rng, sat=(0, 0.2), val=(0.8, 1.0)), "anisotropy": rng.uniform(0.0, 0.7)})
    if "smoke" in effects:
        s = rng.uniform(0.8, 2.0)
        out.append({"location": [rng.uniform(-0.8, 0.8), rng.uniform(-0.5, 1.0), s / 2], "size": [s, s, s],
                    "density": rng.uniform(1.0, 8.0), "colour": rgb(rng, sat=(0, 0.4), val=(0.5, 1.0)),
                    "anisotropy": rng.uniform(-0.2, 0.5),
                    "noise": {"scale": rng.uniform(1.5, 6.0), "detail": rng.uniform(1.0, 6.0),
                              "threshold": rng.uniform(0.4, 0.6)}})
    return out


def camera(rng, effects, objs, split=TRAIN, room=None):
    """The camera: at an azimuth of the split's (:func:`camera_split`); a validation camera in a room of side
    ``room`` stands inside it, with a wider lens (a training one may stand outside a closed room)."""
    if split is TRAIN:
        theta, dist = rng.uniform(-2.2, -0.9), rng.uniform(3.0, 5.0)
    else:
        theta = rng.uniform(*rng.choice(split.azimuths))
        dist = rng.uniform(3.0, 5.0)
        if room:
            dist = min(dist, (room / 2 - 0.25) / max(abs(math.cos(theta)), abs(math.sin(theta))))
    low = "fine_tiles" in effects
    loc = [dist * math.cos(theta), dist * math.sin(theta), rng.uniform(0.15, 0.4) if low else rng.uniform(0.8, 2.4)]
    cam = {"location": loc, "target": [rng.uniform(-0.4, 0.4), rng.uniform(-0.2, 0.6), rng.uniform(0.2, 0.8)],
           "lens": rng.uniform(16, 26) if room and split is not TRAIN else rng.uniform(24, 50)}
    if low:
        cam["target"][2] = rng.uniform(0.0, 0.3)
    if "dof" in effects or rng.random() < 0.1:
        focus = rng.choice(objs)["location"]
        cam["dof"] = {"fstop": rng.uniform(0.5, 2.0) if "dof" in effects else rng.uniform(2.8, 5.6),
                      "distance": math.dist(loc, focus)}
    if "motion_blur" in effects:
        cam["shutter"] = rng.uniform(0.5, 1.0)
    return cam


def extras(rng, effects, kind, split=TRAIN):
    """The surfaces effects add: a far brick wall, a tiled floor, text, a water surface."""
    out = []
    if "brick_far" in effects:
        m = {"kind": "diffuse", "base": rgb(rng), "roughness": rng.uniform(0.7, 1.0),
             "texture": texture(rng, "brick", rng.uniform(20.0, 60.0), split)}
        d = 2.9 if kind == "room" else rng.uniform(4.0, 10.0)
        out.append(quad((0, d, 3), (math.pi / 2, 0, 0), (12, 6), m))
    if "fine_tiles" in effects:
        m = {"kind": "plastic", "base": rgb(rng), "roughness": rng.uniform(0.1, 0.5),
             "texture": texture(rng, rng.choice(("checker", "brick")), rng.uniform(40.0, 150.0), split)}
        out.append(quad((0, 0, 0.002), (0, 0, 0), (8, 8), m))
    if "water_caustics" in effects:
        out.append(quad((rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(0.08, 0.25)), (0, 0, 0),
                        (rng.uniform(2.0, 4.0), rng.uniform(2.0, 4.0)), glass(rng, ior=1.33),
                        waves={"scale": rng.uniform(2.0, 8.0), "height": rng.uniform(0.01, 0.04)}))
    return out


def texts(rng, effects, split=TRAIN):
    if "text" not in effects:
        return []
    out = []
    for _ in range(rng.randint(1, 3)):
        on_floor = rng.random() < 0.5
        out.append({"body": rng.choice(split.texts), "size": rng.uniform(0.08, 0.3),
                    "location": [rng.uniform(-1.5, 1.0), rng.uniform(-1.0, 1.5), 0.003 if on_floor else
                                 rng.uniform(0.5, 1.8)],
                    "rotation": [0, 0, rng.uniform(0, 2 * math.pi)] if on_floor else [math.pi / 2, 0, 0],
                    "material": {"kind": "diffuse", "base": rgb(rng), "roughness": 0.8} if rng.random() < 0.7 else
                    {"kind": "emission", "emission": rgb(rng, (0.5, 1), (1, 1)), "strength": rng.uniform(2, 15)}})
    return out


def draw(seed: int, index: int, resolutions=(128,), frames=(), split: str = "train") -> dict:
    """The recipe of scene ``index`` under ``seed`` in ``split`` (:data:`SPLITS`): the same arguments draw the
    same dict. ``frames``, the sample counts of its frames (the reference's last), is recorded, not drawn: the
    manifest's frames planned. A validation recipe records its split; a training one is as it was before."""
    sp = SPLITS[split]
    rng = scene_rng(seed, index, sp)
    effects = draw_effects(rng) if sp is TRAIN else forced_effects(rng, index)
    window = "window" in effects or "shafts" in effects
    kind = "room" if window else rng.choice(("studio", "ground")) if "sun_sky" in effects else rng.choice(KINDS)
    surfaces, opening = [], None
    if kind == "room":
        size, h = rng.uniform(3.0, 6.0), rng.uniform(2.4, 3.2)
        walls, opening = room_walls(rng, effects, size, h, window, sp)
        surfaces = [quad((0, 0, 0), (0, 0, 0), (size, size), material(rng, effects, True, sp))] + walls
        extent = [size, size, h]
    elif kind == "studio":
        surfaces = [quad((0, 0, 0), (0, 0, 0), (12, 12), material(rng, effects, True, sp)),
                    quad((0, 3, 3), (math.pi / 2, 0, 0), (12, 6), material(rng, effects, True, sp))]
        extent = [6, 6, 3]
    else:
        surfaces = [quad((0, 0, 0), (0, 0, 0), (40, 40), material(rng, effects, True, sp))]
        extent = [8, 8, 3]
    surfaces += extras(rng, effects, kind, sp)
    objs = objects(rng, effects, sp)
    world_ = world(rng, kind, effects)
    lamps = lights(rng, kind, window)
    if "glass_caustics" in effects or "water_caustics" in effects:  # a small hard light makes sharp caustics
        lamps.append({"type": "point", "location": [rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(2.0, 3.0)],
                      "target": [0, 0, 0], "rgb": warm(rng), "energy": rng.uniform(200, 800), "size": 0.02})
    lamps += sun_for(rng, world_, opening, effects)
    recipe = {"version": RECIPE_VERSION, "seed": seed, "index": index, "name": f"{sp.prefix}{kind}-{index:03d}",
              "kind": kind, "res": scene_res(seed, index, resolutions, sp), "effects": effects,
              "groups": sorted({BY_NAME[e].group for e in effects}, key=GROUPS.index),
              "exposure": random.Random(f"{sp.stream}-exposure:{seed}:{index}").uniform(0.1, 0.5),
              "frames": list(frames), "surfaces": surfaces, "objects": objs,
              "texts": texts(rng, effects, sp), "lights": lamps, "world": world_, "window": opening,
              "media": media(rng, effects, extent),
              "camera": camera(rng, effects, objs, sp, extent[0] if kind == "room" else None)}
    return recipe if sp is TRAIN else {"split": sp.name, **recipe}


MANIFEST = "manifest.json"
RENDER_LOG = "render_log.json"


def frame_name(scene: str, spp: int) -> str:
    return f"{scene}-{spp:05d}spp.exr"


def denoised_name(scene: str, spp: int) -> str:
    """Blender's own denoised frame of ``frame_name(scene, spp)`` (same seed), as a validation scene has."""
    return f"{scene}-{spp:05d}spp-blender-oidn.exr"


def pair_names(scene: str, spp: int) -> tuple:
    """The two halves of ``frame_name(scene, spp)``: two renders of the frame with different seeds, each of
    ``spp / 2`` samples (its own spp, in its name as in its header), whose mean has ``spp`` samples, as
    ``kpcn denoise A --pair B`` takes them: ``<scene>-<spp/2, 5 digits>spp-pair-a.exr`` and ``...-pair-b.exr``.
    Every renderer's pairs are named here (kpcn's tracer, Cycles, the docs' Mitsuba recipe). ValueError for an
    odd ``spp`` (no two equal halves)."""
    if spp < 2 or spp % 2:
        raise ValueError(f"{spp} spp has no two equal halves (an even count of samples, 2 or more)")
    return tuple(f"{scene}-{spp // 2:05d}spp-pair-{half}.exr" for half in "ab")


def half_seeds(seed: int) -> tuple:
    """Cycles' seeds of the two halves of a frame rendered with ``seed``: 2**28 and 2**29 above it (mod 2**31),
    so each is other than the other's and than the frame's own."""
    return tuple((seed + k * 2**28) % 2**31 for k in (1, 2))


_HALF = re.compile(r"^(?P<scene>.+)-(?P<spp>\d{5,})spp-pair-(?P<half>[ab])\.exr$")


def pair_half(name: str):
    """(scene, spp of the whole frame, "a" or "b") of a file name :func:`pair_names` gives; None for any other."""
    m = _HALF.match(name)
    return None if m is None else (m["scene"], 2 * int(m["spp"]), m["half"])


def planned_files(recipe) -> list:
    """The frames a recipe plans: one per ``frames`` entry, and for a validation scene Blender's denoised frame
    of each input (every entry but the last, the reference) and the input's two halves (:func:`pair_names`)."""
    spps = recipe.get("frames", [])
    names = [frame_name(recipe["name"], spp) for spp in spps]
    if recipe.get("split") == VALIDATION.name:
        names += [denoised_name(recipe["name"], spp) for spp in spps[:-1]]
        names += [n for spp in spps[:-1] for n in pair_names(recipe["name"], spp)]
    return names


def sha256(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def checksums(out: str, recipes, fresh=()) -> dict:
    """{file: sha256} of a validation folder's recipes and frames there: a file's checksum is the one recorded
    in the manifest when it was first counted (so a file changed since shows in :func:`verify`), unless it is
    in ``fresh`` (written again just now by the render, which records it anew)."""
    try:
        with open(os.path.join(out, MANIFEST)) as f:
            old = json.load(f).get("sha256", {})
    except (OSError, ValueError, AttributeError):
        old = {}
    names = [f"{r['name']}.json" for r in recipes] + [n for r in recipes for n in planned_files(r)]
    return {n: old[n] if n in old and n not in fresh else sha256(os.path.join(out, n))
            for n in sorted(names) if os.path.exists(os.path.join(out, n))}


def verify(out: str):
    """None if folder ``out`` holds every file its manifest's checksums name, each with that checksum, and every
    frame its recipes plan; else one line naming the first file that is missing or differs."""
    path = os.path.join(out, MANIFEST)
    try:
        with open(path) as f:
            recorded = json.load(f)["sha256"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        return f"{path}: no manifest with checksums ({type(e).__name__}: {e})"
    for name, digest in sorted(recorded.items()):
        there = os.path.join(out, name)
        if not os.path.isfile(there):
            return f"{there}: missing (the manifest records sha256 {digest[:16]}...)"
        found = sha256(there)
        if found != digest:
            return f"{there}: sha256 {found[:16]}... differs from the manifest's {digest[:16]}..."
    for r in read_recipes(out):
        for name in planned_files(r):
            if name not in recorded:
                return f"{os.path.join(out, name)}: planned by {r['name']}.json but not rendered (run it again)"
    return None


def read_recipes(out: str) -> list:
    """Every recipe of ``out`` (``<scene>.json`` with an ``effects`` list), by scene index."""
    recipes = []
    for name in sorted(os.listdir(out)):
        if name.endswith(".json") and not name.startswith(".") and name not in (MANIFEST, RENDER_LOG):
            with open(os.path.join(out, name)) as f:
                r = json.load(f)
            if isinstance(r, dict) and "effects" in r:
                recipes.append(r)
    return sorted(recipes, key=lambda r: (r["seed"], r["index"]))


def count_manifest(out: str) -> dict:
    """The manifest of folder ``out``."""
    recipes = read_recipes(out)
    log = {}
    if os.path.exists(os.path.join(out, RENDER_LOG)):
        with open(os.path.join(out, RENDER_LOG)) as f:
            log = json.load(f)
    wall, cpu = log.get("renders", {}), log.get("cpu", {})
    threads = log.get("threads", 1)
    effects = {e.name: 0 for e in EFFECTS}
    groups = {g: 0 for g in GROUPS}
    planned = done = complete = 0
    kinds, sizes = {}, {}
    for r in recipes:
        for e in r["effects"]:
            effects[e] = effects.get(e, 0) + 1
        for g in {BY_NAME[e].group for e in r["effects"] if e in BY_NAME}:
            groups[g] += 1
        kinds[r["kind"]] = kinds.get(r["kind"], 0) + 1
        sizes[str(r["res"])] = sizes.get(str(r["res"]), 0) + 1
        frames = planned_files(r)
        there = sum(os.path.exists(os.path.join(out, f)) for f in frames)
        planned, done, complete = planned + len(frames), done + there, complete + (there == len(frames) > 0)
    cpu_s = sum(cpu.get(name, seconds * threads) for name, seconds in wall.items())
    return {"scenes": len(recipes), "scenes_complete": complete, "frames_done": done, "frames_planned": planned,
            "effects": effects, "groups": groups, "kinds": kinds, "resolutions": sizes,
            "cpu_hours": round(cpu_s / 3600, 4), "wall_hours": round(sum(wall.values()) / 3600, 4),
            "cpu_measure": "process CPU time of Blender's Python per frame (render threads, build, probe); frames "
                           "logged without it: wall seconds x threads"}


def write_manifest(out: str, fresh=()) -> dict:
    """Count ``out`` and write its manifest (through a temporary name); returns it. A folder of validation scenes
    also records the checksum of each of their files (:func:`checksums`; ``fresh``, the files just written)."""
    m = count_manifest(out)
    valid = [r for r in read_recipes(out) if r.get("split") == VALIDATION.name]
    if valid:
        m["sha256"] = checksums(out, valid, fresh)
    tmp = os.path.join(out, "." + MANIFEST)
    with open(tmp, "w") as f:
        json.dump(m, f, indent=1)
    os.replace(tmp, os.path.join(out, MANIFEST))
    return m


def summary(m: dict) -> str:
    """The manifest in a few lines, as the command prints it."""
    lines = [f"{m['scenes']} scenes ({m['scenes_complete']} complete), frames {m['frames_done']} of "
             f"{m['frames_planned']}, {m['cpu_hours']:.3f} CPU hours ({m['wall_hours']:.3f} h wall)",
             "groups: " + ", ".join(f"{g} {n}" for g, n in m["groups"].items()),
             "effects: " + ", ".join(f"{e} {n}" for e, n in m["effects"].items()),
             "resolutions: " + ", ".join(f"{r}px {n}" for r, n in sorted(m["resolutions"].items()))]
    return "\n".join(lines)
