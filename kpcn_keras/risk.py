"""The error of a denoiser's output of two renders' mean, estimated from the two renders alone: no reference.

Two independent renders A and B of one frame at the same samples have the same noise distribution around the
clean image c. Their mean M = (A + B) / 2 is what a pair is denoised as; their half-difference D = (A - B) / 2
has exactly the covariance of M's noise, Cov D = (Cov A + Cov B) / 4 = Cov M, and is uncorrelated with it,
E[(M - c) D^T] = (Cov A - Cov B) / 4 = 0. So D stands in for M's noise where a risk estimate needs it:

    ||f(M) - c||^2 = ||f(M) - M||^2 - ||M - c||^2 + 2 <f(M) - c, M - c>

and in expectation ||M - c||^2 is ||D||^2, and <f(M) - c, M - c>, the covariance of the output with the input's
noise (what makes ||f(M) - M||^2 an optimistic estimate), is <D, f(M + D) - f(M - D)> / 2 = <D, f(A) - f(B)> / 2
for an affine f: its Jacobian meets the noise's covariance in both, whatever the noise's distribution, through
every noisy input of f (the colour, the albedo, the normal, the depth: A and B differ in each). This is Stein's
unbiased risk estimate with the pair's own difference as its probe, with the Jacobian taken as the secant from B
to A: exact for a linear denoiser, first order for a network. Per pixel, with a weight w (relMSE's, held fixed):

    risk = w [ (f(M) - M)^2 - D^2 + D (f(A) - f(B)) ]

The estimate is of the output of all the samples, the one shipped, from the model's outputs of the two halves
and of their mean alone; ``tests/test_risk.py`` checks it against the true error of linear denoisers on
heavy-tailed noise within a statistical bound. The adaptation's guard (``kpcn_keras.adapt``) compares a
correction's estimate with the model's on pixels the correction never trained on.
"""

from __future__ import annotations

import numpy as np


def pair_risk(weight, mean, half_diff, out_mean, out_a, out_b) -> np.ndarray:
    """Per pixel, the estimated weighted squared error of ``out_mean`` (a denoiser's output of ``mean``, the two
    renders' mean) against the clean image: ``weight`` (broadcast), the noisy ``mean`` colour, ``half_diff``
    (A - B) / 2 of the colour, and the same denoiser's outputs of each render, ``out_a`` and ``out_b`` (module
    docstring). Arrays (..., 3) of the colour; the result (...), the mean over the channels, in float64. One pixel's
    estimate is noisy, even negative; its mean over many pixels is what it estimates."""
    m, d = np.asarray(mean, np.float64), np.asarray(half_diff, np.float64)
    f, fa, fb = (np.asarray(x, np.float64) for x in (out_mean, out_a, out_b))
    return (np.asarray(weight, np.float64) * ((f - m) ** 2 - d**2 + d * (fa - fb))).mean(-1)


__all__ = ["pair_risk"]
