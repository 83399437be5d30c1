"""The path-tracing integrator, compiled once per set of effects a scene calls for.

Unidirectional path tracing with next-event estimation to the lights (one picked in proportion to its
power: a uniform point on a rectangle or on a triangle of an emissive mesh, a direction uniform in the cone
a sphere subtends, an environment map by texel luminance; ``lights.py`` samples each kind) combined with BSDF
sampling by the power heuristic. :func:`trace_sample` is the loop over a path's vertices: it reads the scene's
tables and hands values to inline functions (``inline="always"``, so the kernel compiles as one function) for
each light kind's geometry (``lights.py``), the MIS weights (:func:`power_heuristic`), the radiance a path gathers
(:func:`add_emitted`, :func:`add_direct`) and path continuation (:func:`continue_delta`, :func:`continue_bsdf`,
:func:`roulette`). Those take no packed scene and no array, which numba would count references to per call.
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

from prep.render.lights import (
    planar_density,
    quad_point,
    sphere_density,
    toward_planar_light,
    toward_sphere_light,
    triangle_point,
)
from prep.render.media import (
    MD_G,
    TRACK_DIM,
    TRACK_STRIDE,
    free_flight,
    hg_sample,
    phase_value,
    tracked_free_flight,
    tracked_transmittance,
    transmittance,
)
from prep.render.tracer import (
    DIMS_PER_BOUNCE,
    EMITTER,
    GLASS,
    GLOSSY,
    INV_PI,
    L_A,
    L_AREA,
    L_B,
    L_C,
    L_EMISSION,
    L_ENVIRONMENT,
    L_NORMAL,
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
    RAY_OFFSET,
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
HAS_MEDIUM = True
HAS_HETEROGENEOUS = True
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
# the steps of a path. Those of every vertex take no packed scene and no array (see lights.py: numba counts
# references to every array of an argument it binds, per call); trace_sample reads the tables and hands them
# values. The two that end a path (escaped, emitter_weight) take the scene: they run once per path, not once
# per vertex, so the reference counts of its arrays are paid once a path.
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def power_heuristic(pdf_a, pdf_b):
    """The MIS weight (power heuristic, exponent 2) of a sample drawn with density pdf_a that pdf_b could draw."""
    return pdf_a * pdf_a / (pdf_a * pdf_a + pdf_b * pdf_b)


@njit(cache=True, inline="always")
def add_emitted(ld, ls, bd, bs, le, w, bounce):
    """(ld, ls) plus radiance ``le`` that the path reached, weighted ``w``: seen directly from the camera it is
    specular (the first vertex has no lobe), later it goes through the two throughputs."""
    if bounce == 0:
        return ld, _add(ls, le)
    return _madd(ld, _mul(bd, le), w), _madd(ls, _mul(bs, le), w)


@njit(cache=True, inline="always")
def add_direct(ld, ls, bd, bs, fd, fs, c, bounce):
    """(ld, ls) plus a light sample's radiance ``c`` (its weight folded in) scattered by the BSDF values
    (fd, fs) of the vertex: split by lobe at the first vertex, through the throughputs later."""
    if bounce == 0:
        return _add(ld, _mul(fd, c)), _add(ls, _mul(fs, c))
    fc = _mul(_add(fd, fs), c)
    return _add(ld, _mul(bd, fc)), _add(ls, _mul(bs, fc))


@njit(cache=True, inline="always")
def continue_delta(key, base, glass, wt, ior, p, n, d, cos_d, bounce, bd, bs):
    """The next ray from a mirror or glass vertex (of reflectance or tint ``wt``; one direction, glass reflects
    with the Fresnel probability, refracts otherwise) and the throughputs through it: (origin, wi, bd, bs).
    The first vertex's is specular."""
    cos_i = -_dot(n, d)
    if glass:
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
def toward_light(kind, a, b, c, normal, area, origin, prob, u1, u2):
    """Light sampling of a light of the light table but the environment map, from the values of its row:
    (lit, wi, tmax, pdf) of the ``toward_*`` function of its kind (lights.py)."""
    if kind == L_SPHERE:
        return toward_sphere_light(origin, a, b[0], prob, u1, u2)
    if HAS_MESH and kind == L_TRIANGLE:
        return toward_planar_light(origin, triangle_point(a, b, c, u1, u2), normal, area, prob)
    return toward_planar_light(origin, quad_point(a, b, c, u1, u2), normal, area, prob)


@njit(cache=True, inline="always")
def light_density(kind, a, radius, area, o, t, cos_l, prob):
    """The density of :func:`toward_light` from ``o`` at the point at distance ``t`` of a light that a path hit,
    seen from the light at cosine ``cos_l``: the cone a sphere subtends, or a planar light's area."""
    if kind == L_SPHERE:
        return sphere_density(o, a, radius, prob)
    return planar_density(prob, t, cos_l, area)


@njit(cache=True, inline="always")
def roulette(bd, bs, u):
    """Russian roulette on the throughputs: (alive, bd, bs), those of a surviving path scaled by 1 / its odds."""
    survive = min(0.95, max(bd[0] + bs[0], max(bd[1] + bs[1], bd[2] + bs[2])))
    if u >= survive:
        return False, bd, bs
    return True, _scale(bd, 1.0 / survive), _scale(bs, 1.0 / survive)


@njit(cache=True, inline="always")
def escaped(sc, d, bounce, prev_pdf):
    """(radiance, MIS weight) of a path that leaves the scene along ``d``: the environment (a map, a gradient or
    none), weighted against light sampling where the map is a light that could have drawn ``d``."""
    if HAS_ENVIRONMENT_MAP and sc.env_map.shape[0] > 0:
        env, pdf_dir = env_lookup(sc, d)
        if bounce > 0 and prev_pdf > 0.0 and sc.env_light >= 0:
            return env, power_heuristic(prev_pdf, sc.light_prob[sc.env_light] * pdf_dir)
        return env, 1.0
    if HAS_ENVIRONMENT:
        return environment_at(sc, d), 1.0
    return (0.0, 0.0, 0.0), 1.0


@njit(cache=True, inline="always")
def emitter_weight(sc, kind, idx, o, t, cos_d, bounce, prev_pdf):
    """The MIS weight of the emitter (primitive ``idx`` of ``kind``) that a path from the vertex ``o`` hit at distance
    ``t``, at cosine ``cos_d`` to its normal: 1 where light sampling could not have drawn it."""
    li = sc.quad_light[idx] if kind == 1 else (sc.sphere_light[idx] if kind == 0 else -1)
    if HAS_MESH and kind == 2:
        li = sc.tri_light[idx]
    if not (bounce > 0 and li >= 0 and prev_pdf > 0.0):
        return 1.0
    lt = sc.light_table
    return power_heuristic(prev_pdf, light_density(sc.light_kind[li], _row3(lt, li, L_A), lt[li, L_B],
                                                   lt[li, L_AREA], o, t, -cos_d, sc.light_prob[li]))


@njit(cache=True)
def light_sample(sc, key, base, origin):
    """Next-event estimation from a point in the medium: a light picked by power and a sample on it,
    (lit, wi, tmax, pdf, radiance), as a surface vertex draws it (same random dimensions)."""
    li = search_cdf(sc.light_cdf, rand(key, base))
    lk, u1, u2 = sc.light_kind[li], rand(key, base + 1), rand(key, base + 2)
    lt = sc.light_table
    if HAS_ENVIRONMENT_MAP and lk == L_ENVIRONMENT:
        wi, pdf_dir, le = env_sample(sc, u1, u2)
        return pdf_dir > 0.0, wi, np.inf, sc.light_prob[li] * pdf_dir, le
    lit, wi, tmax, pdf_l = toward_light(lk, _row3(lt, li, L_A), _row3(lt, li, L_B), _row3(lt, li, L_C),
                                        _row3(lt, li, L_NORMAL), lt[li, L_AREA], origin, sc.light_prob[li], u1, u2)
    return lit, wi, tmax, pdf_l, _row3(lt, li, L_EMISSION)


@njit(cache=True)
def medium_vertex(sc, key, base, x, d, bounce, ld, ls, bd, bs):
    """A scattering event at ``x`` in the medium, reached along ``d``: the light it scatters from a light sample
    (phase function x transmittance, MIS-weighted against phase sampling) added to (ld, ls), then the next
    direction drawn from the phase function. Returns (ld, ls, wi, bd, bs, pdf). At the first vertex the light
    goes to the specular part (as Cycles' Volume passes are read, see docs/formats.md); the phase function is
    sampled exactly, so the throughputs keep their value."""
    g = sc.medium[MD_G]
    zero = (0.0, 0.0, 0.0)
    if sc.lights.shape[0] > 0:
        lit, wi, tmax, pdf_l, le = light_sample(sc, key, base, x)
        if lit and pdf_l > 0.0:
            f, pdf_p = phase_value(g, d, wi)
            if not (occluded(x, wi, tmax, sc) or (HAS_MESH and occluded_mesh(x, wi, tmax, sc))):
                c = through_medium(_scale(le, power_heuristic(pdf_l, pdf_p) / pdf_l), sc, key, bounce, x, wi, tmax)
                ld, ls = add_direct(ld, ls, bd, bs, zero, f, c, bounce)
    wi, pdf = hg_sample(g, d, rand(key, base + 4), rand(key, base + 5))
    if bounce == 0:
        return ld, ls, wi, zero, (1.0, 1.0, 1.0), pdf
    return ld, ls, wi, bd, bs, pdf


@njit(cache=True, inline="always")
def through_medium(c, sc, key, bounce, o, wi, tmax):
    """``c`` times the medium's transmittance along the shadow ray o + t wi, t < tmax: exact for a homogeneous
    medium, ratio tracking through a heterogeneous one."""
    if HAS_HETEROGENEOUS and sc.medium_grid.shape[0] > 0:
        return _mul(c, tracked_transmittance(o, wi, tmax, sc.medium, sc.medium_grid, key,
                                             TRACK_DIM + bounce * TRACK_STRIDE + TRACK_STRIDE // 2))
    return _mul(c, transmittance(o, wi, tmax, sc.medium))


@njit(cache=True, inline="always")
def medium_step(sc, key, o, d, t, bounce, max_depth, rr_depth, ld, ls, bd, bs, w0, prev_pdf, out):
    """Free flight along o + t d up to the next surface at ``t``, and the scattering event where one is drawn:
    (step, o, d, ld, ls, bd, bs, w0, prev_pdf), step 0 where the path goes on to the surface, 1 where it scattered
    and goes on from (o, d), 2 where it ends. The free flight draws the one dimension of a bounce that no surface
    uses, so the surfaces keep their random numbers."""
    base = 2 + bounce * DIMS_PER_BOUNCE
    if HAS_HETEROGENEOUS and sc.medium_grid.shape[0] > 0:
        scattered, ts, wm = tracked_free_flight(o, d, t, sc.medium, sc.medium_grid, key,
                                                TRACK_DIM + bounce * TRACK_STRIDE)
    else:
        scattered, ts, wm = free_flight(o, d, t, sc.medium, rand(key, base + 7))
    if bounce == 0:
        w0 = wm
    else:
        bd, bs = _mul(bd, wm), _mul(bs, wm)
    if not scattered:
        return 0, o, d, ld, ls, bd, bs, w0, prev_pdf
    if bounce == 0:
        out[12] = ts  # albedo and normal stay 0, as in the background (docs/formats.md)
    if bounce == max_depth:
        return 2, o, d, ld, ls, bd, bs, w0, prev_pdf
    x = _madd(o, d, ts)
    ld, ls, wi, bd, bs, prev_pdf = medium_vertex(sc, key, base, x, d, bounce, ld, ls, bd, bs)
    if bounce >= rr_depth:
        alive, bd, bs = roulette(bd, bs, rand(key, base + 6))
        if not alive:
            return 2, x, wi, ld, ls, bd, bs, w0, prev_pdf
    return 1, x, wi, ld, ls, bd, bs, w0, prev_pdf


@njit(cache=True, inline="always")
def facing(ng, d):
    """(cosine of ``d`` to the geometric normal, the shading normal): surfaces are double-sided, shaded on the
    side the ray came from."""
    cos_d = _dot(ng, d)
    return cos_d, (_scale(ng, -1.0) if cos_d > 0.0 else ng)


@njit(cache=True, inline="always")
def has_diffuse(mk):
    """Whether material kind ``mk`` has a diffuse lobe (an albedo)."""
    return (HAS_LAMBERT and mk == LAMBERT) or (HAS_PLASTIC and mk == PLASTIC)


@njit(cache=True, inline="always")
def first_hit(out, bounce, kd, n, t):
    """The auxiliary features of the camera ray's first surface (bounce 0): albedo, normal, depth."""
    if bounce == 0:
        out[6], out[7], out[8] = kd
        out[9], out[10], out[11] = n
        out[12] = t


@njit(cache=True, inline="always")
def finish(out, ld, ls, w0):
    """out[0:6] = the path's diffuse and specular radiance, scaled by the medium's weight ``w0`` on the camera
    ray; a non-finite sample (should not happen) counts as black rather than poisoning its pixel."""
    if HAS_MEDIUM:
        ld, ls = _mul(ld, w0), _mul(ls, w0)
    if all_finite(ld, ls):
        out[0], out[1], out[2] = ld
        out[3], out[4], out[5] = ls


# ---------------------------------------------------------------------------------------------
# the integrator
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def trace_sample(o, d, key, sc, max_depth, rr_depth, out):
    """Trace one camera ray through the packed scene ``sc``: out[0:13] = diffuse, specular, albedo, normal, depth."""
    out[:13] = 0.0
    zero = (0.0, 0.0, 0.0)
    # radiance, throughputs of the first vertex's diffuse and glossy parts, the medium's weight on the camera ray
    ld, ls, bd, bs, w0 = zero, zero, zero, zero, (1.0, 1.0, 1.0)
    prev_pdf = 0.0  # of the direction that led here; < 0 after a delta (mirror, glass) vertex
    materials, light_prob, lt = sc.materials, sc.light_prob, sc.light_table
    for bounce in range(max_depth + 1):
        t, kind, idx = intersect(o, d, np.inf, sc)
        if HAS_MESH:  # triangles after spheres and quads, up to the nearer hit (t is inf on a miss)
            tm, ti = intersect_mesh(o, d, t, sc)
            if ti >= 0:
                t, kind, idx = tm, 2, ti
        if HAS_MEDIUM:
            step, o, d, ld, ls, bd, bs, w0, prev_pdf = medium_step(sc, key, o, d, t, bounce, max_depth, rr_depth,
                                                                   ld, ls, bd, bs, w0, prev_pdf, out)
            if step == 2:
                break
            if step == 1:
                continue
        if kind < 0:
            env, w = escaped(sc, d, bounce, prev_pdf)
            ld, ls = add_emitted(ld, ls, bd, bs, env, w, bounce)
            break
        p = _madd(o, d, t)
        ng, tu, tv = surface(p, kind, idx, sc.spheres, sc.quads, sc.triangles)
        m = sc.tri_mat[idx] if HAS_MESH and kind == 2 else (sc.sphere_mat[idx] if kind == 0 else sc.quad_mat[idx])
        mk = int(materials[m, M_KIND])
        cos_d, n = facing(ng, d)
        kd = albedo_at(sc, m, p, tu, tv) if has_diffuse(mk) else zero
        first_hit(out, bounce, kd, n, t)
        if HAS_EMITTER and mk == EMITTER:
            if cos_d < 0.0:  # front side only
                w = emitter_weight(sc, kind, idx, o, t, cos_d, bounce, prev_pdf)
                ld, ls = add_emitted(ld, ls, bd, bs, _row3(materials, m, M_EMISSION), w, bounce)
            break
        if bounce == max_depth:
            break
        base = 2 + bounce * DIMS_PER_BOUNCE
        if (HAS_MIRROR and mk == MIRROR) or (HAS_GLASS and mk == GLASS):  # a delta vertex: no light sampling
            origin, wi, bd, bs = continue_delta(key, base, HAS_GLASS and mk == GLASS, _row3(materials, m, M_SPECULAR),
                                                materials[m, M_IOR], p, n, d, cos_d, bounce, bd, bs)
            prev_pdf = -1.0
        else:
            ks, alpha = _row3(materials, m, M_SPECULAR), materials[m, M_ROUGHNESS]
            wo = _scale(d, -1.0)
            origin = _madd(p, n, RAY_OFFSET)
            if (HAS_EMITTER or HAS_ENVIRONMENT_MAP) and sc.lights.shape[0] > 0:
                # next-event estimation: a light picked by power, a sample on it, MIS-weighted against the BSDF
                li = search_cdf(sc.light_cdf, rand(key, base))
                lk, u1, u2 = sc.light_kind[li], rand(key, base + 1), rand(key, base + 2)
                lit, wi, tmax, pdf_l, le = False, n, 0.0, 0.0, zero
                if HAS_ENVIRONMENT_MAP and lk == L_ENVIRONMENT:
                    wi, pdf_dir, le = env_sample(sc, u1, u2)
                    lit, tmax, pdf_l = pdf_dir > 0.0, np.inf, light_prob[li] * pdf_dir
                elif HAS_EMITTER:
                    lit, wi, tmax, pdf_l = toward_light(lk, _row3(lt, li, L_A), _row3(lt, li, L_B), _row3(lt, li, L_C),
                                                        _row3(lt, li, L_NORMAL), lt[li, L_AREA], origin,
                                                        light_prob[li], u1, u2)
                    le = _row3(lt, li, L_EMISSION)
                ci = _dot(n, wi)
                if lit and ci > 0.0:
                    fd, fs, pdf_b = bsdf_eval(mk, kd, ks, alpha, n, wo, wi)
                    if pdf_b > 0.0 and not (occluded(origin, wi, tmax, sc)
                                            or (HAS_MESH and occluded_mesh(origin, wi, tmax, sc))):
                        c = _scale(le, ci * power_heuristic(pdf_l, pdf_b) / pdf_l)
                        if HAS_MEDIUM:
                            c = through_medium(c, sc, key, bounce, origin, wi, tmax)
                        ld, ls = add_direct(ld, ls, bd, bs, fd, fs, c, bounce)
            ok, wi, bd, bs, prev_pdf = continue_bsdf(key, base, mk, kd, ks, alpha, n, wo, bounce, bd, bs)
            if not ok:
                break
        o, d = origin, wi
        if bounce >= rr_depth:
            alive, bd, bs = roulette(bd, bs, rand(key, base + 6))
            if not alive:
                break
    finish(out, ld, ls, w0)


@njit(cache=True, inline="always")
def all_finite(a, b):
    """Whether every component of the RGB tuples a and b is finite."""
    good = True
    for c in range(3):
        if not (math.isfinite(a[c]) and math.isfinite(b[c])):
            good = False
    return good


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
