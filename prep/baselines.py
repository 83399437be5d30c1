"""Denoisers to compare the networks with, at the same input spp: non-local means (always there) and Intel
Open Image Denoise (the yardstick users hold up; the optional ``pyoidn`` package, ``pip install '.[oidn]'``) in
each of :data:`OIDN_MODES`; and the anchors a frame is judged against (:data:`ANCHORS`, :func:`anchor`): a frame
is won only where kpcn's relMSE is below the best of plain OIDN, prefiltered OIDN (as Blender runs it) and, where
the folder has it, the renderer's own denoised frame (:func:`renderer_denoised`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prep import layouts
from prep.colour import linear_colour, log_colour, log_variance


def nlm_denoise(colour: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """scikit-image non-local means on the colour alone, in the log(1 + x) domain, back to linear.

    The filter is told the true noise level: sigma is the RMS over the image of the render's own
    per-pixel standard deviation (``colorVariance``) carried into the log domain by the delta method,
    sqrt(var) / (1 + x). Settings follow scikit-image's guide: h = 0.8 sigma, 5x5 patches, search
    radius 6.
    """
    from skimage.restoration import denoise_nl_means

    x = np.maximum(np.asarray(colour, dtype=np.float64), 0.0)
    log_c = log_colour(x)
    var_log = log_variance(np.maximum(np.asarray(variance, dtype=np.float64), 0.0)[..., None], x)
    sigma = float(np.sqrt(np.mean(var_log)))
    out = denoise_nl_means(
        log_c, h=0.8 * sigma, sigma=sigma, patch_size=5, patch_distance=6, fast_mode=True, channel_axis=-1
    )
    return linear_colour(out).astype(np.float32)


def oidn_available() -> bool:
    """Whether Intel Open Image Denoise can run here (the optional ``pyoidn`` package is installed)."""
    import importlib.util

    return importlib.util.find_spec("pyoidn") is not None


OIDN_MODES = ("plain", "prefiltered")  # how OIDN treats the auxiliary layers; docs/design.md, "OIDN anchor"
# OIDN's own quality setting (its filters' "quality"), the names kpcn's --quality takes too; "high" is OIDN's default
# and every anchor's unless a study asks for another
OIDN_QUALITIES = ("fast", "balanced", "high")
DEFAULT_OIDN_QUALITY = "high"


def _oidn_layers(aovs: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The colour, albedo and normal layers as OIDN wants them: float32, contiguous, non-negative linear HDR
    colour, albedo in [0, 1], normals in [-1, 1] (NaN to 0)."""

    def layer(name, lo, hi):
        return np.ascontiguousarray(np.clip(np.nan_to_num(aovs[name]), lo, hi), dtype=np.float32)

    return layer("default", 0.0, np.finfo(np.float32).max), layer("albedo", 0.0, 1.0), layer("normal", -1.0, 1.0)


def _oidn_quality(pyoidn, quality: str) -> int:
    return {"fast": pyoidn.OIDN_QUALITY_FAST, "balanced": pyoidn.OIDN_QUALITY_BALANCED,
            "high": pyoidn.OIDN_QUALITY_HIGH}[quality]


def _oidn_auxiliary(pyoidn, device, name: str, image: np.ndarray, quality: str) -> np.ndarray:
    """OIDN's own denoise of one auxiliary layer: an ``RT`` filter with ``image`` as its only input, set in
    the ``name`` slot (``albedo`` or ``normal``), at ``quality``, written to a new array."""
    out = np.empty_like(image)
    with pyoidn.Filter(device, pyoidn.OIDN_FILTER_TYPE_RT) as flt:
        flt.set_image(name, image, pyoidn.OIDN_FORMAT_FLOAT3)
        flt.set_image(pyoidn.OIDN_IMAGE_OUTPUT, out, pyoidn.OIDN_FORMAT_FLOAT3)
        flt.set_quality(_oidn_quality(pyoidn, quality))
        flt.commit()
        flt.execute()
    error = device.get_error()
    if error is not None:
        raise RuntimeError(f"OIDN's {name} filter failed: {error}")
    return out


def oidn_filter_auxiliary(image: np.ndarray, name: str, quality: str = DEFAULT_OIDN_QUALITY) -> np.ndarray:
    """One auxiliary layer (H, W, 3) denoised by OIDN as the ``prefiltered`` mode does (an ``RT`` filter with
    that layer alone in its ``name`` slot, ``albedo`` or ``normal``, at ``quality``, high unless asked): the layer
    clipped to what OIDN takes there ([0, 1] for an albedo, [-1, 1] for a normal) first. ImportError without
    ``pyoidn``."""
    import pyoidn

    lo = 0.0 if name == "albedo" else -1.0
    image = np.ascontiguousarray(np.clip(np.nan_to_num(image), lo, 1.0), dtype=np.float32)
    with pyoidn.Device() as device:
        device.commit()
        return _oidn_auxiliary(pyoidn, device, name, image, quality)


def oidn_denoise(aovs: dict[str, np.ndarray], mode: str = "prefiltered",
                 quality: str = DEFAULT_OIDN_QUALITY) -> np.ndarray:
    """Intel Open Image Denoise's ``RT`` filter at ``quality`` (one of :data:`OIDN_QUALITIES`, OIDN's own
    ``fast`` / ``balanced`` / ``high``; ``high``, OIDN's default, unless asked) on the HDR colour with the albedo
    and normal layers of the same render as its auxiliary inputs, in one of :data:`OIDN_MODES`:

    - ``prefiltered`` (the default; Blender's default, its *Accurate* prefilter): the albedo and the normal are
      each denoised first by an ``RT`` filter that has only that layer as input, then the colour is filtered
      with the cleaned layers and ``cleanAux`` set. The strongest OIDN there is: the anchor the tables judge by.
      The auxiliary filters run at the same ``quality`` as the colour's, as Blender's Cycles runs them (its
      ``denoiser_oidn.cpp`` sets the one denoising quality on the colour filter and on each prefilter alike).
    - ``plain``: one call with the noisy albedo and normal as they are (``cleanAux`` off: OIDN guards itself
      against their noise inside the one filter); what the tables called "OIDN" before the prefiltered mode.

    OIDN wants non-negative linear HDR colour, albedo in [0, 1] and normals in [-1, 1]; the layers are
    clipped to that. ValueError for another mode or quality; ImportError (naming the package) if ``pyoidn`` is
    not installed.
    """
    if mode not in OIDN_MODES:
        raise ValueError(f"OIDN mode {mode!r}: expected one of {', '.join(OIDN_MODES)}")
    if quality not in OIDN_QUALITIES:
        raise ValueError(f"OIDN quality {quality!r}: expected one of {', '.join(OIDN_QUALITIES)}")
    try:
        import pyoidn
    except ImportError:
        raise ImportError("Intel Open Image Denoise needs the optional package pyoidn: pip install '.[oidn]'") from None

    colour, albedo, normal = _oidn_layers(aovs)
    level = _oidn_quality(pyoidn, quality)
    if mode == "plain":
        return pyoidn.denoise(colour, albedo=albedo, normal=normal, hdr=True, quality=level)
    with pyoidn.Device() as device:
        device.commit()
        albedo = _oidn_auxiliary(pyoidn, device, pyoidn.OIDN_IMAGE_ALBEDO, albedo, quality)
        normal = _oidn_auxiliary(pyoidn, device, pyoidn.OIDN_IMAGE_NORMAL, normal, quality)
    return pyoidn.denoise(colour, albedo=albedo, normal=normal, hdr=True, clean_aux=True, quality=level)


def oidn_inputs(frame) -> dict[str, np.ndarray]:
    """The layers OIDN is given for ``frame`` (a ``prep.layouts.Frame``): its own, with the albedo and normal
    its renderer hands its own denoiser where the file has them in place of the network's (Cycles' Denoising
    Albedo and Denoising Normal, which Blender gives OIDN: they follow mirrors and glass, where Diffuse Color is
    black), so that the anchor is OIDN as the renderer runs it."""
    return layouts.denoiser_guides(frame.served_layers())


# The anchors a frame is judged against, by their keys in the studies' and evaluate's rows: OIDN in each of
# OIDN_MODES and the renderer's own denoised frame where the folder has it.
OIDN_KEYS = {"plain": "oidn", "prefiltered": "oidn_prefiltered"}  # "oidn" kept for plain: older reports read as before
ANCHORS = (*OIDN_KEYS.values(), "blender")
RENDERER_DENOISED = "-blender-oidn.exr"  # the name Blender's own denoised frame ends in, beside its noisy render


def renderer_denoised(noisy_path: Path) -> Path:
    """Where the renderer's own denoised frame of ``noisy_path`` is (``<scene>-<spp>spp-blender-oidn.exr``
    beside it), if it wrote one."""
    noisy_path = Path(noisy_path)
    return noisy_path.with_name(noisy_path.name[: -len(".exr")] + RENDERER_DENOISED)


def anchor(row: dict) -> tuple[str, dict] | None:
    """The strongest anchor of a row that holds some of :data:`ANCHORS` as ``{"relmse": ...}`` scores: (its key,
    its scores), the lowest relMSE of those present (the first of :data:`ANCHORS` on a tie); None where the row
    has none. A frame is won only where kpcn's relMSE is strictly below this one's."""
    present = [(key, row[key]) for key in ANCHORS if row.get(key) is not None]
    return min(present, key=lambda kv: kv[1]["relmse"]) if present else None
