"""Physics-preserving augmentation of training patches (pure numpy).

An :class:`Augmentation` is one of the 8 symmetries of the square (``spatial``) together with one of
the 6 permutations of R, G, B (``colour``); :func:`draw` picks one of the 48 uniformly.
``spatial`` is a 3-bit code: bit 0 transpose, bit 1 flip x (mirror columns), bit 2 flip y (mirror
rows), applied in that order. ``colour[i]`` is the input channel that output channel ``i`` takes.

=======================================  ==============================================================
function                                 array, channels last
=======================================  ==============================================================
:func:`augment_features` (f, aug)        (..., H, W, C >= 27): channels 0-26 in the :mod:`prep.features`
                                         layout, channels 27+ (conditioning maps, one-hot indicators)
                                         only moved
:func:`augment_colour` (x, aug)          (..., H, W, 3): any colour (noisy, reference, albedo, final),
                                         moved and RGB-permuted
:func:`augment_spatial` (x, aug)         (..., H, W, C): anything else, only moved
:func:`moved_box` (box, shape, aug)      where a rectangle of an (H, W) array lands once it is moved
=======================================  ==============================================================

Every function is a signed permutation of the array's entries (indexing and negation, no other
arithmetic): dtype is kept and ``f == augment_features(augment_features(f, a), a.inverse())`` bit for
bit. A transpose turns (H, W) into (W, H); H != W is allowed.

Why the features are *transformed* rather than recomputed:

- Gradients are forward differences, ``dx[y, x] = c[y, x+1] - c[y, x]``, 0 in the last column. On the
  mirror of an image of width W, ``dx'[x] = -dx[W-2-x]`` for ``x <= W-2`` and ``dx'[W-1] = 0``, so a
  flip x maps the dx channels (3-12) to ``dx'[x] = -dx[(W-2-x) mod W]``: mirrored, shifted by one
  column, negated. This is an involution, and on a full image it equals the features of the mirrored
  image exactly (its last column is ``-dx[W-1] = 0``). On a patch cut from inside an image only the
  last column differs from the true features: it holds the difference across the patch's opposite
  border instead of 0. The dy channels (13-22) are plainly mirrored: a column flip does not change
  vertical differences. A flip y is the same along rows, with the roles of dx and dy exchanged.
- A transpose swaps the dx block (3-12) with the dy block (13-22), channel for channel.
- Normals are world space (docs/formats.md §1: ``normal``), and mirroring the image mirrors no world
  axis, so the normal components are neither negated nor swapped. Only the direction of the
  derivative changes sign, and that holds for every gradient alike (colour, normal, albedo, depth).
- The colour permutation applies to the RGB of colour (0-2), dx colour (3-5), dx albedo (9-11),
  dy colour (13-15), dy albedo (19-21) and of every colour target. Permuting the RGB of every AOV
  (diffuse, specular, albedo) at once is the render of the same scene with permuted spectra,
  physically valid. Normal gradients are xyz, not colours; depth is scalar; the relative variances
  (23-26) are means over channels, so invariant.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from prep.bounds import is_integer
from prep.features import FEATURE_NAMES, NUM_FEATURES

TRANSPOSE, FLIP_X, FLIP_Y = 1, 2, 4
PERMUTATIONS = tuple(itertools.permutations(range(3)))


def _indices(prefix: str) -> list[int]:
    return [i for i, name in enumerate(FEATURE_NAMES) if name.startswith(prefix)]


DX = slice(min(_indices("dx_")), max(_indices("dx_")) + 1)
DY = slice(min(_indices("dy_")), max(_indices("dy_")) + 1)
# first channel of every RGB triplet that is a colour (not a normal's xyz)
RGB_STARTS = tuple(i for i, name in enumerate(FEATURE_NAMES) if name.endswith(".R") and "normal" not in name)

assert _indices("dx_") == list(range(DX.start, DX.stop)) and _indices("dy_") == list(range(DY.start, DY.stop))
assert [n.replace("dx_", "dy_") for n in FEATURE_NAMES[DX]] == list(FEATURE_NAMES[DY])
assert [FEATURE_NAMES[i] for i in RGB_STARTS] == [
    "colour.R", "dx_colour.R", "dx_albedo.R", "dy_colour.R", "dy_albedo.R"]
assert all(FEATURE_NAMES[i + k].endswith("." + "RGB"[k]) for i in RGB_STARTS for k in range(3))


@dataclass(frozen=True)
class Augmentation:
    """One of the 48 augmentations: ``spatial`` code 0..7 and ``colour`` permutation of (0, 1, 2)."""

    spatial: int = 0
    colour: tuple[int, int, int] = (0, 1, 2)

    def __post_init__(self):
        s = self.spatial
        if not is_integer(s) or not 0 <= s <= 7:
            raise ValueError(f"spatial must be an integer code in 0..7, got {self.spatial!r}")
        colour = tuple(self.colour) if isinstance(self.colour, (tuple, list)) else ()
        if not all(isinstance(c, (int, np.integer)) for c in colour) or sorted(colour) != [0, 1, 2]:
            raise ValueError(f"colour must be a permutation of (0, 1, 2), got {self.colour!r}")
        object.__setattr__(self, "spatial", int(self.spatial))
        object.__setattr__(self, "colour", tuple(int(c) for c in colour))

    def inverse(self) -> Augmentation:
        spatial = self.spatial
        if spatial & TRANSPOSE:
            # undoing "transpose, then flips" transposes last; transpose . flip x = flip y . transpose
            spatial = TRANSPOSE | (FLIP_Y if spatial & FLIP_X else 0) | (FLIP_X if spatial & FLIP_Y else 0)
        return Augmentation(spatial, tuple(int(i) for i in np.argsort(self.colour)))


IDENTITY = Augmentation()
ALL = tuple(Augmentation(s, p) for s in range(8) for p in PERMUTATIONS)


def draw(rng: np.random.Generator) -> Augmentation:
    """One of the 48 augmentations, uniformly, from ``rng``."""
    return ALL[int(rng.integers(len(ALL)))]


def _flip(x: np.ndarray, axis: int, grad: slice | None) -> np.ndarray:
    """Mirror along ``axis``; channels ``grad`` (forward differences along it) also shifted and negated."""
    out = np.flip(x, axis).copy()
    if grad is not None:
        n = x.shape[axis]
        out[..., grad] = -np.take(x[..., grad], (n - 2 - np.arange(n)) % n, axis=axis)
    return out


def _move(x: np.ndarray, spatial: int, features: bool) -> np.ndarray:
    if spatial & TRANSPOSE:
        x = np.swapaxes(x, -3, -2)
        if features:
            x = x[..., np.r_[0:DX.start, DY, DX, DY.stop:x.shape[-1]]]
    if spatial & FLIP_X:
        x = _flip(x, -2, DX if features else None)
    if spatial & FLIP_Y:
        x = _flip(x, -3, DY if features else None)
    return np.ascontiguousarray(x)


def _check(x, aug: Augmentation, what: str) -> np.ndarray:
    if not isinstance(aug, Augmentation):
        raise ValueError(f"aug must be an Augmentation, got {aug!r}")
    x = np.asarray(x)
    if x.ndim < 3:
        raise ValueError(f"{what} must be (..., H, W, C), got shape {x.shape}")
    return x


def augment_spatial(x, aug: Augmentation) -> np.ndarray:
    """``x`` (..., H, W, C) moved by ``aug.spatial``; channels untouched (masks, λ maps, indicators)."""
    return _move(_check(x, aug, "x"), aug.spatial, features=False)


def moved_box(box, shape: tuple[int, int], aug: Augmentation) -> tuple[int, int, int, int]:
    """Where the rows y0:y1 and columns x0:x1 (``box``) of an (H, W) = ``shape`` array are once it is moved by
    ``aug.spatial``: ``augment_spatial(x, aug)`` cut to the result is ``augment_spatial`` of ``x`` cut to ``box``."""
    y0, y1, x0, x1 = box
    h, w = shape
    if aug.spatial & TRANSPOSE:
        y0, y1, x0, x1, h, w = x0, x1, y0, y1, w, h
    if aug.spatial & FLIP_X:
        x0, x1 = w - x1, w - x0
    if aug.spatial & FLIP_Y:
        y0, y1 = h - y1, h - y0
    return y0, y1, x0, x1


def augment_colour(x, aug: Augmentation) -> np.ndarray:
    """``x`` (..., H, W, 3), a colour, moved by ``aug.spatial`` and RGB-permuted by ``aug.colour``."""
    x = _check(x, aug, "colour")
    if x.shape[-1] != 3:
        raise ValueError(f"colour must have 3 channels, got shape {x.shape}")
    return _move(x[..., list(aug.colour)], aug.spatial, features=False)


def augment_features(features, aug: Augmentation) -> np.ndarray:
    """``features`` (..., H, W, C >= 27) transformed as the features of the augmented image (module doc)."""
    f = _check(features, aug, "features")
    if f.shape[-1] < NUM_FEATURES:
        raise ValueError(f"features must have at least {NUM_FEATURES} channels, got shape {f.shape}")
    channels = np.arange(f.shape[-1])
    for start in RGB_STARTS:
        channels[start:start + 3] = start + np.asarray(aug.colour)
    return _move(f[..., channels], aug.spatial, features=True)
