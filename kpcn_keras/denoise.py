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
branches are mapped back to linear colour (``prep.colour`` inverses), summed in float64 and clamped to the float32
range (``prep.exr.to_float32``), so the output is finite for any finite input. The diffuse network predicts
irradiance, which is multiplied back by an albedo cleaner than the input's: the run's albedo network's where it has
one (``--albedo-steps``: a copy of the diffuse network trained to filter the albedo, ``models.albedo_input``), run on
each tile's window as the branches are; else the albedo prefiltered with its variance (``prep.albedo``: the noisy
albedo where a frame has no variance), each tile's from its own neighbourhood. Either way tiles still equal an
untiled run.

A run trained on prefiltered auxiliaries (``kpcn train --auxiliaries``, ``RunRecord.auxiliaries``) is given them
so: each frame, as its input set reads it, has its albedo, normal and depth prefiltered once, whole, before any
tile (``prep.auxiliary.network_layers``, the function its shards were cut with; :meth:`Denoiser.given`), so tiles
still equal an untiled run. That holds three float32 layers more than the frame (seven channels) besides what the
filter itself holds (OIDN's buffers, the frame's size), not bounded by the tile (docs/denoise.md §3). A run needing
``pyoidn`` where it is not installed is refused when it is loaded.

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

Files in, files out (a batch of frames, their reports, the outputs' names) are ``kpcn_keras.batch``'s; a model's
variants and the denoisers loaded from them, ``kpcn_keras.serving``'s; the side-by-side PNGs,
``kpcn_keras.panels``'.
"""

from __future__ import annotations

import gc

import keras
import numpy as np

from kpcn_keras import slope_map
from kpcn_keras.augment import Augmentation, augment_spatial, moved_box
from kpcn_keras.config import ALBEDO_NETWORK
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
from kpcn_keras.onnx_export import onnx_networks
from kpcn_keras.onnx_runtime import check_servable
from kpcn_keras.precision import apply as apply_precision
from kpcn_keras.precision import resolve
from kpcn_keras.run import Run, RunRecord, check_architecture
from kpcn_keras.settings import InferenceSettings
from prep import colour, exr, features
from prep.albedo import prefilter as prefilter_albedo
from prep.auxiliary import RAW, check_method, network_layers
from prep.errors import KpcnError, OptionError


class Denoiser:
    """The finished networks of one run, applied to whole renders.

    :meth:`from_run` reads them: the run must be finished and its files the ones it wrote
    (``RunRecord.finished``, ``Run.load_component``). ``slope`` is given per call: λ for a run trained with
    a slope input channel (required there, refused elsewhere: ``RunRecord.check_slope``), so one loaded
    denoiser serves every λ. :meth:`without_compositor` is the same networks without a multiscale run's
    compositor (the "without" of a with/without comparison), nothing loaded again.

    A frame is first restricted to the run's input set (``prep.inputs.restrict``, ``RunRecord.inputs``) and its
    auxiliaries prefiltered as the run's were (``RunRecord.auxiliaries``; :meth:`given`): the networks see what
    their shards held. A no-split run has the diffuse network alone (:attr:`branches`):
    its input is the total colour, the specular branch is not run and its output is 0, so ``default`` is the
    diffuse output. ``settings`` (``kpcn_keras.settings``): the tile, the trunks' precision and the members of a
    self-ensemble (module docstring; 1: the networks once).
    """

    def __init__(self, run: Run, record: RunRecord, networks: dict[str, keras.Model],
                 compositor: keras.Model | None = None, settings: InferenceSettings = InferenceSettings(),
                 albedo: keras.Model | None = None):
        self.run, self.record, self.model_config, self.settings = run, record, record.model, settings
        self.networks, self.compositor, self.asked_tile = networks, compositor, settings.tile
        self.albedo_network = albedo
        self.symmetries = tuple(Augmentation(code) for code in range(settings.ensemble))
        onnx = settings.runtime == "onnx"
        if onnx:  # what onnxruntime cannot serve is refused before any network is touched
            check_servable(run.dir, precision=settings.precision, compositor=compositor is not None,
                           slope_module=bool(self.model_config.slope_module))
        # the trunks' arithmetic, set on the networks given (kpcn_keras/precision.py): "float32" or "bfloat16";
        # with onnx "auto" is float32: the graphs are float32 (an explicit bfloat16 was refused above)
        self.precision = "float32" if onnx else resolve(settings.precision)
        for net in [*networks.values(), *([albedo] if albedo is not None else [])]:
            apply_precision(net, self.precision)
        if onnx:
            networks, self.albedo_network = self._onnx(networks, albedo)
        self.inputs, self.branches, self.auxiliaries = record.inputs, record.branches, record.auxiliaries
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

    def _onnx(self, networks: dict, albedo):
        """The float32 networks (and the albedo network) as onnxruntime runs them (``kpcn_keras.onnx_runtime``)."""
        align = input_alignment(self.model_config)
        networks = onnx_networks(networks, align)
        return networks, None if albedo is None else onnx_networks({"albedo": albedo}, align)["albedo"]

    @classmethod
    def from_run(cls, run: Run, settings: InferenceSettings = InferenceSettings(), *,
                 record: RunRecord | None = None, multiscale: bool = True, resampling: bool = False) -> Denoiser:
        """The denoiser of ``run`` applied with ``settings`` (tile, precision, ensemble: ``kpcn_keras.settings``):
        its ``record`` (read here if not given) and each network loaded once. ``multiscale=False`` leaves a
        multiscale run's compositor out; ``resampling``: the resample loop's own use, between the phases of its
        current round. Only the networks of the branches the run's input set runs are read
        (``RunRecord.branches``)."""
        record = (run.record() if record is None else record).finished(resampling=resampling)
        if not settings.clean_aux:  # clean auxiliaries are given as they are: no prefilter runs
            check_method(record.auxiliaries, f"model {run.dir}")  # before any network is read
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
        return cls(run, record, networks, compositor, settings, albedo)

    def given(self, aovs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The layers of the frame ``aovs`` the networks are given: as the run's input set reads them, the
        auxiliaries prefiltered, whole, as the run's shards were (``prep.auxiliary.network_layers``). A frame
        is given once: every tile, branch and member reads the result. With ``settings.clean_aux`` the frame's
        auxiliaries are clean already and are given as they are."""
        return network_layers(aovs, self.inputs, RAW if self.settings.clean_aux else self.auxiliaries)

    @property
    def ensemble(self) -> int:
        return len(self.symmetries)

    def without_compositor(self) -> Denoiser:
        """The same networks without the compositor (itself for a run that has none)."""
        if self.compositor is None:
            return self
        return Denoiser(self.run, self.record, self.networks, None, self.settings, self.albedo_network)

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
        aovs = self.given(aovs)
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
        recombination of one tile), at any frame size (and, for a run with prefiltered auxiliaries, the
        frame's prefiltered auxiliaries). The frame is restricted to the run's input set first (what is kept is
        not copied; :meth:`given`); the specular branch a no-split run does not run gives 0."""
        aovs = self.given(aovs)
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
            diffuse = colour.diffuse_from_log(predict("diffuse", tile, window)[cut], albedo(tile, window)[cut])
            specular = (colour.specular_from_log(predict("specular", tile, window)[cut])
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
        aovs = denoiser.given(aovs)  # once per frame, as the trunks
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
