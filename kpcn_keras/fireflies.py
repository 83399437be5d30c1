"""Synthetic fireflies in training patches: teach a branch network that an isolated spike is noise.

Why: a pixel far brighter than anything near it, a rare path a low sample count caught once (a caustic through
glass onto a dark floor), is noise the reference does not have. The networks repair the fireflies they have seen
(the ``fireflies`` family), but let one far outside that range through unchanged: a ReLU network's kernel logits
grow with its input, so a spike larger than any it trained on saturates the softmax on one tap, the centre, and
bright pixels the networks did see were mostly emitters, which are signal (docs/results/18-synthetic-fireflies.md).

What is added: a patch of a training stream gets a Poisson number of spikes, the run's ``fireflies`` on average
(``kpcn_keras.config.TrainConfig``; 1 by default), each at a uniform pixel, of a grey value ``S`` log-uniform in
:data:`SPIKE_RANGE` added to the branch's linear colour there (the irradiance for the diffuse branch, the
specular colour for the specular one), as one sample of radiance ``n S`` among ``n`` would add to a mean; the
target, the reference, is left as it is. A spike carries the variance such a sample gives the mean, ``S ** 2``
on each channel, when the shard set has variance layers; without them (a ``no-variance`` set) the relative
variance stays 0, as at inference.

What is changed is what a shard stores (``prep.shards.format``), before the features are made of it, so every
feature of the spike follows from the same transforms as at render time (``prep.colour``): the log colour
``c = log(1 + x)`` of the pixel, and the colour's relative variance ``log(1 + (vlog / 3) / (mean_ch(c ** 2) +
REL_EPS))`` (``relative_variance``), ``vlog = sum_ch var(x) / (1 + x) ** 2`` (``log_variance``). The pixel's variance
before the spike is read back from its stored relative variance (``variance_of``, the inverse) as
``var(x_ch) = (vlog / 3) (1 + x_ch) ** 2``, exact for a grey pixel (every channel's term alike) and otherwise the
same total spread evenly; the spike's ``S ** 2`` dominates either way. Both stored values are rounded to float16 as
the shards round them (``to_half``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from prep import colour
from prep.shards.format import to_half

SPIKE_RANGE = (1.0, 1.0e4)  # the added linear colour S, log-uniform: from a bright highlight to a caustic's spike


@dataclass(frozen=True)
class Spike:
    """One firefly: pixel (``y``, ``x``) of the patch gains ``value`` in its branch's linear colour."""

    y: int
    x: int
    value: float


def draw(rng: np.random.Generator, rate: float, patch_size: int) -> tuple[Spike, ...]:
    """The spikes of one patch: a Poisson(``rate``) count, each at a uniform pixel of the ``patch_size`` square
    with a value log-uniform in :data:`SPIKE_RANGE`."""
    count = int(rng.poisson(rate)) if rate > 0 else 0
    lo, hi = np.log(SPIKE_RANGE[0]), np.log(SPIKE_RANGE[1])
    return tuple(Spike(int(rng.integers(patch_size)), int(rng.integers(patch_size)), float(np.exp(rng.uniform(lo, hi))))
                 for _ in range(count))


def inject(stored: dict[str, np.ndarray], branch: str, spikes, variance: bool) -> dict[str, np.ndarray]:
    """``stored`` (one patch's stored datasets, as ``prep.shards.format.read_stored`` gives them) with
    ``spikes`` added to ``branch``'s colour (module docstring); the arrays it changes are copies, the rest
    are ``stored``'s own. ``variance``: whether the shard set has variance layers."""
    if not spikes:
        return stored
    out = dict(stored)
    log_colour = np.array(stored[f"{branch}/log_colour"])
    relvar = np.array(stored[f"{branch}/relvar"])
    for s in spikes:
        c = log_colour[s.y, s.x].astype(np.float64)
        x = colour.linear_colour(c)
        x_new = x + s.value
        c_new = colour.log_colour(x_new)
        log_colour[s.y, s.x] = to_half(c_new, colour.LOG_COLOUR_MAX)
        if variance:
            vlog3 = colour.variance_of(float(relvar[s.y, s.x, 0]), float(np.mean(c * c)))
            var_x = colour.linear_variance(vlog3, x) + s.value ** 2
            vlog3_new = float(np.mean(colour.log_variance(var_x, x_new)))
            relvar[s.y, s.x, 0] = to_half(colour.relative_variance(vlog3_new, float(np.mean(c_new * c_new))),
                                          colour.RELVAR_MAX)
    out[f"{branch}/log_colour"] = log_colour
    out[f"{branch}/relvar"] = relvar
    return out
