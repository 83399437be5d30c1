"""Network inputs of the diffuse and specular branches (docs/method.md §1, §2; docs/formats.md §2).

Features are those of the full image: a patch or a tile cut from them sees the true gradients at its
borders. They can be computed for a window of the image alone (:func:`branch_features` with ``window``): a
pixel's features read only that pixel, the next one along x and along y (the forward differences) and one
whole-image statistic, the depth scale 1 / max(depth) (:func:`depth_scale`), computed once by a cheap pass
over the depth layer. So a window's features equal the same pixels of the whole image's, bit for bit, and a
caller that streams windows (tiled inference) holds features of one window at a time. Each branch gets
``NUM_FEATURES`` = 27 channels, in this order:

=======  ==========================  =====================================================  ==============
channel  name                        formula                                                range
=======  ==========================  =====================================================  ==============
0-2      colour                      c = log(1 + max(x, 0)), x = branch colour (below)      [0, 94.5]
3-5      dx colour                   c[y, x+1] - c[y, x]  (0 in the last column)            [-95, 95]
6-8      dx normal                   n = clip(normal, -1, 1), forward difference            [-2, 2]
9-11     dx albedo                   a = clip(albedo, 0, 1), forward difference             [-1, 1]
12       dx depth                    d = depth / max(depth) (0 if max <= 0), forward diff.  [-1, 1]
13-22    dy of the same              forward differences along y (0 in the last row)        as above
23       relvar colour               log(1 + v_c / (mean_ch(c^2) + REL_EPS))                [0, 300]
24       relvar normal               log(1 + v_n / (mean_ch(n^2) + REL_EPS))                [0, 300]
25       relvar albedo               log(1 + v_a / (mean_ch(a^2) + REL_EPS))                [0, 300]
26       relvar depth                log(1 + v_d / (d^2 + REL_EPS))                         [0, 300]
=======  ==========================  =====================================================  ==============

Branch colour x: diffuse branch: irradiance = diffuse / (albedo + ALBEDO_EPS), albedo clipped to
[0, 1]; specular branch: the specular layer. Variances are carried through the same transforms
by the delta method: irradiance variance = diffuseVariance / (albedo + ALBEDO_EPS)^2, log-colour
variance v_c = var(x) / (1 + x)^2, depth variance / max(depth)^2. Each relative variance is taken
against the transformed buffer and compressed by log(1 + .), so every feature is finite and inside
the range above for any finite input (arithmetic is float64; the bounds are those of float32
input). Negative variances (a renderer's rounding) count as 0.

The features are made in two steps, one function each, so that the feature definition has one owner:
:func:`branch_buffers` (the numba kernel) computes the per-pixel buffers, the transformed colour, normal,
albedo and depth (:data:`BUFFERS`) over the window and the next row and column, and the relative variances
23-26; :func:`features_from_buffers` (vectorised numpy, any leading batch axes) takes the values and forward
differences of the buffers. :func:`branch_features` is the two at render time, on float64 buffers; a shard
stores the buffers in float16 and its reader makes the features with the same second function
(``prep.shards.format``).

The transforms (the irradiance, the log colour, the delta method, the relative variance) and their inverses
are ``prep.colour``'s, with their constants. The numba kernel writes their per-pixel arithmetic itself, the same
float operations on scalars, and is handed the constants as arguments: numba's on-disk cache checks only the file
a function is in, so a kernel that called into ``prep.colour`` or read its constants as globals would be served
stale after an edit there. ``tests/test_colour.py`` holds the kernel's buffers to ``prep.colour``'s functions.

:func:`reference_features` evaluates the same table in plain float64 numpy, from ``prep.colour``'s array
functions and a relative variance of its own, sharing nothing with the numba kernel but the constants: the
tests hold the kernel to it, and ``kpcn_keras.studies.data_costs`` times the two.
"""

from __future__ import annotations

import numba
import numpy as np

from prep.colour import (
    ALBEDO_EPS,
    REL_EPS,
    diffuse_to_log,
    irradiance,
    irradiance_variance,
    log_colour,
    log_variance,
    specular_to_log,
)
from prep.exr import VARIANCE_OF

NUM_FEATURES = 27
FEATURE_NAMES = (
    ["colour.R", "colour.G", "colour.B"]
    + [f"dx_{b}.{c}" for b in ("colour", "normal", "albedo") for c in "RGB"]
    + ["dx_depth"]
    + [f"dy_{b}.{c}" for b in ("colour", "normal", "albedo") for c in "RGB"]
    + ["dy_depth"]
    + ["relvar_colour", "relvar_normal", "relvar_albedo", "relvar_depth"]
)
BRANCHES = ("diffuse", "specular")
assert len(FEATURE_NAMES) == NUM_FEATURES


# Serial on purpose: one 256x256 branch is ~3 ms of work, and with parallel=True the thread start and
# barriers cost more than they save, by 5x in the median when another process holds a core (measured:
# median 30 ms parallel against 7 ms serial for both branches). Callers that cut many images (kpcn shards)
# get their parallelism from images, not from pixels.
@numba.njit(cache=True, nogil=True)
def _depth_max(depth):
    """max(0, max(depth)), NaN ignored: the statistic behind :func:`depth_scale`."""
    h, w = depth.shape
    dmax = 0.0
    for y in range(h):
        for x in range(w):
            if depth[y, x] > dmax:
                dmax = depth[y, x]
    return dmax


@numba.njit(cache=True, nogil=True)
def _relative_variance(variance, mean_square, rel_eps):
    """``prep.colour.relative_variance`` as the kernel computes it (module docstring)."""
    return np.log1p(max(variance, 0.0) / (mean_square + rel_eps))


@numba.njit(cache=True, nogil=True)
def _buffers_kernel(colour, colour_var, albedo, albedo_var, normal, normal_var, depth, depth_var, divide_albedo,
                    dscale, albedo_eps, rel_eps, buffers, relvar):
    """Fill the pixel buffers of one branch (:func:`branch_buffers`): ``buffers`` (input rows, input columns,
    BUFFER_CHANNELS) with the transformed buffers the differences read, ``relvar`` (h, w, 4) with the relative
    variances of out's own pixels; colour is linear, albedo divided when divide_albedo."""
    h, w = relvar.shape[0], relvar.shape[1]
    hi, wi = depth.shape
    for y in range(hi):
        for x in range(wi):
            vc = max(float(colour_var[y, x]), 0.0)
            sq_c = 0.0
            sq_n = 0.0
            sq_a = 0.0
            vlog = 0.0
            for c in range(3):
                a = min(max(float(albedo[y, x, c]), 0.0), 1.0)
                buffers[y, x, 6 + c] = a
                n = min(max(float(normal[y, x, c]), -1.0), 1.0)
                buffers[y, x, 3 + c] = n
                v = float(colour[y, x, c])
                var_c = vc
                if divide_albedo:
                    v = v / (a + albedo_eps)
                    var_c = vc / ((a + albedo_eps) * (a + albedo_eps))
                v = max(v, 0.0)
                lc = np.log1p(v)
                buffers[y, x, c] = lc
                vlog += var_c / ((1.0 + v) * (1.0 + v))
                sq_c += lc * lc
                sq_n += n * n
                sq_a += a * a
            d = max(float(depth[y, x]), 0.0) * dscale
            buffers[y, x, 9] = d
            if y < h and x < w:
                relvar[y, x, 0] = _relative_variance(vlog / 3.0, sq_c / 3.0, rel_eps)
                relvar[y, x, 1] = _relative_variance(float(normal_var[y, x]), sq_n / 3.0, rel_eps)
                relvar[y, x, 2] = _relative_variance(float(albedo_var[y, x]), sq_a / 3.0, rel_eps)
                relvar[y, x, 3] = _relative_variance(max(float(depth_var[y, x]), 0.0) * dscale * dscale, d * d, rel_eps)


# The per-pixel buffers the features are made of, in two kinds (what a shard stores: ``prep.shards.format``):
# the transformed buffers whose forward differences are features (BUFFERS, read at a pixel and its next
# neighbours), and the relative variances (RELVARS, read at the pixel alone). The buffers' channel order is that
# of the dx (and dy) block, so channels 3-22 are their differences in one operation each.
BUFFERS = (("colour", 3), ("normal", 3), ("albedo", 3), ("depth", 1))
BUFFER_CHANNELS = sum(n for _, n in BUFFERS)  # 10 float64 per pixel of the window grown by one row and column
RELVARS = ("colour", "normal", "albedo", "depth")
COLOUR, DX, DY, RELVAR = slice(0, 3), slice(3, 13), slice(13, 23), slice(23, 27)
assert DX.stop - DX.start == BUFFER_CHANNELS and RELVAR.stop - RELVAR.start == len(RELVARS)

_GUIDE_LAYERS = ("albedo", "normal", "depth")  # after the branch's colour, each followed by its variance: the kernel's


def depth_scale(depth: np.ndarray) -> float:
    """1 / max(depth) over the whole image, 0 when max(depth) <= 0: the features' one whole-image quantity
    (every other feature of a pixel reads that pixel and its next neighbours only)."""
    dmax = _depth_max(np.ascontiguousarray(depth))
    return 1.0 / dmax if dmax > 0.0 else 0.0


def branch_buffers(aovs: dict[str, np.ndarray], branch: str, window: tuple[int, int, int, int] | None = None,
                   *, scale: float | None = None, relvar: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The per-pixel buffers of ``branch``'s features over ``window`` (y0, y1, x0, x1; default the whole
    image) of a noisy render: ``(buffers, relvar)``, what :func:`features_from_buffers` makes the features of.

    ``buffers`` (h + 1, w + 1, BUFFER_CHANNELS) float64: the log colour, clipped normal, clipped albedo and
    scaled depth (:data:`BUFFERS`) of the window's pixels and of the next row and column; past the image's
    last row or column that row or column is the last one repeated, so its forward differences are the 0 of
    the table. ``relvar`` (h, w, 4): channels 23-26 of the table, written into the array given (any float
    dtype, a view of the features' own: :func:`branch_features`), else a new float64 one. ``scale``: the whole
    image's :func:`depth_scale` (computed here when not given).
    """
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
    h, w = aovs["depth"].shape
    y0, y1, x0, x1 = (0, h, 0, w) if window is None else window
    if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
        raise ValueError(f"window must lie inside the {h}x{w} image and hold a pixel, got {window}")
    if scale is None:
        scale = depth_scale(aovs["depth"])
    rows, cols = slice(y0, min(y1 + 1, h)), slice(x0, min(x1 + 1, w))
    names = [n for layer in (branch,) + _GUIDE_LAYERS for n in (layer, VARIANCE_OF[layer])]
    # The kernel widens each value to float64 itself: float32 renders (what prep.exr reads) go in without a
    # float64 copy of every layer; anything else is widened here, so at most two specialisations compile.
    dtype = np.float32 if all(aovs[n].dtype == np.float32 for n in names) else np.float64
    layers = [np.ascontiguousarray(aovs[n][rows, cols], dtype=dtype) for n in names]
    hi, wi = layers[-2].shape
    buffers = np.empty((y1 - y0 + 1, x1 - x0 + 1, BUFFER_CHANNELS))
    if relvar is None:
        relvar = np.empty((y1 - y0, x1 - x0, len(RELVARS)))
    _buffers_kernel(*layers, branch == "diffuse", float(scale), ALBEDO_EPS, REL_EPS, buffers[:hi, :wi], relvar)
    if hi == y1 - y0:  # the image's last row: its neighbour is itself
        buffers[hi] = buffers[hi - 1]
    if wi == x1 - x0:
        buffers[:, wi] = buffers[:, wi - 1]
    return buffers, relvar


def features_from_buffers(buffers: np.ndarray, relvar: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """The features (..., h, w, 27) float32 of per-pixel buffers (..., h + 1, w + 1, BUFFER_CHANNELS) and
    relative variances (..., h, w, 4) (:func:`branch_buffers`), any number of leading (batch) axes: the one
    place the table's values and differences are made, at render time (:func:`branch_features`, float64
    buffers) and when a shard's stored buffers are read (``prep.shards.format.read_patches``, float16 ones).

    The differences are taken in float64 for float64 buffers (each feature is the float64 value rounded once
    to float32, as the table's reference :func:`reference_features` is) and in float32 otherwise, which is
    exact for two float16 values of like magnitude: a stored buffer's rounding is the only error it adds.
    No temporary the size of the features is made (the bound of tiled inference's memory counts on it).
    """
    h, w = relvar.shape[-3], relvar.shape[-2]
    if buffers.shape[-3:] != (h + 1, w + 1, BUFFER_CHANNELS) or buffers.shape[:-3] != relvar.shape[:-3]:
        raise ValueError(f"buffers {buffers.shape} do not fit relative variances {relvar.shape}")
    if out is None:
        out = np.empty(relvar.shape[:-1] + (NUM_FEATURES,), np.float32)
    loop = np.result_type(buffers.dtype, np.float32)
    value = buffers[..., :h, :w, :]
    np.copyto(out[..., COLOUR], value[..., COLOUR], casting="same_kind")
    np.subtract(buffers[..., :h, 1:, :], value, out=out[..., DX], dtype=loop, casting="same_kind")
    np.subtract(buffers[..., 1:, :w, :], value, out=out[..., DY], dtype=loop, casting="same_kind")
    if not np.shares_memory(relvar, out):
        np.copyto(out[..., RELVAR], relvar, casting="same_kind")
    return out


def branch_features(aovs: dict[str, np.ndarray], branch: str, window: tuple[int, int, int, int] | None = None,
                    *, scale: float | None = None) -> np.ndarray:
    """The (H, W, 27) float32 network input of ``branch`` ('diffuse' or 'specular') for one render.

    ``aovs`` is a noisy render as returned by :func:`prep.exr.read_aovs` (variance layers needed).
    ``window`` = (y0, y1, x0, x1): only those rows and columns, equal bit for bit to the same pixels of the
    whole image's features, from the window's pixels and the next row and column alone; ``scale``: the
    whole image's :func:`depth_scale` (computed here when not given: a caller cutting many windows passes it).
    :func:`branch_buffers`, then :func:`features_from_buffers`. Memory: the result, a float32 copy of the
    window of the 14 input channels and ``BUFFER_CHANNELS`` float64 per pixel of the window grown by one row
    and column.
    """
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
    h, w = aovs["depth"].shape
    y0, y1, x0, x1 = (0, h, 0, w) if window is None else window
    out = np.empty((max(y1 - y0, 0), max(x1 - x0, 0), NUM_FEATURES), dtype=np.float32)
    buffers, relvar = branch_buffers(aovs, branch, window, scale=scale, relvar=out[..., RELVAR])
    return features_from_buffers(buffers, relvar, out)


def reference_features(aovs: dict[str, np.ndarray], branch: str) -> np.ndarray:
    """The (H, W, 27) features of ``branch`` in float64, by whole-array numpy from the table in the module
    docstring: the reference that :func:`branch_features` is tested (and timed) against."""
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
    f64 = {name: np.asarray(image, np.float64) for name, image in aovs.items()}
    a = np.clip(f64["albedo"], 0.0, 1.0)
    n = np.clip(f64["normal"], -1.0, 1.0)
    depth = np.maximum(f64["depth"], 0.0)
    dmax = depth.max()
    scale = 1.0 / dmax if dmax > 0 else 0.0
    d = depth * scale
    x = f64[branch]
    var = np.maximum(f64[VARIANCE_OF[branch]], 0.0)[..., None]
    if branch == "diffuse":
        x = irradiance(x, a)
        var = irradiance_variance(var, a)
    x = np.maximum(x, 0.0)
    c = log_colour(x)
    v_c = np.mean(log_variance(var, x), axis=-1)

    def dx(img):
        out = np.zeros_like(img)
        out[:, :-1] = img[:, 1:] - img[:, :-1]
        return out

    def dy(img):
        out = np.zeros_like(img)
        out[:-1] = img[1:] - img[:-1]
        return out

    def relvar(v, mean_square):
        return np.log1p(np.maximum(v, 0.0) / (mean_square + REL_EPS))[..., None]

    return np.concatenate(
        [c, dx(c), dx(n), dx(a), dx(d)[..., None], dy(c), dy(n), dy(a), dy(d)[..., None],
         relvar(v_c, np.mean(c * c, axis=-1)),
         relvar(f64["normalVariance"], np.mean(n * n, axis=-1)),
         relvar(f64["albedoVariance"], np.mean(a * a, axis=-1)),
         relvar(np.maximum(f64["depthVariance"], 0.0) * scale**2, d * d)],
        axis=-1,
    )


def branch_colour(aovs: dict[str, np.ndarray], branch: str, albedo: np.ndarray | None = None) -> np.ndarray:
    """The branch colour in the network's log domain, (H, W, 3) float32 (channels 0-2 of the features):
    ``prep.colour.diffuse_to_log`` or ``specular_to_log``, whose inverses are ``diffuse_from_log`` and
    ``specular_from_log``.

    ``albedo`` overrides the render's own albedo for the irradiance divide (used for references).
    """
    if branch not in BRANCHES:
        raise ValueError(f"branch must be one of {BRANCHES}, got {branch!r}")
    if branch == "diffuse":
        return diffuse_to_log(aovs[branch], aovs["albedo"] if albedo is None else albedo).astype(np.float32)
    return specular_to_log(aovs[branch]).astype(np.float32)
