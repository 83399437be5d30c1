"""Light sampling for next-event estimation: the geometry of each light kind, as pbrt's ``Light::SampleLi``.

The functions take a light's geometry as tuples and numbers (read from the light table, ``packing.LIGHT_*``, by
the integrator, which dispatches on ``sc.light_kind`` under its ``HAS_*`` flags) and the probability ``prob``
with which it was picked.
A ``toward_*`` function returns ``(lit, wi, tmax, pdf)`` for a sample seen from ``origin``: ``wi`` the unit
direction towards it, ``tmax`` the distance a shadow ray along it tests (short of the light itself), ``pdf`` the
solid-angle density of the sample times ``prob``; ``lit`` is False, and pdf 0, where the light can send origin
nothing (behind a planar light, inside a sphere light). The ``*_density`` functions give the same density at a
direction BSDF sampling found, for the MIS weight of an emitter a path hits.

None of them takes the packed scene or an array: every function is inlined into the integrator
(``inline="always"``), and numba increments and decrements the reference count of every array of an argument
it binds, per call; passing ``sc`` to an inlined function made the render 30-45% slower. ``kernels.py`` digests
this file with the integrator's other callees.
"""

from __future__ import annotations

import math

from numba import njit

from prep.render.tracer import _dot, _madd, _scale, _sub, _to_world


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
def quad_point(corner, u, v, u1, u2):
    """A uniform point on the rectangle ``corner + a u + b v``."""
    return _madd(_madd(corner, u, u1), v, u2)


@njit(cache=True, inline="always")
def triangle_point(v0, e1, e2, u1, u2):
    """A uniform point on the triangle ``v0, v0 + e1, v0 + e2``."""
    su = math.sqrt(u1)
    return _madd(_madd(v0, e1, u2 * su), e2, su * (1.0 - u2))


@njit(cache=True, inline="always")
def _cone_one_minus(sin2):
    """1 - cos of the half-angle of a cone whose sine squared is ``sin2``, without cancellation."""
    return sin2 / (1.0 + math.sqrt(max(0.0, 1.0 - sin2)))


@njit(cache=True, inline="always")
def _cone_density(prob, one_minus):
    """Solid-angle density of a direction uniform in a cone of ``1 - cos`` = ``one_minus``, times ``prob``."""
    return prob / (2.0 * math.pi * one_minus)


@njit(cache=True, inline="always")
def toward_sphere_light(origin, centre, radius, prob, u1, u2):
    """A direction uniform in the cone the sphere subtends from origin (unlit from inside it)."""
    wc = _sub(centre, origin)
    dc2 = _dot(wc, wc)
    r2 = radius * radius
    if not dc2 > r2:
        return False, wc, 0.0, 0.0
    dc = math.sqrt(dc2)
    one_minus = _cone_one_minus(r2 / dc2)
    ct = 1.0 - u1 * one_minus
    st = math.sqrt(max(0.0, 1.0 - ct * ct))
    phi = 2.0 * math.pi * u2
    wi = _to_world((st * math.cos(phi), st * math.sin(phi), ct), _scale(wc, 1.0 / dc))
    b = _dot(wc, wi)
    tmax = (b - math.sqrt(max(0.0, b * b - dc2 + r2))) * (1.0 - 1e-5)
    return True, wi, tmax, _cone_density(prob, one_minus)


@njit(cache=True, inline="always")
def sphere_density(origin, centre, radius, prob):
    """The density of :func:`toward_sphere_light` from ``origin`` (at any direction inside the cone)."""
    wc = _sub(centre, origin)
    return _cone_density(prob, _cone_one_minus(radius * radius / _dot(wc, wc)))
