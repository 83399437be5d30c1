"""Light sampling for next-event estimation: one function per light kind, as pbrt's ``Light::SampleLi``.

Each ``sample_*`` takes the light's row ``q`` in its table (``sc.quads``, ``sc.triangles``, ``sc.spheres``; the
environment map has none), the probability ``prob`` with which it was picked, the shading point ``origin`` and
two uniform numbers, and returns ``(lit, wi, tmax, pdf, le)``: ``wi`` the unit direction from origin towards the
sample, ``tmax`` the distance a shadow ray along it tests (short of the light itself), ``pdf`` the solid-angle
density of the sample times ``prob``, ``le`` the radiance the light sends along ``-wi``. ``lit`` is False, and
pdf 0, where the light can send origin nothing (behind a planar light, inside a sphere light, a direction of
zero density on the map). The ``*_density`` functions are the same densities at a direction BSDF sampling found
(``pdf_li``), for the MIS weight of an emitter a path hits.

Which kinds a kernel compiles in is the integrator's choice: ``integrator.sample_light`` dispatches on
``sc.light_kind`` under its ``HAS_*`` flags, and this file has none. Every function here is inlined into the
integrator (``inline="always"``), so ``kernels.py`` digests this file with the integrator's other callees.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from prep.render.tracer import (
    M_EMISSION,
    Q_AREA,
    Q_CORNER,
    Q_NORMAL,
    Q_U,
    Q_V,
    T_AREA,
    T_E1,
    T_E2,
    T_NORMAL,
    T_V0,
    _dot,
    _madd,
    _row3,
    _scale,
    _sub,
    _to_world,
    env_sample,
)


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


@njit(cache=True, inline="always")
def planar_density(prob, t, cos_l, area):
    """The density of :func:`toward_planar_light` at a point at distance ``t`` whose light sees the direction at
    cosine ``cos_l`` (> 0). Written from t, not from the squared distance as when sampling, to keep the rounding
    the renders were made with."""
    return prob * t * t / (cos_l * area)


@njit(cache=True, inline="always")
def sample_quad(sc, q, prob, origin, u1, u2):
    """A uniform point on rectangle ``q``."""
    quads = sc.quads
    point = _madd(_madd(_row3(quads, q, Q_CORNER), _row3(quads, q, Q_U), u1), _row3(quads, q, Q_V), u2)
    lit, wi, tmax, pdf = toward_planar_light(origin, point, _row3(quads, q, Q_NORMAL), quads[q, Q_AREA], prob)
    return lit, wi, tmax, pdf, _row3(sc.materials, sc.quad_mat[q], M_EMISSION)


@njit(cache=True, inline="always")
def sample_triangle(sc, q, prob, origin, u1, u2):
    """A uniform point on triangle ``q`` of an emissive mesh."""
    tris = sc.triangles
    su = math.sqrt(u1)
    point = _madd(_madd(_row3(tris, q, T_V0), _row3(tris, q, T_E1), u2 * su), _row3(tris, q, T_E2), su * (1.0 - u2))
    lit, wi, tmax, pdf = toward_planar_light(origin, point, _row3(tris, q, T_NORMAL), tris[q, T_AREA], prob)
    return lit, wi, tmax, pdf, _row3(sc.materials, sc.tri_mat[q], M_EMISSION)


@njit(cache=True, inline="always")
def _cone_one_minus(sin2):
    """1 - cos of the half-angle of a cone whose sine squared is ``sin2``, without cancellation."""
    return sin2 / (1.0 + math.sqrt(max(0.0, 1.0 - sin2)))


@njit(cache=True, inline="always")
def _cone_density(prob, one_minus):
    """Solid-angle density of a direction uniform in a cone of ``1 - cos`` = ``one_minus``, times ``prob``."""
    return prob / (2.0 * math.pi * one_minus)


@njit(cache=True, inline="always")
def sample_sphere(sc, q, prob, origin, u1, u2):
    """A direction uniform in the cone sphere ``q`` subtends from origin (unlit from inside it)."""
    wc = _sub(_row3(sc.spheres, q, 0), origin)
    dc2 = _dot(wc, wc)
    r2 = sc.spheres[q, 3] * sc.spheres[q, 3]
    if not dc2 > r2:
        zero = (0.0, 0.0, 0.0)
        return False, zero, 0.0, 0.0, zero
    dc = math.sqrt(dc2)
    one_minus = _cone_one_minus(r2 / dc2)
    ct = 1.0 - u1 * one_minus
    st = math.sqrt(max(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * u2
    wi = _to_world((st * math.cos(phi), st * math.sin(phi), ct), _scale(wc, 1.0 / dc))
    b = _dot(wc, wi)
    tmax = (b - math.sqrt(max(0.0, b * b - dc2 + r2))) * (1.0 - 1e-5)
    return True, wi, tmax, _cone_density(prob, one_minus), _row3(sc.materials, sc.sphere_mat[q], M_EMISSION)


@njit(cache=True, inline="always")
def sphere_density(sc, q, prob, origin):
    """The density of :func:`sample_sphere` from ``origin`` (at any direction inside the cone)."""
    wc = _sub(_row3(sc.spheres, q, 0), origin)
    return _cone_density(prob, _cone_one_minus(sc.spheres[q, 3] * sc.spheres[q, 3] / _dot(wc, wc)))


@njit(cache=True, inline="always")
def sample_environment(sc, prob, u1, u2):
    """A direction of the environment map, in proportion to texel luminance x solid angle (``tracer.env_sample``);
    its shadow ray is unbounded."""
    wi, pdf_dir, le = env_sample(sc, u1, u2)
    if pdf_dir > 0.0:
        return True, wi, np.inf, prob * pdf_dir, le
    return False, wi, 0.0, 0.0, le
