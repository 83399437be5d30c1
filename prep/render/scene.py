"""Scene description for the numba path tracer: plain dataclasses, and the effects a scene calls for.

Conventions (world space, y up, units arbitrary but scenes are a few units across):

* ``Quad(corner, u, v, material)`` is the parallelogram ``corner + a*u + b*v``, a, b in [0, 1].
  Its normal is ``normalize(cross(u, v))``. Quads are double-sided for shading (the shading normal
  is flipped to face the incoming ray); an ``emitter`` quad emits only on the side its normal points
  to and is black on the other side.
* ``Sphere(center, radius, material)``; an ``emitter`` sphere is a light that emits outwards (light
  sampling picks a direction in the cone it subtends).
* ``Mesh(vertices, faces, material)``: a triangle mesh, ``faces`` index ``vertices`` from 0. A triangle's
  geometric normal is ``normalize(cross(v1 - v0, v2 - v0))``: counter-clockwise winding seen from outside
  makes it point outwards, which glass needs (a closed mesh wound that way). Shading is double-sided as
  for quads; texture coordinates are the barycentrics (u along v1 - v0, v along v2 - v0). An ``emitter``
  mesh is an area light made of its triangles, each emitting only on the side its geometric normal points
  to (black on the other side) and sampled as a light of its own in proportion to its power. ``obj.load_obj``
  reads one from an OBJ file, ``shapes.py`` makes a few procedurally.
* ``Material.kind``:

  - ``lambert``: diffuse ``albedo``; ``texture`` ``"world"`` (3-D checker with cells of side
    ``1/checker_scale`` in world space) or ``"uv"`` (``checker_scale`` cells along each quad edge;
    on spheres ``checker_scale`` along a meridian, twice that around the equator) alternates
    ``albedo`` and ``albedo2``; ``texture`` ``"image"`` multiplies ``albedo`` by the texel of the PNG
    file ``image`` at the surface's texture coordinates (tiled ``checker_scale`` times along each; u runs
    across the image, v down it; nearest texel; sRGB values decoded to linear with gamma 2.2).
  - ``glossy``: rough metal, GGX lobe, Schlick Fresnel with ``specular`` as F0, GGX alpha
    ``roughness``; no diffuse lobe.
  - ``plastic``: lambert base (``albedo``, textures as for lambert) plus a GGX coat with F0
    ``specular``; the sampled lobe is picked at random per bounce (in proportion to the coat's
    Fresnel weight, clamped to [0.15, 0.85]). The base is not dimmed by the coat: keep
    albedo + specular <= 1. The ``albedo`` AOV of a plastic is its base albedo.
  - ``emitter``: radiance ``emission`` (RGB), reflects nothing.
  - ``mirror``: perfect mirror reflecting ``specular`` (RGB reflectance).
  - ``glass``: smooth dielectric of index of refraction ``ior`` (exact Fresnel, unpolarised): each
    crossing reflects with the Fresnel probability and refracts otherwise; refracted light is tinted by
    ``specular`` (1, 1, 1 is clear glass). Radiance is not scaled by the squared index ratio on
    crossing, which cancels for closed objects seen from outside. Glass needs closed shapes whose
    normals point outwards (spheres; boxes of quads with outward ``cross(u, v)``).

  The AOVs follow the lobe of the first scattering vertex: mirror, glass and glossy surfaces go to
  ``specular``, and their ``albedo`` is 0 (as for emitters and the background), so that ``diffuse /
  albedo`` stays the irradiance of diffuse surfaces only.

* ``Camera``: at ``position`` looking at ``look_at``, vertical field of view ``fov`` degrees; a pinhole
  when ``aperture`` (the lens radius) is 0, else a thin lens focused at ``focus_distance`` along the view
  direction (default: the distance to ``look_at``).
* ``environment``: RGB radiance of rays that leave the scene towards the horizon; with
  ``environment_zenith`` set, radiance blends linearly from the horizon colour to that colour as the
  direction rises to straight up (below the horizon: the horizon colour). Constant otherwise.
* ``environment_map``: instead (``environment`` then stays black), an :class:`EnvironmentMap`: radiance
  from a latitude-longitude texture, either an image file (OpenEXR for real HDR, or PNG) or a
  procedural HDR :class:`Sky` baked into one; texel (row, column) of an H x W map covers polar angles
  theta in [row, row + 1) * pi / H from straight up (+y) and azimuths phi in [column, column + 1) * 2 pi / W
  - pi, phi measured about y from +x towards +z (``environment.py`` owns the mapping). Radiance is the
  texel's (nearest, no filtering), times ``scale``. Unlike a constant or gradient environment, a map is
  a light: it is importance sampled in proportion to texel luminance x solid angle and MIS-weighted
  against BSDF sampling, so a small bright sun converges as an area light does.

The built-in scene families are in ``families.py``; ``packing.py`` flattens a scene for the kernels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from prep.bounds import is_integer

MATERIAL_KINDS = ("lambert", "glossy", "plastic", "emitter", "mirror", "glass")
TEXTURES = ("none", "world", "uv", "image")
# What a scene can call for; the tracer compiles a kernel for each set it meets (see kernels.py): the
# material kinds, plus these.
EFFECTS = MATERIAL_KINDS + ("environment", "texture", "lens", "mesh", "environment_map", "medium", "heterogeneous")
DENSITIES = ("homogeneous", "noise")
IOR_RANGE = (1.0, 3.0)

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
    ior: float = 1.5
    image: str = ""

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
        if (self.texture == "image") != bool(self.image):
            raise ValueError(f"Material.image names the PNG of texture 'image' (and only then), got texture "
                             f"{self.texture!r} and image {self.image!r}")
        if not IOR_RANGE[0] <= self.ior <= IOR_RANGE[1]:
            raise ValueError(f"Material.ior must be in [{IOR_RANGE[0]}, {IOR_RANGE[1]}], got {self.ior!r}")


def lambert(albedo, texture: str = "none", albedo2=(0.0, 0.0, 0.0), checker_scale: float = 1.0,
            image: str = "") -> Material:
    return Material("lambert", albedo=albedo, texture=texture, albedo2=albedo2, checker_scale=checker_scale,
                    image=image)


def glossy(specular, roughness: float) -> Material:
    return Material("glossy", specular=specular, roughness=roughness)


def plastic(albedo, specular, roughness: float, texture: str = "none", albedo2=(0.0, 0.0, 0.0),
            checker_scale: float = 1.0) -> Material:
    return Material("plastic", albedo=albedo, specular=specular, roughness=roughness, texture=texture,
                    albedo2=albedo2, checker_scale=checker_scale)


def emitter(emission) -> Material:
    return Material("emitter", emission=emission)


def mirror(reflectance=(1.0, 1.0, 1.0)) -> Material:
    return Material("mirror", specular=reflectance)


def glass(ior: float = 1.5, tint=(1.0, 1.0, 1.0)) -> Material:
    return Material("glass", specular=tint, ior=ior)


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


@dataclass(frozen=True, repr=False)
class Mesh:
    """A triangle mesh: ``faces`` are triples of 0-based indices into ``vertices``; plain tuples, so that
    meshes compare by value. Degenerate (zero-area) faces are allowed but never hit; a mesh needs at
    least one face that is not."""

    vertices: tuple[Vec3, ...]
    faces: tuple[tuple[int, int, int], ...]
    material: str

    def __post_init__(self):
        try:
            v = np.asarray(self.vertices, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"Mesh.vertices must be an array of 3 finite numbers each, "
                             f"got {self.vertices!r}") from None
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
            raise ValueError(f"Mesh.vertices must be at least 3 points of 3 numbers, got shape {v.shape}")
        if not np.all(np.isfinite(v)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(v), axis=1))[0])
            raise ValueError(f"Mesh.vertices must be finite, vertex {bad} is {tuple(v[bad].tolist())}")
        f = np.asarray(self.faces)
        if f.size == 0:
            raise ValueError("Mesh.faces must hold at least one face, got none")
        if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
            raise ValueError(f"Mesh.faces must be triples of integer vertex indices, got shape {f.shape} "
                             f"of {f.dtype}")
        if f.min() < 0 or f.max() >= len(v):
            bad = int(np.flatnonzero((f < 0).any(axis=1) | (f >= len(v)).any(axis=1))[0])
            raise ValueError(f"Mesh.faces must index the {len(v)} vertices (0 to {len(v) - 1}), face {bad} is "
                             f"{tuple(f[bad].tolist())}")
        if not np.any(triangle_areas(v, f) > 0):
            raise ValueError(f"Mesh.faces must include a face of non-zero area; all {len(f)} are degenerate")
        object.__setattr__(self, "vertices", tuple((float(a), float(b), float(c)) for a, b, c in v.tolist()))
        object.__setattr__(self, "faces", tuple((int(a), int(b), int(c)) for a, b, c in f.tolist()))

    def __repr__(self) -> str:  # short: a mesh can have thousands of vertices
        return f"Mesh(<{len(self.vertices)} vertices>, <{len(self.faces)} faces>, material={self.material!r})"

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(vertices (N, 3) float64, faces (M, 3) int64)."""
        return (np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3),
                np.asarray(self.faces, dtype=np.int64).reshape(-1, 3))


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area of each face; 0 for degenerate ones (and for slivers whose area is lost to rounding)."""
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    e1, e2 = v1 - v0, v2 - v0
    area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
    return np.where(area > 1e-12 * scale, area, 0.0)


@dataclass(frozen=True)
class Camera:
    position: Vec3
    look_at: Vec3
    up: Vec3 = (0.0, 1.0, 0.0)
    fov: float = 40.0
    aperture: float = 0.0
    focus_distance: float | None = None

    def __post_init__(self):
        for name in ("position", "look_at", "up"):
            object.__setattr__(self, name, _vec(getattr(self, name), f"Camera.{name}"))
        if not 0 < self.fov < 180:
            raise ValueError(f"Camera.fov must be in (0, 180) degrees, got {self.fov!r}")
        if not (math.isfinite(self.aperture) and self.aperture >= 0):
            raise ValueError(f"Camera.aperture must be >= 0, got {self.aperture!r}")
        if self.focus_distance is not None and not (math.isfinite(self.focus_distance) and self.focus_distance > 0):
            raise ValueError(f"Camera.focus_distance must be > 0, got {self.focus_distance!r}")
        fwd = np.subtract(self.look_at, self.position)
        if np.linalg.norm(fwd) < 1e-12 or np.linalg.norm(np.cross(fwd, self.up)) < 1e-9 * np.linalg.norm(fwd):
            raise ValueError(
                f"Camera looks from {self.position} to {self.look_at} with up {self.up}: degenerate"
            )

    @property
    def focus(self) -> float:
        """Distance of the plane in focus along the view direction."""
        if self.focus_distance is not None:
            return float(self.focus_distance)
        return float(np.linalg.norm(np.subtract(self.look_at, self.position)))

    def frame(self) -> np.ndarray:
        """(12,) float64: position, forward, right, up (unit vectors; right-handed, image x = right)."""
        pos = np.asarray(self.position)
        fwd = np.subtract(self.look_at, pos)
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, self.up)
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        return np.concatenate([pos, fwd, right, up]).astype(np.float64)


@dataclass(frozen=True)
class Sky:
    """A procedural HDR sky (a clear day): above the horizon, ``horizon`` blending to ``zenith`` as
    (sin elevation) ** 0.5, plus a glow around the sun; a sun disc of angular radius ``sun_radius``
    degrees and radiance ``sun`` at ``sun_elevation`` degrees above the horizon and ``sun_azimuth`` degrees
    (about y from +x towards +z); ``ground`` below the horizon. Baked at ``height`` x 2 ``height``
    texels: keep ``sun_radius`` above a texel (180 / ``height`` degrees) so the disc is round."""

    sun_elevation: float = 40.0
    sun_azimuth: float = 0.0
    sun_radius: float = 2.0
    sun: Vec3 = (500.0, 470.0, 420.0)
    zenith: Vec3 = (0.15, 0.3, 0.8)
    horizon: Vec3 = (0.7, 0.75, 0.85)
    ground: Vec3 = (0.15, 0.13, 0.11)
    height: int = 256

    def __post_init__(self):
        for name in ("sun", "zenith", "horizon", "ground"):
            v = _vec(getattr(self, name), f"Sky.{name}")
            if min(v) < 0:
                raise ValueError(f"Sky.{name} must be >= 0, got {v}")
            object.__setattr__(self, name, v)
        if not -90 <= self.sun_elevation <= 90:
            raise ValueError(f"Sky.sun_elevation must be in [-90, 90] degrees, got {self.sun_elevation!r}")
        if not math.isfinite(self.sun_azimuth):
            raise ValueError(f"Sky.sun_azimuth must be finite, got {self.sun_azimuth!r}")
        if not 0 < self.sun_radius <= 20:
            raise ValueError(f"Sky.sun_radius must be in (0, 20] degrees, got {self.sun_radius!r}")
        if not is_integer(self.height) or not 4 <= self.height <= 4096:
            raise ValueError(f"Sky.height must be an integer in [4, 4096], got {self.height!r}")


@dataclass(frozen=True)
class EnvironmentMap:
    """Radiance of rays that leave the scene from a latitude-longitude texture: the image file ``image``
    (``.exr``: its R G B channels, unprefixed or of layer ``default``; ``.png``: sRGB decoded) or the
    baked ``sky``, exactly one of them, times ``scale``."""

    image: str = ""
    sky: Sky | None = None
    scale: float = 1.0

    def __post_init__(self):
        if bool(self.image) == (self.sky is not None):
            raise ValueError(f"EnvironmentMap.image names a file or EnvironmentMap.sky describes a sky, exactly "
                             f"one of them; got image {self.image!r} and sky {self.sky!r}")
        if self.image and not self.image.lower().endswith((".exr", ".png")):
            raise ValueError(f"EnvironmentMap.image must be an .exr or .png file, got {self.image!r}")
        if not (math.isfinite(self.scale) and self.scale >= 0):
            raise ValueError(f"EnvironmentMap.scale must be >= 0, got {self.scale!r}")


@dataclass(frozen=True)
class Medium:
    """A homogeneous participating medium filling the axis-aligned box [``box_min``, ``box_max``] (fog, haze,
    smoke of even density): RGB absorption coefficient ``sigma_a`` and grey scattering coefficient ``sigma_s``
    (per unit length), Henyey-Greenstein phase function of asymmetry ``g`` (> 0 forwards). The box has no
    surface of its own and no index of refraction; surfaces inside it are lit through it (``media.py``).
    ``density`` ``"noise"`` makes it heterogeneous (smoke): both coefficients scaled by ``(1 - noise_amount) +
    noise_amount x`` value noise in [0, 1] of ``noise_cells`` cells across the box, drawn from ``noise_seed``
    (``packing.medium_grid``)."""

    sigma_a: Vec3
    sigma_s: float
    g: float
    box_min: Vec3
    box_max: Vec3
    density: str = "homogeneous"
    noise_cells: int = 3
    noise_amount: float = 1.0
    noise_seed: int = 0

    def __post_init__(self):
        for name in ("sigma_a", "box_min", "box_max"):
            object.__setattr__(self, name, _vec(getattr(self, name), f"Medium.{name}"))
        if min(self.sigma_a) < 0 or not (math.isfinite(self.sigma_s) and self.sigma_s >= 0):
            raise ValueError(f"Medium.sigma_a and Medium.sigma_s must be >= 0, got {self.sigma_a} and "
                             f"{self.sigma_s!r}")
        if not -0.95 <= self.g <= 0.95:
            raise ValueError(f"Medium.g must be in [-0.95, 0.95], got {self.g!r}")
        if self.density not in DENSITIES:
            raise ValueError(f"Medium.density must be one of {', '.join(DENSITIES)}, got {self.density!r}")
        if not is_integer(self.noise_cells) or not 1 <= self.noise_cells <= 8:
            raise ValueError(f"Medium.noise_cells must be an integer in [1, 8], got {self.noise_cells!r}")
        if not 0 <= self.noise_amount <= 1:
            raise ValueError(f"Medium.noise_amount must be in [0, 1], got {self.noise_amount!r}")
        if not is_integer(self.noise_seed) or self.noise_seed < 0:
            raise ValueError(f"Medium.noise_seed must be an integer >= 0, got {self.noise_seed!r}")
        if not all(lo < hi for lo, hi in zip(self.box_min, self.box_max)):
            raise ValueError(f"Medium.box_min must be below Medium.box_max on every axis, got {self.box_min} "
                             f"and {self.box_max}")


def _lists(obj):
    """Tuples to lists, recursively, so a dict equals its JSON round trip."""
    if isinstance(obj, dict):
        return {k: _lists(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_lists(v) for v in obj]
    return obj


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
    environment_zenith: Vec3 | None = None
    seed: int | None = None  # the seed the family was generated from, if any
    meshes: list[Mesh] = field(default_factory=list)
    environment_map: EnvironmentMap | None = None
    medium: Medium | None = None

    def validate(self) -> None:
        """Raise ValueError if an object names an unknown material or the environment is negative."""
        for name in ("environment", "environment_zenith"):
            value = getattr(self, name)
            if value is not None and min(_vec(value, f"Scene.{name}")) < 0:
                raise ValueError(f"Scene.{name} must be >= 0, got {value}")
        if self.environment_map is not None and self._environment_colour():
            raise ValueError(f"Scene.environment must stay black when Scene.environment_map is set (the map is "
                             f"the environment), got environment {self.environment} and zenith "
                             f"{self.environment_zenith}")
        for obj in self._objects():
            if obj.material not in self.materials:
                raise ValueError(f"{self.name}: object {obj} names unknown material {obj.material!r}; "
                                 f"known: {sorted(self.materials)}")

    def _objects(self) -> list:
        return list(self.spheres) + list(self.quads) + list(self.meshes)

    def effects(self) -> frozenset[str]:
        """The effects (names of :data:`EFFECTS`) this scene calls for: the kinds of the materials its
        objects use, ``texture`` if one of them is textured, ``environment`` if the environment is not black,
        ``environment_map`` with a map, ``lens`` for a thin-lens camera, ``mesh`` if the scene has a triangle
        mesh, ``medium`` with a participating medium (and ``heterogeneous`` where its density varies)."""
        used = [self.materials[obj.material] for obj in self._objects()]
        out = {m.kind for m in used}
        if any(m.texture != "none" and m.kind in ("lambert", "plastic") for m in used):
            out.add("texture")
        if self._environment_colour():
            out.add("environment")
        if self.environment_map is not None:
            out.add("environment_map")
        if self.camera.aperture > 0:
            out.add("lens")
        if self.meshes:
            out.add("mesh")
        if self.medium is not None:
            out.add("medium")
            if self.medium.density == "noise":
                out.add("heterogeneous")
        return frozenset(out)

    def _environment_colour(self) -> bool:
        return max(self.environment) > 0 or (self.environment_zenith is not None and max(self.environment_zenith) > 0)

    def to_dict(self) -> dict:
        """A JSON-able description, vectors as lists (inverse: :meth:`from_dict`)."""
        out = _lists({
            "name": self.name,
            "family": self.family,
            "seed": self.seed,
            "camera": asdict(self.camera),
            "environment": list(self.environment),
            "environment_zenith": None if self.environment_zenith is None else list(self.environment_zenith),
            "materials": {k: asdict(m) for k, m in self.materials.items()},
            "spheres": [asdict(s) for s in self.spheres],
            "quads": [asdict(q) for q in self.quads],
        })
        if self.meshes:  # only when there are any: the descriptions of scenes without meshes stay as they were
            out["meshes"] = _lists([asdict(m) for m in self.meshes])
        if self.environment_map is not None:  # likewise
            out["environment_map"] = _lists(asdict(self.environment_map))
        if self.medium is not None:  # likewise
            out["medium"] = _lists(asdict(self.medium))
        return out

    @classmethod
    def from_dict(cls, d: dict) -> Scene:
        return cls(
            name=d["name"], family=d["family"], seed=d.get("seed"),
            camera=Camera(**d["camera"]),
            environment=tuple(d["environment"]),
            environment_zenith=None if d.get("environment_zenith") is None else tuple(d["environment_zenith"]),
            materials={k: Material(**m) for k, m in d["materials"].items()},
            spheres=[Sphere(**s) for s in d["spheres"]],
            quads=[Quad(**q) for q in d["quads"]],
            meshes=[Mesh(**m) for m in d.get("meshes", [])],
            environment_map=_environment_map(d.get("environment_map")),
            medium=None if d.get("medium") is None else Medium(**d["medium"]),
        )


def _environment_map(d: dict | None) -> EnvironmentMap | None:
    if d is None:
        return None
    sky = d.get("sky")
    return EnvironmentMap(**{**d, "sky": None if sky is None else Sky(**sky)})
