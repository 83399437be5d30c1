"""What a frame's inputs hold, and how a piece a renderer does not write is filled (docs/formats.md §1b).

The networks read the AOV layout of ``prep.exr``: a diffuse/specular split and six variance layers. Most
renderers write neither (Cycles 3.0+ writes no variance; Mitsuba, PBRT and a plain colour file have no
split). An :class:`InputSet` says which of the two a frame has; each set has a network trained for it
(``kpcn train --inputs``). :func:`restrict` turns a frame's layers into the full AOV layout in the one way
that set's network is trained on, so a model sees at inference exactly what its shards held:

=========================  ==========================================================================
missing                    filled as
=========================  ==========================================================================
variance                   every variance layer 0 (the relative-variance features are then 0)
split                      diffuse = the total colour, diffuseVariance = colorVariance; specular 0,
                           specularVariance 0: the diffuse branch (the colour divided by the albedo)
                           denoises the whole frame and the specular branch is not run
=========================  ==========================================================================

A frame with more than its model's set is restricted to it (a split frame served by a no-split model gives
that model its total colour). :func:`mean_layers` joins two renders of the same frame with different seeds
into one render of all their samples (``kpcn denoise A.exr --pair B.exr``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prep.errors import OptionError
from prep.exr import VARIANCE_LAYERS, to_float32

# the order of INPUT_SETS is the order of preference of a model for a frame: the most the frame has first
INPUT_SETS = ("full", "no-variance", "no-split", "no-split-no-variance")


@dataclass(frozen=True)
class InputSet:
    """Whether a frame has a diffuse/specular split and variance layers."""

    split: bool = True
    variance: bool = True

    @property
    def name(self) -> str:
        return INPUT_SETS[(0 if self.variance else 1) + (0 if self.split else 2)]

    @classmethod
    def named(cls, name: str, option: str = "inputs") -> InputSet:
        if name not in INPUT_SETS:
            raise OptionError(option, f"must be one of {', '.join(INPUT_SETS)}, got {name!r}")
        i = INPUT_SETS.index(name)
        return cls(split=i < 2, variance=i % 2 == 0)

    def serves(self, frame: InputSet) -> bool:
        """Whether a model trained on this set can denoise a frame that has ``frame``: it needs nothing the
        frame lacks."""
        return (frame.split or not self.split) and (frame.variance or not self.variance)

    def __str__(self) -> str:
        return self.name


FULL = InputSet()


def restrict(layers: dict[str, np.ndarray], inputs: InputSet) -> dict[str, np.ndarray]:
    """The AOV layout a model of ``inputs`` reads, from ``layers`` (which must have at least what ``inputs``
    needs: ``default`` always; ``diffuse``, ``specular`` for a split set; the variance layers for a set with
    variance). The filled layers are the table of the module docstring; what is kept is not copied."""
    out = {k: layers[k] for k in ("default", "albedo", "normal", "depth")}
    shape = layers["depth"].shape
    if inputs.split:
        out["diffuse"], out["specular"] = layers["diffuse"], layers["specular"]
    else:
        out["diffuse"], out["specular"] = layers["default"], np.zeros_like(layers["default"])
    if inputs.variance:
        out.update({name: layers[name] for name in VARIANCE_LAYERS})
        if not inputs.split:
            out["diffuseVariance"] = layers["colorVariance"]
            out["specularVariance"] = np.zeros(shape, np.float32)
    else:
        out.update({name: np.zeros(shape, np.float32) for name in VARIANCE_LAYERS})
    return out


def box_mean(image: np.ndarray, radius: int) -> np.ndarray:
    """Mean of a 2-D image over a (2 radius + 1)^2 box cut at the border (a summed-area table, float64)."""
    h, w = image.shape
    table = np.zeros((h + 1, w + 1))
    table[1:, 1:] = np.asarray(image, np.float64).cumsum(0).cumsum(1)
    y0, y1 = np.clip(np.arange(h) - radius, 0, h), np.clip(np.arange(h) + radius + 1, 0, h)
    x0, x1 = np.clip(np.arange(w) - radius, 0, w), np.clip(np.arange(w) + radius + 1, 0, w)
    total = table[y1][:, x1] - table[y0][:, x1] - table[y1][:, x0] + table[y0][:, x0]
    return total / ((y1 - y0)[:, None] * (x1 - x0)[None, :])


def mean_layers(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """One frame from two independent renders of it, as one render of all their samples: each layer the mean of the
    two, and each variance layer the variance of that mean, (var_a + var_b) / 4 (where both have it). No variance is
    made from their difference for a renderer that writes none (``kpcn_keras.batch.join_pair`` says why)."""
    out = {}
    for k in (k for k in a if k in b):
        total = np.asarray(a[k], np.float64) + b[k]
        out[k] = to_float32(total / 4.0 if k in VARIANCE_LAYERS else total / 2.0)
    return out
