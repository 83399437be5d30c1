"""numba kernels of the path tracer: plain functions over the flat arrays of ``scene.SceneArrays``.

Unidirectional path tracing with next-event estimation to the rectangle lights (light picked in
proportion to power, uniform area sampling) combined with BSDF sampling by the power heuristic.
Per-sample radiance is split by the lobe of the first scattering vertex: the path throughput after
that vertex is carried as two RGB weights (diffuse part, glossy part) that later vertices scale
alike, so every path's radiance lands exactly in diffuse + specular without a random lobe choice
deciding the split.

Randomness is a counter-based hash of (seed, pixel, sample, dimension), so the output depends on
nothing but the arguments (not on threads or scheduling).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

LAMBERT, GLOSSY, PLASTIC, EMITTER = 0, 1, 2, 3  # order of scene.MATERIAL_KINDS
TEX_NONE, TEX_WORLD, TEX_UV = 0, 1, 2  # order of scene.TEXTURES
# Column layouts of the material and quad tables, mirrored from scene.py (MAT_*, QUAD_COLS) rather than
# imported, so that numba's cache of this file cannot hold stale copies; a test checks they agree.
M_KIND, M_ALBEDO, M_SPECULAR, M_ROUGHNESS, M_EMISSION, M_TEXTURE, M_ALBEDO2, M_SCALE = 0, 1, 4, 7, 8, 11, 12, 15
Q_CORNER, Q_U, Q_V, Q_NORMAL, Q_DUAL_U, Q_DUAL_V, Q_AREA = 0, 3, 6, 9, 12, 15, 18

# Spawned rays start this far off the surface along the shading normal; scenes are a few units big.
RAY_OFFSET = 1e-4
T_MIN = 1e-7
INV_PI = 1.0 / math.pi
# Random dimensions used per bounce (light pick, 2 for the light point, lobe pick, 2 for the
# direction, roulette) plus 2 for the pixel jitter.
DIMS_PER_BOUNCE = 8

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
def intersect(o, d, tmax, spheres, quads, n_single, groups, bounds):
    """Closest hit in (T_MIN, tmax) of the ray o + t d (d unit): (t, kind, index); kind 0 sphere,
    1 quad, -1 miss. ``n_single``, ``groups``, ``bounds``: see SceneArrays."""
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
def occluded(o, d, tmax, spheres, quads, n_single, groups, bounds):
    """Whether anything lies on the ray o + t d for t in (T_MIN, tmax)."""
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


@njit(cache=True)
def _surface(p, kind, idx, spheres, quads):
    """Geometric normal (outward for spheres, cross(u, v) for quads) and texture coordinates."""
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


@njit(cache=True)
def _albedo(materials, m, p, u, v):
    """Diffuse reflectance of material m at p (checker textures evaluated)."""
    tex = int(materials[m, M_TEXTURE])
    if tex == TEX_NONE:
        return _row3(materials, m, M_ALBEDO)
    s = materials[m, M_SCALE]
    if tex == TEX_WORLD:
        # odd offsets keep axis-aligned planes at round coordinates (y = 0) off the cell borders
        k = (math.floor((p[0] + 0.01370) * s) + math.floor((p[1] + 0.02910) * s)
             + math.floor((p[2] + 0.01730) * s))
    else:
        k = math.floor(u * s) + math.floor(v * s)
    if int(k) % 2 == 0:
        return _row3(materials, m, M_ALBEDO)
    return _row3(materials, m, M_ALBEDO2)


# ---------------------------------------------------------------------------------------------
# BSDFs: lambert, GGX metal, plastic = lambert + GGX coat
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def _ggx_d(nh, a2):
    k = nh * nh * (a2 - 1.0) + 1.0
    return a2 / (math.pi * k * k)


@njit(cache=True)
def _ggx_g1(c, a2):
    return 2.0 * c / (c + math.sqrt(a2 + (1.0 - a2) * c * c))


@njit(cache=True)
def _plastic_spec_prob(kd, ks, cos_o):
    """Probability of sampling the coat of a plastic: its Fresnel weight against the base's."""
    f0 = _luminance(ks)
    fo = f0 + (1.0 - f0) * (1.0 - cos_o) ** 5
    p = fo / (fo + _luminance(kd) * (1.0 - fo) + 1e-12)
    return min(0.85, max(0.15, p))


@njit(cache=True)
def bsdf_eval(mk, kd, ks, alpha, n, wo, wi):
    """(f_diffuse RGB, f_glossy RGB, pdf of bsdf_sample for wi) at a surface with unit normal n
    facing wo. Zero below the horizon."""
    zero = (0.0, 0.0, 0.0)
    ci = _dot(n, wi)
    co = _dot(n, wo)
    if ci <= 0.0 or co <= 0.0:
        return zero, zero, 0.0
    if mk == LAMBERT:
        return _scale(kd, INV_PI), zero, ci * INV_PI
    h = _normalize(_add(wo, wi))
    nh = _dot(n, h)
    oh = _dot(wo, h)
    a2 = alpha * alpha
    dd = _ggx_d(nh, a2)
    common = dd * _ggx_g1(co, a2) * _ggx_g1(ci, a2) / (4.0 * co * ci)
    fw = (1.0 - oh) ** 5
    fs = ((ks[0] + (1.0 - ks[0]) * fw) * common,
          (ks[1] + (1.0 - ks[1]) * fw) * common,
          (ks[2] + (1.0 - ks[2]) * fw) * common)
    pdf_s = dd * nh / (4.0 * oh)
    if mk == GLOSSY:
        return zero, fs, pdf_s
    ps = _plastic_spec_prob(kd, ks, co)
    return _scale(kd, INV_PI), fs, ps * pdf_s + (1.0 - ps) * ci * INV_PI


@njit(cache=True)
def bsdf_sample(mk, kd, ks, alpha, n, wo, u0, u1, u2):
    """A direction wi drawn from the BSDF's sampling density (cosine for the diffuse lobe, GGX
    normals for the glossy one, lobes mixed for plastic); (wi, ok)."""
    diffuse = mk == LAMBERT
    if mk == PLASTIC:
        diffuse = u0 >= _plastic_spec_prob(kd, ks, _dot(n, wo))
    phi = 2.0 * math.pi * u2
    if diffuse:
        r = math.sqrt(u1)
        wi = _to_world((r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - u1))), n)
    else:
        a2 = alpha * alpha
        tan2 = a2 * u1 / (1.0 - u1)
        ct = 1.0 / math.sqrt(1.0 + tan2)
        st = math.sqrt(max(0.0, 1.0 - ct * ct))
        h = _to_world((st * math.cos(phi), st * math.sin(phi), ct), n)
        oh = _dot(wo, h)
        if oh <= 0.0:
            return wo, False
        wi = _madd(_scale(wo, -1.0), h, 2.0 * oh)
    return wi, _dot(n, wi) > 0.0


# ---------------------------------------------------------------------------------------------
# the integrator
# ---------------------------------------------------------------------------------------------

@njit(cache=True)
def trace_sample(o, d, key, spheres, sphere_mat, quads, quad_mat, quad_light, n_single, groups, bounds,
                 materials, lights, light_cdf, light_prob, env, max_depth, rr_depth, out):
    """Trace one camera ray; writes out[0:13] = diffuse, specular, albedo, normal, depth."""
    for i in range(13):
        out[i] = 0.0
    ld = (0.0, 0.0, 0.0)
    ls = (0.0, 0.0, 0.0)
    bd = (0.0, 0.0, 0.0)  # throughput of the diffuse part of the first vertex
    bs = (0.0, 0.0, 0.0)  # throughput of the glossy part
    prev_pdf = 0.0
    n_lights = lights.shape[0]
    for bounce in range(max_depth + 1):
        t, kind, idx = intersect(o, d, np.inf, spheres, quads, n_single, groups, bounds)
        if kind < 0:
            if bounce == 0:
                ls = _add(ls, env)
            else:
                ld = _add(ld, _mul(bd, env))
                ls = _add(ls, _mul(bs, env))
            break
        p = _madd(o, d, t)
        ng, tu, tv = _surface(p, kind, idx, spheres, quads)
        m = sphere_mat[idx] if kind == 0 else quad_mat[idx]
        mk = int(materials[m, M_KIND])
        cos_d = _dot(ng, d)
        n = _scale(ng, -1.0) if cos_d > 0.0 else ng  # double-sided: shade the side the ray came from
        kd = (0.0, 0.0, 0.0)
        if mk == LAMBERT or mk == PLASTIC:
            kd = _albedo(materials, m, p, tu, tv)
        if bounce == 0:
            out[6] = kd[0]
            out[7] = kd[1]
            out[8] = kd[2]
            out[9] = n[0]
            out[10] = n[1]
            out[11] = n[2]
            out[12] = t
        if mk == EMITTER:
            if cos_d < 0.0:  # front side only
                le = _row3(materials, m, M_EMISSION)
                if bounce == 0:
                    ls = _add(ls, le)
                else:
                    li = quad_light[idx] if kind == 1 else -1
                    w = 1.0
                    if li >= 0:
                        pdf_l = light_prob[li] * t * t / (-cos_d * quads[idx, Q_AREA])
                        w = prev_pdf * prev_pdf / (prev_pdf * prev_pdf + pdf_l * pdf_l)
                    ld = _madd(ld, _mul(bd, le), w)
                    ls = _madd(ls, _mul(bs, le), w)
            break
        if bounce == max_depth:
            break
        ks = _row3(materials, m, M_SPECULAR)
        alpha = materials[m, M_ROUGHNESS]
        wo = _scale(d, -1.0)
        base = 2 + bounce * DIMS_PER_BOUNCE
        origin = _madd(p, n, RAY_OFFSET)

        # next-event estimation, MIS-weighted against BSDF sampling
        if n_lights > 0:
            u0 = rand(key, base)
            li = 0
            while li < n_lights - 1 and u0 >= light_cdf[li]:
                li += 1
            q = lights[li]
            u1 = rand(key, base + 1)
            u2 = rand(key, base + 2)
            point = _madd(_madd(_row3(quads, q, Q_CORNER), _row3(quads, q, Q_U), u1), _row3(quads, q, Q_V), u2)
            dl = _sub(point, origin)
            dist2 = _dot(dl, dl)
            dist = math.sqrt(dist2)
            wi = _scale(dl, 1.0 / dist)
            cos_l = -_dot(_row3(quads, q, Q_NORMAL), wi)
            ci = _dot(n, wi)
            if cos_l > 0.0 and ci > 0.0:
                fd, fs, pdf_b = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
                if pdf_b > 0.0:
                    # stop short of the light's own plane
                    tmax = dist * (1.0 - 1e-5)
                    if not occluded(origin, wi, tmax, spheres, quads, n_single, groups, bounds):
                        pdf_l = light_prob[li] * dist2 / (cos_l * quads[q, Q_AREA])
                        w = pdf_l * pdf_l / (pdf_l * pdf_l + pdf_b * pdf_b)
                        c = _scale(_row3(materials, quad_mat[q], M_EMISSION), ci * w / pdf_l)
                        if bounce == 0:
                            ld = _add(ld, _mul(fd, c))
                            ls = _add(ls, _mul(fs, c))
                        else:
                            fc = _mul(_add(fd, fs), c)
                            ld = _add(ld, _mul(bd, fc))
                            ls = _add(ls, _mul(bs, fc))

        # continue the path by sampling the BSDF
        wi, ok = bsdf_sample(mk, kd, ks, alpha, n, wo, rand(key, base + 3), rand(key, base + 4),
                             rand(key, base + 5))
        if not ok:
            break
        fd, fs, pdf = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
        if pdf <= 0.0:
            break
        ci = _dot(n, wi)
        if bounce == 0:
            bd = _scale(fd, ci / pdf)
            bs = _scale(fs, ci / pdf)
        else:
            f = _scale(_add(fd, fs), ci / pdf)
            bd = _mul(bd, f)
            bs = _mul(bs, f)
        prev_pdf = pdf
        o = origin
        d = wi
        if bounce >= rr_depth:
            survive = min(0.95, max(bd[0] + bs[0], max(bd[1] + bs[1], bd[2] + bs[2])))
            if rand(key, base + 6) >= survive:
                break
            bd = _scale(bd, 1.0 / survive)
            bs = _scale(bs, 1.0 / survive)

    good = True
    for c in range(3):
        if not (math.isfinite(ld[c]) and math.isfinite(ls[c])):
            good = False
    if good:  # a non-finite sample (should not happen) counts as black rather than poisoning the pixel
        out[0] = ld[0]
        out[1] = ld[1]
        out[2] = ld[2]
        out[3] = ls[0]
        out[4] = ls[1]
        out[5] = ls[2]


@njit(cache=True, parallel=True)
def render_kernel(spheres, sphere_mat, quads, quad_mat, quad_light, n_single, groups, bounds, materials,
                  lights, light_cdf, light_prob, camera, tan_half, env, width, height, spp, seed, max_depth,
                  rr_depth, row_order, out):
    """Render into out (height, width, N_OUT) float64: means of the 13 sample channels, then the
    variances of the pixel mean (unbiased per-sample variance / spp, averaged over RGB) of
    diffuse, specular, colour, albedo, normal, depth. ``row_order`` is a permutation of the rows
    that spreads cheap and expensive rows over the threads; results do not depend on it."""
    pos = (camera[0], camera[1], camera[2])
    fwd = (camera[3], camera[4], camera[5])
    right = (camera[6], camera[7], camera[8])
    up = (camera[9], camera[10], camera[11])
    aspect = width / height
    for ri in prange(height):
        y = row_order[ri]
        v = np.zeros(N_SAMPLE)
        first = np.zeros(N_SAMPLE)
        s1 = np.zeros(N_SAMPLE)
        s2 = np.zeros(N_SAMPLE)
        for x in range(width):
            s1[:] = 0.0
            s2[:] = 0.0
            pix = y * width + x
            for s in range(spp):
                key = sample_key(seed, pix, s)
                sx = (2.0 * (x + rand(key, 0)) / width - 1.0) * tan_half * aspect
                sy = (1.0 - 2.0 * (y + rand(key, 1)) / height) * tan_half
                d = _normalize(_madd(_madd(fwd, right, sx), up, sy))
                trace_sample(pos, d, key, spheres, sphere_mat, quads, quad_mat, quad_light, n_single, groups,
                             bounds, materials, lights, light_cdf, light_prob, env, max_depth, rr_depth, v)
                for c in range(3):
                    v[13 + c] = v[c] + v[3 + c]
                if s == 0:
                    first[:] = v
                # sums of differences from the first sample: exact zero variance for constant
                # pixels and no catastrophic cancellation for bright ones
                for c in range(N_SAMPLE):
                    dv = v[c] - first[c]
                    s1[c] += dv
                    s2[c] += dv * dv
            inv_n = 1.0 / spp
            for c in range(OUT_MEANS):
                out[y, x, c] = first[c] + s1[c] * inv_n
            if spp > 1:
                # per-channel variance of the mean, then averaged over each buffer's channels
                for b in range(OUT_VARS):
                    if b == 0:
                        c0, nc = 0, 3
                    elif b == 1:
                        c0, nc = 3, 3
                    elif b == 2:
                        c0, nc = 13, 3
                    elif b == 3:
                        c0, nc = 6, 3
                    elif b == 4:
                        c0, nc = 9, 3
                    else:
                        c0, nc = 12, 1
                    acc = 0.0
                    for c in range(c0, c0 + nc):
                        acc += max(0.0, s2[c] - s1[c] * s1[c] * inv_n) / (spp - 1) * inv_n
                    out[y, x, OUT_MEANS + b] = acc / nc
            else:
                for b in range(OUT_VARS):
                    out[y, x, OUT_MEANS + b] = 0.0
