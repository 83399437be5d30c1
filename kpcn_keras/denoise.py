"""Full-frame inference: a noisy render in the AOV layout in, the denoised colour out.

Each branch network (or the shared one, or either wrapped in the multiscale compositor) runs on overlapping
tiles so that memory stays bounded at any resolution. A tile's margin is the model's receptive radius
(trunk + kernel, ``models.receptive_radius``; ``multiscale.multiscale_radius`` with a compositor), and only
its centre is kept, so the result equals an untiled run up to float rounding. With a compositor, tiles and
margins are multiples of the pyramid's alignment, so each tile pools the same 2x2 blocks as the whole image. The branches are
mapped back to linear colour (``prep.features`` inverses, with the noisy albedo), summed in float64 and
clamped to the float32 range (``prep.exr.to_float32``), so the output is finite for any finite input.

``denoise_file`` checks its outputs before it loads anything: an output that is the input itself, or that
could not be written, is refused at once. The default output is ``<input stem>-denoised.exr`` beside the
input (:func:`default_output`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import keras
import numpy as np

from kpcn_keras.config import DEFAULT_TILE
from kpcn_keras.models import network_input, receptive_radius
from kpcn_keras.multiscale import CompositorConfig, alignment, build_multiscale_model, multiscale_radius
from kpcn_keras.run import Run, check_architecture
from prep import exr, features
from prep.errors import KpcnError, OptionError
from prep.features import BRANCHES
from prep.files import check_writable, pyplot, save_png



class Denoiser:
    """The finished networks of one run folder, applied to whole renders.

    ``slope``: λ for a run trained with a slope input channel (required there, refused elsewhere).
    ``multiscale=False`` leaves a multiscale run's compositor out (the single-scale networks alone: the
    "without" of a with/without comparison).
    """

    def __init__(self, run_dir: str | Path, tile: int = DEFAULT_TILE, *, slope: float | None = None,
                 multiscale: bool = True):
        if isinstance(tile, bool) or not isinstance(tile, int) or tile < 1:
            raise OptionError("tile", f"must be an integer >= 1 (pixels), got {tile!r}")
        self.run = Run(run_dir)
        self.record = self.run.read_record()
        self.model_config = self.run.model_config(self.record)
        if self.model_config.slope_channel and slope is None:
            raise OptionError("slope", f"is needed: {self.run.dir} was trained with λ as an input, for λ in "
                              f"{self.record['train']['slope_range']}")
        self.slope = slope
        names = {b: "shared" if self.model_config.branch_channels else b for b in BRANCHES}
        networks = {}
        for name in dict.fromkeys(names.values()):
            networks[name] = self.run.load_component(self.record, name)
            check_architecture(networks[name], self.model_config, self.run.dir / self.record["components"][name]["file"])
        self.networks = networks
        self.margin = receptive_radius(self.model_config)
        self.align = 1
        self.compositor = None
        if multiscale and "compositor" in self.record["components"]:
            comp_cfg = CompositorConfig.from_dict(self.record["train"]["compositor"])
            self.compositor = self.run.load_component(self.record, "compositor")
            networks = {name: build_multiscale_model(net, comp_cfg, compositor=self.compositor, name=f"multiscale_{name}")
                        for name, net in networks.items()}
            self.margin = multiscale_radius(self.margin, comp_cfg)
            self.align = alignment(comp_cfg)
        self.models = {b: networks[names[b]] for b in BRANCHES}
        # tiles start at multiples of the pyramid's alignment, so every tile pools the image's own 2x2 blocks
        self.margin = -(-self.margin // self.align) * self.align
        self.tile = -(-tile // self.align) * self.align

    def warm_up(self) -> None:
        """Denoise a small black frame once, so that timings exclude one-time setup (numba, torch)."""
        size = 2 * self.margin + 1
        black = {name: np.zeros((size, size, 3), np.float32) for name in exr.RGB_LAYERS}
        black.update({name: np.zeros((size, size), np.float32) for name in exr.SCALAR_LAYERS})
        self(black)

    def run_branch(self, branch: str, feats: np.ndarray) -> np.ndarray:
        """Model output (log domain) for one (H, W, 27) feature image, tile by tile."""
        model = self.models[branch]
        feats = network_input(feats, self.model_config, branch, self.slope)
        h, w, _ = feats.shape
        out = np.empty((h, w, 3), dtype=np.float32)
        t, m = self.tile, self.margin
        for y0 in range(0, h, t):
            for x0 in range(0, w, t):
                y1, x1 = min(y0 + t, h), min(x0 + t, w)
                ya, xa = max(y0 - m, 0), max(x0 - m, 0)
                yb, xb = min(y1 + m, h), min(x1 + m, w)
                pred = model.predict_on_batch(feats[None, ya:yb, xa:xb])
                pred = keras.ops.convert_to_numpy(pred)[0]
                out[y0:y1, x0:x1] = pred[y0 - ya : y1 - ya, x0 - xa : x1 - xa]
        return out

    def __call__(self, aovs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Denoised ``diffuse``, ``specular`` and ``default`` (linear, float32) of one noisy render."""
        diffuse_log = self.run_branch("diffuse", features.branch_features(aovs, "diffuse"))
        specular_log = self.run_branch("specular", features.branch_features(aovs, "specular"))
        diffuse = features.diffuse_from_log(diffuse_log, aovs["albedo"])
        specular = features.specular_from_log(specular_log)
        return {
            "diffuse": exr.to_float32(diffuse),
            "specular": exr.to_float32(specular),
            "default": exr.to_float32(diffuse + specular),
        }


def side_by_side_png(path: str | Path, panels: list[tuple[str, np.ndarray]], title: str = "") -> Path:
    """Tonemapped panels in a row with their captions (``prep.metrics.tonemap``)."""
    plt = pyplot()

    from prep.metrics import tonemap

    h, w = panels[0][1].shape[:2]
    scale = 4.0 / max(h, w)
    fig, axes = plt.subplots(1, len(panels), figsize=(len(panels) * w * scale, h * scale + 0.8), squeeze=False)
    for ax, (caption, image) in zip(axes[0], panels):
        ax.imshow(tonemap(image), interpolation="nearest")
        ax.set_title(caption, fontsize=9)
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def default_output(input_path: str | os.PathLike) -> Path:
    """``<input stem>-denoised.exr`` beside the input, whatever the input's suffix (or none)."""
    path = Path(input_path)
    stem = path.name[: -len(".exr")] if path.name.lower().endswith(".exr") else path.name
    return path.with_name(f"{stem}-denoised.exr")


def png_path(output: str | os.PathLike) -> Path:
    """The side-by-side PNG written beside an output EXR."""
    return Path(output).with_suffix(".png")


def denoise_file(input_path, run_dir, output=None, reference=None, *, png: bool = True,
                 tile: int = DEFAULT_TILE, slope: float | None = None) -> dict:
    """Denoise one EXR; writes ``output`` (default :func:`default_output`) and a PNG beside it; returns
    timings and, with a reference, metrics."""
    from prep import metrics

    output = Path(output) if output is not None else default_output(input_path)
    for label, other in (("input", input_path), ("reference", reference)):
        if other is not None and Path(other).exists() and output.exists() and os.path.samefile(output, other):
            raise KpcnError(f"--output {output} is the {label} file itself; choose another -o")
    check_writable(output, "--output")
    if png:
        check_writable(png_path(output), "side-by-side PNG")
    denoiser = Denoiser(run_dir, tile=tile, slope=slope)
    noisy = exr.read_aovs(input_path)
    ref = exr.read_aovs(reference, variances=False) if reference else None
    if ref is not None and ref["default"].shape != noisy["default"].shape:
        raise KpcnError(
            f"{reference} is {ref['default'].shape[1]}x{ref['default'].shape[0]} but {input_path} is "
            f"{noisy['default'].shape[1]}x{noisy['default'].shape[0]}"
        )
    denoiser.warm_up()
    start = time.perf_counter()
    result = denoiser(noisy)
    seconds = time.perf_counter() - start
    layers = dict(result)
    layers.update({k: noisy[k] for k in ("albedo", "normal", "depth")})
    exr.write_aovs(output, layers)
    report = {"input": str(input_path), "output": str(output), "seconds": seconds}
    panels = [("input", noisy["default"]), ("denoised", result["default"])]
    if ref is not None:
        report["input_metrics"] = metrics.all_metrics(noisy["default"], ref["default"])
        report["metrics"] = metrics.all_metrics(result["default"], ref["default"])
        panels.append(("reference", ref["default"]))
    if png:
        report["png"] = str(side_by_side_png(png_path(output), panels, title=Path(input_path).name))
    return report
