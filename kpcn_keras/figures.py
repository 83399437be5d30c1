"""``kpcn figures``: the seed report's figures (docs/method.md §10), drawn from a run's own networks on one frame.

Written into ``<run>/figures/`` (``Run.figures_dir``), each as a PNG, for the frame given (default: the
run's first held-out scene at its lowest sample count):

=====================  ===================================================================================
file                   what (seed report figure: docs/method.md §10)
=====================  ===================================================================================
``kernels.png``        per branch, the kernel predicted at a chosen pixel beside the input crop around it
                       and the reference crop, with the filtered value (Fig. 2); not for dpcn, which
                       predicts colour directly; a no-split run's diffuse branch alone
``multiscale.png``     input | without the compositor | with it | reference, relMSE in the captions
                       (Fig. 15); a multiscale run only
``alpha.png``          the compositor's α maps, per branch and per scale, finest first (Fig. 16); a
                       multiscale run only
``slopes.png``         the same frame denoised at a sweep of λ (Fig. 17); a run trained with
                       ``--slope-input`` only (a network trained at one λ has nothing to sweep)
``slope_map.png``      Fig. 17 with a map: λ at the low end of the run's range on the left half, the high end
                       on the right, beside both uniform results and each half's largest difference from
                       its uniform frame; a run trained with ``--slope-module`` only
``sampling.png``       the run's shard set: a render's sampling PDF and the patches cut from it (Fig. 3)
``inputs.png``         the run's shard set: the network inputs of one of those patches (Fig. 4)
=====================  ===================================================================================

The last two are the data figures of ``prep.figures`` (which draws them for a shard set alone too), on the
frame when it is an input of the run's shard set, else on the set's first held-out input; a run whose
shard set, or that render, is not there (a shipped model) draws the others.

The chosen pixel defaults to the pixel of the highest noisy-colour variance at least a kernel radius from
the border: where a kernel has the most to do. Each of the seven files is checked against every file the
figures read (the frame, its reference, the run's models, the shard set's manifest, render and shards)
before the run is loaded. The run's record is read once and its networks loaded once
(``Denoiser.from_run``): every figure, the λ sweep and the comparison without the compositor use that one
denoiser, λ given per call (the run's validation λ, ``RunRecord.validation_slope``, but for the sweep).
"""

from __future__ import annotations

from pathlib import Path

import keras
import numpy as np

from kpcn_keras.config import DEFAULT_SLOPES
from kpcn_keras.denoise import Denoiser
from kpcn_keras.models import build_kernel_model, network_input
from kpcn_keras.multiscale import alpha_maps
from kpcn_keras.panels import side_by_side_png
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from prep import exr, features, metrics
from prep.colour import tonemap
from prep.errors import KpcnError, OptionError
from prep.features import BRANCHES
from prep.figures import DATA_FIGURES, data_plan
from prep.files import check_outputs, pyplot, save_png
from prep.inputs import InputSet, restrict

FIGURES = {**{name: f"{name}.png" for name in ("kernels", "multiscale", "alpha", "slopes", "slope_map")},
           **DATA_FIGURES}


def _to_numpy(x) -> np.ndarray:
    return np.asarray(keras.ops.convert_to_numpy(x))


def choose_pixel(aovs: dict, radius: int) -> tuple[int, int]:
    """(y, x) of the highest colour variance at least ``radius`` from every border."""
    var = np.asarray(aovs["colorVariance"], np.float64)
    h, w = var.shape
    if h <= 2 * radius or w <= 2 * radius:
        raise KpcnError(f"the frame ({w}x{h}) is smaller than one {2 * radius + 1}-pixel kernel")
    inner = var[radius : h - radius, radius : w - radius]
    y, x = np.unravel_index(np.argmax(inner), inner.shape)
    return int(y) + radius, int(x) + radius


def kernel_figure(den: Denoiser, aovs: dict, ref: dict | None, path: Path, pixel=None, slope=None) -> Path | None:
    """``kernels.png`` (Fig. 2) at ``slope``; None for a run whose networks predict no kernels."""
    cfg = den.model_config
    if cfg.arch == "dpcn":
        return None
    k, r = cfg.kernel_size, cfg.kernel_size // 2
    y, x = pixel if pixel is not None else choose_pixel(aovs, r)
    h, w = aovs["default"].shape[:2]
    if not (r <= y < h - r and r <= x < w - r):
        raise OptionError("pixel", f"must be at least {r} pixels from the border of the {w}x{h} frame, got {y},{x}")
    # the branches the run's networks denoise, of the layers they read (the pixel is chosen on the frame as
    # it is: a no-variance run reads no variance), its auxiliaries as the run's were prefiltered
    aovs = den.given(aovs)
    ref = None if ref is None else restrict(ref, InputSet(split=den.inputs.split, variance=False))
    plt = pyplot()
    fig, axes = plt.subplots(len(den.branches), 4, figsize=(10, 2.7 * len(den.branches)), squeeze=False)
    # the network sees a window of its receptive radius around the pixel: enough for this pixel's kernel
    m = den.margin
    ya, yb, xa, xb = max(y - m, 0), min(y + m + 1, h), max(x - m, 0), min(x + m + 1, w)
    for row, branch in zip(axes, den.branches):
        net = den.networks["shared" if cfg.branch_channels else branch]
        feats = network_input(features.branch_features(aovs, branch, (ya, yb, xa, xb)), cfg, branch, slope)
        kernels = _to_numpy(build_kernel_model(net).predict_on_batch(feats[None]))[0]
        kernel = kernels[y - ya, x - xa].reshape(k, k)
        colour = features.branch_colour(aovs, branch)
        crop = colour[y - r : y + r + 1, x - r : x + r + 1]
        filtered = float((kernel[..., None] * crop).sum(axis=(0, 1)).mean())
        panels = [(f"{branch} input (log) around ({y},{x})", crop.mean(-1), "magma"),
                  (f"kernel {k}x{k}, max weight {kernel.max():.3f}", kernel, "viridis")]
        if ref is not None:
            ref_colour = features.branch_colour(ref, branch)
            panels.append(("reference (log)", ref_colour[y - r : y + r + 1, x - r : x + r + 1].mean(-1), "magma"))
        # the input and reference crops share one colour scale, so they can be compared by eye
        crops = [image for _, image, cmap in panels if cmap == "magma"]
        lo, hi = min(c.min() for c in crops), max(c.max() for c in crops)
        for ax, (title, image, cmap) in zip(row, panels):
            scale = {"vmin": lo, "vmax": hi} if cmap == "magma" else {}
            ax.imshow(image, cmap=cmap, interpolation="nearest", **scale)
            ax.set_title(title, fontsize=8)
        row[0].plot([r], [r], "c+", markersize=12)
        row[-1].axis("off")
        row[-1].text(0.0, 0.5, f"filtered pixel (log, mean of RGB): {filtered:.3f}\n"
                     f"input pixel: {crop[r, r].mean():.3f}", fontsize=9, va="center")
        for ax in row[:-1]:
            ax.set_xticks([])
            ax.set_yticks([])
    fig.suptitle("predicted kernels (seed report Fig. 2)", fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def _caption(name: str, image: np.ndarray, ref: dict | None) -> str:
    return name if ref is None else f"{name}\nrelMSE {metrics.relmse(image, ref['default']):.4f}"


def multiscale_figure(den: Denoiser, aovs: dict, ref: dict | None, path: Path, slope=None) -> Path:
    """``multiscale.png`` (Fig. 15): the run with and without its compositor, side by side, at ``slope``."""
    without = den.without_compositor()(aovs, slope=slope)["default"]
    with_ = den(aovs, slope=slope)["default"]
    panels = [("input", aovs["default"]), (_caption("without multiscale", without, ref), without),
              (_caption("with multiscale", with_, ref), with_)]
    if ref is not None:
        panels.append(("reference", ref["default"]))
    return side_by_side_png(path, panels, title="multiscale (seed report Fig. 15)")


def alpha_figure(den: Denoiser, aovs: dict, path: Path, slope=None) -> Path:
    """``alpha.png`` (Fig. 16): α of every compositor application at ``slope``, per branch, finest scale
    first."""
    plt = pyplot()
    rows = []
    for branch in BRANCHES:
        feats = network_input(features.branch_features(aovs, branch), den.model_config, branch, slope)
        rows.append((branch, [a[0, ..., 0] for a in alpha_maps(den.models[branch], feats[None])]))
    cols = 1 + len(rows[0][1])
    fig, axes = plt.subplots(len(rows), cols, figsize=(3 * cols, 3 * len(rows)), squeeze=False)
    for ax_row, (branch, alphas) in zip(axes, rows):
        ax_row[0].imshow(tonemap(aovs[branch]), interpolation="nearest")
        ax_row[0].set_title(f"{branch} input", fontsize=9)
        for i, (ax, alpha) in enumerate(zip(ax_row[1:], alphas)):
            im = ax.imshow(alpha, vmin=0, vmax=1, cmap="gray", interpolation="nearest")
            ax.set_title(f"α, scale 1/{2 ** i}: mean {alpha.mean():.2f}", fontsize=9)
        fig.colorbar(im, ax=ax_row[-1], fraction=0.046)
        for ax in ax_row:
            ax.axis("off")
    fig.suptitle("compositor α: 1 takes the coarse scale's low frequencies (seed report Fig. 16)", fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def slope_figure(den: Denoiser, aovs: dict, ref: dict | None, path: Path, slopes) -> Path:
    """``slopes.png`` (Fig. 17): one frame denoised at every λ of ``slopes``."""
    panels = [("input", aovs["default"])]
    for slope in slopes:
        out = den(aovs, slope=slope)["default"]
        panels.append((_caption(f"λ = {slope:g}", out, ref), out))
    if ref is not None:
        panels.append(("reference", ref["default"]))
    return side_by_side_png(path, panels, title="asymmetric loss slope λ at inference (seed report Fig. 17)")


def half_and_half(den: Denoiser, aovs: dict, low: float, high: float) -> dict[str, np.ndarray]:
    """The frame denoised with λ = ``low`` on the left half (columns below W // 2) and ``high`` on the right
    (``"map"``), and at each λ alone (``"low"``, ``"high"``): the default colour of each."""
    h, w = aovs["depth"].shape
    painted = np.where(np.arange(w) < w // 2, low, high)[None].repeat(h, 0)
    return {"map": den(aovs, slope=painted)["default"], "low": den(aovs, slope=low)["default"],
            "high": den(aovs, slope=high)["default"]}


def slope_map_figure(den: Denoiser, aovs: dict, ref: dict | None, path: Path) -> Path:
    """``slope_map.png``: :func:`half_and_half` at the ends of the run's λ range, the map's halves against
    the uniform frames in the captions."""
    low, high = den.record.train.slope_range
    got = half_and_half(den, aovs, low, high)
    half = aovs["depth"].shape[1] // 2
    left = np.abs(got["map"][:, :half] - got["low"][:, :half]).max()
    right = np.abs(got["map"][:, half:] - got["high"][:, half:]).max()
    panels = [(_caption(f"λ = {low:g} everywhere", got["low"], ref), got["low"]),
              (f"λ = {low:g} | {high:g}\nhalves vs uniform: max |Δ| {left:.2g}, {right:.2g}", got["map"]),
              (_caption(f"λ = {high:g} everywhere", got["high"], ref), got["high"])]
    return side_by_side_png(path, [("input", aovs["default"]), *panels],
                            title="a painted λ map: one half at each end of the range (Fig. 17 with a map)")


def make_figures(run: Run, frame: tuple[str, str | None] | None = None, *, pixel=None,
                 slopes=DEFAULT_SLOPES, settings: InferenceSettings = InferenceSettings()) -> dict[str, Path]:
    """Every figure ``run`` can show, for ``frame`` = (noisy EXR, reference EXR or None), its denoiser applied
    with ``settings``; returns name -> path."""
    from kpcn_keras.evaluate import held_out_pairs

    record = run.record()
    if frame is None:
        pairs = held_out_pairs(run, record)
        if not pairs:
            raise KpcnError(f"{run.dir}: no held-out scenes; give a noisy render")
        frame = min(pairs, key=lambda pair: exr.parse_render_filename(pair[0]))  # (scene, spp)
    noisy_path, ref_path = frame
    data = data_plan(run.shard_set(record).dir, noisy_path, for_run=True)
    read = [("input", noisy_path)] + ([("reference", ref_path)] if ref_path else []) + run.read_files(record)
    read += data.reads() if data else []
    check_outputs([("figure", run.figures_dir / name) for name in FIGURES.values()], read,
                  f"give a render from outside {run.figures_dir}")
    aovs = exr.read_aovs(noisy_path)
    ref = exr.read_aovs(ref_path, variances=False) if ref_path else None
    den = Denoiser.from_run(run, settings, record=record)
    slope = record.validation_slope
    out_dir = run.figures_dir
    written = {}
    kernels = kernel_figure(den, aovs, ref, out_dir / FIGURES["kernels"], pixel, slope)
    if kernels:
        written["kernels"] = kernels
    if den.compositor is not None:
        written["multiscale"] = multiscale_figure(den, aovs, ref, out_dir / FIGURES["multiscale"], slope)
        written["alpha"] = alpha_figure(den, aovs, out_dir / FIGURES["alpha"], slope)
    if slope is not None:
        written["slopes"] = slope_figure(den, aovs, ref, out_dir / FIGURES["slopes"], slopes)
    if den.model_config.slope_module:
        written["slope_map"] = slope_map_figure(den, aovs, ref, out_dir / FIGURES["slope_map"])
    if data:
        written.update(data.draw(out_dir))
    return written


__all__ = ["choose_pixel", "half_and_half", "make_figures"]
