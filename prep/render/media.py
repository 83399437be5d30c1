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

A heterogeneous medium (``Medium.density = "noise"``, the ``heterogeneous`` effect) scales both coefficients by a
density grid (``sc.medium_grid``, trilinear) and is tracked against a majorant (``MD_MAJORANT``): weighted delta
tracking for free flight, ratio tracking for shadow rays (:func:`tracked_free_flight`,
:func:`tracked_transmittance`). Their random numbers are dimensions of their own (``TRACK_DIM`` on), as many as
the collisions a ray meets.

HG convention: ``cos`` is the cosine between the direction the light travelled before the event (the ray
direction ``d``) and the direction after it; ``g > 0`` scatters forwards.
"""

from __future__ import annotations

import math

from numba import njit

from prep.render.tracer import _dot, _madd, _scale, _to_world, rand

# Columns of sc.medium, mirrored from packing.MEDIUM_* (a test checks they agree): absorption RGB, scattering,
# HG asymmetry, the box's low and high corners.
MD_SIGMA_A, MD_SIGMA_S, MD_G, MD_LO, MD_HI, MD_MAJORANT = 0, 3, 4, 5, 8, 11
# tracking's random dimensions: bounce b's free flight from TRACK_DIM + b TRACK_STRIDE, its shadow ray from half a
# stride further; far above the dimensions of the surfaces and of the lens (tracer.LENS_DIM = 2**40)
TRACK_DIM = 1 << 41
TRACK_STRIDE = 1 << 20
MAX_COLLISIONS = (1 << 18) - 2  # a guard: a ray meets about majorant x length of them
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


# ---------------------------------------------------------------------------------------------
# heterogeneous density (HAS_HETEROGENEOUS kernels): a grid over the box, tracked against a majorant
# ---------------------------------------------------------------------------------------------

@njit(cache=True, inline="always")
def _cell(p, med, a, n):
    """(lattice index, fraction) of p along axis a of a grid of n points spanning the box."""
    x = (p[a] - med[MD_LO + a]) / (med[MD_HI + a] - med[MD_LO + a]) * (n - 1)
    x = min(max(x, 0.0), n - 1.0)
    k = min(int(x), n - 2)
    return k, x - k


@njit(cache=True, inline="always")
def density_at(grid, med, p):
    """The density grid (n x n x n values at the lattice points spanning the box) trilinearly interpolated at p."""
    n = grid.shape[0]
    i, fx = _cell(p, med, 0, n)
    j, fy = _cell(p, med, 1, n)
    k, fz = _cell(p, med, 2, n)
    c00 = grid[i, j, k] * (1.0 - fx) + grid[i + 1, j, k] * fx
    c10 = grid[i, j + 1, k] * (1.0 - fx) + grid[i + 1, j + 1, k] * fx
    c01 = grid[i, j, k + 1] * (1.0 - fx) + grid[i + 1, j, k + 1] * fx
    c11 = grid[i, j + 1, k + 1] * (1.0 - fx) + grid[i + 1, j + 1, k + 1] * fx
    return ((c00 * (1.0 - fy) + c10 * fy) * (1.0 - fz) + (c01 * (1.0 - fy) + c11 * fy) * fz)


@njit(cache=True)
def tracked_free_flight(o, d, tmax, med, grid, key, dim0):
    """Free flight in a medium of density ``grid``: weighted delta tracking against the majorant mu (>= sigma_t x
    density everywhere, every channel). Tentative collisions at rate mu; one at x is a scattering event with
    probability sigma_s(x) / mu (weight 1), else a null collision weighted by (mu - sigma_t(x)) / (mu - sigma_s(x))
    per channel, which carries absorption as the homogeneous :func:`free_flight` does. Random numbers: dimensions
    ``dim0``, ``dim0 + 1``, ... of ``key``. Returns (scattered, t, weight) as :func:`free_flight`."""
    one = (1.0, 1.0, 1.0)
    t0, t1 = box_span(o, d, tmax, med)
    mu = med[MD_MAJORANT]
    if t1 <= t0 or mu <= 0.0:
        return False, tmax, one
    sa, ss = (med[0], med[1], med[2]), med[MD_SIGMA_S]
    w0, w1, w2 = 1.0, 1.0, 1.0
    t = t0
    j = 0
    while j < MAX_COLLISIONS:
        t -= math.log1p(-rand(key, dim0 + j)) / mu
        if t >= t1:
            break
        rho = density_at(grid, med, _madd(o, d, t))
        if rand(key, dim0 + j + 1) * mu < ss * rho:
            return True, t, (w0, w1, w2)
        j += 2
        null = mu - ss * rho
        w0 *= (mu - (sa[0] + ss) * rho) / null
        w1 *= (mu - (sa[1] + ss) * rho) / null
        w2 *= (mu - (sa[2] + ss) * rho) / null
    return False, tmax, (w0, w1, w2)


@njit(cache=True)
def tracked_transmittance(o, d, tmax, med, grid, key, dim0):
    """Ratio tracking: an unbiased estimate of the RGB transmittance of o + t d, t in [0, tmax], through the
    density ``grid``, the product of 1 - sigma_t(x) / mu over tentative collisions at rate mu."""
    t0, t1 = box_span(o, d, tmax, med)
    mu = med[MD_MAJORANT]
    if t1 <= t0 or mu <= 0.0:
        return (1.0, 1.0, 1.0)
    ss = med[MD_SIGMA_S]
    w0, w1, w2 = 1.0, 1.0, 1.0
    t = t0
    for j in range(MAX_COLLISIONS):
        t -= math.log1p(-rand(key, dim0 + j)) / mu
        if t >= t1:
            break
        rho = density_at(grid, med, _madd(o, d, t))
        w0 *= 1.0 - (med[0] + ss) * rho / mu
        w1 *= 1.0 - (med[1] + ss) * rho / mu
        w2 *= 1.0 - (med[2] + ss) * rho / mu
    return (w0, w1, w2)
