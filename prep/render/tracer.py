"""Building blocks of the path tracer that every kernel shares, whatever the effects of its scene:
random numbers, vector algebra, ray-shape intersection over the packed scene (``packing.PackedScene``)
and the GGX microfacet terms. The integrator that puts them together is ``integrator.py``.

Randomness is a counter-based hash of (seed, pixel, sample, dimension), so the output depends on
nothing but the arguments (not on threads or scheduling).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

LAMBERT, GLOSSY, PLASTIC, EMITTER, MIRROR, GLASS = 0, 1, 2, 3, 4, 5  # order of scene.MATERIAL_KINDS
TEX_NONE, TEX_WORLD, TEX_UV, TEX_IMAGE = 0, 1, 2, 3  # order of scene.TEXTURES
# Column layouts of the material, quad, triangle, light and BVH tables and the kinds of lights, mirrored from
# packing.py (MAT_*, QUAD_COLS, TRI_*, LIGHT_*, BVH_*) rather than imported, so that numba's cache of this file
# cannot hold stale copies; a test checks they agree.
M_KIND, M_ALBEDO, M_SPECULAR, M_ROUGHNESS, M_EMISSION = 0, 1, 4, 7, 8
M_TEXTURE, M_ALBEDO2, M_SCALE, M_IOR = 11, 12, 15, 16
Q_CORNER, Q_U, Q_V, Q_NORMAL, Q_DUAL_U, Q_DUAL_V, Q_AREA = 0, 3, 6, 9, 12, 15, 18
T_V0, T_E1, T_E2, T_NORMAL, T_AREA = 0, 3, 6, 9, 12
L_QUAD, L_SPHERE, L_TRIANGLE, L_ENVIRONMENT = 0, 1, 2, 3
L_A, L_B, L_C, L_NORMAL, L_AREA, L_EMISSION = 0, 3, 6, 9, 12, 13
B_LEFT, B_RIGHT, B_IS_LEAF, B_FIRST, B_COUNT = 0, 1, 2, 0, 1
BVH_STACK = 64  # > packing.BVH_MAX_DEPTH: the traversal pushes at most one node per level

# Spawned rays start this far off the surface along the shading normal; scenes are a few units big.
RAY_OFFSET = 1e-4
T_MIN = 1e-7
INV_PI = 1.0 / math.pi
# Random dimensions used per bounce (light pick, 2 for the light point, lobe pick, 2 for the
# direction, roulette) plus 2 for the pixel jitter; the lens point uses two dimensions of its own.
DIMS_PER_BOUNCE = 8
LENS_DIM = 1 << 40

# Channel layout of the per-sample vector and of the kernel output.
N_SAMPLE = 16  # diffuse 0:3, specular 3:6, albedo 6:9, normal 9:12, depth 12, default 13:16
OUT_MEANS = 13  # out[..., 0:13] = means of the first 13 sample channels
OUT_VARS = 6  # out[..., 13:19] = variance of the mean: diffuse, specular, colour, albedo, normal, depth
N_OUT = OUT_MEANS + OUT_VARS

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_K_PIX = np.uint64(0xD1B54A32D192ED03)
_K_SAMPLE = np.uint64(0x8CB92BA72F3D8DD7)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV_2_53 = 1.0 / 9007199254740992.0


# ---------------------------------------------------------------------------------------------
# random numbers
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def mix64(z):
    """splitmix64 finaliser: a bijective 64-bit hash (uint64 arithmetic wraps)."""
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True)
def sample_key(seed, pixel, sample):
    """Key of one pixel sample; seed is uint64, pixel and sample are ints >= 0."""
    k = mix64(seed ^ _GOLDEN)
    k = mix64(k + np.uint64(pixel) * _K_PIX)
    return mix64(k + np.uint64(sample) * _K_SAMPLE)


@njit(cache=True)
def rand(key, dim):
    """Uniform float64 in [0, 1) for dimension ``dim`` of the sample with ``key``."""
    return float(mix64(key + np.uint64(dim) * _GOLDEN) >> _S11) * _INV_2_53


# ---------------------------------------------------------------------------------------------
# vectors as 3-tuples
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def _add(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


@njit(cache=True)
def _sub(a, b):
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


@njit(cache=True)
def _mul(a, b):
    return (a[0] * b[0], a[1] * b[1], a[2] * b[2])


@njit(cache=True)
def _scale(a, s):
    return (a[0] * s, a[1] * s, a[2] * s)


@njit(cache=True)
def _madd(a, b, s):
    """a + b * s"""
    return (a[0] + b[0] * s, a[1] + b[1] * s, a[2] + b[2] * s)


@njit(cache=True)
def _normalize(a):
    inv = 1.0 / math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return (a[0] * inv, a[1] * inv, a[2] * inv)


@njit(cache=True)
def _row3(arr, i, j):
    return (arr[i, j], arr[i, j + 1], arr[i, j + 2])


@njit(cache=True)
def _luminance(c):
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


@njit(cache=True)
def _onb(n):
    """Two tangents completing the unit normal n (Duff et al. 2017, branchless)."""
    sign = math.copysign(1.0, n[2])
    a = -1.0 / (sign + n[2])
    b = n[0] * n[1] * a
    t = (1.0 + sign * n[0] * n[0] * a, sign * b, -sign * n[0])
    s = (b, sign + n[1] * n[1] * a, -n[1])
    return t, s


@njit(cache=True)
def _to_world(local, n):
    t, s = _onb(n)
    return (t[0] * local[0] + s[0] * local[1] + n[0] * local[2],
            t[1] * local[0] + s[1] * local[1] + n[1] * local[2],
            t[2] * local[0] + s[2] * local[1] + n[2] * local[2])


# ---------------------------------------------------------------------------------------------
# geometry
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _sphere_t(o, d, tmax, spheres, i):
    """Distance along o + t d (d unit) to the nearest crossing of sphere i in (T_MIN, tmax), else -1."""
    ocx = spheres[i, 0] - o[0]
    ocy = spheres[i, 1] - o[1]
    ocz = spheres[i, 2] - o[2]
    b = ocx * d[0] + ocy * d[1] + ocz * d[2]
    c = ocx * ocx + ocy * ocy + ocz * ocz - spheres[i, 3] * spheres[i, 3]
    disc = b * b - c
    if disc <= 0.0:
        return -1.0
    sq = math.sqrt(disc)
    t = b - sq
    if t <= T_MIN:
        t = b + sq
    if T_MIN < t < tmax:
        return t
    return -1.0


@njit(cache=True, inline="always")
def _quad_t(o, d, tmax, quads, i):
    """Distance along o + t d (d unit) to quad i if in (T_MIN, tmax), else -1. (Columns as Q_*,
    spelled out: this is the innermost loop.)"""
    denom = quads[i, 9] * d[0] + quads[i, 10] * d[1] + quads[i, 11] * d[2]
    if abs(denom) < 1e-12:
        return -1.0
    qx = quads[i, 0] - o[0]
    qy = quads[i, 1] - o[1]
    qz = quads[i, 2] - o[2]
    t = (qx * quads[i, 9] + qy * quads[i, 10] + qz * quads[i, 11]) / denom
    if t <= T_MIN or t >= tmax:
        return -1.0
    px = t * d[0] - qx
    py = t * d[1] - qy
    pz = t * d[2] - qz
    a = px * quads[i, 12] + py * quads[i, 13] + pz * quads[i, 14]
    if a < 0.0 or a > 1.0:
        return -1.0
    b = px * quads[i, 15] + py * quads[i, 16] + pz * quads[i, 17]
    if b < 0.0 or b > 1.0:
        return -1.0
    return t


@njit(cache=True, inline="always")
def _bound_hit(o, d, tmax, bounds, g):
    """Whether the ray's (T_MIN, tmax) segment can touch bounding sphere g (conservative)."""
    ocx = bounds[g, 0] - o[0]
    ocy = bounds[g, 1] - o[1]
    ocz = bounds[g, 2] - o[2]
    b = ocx * d[0] + ocy * d[1] + ocz * d[2]
    c = ocx * ocx + ocy * ocy + ocz * ocz - bounds[g, 3] * bounds[g, 3]
    disc = b * b - c
    if disc < 0.0:
        return False
    sq = math.sqrt(disc)
    return b + sq > T_MIN and b - sq < tmax


@njit(cache=True)
def intersect(o, d, tmax, sc):
    """Closest hit in (T_MIN, tmax) of the ray o + t d (d unit) in the packed scene ``sc``: (t, kind,
    index); kind 0 sphere, 1 quad, -1 miss."""
    spheres, quads, n_single, groups, bounds = sc.spheres, sc.quads, sc.n_single, sc.groups, sc.group_bounds
    best = tmax
    kind = -1
    idx = -1
    for i in range(spheres.shape[0]):
        t = _sphere_t(o, d, best, spheres, i)
        if t > 0.0:
            best = t
            kind = 0
            idx = i
    for i in range(n_single):
        t = _quad_t(o, d, best, quads, i)
        if t > 0.0:
            best = t
            kind = 1
            idx = i
    for g in range(groups.shape[0]):
        if not _bound_hit(o, d, best, bounds, g):
            continue
        for i in range(groups[g, 0], groups[g, 1]):
            t = _quad_t(o, d, best, quads, i)
            if t > 0.0:
                best = t
                kind = 1
                idx = i
    return best, kind, idx


@njit(cache=True)
def occluded(o, d, tmax, sc):
    """Whether anything of the packed scene ``sc`` lies on the ray o + t d for t in (T_MIN, tmax)."""
    spheres, quads, n_single, groups, bounds = sc.spheres, sc.quads, sc.n_single, sc.groups, sc.group_bounds
    for i in range(spheres.shape[0]):
        if _sphere_t(o, d, tmax, spheres, i) > 0.0:
            return True
    for i in range(n_single):
        if _quad_t(o, d, tmax, quads, i) > 0.0:
            return True
    for g in range(groups.shape[0]):
        if not _bound_hit(o, d, tmax, bounds, g):
            continue
        for i in range(groups[g, 0], groups[g, 1]):
            if _quad_t(o, d, tmax, quads, i) > 0.0:
                return True
    return False


@njit(cache=True, inline="always")
def _triangle_t(o, d, tmax, tris, i):
    """Distance along o + t d to triangle i if in (T_MIN, tmax), else -1 (Moeller-Trumbore; columns as
    T_*, spelled out: this is the innermost loop)."""
    # pvec = d x e2
    px = d[1] * tris[i, 8] - d[2] * tris[i, 7]
    py = d[2] * tris[i, 6] - d[0] * tris[i, 8]
    pz = d[0] * tris[i, 7] - d[1] * tris[i, 6]
    det = tris[i, 3] * px + tris[i, 4] * py + tris[i, 5] * pz
    if det == 0.0:
        return -1.0
    inv = 1.0 / det
    sx = o[0] - tris[i, 0]
    sy = o[1] - tris[i, 1]
    sz = o[2] - tris[i, 2]
    u = (sx * px + sy * py + sz * pz) * inv
    if u < 0.0 or u > 1.0:
        return -1.0
    # qvec = s x e1
    qx = sy * tris[i, 5] - sz * tris[i, 4]
    qy = sz * tris[i, 3] - sx * tris[i, 5]
    qz = sx * tris[i, 4] - sy * tris[i, 3]
    v = (d[0] * qx + d[1] * qy + d[2] * qz) * inv
    if v < 0.0 or u + v > 1.0:
        return -1.0
    t = (tris[i, 6] * qx + tris[i, 7] * qy + tris[i, 8] * qz) * inv
    if T_MIN < t < tmax:
        return t
    return -1.0


@njit(cache=True, inline="always")
def _box_t(o, inv, tmax, bounds, n):
    """Where the ray o + t d (inv = 1 / d per axis, a huge finite value for a zero component) enters BVH
    node n's box within [0, tmax); -1 if it misses the box there."""
    t0 = 0.0
    t1 = tmax
    for a in range(3):
        ta = (bounds[n, a] - o[a]) * inv[a]
        tb = (bounds[n, a + 3] - o[a]) * inv[a]
        if ta > tb:
            ta, tb = tb, ta
        if ta > t0:
            t0 = ta
        if tb < t1:
            t1 = tb
    if t0 <= t1:
        return t0
    return -1.0


@njit(cache=True, inline="always")
def _inverse(d):
    """1 / d per axis, with a huge finite value (not inf: no 0 * inf) for a zero component."""
    return (1.0 / d[0] if d[0] != 0.0 else 1e300, 1.0 / d[1] if d[1] != 0.0 else 1e300,
            1.0 / d[2] if d[2] != 0.0 else 1e300)


@njit(cache=True, inline="always")
def intersect_mesh(o, d, tmax, sc):
    """Closest triangle hit in (T_MIN, tmax) of the ray o + t d over the meshes of ``sc`` (BVH traversal,
    nearer child first, with a fixed stack): (t, triangle index), (tmax, -1) on a miss."""
    # inlined, so that the call below passes three arrays rather than the whole packed scene
    return _intersect_bvh(o, d, tmax, sc.triangles, sc.bvh_bounds, sc.bvh_nodes)


@njit(cache=True, inline="always")
def occluded_mesh(o, d, tmax, sc):
    """Whether a triangle of the meshes of ``sc`` lies on the ray o + t d for t in (T_MIN, tmax)."""
    return _occluded_bvh(o, d, tmax, sc.triangles, sc.bvh_bounds, sc.bvh_nodes)


@njit(cache=True)
def _intersect_bvh(o, d, tmax, tris, bounds, nodes):
    """intersect_mesh over the triangle table and BVH arrays."""
    best = tmax
    hit = -1
    if nodes.shape[0] == 0:
        return best, hit
    inv = _inverse(d)
    if _box_t(o, inv, best, bounds, 0) < 0.0:
        return best, hit
    stack = np.empty(BVH_STACK, dtype=np.int64)
    stack_t = np.empty(BVH_STACK, dtype=np.float64)
    sp = 0
    node = 0
    while True:
        if nodes[node, B_IS_LEAF] != 0:
            first = nodes[node, B_FIRST]
            for i in range(first, first + nodes[node, B_COUNT]):
                t = _triangle_t(o, d, best, tris, i)
                if t > 0.0:
                    best = t
                    hit = i
            node = -1
        else:
            left = nodes[node, B_LEFT]
            right = nodes[node, B_RIGHT]
            tl = _box_t(o, inv, best, bounds, left)
            tr = _box_t(o, inv, best, bounds, right)
            if tl >= 0.0 and tr >= 0.0:
                if tr < tl:
                    left, right = right, left
                    tl, tr = tr, tl
                stack[sp] = right
                stack_t[sp] = tr
                sp += 1
                node = left
            elif tl >= 0.0:
                node = left
            elif tr >= 0.0:
                node = right
            else:
                node = -1
        while node < 0 and sp > 0:  # the next pushed node the ray can still reach before its best hit
            sp -= 1
            if stack_t[sp] <= best:
                node = stack[sp]
        if node < 0:
            return best, hit


@njit(cache=True)
def _occluded_bvh(o, d, tmax, tris, bounds, nodes):
    """occluded_mesh over the triangle table and BVH arrays."""
    if nodes.shape[0] == 0:
        return False
    inv = _inverse(d)
    if _box_t(o, inv, tmax, bounds, 0) < 0.0:  # before the stack is allocated: most rays stop here
        return False
    stack = np.empty(BVH_STACK, dtype=np.int64)
    stack[0] = 0
    sp = 1
    while sp > 0:
        sp -= 1
        node = stack[sp]
        if node != 0 and _box_t(o, inv, tmax, bounds, node) < 0.0:
            continue
        if nodes[node, B_IS_LEAF] != 0:
            first = nodes[node, B_FIRST]
            for i in range(first, first + nodes[node, B_COUNT]):
                if _triangle_t(o, d, tmax, tris, i) > 0.0:
                    return True
        else:
            stack[sp] = nodes[node, B_RIGHT]
            stack[sp + 1] = nodes[node, B_LEFT]
            sp += 2
    return False


@njit(cache=True)
def surface(p, kind, idx, spheres, quads, tris):
    """Geometric normal (outward for spheres, cross(u, v) for quads, cross(e1, e2) for triangles) and
    texture coordinates (barycentrics u, v for triangles)."""
    if kind == 2:
        ng = _row3(tris, idx, T_NORMAL)
        e1 = _row3(tris, idx, T_E1)
        e2 = _row3(tris, idx, T_E2)
        q = _sub(p, _row3(tris, idx, T_V0))
        # q = u e1 + v e2 in the triangle's plane: u = q . (e2 x w), v = q . (w x e1), w = n / |n|^2
        nn = (e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2], e1[0] * e2[1] - e1[1] * e2[0])
        w = _scale(nn, 1.0 / _dot(nn, nn))
        du = (e2[1] * w[2] - e2[2] * w[1], e2[2] * w[0] - e2[0] * w[2], e2[0] * w[1] - e2[1] * w[0])
        dv = (w[1] * e1[2] - w[2] * e1[1], w[2] * e1[0] - w[0] * e1[2], w[0] * e1[1] - w[1] * e1[0])
        return ng, _dot(q, du), _dot(q, dv)
    if kind == 0:
        r = spheres[idx, 3]
        ng = ((p[0] - spheres[idx, 0]) / r, (p[1] - spheres[idx, 1]) / r, (p[2] - spheres[idx, 2]) / r)
        ng = _normalize(ng)
        # longitude in [0, 2), latitude in [0, 1]: checks come out square at the equator
        u = math.atan2(ng[2], ng[0]) / math.pi + 1.0
        v = math.acos(min(1.0, max(-1.0, ng[1]))) / math.pi
        return ng, u, v
    ng = _row3(quads, idx, Q_NORMAL)
    q = _sub(p, _row3(quads, idx, Q_CORNER))
    return ng, _dot(q, _row3(quads, idx, Q_DUAL_U)), _dot(q, _row3(quads, idx, Q_DUAL_V))


# ---------------------------------------------------------------------------------------------
# GGX and the plastic's lobe choice (the BSDFs that use them are in integrator.py)
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _ggx_d(nh, a2):
    k = nh * nh * (a2 - 1.0) + 1.0
    return a2 / (math.pi * k * k)


@njit(cache=True)
def _ggx_g1(c, a2):
    return 2.0 * c / (c + math.sqrt(a2 + (1.0 - a2) * c * c))


@njit(cache=True)
def ggx_visible_normal(wo, n, alpha, u1, u2):
    """A microfacet normal drawn from the GGX normals visible from wo (unit, above the surface with unit
    normal n), density D_wo(h) = G1(wo) max(0, wo.h) D(h) / (n.wo) (Heitz 2018, "Sampling the GGX
    distribution of visible normals"): every h faces wo, so no sample is wasted on a back-facing normal and
    the weight f cos / pdf of the lobe is F G1(wi) <= 1 rather than unbounded at grazing angles."""
    t, s = _onb(n)
    # wo in the frame (t, s, n), stretched to the hemisphere configuration of roughness 1
    vh = _normalize((alpha * _dot(wo, t), alpha * _dot(wo, s), _dot(wo, n)))
    lensq = vh[0] * vh[0] + vh[1] * vh[1]
    if lensq > 0.0:
        inv = 1.0 / math.sqrt(lensq)
        t1 = (-vh[1] * inv, vh[0] * inv, 0.0)
    else:
        t1 = (1.0, 0.0, 0.0)
    t2 = (vh[1] * t1[2] - vh[2] * t1[1], vh[2] * t1[0] - vh[0] * t1[2], vh[0] * t1[1] - vh[1] * t1[0])
    # a point of the disc, warped to the visible half of the projected hemisphere
    r = math.sqrt(u1)
    phi = 2.0 * math.pi * u2
    p1 = r * math.cos(phi)
    p2 = r * math.sin(phi)
    w = 0.5 * (1.0 + vh[2])
    p2 = (1.0 - w) * math.sqrt(max(0.0, 1.0 - p1 * p1)) + w * p2
    pz = math.sqrt(max(0.0, 1.0 - p1 * p1 - p2 * p2))
    nh = (p1 * t1[0] + p2 * t2[0] + pz * vh[0], p1 * t1[1] + p2 * t2[1] + pz * vh[1],
          p1 * t1[2] + p2 * t2[2] + pz * vh[2])
    # unstretched back to roughness alpha, and out of the local frame
    local = _normalize((alpha * nh[0], alpha * nh[1], max(1e-12, nh[2])))
    return _to_world(local, n)


@njit(cache=True)
def _plastic_spec_prob(kd, ks, cos_o):
    """Probability of sampling the coat of a plastic: its Fresnel weight against the base's."""
    f0 = _luminance(ks)
    fo = f0 + (1.0 - f0) * (1.0 - cos_o) ** 5
    p = fo / (fo + _luminance(kd) * (1.0 - fo) + 1e-12)
    return min(0.85, max(0.15, p))




# ---------------------------------------------------------------------------------------------
# discrete sampling and the environment map (the mapping and tables of environment.py)
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def search_cdf(cdf, u):
    """The first index k with u < cdf[k] (the last index if there is none): the entry a uniform u picks
    from a table with cumulative probabilities ``cdf`` (non-decreasing), by bisection, since emissive meshes
    bring thousands of lights and a map a row per texel row. It returns exactly what the scan ``while k < n - 1
    and u >= cdf[k]: k += 1`` would (neither reads the last entry)."""
    lo = 0
    hi = cdf.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if u < cdf[mid]:
            hi = mid
        else:
            lo = mid + 1
    return lo


@njit(cache=True)
def env_texel(sc, d):
    """(row, column) of the environment map's texel in unit direction d."""
    height, width = sc.env_pdf.shape
    theta = math.acos(min(1.0, max(-1.0, d[1])))
    phi = math.atan2(d[2], d[0])
    row = min(int(theta * INV_PI * height), height - 1)
    col = min(int((phi + math.pi) * (0.5 * INV_PI) * width), width - 1)
    return row, col


@njit(cache=True)
def _env_density(sc, row, col, sin_t):
    """Solid-angle density of env_sample at a direction in texel (row, col) with sin theta = sin_t."""
    if sin_t <= 0.0:
        return 0.0
    return sc.env_pdf[row, col] / (2.0 * math.pi * math.pi * sin_t)


@njit(cache=True)
def env_lookup(sc, d):
    """(radiance of the environment map in unit direction d, solid-angle density with which env_sample
    draws d): one texel lookup serves both."""
    row, col = env_texel(sc, d)
    pdf = _env_density(sc, row, col, math.sqrt(max(0.0, 1.0 - d[1] * d[1])))
    return _row3(sc.env_map, row * sc.env_pdf.shape[1] + col, 0), pdf


@njit(cache=True)
def env_sample(sc, u1, u2):
    """A direction drawn in proportion to texel luminance x solid angle, uniform in (theta, phi) within
    its texel: (direction, solid-angle density, radiance)."""
    height, width = sc.env_pdf.shape
    row = search_cdf(sc.env_row_cdf, u1)
    lo = sc.env_row_cdf[row - 1] if row > 0 else 0.0
    fr = (u1 - lo) / (sc.env_row_cdf[row] - lo)
    cdf = sc.env_col_cdf[row]
    col = search_cdf(cdf, u2)
    lo = cdf[col - 1] if col > 0 else 0.0
    fc = (u2 - lo) / (cdf[col] - lo)
    theta = (row + min(max(fr, 0.0), 1.0)) * math.pi / height
    phi = (col + min(max(fc, 0.0), 1.0)) * 2.0 * math.pi / width - math.pi
    sin_t = math.sin(theta)
    d = (sin_t * math.cos(phi), math.cos(theta), sin_t * math.sin(phi))
    return d, _env_density(sc, row, col, sin_t), _row3(sc.env_map, row * width + col, 0)


# ---------------------------------------------------------------------------------------------
# smooth dielectric
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def fresnel_dielectric(cos_i, eta):
    """(unpolarised Fresnel reflectance, cosine of the refracted direction) for light arriving at
    cos_i > 0 from a medium with eta = n_incident / n_transmitted; reflectance 1 under total internal
    reflection."""
    sin2_t = eta * eta * max(0.0, 1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0, 0.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return 0.5 * (rs * rs + rp * rp), cos_t


@njit(cache=True)
def reflect(d, n):
    """The mirror direction of d (travelling towards the surface) about the unit normal n."""
    return _madd(d, n, -2.0 * _dot(d, n))


@njit(cache=True)
def refract(d, n, eta, cos_i, cos_t):
    """The refracted direction of unit d through the surface with unit normal n facing d's origin."""
    return _normalize(_madd(_scale(d, eta), n, eta * cos_i - cos_t))
