"""The variance of two renders' mean estimated from their difference, for renderers that write none: what
``kpcn denoise A --pair B`` fed the variance network until it measured worse than the mean alone on the Cycles
validation frames (``reports/adapt_pair_join.json``). Kept for the studies that compare the two
(``inputs_study``, ``remodulation``); the library joins a pair by ``prep.inputs.mean_layers``."""

from __future__ import annotations

import dataclasses

import numpy as np

from prep.exr import VARIANCE_OF, to_float32
from prep.inputs import InputSet, box_mean

PAIR_SMOOTHING = 1  # radius of the box that smooths a two-buffer variance: 3x3


def pair_variance(a: np.ndarray, b: np.ndarray, radius: int = PAIR_SMOOTHING) -> np.ndarray:
    """Variance of the mean (a + b) / 2 of two independent renders of the same pixels, one (H, W) layer:
    (a - b)^2 / 4 averaged over the channels, smoothed by a (2 radius + 1)^2 box. (a - b)^2 / 4 is unbiased
    for each pixel (E (a - b)^2 = 2 var(a) and var((a + b) / 2) = var(a) / 2) but has one degree of freedom;
    the box trades a little bias at edges for 9 of them."""
    d = np.asarray(a, np.float64) - np.asarray(b, np.float64)
    v = d * d / 4.0
    if v.ndim == 3:
        v = v.mean(axis=-1)
    return to_float32(box_mean(v, radius) if radius else v)


def pair_layers(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One frame from two renders of it with different seeds: each layer the mean of the two, and the
    variance layers from their difference (:func:`pair_variance`). Without a split (``diffuse`` in neither),
    ``diffuseVariance`` and ``specularVariance`` are the colour's, as every layout without a split gives them."""
    out = {k: to_float32((np.asarray(a[k], np.float64) + b[k]) / 2.0) for k in a if k in b}
    split = "diffuse" in a and "diffuse" in b
    for layer in ("default", "albedo", "normal", "depth", *(("diffuse", "specular") if split else ())):
        out[VARIANCE_OF[layer]] = pair_variance(a[layer], b[layer])
    if not split:
        out["diffuseVariance"] = out["specularVariance"] = out["colorVariance"]
    return out


def read_with_pair_variance(first, second):
    """``first`` and ``second``, two renders of one frame (``batch.read_halves``' checks), as one frame of their mean
    with the variance of their difference (:func:`pair_layers`): the variance network's input set."""
    from kpcn_keras.batch import ReadOptions, read_halves

    a, b = read_halves(first, ReadOptions(pair=second))
    return dataclasses.replace(a, layers=pair_layers(a.layers, b.layers), inputs=InputSet(a.inputs.split, True),
                               spp=a.spp + b.spp if a.spp and b.spp else None)
