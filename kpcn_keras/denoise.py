"""Full-frame inference: a noisy render in the AOV layout in, the denoised colour out.

Each branch network (or the shared one, or either wrapped in the multiscale compositor) runs on overlapping
tiles, and so do the features and the recombination, so that memory beyond the frame's own AOVs and the three
float32 outputs is bounded by the tile at any resolution (``tests/test_denoise.py::
test_memory_beyond_the_frame_and_the_output_is_bounded_by_the_tile``): a tile's features are computed from its
window alone, with the frame's depth scale computed once (``prep.features``), and equal those pixels of the
whole frame's bit for bit. A tile's margin is the model's receptive radius
(trunk + kernel, ``models.receptive_radius``; ``multiscale.multiscale_radius`` with a compositor), and only
its centre is kept, so the result equals an untiled run up to float rounding. Tiles and margins are multiples
of the network's alignment (``models.input_alignment``: a unet's pooling grid), times the pyramid's with a
compositor (``multiscale.tile_alignment``), so each tile pools the same 2x2 blocks as the whole image. The
branches are mapped back to linear colour (``prep.features`` inverses), summed in float64 and clamped to the float32
range (``prep.exr.to_float32``), so the output is finite for any finite input. The diffuse network predicts
irradiance, which is multiplied back by an albedo cleaner than the input's: the run's albedo network's where it has
one (``--albedo-steps``: a copy of the diffuse network trained to filter the albedo, ``models.albedo_input``), run on
each tile's window as the branches are; else the albedo prefiltered with its variance (``prep.albedo``: the noisy
albedo where a frame has no variance), each tile's from its own neighbourhood. Either way tiles still equal an
untiled run.

A self-ensemble (``ensemble`` N > 1, ``--ensemble``) trades time for accuracy without training: each tile is
predicted N times, from the frame moved by each of the first N symmetries of the square (``kpcn_keras.augment``'s
spatial codes 0..N-1, the identity first), each prediction moved back, and each branch keeps the per-pixel,
per-channel median of the N (in the log domain: the same pixels as the median of the linear colours, the
transforms being monotone), so that one member's firefly does not pass, where a mean would carry 1/N of it. An
albedo network runs once, on the frame as it is.
A member is exactly the network on the moved frame: its window (grown to start on the moved frame's pooling grid)
is cut with the row and column on each side that the moved window's features read, moved, and its features
computed there (:meth:`Denoiser.predict_member`), so tiles still equal an untiled run and memory is still bounded
by the tile (N predictions of one).

Batches: :func:`denoise_files` reads a run's record and loads its networks once (``Denoiser.from_run``), warms
them up once, then denoises many frames (files, or every render in a folder) and reports start-up, load and
warm-up apart from each frame's time; a frame's ``seconds`` never includes the model load. A frame of a batch
is denoised exactly as alone (the same networks on the same tiles: bit-identical). ``denoise_file`` is the
batch of one. Inputs and outputs are checked before anything is loaded: a file it would write (an output EXR,
its PNG) that is a file it reads (an input, the reference, the run's record or models) or another output, or
that could not be written, an input whose header lacks a layer, a frame whose whole-frame arrays
(:func:`frame_bytes`) the machine cannot hold. Each output is written atomically, so a batch stopped by a bad
frame leaves every earlier output whole. The default output is ``<input stem>-denoised.exr`` beside the input
(:func:`default_output`); with several inputs ``-o`` is a folder.
"""

from __future__ import annotations

import dataclasses
import gc
import os
import time
from pathlib import Path

import keras
import numpy as np

from kpcn_keras import slope_map
from kpcn_keras.augment import Augmentation, augment_spatial, moved_box
from kpcn_keras.config import ALBEDO_NETWORK, DEFAULT_ENSEMBLE, DEFAULT_TILE, ENSEMBLE, TILE
from kpcn_keras.models import (
    albedo_input,
    input_alignment,
    kept_of,
    network_input,
    receptive_radius,
    slope_module_parts,
    slope_plane,
)
from kpcn_keras.multiscale import build_multiscale_model, multiscale_radius, tile_alignment
from kpcn_keras.precision import apply as apply_precision
from kpcn_keras.precision import resolve
from kpcn_keras.run import Run, RunRecord, check_architecture
from prep import exr, features, layouts
from prep.albedo import prefilter as prefilter_albedo
from prep.errors import KpcnError, OptionError
from prep.files import atomic_path, check_outputs, check_writable, pyplot, save_png
from prep.inputs import InputSet, pair_layers, restrict
from prep.processes import memory_shortfall, peak_memory_mb, process_age

DENOISED_SUFFIX = "-denoised.exr"  # what default_output appends; a folder's renders never include one
PNG_ROWS = 256  # rows of a panel tonemapped at a time
# Bytes a pixel of what denoising a frame holds whole, the tiles bounding the rest: the render as read (its
# float32 layers) with the three float32 outputs; the side-by-side PNG (canvas, image and encoder); a
# reference as read with the metrics' float64 arithmetic. Upper bounds of what numpy allocates
# (tests/test_denoise.py::test_frame_bytes_bound_what_a_frame_holds_whole), used to refuse a frame the
# machine cannot hold before any work (frame_bytes).
FRAME_BYTES, PNG_BYTES, REFERENCE_BYTES = 128, 32, 384
# A file of another layout is decoded whole before its layers are made (4 bytes a channel, half or float), and a
# pair is two frames and their float64 mean and difference.
FILE_CHANNEL_BYTES, PAIR_BYTES = 4, 512



class Denoiser:
    """The finished networks of one run, applied to whole renders.

    :meth:`from_run` reads them: the run must be finished and its files the ones it wrote
    (``RunRecord.finished``, ``Run.load_component``). ``slope`` is given per call: λ for a run trained with
    a slope input channel (required there, refused elsewhere: ``RunRecord.check_slope``), so one loaded
    denoiser serves every λ. :meth:`without_compositor` is the same networks without a multiscale run's
    compositor (the "without" of a with/without comparison), nothing loaded again.

    A frame is first restricted to the run's input set (``prep.inputs.restrict``, ``RunRecord.inputs``): the
    networks see what their shards held. A no-split run has the diffuse network alone (:attr:`branches`):
    its input is the total colour, the specular branch is not run and its output is 0, so ``default`` is the
    diffuse output. ``ensemble``: the members of a self-ensemble (module docstring; 1: the networks once).
    """

    def __init__(self, run: Run, record: RunRecord, networks: dict[str, keras.Model],
                 compositor: keras.Model | None = None, tile: int = DEFAULT_TILE, precision: str | None = None,
                 ensemble: int = DEFAULT_ENSEMBLE, albedo: keras.Model | None = None):
        self.run, self.record, self.model_config = run, record, record.model
        self.networks, self.compositor, self.asked_tile = networks, compositor, TILE.check("tile", tile)
        self.albedo_network = albedo
        self.symmetries = tuple(Augmentation(code) for code in range(ENSEMBLE.check("ensemble", ensemble)))
        # the trunks' arithmetic, set on the networks given (kpcn_keras/precision.py): "float32" or "bfloat16"
        self.precision = resolve(precision)
        for net in [*networks.values(), *([albedo] if albedo is not None else [])]:
            apply_precision(net, self.precision)
        self.inputs, self.branches = record.inputs, record.branches
        names = {b: "shared" if self.model_config.branch_channels else b for b in self.branches}
        self.margin = receptive_radius(self.model_config)
        self.align = input_alignment(self.model_config)
        if compositor is not None:
            comp_cfg = record.compositor
            networks = {name: build_multiscale_model(net, comp_cfg, compositor=compositor, name=f"multiscale_{name}")
                        for name, net in networks.items()}
            self.margin = multiscale_radius(self.margin, comp_cfg)
            self.align = tile_alignment(comp_cfg, self.align)
        self.models = {b: networks[names[b]] for b in self.branches}
        # tiles start at multiples of the alignment, so every tile pools the image's own 2x2 blocks (the pyramid's
        # and the unet's at each of its levels)
        self.margin = -(-self.margin // self.align) * self.align
        self.tile = -(-self.asked_tile // self.align) * self.align

    @classmethod
    def from_run(cls, run: Run, tile: int = DEFAULT_TILE, *, record: RunRecord | None = None,
                 multiscale: bool = True, resampling: bool = False, precision: str | None = None,
                 ensemble: int = DEFAULT_ENSEMBLE) -> Denoiser:
        """The denoiser of ``run``: its ``record`` (read here if not given) and each network loaded once.
        ``multiscale=False`` leaves a multiscale run's compositor out; ``resampling``: the resample loop's
        own use, between the phases of its current round. Only the networks of the branches the run's input
        set runs are read (``RunRecord.branches``). ``precision``: the trunks' arithmetic (``--precision``;
        default ``"auto"``: ``kpcn_keras.precision``); ``ensemble``: a self-ensemble's members (``--ensemble``)."""
        tile = TILE.check("tile", tile)
        record = (run.record() if record is None else record).finished(resampling=resampling)
        names = dict.fromkeys("shared" if record.model.branch_channels else b for b in record.branches)
        networks = {}
        for name in names:
            networks[name] = run.load_component(record, name)
            check_architecture(networks[name], record.model, record.component_path(name))
        compositor = None
        if multiscale and "compositor" in record.components:
            compositor = run.load_component(record, "compositor")
        albedo = None
        if ALBEDO_NETWORK in record.components:
            albedo = run.load_component(record, ALBEDO_NETWORK)
            check_architecture(albedo, record.model, record.component_path(ALBEDO_NETWORK))
        return cls(run, record, networks, compositor, tile, precision, ensemble, albedo)

    @property
    def ensemble(self) -> int:
        return len(self.symmetries)

    def without_compositor(self) -> Denoiser:
        """The same networks without the compositor (itself for a run that has none)."""
        if self.compositor is None:
            return self
        return Denoiser(self.run, self.record, self.networks, None, self.asked_tile, self.precision, self.ensemble,
                        self.albedo_network)

    def warm_up(self, slope: float | None = None) -> None:
        """Denoise a small black frame once (at ``slope``), so that timings exclude one-time setup (numba,
        torch): through :meth:`__call__`, so restricted to the run's input set as a frame is."""
        size = 2 * self.margin + 1
        black = {name: np.zeros((size, size, 3), np.float32) for name in exr.RGB_LAYERS}
        black.update({name: np.zeros((size, size), np.float32) for name in exr.SCALAR_LAYERS})
        # a map's own first λ: the black frame is not its shape
        self(black, slope=float(np.ravel(slope)[0]) if slope_map.is_map(slope) else slope)

    def tiles(self, h: int, w: int):
        """Each tile of an (h, w) frame as ((y0, y1, x0, x1), (ya, yb, xa, xb)): the pixels it gives and the
        window, grown by the margin and cut at the frame's border, that the network sees for them."""
        t, m = self.tile, self.margin
        for y0 in range(0, h, t):
            for x0 in range(0, w, t):
                y1, x1 = min(y0 + t, h), min(x0 + t, w)
                yield (y0, y1, x0, x1), (max(y0 - m, 0), min(y1 + m, h), max(x0 - m, 0), min(x1 + m, w))

    def predict_tile(self, branch: str, aovs: dict[str, np.ndarray], tile, window, scale: float,
                     slope: float | None = None) -> np.ndarray:
        """Model output (log domain, float32) of ``tile``'s pixels from the features of ``window`` alone
        (``prep.features.branch_features`` with the frame's depth ``scale``), at ``slope``: the same as
        those pixels of the whole frame's features. A self-ensemble's tile is its members' median (module
        docstring)."""
        if self.ensemble > 1:
            return np.median([self.predict_member(branch, aovs, tile, window, scale, slope, aug)
                              for aug in self.symmetries], axis=0)
        # features (and the extra input channels) are contiguous: a strided view reaches torch as a strided
        # tensor, and the trunk's convolutions and the kernel layer then run on (and copy) other layouts
        feats = network_input(features.branch_features(aovs, branch, window, scale=scale), self.model_config,
                              branch, _window_of(slope, window))
        # predict_on_batch, not a direct call under torch.inference_mode: measured alike (within 10%, the
        # noise) at 64- and 256-pixel tiles; the convolutions, not the per-call setup, take the time
        pred = keras.ops.convert_to_numpy(self.models[branch].predict_on_batch(feats[None]))[0]
        # torch's pytree flattening, which keras runs on every call, leaves a reference cycle that holds the
        # call's tensors (the window's kernel logits and colour); left to the collector's schedule they pile up
        # in the old generation over the tiles of a frame (measured: 0.9 against 0.37 MB over 4 tiles of 32,
        # 1.45 against 0.50 MB over 30). A young-generation pass is cheap (a full one tripled the time).
        gc.collect(1)
        return _kept(pred, tile, window)

    def predict_member(self, branch: str, aovs: dict[str, np.ndarray], tile, window, scale: float,
                       slope: float | None, aug: Augmentation) -> np.ndarray:
        """:meth:`predict_tile` of the frame moved by ``aug``, moved back: the network's output of ``tile``'s pixels
        where the frame is given to it moved, equal to those pixels of the whole moved frame's run."""
        h, w = aovs["depth"].shape
        # on the moved frame the window starts on the pooling grid (a unet's, a pyramid's) as tiles do
        y0, y1, x0, x1 = moved_box(window, (h, w), aug)
        moved_shape = moved_box((0, h, 0, w), (h, w), aug)[1::2]
        on_grid = (y0 - y0 % self.align, y1, x0 - x0 % self.align, x1)
        window = moved_box(on_grid, moved_shape, aug.inverse())
        ya, yb, xa, xb = window
        # features read the next row and column, which on the moved frame may be the previous one here
        cut = (max(ya - 1, 0), min(yb + 1, h), max(xa - 1, 0), min(xb + 1, w))
        layers = {name: _moved(layer[cut[0]:cut[1], cut[2]:cut[3]], aug) for name, layer in aovs.items()}
        inner = moved_box((ya - cut[0], yb - cut[0], xa - cut[2], xb - cut[2]), (cut[1] - cut[0], cut[3] - cut[2]), aug)
        lam = _window_of(slope, window)
        feats = network_input(features.branch_features(layers, branch, inner, scale=scale), self.model_config, branch,
                              _moved(lam, aug) if slope_map.is_map(slope) else lam)
        pred = keras.ops.convert_to_numpy(self.models[branch].predict_on_batch(feats[None]))[0]
        gc.collect(1)  # as in predict_tile
        return _kept(_moved(pred, aug.inverse()), tile, window)

    def albedo_tile(self, aovs: dict[str, np.ndarray], tile, window, scale: float) -> np.ndarray:
        """The albedo the diffuse irradiance of ``tile``'s pixels is multiplied by (float32, (h, w, 3)): the run's
        albedo network's, from ``window`` alone as a branch's is (:meth:`predict_tile`); without one,
        ``prep.albedo.prefilter``'s of the tile's neighbourhood."""
        if self.albedo_network is None:
            return prefilter_albedo(aovs["albedo"], aovs["albedoVariance"], tile).astype(np.float32, copy=False)
        ya, yb, xa, xb = window
        feats = albedo_input(features.branch_features(aovs, "diffuse", window, scale=scale),
                             aovs["albedo"][ya:yb, xa:xb])
        pred = self.albedo_network.predict_on_batch(network_input(feats, self.model_config, "diffuse")[None])
        pred = keras.ops.convert_to_numpy(pred)[0]
        gc.collect(1)  # as in predict_tile
        return _kept(pred, tile, window)

    def frame_albedo(self, aovs: dict[str, np.ndarray], scale: float) -> np.ndarray:
        """:meth:`albedo_tile` of every tile of the frame ``aovs`` (restricted to the run's input set), put together:
        the albedo a denoise of the whole frame multiplies by (float32, (H, W, 3))."""
        out = np.empty(aovs["albedo"].shape, np.float32)
        for tile, window in self.tiles(*aovs["depth"].shape):
            y0, y1, x0, x1 = tile
            out[y0:y1, x0:x1] = self.albedo_tile(aovs, tile, window, scale)
        return out

    def check_slope(self, slope, shape: tuple[int, int]) -> None:
        """OptionError unless ``slope`` is what this run takes for an (H, W) = ``shape`` frame: a number (or
        None) as ``RunRecord.check_slope`` says, or a map of the frame's shape for a run with a specialisation
        module (``kpcn_keras.slope_map``)."""
        self.record.check_slope(slope)
        if not slope_map.is_map(slope):
            return
        if not self.model_config.slope_module:
            raise OptionError("slope_map", f"is for a run trained with --slope-module; {self.run.dir} takes one "
                              "λ for the whole frame (--slope)")
        if np.shape(slope) != tuple(shape):
            raise OptionError("slope_map", f"has shape {np.shape(slope)}, the frame {tuple(shape)}")

    def run_branch(self, branch: str, aovs: dict[str, np.ndarray], slope: float | None = None) -> np.ndarray:
        """Model output (log domain) of one branch for a whole noisy render (restricted to the run's input set
        first), tile by tile, at ``slope``; 0 (log of 0) for a branch the run does not run."""
        h, w = aovs["depth"].shape
        self.check_slope(slope, (h, w))
        if branch not in self.models:
            return np.zeros((h, w, 3), dtype=np.float32)
        aovs = restrict(aovs, self.inputs)
        scale = features.depth_scale(aovs["depth"])
        out = np.empty((h, w, 3), dtype=np.float32)
        for tile, window in self.tiles(h, w):
            y0, y1, x0, x1 = tile
            out[y0:y1, x0:x1] = self.predict_tile(branch, aovs, tile, window, scale, slope)
        return out

    def __call__(self, aovs: dict[str, np.ndarray], slope: float | None = None) -> dict[str, np.ndarray]:
        """Denoised ``diffuse``, ``specular`` and ``default`` (linear, float32) of one noisy render, at
        ``slope`` (λ, for a run trained with it as an input).

        Tile by tile, both branches and their recombination: beyond ``aovs`` and the three float32 outputs,
        what this holds is bounded by the tile (features of one window, its network activations, the float64
        recombination of one tile), at any frame size. The frame is restricted to the run's input set first
        (what is kept is not copied); the specular branch a no-split run does not run gives 0."""
        aovs = restrict(aovs, self.inputs)
        h, w = aovs["depth"].shape
        self.check_slope(slope, (h, w))
        scale = features.depth_scale(aovs["depth"])  # the one whole-image statistic of the features
        return self.assemble((h, w), lambda tile, window: self.albedo_tile(aovs, tile, window, scale),
                             lambda branch, tile, window: self.predict_tile(branch, aovs, tile, window, scale, slope))

    def assemble(self, shape: tuple[int, int], albedo, predict, region=None) -> dict[str, np.ndarray]:
        """``diffuse``, ``specular`` and ``default`` (linear, float32) of a frame of ``shape`` (H, W), tile by
        tile: ``predict(branch, tile, window)`` is a branch's log-domain output of ``tile``'s pixels, ``albedo(tile,
        window)`` the albedo of ``tile``'s pixels (:meth:`albedo_tile`), each branch mapped back to linear colour
        (the diffuse one with that albedo) and the two summed in float64 (the module docstring).
        ``region`` (y0, y1, x0, x1): those pixels alone, from the tiles that meet them (the others not run)."""
        h, w = shape
        ry0, ry1, rx0, rx1 = (0, h, 0, w) if region is None else region
        out = {name: np.empty((ry1 - ry0, rx1 - rx0, 3), dtype=np.float32)
               for name in ("diffuse", "specular", "default")}
        for tile, window in self.tiles(h, w):
            y0, y1, x0, x1 = tile
            # the tile's pixels in the region (c*), cut from the tile's output and put in the region's
            cy0, cy1, cx0, cx1 = max(y0, ry0), min(y1, ry1), max(x0, rx0), min(x1, rx1)
            if cy0 >= cy1 or cx0 >= cx1:
                continue
            cut = np.s_[cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0]
            put = np.s_[cy0 - ry0 : cy1 - ry0, cx0 - rx0 : cx1 - rx0]
            diffuse = features.diffuse_from_log(predict("diffuse", tile, window)[cut], albedo(tile, window)[cut])
            specular = (features.specular_from_log(predict("specular", tile, window)[cut])
                        if "specular" in self.models else np.zeros_like(diffuse))
            out["diffuse"][put] = exr.to_float32(diffuse)
            out["specular"][put] = exr.to_float32(specular)
            out["default"][put] = exr.to_float32(diffuse + specular)
        return out

    def prepare(self, aovs: dict[str, np.ndarray]) -> PreparedFrame:
        """The frame ``aovs`` with each branch's trunk run once, for λ maps applied to it by
        :class:`PreparedFrame` (the interactive case: a new map re-runs only what follows λ). KpcnError for a
        run without the module, or with a compositor (whose pyramid re-runs the whole network at every scale)."""
        if not self.model_config.slope_module:
            raise KpcnError(f"{self.run.dir}: a prepared frame needs a run trained with --slope-module (λ joined "
                            "after the trunk); this one takes λ at its input or not at all")
        if self.compositor is not None:
            raise KpcnError(f"{self.run.dir}: a prepared frame runs the networks without a compositor; load the run "
                            "with multiscale=False (Denoiser.from_run) or denoise it whole")
        if self.ensemble > 1:
            raise KpcnError(f"{self.run.dir}: a prepared frame runs the networks once; load the run with ensemble 1 "
                            f"(it has {self.ensemble}) or denoise it whole")
        return PreparedFrame(self, aovs)


def check_region(region, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    """``region`` as (y0, y1, x0, x1) ints, a non-empty rectangle inside a frame of ``shape`` (H, W);
    OptionError naming what was found otherwise."""
    try:
        y0, y1, x0, x1 = (int(v) for v in region)
    except (TypeError, ValueError):
        raise OptionError("region", f"must be four integers y0, y1, x0, x1, got {region!r}") from None
    h, w = shape
    if not (0 <= y0 < y1 <= h and 0 <= x0 < x1 <= w):
        raise OptionError("region", f"must be a non-empty rectangle inside the {w}x{h} frame (0 <= y0 < y1 <= {h}, "
                          f"0 <= x0 < x1 <= {w}), got {(y0, y1, x0, x1)}")
    return y0, y1, x0, x1


def _kept(pred: np.ndarray, tile, window) -> np.ndarray:
    """The pixels of ``tile`` (y0, y1, x0, x1) of ``pred``, a model's output over ``window`` (ya, yb, xa, xb)."""
    (y0, y1, x0, x1), (ya, _, xa, _) = tile, window
    return pred[y0 - ya : y1 - ya, x0 - xa : x1 - xa]


def _moved(x: np.ndarray, aug: Augmentation) -> np.ndarray:
    """An (H, W) or (H, W, C) layer moved by ``aug.spatial`` (``augment_spatial``)."""
    return augment_spatial(x[..., None], aug)[..., 0] if x.ndim == 2 else augment_spatial(x, aug)


def _window_of(slope, window):
    """``slope`` for the pixels of ``window`` (ya, yb, xa, xb): a map's window, a number (or None) as it is."""
    if not slope_map.is_map(slope):
        return slope
    ya, yb, xa, xb = window
    return np.asarray(slope)[ya:yb, xa:xb]


class PreparedFrame:
    """One frame with its trunks run once (:meth:`Denoiser.prepare`), for a run with a specialisation module:
    calling it with λ (a number or an (H, W) map, ``kpcn_keras.slope_map``) re-runs only, per tile, what follows
    λ (the module, then the kernel head and the kernel application, or a λ mixture's blend), and gives what
    ``denoiser(aovs, slope)`` gives (the same tiles, the same layers: equal to float rounding, tested). It
    holds, per tile window and branch, what ``models.slope_module_parts``' trunk gives: the trunk's activations
    (``width`` channels in the trunk's precision) and the noisy colour, or a λ mixture's J filtered colours
    (:attr:`nbytes`)."""

    def __init__(self, denoiser: Denoiser, aovs: dict[str, np.ndarray]):
        self.denoiser = denoiser
        aovs = restrict(aovs, denoiser.inputs)
        self.shape = aovs["depth"].shape
        scale = features.depth_scale(aovs["depth"])
        # filtered once, as the trunks run once (a map re-runs only what follows λ), tile by tile as a denoise does
        self.albedo = denoiser.frame_albedo(aovs, scale)
        cfg = denoiser.model_config
        self.modules, self.tiles = {}, {}
        for branch, model in denoiser.models.items():
            trunk, self.modules[branch] = slope_module_parts(model)
            for tile, window in denoiser.tiles(*self.shape):
                # λ = 1 holds the place of the map each call writes
                feats = network_input(features.branch_features(aovs, branch, window, scale=scale), cfg, branch, 1.0)
                # torch tensors: each map hands them to the module as they are, no conversion
                self.tiles[branch, tile] = [keras.ops.convert_to_tensor(x) for x in kept_of(trunk, feats[None])]
            gc.collect(1)

    def __call__(self, slope, region=None) -> dict[str, np.ndarray]:
        """``diffuse``, ``specular`` and ``default`` (linear, float32) at ``slope``; with ``region`` (y0, y1, x0,
        x1), of those pixels alone, re-running only the tiles that meet them: a map changed inside a region
        changes the output there alone (the module is 1x1), so a brush stroke needs its own rectangle only."""
        self.denoiser.check_slope(slope, self.shape)
        if region is not None:
            region = check_region(region, self.shape)
        return self.denoiser.assemble(self.shape, lambda tile, _: self.albedo[tile[0] : tile[1], tile[2] : tile[3]],
                                      lambda branch, tile, window: self._predict(branch, tile, window, slope), region)

    @property
    def nbytes(self) -> int:
        """Bytes of what the prepared frame holds for the maps (the module docstring's tensors)."""
        return sum(x.element_size() * x.nelement() for kept in self.tiles.values() for x in kept)

    def _predict(self, branch: str, tile, window, slope) -> np.ndarray:
        ya, yb, xa, xb = window
        plane = keras.ops.convert_to_tensor(slope_plane(_window_of(slope, window), (yb - ya, xb - xa)))
        pred = keras.ops.convert_to_numpy(self.modules[branch].predict_on_batch([*self.tiles[branch, tile], plane]))[0]
        gc.collect(1)  # as in Denoiser.predict_tile
        return _kept(pred, tile, window)


def side_by_side_png(path: str | Path, panels: list[tuple[str, np.ndarray]], title: str = "") -> Path:
    """Tonemapped panels in a row with their captions (``prep.metrics.tonemap``), drawn by matplotlib (the
    report figures)."""
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


def panels_png(path: str | Path, panels: list[tuple[str, np.ndarray]], title: str = "") -> Path:
    """The side-by-side PNG of ``kpcn denoise``: tonemapped panels at full resolution in a row, each captioned
    above, the title on top; written atomically. Pillow only: matplotlib's figure, layout and resampling
    cost about 120 ms a frame at 256x256 for the same picture."""
    from PIL import Image, ImageDraw

    from prep.metrics import tonemap

    h, w = panels[0][1].shape[:2]
    gap, line = 4, 14
    top = line * (2 if title else 1)
    canvas = np.full((top + h, len(panels) * (w + gap) - gap, 3), 255, np.uint8)
    for i, (_, image) in enumerate(panels):
        x = i * (w + gap)
        for y in range(0, h, PNG_ROWS):  # the float64 tonemap of a whole frame is 24 bytes a pixel at a time
            rows = slice(y, y + PNG_ROWS)
            canvas[top + y : top + y + PNG_ROWS, x : x + w] = np.round(tonemap(image[rows]) * 255.0).astype(np.uint8)
    picture = Image.fromarray(canvas)
    draw = ImageDraw.Draw(picture)
    if title:
        draw.text((2, 1), title, fill=(0, 0, 0))
    for i, (caption, _) in enumerate(panels):
        draw.text((i * (w + gap) + 2, top - line + 1), caption, fill=(0, 0, 0))
    path = Path(path)
    with atomic_path(path) as tmp:
        picture.save(tmp, format="PNG", compress_level=1)  # speed over a few percent of size
    return path


def frame_bytes(height: int, width: int, *, png: bool = True, reference: bool = False, file_channels: int = 0,
                pair: bool = False) -> int:
    """What :func:`denoise_frame` holds whole for a ``height`` x ``width`` frame (see :data:`FRAME_BYTES`): with
    ``file_channels``, a file of another layout decoded whole (``prep.layouts.read``) beside the layers made
    from it; with ``pair``, a second render read and the pair's float64 arithmetic."""
    per_pixel = FRAME_BYTES + PNG_BYTES * png + REFERENCE_BYTES * reference + FILE_CHANNEL_BYTES * file_channels
    return height * width * (per_pixel + PAIR_BYTES * pair)


def check_frame_memory(path, size: tuple[int, int], *, png: bool = True, reference: bool = False,
                       available_mb: float | None = None, file_channels: int = 0, pair: bool = False) -> None:
    """KpcnError naming the render ``path`` of ``size`` (height, width) if denoising it would hold more
    than this machine has available (:func:`frame_bytes`; ``prep.processes.memory_shortfall``)."""
    needed = frame_bytes(*size, png=png, reference=reference, file_channels=file_channels, pair=pair)
    short = memory_shortfall(needed, available_mb=available_mb)
    if short:
        with_ref = ", with the reference" if reference else ""
        raise KpcnError(f"{path}: denoising its {size[1]}x{size[0]} frame ({needed // (size[0] * size[1])} bytes a "
                        f"pixel held whole{with_ref}) {short}" + ("; without --png it holds less" if png else ""))


def default_output(input_path: str | os.PathLike, folder: str | os.PathLike | None = None) -> Path:
    """``<input stem>-denoised.exr`` beside the input (or in ``folder``), whatever the input's suffix (or none)."""
    path = Path(input_path)
    stem = path.name[: -len(".exr")] if path.name.lower().endswith(".exr") else path.name
    return (Path(folder) if folder is not None else path.parent) / f"{stem}{DENOISED_SUFFIX}"


def png_path(output: str | os.PathLike) -> Path:
    """The side-by-side PNG written beside an output EXR."""
    return Path(output).with_suffix(".png")


def is_output(path: str | os.PathLike) -> bool:
    """Whether ``path`` is named like an output of :func:`default_output` (never taken from a folder)."""
    return Path(path).name.lower().endswith(DENOISED_SUFFIX)


def collect_inputs(paths) -> tuple[list[Path], list[Path]]:
    """The renders to denoise for ``paths`` (files and folders), in order, and the files skipped.

    A file is taken as given. A folder gives every ``*.exr`` directly in it (any case, sorted), except the
    outputs of an earlier run (``*-denoised.exr``) and hidden files (temporaries of an interrupted write),
    which are returned as skipped. KpcnError naming the path for one that does not exist or a folder with
    nothing to denoise.
    """
    inputs, skipped = [], []
    for given in map(Path, paths):
        if given.is_dir():
            found = sorted(p for p in given.iterdir() if p.name.lower().endswith(".exr") and p.is_file())
            take = [p for p in found if not is_output(p) and not p.name.startswith(".")]
            skipped += [p for p in found if p not in take]
            if not take:
                raise KpcnError(f"{given}: no renders to denoise in this folder (found {len(found)} .exr files, "
                                f"{len(found) - len(take)} of them earlier outputs or temporaries)")
            inputs += take
        elif given.exists():
            inputs.append(given)
        else:
            raise KpcnError(f"{given}: no such file or folder")
    return inputs, skipped


def plan_outputs(inputs: list[Path], output=None) -> list[Path]:
    """The output EXR of each input: beside it by default; ``output`` a file for one input, or a folder
    (existing, ending in ``/``, or, with several inputs, to be created) that takes every
    ``<stem>-denoised.exr``. Refuses, before any work, an ``output`` that must be a folder but names a file,
    and two inputs that would write the same output (:func:`denoise_files` checks every file it writes
    against every file it reads)."""
    if output is not None:
        # Path() drops a trailing slash, which is how a user says "a folder" for one input
        as_folder = os.fspath(output).endswith(("/", os.sep)) or Path(output).is_dir()
        output = Path(output)
        if len(inputs) > 1 and not as_folder:
            if output.exists() or output.name.lower().endswith(".exr"):
                raise OptionError("output", f"must be a folder with several inputs ({len(inputs)} given), got {output}"
                                  + (" (a file)" if output.exists() else ""))
            as_folder = True
        outputs = [default_output(p, output) if as_folder else output for p in inputs]
    else:
        outputs = [default_output(p) for p in inputs]
    seen: dict[Path, Path] = {}
    for src, out in zip(inputs, outputs):
        key = Path(os.path.abspath(out))
        if key in seen:
            raise KpcnError(f"{seen[key]} and {src} would both be written to {out}; denoise them "
                            "in separate commands or rename one" if seen[key] != src else f"{src} is given twice")
        seen[key] = src
    return outputs


def read_frame(input_path, *, layout: str | None = None, pair=None, albedo=None, normal=None) -> layouts.Frame:
    """The frame to denoise: ``input_path`` in its layout (``prep.layouts.read``), or with ``pair`` (a second
    render of the same frame, another seed) the two as one frame whose variance comes from their difference
    (``prep.inputs.pair_layers``)."""
    frame = layouts.read(input_path, layout, albedo=albedo, normal=normal)
    if pair is None:
        return frame
    other = layouts.read(pair, layout, albedo=albedo, normal=normal)
    if other.size != frame.size or other.layout != frame.layout or other.inputs.split != frame.inputs.split:
        raise KpcnError(f"{pair} ({other.layout}, {other.size[1]}x{other.size[0]}) is not a second render of "
                        f"{input_path} ({frame.layout}, {frame.size[1]}x{frame.size[0]})")
    spp = frame.spp + other.spp if frame.spp and other.spp else None
    alpha = None if frame.alpha is None else (frame.alpha + other.alpha) / 2
    return dataclasses.replace(frame, layers=pair_layers(frame.layers, other.layers),
                               inputs=InputSet(split=frame.inputs.split, variance=True), alpha=alpha, spp=spp,
                               notes=frame.notes + (f"variance from the pair {input_path} + {pair}",))


def read_reference(reference, input_path, size: tuple[int, int]) -> np.ndarray:
    """The colour of ``reference``, the reference EXR of the frame ``input_path`` of (H, W) ``size``; KpcnError
    naming both files and their sizes when they differ."""
    ref = layouts.read(reference).layers["default"]
    if ref.shape[:2] != tuple(size):
        raise KpcnError(f"{reference} is {ref.shape[1]}x{ref.shape[0]} but {input_path} is {size[1]}x{size[0]}")
    return ref


def output_layers(frame: layouts.Frame, result: dict[str, np.ndarray], split: bool) -> dict[str, np.ndarray]:
    """What an output EXR holds: the denoised colour as layer ``default`` (with the input's alpha as
    ``default.A``), the denoised ``diffuse`` and ``specular`` where the model had a split, and the frame's
    albedo, normal and depth as read."""
    layers = {"default": result["default"]}
    if frame.alpha is not None:
        layers["default.A"] = frame.alpha
    if split:
        layers.update(diffuse=result["diffuse"], specular=result["specular"])
    layers.update({k: frame.layers[k] for k in ("albedo", "normal", "depth")})
    return layers


def denoise_frame(denoiser: Denoiser, input_path, output, reference=None, *, png: bool = True,
                  slope: float | None = None, layout: str | None = None, pair=None, albedo=None, normal=None) -> dict:
    """Denoise one EXR with a loaded (warmed-up) ``denoiser`` at ``slope``: writes ``output`` and, with ``png``, the
    side-by-side PNG beside it, each atomically. ``layout``, ``pair``, ``albedo``, ``normal``: as
    :func:`read_frame`. The output carries the input's header attributes, data and display windows and alpha.
    Returns the frame's report: ``input``, ``layout``, ``inputs`` (what the frame gave), ``model`` (the run
    folder that denoised it), ``output``, ``png`` (if written), ``seconds`` (features, network and
    recombination: no file I/O), ``read_s``, ``write_s``, ``png_s``, ``frame_s`` (all of it) and, with a
    reference, ``metrics`` and ``input_metrics``."""
    from prep import metrics

    begin = time.perf_counter()
    frame = read_frame(input_path, layout=layout, pair=pair, albedo=albedo, normal=normal)
    noisy = frame.layers
    ref = read_reference(reference, input_path, frame.size) if reference else None
    start = time.perf_counter()
    result = denoiser(noisy, slope=slope)
    done = time.perf_counter()
    exr.write_aovs(output, output_layers(frame, result, denoiser.record.inputs.split), attributes=frame.attributes,
                   windows=(frame.data_window, frame.display_window))
    written = time.perf_counter()
    report = {"input": str(input_path), "layout": frame.layout, "inputs": frame.inputs.name,
              "model": str(denoiser.run.dir), "output": str(output), "seconds": done - start,
              "read_s": start - begin, "write_s": written - done}
    panels = [("input", noisy["default"]), ("denoised", result["default"])]
    if ref is not None:
        report["input_metrics"] = metrics.all_metrics(noisy["default"], ref)
        report["metrics"] = metrics.all_metrics(result["default"], ref)
        panels.append(("reference", ref))
    if png:
        report["png"] = str(panels_png(png_path(output), panels, title=Path(input_path).name))
    report["png_s"] = time.perf_counter() - written
    report["frame_s"] = time.perf_counter() - begin
    return report


def denoise_files(inputs, run_dir, output=None, reference=None, *, png: bool = True, tile: int = DEFAULT_TILE,
                  slope: float | None = None, layout: str | None = None, pair=None, albedo=None, normal=None,
                  on_frame=None, precision: str | None = None, slope_map=None,
                  ensemble: int = DEFAULT_ENSEMBLE) -> dict:
    """Denoise many EXRs in one process: each model is loaded and warmed up once.

    ``inputs``: files and folders (:func:`collect_inputs`), each in any layout ``prep.layouts`` reads
    (``layout`` forces one); ``output``: see :func:`plan_outputs`; ``reference``: one reference EXR, and
    ``pair``: a second render of the input, ``albedo``, ``normal``: files of an rgb frame's auxiliaries
    (:func:`read_frame`), for a single input only. Each frame is
    denoised by the model of ``run_dir`` trained for what the frame has (``Run.serving``: the run itself, or
    one of its ``inputs/`` variants). Every input's header, the model each needs and every output are
    checked before a model is loaded, so a missing layer, a missing model, a wrong size or an unwritable
    output fails before any work. A frame that still fails (a truncated file) stops the batch with a KpcnError
    naming it; the outputs written before it are complete (each is written atomically) and are named in the
    message. ``on_frame(report)`` is called after each frame (progress). ``precision``: the networks' trunks'
    arithmetic (``kpcn_keras.precision``; default "auto"). ``slope_map``: a painted λ map (``kpcn_keras.slope_map``)
    instead of ``slope``, for a run with a specialisation module, read for each frame's size before any work.
    ``ensemble``: a self-ensemble's members (module docstring).

    Returns ``{"startup_s", "load_s", "warmup_s", "threads", "precision", "ensemble", "peak_memory_mb", "frames",
    "skipped"}``: the seconds from process start to this call (None off Linux), of loading the networks and of
    the warm-ups; torch's thread count; the precision it resolved to; the self-ensemble's members; the process's
    peak resident memory at the end (:func:`peak_memory_mb`); one :func:`denoise_frame` report per input, in
    order; the folder entries skipped (earlier outputs).
    """
    startup = process_age()
    inputs, skipped = collect_inputs([inputs] if isinstance(inputs, (str, os.PathLike)) else inputs)
    singles = (("reference", reference), ("pair", pair), ("albedo", albedo), ("normal", normal))
    for option, value in singles:
        if value is not None and len(inputs) != 1:
            raise OptionError(option, f"is for one input, got {len(inputs)}"
                              + ("; 'kpcn evaluate' compares many" if option == "reference" else ""))
        if value is not None and Path(value).is_dir():
            what = {"reference": "the input's reference", "pair": "a second render's"}.get(option, f"the {option}")
            raise OptionError(option, f"must be {what} EXR file, got {value}, a folder")
    layouts.check_layout(layout)
    outputs = plan_outputs(inputs, output)
    run = Run(run_dir)
    headers = [layouts.read_header(src, layout) for src in inputs]
    pair_header = layouts.read_header(pair, layout) if pair is not None else None
    # what each frame gives: a pair brings the variance its renders lack
    given = [InputSet(h.inputs.split, True) if pair is not None else h.inputs for h in headers]
    serving = {inputs: run.serving(inputs) for inputs in dict.fromkeys(given)}  # the run of each input set
    records = {variant.dir: variant.record() for variant in serving.values()}
    written = [("--output", out) for out in outputs] + [("side-by-side PNG", png_path(out)) for out in outputs if png]
    read = [("input", src) for src in inputs] + [(option, value) for option, value in singles if value is not None]
    if slope_map is not None:
        read.append(("--slope-map", slope_map))
    models = [item for variant in serving.values() for item in variant.read_files(records[variant.dir])]
    check_outputs(written, read + models, "choose another -o" + (" (or leave out --png)" if png else ""))
    ref_size = layouts.read_header(reference).size if reference is not None else None
    for src, header in zip(inputs, headers):
        for other, size in (("reference", ref_size), ("pair", pair_header and pair_header.size)):
            if size is not None and size != header.size:
                raise KpcnError(f"the {other} is {size[1]}x{size[0]} but {src} is {header.size[1]}x{header.size[0]}")
        check_frame_memory(src, header.size, png=png, reference=reference is not None,
                           file_channels=header.channels, pair=pair is not None)
    for out in outputs:
        check_writable(out, "--output")
        if png:
            check_writable(png_path(out), "side-by-side PNG")
    TILE.check("tile", tile)
    ENSEMBLE.check("ensemble", ensemble)
    precision = resolve(precision)
    slopes = [slope] * len(inputs)
    if slope_map is not None:
        slopes = _read_slope_maps(slope_map, slope, [records[serving[g].dir] for g in given], headers)
    for record in records.values():
        record.finished().check_slope(slopes[0])  # before the networks are loaded
    load_s = warmup_s = 0.0
    denoisers = {}
    frames = []
    for src, out, frame_inputs in zip(inputs, outputs, given):
        variant = serving[frame_inputs]
        if variant.dir not in denoisers:
            begin = time.perf_counter()
            denoisers[variant.dir] = Denoiser.from_run(variant, tile, record=records[variant.dir],
                                                       precision=precision, ensemble=ensemble)
            loaded = time.perf_counter()
            denoisers[variant.dir].warm_up(slopes[0])
            load_s, warmup_s = load_s + loaded - begin, warmup_s + time.perf_counter() - loaded
        try:
            frames.append(denoise_frame(denoisers[variant.dir], src, out, reference, png=png, slope=slopes[len(frames)],
                                        layout=layout, pair=pair, albedo=albedo, normal=normal))
        except KpcnError as exc:
            if frames:
                raise KpcnError(f"{exc} (stopped after {len(frames)} of {len(inputs)} frames; written: "
                                f"{', '.join(f['output'] for f in frames)})") from exc
            raise
        if on_frame is not None:
            on_frame(frames[-1])
    threads = None
    if keras.backend.backend() == "torch":
        import torch

        threads = torch.get_num_threads()
    return {"startup_s": startup, "load_s": load_s, "warmup_s": warmup_s, "threads": threads, "precision": precision,
            "ensemble": ensemble,
            "peak_memory_mb": peak_memory_mb(),
            "frames": frames, "skipped": [str(p) for p in skipped]}


def _read_slope_maps(path, slope, records: list[RunRecord], headers) -> list[np.ndarray]:
    """The λ map ``path`` for each frame (its record's λ range, its header's size); OptionError for a run that
    cannot take one or with ``--slope`` beside it."""
    if slope is not None:
        raise OptionError("slope_map", "and --slope both give λ: give one")
    maps = {}
    for record, header in zip(records, headers):
        if not record.model.slope_module:
            raise OptionError("slope_map", f"is for a run trained with --slope-module (λ joined after the trunk); "
                              f"{record.dir} takes " + ("one λ for the whole frame (--slope)" if
                                                        record.model.slope_channel else "no λ"))
        key = (tuple(record.train.slope_range), tuple(header.size))
        if key not in maps:
            maps[key] = slope_map.read(path, header.size, record.train.slope_range)
    return [maps[tuple(r.train.slope_range), tuple(h.size)] for r, h in zip(records, headers)]


def denoise_file(input_path, run_dir, output=None, reference=None, *, png: bool = True,
                 tile: int = DEFAULT_TILE, slope: float | None = None, precision: str | None = None,
                 **frame_options) -> dict:
    """Denoise one EXR (:func:`denoise_files` with one input); returns its frame report (:func:`denoise_frame`)
    with the batch's ``load_s`` and ``warmup_s``."""
    batch = denoise_files([input_path], run_dir, output, reference, png=png, tile=tile, slope=slope,
                          precision=precision, **frame_options)
    return {**batch["frames"][0], "load_s": batch["load_s"], "warmup_s": batch["warmup_s"]}
