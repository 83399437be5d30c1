"""The path-tracing integrator, compiled once per set of effects a scene calls for.

Unidirectional path tracing with next-event estimation to the lights (one picked in proportion to its
power: a uniform point on a rectangle or on a triangle of an emissive mesh, a direction uniform in the cone
a sphere subtends, an environment map by texel luminance) combined with BSDF sampling by the power heuristic.
Per-sample radiance is split by the lobe of the first scattering vertex: the path throughput after
that vertex is carried as two RGB weights (diffuse part, glossy part) that later vertices scale
alike, so every path's radiance lands exactly in diffuse + specular without a random lobe choice
deciding the split.

**Specialisation.** The ``HAS_*`` flags below are module constants, which numba compiles as constants:
the code of an effect whose flag is False is removed from the kernel, not branched around per sample.
The kernels are not compiled from this file: ``kernels.kernel_for(effects)`` loads a copy of it with the
flags of an effect set (``Scene.effects()``; every flag on for the all-effects kernel). Which random dimension each
decision uses does not depend on the flags, so a specialised kernel gives the all-effects kernel's
output bit for bit on a scene it was made for.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from prep.render.tracer import (
    DIMS_PER_BOUNCE,
    EMITTER,
    GLASS,
    GLOSSY,
    INV_PI,
    L_ENVIRONMENT,
    L_QUAD,
    L_SPHERE,
    L_TRIANGLE,
    LAMBERT,
    LENS_DIM,
    M_ALBEDO,
    M_ALBEDO2,
    M_EMISSION,
    M_IOR,
    M_KIND,
    M_ROUGHNESS,
    M_SCALE,
    M_SPECULAR,
    M_TEXTURE,
    MIRROR,
    N_SAMPLE,
    OUT_MEANS,
    OUT_VARS,
    PLASTIC,
    Q_AREA,
    Q_CORNER,
    Q_NORMAL,
    Q_U,
    Q_V,
    RAY_OFFSET,
    T_AREA,
    T_E1,
    T_E2,
    T_NORMAL,
    T_V0,
    TEX_IMAGE,
    TEX_NONE,
    TEX_WORLD,
    _add,
    _dot,
    _ggx_d,
    _ggx_g1,
    _madd,
    _mul,
    _normalize,
    _plastic_spec_prob,
    _row3,
    _scale,
    _sub,
    _to_world,
    env_lookup,
    env_sample,
    fresnel_dielectric,
    ggx_visible_normal,
    intersect,
    intersect_mesh,
    occluded,
    occluded_mesh,
    rand,
    reflect,
    refract,
    sample_key,
    search_cdf,
    surface,
)

# --- effects (kernels.py rewrites this block; one line per name of scene.EFFECTS) ---
HAS_LAMBERT = True
HAS_GLOSSY = True
HAS_PLASTIC = True
HAS_EMITTER = True
HAS_MIRROR = True
HAS_GLASS = True
HAS_ENVIRONMENT = True
HAS_TEXTURE = True
HAS_LENS = True
HAS_MESH = True
HAS_ENVIRONMENT_MAP = True
# --- end of effects ---


@njit(cache=True)
def albedo_at(sc, m, p, u, v):
    """Diffuse reflectance of material m at p (checker and image textures evaluated)."""
    materials = sc.materials
    if not HAS_TEXTURE:
        return _row3(materials, m, M_ALBEDO)
    tex = int(materials[m, M_TEXTURE])
    if tex == TEX_NONE:
        return _row3(materials, m, M_ALBEDO)
    s = materials[m, M_SCALE]
    if tex == TEX_IMAGE:
        first, w, h = sc.image_info[m, 0], sc.image_info[m, 1], sc.image_info[m, 2]
        fu = u * s - math.floor(u * s)
        fv = v * s - math.floor(v * s)
        i = first + min(int(fv * h), h - 1) * w + min(int(fu * w), w - 1)
        return _mul(_row3(materials, m, M_ALBEDO), _row3(sc.image_pixels, i, 0))
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
def bsdf_eval(mk, kd, ks, alpha, n, wo, wi):
    """(f_diffuse RGB, f_glossy RGB, pdf of bsdf_sample for wi) at a surface with unit normal n
    facing wo. Zero below the horizon."""
    zero = (0.0, 0.0, 0.0)
    ci = _dot(n, wi)
    co = _dot(n, wo)
    if ci <= 0.0 or co <= 0.0:
        return zero, zero, 0.0
    if HAS_LAMBERT and mk == LAMBERT:
        return _scale(kd, INV_PI), zero, ci * INV_PI
    if HAS_GLOSSY or HAS_PLASTIC:
        h = _normalize(_add(wo, wi))
        nh = _dot(n, h)
        oh = _dot(wo, h)
        a2 = alpha * alpha
        dd = _ggx_d(nh, a2)
        g1o = _ggx_g1(co, a2)
        common = dd * g1o * _ggx_g1(ci, a2) / (4.0 * co * ci)
        fw = (1.0 - oh) ** 5
        fs = ((ks[0] + (1.0 - ks[0]) * fw) * common,
              (ks[1] + (1.0 - ks[1]) * fw) * common,
              (ks[2] + (1.0 - ks[2]) * fw) * common)
        pdf_s = dd * g1o / (4.0 * co)  # visible normals: D_wo(h) / (4 wo.h)
        if HAS_GLOSSY and mk == GLOSSY:
            return zero, fs, pdf_s
        if HAS_PLASTIC:
            ps = _plastic_spec_prob(kd, ks, co)
            return _scale(kd, INV_PI), fs, ps * pdf_s + (1.0 - ps) * ci * INV_PI
    return zero, zero, 0.0


@njit(cache=True)
def bsdf_sample(mk, kd, ks, alpha, n, wo, u0, u1, u2):
    """A direction wi drawn from the BSDF's sampling density (cosine for the diffuse lobe, GGX normals
    visible from wo for the glossy one, lobes mixed for plastic); (wi, ok): not ok below the horizon."""
    diffuse = HAS_LAMBERT and mk == LAMBERT
    if HAS_PLASTIC and mk == PLASTIC:
        diffuse = u0 >= _plastic_spec_prob(kd, ks, _dot(n, wo))
    if diffuse or not (HAS_GLOSSY or HAS_PLASTIC):
        phi = 2.0 * math.pi * u2
        r = math.sqrt(u1)
        wi = _to_world((r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - u1))), n)
    else:
        h = ggx_visible_normal(wo, n, alpha, u1, u2)
        wi = _madd(_scale(wo, -1.0), h, 2.0 * _dot(wo, h))
    return wi, _dot(n, wi) > 0.0


@njit(cache=True, inline="always")
def toward_planar_light(origin, point, normal, area, prob):
    """Light sampling of a planar light (a rectangle, a triangle) of unit ``normal`` and ``area``, picked with
    probability ``prob``, at ``point`` drawn uniformly on it: (lit, wi, tmax, pdf) with wi the unit direction from
    ``origin``, tmax the distance that a shadow ray tests and pdf the solid-angle density of light sampling
    there; lit is False, and pdf 0, where origin is behind the light (it emits on the side of its normal)."""
    dl = _sub(point, origin)
    dist2 = _dot(dl, dl)
    dist = math.sqrt(dist2)
    wi = _scale(dl, 1.0 / dist)
    cos_l = -_dot(normal, wi)
    if cos_l <= 0.0:
        return False, wi, 0.0, 0.0
    # the shadow ray stops short of the light's own plane
    return True, wi, dist * (1.0 - 1e-5), prob * dist2 / (cos_l * area)


@njit(cache=True)
def environment_at(sc, d):
    """Radiance of the environment in direction d: horizon colour blended to the zenith colour."""
    t = max(d[1], 0.0)
    e, z = sc.environment, sc.environment_zenith
    return (e[0] + (z[0] - e[0]) * t, e[1] + (z[1] - e[1]) * t, e[2] + (z[2] - e[2]) * t)


# ---------------------------------------------------------------------------------------------
# the integrator
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def trace_sample(o, d, key, sc, max_depth, rr_depth, out):
    """Trace one camera ray through the packed scene ``sc``; writes out[0:13] = diffuse, specular,
    albedo, normal, depth."""
    for i in range(13):
        out[i] = 0.0
    ld = (0.0, 0.0, 0.0)
    ls = (0.0, 0.0, 0.0)
    bd = (0.0, 0.0, 0.0)  # throughput of the diffuse part of the first vertex
    bs = (0.0, 0.0, 0.0)  # throughput of the glossy part
    prev_pdf = 0.0  # of the direction that led here; < 0 after a delta (mirror, glass) vertex
    materials, quads = sc.materials, sc.quads
    n_lights = sc.lights.shape[0]
    for bounce in range(max_depth + 1):
        t, kind, idx = intersect(o, d, np.inf, sc)
        if HAS_MESH:  # triangles after spheres and quads, up to the nearer hit (t is inf on a miss)
            tm, ti = intersect_mesh(o, d, t, sc)
            if ti >= 0:
                t = tm
                kind = 2
                idx = ti
        if kind < 0:
            env = (0.0, 0.0, 0.0)
            w = 1.0
            if HAS_ENVIRONMENT_MAP and sc.env_map.shape[0] > 0:
                env, pdf_dir = env_lookup(sc, d)
                if bounce > 0 and prev_pdf > 0.0 and sc.env_light >= 0:
                    pdf_l = sc.light_prob[sc.env_light] * pdf_dir
                    w = prev_pdf * prev_pdf / (prev_pdf * prev_pdf + pdf_l * pdf_l)
            elif HAS_ENVIRONMENT:
                env = environment_at(sc, d)
            if bounce == 0:
                ls = _add(ls, env)
            else:
                ld = _madd(ld, _mul(bd, env), w)
                ls = _madd(ls, _mul(bs, env), w)
            break
        p = _madd(o, d, t)
        ng, tu, tv = surface(p, kind, idx, sc.spheres, quads, sc.triangles)
        if HAS_MESH and kind == 2:
            m = sc.tri_mat[idx]
        else:
            m = sc.sphere_mat[idx] if kind == 0 else sc.quad_mat[idx]
        mk = int(materials[m, M_KIND])
        cos_d = _dot(ng, d)
        n = _scale(ng, -1.0) if cos_d > 0.0 else ng  # double-sided: shade the side the ray came from
        kd = (0.0, 0.0, 0.0)
        if (HAS_LAMBERT and mk == LAMBERT) or (HAS_PLASTIC and mk == PLASTIC):
            kd = albedo_at(sc, m, p, tu, tv)
        if bounce == 0:
            out[6] = kd[0]
            out[7] = kd[1]
            out[8] = kd[2]
            out[9] = n[0]
            out[10] = n[1]
            out[11] = n[2]
            out[12] = t
        if HAS_EMITTER and mk == EMITTER:
            if cos_d < 0.0:  # front side only
                le = _row3(materials, m, M_EMISSION)
                if bounce == 0:
                    ls = _add(ls, le)
                else:
                    li = sc.quad_light[idx] if kind == 1 else (sc.sphere_light[idx] if kind == 0 else -1)
                    if HAS_MESH and kind == 2:
                        li = sc.tri_light[idx]
                    w = 1.0
                    if li >= 0 and prev_pdf > 0.0:
                        if kind == 1:
                            pdf_l = sc.light_prob[li] * t * t / (-cos_d * quads[idx, Q_AREA])
                        elif HAS_MESH and kind == 2:
                            pdf_l = sc.light_prob[li] * t * t / (-cos_d * sc.triangles[idx, T_AREA])
                        else:  # the cone density light sampling used from the previous vertex, o
                            wc = _sub(_row3(sc.spheres, idx, 0), o)
                            sin2 = sc.spheres[idx, 3] * sc.spheres[idx, 3] / _dot(wc, wc)
                            one_minus = sin2 / (1.0 + math.sqrt(max(0.0, 1.0 - sin2)))
                            pdf_l = sc.light_prob[li] / (2.0 * math.pi * one_minus)
                        w = prev_pdf * prev_pdf / (prev_pdf * prev_pdf + pdf_l * pdf_l)
                    ld = _madd(ld, _mul(bd, le), w)
                    ls = _madd(ls, _mul(bs, le), w)
            break
        if bounce == max_depth:
            break
        base = 2 + bounce * DIMS_PER_BOUNCE
        if (HAS_MIRROR and mk == MIRROR) or (HAS_GLASS and mk == GLASS):
            # a delta vertex: one direction (or two, for glass), no light sampling
            wt = _row3(materials, m, M_SPECULAR)
            cos_i = -_dot(n, d)
            if HAS_GLASS and mk == GLASS:
                ior = materials[m, M_IOR]
                eta = 1.0 / ior if cos_d < 0.0 else ior  # entering through the outward normal, or leaving
                fr, cos_t = fresnel_dielectric(cos_i, eta)
                if rand(key, base + 3) < fr:
                    wi = reflect(d, n)
                    origin = _madd(p, n, RAY_OFFSET)
                    wt = (1.0, 1.0, 1.0)
                else:
                    wi = refract(d, n, eta, cos_i, cos_t)
                    origin = _madd(p, n, -RAY_OFFSET)
            else:
                wi = reflect(d, n)
                origin = _madd(p, n, RAY_OFFSET)
            if bounce == 0:
                bd = (0.0, 0.0, 0.0)
                bs = wt
            else:
                bd = _mul(bd, wt)
                bs = _mul(bs, wt)
            prev_pdf = -1.0
        else:
            ks = _row3(materials, m, M_SPECULAR)
            alpha = materials[m, M_ROUGHNESS]
            wo = _scale(d, -1.0)
            origin = _madd(p, n, RAY_OFFSET)

            # next-event estimation, MIS-weighted against BSDF sampling
            if (HAS_EMITTER or HAS_ENVIRONMENT_MAP) and n_lights > 0:
                li = search_cdf(sc.light_cdf, rand(key, base))
                q = sc.lights[li]
                u1 = rand(key, base + 1)
                u2 = rand(key, base + 2)
                lit = False
                wi = n
                tmax = 0.0
                pdf_l = 0.0
                le = (0.0, 0.0, 0.0)
                if HAS_EMITTER and sc.light_kind[li] == L_QUAD:  # a rectangle: a uniform point on it
                    point = _madd(_madd(_row3(quads, q, Q_CORNER), _row3(quads, q, Q_U), u1), _row3(quads, q, Q_V), u2)
                    lit, wi, tmax, pdf_l = toward_planar_light(origin, point, _row3(quads, q, Q_NORMAL),
                                                               quads[q, Q_AREA], sc.light_prob[li])
                    le = _row3(materials, sc.quad_mat[q], M_EMISSION)
                elif HAS_EMITTER and HAS_MESH and sc.light_kind[li] == L_TRIANGLE:  # a uniform point on it
                    tris = sc.triangles
                    su = math.sqrt(u1)
                    point = _madd(_madd(_row3(tris, q, T_V0), _row3(tris, q, T_E1), u2 * su), _row3(tris, q, T_E2),
                                  su * (1.0 - u2))
                    lit, wi, tmax, pdf_l = toward_planar_light(origin, point, _row3(tris, q, T_NORMAL),
                                                               tris[q, T_AREA], sc.light_prob[li])
                    le = _row3(materials, sc.tri_mat[q], M_EMISSION)
                elif HAS_EMITTER and sc.light_kind[li] == L_SPHERE:  # a direction uniform in the cone it subtends
                    wc = _sub(_row3(sc.spheres, q, 0), origin)
                    dc2 = _dot(wc, wc)
                    r2 = sc.spheres[q, 3] * sc.spheres[q, 3]
                    if dc2 > r2:
                        dc = math.sqrt(dc2)
                        sin2 = r2 / dc2
                        cos_max = math.sqrt(max(0.0, 1.0 - sin2))
                        one_minus = sin2 / (1.0 + cos_max)  # 1 - cos_max without cancellation
                        ct = 1.0 - u1 * one_minus
                        st = math.sqrt(max(0.0, 1.0 - ct * ct))
                        phi = 2.0 * math.pi * u2
                        wi = _to_world((st * math.cos(phi), st * math.sin(phi), ct), _scale(wc, 1.0 / dc))
                        b = _dot(wc, wi)
                        lit = True
                        tmax = (b - math.sqrt(max(0.0, b * b - dc2 + r2))) * (1.0 - 1e-5)
                        pdf_l = sc.light_prob[li] / (2.0 * math.pi * one_minus)
                        le = _row3(materials, sc.sphere_mat[q], M_EMISSION)
                elif HAS_ENVIRONMENT_MAP and sc.light_kind[li] == L_ENVIRONMENT:
                    wi, pdf_dir, le = env_sample(sc, u1, u2)
                    if pdf_dir > 0.0:
                        lit = True
                        tmax = np.inf
                        pdf_l = sc.light_prob[li] * pdf_dir
                ci = _dot(n, wi)
                if lit and ci > 0.0:
                    fd, fs, pdf_b = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
                    if pdf_b > 0.0:
                        blocked = occluded(origin, wi, tmax, sc)
                        if HAS_MESH and not blocked:
                            blocked = occluded_mesh(origin, wi, tmax, sc)
                        if not blocked:
                            w = pdf_l * pdf_l / (pdf_l * pdf_l + pdf_b * pdf_b)
                            c = _scale(le, ci * w / pdf_l)
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
def render_kernel(sc, width, height, spp, seed, max_depth, rr_depth, row_order, out):
    """Render the packed scene ``sc`` into out (height, width, N_OUT) float64: means of the 13 sample
    channels, then the variances of the pixel mean (unbiased per-sample variance / spp, averaged over
    RGB) of diffuse, specular, colour, albedo, normal, depth. ``row_order`` is a permutation of the
    rows that spreads cheap and expensive rows over the threads; results do not depend on it.

    The parallel loop only hands rows to :func:`render_row`, into which numba inlines :func:`trace_sample`
    (``inline="always"``). Without both, a kernel loaded from numba's cache ran at other speeds than the same
    kernel freshly compiled (numba issue #10617: on fireflies-000 the specialised kernel ran 3.35 Msamples/s
    fresh and 2.1 from the cache, the all-effects kernel 2.3 and 2.75), so what specialisation saved depended
    on the state of the cache; compiled as one function, both give the same speed."""
    for ri in prange(height):
        render_row(sc, row_order[ri], width, height, spp, seed, max_depth, rr_depth, out)


@njit(cache=True)
def render_row(sc, y, width, height, spp, seed, max_depth, rr_depth, out):
    """Row y of :func:`render_kernel`."""
    camera = sc.camera
    tan_half = sc.tan_half
    pos = (camera[0], camera[1], camera[2])
    fwd = (camera[3], camera[4], camera[5])
    right = (camera[6], camera[7], camera[8])
    up = (camera[9], camera[10], camera[11])
    aspect = width / height
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
            o = pos
            if HAS_LENS and sc.lens_radius > 0.0:
                # thin lens: a point on the lens disc, aimed at the ray's point on the focal plane
                focal = _madd(pos, d, sc.focus_distance / _dot(d, fwd))
                r = sc.lens_radius * math.sqrt(rand(key, LENS_DIM))
                phi = 2.0 * math.pi * rand(key, LENS_DIM + 1)
                o = _madd(_madd(pos, right, r * math.cos(phi)), up, r * math.sin(phi))
                d = _normalize(_sub(focal, o))
            trace_sample(o, d, key, sc, max_depth, rr_depth, v)
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
