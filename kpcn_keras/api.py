"""Denoising numpy arrays in a Python process, as small as pyoidn's call (``kpcn.denoise``).

:func:`denoise` makes a frame from the arrays given, in kpcn's names (``prep.layouts.Frame``), and denoises it
exactly as ``kpcn denoise`` does a file that holds the same layers: the same model (``Run.serving`` picks the
run's variant for what the arrays give), the same ``denoise.Denoiser`` held by a ``serving.Serving``, so the
result equals the command's output bit for bit (``tests/test_renderers.py``). What is not given is filled as the
rgb layout fills it (albedo 1, normal 0, depth 0; ``prep.layouts.FILL``). ``variance`` is the variance of the
pixel mean of ``color`` ((H, W) or (H, W, 3), averaged over channels); with ``diffuse`` and ``specular`` it must
be a dict of the six ``<x>Variance`` layers of ``prep.exr`` (a split model needs each branch's). A model's
serving object, and the denoisers it loaded, are kept for the next call with the same run and settings (until
the run's record changes: a run trained again is loaded again). As a file's layers are, the arrays are repaired by
``prep.exr``'s rule for non-finite values, with its warning; an argument that is not an array of real numbers of
the right shape is an :class:`~prep.errors.ArrayError` naming it, and a frame this machine cannot hold is refused
by the command's memory check before any array is copied. ``pair=`` (a second render of the frame) and ``adapt=``
(seconds of adapting to the two halves first) do what ``kpcn denoise --pair B [--adapt S]`` does, through the same
functions (:func:`denoise`).
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import numbers
import os
from pathlib import Path

import numpy as np

from kpcn_keras.settings import InferenceSettings
from prep.errors import ArrayError, KpcnError, OptionError
from prep.exr import VARIANCE_LAYERS, repair_layers, repair_note
from prep.inputs import InputSet
from prep.layouts import FILL, Frame

log = logging.getLogger("kpcn")

WHERE = "kpcn.denoise"  # what the repair warning names in place of a file
REAL = "biuf"  # the numpy kinds an image may be given in: bool, integers, floats


def _numbers(name: str, value) -> np.ndarray:
    """``value`` as a numpy array of real numbers, not yet cast (a broadcast view stays a view, so a frame too big
    to hold is refused before it is copied); ArrayError naming ``name`` for anything else."""
    try:
        a = np.asarray(value)
        if a.dtype.kind == "O":  # objects: numbers only if each is one (numpy would take None for NaN)
            a = a.astype(np.float64) if all(isinstance(x, numbers.Real) for x in a.flat) else None
    except (TypeError, ValueError, OverflowError):
        a = None
    if a is None or a.dtype.kind not in REAL:
        what = type(value).__name__ + (f" of {np.asarray(value, dtype=object).dtype if a is None else a.dtype}"
                                       if isinstance(value, (np.ndarray, list, tuple)) else "")
        kind = " (take np.real or np.abs of it first)" if a is not None and a.dtype.kind == "c" else ""
        raise ArrayError(f"{name} must be an array of real numbers, got {what}{kind}")
    return a


def _float32(a: np.ndarray) -> np.ndarray:
    """``a`` as float32; a finite value beyond its range becomes inf, which the repair rule then takes in."""
    with np.errstate(over="ignore", invalid="ignore"):
        return a.astype(np.float32, copy=False)


def _array(name: str, value, shape: tuple[int, ...]) -> np.ndarray:
    a = _numbers(name, value)
    if a.shape != shape:
        raise ArrayError(f"{name} must have shape {shape} (the colour's), got {a.shape}")
    return _float32(a)


def _variance(value, h: int, w: int) -> np.ndarray:
    """One colour variance, (H, W) or (H, W, 3) averaged over channels (in float64), as float32."""
    v = _numbers("variance", value)
    if v.shape not in ((h, w), (h, w, 3)):
        raise ArrayError(f"variance must be (H, W) or (H, W, 3) like the colour, got {v.shape}")
    return _float32(v.astype(np.float64).mean(axis=-1) if v.ndim == 3 else v)


def frame_from_arrays(color, albedo=None, normal=None, depth=None, variance=None, *, diffuse=None,
                      specular=None) -> Frame:
    """The frame :func:`denoise` denoises (module docstring), its non-finite values repaired by the readers' rule
    (``prep.exr.repair_layers``) with their warning; ArrayError naming an array it cannot take, KpcnError for a
    frame this machine cannot hold (the command's check: ``batch.check_frame_memory``)."""
    from kpcn_keras.batch import check_frame_memory

    given = _numbers("color", color)
    if given.ndim != 3 or given.shape[2] not in (3, 4) or 0 in given.shape:
        raise ArrayError(f"color must be (H, W, 3) or (H, W, 4), H and W at least 1, got {given.shape}")
    h, w = given.shape[:2]
    check_frame_memory("color", (h, w), png=False)
    color = _float32(given)
    layers = {"default": np.ascontiguousarray(color[..., :3])}
    for name, value in (("albedo", albedo), ("normal", normal), ("depth", depth)):
        shape = (h, w) if name == "depth" else (h, w, 3)
        layers[name] = np.full(shape, FILL[name], np.float32) if value is None else _array(name, value, shape)
    split = diffuse is not None or specular is not None
    if split:
        if diffuse is None or specular is None:
            raise KpcnError("diffuse and specular go together: got only " + ("diffuse" if specular is None
                                                                               else "specular"))
        layers["diffuse"] = _array("diffuse", diffuse, (h, w, 3))
        layers["specular"] = _array("specular", specular, (h, w, 3))
    has_variance = variance is not None
    names = {"default": "color"}  # the argument each layer came from, as the warning names it
    if isinstance(variance, dict):
        missing = [n for n in VARIANCE_LAYERS if n not in variance and (split or n not in
                                                                        ("diffuseVariance", "specularVariance"))]
        if missing:
            raise ArrayError(f"variance lacks {', '.join(missing)}; it has {', '.join(sorted(variance)) or 'nothing'}")
        layers.update({n: _array(n, v, (h, w)) for n, v in variance.items() if n in VARIANCE_LAYERS})
    elif has_variance:
        colour_variance = _variance(variance, h, w)
        if split:  # a split model needs each branch's variance, which one colour variance does not give
            has_variance = False
        else:
            layers["colorVariance"], names["colorVariance"] = colour_variance, "variance"
            for n in ("albedoVariance", "normalVariance", "depthVariance"):
                layers[n] = np.zeros((h, w), np.float32)
    layers, repaired = repair_layers(layers)
    if repaired:
        log.warning("%s: %s", WHERE, repair_note({names.get(k, k): n for k, n in repaired.items()}))
    if has_variance and not split:
        layers["diffuseVariance"] = layers["specularVariance"] = layers["colorVariance"]
    alpha = color[..., 3] if color.shape[2] == 4 else None
    window = ((0, 0), (w - 1, h - 1))
    return Frame(Path("<arrays>"), "arrays", layers, InputSet(split=split, variance=has_variance), alpha,
                 data_window=window, display_window=window)


@functools.lru_cache(maxsize=4)
def _serving(run_dir: str, settings: InferenceSettings, stamp: float):
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving

    return Serving(Run(run_dir), settings)


def denoise(color, albedo=None, normal=None, depth=None, variance=None, *, diffuse=None, specular=None,
            run: str | os.PathLike | None = None, settings: InferenceSettings = InferenceSettings(),
            slope: float | None = None, quality: str | None = None, pair=None, adapt=None, on_adapt=None,
            on_outcome=None) -> np.ndarray:
    """The denoised colour, (H, W, 3) float32, of ``color`` ((H, W, 3), linear, or (H, W, 4) with alpha), with the
    auxiliary buffers given (module docstring), or of ``color`` a frame of ``kpcn.read`` with every layer it has,
    by the model of ``run`` (a run folder of ``kpcn train``; default: the shipped model, ``run.default_model``)
    at ``slope`` (λ, for a run trained with it as an input), applied with ``settings``
    (``kpcn.InferenceSettings``: the tile, the trunks' precision, ``"auto"``, ``"float32"`` or ``"bfloat16"``, and
    a self-ensemble's members where more than 1, that many times the time, and the quality mode;
    ``kpcn_keras.settings``).
    ``quality`` (``"fast"``, ``"balanced"`` or ``"high"``), where given, is that of ``settings``: the model's network
    set for that mode, a KpcnError naming the modes it has where it lacks it.

    ``pair``: a second render of the frame with another seed, given as the frame is (a ``kpcn.read`` frame beside
    one; beside arrays, a dict of this function's array arguments, ``color`` and whichever others, or the second
    colour alone, whose albedo, normal and depth are then the frame's), checked as ``kpcn denoise --pair`` checks
    a file (``prep.pairs.check_colours``). The two are denoised as one render of all their samples, their mean
    (``kpcn denoise A --pair B``, by the same function: ``batch.join_pair``); with ``adapt`` (seconds, or a
    ``kpcn_keras.settings.AdaptSettings`` for steps and seed) the model first adapts to the two halves
    (``kpcn denoise A --pair B --adapt``: ``batch.adapt_to_layers``). ``on_adapt(step, loss, seconds)`` is the
    adaptation's progress, ``on_outcome`` is handed what it decided (``kpcn_keras.adapt.Outcome``: ``kept``,
    ``line()``...), which is also logged at INFO on the ``kpcn`` logger."""
    from kpcn_keras.batch import adapt_to_layers, join_pair

    if quality is not None:
        settings = dataclasses.replace(settings, quality=quality)  # checked there, as the command line's
    adapt = _adapt_settings(adapt, pair)
    if run is None:
        from kpcn_keras.run import default_model

        run = default_model().dir
    arrays = dict(albedo=albedo, normal=normal, depth=depth, variance=variance, diffuse=diffuse, specular=specular)
    frame = _frame(color, arrays)
    halves = None
    if pair is not None:
        other = _pair_frame(pair, frame, color, arrays)
        halves = (frame.layers, other.layers) if adapt is not None else None
        frame = join_pair(frame, other, _names(frame, other))
    record = Path(run) / "config.json"
    stamp = record.stat().st_mtime if record.exists() else 0.0  # a run trained again is loaded again
    denoiser = _serving(str(Path(run).resolve()), settings, stamp).denoiser(frame.inputs)
    if adapt is not None:
        denoiser, outcome = adapt_to_layers(denoiser, *halves, adapt, on_adapt)
        del halves
        log.info("%s: %s", WHERE, outcome.line())
        if on_outcome is not None:
            on_outcome(outcome)
    return denoiser(frame.served_layers(), slope=slope)["default"]


def _frame(color, arrays: dict) -> Frame:
    """``color`` as :func:`denoise` takes it: a ``kpcn.read`` frame as it was read, or arrays
    (:func:`frame_from_arrays`)."""
    if isinstance(color, Frame):  # kpcn.read's frame, as it was read
        return color
    return frame_from_arrays(color, **arrays)


def _adapt_settings(adapt, pair):
    """``adapt`` as ``AdaptSettings`` (None where not given); KpcnError naming ``adapt`` for anything else, or for
    an adaptation without a ``pair``."""
    from kpcn_keras.settings import AdaptSettings

    if adapt is None:
        return None
    if pair is None:
        raise OptionError("adapt", "needs pair=: a second render of the frame with another seed (each of the two at "
                          "half the samples)")
    if isinstance(adapt, AdaptSettings):
        return adapt
    if isinstance(adapt, bool) or not isinstance(adapt, numbers.Real):
        raise OptionError("adapt", f"must be seconds (a number) or an AdaptSettings, got {type(adapt).__name__}")
    try:
        return AdaptSettings(seconds=float(adapt))
    except OptionError as exc:
        raise OptionError("adapt", exc.detail) from None


def _pair_frame(pair, frame: Frame, color, arrays: dict) -> Frame:
    """The second render ``pair`` as a frame (:func:`denoise`'s docstring), after refusing in one line one not given
    as the frame is, of another size or inputs, or not a second render of it (``prep.pairs.check_colours``)."""
    from prep import pairs

    if isinstance(color, Frame) != isinstance(pair, Frame):
        raise ArrayError("pair must be given as the frame is: " + ("a kpcn.read frame beside one" if
                         isinstance(color, Frame) else "arrays (a dict of color, albedo... or a colour array) "
                                                          f"beside arrays, not a {type(pair).__name__}"))
    if isinstance(pair, Frame):
        other = pair
    elif isinstance(pair, dict):
        unknown = sorted(set(pair) - {"color", *arrays})
        if unknown or "color" not in pair:
            raise ArrayError(f"pair's dict takes color (required), {', '.join(arrays)}; got {', '.join(sorted(pair))}")
        other = frame_from_arrays(**pair)
    else:
        other = frame_from_arrays(pair, albedo=arrays["albedo"], normal=arrays["normal"], depth=arrays["depth"])
    if other.size != frame.size:
        raise ArrayError(f"pair is {other.size[1]}x{other.size[0]}, the frame {frame.size[1]}x{frame.size[0]}: a "
                         "second render of the frame has its size")
    if other.inputs != frame.inputs:
        raise ArrayError(f"pair gives {other.inputs.name}, the frame {frame.inputs.name}: give the second render "
                         "the layers the first has (a variance, a diffuse/specular split)")
    if frame.spp and other.spp and frame.spp != other.spp:
        raise ArrayError(f"pair has {other.spp} spp, the frame {frame.spp}: the two halves have the same samples")
    names = _names(frame, other)
    pairs.check_colours(names[0], frame.layers["default"], names[1], other.layers["default"])
    return other


def _names(frame: Frame, other: Frame) -> tuple[str, str]:
    """What the two renders are called in a message: their files, or the arguments they came from."""
    if frame.path == other.path == Path("<arrays>"):
        return "color", "pair"
    return str(frame.path), str(other.path)
