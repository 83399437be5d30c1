"""A homogeneous participating medium in an axis-aligned box: what the ``medium`` kernels add to a path.

The medium (``scene.Medium``, packed by ``packing.py`` into ``sc.medium``, columns ``MD_*``) has an RGB absorption
coefficient ``sigma_a``, a grey scattering coefficient ``sigma_s`` and a Henyey-Greenstein phase function of
asymmetry ``g``. Only kernels whose ``HAS_MEDIUM`` flag is on call these functions (``integrator.py``), so a scene
without a medium compiles none of this.

Free-flight sampling draws the distance to a scattering event in proportion to ``sigma_s exp(-sigma_s s)`` and
carries absorption as a weight: a segment that crosses the box without scattering is weighted by
``exp(-sigma_a L)`` (its transmittance divided by the probability ``exp(-sigma_s L)`` of drawing no event), one that
scatters at ``s`` by ``exp(-sigma_a s)`` (``sigma_s exp(-sigma_t s)`` over the density). A purely absorbing medium
(``sigma_s = 0``) is thus rendered without noise, and the weights stay RGB while the distances are drawn once
for all channels. Shadow rays multiply by the analytic transmittance ``exp(-sigma_t L)``, L the length of the
shadow ray inside the box.

HG convention: ``cos`` is the cosine between the direction the light travelled before the event (the ray
direction ``d``) and the direction after it; ``g > 0`` scatters forwards.
"""

from __future__ import annotations

import math

from numba import njit

from prep.render.tracer import _dot, _scale, _to_world

# Columns of sc.medium, mirrored from packing.MEDIUM_* (a test checks they agree): absorption RGB, scattering,
# HG asymmetry, the box's low and high corners.
MD_SIGMA_A, MD_SIGMA_S, MD_G, MD_LO, MD_HI = 0, 3, 4, 5, 8
INV_4PI = 1.0 / (4.0 * math.pi)


@njit(cache=True, inline="always")
def box_span(o, d, tmax, med):
    """The part (t0, t1) of the ray o + t d, t in [0, tmax], inside the medium's box; t0 >= t1 where it misses
    (always, for the empty box of a scene without a medium)."""
    if not med[MD_HI] > med[MD_LO]:
        return 1.0, 0.0
    t0 = 0.0
    t1 = tmax
    for a in range(3):
        lo = med[MD_LO + a]
        hi = med[MD_HI + a]
        if d[a] == 0.0:
            if o[a] < lo or o[a] > hi:
                return 1.0, 0.0
            continue
        inv = 1.0 / d[a]
        ta = (lo - o[a]) * inv
        tb = (hi - o[a]) * inv
        if ta > tb:
            ta, tb = tb, ta
        t0 = max(t0, ta)
        t1 = min(t1, tb)
    return t0, t1


@njit(cache=True, inline="always")
def transmittance(o, d, tmax, med):
    """RGB transmittance exp(-sigma_t L) of the ray o + t d (d unit), t in [0, tmax], L its length inside the box."""
    t0, t1 = box_span(o, d, tmax, med)
    if t1 <= t0:
        return (1.0, 1.0, 1.0)
    length = t1 - t0
    s = med[MD_SIGMA_S]
    return (math.exp(-(med[0] + s) * length), math.exp(-(med[1] + s) * length), math.exp(-(med[2] + s) * length))


@njit(cache=True, inline="always")
def free_flight(o, d, tmax, med, u):
    """Free-flight sampling along o + t d up to tmax (the next surface, inf on a miss): (scattered, t, weight),
    ``t`` the distance to the scattering event where scattered, ``weight`` the RGB absorption weight of the
    segment walked (see the module's docstring)."""
    t0, t1 = box_span(o, d, tmax, med)
    if t1 <= t0:
        return False, tmax, (1.0, 1.0, 1.0)
    length = t1 - t0
    sigma_s = med[MD_SIGMA_S]
    scattered = False
    if sigma_s > 0.0:
        s = -math.log1p(-u) / sigma_s
        if s < length:
            scattered = True
            length = s
    w = (math.exp(-med[0] * length), math.exp(-med[1] * length), math.exp(-med[2] * length))
    return scattered, t0 + length, w


@njit(cache=True, inline="always")
def hg_eval(g, cos):
    """The Henyey-Greenstein phase function (per steradian) at cosine ``cos`` to the travel direction."""
    denom = 1.0 + g * g - 2.0 * g * cos
    return INV_4PI * (1.0 - g * g) / (denom * math.sqrt(denom))


@njit(cache=True, inline="always")
def hg_sample(g, d, u1, u2):
    """A direction drawn from the HG phase function about the travel direction ``d`` (unit): (wi, density)."""
    if abs(g) < 1e-3:
        cos = 1.0 - 2.0 * u1
    else:
        sq = (1.0 - g * g) / (1.0 - g + 2.0 * g * u1)
        cos = (1.0 + g * g - sq * sq) / (2.0 * g)
    cos = min(1.0, max(-1.0, cos))
    sin = math.sqrt(max(0.0, 1.0 - cos * cos))
    phi = 2.0 * math.pi * u2
    wi = _to_world((sin * math.cos(phi), sin * math.sin(phi), cos), d)
    return wi, hg_eval(g, cos)


@njit(cache=True, inline="always")
def phase_value(g, d, wi):
    """(phase RGB, density of :func:`hg_sample`) of the direction ``wi`` after travelling along ``d``."""
    p = hg_eval(g, _dot(d, wi))
    return _scale((1.0, 1.0, 1.0), p), p
