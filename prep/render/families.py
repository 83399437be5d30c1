"""The built-in scene families: functions ``(rng or seed) -> Scene`` with seeded random variations of
geometry, materials, colours, light placement and camera; see :data:`FAMILIES` and :func:`make_scene`."""

from __future__ import annotations

import colorsys
import math
import zlib

import numpy as np

from prep.bounds import is_integer
from prep.errors import OptionError
from prep.render.scene import (
    Camera,
    EnvironmentMap,
    Material,
    Medium,
    Mesh,
    Quad,
    Scene,
    Sky,
    Sphere,
    Vec3,
    _luminance,
    emitter,
    glass,
    glossy,
    lambert,
    mirror,
    plastic,
)
from prep.render.shapes import icosphere, torus

# ---------------------------------------------------------------------------------------------

def _rng(rng_or_seed) -> np.random.Generator:
    if isinstance(rng_or_seed, np.random.Generator):
        return rng_or_seed
    return np.random.default_rng(rng_or_seed)


def _u(rng, lo, hi) -> float:
    return float(rng.uniform(lo, hi))


def _hsv(h, s, v) -> Vec3:
    r, g, b = colorsys.hsv_to_rgb(h % 1.0, s, v)
    return (float(r), float(g), float(b))


def _colour(rng, sat=(0.4, 0.85), val=(0.45, 0.8)) -> Vec3:
    return _hsv(_u(rng, 0, 1), _u(rng, *sat), _u(rng, *val))


def _light_colour(rng) -> Vec3:
    # warm to cool white, normalised to luminance 1 so intensity is set separately
    tint = _hsv(_u(rng, 0.05, 0.6), _u(rng, 0.0, 0.25), 1.0)
    lum = _luminance(tint)
    return tuple(c / lum for c in tint)


def _object_material(rng, kind: str | None = None) -> Material:
    """A random lambert / glossy metal / plastic material for an object."""
    if kind is None:
        kind = str(rng.choice(["lambert", "glossy", "plastic"], p=[0.35, 0.3, 0.35]))
    if kind == "lambert":
        if rng.uniform() < 0.3:
            return lambert(_colour(rng), texture="uv", albedo2=_colour(rng, val=(0.7, 0.9)),
                           checker_scale=float(rng.integers(4, 12)))
        return lambert(_colour(rng))
    if kind == "glossy":
        # metals: silver, gold, copper-ish and coloured tints; F0 kept high as for conductors
        base = _hsv(_u(rng, 0.0, 1.0), _u(rng, 0.0, 0.6), _u(rng, 0.75, 0.95))
        return glossy(base, roughness=_u(rng, 0.08, 0.35))
    if kind == "plastic":
        f0 = _u(rng, 0.04, 0.08)
        return plastic(_colour(rng), (f0, f0, f0), roughness=_u(rng, 0.05, 0.3))
    raise ValueError(f"unknown object material kind {kind!r}")


def _place_on_floor(rng, n, radii_range, x_range, z_range, existing=(), gap=0.05, tries=200):
    """Non-overlapping discs (x, z, r) on the floor; fewer than n if it runs out of room."""
    placed = list(existing)
    out = []
    for _ in range(n):
        for _ in range(tries):
            r = _u(rng, *radii_range)
            x = _u(rng, x_range[0] + r, x_range[1] - r)
            z = _u(rng, z_range[0] + r, z_range[1] - r)
            if all((x - px) ** 2 + (z - pz) ** 2 > (r + pr + gap) ** 2 for px, pz, pr in placed):
                placed.append((x, z, r))
                out.append((x, z, r))
                break
    return out


def _ceiling_light(centre, sx, sz, material: str = "light") -> Quad:
    """Horizontal sx*sz rectangle of ``material`` centred at ``centre``, emitting downwards (-y)."""
    cx, cy, cz = centre
    # cross((sx,0,0), (0,0,sz)) = (0, -sx*sz, 0): normal points down
    return Quad((cx - sx / 2, cy, cz - sz / 2), (sx, 0.0, 0.0), (0.0, 0.0, sz), material)


def _box_quads(x0, x1, y0, y1, z0, z1, material) -> list[Quad]:
    """The five visible faces of an axis-aligned box standing on a floor (no bottom face)."""
    dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
    return [
        Quad((x0, y1, z0), (0, 0, dz), (dx, 0, 0), material),  # top
        Quad((x0, y0, z1), (dx, 0, 0), (0, dy, 0), material),  # front (+z)
        Quad((x0, y0, z0), (0, dy, 0), (dx, 0, 0), material),  # back (-z)
        Quad((x0, y0, z0), (0, 0, dz), (0, dy, 0), material),  # left (-x)
        Quad((x1, y0, z0), (0, dy, 0), (0, 0, dz), material),  # right (+x)
    ]


def cornell(rng_or_seed=None, name: str = "cornell") -> Scene:
    """A 2x2x2 box room open towards the camera: coloured side walls, checker floor, a ceiling light,
    2-3 spheres of mixed materials (at least one glossy or plastic)."""
    rng = _rng(rng_or_seed)
    hue = _u(rng, 0, 1)
    left = _hsv(hue, _u(rng, 0.6, 0.85), _u(rng, 0.55, 0.75))
    right = _hsv(hue + _u(rng, 0.25, 0.5), _u(rng, 0.6, 0.85), _u(rng, 0.55, 0.75))
    white = _u(rng, 0.65, 0.8)
    floor_a = _colour(rng, sat=(0.0, 0.3), val=(0.6, 0.8))
    floor_b = _colour(rng, sat=(0.0, 0.5), val=(0.15, 0.35))
    mats = {
        "white": lambert((white, white, white)),
        "left": lambert(left),
        "right": lambert(right),
        "floor": lambert(floor_a, texture=str(rng.choice(["world", "uv"])), albedo2=floor_b,
                         checker_scale=float(rng.integers(3, 8))),
    }
    quads = [
        Quad((-1, 0, -1), (0, 0, 2), (2, 0, 0), "floor"),
        Quad((-1, 2, -1), (2, 0, 0), (0, 0, 2), "white"),  # ceiling
        Quad((-1, 0, -1), (2, 0, 0), (0, 2, 0), "white"),  # back
        Quad((-1, 0, -1), (0, 2, 0), (0, 0, 2), "left"),
        Quad((1, 0, -1), (0, 0, 2), (0, 2, 0), "right"),
    ]
    sx, sz = _u(rng, 0.3, 0.7), _u(rng, 0.3, 0.7)
    power = _u(rng, 3.0, 6.0)
    mats["light"] = emitter(tuple(c * power / (sx * sz) for c in _light_colour(rng)))
    # 1e-3 below the ceiling so the two never fight for the same depth
    quads.append(_ceiling_light((_u(rng, -0.3, 0.3), 2 - 1e-3, _u(rng, -0.3, 0.3)), sx, sz))

    n = int(rng.integers(2, 4))
    kinds = [str(rng.choice(["glossy", "plastic"]))] + [None] * (n - 1)
    spheres = []
    for i, (x, z, r) in enumerate(_place_on_floor(rng, n, (0.22, 0.45), (-0.95, 0.95), (-0.95, 0.7))):
        key = f"sphere{i}"
        mats[key] = _object_material(rng, kinds[i])
        spheres.append(Sphere((x, r, z), r, key))
    cam = Camera(position=(_u(rng, -0.15, 0.15), _u(rng, 0.9, 1.1), _u(rng, 3.2, 3.6)),
                 look_at=(0.0, _u(rng, 0.9, 1.0), 0.0), fov=_u(rng, 37, 42))
    return Scene(name=name, family="cornell", camera=cam, materials=mats, spheres=spheres, quads=quads,
                 environment=(0.0, 0.0, 0.0))


def spheres(rng_or_seed=None, name: str = "spheres") -> Scene:
    """An open checker ground with 6-12 spheres of mixed materials, 1-2 area lights overhead and a dim
    gradient environment (bluer and brighter towards the zenith)."""
    rng = _rng(rng_or_seed)
    mats = {
        "ground": lambert(_colour(rng, sat=(0.0, 0.35), val=(0.55, 0.8)), texture="world",
                          albedo2=_colour(rng, sat=(0.0, 0.6), val=(0.1, 0.3)),
                          checker_scale=_u(rng, 0.8, 2.5)),
    }
    quads = [Quad((-30, 0, -30), (0, 0, 60), (60, 0, 0), "ground")]
    n = int(rng.integers(6, 13))
    spheres_ = []
    for i, (x, z, r) in enumerate(_place_on_floor(rng, n, (0.25, 0.75), (-3.2, 3.2), (-3.2, 2.2))):
        key = f"sphere{i}"
        mats[key] = _object_material(rng)
        spheres_.append(Sphere((x, r, z), r, key))
    n_lights = int(rng.integers(1, 3))
    for i in range(n_lights):
        sx, sz = _u(rng, 0.8, 2.0), _u(rng, 0.8, 2.0)
        power = _u(rng, 50.0, 110.0) / n_lights ** 0.5
        key = "light" if i == 0 else f"light{i}"
        mats[key] = emitter(tuple(c * power / (sx * sz) for c in _light_colour(rng)))
        quads.append(_ceiling_light((_u(rng, -3, 3), _u(rng, 3.0, 5.0), _u(rng, -3, 2)), sx, sz, key))
    angle = _u(rng, -0.5, 0.5)
    dist = _u(rng, 6.5, 8.0)
    cam = Camera(position=(dist * math.sin(angle), _u(rng, 1.5, 3.0), dist * math.cos(angle)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.3, 0.6), _u(rng, -0.5, 0.0)), fov=_u(rng, 38, 46))
    env = _u(rng, 0.03, 0.1)
    return Scene(name=name, family="spheres", camera=cam, materials=mats, spheres=spheres_, quads=quads,
                 environment=(env, env * 0.95, env * 0.9), environment_zenith=(env * 0.5, env * 0.8, env * 2.0))


def boxes(rng_or_seed=None, name: str = "boxes") -> Scene:
    """Axis-aligned boxes on a glossy or plastic floor against a back wall, lit by one small bright
    light (hard-ish shadows) and a dim environment."""
    rng = _rng(rng_or_seed)
    if rng.uniform() < 0.5:
        floor = glossy(_hsv(_u(rng, 0, 1), _u(rng, 0.0, 0.3), _u(rng, 0.6, 0.85)),
                       roughness=_u(rng, 0.12, 0.3))
    else:
        f0 = _u(rng, 0.04, 0.08)
        floor = plastic(_colour(rng, val=(0.3, 0.6)), (f0, f0, f0), roughness=_u(rng, 0.06, 0.25),
                        texture="world", albedo2=_colour(rng, val=(0.15, 0.35)),
                        checker_scale=_u(rng, 1.0, 2.5))
    wall = _u(rng, 0.55, 0.75)
    mats = {
        "floor": floor,
        "wall": lambert((wall, wall, wall), texture="world", albedo2=(wall * 0.75, wall * 0.75, wall * 0.75),
                        checker_scale=_u(rng, 1.0, 2.0)),
    }
    quads = [
        Quad((-6, 0, -6), (0, 0, 12), (12, 0, 0), "floor"),
        Quad((-6, 0, -2.5), (12, 0, 0), (0, 6, 0), "wall"),
    ]
    if rng.uniform() < 0.5:
        side = -1 if rng.uniform() < 0.5 else 1
        quads.append(Quad((side * 3.0, 0, -2.5), (0, 0, 6), (0, 6, 0), "wall"))
    n = int(rng.integers(3, 7))
    kinds = ["glossy"] + [None] * (n - 1)
    for i, (x, z, r) in enumerate(_place_on_floor(rng, n, (0.3, 0.7), (-2.0, 2.0), (-2.2, 1.0))):
        key = f"box{i}"
        mats[key] = _object_material(rng, kinds[i])
        hx, hz = r * _u(rng, 0.6, 0.7), r * _u(rng, 0.6, 0.7)  # half sides that fit in the placed disc
        height = _u(rng, 0.3, 1.4)
        quads.extend(_box_quads(x - hx, x + hx, 0.0, height, z - hz, z + hz, key))
    s = _u(rng, 0.15, 0.35)
    power = _u(rng, 20.0, 40.0)
    mats["light"] = emitter(tuple(c * power / (s * s) for c in _light_colour(rng)))
    quads.append(_ceiling_light((_u(rng, -1.5, 1.5), _u(rng, 2.5, 3.5), _u(rng, -1.0, 1.0)), s, s))
    cam = Camera(position=(_u(rng, -1.0, 1.0), _u(rng, 1.5, 2.5), _u(rng, 4.5, 5.5)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.4, 0.7), 0.0), fov=_u(rng, 38, 46))
    env = _u(rng, 0.02, 0.06)
    return Scene(name=name, family="boxes", camera=cam, materials=mats, quads=quads,
                 environment=(env, env, env * 1.1))


def _closed_box(x0, x1, y0, y1, z0, z1, material) -> list[Quad]:
    """All six faces of an axis-aligned box, normals outwards (what glass needs)."""
    return _box_quads(x0, x1, y0, y1, z0, z1, material) + [
        Quad((x0, y0, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), material)]  # bottom, normal -y


def _room(w, h, d, wall="wall") -> list[Quad]:
    """Floor, ceiling, back and side walls of a w x h x d room centred on x = 0, z in [-d/2, d/2],
    open towards +z (the camera's side)."""
    x0, x1, z0 = -w / 2, w / 2, -d / 2
    return [
        Quad((x0, 0, z0), (0, 0, d), (w, 0, 0), "floor"),
        Quad((x0, h, z0), (w, 0, 0), (0, 0, d), wall),  # ceiling
        Quad((x0, 0, z0), (w, 0, 0), (0, h, 0), wall),  # back
        Quad((x0, 0, z0), (0, h, 0), (0, 0, d), wall),  # left
        Quad((x1, 0, z0), (0, 0, d), (0, h, 0), wall),  # right
    ]


def indirect(rng_or_seed=None, name: str = "indirect") -> Scene:
    """A closed-off room lit only indirectly: the light faces the ceiling from above a tall cabinet,
    so every visible surface is lit by interreflection; mixed objects on the floor."""
    rng = _rng(rng_or_seed)
    wall = _u(rng, 0.6, 0.8)
    mats = {
        "wall": lambert(_colour(rng, sat=(0.0, 0.25), val=(wall, wall + 0.1))),
        "floor": lambert(_colour(rng, sat=(0.2, 0.6), val=(0.35, 0.6)), texture="world",
                         albedo2=_colour(rng, sat=(0.2, 0.6), val=(0.15, 0.3)), checker_scale=_u(rng, 1.5, 3.0)),
        "cabinet": _object_material(rng, str(rng.choice(["lambert", "plastic"]))),
    }
    w, h, d = 4.0, 2.6, 4.0
    quads = _room(w, h, d)
    side = -1 if rng.uniform() < 0.5 else 1
    cx = side * _u(rng, 0.9, 1.4)
    top = _u(rng, 1.6, 2.0)
    quads.extend(_box_quads(cx - 0.4, cx + 0.4, 0.0, top, -1.9, -1.2, "cabinet"))
    power = _u(rng, 25.0, 45.0)
    mats["light"] = emitter(tuple(c * power for c in _light_colour(rng)))
    # facing up (cross(u, v) = +y), just above the cabinet top: no camera ray sees it
    quads.append(Quad((cx - 0.3, top + 1e-3, -1.85), (0, 0, 0.6), (0.6, 0, 0), "light"))
    spheres = []
    for i, (x, z, r) in enumerate(_place_on_floor(rng, int(rng.integers(2, 5)), (0.2, 0.45), (-1.6, 1.6),
                                                    (-1.0, 1.2), existing=[(cx, -1.55, 0.6)])):
        mats[f"sphere{i}"] = _object_material(rng)
        spheres.append(Sphere((x, r, z), r, f"sphere{i}"))
    cam = Camera(position=(_u(rng, -0.5, 0.5), _u(rng, 1.1, 1.5), _u(rng, 3.8, 4.4)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.6, 0.9), -1.0), fov=_u(rng, 45, 55))
    return Scene(name=name, family="indirect", camera=cam, materials=mats, spheres=spheres, quads=quads)


def fireflies(rng_or_seed=None, name: str = "fireflies") -> Scene:
    """Small, very bright lights over smooth glossy and plastic objects: the paths that find a light
    by BSDF sampling are rare and bright, so low sample counts show fireflies (while light sampling lets the
    reference converge)."""
    rng = _rng(rng_or_seed)
    mats = {
        "floor": plastic(_colour(rng, val=(0.2, 0.45)), (0.05, 0.05, 0.05), roughness=_u(rng, 0.05, 0.15)),
        "wall": lambert(_colour(rng, sat=(0.0, 0.3), val=(0.3, 0.5))),
    }
    quads = [Quad((-8, 0, -8), (0, 0, 16), (16, 0, 0), "floor"), Quad((-8, 0, -3), (16, 0, 0), (0, 6, 0), "wall")]
    spheres = []
    for i, (x, z, r) in enumerate(_place_on_floor(rng, int(rng.integers(4, 8)), (0.2, 0.5), (-2.5, 2.5),
                                                    (-2.5, 1.5))):
        # no perfect mirrors: light -> mirror -> wall is a caustic that only BSDF sampling finds, and it stays
        # speckled in a reference of thousands of samples; a glossy sphere's caustic is found by light sampling
        kind = str(rng.choice(["glossy", "plastic", "lambert"], p=[0.55, 0.3, 0.15]))
        mats[f"sphere{i}"] = _object_material(rng, kind)
        spheres.append(Sphere((x, r, z), r, f"sphere{i}"))
    for i in range(int(rng.integers(2, 5))):
        s = _u(rng, 0.02, 0.06)
        power = _u(rng, 1.0, 4.0)
        key = f"light{i}"
        mats[key] = emitter(tuple(c * power / (s * s) for c in _light_colour(rng)))
        quads.append(_ceiling_light((_u(rng, -2.5, 2.5), _u(rng, 1.0, 3.0), _u(rng, -2.5, 1.5)), s, s, key))
    cam = Camera(position=(_u(rng, -1.5, 1.5), _u(rng, 1.2, 2.5), _u(rng, 5.0, 6.5)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.3, 0.6), -0.5), fov=_u(rng, 38, 46))
    env = _u(rng, 0.005, 0.02)
    return Scene(name=name, family="fireflies", camera=cam, materials=mats, spheres=spheres, quads=quads,
                 environment=(env, env, env))


def caustics(rng_or_seed=None, name: str = "caustics") -> Scene:
    """Glass spheres and boxes and a mirror panel on a diffuse floor under one small light: caustics
    (light focused through glass, or off the mirror, onto diffuse surfaces) and refraction."""
    rng = _rng(rng_or_seed)
    mats = {
        "floor": lambert(_colour(rng, sat=(0.0, 0.3), val=(0.55, 0.8)), texture="world",
                         albedo2=_colour(rng, sat=(0.0, 0.4), val=(0.3, 0.5)), checker_scale=_u(rng, 1.0, 2.5)),
        "wall": lambert(_colour(rng, sat=(0.0, 0.3), val=(0.5, 0.7))),
        "mirror": mirror(_colour(rng, sat=(0.0, 0.15), val=(0.85, 0.97))),
    }
    quads = [Quad((-8, 0, -8), (0, 0, 16), (16, 0, 0), "floor"), Quad((-8, 0, -2.5), (16, 0, 0), (0, 6, 0), "wall")]
    spheres = []
    placed = _place_on_floor(rng, int(rng.integers(2, 5)), (0.3, 0.6), (-2.0, 2.0), (-1.8, 1.0))
    for i, (x, z, r) in enumerate(placed):
        tint = _hsv(_u(rng, 0, 1), _u(rng, 0.0, 0.25), 1.0)
        mats[f"glass{i}"] = glass(_u(rng, 1.33, 1.8), tint)
        if i % 2 == 0 or rng.uniform() < 0.5:
            spheres.append(Sphere((x, r + 1e-3, z), r, f"glass{i}"))
        else:
            hx = r * 0.65
            quads.extend(_closed_box(x - hx, x + hx, 1e-3, _u(rng, 0.3, 0.9), z - hx, z + hx, f"glass{i}"))
    mx = _u(rng, -2.5, 2.5)
    quads.append(Quad((mx - 0.6, 0.0, -2.4), (1.2, 0, 0), (0, 1.5, 0), "mirror"))  # leaning on the wall
    s = _u(rng, 0.1, 0.25)
    power = _u(rng, 15.0, 30.0)
    mats["light"] = emitter(tuple(c * power / (s * s) for c in _light_colour(rng)))
    quads.append(_ceiling_light((_u(rng, -1.5, 1.5), _u(rng, 2.5, 3.5), _u(rng, -1.0, 1.0)), s, s))
    cam = Camera(position=(_u(rng, -1.0, 1.0), _u(rng, 1.5, 2.5), _u(rng, 4.5, 5.5)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.3, 0.6), -0.3), fov=_u(rng, 38, 46))
    env = _u(rng, 0.01, 0.04)
    return Scene(name=name, family="caustics", camera=cam, materials=mats, spheres=spheres, quads=quads,
                 environment=(env, env, env))


def outdoor(rng_or_seed=None, name: str = "outdoor") -> Scene:
    """A long ground under a procedural HDR sky (an environment map: horizon-to-zenith gradient, a glow and
    a small intense sun disc, importance sampled): rows of objects and thin poles receding into the distance
    (high depth variation), often seen through a lens with shallow depth of field; in front, two triangle
    meshes (a torus and an icosphere)."""
    rng = _rng(rng_or_seed)
    mats = {
        "ground": lambert(_colour(rng, sat=(0.2, 0.6), val=(0.3, 0.55)), texture="world",
                          albedo2=_colour(rng, sat=(0.2, 0.6), val=(0.15, 0.3)), checker_scale=_u(rng, 0.5, 1.5)),
        "pole": _object_material(rng, str(rng.choice(["lambert", "glossy"]))),
    }
    quads = [Quad((-200, 0, -200), (0, 0, 400), (400, 0, 0), "ground")]
    spheres = []
    for row in range(int(rng.integers(3, 6))):
        z = -row * _u(rng, 3.0, 6.0)
        for side in (-1, 1):
            x = side * _u(rng, 1.0, 3.0)
            key = f"obj{row}{'lr'[side > 0]}"
            mats[key] = _object_material(rng)
            if rng.uniform() < 0.5:
                r = _u(rng, 0.3, 0.8)
                spheres.append(Sphere((x, r, z), r, key))
            else:
                h = _u(rng, 0.5, 2.0)
                quads.extend(_box_quads(x - 0.4, x + 0.4, 0.0, h, z - 0.4, z + 0.4, key))
        px = _u(rng, -0.5, 0.5)
        quads.extend(_box_quads(px - 0.02, px + 0.02, 0.0, _u(rng, 2.0, 4.0), z - 1.5, z - 1.46, "pole"))
    # an HDR sky map: the sun disc's radiance is set by its irradiance at normal incidence, drawn in [4, 10]
    # (the sky's alone is 0.5-1 on level ground: sunlit and shaded ground differ as on a clear day)
    radius = _u(rng, 1.0, 3.0)
    solid_angle = 2 * math.pi * (1 - math.cos(math.radians(radius)))
    sun = tuple(c * _u(rng, 4.0, 10.0) / solid_angle for c in _light_colour(rng))
    sky = Sky(sun_elevation=_u(rng, 12.0, 60.0), sun_azimuth=_u(rng, -180.0, 180.0), sun_radius=radius, sun=sun,
              zenith=_hsv(_u(rng, 0.55, 0.65), _u(rng, 0.5, 0.8), _u(rng, 0.2, 0.4)),
              horizon=_hsv(_u(rng, 0.05, 0.15), _u(rng, 0.1, 0.3), _u(rng, 0.35, 0.6)),
              ground=_hsv(_u(rng, 0.05, 0.15), _u(rng, 0.2, 0.4), _u(rng, 0.05, 0.15)))
    cam_z = _u(rng, 4.0, 6.0)
    aperture = _u(rng, 0.02, 0.12) if rng.uniform() < 0.7 else 0.0
    cam = Camera(position=(_u(rng, -0.5, 0.5), _u(rng, 0.8, 1.6), cam_z),
                 look_at=(_u(rng, -0.5, 0.5), _u(rng, 0.5, 1.0), -5.0), fov=_u(rng, 35, 50),
                 aperture=aperture, focus_distance=_u(rng, 3.0, 12.0) if aperture else None)
    # drawn last, so the rest of the scene is what it was before the family had meshes
    meshes = _foreground_meshes(rng, mats)
    return Scene(name=name, family="outdoor", camera=cam, materials=mats, spheres=spheres, quads=quads,
                 meshes=meshes, environment_map=EnvironmentMap(sky=sky))


def _foreground_meshes(rng, mats: dict) -> list[Mesh]:
    """A torus (lying, or tilted up) and an icosphere on the ground between the camera and the first
    row of objects (z in [1.5, 2.3], either side of the aisle), each with a random object material."""
    side = -1 if rng.uniform() < 0.5 else 1
    major, minor = _u(rng, 0.22, 0.32), _u(rng, 0.07, 0.11)
    tilt = _u(rng, 0.0, 70.0) if rng.uniform() < 0.5 else 0.0
    # lowest point of the tilted torus: its centre minus the tube radius minus major * sin(tilt)
    lift = minor + major * math.sin(math.radians(tilt)) + 1e-3
    centre = (side * _u(rng, 0.35, 0.8), lift, _u(rng, 1.5, 2.3))
    mats["torus"] = _object_material(rng)
    ring = torus(centre, major, minor, "torus", n_major=32, n_minor=12, tilt=tilt)
    r = _u(rng, 0.18, 0.3)
    mats["icosphere"] = _object_material(rng)
    ball = icosphere((-side * _u(rng, 0.35, 0.8), r + 1e-3, _u(rng, 1.5, 2.3)), r, int(rng.integers(1, 3)),
                     "icosphere")
    return [ring, ball]


def textures(rng_or_seed=None, name: str = "textures") -> Scene:
    """Fine texture detail: small checker cells on the floor, the walls and the objects (several cells
    per pixel in the distance), a mirror, an area light and a dim environment."""
    rng = _rng(rng_or_seed)
    mats = {
        "floor": lambert(_colour(rng, val=(0.6, 0.85)), texture="world", albedo2=_colour(rng, val=(0.1, 0.3)),
                         checker_scale=_u(rng, 6.0, 16.0)),
        "wall": lambert(_colour(rng, sat=(0.0, 0.3), val=(0.6, 0.8)), texture="world",
                        albedo2=_colour(rng, sat=(0.0, 0.3), val=(0.3, 0.5)), checker_scale=_u(rng, 4.0, 10.0)),
        "mirror": mirror(_colour(rng, sat=(0.0, 0.1), val=(0.85, 0.95))),
    }
    quads = [Quad((-10, 0, -10), (0, 0, 20), (20, 0, 0), "floor"), Quad((-10, 0, -3), (20, 0, 0), (0, 6, 0), "wall"),
             Quad((_u(rng, -2.5, 1.0), 0.0, -2.95), (1.5, 0, 0), (0, 2.0, 0), "mirror")]
    spheres = []
    for i, (x, z, r) in enumerate(_place_on_floor(rng, int(rng.integers(3, 7)), (0.25, 0.6), (-2.5, 2.5),
                                                    (-2.5, 1.5))):
        key = f"sphere{i}"
        if rng.uniform() < 0.6:
            mats[key] = lambert(_colour(rng), texture="uv", albedo2=_colour(rng, val=(0.75, 0.95)),
                                checker_scale=float(rng.integers(12, 40)))
        else:
            mats[key] = plastic(_colour(rng), (0.05, 0.05, 0.05), _u(rng, 0.05, 0.3), texture="uv",
                                albedo2=_colour(rng, val=(0.1, 0.3)), checker_scale=float(rng.integers(12, 40)))
        spheres.append(Sphere((x, r, z), r, key))
    sx, sz = _u(rng, 0.8, 1.5), _u(rng, 0.8, 1.5)
    power = _u(rng, 40.0, 80.0)
    mats["light"] = emitter(tuple(c * power / (sx * sz) for c in _light_colour(rng)))
    quads.append(_ceiling_light((_u(rng, -1.5, 1.5), _u(rng, 3.0, 4.0), _u(rng, -1.0, 1.0)), sx, sz))
    aperture = _u(rng, 0.02, 0.08) if rng.uniform() < 0.4 else 0.0
    cam = Camera(position=(_u(rng, -1.0, 1.0), _u(rng, 1.2, 2.2), _u(rng, 4.5, 6.0)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.3, 0.6), -1.0), fov=_u(rng, 35, 45),
                 aperture=aperture, focus_distance=_u(rng, 4.0, 7.0) if aperture else None)
    env = _u(rng, 0.02, 0.08)
    return Scene(name=name, family="textures", camera=cam, materials=mats, spheres=spheres, quads=quads,
                 environment=(env, env, env * 1.2))


def _ceiling_with_opening(w, h, d, hx, hz, wall="wall") -> list[Quad]:
    """The ceiling of a w x d room at height h (as :func:`_room`'s) with a 2 hx x 2 hz opening in its middle:
    four quads around it."""
    x0, x1, z0, z1 = -w / 2, w / 2, -d / 2, d / 2
    return [Quad((x0, h, z0), (w, 0, 0), (0, 0, d / 2 - hz), wall),  # back strip
            Quad((x0, h, hz), (w, 0, 0), (0, 0, z1 - hz), wall),  # front strip
            Quad((x0, h, -hz), (w / 2 - hx, 0, 0), (0, 0, 2 * hz), wall),  # left of the opening
            Quad((hx, h, -hz), (x1 - hx, 0, 0), (0, 0, 2 * hz), wall)]  # right of it


def media(rng_or_seed=None, name: str = "media") -> Scene:
    """A room filled with fog (a participating medium), or a denser box of it on the floor: lit by a ceiling light,
    or by a small bright light above an opening in the ceiling, whose light falls through the fog as a shaft;
    mixed objects on the floor. Fog density, colour (absorption) and forward scattering vary, and half of the
    media are heterogeneous (smoke: density from value noise)."""
    rng = _rng(rng_or_seed)
    wall = _u(rng, 0.55, 0.8)
    mats = {"wall": lambert(_colour(rng, sat=(0.0, 0.2), val=(wall, wall + 0.1))),
            "floor": lambert(_colour(rng, sat=(0.2, 0.6), val=(0.35, 0.6)), texture="world",
                             albedo2=_colour(rng, sat=(0.2, 0.6), val=(0.15, 0.3)), checker_scale=_u(rng, 1.5, 3.0))}
    w, h, d = 4.0, 2.6, 4.0
    quads = _room(w, h, d)
    spheres = []
    shaft = rng.uniform() < 0.5
    if shaft:
        hx, hz = _u(rng, 0.25, 0.5), _u(rng, 0.25, 0.5)
        quads = [quads[0]] + quads[2:] + _ceiling_with_opening(w, h, d, hx, hz)  # _room's ceiling is quads[1]
        power = _u(rng, 6000.0, 12000.0)
        mats["light"] = emitter(tuple(c * power for c in _light_colour(rng)))
        spheres.append(Sphere((_u(rng, -1.0, 1.0), h + _u(rng, 3.0, 5.0), _u(rng, -1.0, 0.5)), 0.1, "light"))
    else:
        power = _u(rng, 30.0, 60.0)
        mats["light"] = emitter(tuple(c * power for c in _light_colour(rng)))
        quads.append(_ceiling_light((_u(rng, -0.8, 0.8), h - 1e-3, _u(rng, -0.8, 0.4)), _u(rng, 0.3, 0.5),
                                    _u(rng, 0.3, 0.5)))
    for i, (x, z, r) in enumerate(_place_on_floor(rng, int(rng.integers(2, 5)), (0.2, 0.45), (-1.5, 1.5),
                                                    (-1.4, 1.2))):
        mats[f"sphere{i}"] = _object_material(rng)
        spheres.append(Sphere((x, r, z), r, f"sphere{i}"))
    tint = _colour(rng, sat=(0.0, 0.4), val=(0.6, 1.0))
    absorb = _u(rng, 0.0, 0.15)
    sigma_s = _u(rng, 0.08, 0.45)
    box_min, box_max = (-w / 2, 0.0, -d / 2), (w / 2, h, d / 2 + 2.0)  # the room and the camera's side of it
    if rng.uniform() < 0.4:  # a denser box of it standing on the floor instead
        sx, sz, top = _u(rng, 0.8, 1.5), _u(rng, 0.6, 1.2), _u(rng, 1.0, 2.2)
        cx, cz = _u(rng, -0.6, 0.6), _u(rng, -1.0, 0.3)
        box_min, box_max, sigma_s = (cx - sx, 0.0, cz - sz), (cx + sx, top, cz + sz), 4 * sigma_s + 0.5
    smoke = rng.uniform() < 0.5  # heterogeneous: density from value noise
    fog = Medium(sigma_a=tuple(absorb * (1.2 - c) for c in tint), sigma_s=sigma_s, g=_u(rng, 0.0, 0.7),
                 box_min=box_min, box_max=box_max, density="noise" if smoke else "homogeneous",
                 noise_cells=int(rng.integers(2, 5)), noise_amount=_u(rng, 0.6, 1.0),
                 noise_seed=int(rng.integers(0, 2**31)))
    cam = Camera(position=(_u(rng, -0.5, 0.5), _u(rng, 1.0, 1.5), _u(rng, 3.8, 4.4)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.8, 1.2), -1.0), fov=_u(rng, 45, 55))
    return Scene(name=name, family="media", camera=cam, materials=mats, spheres=spheres, quads=quads, medium=fog)


FAMILIES = {"cornell": cornell, "spheres": spheres, "boxes": boxes, "indirect": indirect,
            "fireflies": fireflies, "caustics": caustics, "outdoor": outdoor, "textures": textures, "media": media}
# The families a render set (and `kpcn bench render`) takes unless told otherwise: all but media, whose scenes
# cost several times the others' per sample and whose references' convergence is not measured yet; `--families`
# adds it. (Kept out so that `make train`'s set, and its time, stay those of the results in docs/results.)
DEFAULT_FAMILIES = tuple(f for f in FAMILIES if f != "media")
# Families with light paths that only BSDF sampling finds (caustics through glass and off mirrors, small
# lights seen in glossy surfaces, a room lit through a gap): their references take this many times a
# render set's reference_spp, so that the targets the network learns from are not themselves noisy.
# `kpcn references` measures how far they get (docs/scenes.md §4, p99 relSE at 64x64, 2026-12-02). indirect's
# fell as 1/sqrt(spp), 0.19-0.25 at 1024 to 0.13-0.16 at 2048, so it takes 4 (about 80 s more of make train's
# render than 2); 8 (0.09-0.11) would cost about 4 min more, past make train's 30 min. The tails of textures
# (0.11-0.18 at 1024, 89-93 % of pixels converged) and caustics are left to the loss weighting
# (kpcn_keras.losses): caustics' p99 rose from 0.05-0.08 at 512 to 0.56-0.62 at 2048 in two of three scenes,
# as rare paths appear.
REFERENCE_SPP_FACTOR = {"caustics": 4, "fireflies": 4, "indirect": 4, "textures": 2}


def check_families(families) -> None:
    """Refuse a ``families`` option (a config's tuple of family names) that is a string, empty or names an
    unknown family; repeats are refused with the config's other distinct fields (``bounds.check_fields``)."""
    if isinstance(families, str):
        raise OptionError("families", f"must be a tuple of names, got the string {families!r}")
    if not families:
        raise OptionError("families", "must name at least one scene family")
    for fam in families:
        if fam not in FAMILIES:
            raise OptionError("families", f"has unknown scene family {fam!r}; valid families: {', '.join(FAMILIES)}")


def family_seed(family: str, index: int, seed: int) -> list[int]:
    """The SeedSequence entropy a scene is generated from: stable across runs and Python versions."""
    return [int(seed), zlib.crc32(family.encode()), int(index)]


def make_scene(family: str, index: int, seed: int) -> Scene:
    """Scene number ``index`` of ``family`` for a set seeded with ``seed``; deterministic.

    Named ``f"{family}-{index:03d}"``. Raises ValueError for an unknown family (listing the valid
    ones) or a negative index/seed.
    """
    if family not in FAMILIES:
        raise ValueError(f"unknown scene family {family!r}; valid families: {', '.join(FAMILIES)}")
    if not is_integer(index) or index < 0:
        raise ValueError(f"scene index must be an int >= 0, got {index!r}")
    if not is_integer(seed) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    rng = np.random.default_rng(family_seed(family, index, seed))
    scene = FAMILIES[family](rng, name=f"{family}-{int(index):03d}")
    scene.seed = int(seed)
    scene.validate()
    return scene
