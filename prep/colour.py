"""The colour transforms, each written once beside its inverse (docs/method.md §1, §2, §9), after Intel Open Image
Denoise's ``training/color.py``: whatever goes into the networks' log domain and back, and what goes to a screen.

==========================  ==============================================  ===========================================
forward                     formula                                         inverse
==========================  ==============================================  ===========================================
:func:`irradiance`          x / (clip(albedo, 0, 1) + ALBEDO_EPS)           :func:`remodulate`
:func:`log_colour`          log(1 + max(x, 0))                              :func:`linear_colour`: exp(c) - 1
:func:`diffuse_to_log`      log_colour(irradiance(diffuse, albedo))         :func:`diffuse_from_log`
:func:`specular_to_log`     log_colour(specular)                            :func:`specular_from_log`
:func:`log_variance`        var(x) / (1 + x)^2 (the delta method)           :func:`linear_variance`
:func:`relative_variance`   log(1 + max(v, 0) / (mean_square + REL_EPS))   :func:`variance_of`
:func:`tonemap`             (y / (1 + y))^(1 / 2.2), y = max(x, 0)          none (below)
==========================  ==============================================  ===========================================

The forward transforms work in float64 whatever they are given. :func:`remodulate` (and so
:func:`diffuse_from_log`) adds ALBEDO_EPS to the albedo in the albedo's own precision: a float32 albedo (a frame's,
or the prefiltered one of ``prep.albedo``) gives ``clip(albedo) + ALBEDO_EPS`` rounded to float32, a relative
6e-8, which is what every denoised frame has been made with; a float64 albedo gives the inverse of
:func:`irradiance` to float64 rounding. The irradiance's variance is carried by :func:`irradiance_variance`;
nothing needs it back.

Where else a transform is written, and what holds it to these: the per-pixel numba kernel of ``prep.features``
(the features' colour and relative variances, the same float operations on scalars, handed these constants:
numba's on-disk cache sees only the kernel's own file; ``tests/test_colour.py`` holds its buffers to these
functions), ``FinalColour`` in ``kpcn_keras.layers`` (the inverse in ``keras.ops``, on these constants, clamped at
:data:`LOG_LINEAR_MAX`; ``tests/test_layers.py`` holds it to :func:`diffuse_from_log` + :func:`specular_from_log`)
and the page of ``kpcn view`` (:func:`tonemap` in JavaScript, after the exposure; ``tests/test_viewer_browser.py``
holds it to this one).

:func:`tonemap` has no inverse on purpose: it is the display transform of every PNG and panel and of DSSIM and
PSNR (``prep.metrics``), and nothing is ever computed back from a tonemapped image. (It is invertible on [0, 1):
y = t^2.2 / (1 - t^2.2); 1 itself is infinity.)
"""

from __future__ import annotations

import numba
import numpy as np

ALBEDO_EPS = 0.00316
REL_EPS = 0.01
# Largest log colour any float32 input can give: log1p(float32 max / ALBEDO_EPS), about 94.48. The
# colour features (and every network output in the log domain) lie in [0, LOG_COLOUR_MAX].
LOG_COLOUR_MAX = float(np.log1p(np.float64(np.finfo(np.float32).max) / ALBEDO_EPS))
# Largest relative variance any float32 input can give: a depth variance of float32 max at a miss (d = 0) in
# an image whose largest depth is the smallest subnormal (depth scale 1 / that), about 299.89.
RELVAR_MAX = float(np.log1p(np.float64(np.finfo(np.float32).max)
                            / np.float64(np.finfo(np.float32).smallest_subnormal) ** 2 / REL_EPS))
# exp() of a log colour above this would overflow float32 once remodulated and summed; a kernel output
# never gets there on real data, but a clamp keeps a wild early training step finite (``FinalColour``)
LOG_LINEAR_MAX = float(np.log(np.finfo(np.float32).max / 4))
GAMMA = 2.2  # the display gamma of :func:`tonemap`

# What a shard set records of the transforms its buffers were made with (its manifest and every shard's
# attributes: ``prep.shards``): the words of the two forward transforms and their constants.
DESCRIPTION = "diffuse: log1p(diffuse / (albedo + ALBEDO_EPS)); specular: log1p(max(specular, 0))"
CONSTANTS = {"ALBEDO_EPS": ALBEDO_EPS, "REL_EPS": REL_EPS}


def _albedo_term(albedo: np.ndarray) -> np.ndarray:
    """clip(albedo, 0, 1) + ALBEDO_EPS in float64: what the irradiance is divided by."""
    return np.clip(np.asarray(albedo, dtype=np.float64), 0.0, 1.0) + ALBEDO_EPS


def irradiance(diffuse: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """The irradiance of a diffuse colour, ``diffuse / (clip(albedo, 0, 1) + ALBEDO_EPS)``, float64;
    :func:`remodulate` is its inverse."""
    return np.asarray(diffuse, dtype=np.float64) / _albedo_term(albedo)


def remodulate(irradiance: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """The diffuse colour of an irradiance, ``irradiance * (clip(albedo, 0, 1) + ALBEDO_EPS)``, float64, the albedo
    term in the albedo's own precision (module docstring)."""
    return np.asarray(irradiance, dtype=np.float64) * (np.clip(albedo, 0.0, 1.0) + ALBEDO_EPS)


def irradiance_variance(variance: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """The variance of :func:`irradiance` of a colour whose variance is ``variance`` (the albedo taken as exact):
    ``variance / (clip(albedo, 0, 1) + ALBEDO_EPS)^2``, float64."""
    return np.asarray(variance, dtype=np.float64) / _albedo_term(albedo) ** 2


def log_colour(x: np.ndarray) -> np.ndarray:
    """The networks' log domain, ``log(1 + max(x, 0))``, float64; :func:`linear_colour` is its inverse (on x >= 0:
    a negative colour, a renderer's rounding, comes back as 0)."""
    return np.log1p(np.maximum(np.asarray(x, dtype=np.float64), 0.0))


def linear_colour(c: np.ndarray) -> np.ndarray:
    """The linear colour of a log colour, ``exp(c) - 1``, float64."""
    return np.expm1(np.asarray(c, dtype=np.float64))


def log_variance(variance: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The variance of :func:`log_colour` of a colour ``x`` (>= 0, already clamped) whose variance is ``variance``,
    by the delta method: ``variance / (1 + x)^2``; :func:`linear_variance` is its inverse."""
    return variance / (1.0 + x) ** 2


def linear_variance(variance: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The variance of a colour ``x`` whose log colour has variance ``variance``: ``variance * (1 + x)^2``."""
    return variance * (1.0 + x) ** 2


def diffuse_to_log(diffuse: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """The diffuse branch's colour in the log domain, the log of its irradiance, float64."""
    return log_colour(irradiance(diffuse, albedo))


def diffuse_from_log(log_irradiance: np.ndarray, albedo: np.ndarray) -> np.ndarray:
    """Inverse of :func:`diffuse_to_log`: ``(exp(c) - 1) * (clip(albedo, 0, 1) + ALBEDO_EPS)``, float64."""
    return remodulate(linear_colour(log_irradiance), albedo)


def specular_to_log(specular: np.ndarray) -> np.ndarray:
    """The specular branch's colour in the log domain, float64."""
    return log_colour(specular)


def specular_from_log(log_specular: np.ndarray) -> np.ndarray:
    """Inverse of :func:`specular_to_log`: ``exp(c) - 1``, float64."""
    return linear_colour(log_specular)


@numba.njit(cache=True, nogil=True)
def relative_variance(variance, mean_square):
    """A buffer's relative variance feature (channels 23-26 of ``prep.features``): ``log(1 + max(variance, 0) /
    (mean_square + REL_EPS))``, ``mean_square`` the pixel's mean square of the transformed buffer; :func:`variance_of`
    is its inverse. Both take float scalars (the features' kernel's per pixel, ``kpcn_keras.fireflies``' per spike)."""
    return np.log1p(max(variance, 0.0) / (mean_square + REL_EPS))


@numba.njit(cache=True, nogil=True)
def variance_of(relvar, mean_square):
    """The variance whose :func:`relative_variance` against ``mean_square`` is ``relvar``."""
    return np.expm1(relvar) * (mean_square + REL_EPS)


def tonemap(x: np.ndarray) -> np.ndarray:
    """Display transform: Reinhard x / (1 + x) of max(x, 0), then gamma 1/2.2; values in [0, 1], float64. No
    inverse (module docstring)."""
    x = np.maximum(np.asarray(x, dtype=np.float64), 0.0)
    return (x / (1.0 + x)) ** (1.0 / GAMMA)
