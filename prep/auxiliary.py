"""The auxiliary layers a frame gives the networks: as rendered, or prefiltered first (docs/results/26).

The networks read a frame's ``albedo``, ``normal`` and ``depth`` (:data:`AUXILIARIES`) as features (``prep.features``)
and the diffuse branch is multiplied back by the albedo (``prep.albedo``). At a few samples those layers are noisy
themselves (edges, textures finer than a pixel, depth of field, motion blur, what glass shows). :func:`auxiliaries`
is the one place a frame's auxiliaries are chosen, by :data:`METHODS`:

=========  ====================================================================================================
method     the auxiliaries given
=========  ====================================================================================================
raw        the layers as rendered (what every network has been trained and served with)
clean      those of a cleaner render of the same frame (``clean=``: e.g. the scene's render at the most samples
           below the reference; a study's oracle, the ceiling of what a prefilter could give)
oidn       OIDN's auxiliary filters, as Blender runs them before its colour filter: the albedo and the normal each
           denoised by an ``RT`` filter with that layer alone (``prep.baselines.oidn_filter_auxiliary``); the depth
           through the albedo's filter, as a grey image divided by its maximum (OIDN has no depth slot) and
           multiplied back
nlm        kpcn's own prefilter, ``prep.albedo``'s variance-guided non-local means, on each of the three (the
           normal clipped to [-1, 1], the depth not clipped), with the frame's variance of that layer where it has
           one, else :func:`local_variance`
=========  ====================================================================================================

Every other layer (colour, split, variances) is the frame's own array, not copied: the variance layers still
describe the rendered auxiliaries (a network trained on prefiltered auxiliaries learns with them so).

A network is trained and served with one of :data:`TRAINED` (``kpcn shards --auxiliaries``; ``clean`` needs a
second render, which a frame to denoise does not have): the shard writer cuts its patches from
:func:`network_layers` of each noisy input, and the denoiser (``kpcn_keras.denoise``) gives its networks
:func:`network_layers` of each frame, the same function, so a network is served its auxiliaries exactly as it was
trained on them. :func:`check_method` refuses, in one line, a method that cannot run here.
"""

from __future__ import annotations

import numpy as np

from prep import albedo as albedo_filter
from prep.errors import KpcnError
from prep.exr import VARIANCE_OF, to_float32
from prep.inputs import InputSet, restrict

AUXILIARIES = ("albedo", "normal", "depth")
METHODS = ("raw", "clean", "oidn", "nlm")
TRAINED = ("raw", "oidn", "nlm")  # the methods a network is trained and served with (no second render needed)
RAW = "raw"  # what every network trained before the option existed was given: left out of records at this value
# the clip before the filter, as each layer's feature clips it (prep.features): None for the depth
BOUNDS = {"albedo": (0.0, 1.0), "normal": (-1.0, 1.0), "depth": None}
# the four directions of the second differences of local_variance: along x, y and both diagonals
DIRECTIONS = ((0, 1), (1, 0), (1, 1), (1, -1))
VARIANCE_BOX = 1  # local_variance averages each direction's estimate over (2 * 1 + 1)^2 pixels


def local_variance(layer: np.ndarray, radius: int = VARIANCE_BOX) -> np.ndarray:
    """An estimate of the variance of the pixel's mean of ``layer`` (H, W) or (H, W, C), one value a pixel (H, W),
    from the layer alone, for frames whose renderer writes none (Cycles): for each of :data:`DIRECTIONS`, the
    squared second difference x(p - d) - 2 x(p) + x(p + d) over 6 (whose mean is the variance of independent
    noise of one variance, any linear ramp cancelling), averaged over the channels and a (2 radius + 1)^2 box;
    the smallest of the four. Along a straight edge one direction sees no step, so an edge without noise reads
    about 0 and is kept, where a plain local variance would read the step as noise and blur it; a constant layer
    reads exactly 0. Pixels beyond the frame are its edge's. Float64 arithmetic, float32 out."""
    x = np.asarray(layer, np.float64)
    x = x[..., None] if x.ndim == 2 else x
    h, w = x.shape[:2]
    pad = 1 + radius
    xp = np.pad(x, ((pad, pad), (pad, pad), (0, 0)), mode="edge")
    best = None
    for dy, dx in DIRECTIONS:
        hh, ww = h + 2 * radius, w + 2 * radius  # the pixels and the box around them
        c = xp[1 : 1 + hh, 1 : 1 + ww]
        before = xp[1 - dy : 1 - dy + hh, 1 - dx : 1 - dx + ww]
        after = xp[1 + dy : 1 + dy + hh, 1 + dx : 1 + dx + ww]
        s = ((before - 2.0 * c + after) ** 2).mean(axis=-1) / 6.0
        box = sum(s[i : i + h, j : j + w] for i in range(2 * radius + 1) for j in range(2 * radius + 1))
        est = box / (2 * radius + 1) ** 2
        best = est if best is None else np.minimum(best, est)
    return to_float32(best)


def nlm_layer(layer: np.ndarray, name: str, variance: np.ndarray | None = None) -> np.ndarray:
    """``layer`` (one of :data:`AUXILIARIES`) prefiltered by ``prep.albedo.prefilter`` with ``variance`` (H, W;
    :func:`local_variance` of the layer where None or all 0), clipped to the layer's :data:`BOUNDS`; float32 in
    the layer's shape (a depth (H, W) is filtered as three equal channels, which the formula treats as one)."""
    x = np.asarray(layer, np.float32)
    if variance is None or not np.any(np.asarray(variance) > 0):
        variance = local_variance(np.clip(x, *BOUNDS[name]) if BOUNDS[name] else x)
    three = np.repeat(x[..., None], 3, axis=-1) if x.ndim == 2 else x
    out = albedo_filter.prefilter(three, variance, bounds=BOUNDS[name])
    return out[..., 0].copy() if x.ndim == 2 else out


def _oidn(layers: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    from prep.baselines import oidn_filter_auxiliary

    depth = np.asarray(layers["depth"], np.float64)
    top = float(depth.max()) if depth.size else 0.0
    out = {"albedo": oidn_filter_auxiliary(layers["albedo"], "albedo"),
           "normal": oidn_filter_auxiliary(layers["normal"], "normal")}
    if top > 0:
        grey = np.repeat((np.maximum(depth, 0.0) / top)[..., None], 3, axis=-1)
        out["depth"] = to_float32(oidn_filter_auxiliary(grey, "albedo").mean(axis=-1, dtype=np.float64) * top)
    else:  # no depth to speak of (0 everywhere): nothing to filter
        out["depth"] = layers["depth"]
    return out


def auxiliaries(layers: dict[str, np.ndarray], method: str = "raw", *,
                clean: dict[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """``layers`` (a frame's, ``prep.layouts`` names) with its :data:`AUXILIARIES` given by ``method`` (one of
    :data:`METHODS`, the module docstring); every other layer the same array. ``clean``: the layers of the
    cleaner render, for ``clean`` (of the same size). KpcnError naming what is wrong for another method, a
    ``clean`` without its layers or of another size; ImportError (naming the package) for ``oidn`` without
    ``pyoidn``."""
    if method not in METHODS:
        raise KpcnError(f"auxiliaries {method!r}: expected one of {', '.join(METHODS)}")
    if method == "raw":
        return dict(layers)
    if method == "clean":
        if clean is None or any(k not in clean for k in AUXILIARIES):
            raise KpcnError("auxiliaries 'clean': give the cleaner render's layers (albedo, normal, depth)")
        for k in AUXILIARIES:
            if np.shape(clean[k]) != np.shape(layers[k]):
                raise KpcnError(f"auxiliaries 'clean': its {k} is {np.shape(clean[k])}, the frame's "
                                f"{np.shape(layers[k])}")
        new = {k: clean[k] for k in AUXILIARIES}
    elif method == "oidn":
        new = _oidn(layers)
    else:
        new = {k: nlm_layer(layers[k], k, layers.get(VARIANCE_OF[k])) for k in AUXILIARIES}
    return {**layers, **new}


def check_method(method: str, what: str) -> str:
    """``method`` if a network can be trained and served with it here (one of :data:`TRAINED`, and ``pyoidn``
    importable for ``oidn``); else KpcnError in one line naming ``what`` (an option, a model folder) and the
    remedy."""
    if method not in TRAINED:
        raise KpcnError(f"{what}: auxiliaries {method!r}: expected one of {', '.join(TRAINED)}")
    if method == "oidn":
        import importlib.util

        if importlib.util.find_spec("pyoidn") is None:
            raise KpcnError(f"{what}: its auxiliaries are prefiltered by OIDN (--auxiliaries oidn), which needs the "
                            "optional package pyoidn: pip install 'kpcn[oidn]'")
    return method


def network_layers(layers: dict[str, np.ndarray], inputs: InputSet, method: str = RAW) -> dict[str, np.ndarray]:
    """What a network of the input set ``inputs`` trained with ``method`` (one of :data:`TRAINED`) is given of a
    frame's ``layers``: the frame as that set reads it (``prep.inputs.restrict``), then its auxiliaries by
    ``method`` (:func:`auxiliaries`, on the whole frame: OIDN and the NLM filter see all of it). The one function
    both the shard writer and the denoiser call; with ``raw`` it is ``restrict`` alone."""
    return auxiliaries(restrict(layers, inputs), method)
