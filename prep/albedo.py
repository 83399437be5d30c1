"""The albedo a denoised diffuse branch is multiplied back by (docs/method.md §2).

The diffuse network predicts irradiance: it is trained against the reference's irradiance, the reference diffuse
divided by the reference's own albedo (``prep.shards.format``; the division and its inverse, the remodulation, are
``prep.colour.irradiance`` and ``remodulate``). Multiplied back by the *noisy* albedo, the frame
gets the albedo's own Monte Carlo noise back: where a pixel's samples see different albedos (texture detail finer
than a pixel, an edge, a surface out of focus) the input's albedo is a mean of a few of them, the reference's a
mean of thousands. So the denoiser multiplies by the albedo prefiltered by non-local means with its per-pixel
variance (Rousselle, Knaus and Zwicker 2012, the prefilter of feature buffers in NFOR, Bitterli et al. 2016):

    d²(p, q) = 1 / (3 |P|) Σ_{n in P} Σ_c [(a_c(p+n) - a_c(q+n))² - (v(p+n) + min(v(p+n), v(q+n)))]
                                           / (EPS + k² (v(p+n) + v(q+n)))
    out(p) = Σ_q w(p, q) a(q) / Σ_q w(p, q),   w = exp(-max(d², 0)),

q over the (2r + 1)² pixels around p, P the (2f + 1)² offsets of a patch, a the albedo clipped to [0, 1] (what
remodulation uses), v its variance (of the pixel's mean, one value a pixel, every channel) averaged over the
(2s + 1)² pixels around each (a variance from a few samples is noisy itself: a pixel whose samples happened to
agree reads 0), pixels beyond the frame those of its edge. The variance term cancels the expected squared
difference of two noisy pixels of one albedo, so two such patches weigh about 1 whatever the noise, two different
ones fall off by how many of their standard deviations apart they are (k). A pixel whose albedo has no variance,
nor its neighbours' (every sample saw the same albedo), is converged and kept as it is. ``tests/test_albedo.py``
holds the filter to a float64 numpy evaluation of the formula.

The filter reads a pixel's (r + f + s)-neighbourhood and nothing else of the frame, so a region of the frame
filtered alone (``region``, a tile of tiled inference) equals the same pixels of the frame filtered whole.
"""

from __future__ import annotations

import numba
import numpy as np

# Chosen on training scenes by the error the filtered albedo leaves in their frames
# (docs/results/19-albedo-prefilter.md): a wider search or patch removed little more and cost up to 2.3x the
# time; the averaged variance removed more
SEARCH_RADIUS = 3  # r: a pixel draws on the 7 x 7 pixels around it
PATCH_RADIUS = 1  # f: compared by their 3 x 3 neighbourhoods
STRENGTH = 1.0  # k: how many standard deviations apart two patches may be before their weight falls
VARIANCE_RADIUS = 1  # s: the variance averaged over 3 x 3 pixels
EPS = 1e-10  # keeps d² finite where both patches have no variance (then any difference rules q out)


def prefilter(albedo: np.ndarray, variance: np.ndarray, region: tuple[int, int, int, int] | None = None,
              *, r: int = SEARCH_RADIUS, f: int = PATCH_RADIUS, k: float = STRENGTH,
              s: int = VARIANCE_RADIUS, bounds: tuple[float, float] | None = (0.0, 1.0)) -> np.ndarray:
    """The prefiltered albedo (float32, clipped to [0, 1]) of ``region`` (y0, y1, x0, x1; the whole frame by
    default) of a frame's ``albedo`` (H, W, 3) and its per-pixel ``variance`` (H, W). ``bounds``: what the
    layer is clipped to first ((-1, 1) for a normal, None for a depth: ``prep.auxiliary`` filters those too)."""
    h, w = albedo.shape[:2]
    y0, y1, x0, x1 = (0, h, 0, w) if region is None else region
    m = r + f
    ys = np.clip(np.arange(y0 - m, y1 + m), 0, h - 1)
    xs = np.clip(np.arange(x0 - m, x1 + m), 0, w - 1)
    # the window first, then float64: a tile's filter never holds a copy of the whole frame
    a = np.asarray(albedo)[ys[:, None], xs[None, :]].astype(np.float64)
    if bounds is not None:
        a = np.clip(a, *bounds)
    v = _box_mean(np.asarray(variance), ys, xs, s, h, w)
    if not (v[m : m + y1 - y0, m : m + x1 - x0] > 0.0).any():  # every pixel converged (or no variance layer)
        return a[m : m + y1 - y0, m : m + x1 - x0].astype(np.float32)
    out = np.empty((y1 - y0, x1 - x0, 3), dtype=np.float64)
    _nlm(a, v, r, f, k * k, out)
    return out.astype(np.float32)


def _box_mean(variance: np.ndarray, ys: np.ndarray, xs: np.ndarray, s: int, h: int, w: int) -> np.ndarray:
    """The variance (negatives as 0) at the pixels ``ys`` x ``xs`` of an (h, w) frame, each the mean over the
    (2s + 1)² pixels around it, those beyond the frame its edge's; summed in one order for every pixel, so that a
    region's values equal the whole frame's bit for bit (which ``prep.inputs``' summed-area box, cut at the border,
    does not give)."""
    total = np.zeros((len(ys), len(xs)))
    for dy in range(-s, s + 1):
        for dx in range(-s, s + 1):
            rows, cols = np.clip(ys + dy, 0, h - 1), np.clip(xs + dx, 0, w - 1)
            total += np.maximum(variance[rows[:, None], cols[None, :]].astype(np.float64), 0.0)
    return total / (2 * s + 1) ** 2


@numba.njit(cache=True, parallel=True)
def _nlm(a, v, r, f, k2, out):
    """``out`` (H, W, 3) from ``a`` (H + 2m, W + 2m, 3) and ``v`` (H + 2m, W + 2m), m = r + f: the module's
    formula, one offset q - p at a time (its squared differences box-filtered over the patch)."""
    h, w = out.shape[:2]
    m = r + f
    side = 2 * f + 1
    ph, pw = h + 2 * f, w + 2 * f  # the pixels p + n: the region and a patch radius around it
    norm = 1.0 / (3.0 * side * side)
    acc = np.zeros((h, w, 3))
    wsum = np.zeros((h, w))
    dist = np.empty((ph, pw))
    rows = np.empty((ph, w))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            for y in numba.prange(ph):
                for x in range(pw):
                    vp = v[y + r, x + r]
                    vq = v[y + r + dy, x + r + dx]
                    s = 0.0
                    for c in range(3):
                        d = a[y + r, x + r, c] - a[y + r + dy, x + r + dx, c]
                        s += d * d
                    dist[y, x] = (s - 3.0 * (vp + min(vp, vq))) / (EPS + k2 * (vp + vq))
            for y in numba.prange(ph):  # summed afresh, not as a running sum: a term may be ~1e10
                for x in range(w):
                    t = 0.0
                    for i in range(side):
                        t += dist[y, x + i]
                    rows[y, x] = t
            for y in numba.prange(h):
                for x in range(w):
                    if v[y + m, x + m] <= 0.0:  # kept as it is below: no weight to compute
                        continue
                    t = 0.0
                    for j in range(side):
                        t += rows[y + j, x]
                    wt = np.exp(-max(t * norm, 0.0))
                    wsum[y, x] += wt
                    for c in range(3):
                        acc[y, x, c] += wt * a[y + m + dy, x + m + dx, c]
    for y in numba.prange(h):
        for x in range(w):
            if v[y + m, x + m] > 0.0:
                for c in range(3):
                    out[y, x, c] = acc[y, x, c] / wsum[y, x]
            else:
                for c in range(3):
                    out[y, x, c] = a[y + m, x + m, c]
