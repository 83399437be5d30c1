"""How a trained model is applied: the settings of inference, one object from the command line to the networks.

:class:`InferenceSettings` holds what changes how a frame is denoised but not which model denoises it nor what
the frame is: the tile (memory), the trunks' precision (``kpcn_keras.precision``), the self-ensemble's
members (``kpcn_keras.denoise``) and the quality mode, which of the model's network sets serves
(``Run.for_quality``). Its defaults and bounds are ``kpcn_keras.config``'s, checked once, when it is
made (an OptionError naming the option: the command line's flag), so a reader never checks them again. The
parser fills it from the options given (``parser.inference_settings``); ``kpcn_keras.serving.Serving``,
``denoise.Denoiser``, ``evaluate``, ``figures``, the viewer and ``kpcn.denoise`` take it as it is. λ (``slope``,
a λ map) is not a setting but an input of each call: one loaded model serves every λ.

Imports nothing of keras or torch (``kpcn --help`` builds the parser from it).
"""

from __future__ import annotations

from dataclasses import dataclass

from kpcn_keras.config import (
    DEFAULT_ENSEMBLE,
    DEFAULT_PRECISION,
    DEFAULT_QUALITY,
    DEFAULT_RUNTIME,
    DEFAULT_TILE,
    ENSEMBLE,
    PRECISIONS,
    QUALITY_MODES,
    RUNTIMES,
    TILE,
)
from prep.bounds import SEED, Bound, bounded, check_fields
from prep.errors import OptionError


@dataclass(frozen=True)
class InferenceSettings:
    """``tile``: pixels per side of an inference tile (bounds memory at any resolution; ``--tile``);
    ``precision``: the trunks' arithmetic, one of ``config.PRECISIONS`` (``--precision``; "auto" is resolved for
    the machine by the denoiser, ``kpcn_keras.precision.resolve``); ``ensemble``: a self-ensemble's members, 1
    for the networks once (``--ensemble``); ``quality``: the model's mode, one of ``config.QUALITY_MODES``
    (``--quality``; a mode the model lacks is refused when it is served, ``Run.for_quality``); ``clean_aux``: the
    frame's albedo, normal and depth are clean already (``--clean-aux``, OIDN's ``cleanAux``), so a model trained
    on prefiltered auxiliaries is given them as they are (``prep.auxiliary``'s ``raw``) instead of prefiltered;
    ``runtime``: what runs the networks, one of ``config.RUNTIMES`` (``--runtime``): torch, or onnxruntime on their
    ONNX graphs (``kpcn_keras.onnx_runtime``; what it cannot serve is refused when the model is loaded)."""

    tile: int = bounded(DEFAULT_TILE, TILE)
    precision: str = DEFAULT_PRECISION
    ensemble: int = bounded(DEFAULT_ENSEMBLE, ENSEMBLE)
    quality: str = DEFAULT_QUALITY
    clean_aux: bool = False
    runtime: str = DEFAULT_RUNTIME

    def __post_init__(self):
        check_fields(self)
        check_precision(self.precision)
        check_quality(self.quality)
        check_runtime(self.runtime)


def check_precision(precision: str) -> str:
    """``precision`` if it is one of ``config.PRECISIONS``; OptionError echoing it otherwise."""
    if precision not in PRECISIONS:
        raise OptionError("precision", f"must be one of {', '.join(PRECISIONS)}, received {precision!r}")
    return precision


def check_quality(quality: str) -> str:
    """``quality`` if it is one of ``config.QUALITY_MODES``; OptionError echoing it otherwise."""
    if quality not in QUALITY_MODES:
        raise OptionError("quality", f"must be one of {', '.join(QUALITY_MODES)}, received {quality!r}")
    return quality


def check_runtime(runtime: str) -> str:
    """``runtime`` if it is one of ``config.RUNTIMES``; OptionError echoing it otherwise."""
    if runtime not in RUNTIMES:
        raise OptionError("runtime", f"must be one of {', '.join(RUNTIMES)}, received {runtime!r}")
    return runtime


@dataclass(frozen=True)
class AdaptSettings:
    """How a model adapts to a frame given as two independent renders (``kpcn_keras.adapt``; ``--adapt``):
    ``seconds`` of training at most on this machine (0: none), or exactly ``steps`` steps where given (what makes
    a run reproducible: the same seed and steps give the same weights, whatever the machine's speed); ``seed``
    draws the crops, their order, the held-out blocks and the post-correction's first weights; ``learning_rate``
    of Adam; ``crop`` the side of the training crops and ``crops`` the most of them per render (what bounds
    memory at any frame size);
    ``block`` the side of the held-out blocks, one in :data:`kpcn_keras.adapt.HELD_OUT_EVERY` of them, which
    decide when to stop and whether to keep the adapted network (``check_every`` steps apart, the gain kept only
    where it clears ``confidence`` standard errors; a negative ``confidence`` keeps a correction the estimate puts
    up to that many standard errors worse, a user's call where the estimate is pessimistic, as on path-traced
    noise it mostly is: docs/adapt.md §5)."""

    seconds: float = bounded(60.0, Bound(0.0, 86400.0, integer=False))
    steps: int | None = bounded(None, Bound(1, 10**6))
    seed: int = bounded(0, SEED)
    learning_rate: float = bounded(1e-3, Bound(0.0, 1.0, integer=False, low_open=True))
    crop: int = bounded(128, Bound(16, 1024))
    crops: int = bounded(16, Bound(1, 1024))
    block: int = bounded(16, Bound(2, 256))
    check_every: int = bounded(10, Bound(1, 10**4))
    confidence: float = bounded(2.0, Bound(-10.0, 10.0, integer=False))

    def __post_init__(self):
        check_fields(self)

    @property
    def active(self) -> bool:
        """Whether any training is asked for."""
        return self.steps is not None or self.seconds > 0


__all__ = ["AdaptSettings", "InferenceSettings", "check_precision", "check_quality", "check_runtime"]
