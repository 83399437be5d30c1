"""Self-supervised adaptation: a model corrected on the user's own frames, given as two independent renders each.

Two renders A and B of one frame with different seeds are independent, unbiased estimates of the same image c.
Noise2Noise (Lehtinen et al. 2018) trains a network to map one to the other: where the loss's minimiser under a
noisy target is the target's mean, training on noisy targets is training on clean ones, in expectation. Back et
al. (*Self-Supervised Post-Correction for Monte Carlo Denoising*, SIGGRAPH 2022) make the point that matters here:
the test frame itself, where it is unlike the training data, is the data to correct a supervised denoiser on, with
a small post-correction network trained on it alone. kpcn does that: a post-correction network (:func:`build_post`)
trained on the frame's two halves, A -> B and B -> A, then applied to the model's denoise of their mean, which has
all the samples.

What is trained, and why not the model's own layers: fine-tuning the kernel head of the shipped network (its last
1x1 convolution, the trunk frozen and run once) on the halves made the validation frames worse at every step
count and learning rate tried, its held-out loss rising with the error (docs/adapt.md). The post-correction
instead blends, per pixel, the model's denoised colour with box blurs of it (radii :data:`RADII`: what the
low-frequency residue and a volume left noisy need), weights from a softmax, so its output is a convex combination
of the model's own pixels: it can smooth more where the model kept noise, never add a firefly or extrapolate. Its
guide is the candidates' log colour, the noisy colour and the albedo, normal and depth; it starts as the model's
output (all weight on it but e^-:data:`STAY_BIAS`), and each of its :data:`FOLDS` networks (the guard's, below)
holds about 5,600 weights, few enough for a frame's noisy targets to fit in seconds without fitting their noise.

The loss (:func:`n2n_loss`) is relMSE with a stop-gradient denominator: L = mean(w (f - y)^2), w = 1 / (sg(f)^2
+ RELMSE_EPS), f the corrected linear colour of one half, y the other half's noisy colour. The weight is the
relMSE users are judged by (``prep.metrics``), with f for the unknown reference, and it is a function of the input
half alone, so independent of y: the gradient 2 w (f - y) df/dθ is linear in y, and its expectation over y is the
gradient with the clean target c (``tests/test_adapt.py`` checks it against a statistical bound). A weight or
tone map of the target itself would not be: E[(f - y)^2 / (y^2 + ε)] is minimised by E[y / (y^2 + ε)] / E[1 /
(y^2 + ε)], not by c; Tinits and Mann (2025) bound which nonlinearities of the target stay nearly unbiased, and
a linear target needs none of their bound.

Each half is given to the model as it is, alone: its own layers and the variance its renderer wrote (or none),
never a variance from the pair's difference: (A - B)^2 tells the network about B's noise, and the minimiser
becomes E[B | A, |A - B|], which is not c. So the model's variant is the one for what a half has
(``Serving.variant``), and the mean frame's variance layers (where the halves have them) those of a mean of two
(``prep.inputs.mean_layers``).

The guard, cross-fitted: the correction is :data:`FOLDS` networks trained side by side, each never shown its own
blocks of ``block`` pixels (one in :data:`HELD_OUT_EVERY`, on the same pixels in both directions; the folds' blocks
are disjoint), and applied as the mean of their blends (:func:`combine`). Where to stop: every ``check_every``
steps each held-out block's loss on the halves is taken under the network that never saw it, and each fold's
checkpoint is the one at the step where the *other* folds' blocks did best (:class:`_Choice`), so its own
blocks, which then test it, took no part in choosing it. Whether to keep it: the halves' loss judges the
correction at half the samples (one half in, the other the target), but it is applied to the model's output of
their mean, which has all of them and less noise left, and on the validation frames that verdict did not carry
over (docs/adapt.md §5). So the guard estimates the error of what is applied: on each fold's held-out blocks, the
mean's output corrected by the fold that never saw them against the mean's output itself, each by the pair's own
risk estimate (``kpcn_keras.risk``: the halves' half-difference probes the mean's noise, the outputs of each half
give the secant), and keeps the chosen checkpoints only where the gain clears ``confidence`` standard errors of
the per-block differences. Two folds give it half the frame's blocks to judge by. The mean applied is at least
as good, pixel by pixel, as the mean of its folds' errors (the squared error is convex in the output); on the
blocks one fold trained on, the other's is the honest estimate, as in cross-fitting. :class:`Outcome` says what
was decided and why. With a seed and ``steps`` the adapted weights are the same from run to run; with
``seconds`` the steps depend on the machine.

Memory: training holds, per crop (at most ``crops`` of ``crop`` pixels a side per render, the same for both
halves), the guide and the candidates of its window, and the guard the same of the mean's; applying holds the
same for one tile at a time (:data:`MARGIN` around it), beyond the frame and its denoised output.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import keras
import numpy as np

from kpcn_keras.risk import pair_risk
from kpcn_keras.settings import AdaptSettings
from prep import features
from prep.errors import KpcnError
from prep.inputs import box_mean, mean_layers
from prep.metrics import RELMSE_EPS

RADII = (2, 5, 12)  # box blur radii of the candidates besides the model's own output
WIDTH = 16  # filters of the post-correction's two 3x3 convolutions
STAY_BIAS = 8.0  # the starting logit of the model's own output (the others 0): all but 0.1% of the weight
MARGIN = 2 + max(RADII)  # what a pixel's correction reads around it: the convolutions' reach, then the blurs'
HELD_OUT_EVERY = 4  # one block in this many is held out from each fold's network (the guard's pixels)
FOLDS = 2  # networks cross-fitted, each judged on the blocks held out from it alone (module docstring)
OUTPUTS = ("default", "diffuse", "specular")  # the denoised layers corrected, each with the same weights
GUIDE_CHANNELS = 3 * (1 + len(RADII)) + 3 + 3 + 3 + 1


def n2n_loss(f, y, mask=None):
    """The adaptation loss of corrected colour ``f`` against the noisy target ``y`` (linear, any shape, backend
    tensors): mean of (f - y)^2 / (sg(f)^2 + RELMSE_EPS) over the elements of ``mask`` (broadcast to ``f``; all
    where None). Its expected gradient over an unbiased noisy target is its gradient with the clean target (module
    docstring)."""
    ops = keras.ops
    err = (f - y) ** 2 / (ops.stop_gradient(f) ** 2 + RELMSE_EPS)
    if mask is None:
        return ops.mean(err)
    mask = ops.broadcast_to(ops.cast(mask, err.dtype), ops.shape(err))
    return ops.sum(err * mask) / ops.maximum(ops.sum(mask), 1.0)


def _build_fold(seed: int, name: str) -> keras.Model:
    """One fold's network: guide (None, None, :data:`GUIDE_CHANNELS`) -> logits of the candidates (None, None,
    1 + len(RADII)), two 3x3 convolutions of :data:`WIDTH` then a zero-initialised 1x1 whose bias favours the
    model's own output (:data:`STAY_BIAS`)."""
    guide = keras.Input((None, None, GUIDE_CHANNELS), name="guide")
    x = guide
    for i in range(2):
        x = keras.layers.Conv2D(WIDTH, 3, padding="same", activation="relu",
                                kernel_initializer=keras.initializers.HeNormal(seed=seed + i), name=f"post_conv{i}")(x)
    bias = np.zeros(1 + len(RADII), np.float32)
    bias[0] = STAY_BIAS
    logits = keras.layers.Conv2D(1 + len(RADII), 1, kernel_initializer="zeros",
                                 bias_initializer=keras.initializers.Constant(bias), name="post_logits")(x)
    return keras.Model(guide, logits, name=name)


@keras.saving.register_keras_serializable(package="kpcn")
class LogMeanSoftmax(keras.layers.Layer):
    """log of the mean of the softmaxes of its inputs (logits, the last axis): logits whose softmax is the mean
    of theirs, so the combined network blends the candidates as the mean of its folds' blends."""

    def call(self, logits):
        ops = keras.ops
        mean = ops.mean(ops.stack([ops.softmax(x, axis=-1) for x in logits]), axis=0)
        return ops.log(ops.maximum(mean, 1e-30))

    def compute_output_shape(self, input_shape):
        return input_shape[0]


CUSTOM_OBJECTS = {"kpcn>LogMeanSoftmax": LogMeanSoftmax}  # what loading a saved post-correction needs


def combine(folds: list) -> keras.Model:
    """The post-correction applied: guide -> logits whose softmax is the mean of ``folds``' (networks of
    :func:`_build_fold`'s shape, whose layers it shares)."""
    guide = keras.Input((None, None, GUIDE_CHANNELS), name="guide")
    return keras.Model(guide, LogMeanSoftmax(name="mean_blend")([net(guide) for net in folds]),
                       name="post_correction")


def fold_networks(post: keras.Model) -> list:
    """The fold networks of a combined post-correction (:func:`combine`), in order."""
    return [post.get_layer(f"post_fold{k}") for k in range(FOLDS)]


def build_post(seed: int = 0) -> keras.Model:
    """The post-correction network: :data:`FOLDS` networks (:func:`_build_fold`, each its own seed) combined
    (:func:`combine`); it starts as the model's own output, all but e^-:data:`STAY_BIAS` of the weight on it."""
    return combine([_build_fold(seed + 2 * k, f"post_fold{k}") for k in range(FOLDS)])


def _continue_from(net: keras.Model, post: keras.Model) -> None:
    """Set ``net`` (:func:`build_post`'s) to the weights of ``post``: a post-correction of the same folds, or one
    network (as adaptations before the guard was cross-fitted wrote), which then starts every fold."""
    weights = post.get_weights()
    if len(weights) == len(net.get_weights()):
        net.set_weights(weights)
    else:
        for fold in fold_networks(net):
            fold.set_weights(weights)


def _candidates(colour: np.ndarray) -> np.ndarray:
    """(K, h, w, 3) float32: ``colour`` (linear) and its box blurs of :data:`RADII`, each cut at the window's border."""
    c = np.asarray(colour, np.float64)
    blurs = [np.stack([box_mean(c[..., i], r) for i in range(3)], -1) for r in RADII]
    return np.stack([c, *blurs]).astype(np.float32)


def _guide(candidates: np.ndarray, layers: dict, window, scale: float) -> np.ndarray:
    """(h, w, GUIDE_CHANNELS) float32 guide of ``window`` (y0, y1, x0, x1) of the frame ``layers``: the candidates'
    log colour, the noisy log colour, the albedo, the normal and the depth times ``scale``
    (``prep.features.depth_scale``: 1 / the frame's largest depth, 0 where it has none), in [0, 1] as the
    features' depth is."""
    ya, yb, xa, xb = window
    cut = np.s_[ya:yb, xa:xb]
    parts = [np.log1p(np.maximum(c, 0.0)) for c in candidates]
    parts += [np.log1p(np.maximum(layers["default"][cut], 0.0)), np.clip(layers["albedo"][cut], 0.0, 1.0),
              layers["normal"][cut], (layers["depth"][cut] * scale)[..., None]]
    return np.concatenate(parts, -1).astype(np.float32)


@dataclass
class _Window:
    """One window of a frame as the post-correction reads it: its ``guide``, the ``candidates`` of each denoised
    layer (backend tensors), and ``kept``, the slices of its pixels that are the tile's."""

    guide: object
    candidates: dict
    kept: tuple


def _window(denoised: dict, layers: dict, tile, shape, scale: float, names=OUTPUTS) -> _Window:
    """:class:`_Window` of ``tile`` (y0, y1, x0, x1) in a frame of ``shape``: grown by :data:`MARGIN`, cut at the
    border."""
    h, w = shape
    y0, y1, x0, x1 = tile
    ya, yb, xa, xb = max(y0 - MARGIN, 0), min(y1 + MARGIN, h), max(x0 - MARGIN, 0), min(x1 + MARGIN, w)
    cands = {name: _candidates(denoised[name][ya:yb, xa:xb]) for name in names if name in denoised}
    guide = _guide(cands["default"], layers, (ya, yb, xa, xb), scale)
    tensor = keras.ops.convert_to_tensor
    return _Window(guide=tensor(guide[None]), candidates={k: tensor(v) for k, v in cands.items()},
                   kept=np.s_[y0 - ya : y1 - ya, x0 - xa : x1 - xa])


def _blend(post: keras.Model, window: _Window, names=("default",)) -> dict:
    """The corrected layers ``names`` of ``window``'s tile (backend tensors (h, w, 3)): each candidate weighted by
    the softmax of the post-correction's logits."""
    weights = keras.ops.softmax(post(window.guide)[0], axis=-1)[window.kept]  # (h, w, K)
    weights = keras.ops.transpose(weights, (2, 0, 1))[..., None]  # (K, h, w, 1)
    return {name: keras.ops.sum(window.candidates[name][(slice(None), *window.kept)] * weights, axis=0)
            for name in names}


def correct(post: keras.Model, denoised: dict, layers: dict, tile_size: int) -> dict:
    """``denoised`` (a model's output of the frame ``layers``: linear ``default`` and, where it has them,
    ``diffuse`` and ``specular``) corrected by ``post``, tile by tile (``tile_size``): each layer blended with the
    same weights, so the corrected diffuse and specular still sum to the corrected colour."""
    import torch

    h, w = layers["depth"].shape
    scale = features.depth_scale(layers["depth"])
    out = {name: np.empty_like(denoised[name]) for name in OUTPUTS if name in denoised}
    with torch.no_grad():
        for y0 in range(0, h, tile_size):
            for x0 in range(0, w, tile_size):
                tile = (y0, min(y0 + tile_size, h), x0, min(x0 + tile_size, w))
                blended = _blend(post, _window(denoised, layers, tile, (h, w), scale), tuple(out))
                for name, value in blended.items():
                    out[name][tile[0] : tile[1], tile[2] : tile[3]] = keras.ops.convert_to_numpy(value)
    return out


@dataclass(frozen=True)
class Outcome:
    """What an adaptation did: ``kept`` (the post-correction applies), ``steps`` run in ``seconds``, the error of
    the model's output of the halves' mean estimated from the halves on the held-out blocks (``initial``,
    ``kpcn_keras.risk``) and that of the chosen checkpoints' correction of it (``best``: each fold's network at its
    step of ``best_steps``, 0 for the model's output, on the blocks held out from it), that gain in standard errors
    of the per-block differences (``z``), and ``reason``."""

    kept: bool
    steps: int
    seconds: float
    initial: float
    best: float
    best_steps: tuple
    z: float
    reason: str

    def line(self) -> str:
        # an unbiased estimate of a small error can come out at or below 0: then the change alone says something
        change = (f"{100.0 * (self.best / self.initial - 1.0):+.2f}%" if self.initial > 0 else
                  f"{self.best - self.initial:+.3g}")
        return (f"adaptation {'kept' if self.kept else 'not kept'}: estimated held-out error {self.initial:.5g} -> "
                f"{self.best:.5g} ({change}, {self.z:.1f} standard errors) at steps "
                f"{' and '.join(map(str, self.best_steps))} of {self.steps} in {self.seconds:.1f} s; {self.reason}")

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class _Choice:
    """A fold's checkpoint, chosen by the held-out loss of the other folds' blocks alone (``criterion``): its
    ``step`` and the fold network's ``weights``. The fold's own blocks, which then test it, took no part."""

    criterion: float
    step: int
    weights: list


@dataclass
class _Crop:
    """One crop of one half as a step uses it: its ``tile`` (y0, y1, x0, x1 in the frame), its window
    (:class:`_Window`), the other half's colour of its pixels (the target), which of them each fold trains on
    (``train``, a mask per fold), and which are held out
    (``blocks``: the held-out block of each, -1 where no fold holds it out; ``folds``: the fold that does);
    ``slots``: of each held-out pixel (``blocks >= 0``, in order) its block's place among all the adapter's held-out
    blocks (set by :class:`Adapter`, which numbers them once)."""

    tile: tuple
    window: _Window
    target: object
    train: list
    blocks: np.ndarray
    folds: np.ndarray
    frame: int
    slots: np.ndarray | None = None


@dataclass
class _Probe:
    """One crop's pixels as the guard estimates their error at all the samples (``kpcn_keras.risk``): the crop of
    half A (``crop``: its window, its held-out blocks and their slots), the window of half B (``other``) and of the
    halves' mean (``mean``, its candidates from the model's output of the mean), the mean's noisy colour
    (``colour``), the halves' half-difference (``diff``), the loss weight of the model's output (``weight``) and
    the model's own estimated error per pixel (``base``: it does not change while the correction trains)."""

    crop: _Crop
    other: _Window
    mean: _Window
    colour: np.ndarray
    diff: np.ndarray
    weight: np.ndarray
    base: np.ndarray

    @property
    def windows(self) -> tuple:
        """The windows of the mean, half A and half B: what :func:`kpcn_keras.risk.pair_risk` reads in that order."""
        return self.mean, self.crop.window, self.other


def _held_blocks(tile, s: AdaptSettings, frame_w: int) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel of ``tile`` (frame coordinates) its held-out block's index in the frame and the fold whose
    network never sees it, both -1 where every fold trains on it: the same pixels in both directions of a pair.
    Each fold holds out one block in :data:`HELD_OUT_EVERY`, spread across the frame."""
    y0, y1, x0, x1 = tile
    by = np.arange(y0, y1)[:, None] // s.block
    bx = np.arange(x0, x1)[None, :] // s.block
    index = by * -(-frame_w // s.block) + bx
    code, spacing = (by * 3 + bx) % HELD_OUT_EVERY, HELD_OUT_EVERY // FOLDS
    folds = np.where(code % spacing == 0, code // spacing, -1)
    return np.where(folds >= 0, index, -1), folds


def _crop_tiles(shape, s: AdaptSettings, rng) -> list[tuple]:
    """The crops of a frame of ``shape``: tiles of ``s.crop``, at most ``s.crops`` of them, drawn by ``rng``."""
    h, w = shape
    tiles = [(y0, min(y0 + s.crop, h), x0, min(x0 + s.crop, w))
             for y0 in range(0, h, s.crop) for x0 in range(0, w, s.crop)]
    if len(tiles) > s.crops:
        tiles = [tiles[i] for i in sorted(rng.choice(len(tiles), s.crops, replace=False))]
    return tiles


def _number_blocks(parts: list) -> tuple[np.ndarray, np.ndarray]:
    """Number the held-out blocks of the crops ``parts`` once (a block of a frame: all its pixels in them, in
    (frame, block) order), setting each crop's ``slots``; returns the fold holding out each block and the pixels of
    each (what a block's mean divides by)."""
    keys = sorted({(c.frame, int(k)) for c in parts for k in np.unique(c.blocks[c.blocks >= 0])})
    place = {key: i for i, key in enumerate(keys)}
    folds, pixels = np.full(len(keys), -1), np.zeros(len(keys), np.int64)
    for c in parts:
        held = c.blocks >= 0
        found, index = np.unique(c.blocks[held], return_inverse=True)
        c.slots = np.array([place[c.frame, int(k)] for k in found], np.int64)[index]
        folds[c.slots] = c.folds[held]
        pixels += np.bincount(c.slots, minlength=len(keys))
    return folds, pixels


class Adapter:
    """A post-correction of ``denoise`` (a callable: frame layers -> the model's denoised layers, e.g. a
    ``Denoiser``) trained on ``pairs``, a list of (A, B) layer dicts, two independent renders of each frame.
    ``post``: a network to continue from (an adapted model's); default a new one (:func:`build_post`).
    :meth:`run` trains and decides; :attr:`post` is then the network to apply (:func:`correct`), or None where the
    guard refused it."""

    def __init__(self, denoise, pairs, settings: AdaptSettings | None = None, post: keras.Model | None = None):
        self.settings = settings = settings or AdaptSettings()
        self.start = post
        self.net = build_post(settings.seed)
        if post is not None:
            _continue_from(self.net, post)
        self.folds = fold_networks(self.net)
        rng = np.random.default_rng(settings.seed)
        self.crops, self.probes = [], []
        for frame, (a, b) in enumerate(pairs):
            tiles = _crop_tiles(a["depth"].shape, settings, rng)
            fa, fb = denoise(a), denoise(b)
            ca, cb = self._prepare(a, fa, b, frame, tiles), self._prepare(b, fb, a, frame, tiles)
            self.crops += ca + cb
            self.probes += self._probes(denoise, a, b, tiles, ca, cb)
        self.rng = rng  # the steps' draws continue the crops' stream: one seed decides both
        self.block_folds, self.block_pixels = _number_blocks(self.crops)
        # the probes hold the blocks of half A's crops: the same blocks, each pixel once
        self.probe_pixels = sum(np.bincount(p.crop.slots, minlength=self.block_pixels.size) for p in self.probes)
        self.model_risk = sum(np.bincount(p.crop.slots, p.base[p.crop.blocks >= 0], minlength=self.block_pixels.size)
                              for p in self.probes) / self.probe_pixels
        self.post: keras.Model | None = None
        self.outcome: Outcome | None = None
        self.snapshots: dict = {}

    def _prepare(self, half: dict, denoised: dict, other: dict, frame: int, tiles) -> list[_Crop]:
        """The crops ``tiles`` of ``half`` (``denoised``: the model's output of it), ``other``'s colour their target;
        ``frame`` the pair's index."""
        shape = half["depth"].shape
        scale = features.depth_scale(half["depth"])
        out = []
        for tile in tiles:
            y0, y1, x0, x1 = tile
            blocks, folds = _held_blocks(tile, self.settings, shape[1])
            train = [keras.ops.convert_to_tensor((folds != k)[..., None]) for k in range(FOLDS)]
            out.append(_Crop(tile=tile, window=_window(denoised, half, tile, shape, scale, ("default",)),
                             target=keras.ops.convert_to_tensor(np.asarray(other["default"][y0:y1, x0:x1], np.float32)),
                             train=train, blocks=blocks, folds=folds, frame=frame))
        return out

    def _probes(self, denoise, a: dict, b: dict, tiles, crops_a, crops_b) -> list[_Probe]:
        """The guard's :class:`_Probe` of each crop of ``tiles``: the model's output of the halves' mean, cut as
        the crops are, beside the crops of each half (``crops_a``, ``crops_b``)."""
        mean = mean_layers(a, b)
        out_mean = denoise(mean)
        shape, scale = mean["depth"].shape, features.depth_scale(mean["depth"])
        probes = []
        for tile, ca, cb in zip(tiles, crops_a, crops_b):
            cut = np.s_[tile[0] : tile[1], tile[2] : tile[3]]
            model = np.asarray(out_mean["default"][cut], np.float64)
            colour = np.asarray(mean["default"][cut], np.float64)
            diff = (np.asarray(a["default"][cut], np.float64) - b["default"][cut]) / 2
            weight = 1.0 / (model**2 + RELMSE_EPS)
            window = _window(out_mean, mean, tile, shape, scale, ("default",))
            outputs = [keras.ops.convert_to_numpy(w.candidates["default"][(0, *w.kept)])
                       for w in (window, ca.window, cb.window)]
            probes.append(_Probe(crop=ca, other=cb.window, mean=window, colour=colour, diff=diff, weight=weight,
                                 base=pair_risk(weight, colour, diff, *outputs)))
        return probes

    def _held_losses(self, weights: list | None = None) -> tuple[np.ndarray, list]:
        """The held-out loss of each held-out block (a block of a frame: both directions' pixels of it), in a fixed
        order, and the per-crop loss weights used. ``weights`` None: those of the model's own output (the first
        candidate, exactly: what the checkpoints are compared with), whose losses these are; else each block's
        loss under the fold network that never saw it, weighted by ``weights``."""
        import torch

        sums, used = np.zeros(self.block_pixels.size), []
        mean = lambda f, w, crop: keras.ops.convert_to_numpy(keras.ops.mean(w * (f - crop.target) ** 2, axis=-1))  # noqa: E731
        with torch.no_grad():
            for i, crop in enumerate(self.crops):
                if weights is None:
                    f = crop.window.candidates["default"][(0, *crop.window.kept)]
                    w = 1.0 / (f**2 + RELMSE_EPS)
                    err = mean(f, w, crop)
                else:
                    w, err = weights[i], np.zeros(crop.folds.shape, np.float32)
                    for k, net in enumerate(self.folds):
                        held = crop.folds == k
                        err[held] = mean(_blend(net, crop.window)["default"], w, crop)[held]
                used.append(w)
                sums += np.bincount(crop.slots, err[crop.blocks >= 0], minlength=sums.size)
        return sums / self.block_pixels, used

    def _changes(self, nets: list) -> np.ndarray:
        """Per held-out block of the probes: the change to the model's estimated error at all the samples
        (:attr:`model_risk`, ``kpcn_keras.risk.pair_risk``) that the fold network of ``nets`` that never saw the
        block makes, correcting the mean and each half alike."""
        import torch

        change = np.zeros(self.probe_pixels.size)
        with torch.no_grad():
            for p in self.probes:
                held = p.crop.blocks >= 0
                for k, net in enumerate(nets):
                    own = (p.crop.folds == k)[held]
                    est = pair_risk(p.weight, p.colour, p.diff,
                                    *(keras.ops.convert_to_numpy(_blend(net, w)["default"]) for w in p.windows))
                    change += np.bincount(p.crop.slots[own], (est - p.base)[held][own], minlength=change.size)
        return change / self.probe_pixels

    def run(self, progress=None, marks=()) -> Outcome:
        """Train until ``settings.steps`` steps, or ``settings.seconds`` have passed; ``progress(step, loss,
        seconds)`` after each step. Ends with :attr:`post` the folds' chosen checkpoints, or None where the guard
        refuses them (module docstring). ``marks``: seconds at which to note what a run stopped there would have given
        (:attr:`snapshots`: mark -> (Outcome, the weights to apply or None, the chosen checkpoints' weights whatever
        the guard decided, None where every fold chose the model's output; weights are a list per fold), taken at the
        first held-out check at or after the mark), so one run measures several budgets."""

        s, begin = self.settings, time.perf_counter()
        self.snapshots = {}
        pending = sorted(marks)
        initial, weights = self._held_losses()
        if initial.size < 2:
            raise KpcnError(f"the frame is too small to hold out blocks for the guard: it needs {s.block} x "
                            f"{HELD_OUT_EVERY} pixels a side at least")
        choices = [self._choice(k, 0, initial) for k in range(FOLDS)]
        start = [c.weights for c in choices]
        opt = keras.optimizers.Adam(learning_rate=s.learning_rate)
        opt.build(self.net.trainable_weights)
        step = 0
        while (step < s.steps) if s.steps is not None else (time.perf_counter() - begin < s.seconds):
            loss = self.step(opt)
            step += 1
            if progress is not None:
                progress(step, float(loss.detach()), time.perf_counter() - begin)
            if step % s.check_every == 0:
                blocks, _ = self._held_losses(weights)
                for k in range(FOLDS):
                    if blocks[self.block_folds != k].mean() < choices[k].criterion:
                        choices[k] = self._choice(k, step, blocks)
                while pending and time.perf_counter() - begin >= pending[0]:
                    self._snapshot(pending.pop(0), choices, step, time.perf_counter() - begin)
        self.outcome = self._decide(choices, step, time.perf_counter() - begin)
        for mark in pending:  # the run ended before them: what it gives is what they give
            self._snapshot(mark, choices, step, self.outcome.seconds)
        for fold, value in zip(self.folds, [c.weights for c in choices] if self.outcome.kept else start):
            fold.set_weights(value)
        self.post = self.net if self.outcome.kept else self.start
        return self.outcome

    def _choice(self, k: int, step: int, blocks: np.ndarray) -> _Choice:
        """Fold ``k``'s checkpoint now, at ``step``, the held-out losses of every block ``blocks``."""
        return _Choice(float(blocks[self.block_folds != k].mean()), step, self.folds[k].get_weights())

    def step(self, opt):
        """One step of ``opt`` on a crop drawn by the adapter's stream: each fold's network on the loss of the
        pixels it trains on, their mean the loss (a backend tensor)."""
        crop = self.crops[int(self.rng.integers(len(self.crops)))]
        loss = sum(n2n_loss(_blend(net, crop.window)["default"], crop.target, crop.train[k])
                   for k, net in enumerate(self.folds)) / FOLDS
        descend(self.net.trainable_weights, opt, loss)
        return loss

    def _snapshot(self, mark: float, choices: list, step: int, seconds: float) -> None:
        outcome = self._decide(choices, step, seconds)
        chosen = [c.weights for c in choices]
        self.snapshots[mark] = (outcome, chosen if outcome.kept else None, chosen if any(outcome.best_steps) else None)

    def apply_weights(self, weights) -> keras.Model:
        """A copy of the post-correction with ``weights`` (a snapshot's: each fold network's), to apply
        (:func:`correct`)."""
        net = build_post(self.settings.seed)
        for fold, value in zip(fold_networks(net), weights, strict=True):
            fold.set_weights(value)
        return net

    def _decide(self, choices: list, steps: int, seconds: float) -> Outcome:
        """The guard's decision on the folds' chosen checkpoints ``choices``: each held-out block's error at all the
        samples, estimated from the halves (:meth:`_changes`), under the network that never saw it at a step
        chosen without it, against the model's output."""
        s = self.settings
        steps_chosen = tuple(c.step for c in choices)
        model = self.model_risk
        diff = (self._changes(fold_networks(self.apply_weights([c.weights for c in choices]))) if any(steps_chosen)
                else np.zeros_like(model))
        se = float(diff.std(ddof=1) / np.sqrt(diff.size))
        z = float(-diff.mean() / se) if se > 0 else (float("inf") if diff.mean() < 0 else 0.0)
        kept = any(steps_chosen) and z >= s.confidence
        if not any(steps_chosen):
            reason = "no checkpoint did better on the held-out blocks than the model's own output"
        elif s.confidence < 0:  # the user's call against a pessimistic estimate (AdaptSettings)
            side = "at or above" if kept else "below"
            reason = f"its estimate is {side} the {s.confidence:g} standard errors asked for"
        elif kept:
            reason = f"its estimated gain clears {s.confidence:g} standard errors"
        else:
            reason = f"its estimated gain is within {s.confidence:g} standard errors of none"
        return Outcome(bool(kept), steps, seconds, float(model.mean()), float((model + diff).mean()), steps_chosen,
                       z, reason)


def descend(params: list, opt, loss) -> None:
    """One step of the built optimizer ``opt`` on ``params`` (Keras variables on torch) down ``loss``'s gradient."""
    import torch

    for p in params:
        p.value.grad = None
    loss.backward()
    with torch.no_grad():
        opt.apply([p.value.grad for p in params], params)


class Corrected:
    """A denoiser (``kpcn_keras.denoise.Denoiser``) followed by a post-correction ``post``, called as the denoiser
    is (frame layers -> ``default``, ``diffuse``, ``specular``); what else a denoiser has (its ``run``, ``record``,
    ``settings``, ``precision``, ``warm_up``...) is the denoiser's."""

    def __init__(self, denoiser, post: keras.Model):
        self.denoiser, self.post = denoiser, post

    def __getattr__(self, name):
        return getattr(self.denoiser, name)

    def __call__(self, aovs: dict, slope=None) -> dict:
        return correct(self.post, self.denoiser(aovs, slope=slope), aovs, self.denoiser.tile)

    def prepare(self, aovs: dict):
        raise KpcnError(f"{self.denoiser.run.dir}: a frame prepared for λ maps skips the post-correction of an "
                        "adapted model; denoise it whole")


__all__ = ["CUSTOM_OBJECTS", "FOLDS", "GUIDE_CHANNELS", "HELD_OUT_EVERY", "MARGIN", "RADII", "Adapter", "Corrected",
           "LogMeanSoftmax", "Outcome", "build_post", "combine", "correct", "descend", "fold_networks", "n2n_loss"]
