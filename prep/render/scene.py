"""Scene description for the numba path tracer: plain dataclasses, flat arrays for the kernels.

Conventions (world space, y up, units arbitrary but scenes are a few units across):

* ``Quad(corner, u, v, material)`` is the parallelogram ``corner + a*u + b*v``, a, b in [0, 1].
  Its normal is ``normalize(cross(u, v))``. Quads are double-sided for shading (the shading normal
  is flipped to face the incoming ray); an ``emitter`` quad emits only on the side its normal points
  to and is black on the other side.
* ``Sphere(center, radius, material)``; emitters must be quads (next-event estimation samples quads).
* ``Material.kind``:

  - ``lambert``: diffuse ``albedo``; ``texture`` ``"world"`` (3-D checker with cells of side
    ``1/checker_scale`` in world space) or ``"uv"`` (``checker_scale`` cells along each quad edge;
    on spheres ``checker_scale`` along a meridian, twice that around the equator) alternates
    ``albedo`` and ``albedo2``.
  - ``glossy``: rough metal, GGX lobe, Schlick Fresnel with ``specular`` as F0, GGX alpha
    ``roughness``; no diffuse lobe.
  - ``plastic``: lambert base (``albedo``, textures as for lambert) plus a GGX coat with F0
    ``specular``; the sampled lobe is picked at random per bounce (in proportion to the coat's
    Fresnel weight, clamped to [0.15, 0.85]). The base is not dimmed by the coat: keep
    albedo + specular <= 1. The ``albedo`` AOV of a plastic is its base albedo.
  - ``emitter``: radiance ``emission`` (RGB), reflects nothing.

* ``Camera``: pinhole at ``position`` looking at ``look_at``, vertical field of view ``fov`` degrees.
* ``environment``: constant RGB radiance of rays that leave the scene.

Scene families are functions ``(rng or seed) -> Scene`` with seeded random variations; see
:data:`FAMILIES` and :func:`make_scene`.
"""

from __future__ import annotations

import colorsys
import math
import zlib
from dataclasses import asdict, dataclass, field

import numpy as np

MATERIAL_KINDS = ("lambert", "glossy", "plastic", "emitter")
TEXTURES = ("none", "world", "uv")

# Layout of one row of the material table handed to the kernels (see tracer.py).
MAT_KIND, MAT_ALBEDO, MAT_SPECULAR, MAT_ROUGHNESS = 0, 1, 4, 7
MAT_EMISSION, MAT_TEXTURE, MAT_ALBEDO2, MAT_SCALE = 8, 11, 12, 15
MAT_COLS = 16
# Layout of one row of the quad table: corner, u, v, unit normal, dual vectors of u and v, area.
QUAD_COLS = 19

Vec3 = tuple[float, float, float]


def _vec(x, what: str) -> Vec3:
    arr = np.asarray(x, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be 3 finite numbers, got {x!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Material:
    """One material; see the module docstring for the meaning of each kind."""

    kind: str
    albedo: Vec3 = (0.0, 0.0, 0.0)
    specular: Vec3 = (0.0, 0.0, 0.0)
    roughness: float = 0.2
    emission: Vec3 = (0.0, 0.0, 0.0)
    texture: str = "none"
    albedo2: Vec3 = (0.0, 0.0, 0.0)
    checker_scale: float = 1.0

    def __post_init__(self):
        if self.kind not in MATERIAL_KINDS:
            raise ValueError(f"material kind must be one of {MATERIAL_KINDS}, got {self.kind!r}")
        if self.texture not in TEXTURES:
            raise ValueError(f"texture must be one of {TEXTURES}, got {self.texture!r}")
        for name in ("albedo", "specular", "emission", "albedo2"):
            v = _vec(getattr(self, name), f"Material.{name}")
            if min(v) < 0:
                raise ValueError(f"Material.{name} must be >= 0, got {v}")
            if name in ("albedo", "albedo2", "specular") and max(v) > 1:
                raise ValueError(f"Material.{name} must be <= 1, got {v}")
            object.__setattr__(self, name, v)
        if self.kind in ("glossy", "plastic") and not 0.01 <= self.roughness <= 1.0:
            raise ValueError(f"GGX roughness must be in [0.01, 1], got {self.roughness!r}")
        if self.texture != "none" and not self.checker_scale > 0:
            raise ValueError(f"checker_scale must be > 0, got {self.checker_scale!r}")


def lambert(albedo, texture: str = "none", albedo2=(0.0, 0.0, 0.0), checker_scale: float = 1.0) -> Material:
    return Material("lambert", albedo=albedo, texture=texture, albedo2=albedo2, checker_scale=checker_scale)


def glossy(specular, roughness: float) -> Material:
    return Material("glossy", specular=specular, roughness=roughness)


def plastic(albedo, specular, roughness: float, texture: str = "none", albedo2=(0.0, 0.0, 0.0),
            checker_scale: float = 1.0) -> Material:
    return Material("plastic", albedo=albedo, specular=specular, roughness=roughness, texture=texture,
                    albedo2=albedo2, checker_scale=checker_scale)


def emitter(emission) -> Material:
    return Material("emitter", emission=emission)


@dataclass(frozen=True)
class Sphere:
    center: Vec3
    radius: float
    material: str

    def __post_init__(self):
        object.__setattr__(self, "center", _vec(self.center, "Sphere.center"))
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ValueError(f"Sphere.radius must be > 0, got {self.radius!r}")


@dataclass(frozen=True)
class Quad:
    corner: Vec3
    u: Vec3
    v: Vec3
    material: str

    def __post_init__(self):
        for name in ("corner", "u", "v"):
            object.__setattr__(self, name, _vec(getattr(self, name), f"Quad.{name}"))
        if np.linalg.norm(np.cross(self.u, self.v)) < 1e-12:
            raise ValueError(f"Quad edges are parallel or zero: u={self.u}, v={self.v}")

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.u, self.v)
        return n / np.linalg.norm(n)

    @property
    def area(self) -> float:
        return float(np.linalg.norm(np.cross(self.u, self.v)))


@dataclass(frozen=True)
class Camera:
    position: Vec3
    look_at: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = 40.0

    def __post_init__(self):
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, _vec(getattr(self, name), f"Camera.{name}"))
        if not 0 < self.fov < 180:
            raise ValueError(f"Camera.fov must be in (0, 180) degrees, got {self.fov!r}")
        fwd = np.subtract(self.look_at, self.position)
        if np.linalg.norm(fwd) < 1e-12 or np.linalg.norm(np.cross(fwd, self.up)) < 1e-9 * np.linalg.norm(fwd):
            raise ValueError(
                f"Camera looks from {self.position} to {self.look_at} with up {self.up}: degenerate"
            )

    def frame(self) -> np.ndarray:
        """(12,) float64: position, forward, right, up (unit vectors; right-handed, image x = right)."""
        pos = np.asarray(self.position)
        fwd = np.subtract(self.look_at, pos)
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, self.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        return np.concatenate([pos, fwd, right, up]).astype(np.float64)


@dataclass
class SceneArrays:
    """The flat arrays the kernels take (layouts: the MAT_* and QUAD_COLS constants of this module)."""

    spheres: np.ndarray  # (Ns, 4) centre, radius
    sphere_mat: np.ndarray  # (Ns,) int64
    quads: np.ndarray  # (Nq, QUAD_COLS)
    quad_mat: np.ndarray  # (Nq,) int64
    quad_light: np.ndarray  # (Nq,) int64, index into lights or -1
    n_single: int  # quads[:n_single] are tested one by one
    groups: np.ndarray  # (Ng, 2) int64 [start, end) ranges of the other quads
    group_bounds: np.ndarray  # (Ng, 4) bounding sphere (centre, radius) of each range
    materials: np.ndarray  # (Nm, MAT_COLS)
    lights: np.ndarray  # (Nl,) int64 quad index of each light
    light_cdf: np.ndarray  # (Nl,) cumulative selection probability
    light_prob: np.ndarray  # (Nl,) selection probability (proportional to power)
    camera: np.ndarray  # (12,) see Camera.frame
    environment: np.ndarray  # (3,)


def _lists(obj):
    """Tuples to lists, recursively, so a dict equals its JSON round trip."""
    if isinstance(obj, dict):
        return {k: _lists(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_lists(v) for v in obj]
    return obj


def _quad_order(quads) -> tuple[list[int], int, np.ndarray, np.ndarray]:
    """Order of the quads in the kernel's table: quads tested one by one first, then runs of >= 3
    consecutive quads sharing a material (the faces of one box), each with a bounding sphere so that
    a ray missing it skips them all. Returns (order, number of single quads, ranges, spheres)."""
    singles, runs = [], []
    i = 0
    while i < len(quads):
        j = i + 1
        while j < len(quads) and quads[j].material == quads[i].material:
            j += 1
        (runs.append(list(range(i, j))) if j - i >= 3 else singles.extend(range(i, j)))
        i = j
    order = list(singles)
    ranges, bounds = [], []
    for run in runs:
        pts = np.array([np.asarray(quads[k].corner) + a * np.asarray(quads[k].u) + b * np.asarray(quads[k].v)
                        for k in run for a in (0, 1) for b in (0, 1)])
        centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
        radius = np.linalg.norm(pts - centre, axis=1).max() * (1 + 1e-6) + 1e-6
        ranges.append((len(order), len(order) + len(run)))
        bounds.append((*centre, radius))
        order.extend(run)
    return (order, len(singles), np.asarray(ranges, dtype=np.int64).reshape(-1, 2),
            np.asarray(bounds, dtype=np.float64).reshape(-1, 4))


def _luminance(rgb) -> float:
    return 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2]


@dataclass
class Scene:
    """A renderable scene. Objects name their material by key of ``materials``."""

    name: str
    family: str
    camera: Camera
    materials: dict[str, Material]
    spheres: list[Sphere] = field(default_factory=list)
    quads: list[Quad] = field(default_factory=list)
    environment: Vec3 = (0.0, 0.0, 0.0)
    seed: int | None = None  # the seed the family was generated from, if any

    def validate(self) -> None:
        """Raise ValueError if an object names an unknown material or a sphere is an emitter."""
        env = _vec(self.environment, "Scene.environment")
        if min(env) < 0:
            raise ValueError(f"Scene.environment must be >= 0, got {env}")
        for obj in list(self.spheres) + list(self.quads):
            if obj.material not in self.materials:
                raise ValueError(f"{self.name}: object {obj} names unknown material {obj.material!r}; "
                                 f"known: {sorted(self.materials)}")
        for s in self.spheres:
            if self.materials[s.material].kind == "emitter":
                raise ValueError(f"{self.name}: sphere {s} uses an emitter material; only quads may emit")

    def to_arrays(self) -> SceneArrays:
        """Flatten into the arrays of :class:`SceneArrays` (validates first)."""
        self.validate()
        names = list(self.materials)
        index = {n: i for i, n in enumerate(names)}
        mats = np.zeros((max(len(names), 1), MAT_COLS), dtype=np.float64)
        for i, n in enumerate(names):
            m = self.materials[n]
            mats[i, MAT_KIND] = MATERIAL_KINDS.index(m.kind)
            mats[i, MAT_ALBEDO:MAT_ALBEDO + 3] = m.albedo
            mats[i, MAT_SPECULAR:MAT_SPECULAR + 3] = m.specular
            mats[i, MAT_ROUGHNESS] = m.roughness
            mats[i, MAT_EMISSION:MAT_EMISSION + 3] = m.emission
            mats[i, MAT_TEXTURE] = TEXTURES.index(m.texture)
            mats[i, MAT_ALBEDO2:MAT_ALBEDO2 + 3] = m.albedo2
            mats[i, MAT_SCALE] = m.checker_scale

        spheres = np.array([[*s.center, s.radius] for s in self.spheres], dtype=np.float64).reshape(-1, 4)
        sphere_mat = np.array([index[s.material] for s in self.spheres], dtype=np.int64)

        order, n_single, groups, bounds = _quad_order(self.quads)
        quads = np.zeros((len(self.quads), QUAD_COLS), dtype=np.float64)
        quad_mat = np.zeros(len(self.quads), dtype=np.int64)
        quad_light = np.full(len(self.quads), -1, dtype=np.int64)
        lights, powers = [], []
        for i, q in enumerate(self.quads[k] for k in order):
            u, v = np.asarray(q.u), np.asarray(q.v)
            nn = np.cross(u, v)
            w = nn / nn.dot(nn)
            # p - corner = a*u + b*v  =>  a = (p - corner).cross(v, w), b = (p - corner).cross(w, u)
            quads[i] = np.concatenate([q.corner, u, v, nn / np.linalg.norm(nn),
                                       np.cross(v, w), np.cross(w, u), [np.linalg.norm(nn)]])
            quad_mat[i] = index[q.material]
            m = self.materials[q.material]
            if m.kind == "emitter" and max(m.emission) > 0:
                quad_light[i] = len(lights)
                lights.append(i)
                powers.append(q.area * max(_luminance(m.emission), 1e-6))
        powers = np.asarray(powers, dtype=np.float64)
        prob = powers / powers.sum() if len(powers) else powers
        cdf = np.cumsum(prob)
        if len(cdf):
            cdf[-1] = 1.0
        return SceneArrays(
            spheres=spheres, sphere_mat=sphere_mat, quads=quads, quad_mat=quad_mat, quad_light=quad_light,
            n_single=n_single, groups=groups, group_bounds=bounds, materials=mats,
            lights=np.asarray(lights, dtype=np.int64), light_cdf=cdf, light_prob=prob,
            camera=self.camera.frame(), environment=np.asarray(_vec(self.environment, "environment")),
        )

    def to_dict(self) -> dict:
        """A JSON-able description, vectors as lists (inverse: :meth:`from_dict`)."""
        return _lists({
            "name": self.name,
            "family": self.family,
            "seed": self.seed,
            "camera": asdict(self.camera),
            "environment": list(self.environment),
            "materials": {k: asdict(m) for k, m in self.materials.items()},
            "spheres": [asdict(s) for s in self.spheres],
            "quads": [asdict(q) for q in self.quads],
        })

    @classmethod
    def from_dict(cls, d: dict) -> "Scene":
        return cls(
            name=d["name"], family=d["family"], seed=d.get("seed"),
            camera=Camera(**d["camera"]),
            environment=tuple(d["environment"]),
            materials={k: Material(**m) for k, m in d["materials"].items()},
            spheres=[Sphere(**s) for s in d["spheres"]],
            quads=[Quad(**q) for q in d["quads"]],
        )


# ---------------------------------------------------------------------------------------------
# Scene families
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


def _ceiling_light(centre, sx, sz) -> Quad:
    """Horizontal sx*sz rectangle centred at ``centre``, emitting downwards (-y)."""
    cx, cy, cz = centre
    # cross((sx,0,0), (0,0,sz)) = (0, -sx*sz, 0): normal points down
    return Quad((cx - sx / 2, cy, cz - sz / 2), (sx, 0.0, 0.0), (0.0, 0.0, sz), "light")


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
    environment."""
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
        q = _ceiling_light((_u(rng, -3, 3), _u(rng, 3.0, 5.0), _u(rng, -3, 2)), sx, sz)
        quads.append(Quad(q.corner, q.u, q.v, key))
    angle = _u(rng, -0.5, 0.5)
    dist = _u(rng, 6.5, 8.0)
    cam = Camera(position=(dist * math.sin(angle), _u(rng, 1.5, 3.0), dist * math.cos(angle)),
                 look_at=(_u(rng, -0.3, 0.3), _u(rng, 0.3, 0.6), _u(rng, -0.5, 0.0)), fov=_u(rng, 38, 46))
    env = _u(rng, 0.03, 0.1)
    return Scene(name=name, family="spheres", camera=cam, materials=mats, spheres=spheres_, quads=quads,
                 environment=(env * 0.8, env * 0.9, env))


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


FAMILIES = {"cornell": cornell, "spheres": spheres, "boxes": boxes}


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
    if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or index < 0:
        raise ValueError(f"scene index must be an int >= 0, got {index!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an int >= 0, got {seed!r}")
    rng = np.random.default_rng(family_seed(family, index, seed))
    scene = FAMILIES[family](rng, name=f"{family}-{int(index):03d}")
    scene.seed = int(seed)
    scene.validate()
    return scene
