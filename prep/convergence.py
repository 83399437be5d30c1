"""How converged a reference render is, from its own variance layers (the references of
some families are themselves speckled, and training on them teaches the network that a speckle is signal).

A kpcn render's ``<x>Variance`` layers are the **variance of the pixel mean** (``prep.render.integrator``:
the unbiased per-sample variance divided by spp, per channel, then averaged over R G B), so their square root
is already the standard error of the pixel's estimate; nothing here divides by spp again. The relative
standard error of a colour ``c`` (H, W, 3) with variance layer ``v`` (H, W) is, per pixel,

    relSE = sqrt(max(v, 0)) / (max(mean_RGB(c), 0) + CONVERGENCE_EPS)

The mean over R G B, not the luminance: the variance layer is itself the mean of the three channels'
variances, so numerator and denominator weigh the channels alike. ``CONVERGENCE_EPS`` keeps dark pixels
(where any absolute error is invisible after tonemapping) from reading as unconverged, as relMSE's 0.01
does (``prep.metrics``). A pixel is *converged* when relSE <= ``CONVERGED_RELSE``.

The same measure serves each branch (:func:`branch_relse`): the diffuse colour with ``diffuseVariance``,
the specular with ``specularVariance``, the final colour (``default``) with ``colorVariance``. The diffuse
branch's target is the diffuse colour divided by the albedo; to first order a relative error is unchanged
by that division (the albedo's own noise is far below the colour's), so the diffuse colour's relSE is the
relSE of the diffuse target too.

:func:`frame_summary` reduces one frame to the figures ``kpcn references`` reports: median and p99 relSE,
the fraction of converged pixels, and the spp at which p99 would reach ``CONVERGED_RELSE`` were the error
to fall as 1 / sqrt(spp) (``spp * (p99 / CONVERGED_RELSE) ** 2``). That is an estimate, not a promise: a
family whose rare paths only appear at more samples sees relSE *rise* with spp (caustics did, from 512 to
2048 spp: docs/scenes.md §4), so a change of sample counts is measured, not extrapolated. No numba, no
torch: numpy only.
"""

from __future__ import annotations

import math

import numpy as np

from prep.exr import VARIANCE_OF, AOVError

CONVERGENCE_EPS = 0.01  # added to the mean colour in relSE's denominator (the relMSE constant of prep.metrics)
CONVERGED_RELSE = 0.05  # a pixel whose reference relSE is at most this is converged
SUMMARY_PERCENTILE = 99.0  # the tail a frame is judged by

# branch (or "default", the final colour) -> its colour layer and that layer's variance
BRANCH_LAYERS = {layer: (layer, VARIANCE_OF[layer]) for layer in ("diffuse", "specular", "default")}


def relative_standard_error(colour: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """Per-pixel relSE (module docstring) of ``colour`` (H, W, 3) whose variance of the mean is ``variance``
    (H, W); float32 (H, W), computed in float64."""
    colour = np.asarray(colour, dtype=np.float64)
    variance = np.asarray(variance, dtype=np.float64)
    if colour.ndim != 3 or colour.shape[-1] != 3 or variance.shape != colour.shape[:2]:
        raise ValueError(f"colour must be (H, W, 3) and variance (H, W), got {colour.shape} and {variance.shape}")
    se = np.sqrt(np.maximum(variance, 0.0))
    return (se / (np.maximum(colour.mean(axis=-1), 0.0) + CONVERGENCE_EPS)).astype(np.float32)


def branch_relse(layers: dict, branch: str, path=None) -> np.ndarray:
    """relSE (H, W) of ``branch`` (``diffuse``, ``specular`` or ``default``) of a render read by
    ``prep.exr.read_aovs``; AOVError naming ``path`` and the layer if the variance layer is not there."""
    colour_name, variance_name = BRANCH_LAYERS[branch]
    if variance_name not in layers:
        raise AOVError(f"{path or 'render'}: no layer {variance_name!r}, which the convergence of its {branch} "
                       f"colour is measured from (a kpcn render has it; render the reference with kpcn render)")
    return relative_standard_error(layers[colour_name], layers[variance_name])


def needed_spp(spp: int, p99: float) -> float:
    """The spp at which a tail relSE of ``p99`` measured at ``spp`` would reach :data:`CONVERGED_RELSE`,
    were it to fall as 1 / sqrt(spp)."""
    return float(spp) * (float(p99) / CONVERGED_RELSE) ** 2


def frame_summary(relse: np.ndarray, spp: int) -> dict:
    """``median``, ``p99``, ``converged`` (fraction of pixels with relSE <= :data:`CONVERGED_RELSE`) and
    ``spp_needed`` (:func:`needed_spp` at p99) of one frame's relSE map, measured at ``spp``."""
    r = np.asarray(relse, dtype=np.float64).ravel()
    p99 = float(np.percentile(r, SUMMARY_PERCENTILE))
    return {"spp": int(spp), "median": float(np.median(r)), "p99": p99,
            "converged": float(np.mean(r <= CONVERGED_RELSE)), "spp_needed": _rounded(needed_spp(spp, p99))}


def _rounded(x: float) -> int | float:
    return int(math.ceil(x)) if math.isfinite(x) else x


__all__ = ["BRANCH_LAYERS", "CONVERGED_RELSE", "CONVERGENCE_EPS", "SUMMARY_PERCENTILE", "branch_relse",
           "frame_summary", "needed_spp", "relative_standard_error"]
