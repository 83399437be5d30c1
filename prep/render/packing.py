"""A :class:`~prep.render.scene.Scene` packed into the one typed structure the kernels take.

:func:`pack` flattens a scene into a :class:`PackedScene`, a named tuple of arrays and scalars that numba
passes to the kernels as one argument (``sc.quads``, ``sc.materials``, ...). This module owns the row
layouts of the tables; ``tracer.py`` mirrors the column numbers (a test checks they agree).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from prep.render.environment import load_image, load_texels, sampling_tables
from prep.render.scene import MATERIAL_KINDS, TEXTURES, Scene, _luminance, _vec, triangle_areas

# Layout of one row of the material table handed to the kernels (see tracer.py).
MAT_KIND, MAT_ALBEDO, MAT_SPECULAR, MAT_ROUGHNESS = 0, 1, 4, 7
MAT_EMISSION, MAT_TEXTURE, MAT_ALBEDO2, MAT_SCALE = 8, 11, 12, 15
MAT_IOR = 16
MAT_COLS = 17
# Layout of one row of the quad table: corner, u, v, unit normal, dual vectors of u and v, area.
QUAD_COLS = 19
# Layout of one row of the triangle table: v0, e1 = v1 - v0, e2 = v2 - v0, unit normal normalize(cross(e1, e2)),
# area.
TRI_V0, TRI_E1, TRI_E2, TRI_NORMAL, TRI_AREA = 0, 3, 6, 9, 12
TRI_COLS = 13
# light_kind of each entry of the light list; the list holds the quads, then the spheres, then the triangles,
# then the environment map.
LIGHT_QUAD, LIGHT_SPHERE, LIGHT_TRIANGLE, LIGHT_ENVIRONMENT = 0, 1, 2, 3
# Layout of one row of the light table, what light sampling reads of a light of any kind, copied from its own
# table: a quad's corner, u, v or a triangle's v0, e1, e2 (a sphere's centre, and its radius at LIGHT_B), the
# unit normal and area of a planar light, and the radiance its material emits (zeros for the environment map).
LIGHT_A, LIGHT_B, LIGHT_C, LIGHT_NORMAL, LIGHT_AREA, LIGHT_EMISSION = 0, 3, 6, 9, 12, 13
LIGHT_COLS = 16
# The BVH over the triangles: node bounds (min x y z, max x y z) and links; an inner node's children are
# nodes [BVH_LEFT] and [BVH_RIGHT], a leaf holds triangles [BVH_FIRST, BVH_FIRST + BVH_COUNT). Node 0 is
# the root. Leaves hold at most BVH_LEAF_SIZE triangles; the tree is at most BVH_MAX_DEPTH deep (the
# traversal's fixed stack in tracer.py has room for that).
BVH_LEFT, BVH_RIGHT, BVH_IS_LEAF = 0, 1, 2
BVH_FIRST, BVH_COUNT = 0, 1
BVH_LEAF_SIZE = 4
BVH_MAX_DEPTH = 60
# The participating medium (media.py mirrors the columns): absorption RGB, scattering, HG asymmetry, the box's
# low and high corners, the majorant of sigma_t x density (0 for a homogeneous medium); all zeros (an empty box at
# the origin) without a medium. A heterogeneous one's density is a MEDIUM_GRID^3 grid of lattice points over the box.
MEDIUM_SIGMA_A, MEDIUM_SIGMA_S, MEDIUM_G, MEDIUM_LO, MEDIUM_HI, MEDIUM_MAJORANT = 0, 3, 4, 5, 8, 11
MEDIUM_COLS = 12
MEDIUM_GRID = 32
_SAH_BINS = 12
_SAH_DEPTH = 40  # below this depth splits are at the median, which bounds the depth by ~log2(triangles)


class PackedScene(NamedTuple):
    """The flat arrays (and scalars) of a scene, in the layouts above."""

    spheres: np.ndarray  # (Ns, 4) centre, radius
    sphere_mat: np.ndarray  # (Ns,) int64
    quads: np.ndarray  # (Nq, QUAD_COLS)
    quad_mat: np.ndarray  # (Nq,) int64
    quad_light: np.ndarray  # (Nq,) int64, index into lights or -1
    n_single: int  # quads[:n_single] are tested one by one
    groups: np.ndarray  # (Ng, 2) int64 [start, end) ranges of the other quads
    group_bounds: np.ndarray  # (Ng, 4) bounding sphere (centre, radius) of each range
    materials: np.ndarray  # (Nm, MAT_COLS)
    sphere_light: np.ndarray  # (Ns,) int64, index into lights or -1
    lights: np.ndarray  # (Nl,) int64 index of each light in its table (in the order of LIGHT_*)
    light_kind: np.ndarray  # (Nl,) int64: LIGHT_*
    light_table: np.ndarray  # (Nl, LIGHT_COLS)
    light_cdf: np.ndarray  # (Nl,) cumulative selection probability
    light_prob: np.ndarray  # (Nl,) selection probability (proportional to power)
    camera: np.ndarray  # (12,) see Camera.frame
    tan_half: float  # tan(vertical field of view / 2)
    lens_radius: float  # 0 for a pinhole
    focus_distance: float  # along the view direction
    environment: np.ndarray  # (3,) radiance towards the horizon
    environment_zenith: np.ndarray  # (3,) radiance straight up (= environment when constant)
    image_pixels: np.ndarray  # (Np, 3) linear texels of every image texture, row by row
    image_info: np.ndarray  # (Nm, 3) int64 per material: first texel, width, height (0s without an image)
    triangles: np.ndarray  # (Nt, TRI_COLS) the triangles of every mesh, in BVH leaf order
    tri_mat: np.ndarray  # (Nt,) int64
    tri_light: np.ndarray  # (Nt,) int64, index into lights or -1
    bvh_bounds: np.ndarray  # (Nn, 6) float64 node bounds
    bvh_nodes: np.ndarray  # (Nn, 3) int64 node links (BVH_*)
    env_map: np.ndarray  # (H * W, 3) radiance texels of the environment map, row by row; (0, 3) without one
    env_pdf: np.ndarray  # (H, W) sampling density over the unit square (environment.sampling_tables)
    env_row_cdf: np.ndarray  # (H,)
    env_col_cdf: np.ndarray  # (H, W)
    env_light: int  # index of the map in lights, -1 without one (or for a black one)
    medium: np.ndarray  # (MEDIUM_COLS,) the participating medium (MEDIUM_*)
    medium_grid: np.ndarray  # (G, G, G) density of a heterogeneous medium; (0, 0, 0) otherwise


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


def _split(lo, hi, cen, idx, depth):
    """Split the triangles ``idx`` (more than a leaf holds) in two non-empty parts: binned SAH along the
    longest axis of their centroids, the median along it where SAH finds nothing or the tree is deep."""
    c = cen[idx]
    cmin, cmax = c.min(axis=0), c.max(axis=0)
    axis = int(np.argmax(cmax - cmin))
    extent = cmax[axis] - cmin[axis]
    if extent > 0 and depth < _SAH_DEPTH:
        bins = np.minimum(((c[:, axis] - cmin[axis]) / extent * _SAH_BINS).astype(np.int64), _SAH_BINS - 1)
        counts = np.bincount(bins, minlength=_SAH_BINS)
        blo = np.full((_SAH_BINS, 3), np.inf)
        bhi = np.full((_SAH_BINS, 3), -np.inf)
        np.minimum.at(blo, bins, lo[idx])
        np.maximum.at(bhi, bins, hi[idx])

        def areas(lo_, hi_):
            d = np.maximum(hi_ - lo_, 0.0)
            return d[:, 0] * d[:, 1] + d[:, 1] * d[:, 2] + d[:, 2] * d[:, 0]

        left_lo, left_hi = np.minimum.accumulate(blo), np.maximum.accumulate(bhi)
        right_lo = np.minimum.accumulate(blo[::-1])[::-1]
        right_hi = np.maximum.accumulate(bhi[::-1])[::-1]
        n_left = np.cumsum(counts)
        with np.errstate(invalid="ignore"):
            cost = (n_left[:-1] * areas(left_lo[:-1], left_hi[:-1])
                    + (len(idx) - n_left[:-1]) * areas(right_lo[1:], right_hi[1:]))
        cost = np.where((n_left[:-1] > 0) & (n_left[:-1] < len(idx)), cost, np.inf)
        k = int(np.argmin(cost))
        if np.isfinite(cost[k]):
            mask = bins <= k
            return idx[mask], idx[~mask]
    order = idx[np.argsort(c[:, axis], kind="stable")]
    half = len(order) // 2
    return order[:half], order[half:]


def build_bvh(v0: np.ndarray, v1: np.ndarray, v2: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A BVH over the triangles (v0, v1, v2) (each (Nt, 3)): (order of the triangles in the leaves,
    node bounds (Nn, 6), node links (Nn, 3)) in the layout of ``BVH_*``. Bounds are widened by a hair so
    that a flat node (an axis-aligned face) cannot be missed by rounding."""
    lo = np.minimum(np.minimum(v0, v1), v2)
    hi = np.maximum(np.maximum(v0, v1), v2)
    cen = (lo + hi) / 2
    pad = 1e-9 * (max(np.abs(lo).max(), np.abs(hi).max()) + 1.0)  # one pad for all: children nest exactly
    bounds, links, order = [None], [None], []
    stack = [(0, np.arange(len(v0)), 0)]
    while stack:
        node, idx, depth = stack.pop()
        nlo, nhi = lo[idx].min(axis=0), hi[idx].max(axis=0)
        bounds[node] = np.concatenate([nlo - pad, nhi + pad])
        if len(idx) <= BVH_LEAF_SIZE:
            links[node] = (len(order), len(idx), 1)
            order.extend(idx.tolist())
            continue
        if depth >= BVH_MAX_DEPTH:  # cannot happen below ~2**(BVH_MAX_DEPTH - _SAH_DEPTH) triangles
            raise ValueError(f"BVH deeper than {BVH_MAX_DEPTH} levels over {len(v0)} triangles")
        left, right = _split(lo, hi, cen, idx, depth)
        links[node] = (len(links), len(links) + 1, 0)
        bounds += [None, None]
        links += [None, None]
        stack.append((links[node][1], right, depth + 1))
        stack.append((links[node][0], left, depth + 1))
    return (np.asarray(order, dtype=np.int64), np.asarray(bounds, dtype=np.float64).reshape(-1, 6),
            np.asarray(links, dtype=np.int64).reshape(-1, 3))


def pack_images(scene: Scene) -> tuple[np.ndarray, np.ndarray]:
    """Every image texture's texels in one table, and per material (first texel, width, height)."""
    info = np.zeros((max(len(scene.materials), 1), 3), dtype=np.int64)
    chunks, loaded, count = [], {}, 0
    for i, m in enumerate(scene.materials.values()):
        if m.texture != "image":
            continue
        if m.image not in loaded:
            image = load_image(m.image)
            loaded[m.image] = (count, image.shape[1], image.shape[0])
            chunks.append(image.reshape(-1, 3))
            count += image.shape[0] * image.shape[1]
        info[i] = loaded[m.image]
    pixels = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    return np.ascontiguousarray(pixels, dtype=np.float64), info


def pack_meshes(scene: Scene, index: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The triangles of every mesh of ``scene`` (degenerate ones dropped) in BVH leaf order, their
    material indices, and the BVH: (triangles, tri_mat, bvh_bounds, bvh_nodes); empty arrays of the same
    dtypes and dimensions without meshes."""
    tris, mats = [], []
    for mesh in scene.meshes:
        v, f = mesh.arrays()
        f = f[triangle_areas(v, f) > 0]
        tris.append(np.stack([v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]], axis=1))
        mats.append(np.full(len(f), index[mesh.material], dtype=np.int64))
    if not tris:
        return (np.zeros((0, TRI_COLS)), np.zeros(0, dtype=np.int64), np.zeros((0, 6)),
                np.zeros((0, 3), dtype=np.int64))
    tri = np.concatenate(tris)
    mat = np.concatenate(mats)
    order, bounds, nodes = build_bvh(tri[:, 0], tri[:, 1], tri[:, 2])
    tri, mat = tri[order], mat[order]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    twice_area = np.linalg.norm(n, axis=1, keepdims=True)
    table = np.ascontiguousarray(np.concatenate([tri[:, 0], e1, e2, n / twice_area, twice_area / 2], axis=1))
    return table, np.ascontiguousarray(mat), bounds, nodes


def pack(scene: Scene) -> PackedScene:
    """Flatten ``scene`` (validated first) into a :class:`PackedScene`."""
    scene.validate()
    mats, index = pack_materials(scene)
    spheres = np.array([[*s.center, s.radius] for s in scene.spheres], dtype=np.float64).reshape(-1, 4)
    sphere_mat = np.array([index[s.material] for s in scene.spheres], dtype=np.int64)
    lights = _Lights()
    quads, quad_mat, quad_light, n_single, groups, bounds = _pack_quads(scene, index, lights)
    sphere_light = np.full(len(scene.spheres), -1, dtype=np.int64)
    for i, sp in enumerate(scene.spheres):
        lum = _emitted_luminance(scene.materials[sp.material])
        if lum > 0:
            sphere_light[i] = lights.add(i, LIGHT_SPHERE, 4.0 * math.pi * sp.radius**2 * lum)
    # triangles last, indexed in the table's (BVH leaf) order, which the kernels see
    triangles, tri_mat, bvh_bounds, bvh_nodes = pack_meshes(scene, index)
    lum = np.array([_emitted_luminance(m) for m in scene.materials.values()])
    emitting = np.flatnonzero(lum[tri_mat] > 0)
    tri_light = np.full(len(triangles), -1, dtype=np.int64)
    tri_light[emitting] = lights.extend(emitting, LIGHT_TRIANGLE,
                                        triangles[emitting, TRI_AREA] * lum[tri_mat[emitting]])
    env_map, env_pdf, env_row_cdf, env_col_cdf, env_light = _pack_environment_map(scene, lights)
    prob, cdf = lights.selection()
    image_pixels, image_info = pack_images(scene)
    return PackedScene(
        spheres=spheres, sphere_mat=sphere_mat, quads=quads, quad_mat=quad_mat, quad_light=quad_light,
        n_single=n_single, groups=groups, group_bounds=bounds, materials=mats,
        sphere_light=sphere_light, lights=np.asarray(lights.index, dtype=np.int64),
        light_kind=np.asarray(lights.kinds, dtype=np.int64), light_cdf=cdf, light_prob=prob,
        light_table=lights.table(mats, quads, quad_mat, spheres, sphere_mat, triangles, tri_mat),
        camera=scene.camera.frame(), tan_half=math.tan(math.radians(scene.camera.fov) / 2),
        lens_radius=float(scene.camera.aperture), focus_distance=scene.camera.focus,
        environment=np.asarray(_vec(scene.environment, "environment")),
        environment_zenith=np.asarray(_vec(scene.environment if scene.environment_zenith is None
                                           else scene.environment_zenith, "environment_zenith")),
        image_pixels=image_pixels, image_info=image_info,
        triangles=triangles, tri_mat=tri_mat, tri_light=tri_light, bvh_bounds=bvh_bounds, bvh_nodes=bvh_nodes,
        env_map=env_map, env_pdf=env_pdf, env_row_cdf=env_row_cdf, env_col_cdf=env_col_cdf, env_light=env_light,
        medium=pack_medium(scene), medium_grid=medium_grid(scene.medium),
    )


def pack_medium(scene: Scene) -> np.ndarray:
    """The row of ``sc.medium`` (``MEDIUM_*``): zeros without a medium."""
    out = np.zeros(MEDIUM_COLS, dtype=np.float64)
    m = scene.medium
    if m is not None:
        out[MEDIUM_SIGMA_A:MEDIUM_SIGMA_A + 3] = m.sigma_a
        out[MEDIUM_SIGMA_S], out[MEDIUM_G] = m.sigma_s, m.g
        out[MEDIUM_LO:MEDIUM_LO + 3], out[MEDIUM_HI:MEDIUM_HI + 3] = m.box_min, m.box_max
        if m.density == "noise":
            out[MEDIUM_MAJORANT] = (max(m.sigma_a) + m.sigma_s) * medium_grid(m).max()
    return out


def _upsample(a: np.ndarray, n: int) -> np.ndarray:
    """The lattice ``a`` (k^3 values) linearly interpolated to n^3 points spanning the same cube."""
    for axis in range(3):
        k = a.shape[axis]
        x = np.linspace(0, k - 1, n)
        i = np.minimum(x.astype(int), k - 2)
        f = (x - i).reshape([-1 if ax == axis else 1 for ax in range(3)])
        a = np.take(a, i, axis=axis) * (1 - f) + np.take(a, i + 1, axis=axis) * f
    return a


def medium_grid(medium) -> np.ndarray:
    """The density grid of a heterogeneous medium: (1 - noise_amount) + noise_amount x value noise in [0, 1]
    (three octaves of random lattices from noise_seed, noise_cells cells across the box at the coarsest,
    interpolated to MEDIUM_GRID^3 points); an empty grid for none or a homogeneous one."""
    if medium is None or medium.density != "noise":
        return np.zeros((0, 0, 0))
    rng = np.random.default_rng([int(medium.noise_seed), 0x6D656469])
    noise = sum(_upsample(rng.random((c + 1,) * 3), MEDIUM_GRID) * 0.5 ** o
                for o, c in enumerate(medium.noise_cells * 2 ** np.arange(3)))
    noise = (noise - noise.min()) / max(noise.max() - noise.min(), 1e-12)
    return (1.0 - medium.noise_amount) + medium.noise_amount * noise


class _Lights:
    """The light list as :func:`pack` builds it, in the order of ``LIGHT_*``: each light's index in its table,
    its kind and its power (what picks it)."""

    def __init__(self):
        self.index, self.kinds, self.powers = [], [], []

    def add(self, index: int, kind: int, power: float) -> int:
        """Append a light; its index in the list."""
        self.index.append(index)
        self.kinds.append(kind)
        self.powers.append(power)
        return len(self.index) - 1

    def extend(self, index: np.ndarray, kind: int, powers: np.ndarray) -> np.ndarray:
        """Append lights of one kind; their indices in the list."""
        first = len(self.index)
        self.index.extend(index.tolist())
        self.kinds.extend([kind] * len(index))
        self.powers.extend(powers.tolist())
        return first + np.arange(len(index))

    def table(self, materials, quads, quad_mat, spheres, sphere_mat, triangles, tri_mat) -> np.ndarray:
        """The light table (one row of ``LIGHT_*`` per light), from the tables of the quads, spheres and
        triangles and the material of each of their rows: the same float64 values as theirs."""
        kinds, index = np.asarray(self.kinds, dtype=np.int64), np.asarray(self.index, dtype=np.int64)
        table = np.zeros((len(kinds), LIGHT_COLS))
        geometry = {LIGHT_QUAD: quads[:, np.r_[0:12, QUAD_COLS - 1]],  # corner, u, v, normal; area
                    LIGHT_TRIANGLE: triangles, LIGHT_SPHERE: np.pad(spheres, ((0, 0), (0, 9)))}
        for kind, mats in ((LIGHT_QUAD, quad_mat), (LIGHT_TRIANGLE, tri_mat), (LIGHT_SPHERE, sphere_mat)):
            of_kind = kinds == kind
            rows = index[of_kind]
            table[of_kind, :LIGHT_EMISSION] = geometry[kind][rows]
            table[of_kind, LIGHT_EMISSION:] = materials[mats[rows], MAT_EMISSION:MAT_EMISSION + 3]
        return table

    def selection(self) -> tuple[np.ndarray, np.ndarray]:
        """(probability, cumulative probability) of picking each light, in proportion to its power."""
        powers = np.asarray(self.powers, dtype=np.float64)
        prob = powers / powers.sum() if len(powers) else powers
        cdf = np.cumsum(prob)
        if len(cdf):
            cdf[-1] = 1.0
        return prob, cdf


def pack_materials(scene: Scene) -> tuple[np.ndarray, dict]:
    """The material table (one row of ``MAT_*`` per material, in the scene's order; one row of zeros without
    materials) and the row of each material name."""
    names = list(scene.materials)
    index = {n: i for i, n in enumerate(names)}
    mats = np.zeros((max(len(names), 1), MAT_COLS), dtype=np.float64)
    for i, n in enumerate(names):
        m = scene.materials[n]
        mats[i, MAT_KIND] = MATERIAL_KINDS.index(m.kind)
        mats[i, MAT_ALBEDO:MAT_ALBEDO + 3] = m.albedo
        mats[i, MAT_SPECULAR:MAT_SPECULAR + 3] = m.specular
        mats[i, MAT_ROUGHNESS] = m.roughness
        mats[i, MAT_EMISSION:MAT_EMISSION + 3] = m.emission
        mats[i, MAT_TEXTURE] = TEXTURES.index(m.texture)
        mats[i, MAT_ALBEDO2:MAT_ALBEDO2 + 3] = m.albedo2
        mats[i, MAT_SCALE] = m.checker_scale
        mats[i, MAT_IOR] = m.ior
    return mats, index


def _pack_quads(scene: Scene, index: dict, lights: _Lights):
    """The quad table in :func:`_quad_order`, each emitting quad added to ``lights``: (quads, quad_mat,
    quad_light, n_single, groups, group_bounds)."""
    order, n_single, groups, bounds = _quad_order(scene.quads)
    quads = np.zeros((len(scene.quads), QUAD_COLS), dtype=np.float64)
    quad_mat = np.zeros(len(scene.quads), dtype=np.int64)
    quad_light = np.full(len(scene.quads), -1, dtype=np.int64)
    for i, q in enumerate(scene.quads[k] for k in order):
        u, v = np.asarray(q.u), np.asarray(q.v)
        nn = np.cross(u, v)
        w = nn / nn.dot(nn)
        # p - corner = a*u + b*v  =>  a = (p - corner).cross(v, w), b = (p - corner).cross(w, u)
        quads[i] = np.concatenate([q.corner, u, v, nn / np.linalg.norm(nn),
                                   np.cross(v, w), np.cross(w, u), [np.linalg.norm(nn)]])
        quad_mat[i] = index[q.material]
        lum = _emitted_luminance(scene.materials[q.material])
        if lum > 0:
            quad_light[i] = lights.add(i, LIGHT_QUAD, q.area * lum)
    return quads, quad_mat, quad_light, n_single, groups, bounds


def _pack_environment_map(scene: Scene, lights: _Lights):
    """The environment map's texels and sampling tables, the map added to ``lights`` where it is not black:
    (env_map, env_pdf, env_row_cdf, env_col_cdf, env_light); empty tables and -1 without a map."""
    if scene.environment_map is None:
        return np.zeros((0, 3)), np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)), -1
    texels = load_texels(scene.environment_map)
    env_pdf, env_row_cdf, env_col_cdf, mean_lum = sampling_tables(texels)
    env_light = -1
    if mean_lum > 0:
        # an infinitely distant light's power as it reaches the scene: pi R^2 x mean radiance
        env_light = lights.add(0, LIGHT_ENVIRONMENT, math.pi * _bounding_radius(scene) ** 2 * mean_lum)
    return texels.reshape(-1, 3), env_pdf, env_row_cdf, env_col_cdf, env_light


def _emitted_luminance(m) -> float:
    """The luminance a light of material m emits, for picking lights by power (at least 1e-6, so that a
    light of pure blue is still picked); 0 for a material that is not a light."""
    if m.kind != "emitter" or max(m.emission) <= 0:
        return 0.0
    return max(_luminance(m.emission), 1e-6)


def _bounding_radius(scene: Scene) -> float:
    """Half the diagonal of the box around every object of ``scene`` (1 for an empty scene)."""
    points = [np.asarray(s.center) + sign * s.radius for s in scene.spheres for sign in (-1, 1)]
    points += [np.asarray(q.corner) + a * np.asarray(q.u) + b * np.asarray(q.v)
               for q in scene.quads for a in (0, 1) for b in (0, 1)]
    for mesh in scene.meshes:
        points.extend(mesh.arrays()[0])
    if not points:
        return 1.0
    points = np.asarray(points)
    return max(float(np.linalg.norm(points.max(axis=0) - points.min(axis=0))) / 2, 1e-3)

