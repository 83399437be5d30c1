"""The path-tracing integrator, compiled once per set of effects a scene calls for.

Unidirectional path tracing with next-event estimation to the lights (one picked in proportion to its
power: a uniform point on a rectangle or on a triangle of an emissive mesh, a direction uniform in the cone
a sphere subtends, an environment map by texel luminance; ``lights.py`` samples each kind) combined with BSDF
sampling by the power heuristic. :func:`trace_sample` is the loop over a path's vertices; what it does at a
vertex is in inline functions (``inline="always"``, so the kernel compiles as one function): light sampling
(:func:`direct_light`), the weights of emission the path reaches (:func:`emission_weight`, :func:`escaped`) and
path continuation (:func:`continue_delta`, :func:`continue_bsdf`, :func:`roulette`).
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
    RAY_OFFSET,
    T_AREA,
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
from prep.render.lights import (
    planar_density,
    sample_environment,
    sample_quad,
    sample_sphere,
    sample_triangle,
    sphere_density,
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


@njit(cache=True)
def environment_at(sc, d):
    """Radiance of the environment in direction d: horizon colour blended to the zenith colour."""
    t = max(d[1], 0.0)
    e, z = sc.environment, sc.environment_zenith
    return (e[0] + (z[0] - e[0]) * t, e[1] + (z[1] - e[1]) * t, e[2] + (z[2] - e[2]) * t)


# ---------------------------------------------------------------------------------------------
# light sampling and the MIS weights (the kinds themselves are in lights.py)
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def power_heuristic(pdf_a, pdf_b):
    """The MIS weight (power heuristic, exponent 2) of a sample drawn with density pdf_a that pdf_b could draw."""
    return pdf_a * pdf_a / (pdf_a * pdf_a + pdf_b * pdf_b)


@njit(cache=True, inline="always")
def sample_light(sc, origin, u0, u1, u2):
    """A light picked in proportion to its power (u0), then a point or direction on it (u1, u2) seen from
    ``origin``: (lit, wi, tmax, pdf, le) as ``lights.py`` says; unlit for a kind this kernel has no flag for."""
    li = search_cdf(sc.light_cdf, u0)
    q = sc.lights[li]
    prob = sc.light_prob[li]
    if HAS_EMITTER and sc.light_kind[li] == L_QUAD:
        return sample_quad(sc, q, prob, origin, u1, u2)
    if HAS_EMITTER and HAS_MESH and sc.light_kind[li] == L_TRIANGLE:
        return sample_triangle(sc, q, prob, origin, u1, u2)
    if HAS_EMITTER and sc.light_kind[li] == L_SPHERE:
        return sample_sphere(sc, q, prob, origin, u1, u2)
    if HAS_ENVIRONMENT_MAP and sc.light_kind[li] == L_ENVIRONMENT:
        return sample_environment(sc, prob, u1, u2)
    zero = (0.0, 0.0, 0.0)
    return False, zero, 0.0, 0.0, zero


@njit(cache=True, inline="always")
def direct_light(sc, key, base, mk, kd, ks, alpha, n, wo, origin, bounce, ld, ls, bd, bs):
    """Next-event estimation at a vertex with a BSDF: one light sample, MIS-weighted against BSDF sampling,
    added to the radiance (ld, ls) through the throughputs (bd, bs) of the vertex; (ld, ls)."""
    lit, wi, tmax, pdf_l, le = sample_light(sc, origin, rand(key, base), rand(key, base + 1), rand(key, base + 2))
    ci = _dot(n, wi)
    if not (lit and ci > 0.0):
        return ld, ls
    fd, fs, pdf_b = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
    if not pdf_b > 0.0:
        return ld, ls
    blocked = occluded(origin, wi, tmax, sc)
    if HAS_MESH and not blocked:
        blocked = occluded_mesh(origin, wi, tmax, sc)
    if blocked:
        return ld, ls
    c = _scale(le, ci * power_heuristic(pdf_l, pdf_b) / pdf_l)
    if bounce == 0:
        return _add(ld, _mul(fd, c)), _add(ls, _mul(fs, c))
    fc = _mul(_add(fd, fs), c)
    return _add(ld, _mul(bd, fc)), _add(ls, _mul(bs, fc))


@njit(cache=True, inline="always")
def emission_weight(sc, kind, idx, o, t, cos_d, prev_pdf):
    """The MIS weight of the emission of an emitter that BSDF sampling (density ``prev_pdf``, from ``o``) hit at
    distance t and cosine cos_d < 0: 1 where light sampling could not have drawn it."""
    li = sc.quad_light[idx] if kind == 1 else (sc.sphere_light[idx] if kind == 0 else -1)
    if HAS_MESH and kind == 2:
        li = sc.tri_light[idx]
    if li < 0 or not prev_pdf > 0.0:
        return 1.0
    prob = sc.light_prob[li]
    if kind == 1:
        pdf_l = planar_density(prob, t, -cos_d, sc.quads[idx, Q_AREA])
    elif HAS_MESH and kind == 2:
        pdf_l = planar_density(prob, t, -cos_d, sc.triangles[idx, T_AREA])
    else:  # the cone density light sampling used from the previous vertex, o
        pdf_l = sphere_density(sc, idx, prob, o)
    return power_heuristic(prev_pdf, pdf_l)


@njit(cache=True, inline="always")
def escaped(sc, d, bounce, prev_pdf):
    """(radiance, MIS weight) of the environment along d, for a path that leaves the scene; a map is a light
    that light sampling draws too, the constant or gradient environment is not."""
    env = (0.0, 0.0, 0.0)
    w = 1.0
    if HAS_ENVIRONMENT_MAP and sc.env_map.shape[0] > 0:
        env, pdf_dir = env_lookup(sc, d)
        if bounce > 0 and prev_pdf > 0.0 and sc.env_light >= 0:
            w = power_heuristic(prev_pdf, sc.light_prob[sc.env_light] * pdf_dir)
    elif HAS_ENVIRONMENT:
        env = environment_at(sc, d)
    return env, w


@njit(cache=True, inline="always")
def add_emitted(ld, ls, bd, bs, le, w, bounce):
    """(ld, ls) plus radiance ``le`` that the path reached, weighted ``w``: seen directly from the camera it is
    specular (the first vertex has no lobe), later it goes through the two throughputs."""
    if bounce == 0:
        return ld, _add(ls, le)
    return _madd(ld, _mul(bd, le), w), _madd(ls, _mul(bs, le), w)


# ---------------------------------------------------------------------------------------------
# path continuation
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def continue_delta(sc, key, base, m, mk, p, n, d, cos_d, bounce, bd, bs):
    """The next ray from a mirror or glass vertex (one direction; glass reflects with the Fresnel probability,
    refracts otherwise) and the throughputs through it: (origin, wi, bd, bs). The first vertex's is specular."""
    materials = sc.materials
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
        return origin, wi, (0.0, 0.0, 0.0), wt
    return origin, wi, _mul(bd, wt), _mul(bs, wt)


@njit(cache=True, inline="always")
def continue_bsdf(key, base, mk, kd, ks, alpha, n, wo, bounce, bd, bs):
    """The next direction from a vertex with a BSDF, drawn from it, and the throughputs through it, split by lobe
    at the first vertex: (ok, wi, bd, bs, pdf); not ok where the path ends (below the horizon, zero density)."""
    wi, ok = bsdf_sample(mk, kd, ks, alpha, n, wo, rand(key, base + 3), rand(key, base + 4), rand(key, base + 5))
    if not ok:
        return False, wi, bd, bs, 0.0
    fd, fs, pdf = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
    if pdf <= 0.0:
        return False, wi, bd, bs, pdf
    ci = _dot(n, wi)
    if bounce == 0:
        return True, wi, _scale(fd, ci / pdf), _scale(fs, ci / pdf), pdf
    f = _scale(_add(fd, fs), ci / pdf)
    return True, wi, _mul(bd, f), _mul(bs, f), pdf


@njit(cache=True, inline="always")
def roulette(bd, bs, u):
    """Russian roulette on the throughputs: (alive, bd, bs), those of a surviving path scaled by 1 / its odds."""
    survive = min(0.95, max(bd[0] + bs[0], max(bd[1] + bs[1], bd[2] + bs[2])))
    if u >= survive:
        return False, bd, bs
    return True, _scale(bd, 1.0 / survive), _scale(bs, 1.0 / survive)


# ---------------------------------------------------------------------------------------------
# the integrator
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def nearest_hit(o, d, sc):
    """(t, kind, idx) of the nearest surface along the ray: kind 0 a sphere, 1 a quad, 2 a triangle, < 0 none."""
    t, kind, idx = intersect(o, d, np.inf, sc)
    if HAS_MESH:  # triangles after spheres and quads, up to the nearer hit (t is inf on a miss)
        tm, ti = intersect_mesh(o, d, t, sc)
        if ti >= 0:
            return tm, 2, ti
    return t, kind, idx


@njit(cache=True, inline="always")
def material_of(sc, kind, idx):
    """The material index of surface idx of kind (as :func:`nearest_hit` gives them)."""
    if HAS_MESH and kind == 2:
        return sc.tri_mat[idx]
    return sc.sphere_mat[idx] if kind == 0 else sc.quad_mat[idx]


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
    materials = sc.materials
    for bounce in range(max_depth + 1):
        t, kind, idx = nearest_hit(o, d, sc)
        if kind < 0:
            env, w = escaped(sc, d, bounce, prev_pdf)
            ld, ls = add_emitted(ld, ls, bd, bs, env, w, bounce)
            break
        p = _madd(o, d, t)
        ng, tu, tv = surface(p, kind, idx, sc.spheres, sc.quads, sc.triangles)
        m = material_of(sc, kind, idx)
        mk = int(materials[m, M_KIND])
        cos_d = _dot(ng, d)
        n = _scale(ng, -1.0) if cos_d > 0.0 else ng  # double-sided: shade the side the ray came from
        kd = (0.0, 0.0, 0.0)
        if (HAS_LAMBERT and mk == LAMBERT) or (HAS_PLASTIC and mk == PLASTIC):
            kd = albedo_at(sc, m, p, tu, tv)
        if bounce == 0:
            out[6:9] = kd
            out[9:12] = n
            out[12] = t
        if HAS_EMITTER and mk == EMITTER:
            if cos_d < 0.0:  # front side only
                w = 1.0 if bounce == 0 else emission_weight(sc, kind, idx, o, t, cos_d, prev_pdf)
                ld, ls = add_emitted(ld, ls, bd, bs, _row3(materials, m, M_EMISSION), w, bounce)
            break
        if bounce == max_depth:
            break
        base = 2 + bounce * DIMS_PER_BOUNCE
        if (HAS_MIRROR and mk == MIRROR) or (HAS_GLASS and mk == GLASS):  # a delta vertex: no light sampling
            origin, wi, bd, bs = continue_delta(sc, key, base, m, mk, p, n, d, cos_d, bounce, bd, bs)
            prev_pdf = -1.0
        else:
            ks = _row3(materials, m, M_SPECULAR)
            alpha = materials[m, M_ROUGHNESS]
            wo = _scale(d, -1.0)
            origin = _madd(p, n, RAY_OFFSET)
            if (HAS_EMITTER or HAS_ENVIRONMENT_MAP) and sc.lights.shape[0] > 0:
                ld, ls = direct_light(sc, key, base, mk, kd, ks, alpha, n, wo, origin, bounce, ld, ls, bd, bs)
            ok, wi, bd, bs, prev_pdf = continue_bsdf(key, base, mk, kd, ks, alpha, n, wo, bounce, bd, bs)
            if not ok:
                break
        o = origin
        d = wi
        if bounce >= rr_depth:
            alive, bd, bs = roulette(bd, bs, rand(key, base + 6))
            if not alive:
                break

    good = True
    for c in range(3):
        if not (math.isfinite(ld[c]) and math.isfinite(ls[c])):
            good = False
    if good:  # a non-finite sample (should not happen) counts as black rather than poisoning the pixel
        out[0:3] = ld
        out[3:6] = ls


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
