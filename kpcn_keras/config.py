"""The configuration dataclasses of training and of the networks, and the presets (no keras, no torch).

This module imports nothing else of ``kpcn_keras`` (only ``prep`` and the standard library): every other
module may import it. The studies' configurations are in :mod:`kpcn_keras.studies.config`.

Each default is written once, here, with the bound of its value (``prep.bounds``: checked by the dataclass,
stated by ``--help``); the command line fills these from the options a user gave and never retypes a
default or a bound. Importing this module is cheap, so ``kpcn --help`` and the data stages stay light.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from prep.auxiliary import RAW, TRAINED
from prep.bounds import PATCH_COUNT, SEED, Bound, bounded, check_fields, is_integer
from prep.errors import KpcnError, OptionError
from prep.features import BRANCHES
from prep.inputs import FULL, InputSet
from prep.render.frame import FRAME_SIDE
from prep.shards.config import shard_set_dir, without_defaults

ARCHS = ("kpcn", "kpal", "dpcn", "unet")
DEFAULT_TILE = 256  # pixels per side of an inference tile: bounds memory at any resolution
TILE = Bound(1, FRAME_SIDE.high)
DEFAULT_SLOPES = (1.0, 2.0, 4.0, 8.0)  # the λ sweep of ``kpcn figures``
# The arithmetic of a network's trunk at inference (kpcn_keras/precision.py): "auto" is bfloat16 where the CPU
# multiplies it natively, float32 elsewhere
PRECISIONS = ("auto", "float32", "bfloat16")
DEFAULT_PRECISION = "auto"
# What runs the networks at inference: torch through Keras, or onnxruntime on their ONNX graphs (the optional extra
# "onnx", kpcn_keras/onnx_runtime.py); torch stays the default: it was the faster on this CPU (reports/onnx_speed.md)
RUNTIMES = ("torch", "onnx")
DEFAULT_RUNTIME = "torch"
# A self-ensemble (kpcn_keras/denoise.py, --ensemble N) denoises the frame moved by the first N of the square's 8
# symmetries and keeps each pixel's median: N times the time, for a few per cent of relMSE
# (docs/results/14-self-ensemble.md)
ENSEMBLE = Bound(1, 8)
DEFAULT_ENSEMBLE = 1
# A model's quality modes, as OIDN's: one network set each (``Run.for_quality``). A run folder's own networks are
# its DEFAULT_QUALITY mode; another mode lives in ``<model>/quality/<mode>/``, a run folder of its own (``kpcn ship
# --mode``). ``--quality`` and ``kpcn.denoise(..., quality=...)`` pick one (``settings.InferenceSettings``)
QUALITY_MODES = ("fast", "balanced", "high")
DEFAULT_QUALITY = "balanced"
# The training preset (PRESETS) each mode's networks are trained from (make modes; balanced is make model's):
# fast a quarter of balanced's convolution work a pixel and 9x9 kernels; high balanced's own networks, trained on
# from the shipped ones (QUALITY_INIT) with the Cycles world. The U-Net trunk (preset unet), which sees four times
# as far, lost to them trained from nothing on the scenes this machine renders (docs/results/28, 29): it is the
# preset for high where hundreds of scenes and a GPU are (docs/training.md §7)
QUALITY_PRESETS = {"fast": "fast", "balanced": "cpu", "high": "cpu"}
# The modes whose networks start from another mode's shipped ones (make modes: --init models/<model>), as a
# fine-tune: they are balanced's architecture, and balanced's networks were trained on all of make model's renders
QUALITY_INIT = {"high": "balanced"}
# The modes whose networks' frame is mixed with OIDN's (kpcn_keras.oidn_mix; make modes fits the weight on
# MIX_FRAMES with kpcn mix-oidn): high, whose time may be OIDN's as Blender runs it and kpcn's networks' on top
QUALITY_OIDN_MIX = ("high",)
# The auxiliaries (prep.auxiliary.TRAINED) each mode's networks are trained and served on: raw for all three.
# OIDN's prefilter of the albedo, normal and depth costs more at 1920x1080 than OIDN's whole fast mode
# (reports/mode_costs-architectures.json), and inside high's mix it gained little over the raw networks for it
# (docs/results/29)
QUALITY_AUXILIARIES = {"fast": "raw", "balanced": "raw", "high": "raw"}
# The model ``kpcn denoise`` uses without --run: a run folder shipped in the repository's ``models/``
# (``Run.ship``, ``make model``), found beside the package rather than in the working directory, so that it
# serves from any folder; the environment variable MODEL_ENV names another folder instead (a model of one's
# own). The Makefile reads DEFAULT_MODEL from this line (``make model`` ships to models/<it>).
MODELS_DIR = Path(__file__).resolve().parent.parent / "models"
DEFAULT_MODEL = "default"
MODEL_ENV = "KPCN_MODEL"
# The flags of the options a message spells in a command it suggests (a run's hint, ``Run._training_commands``),
# by command and option: the parser declares them under these (tests/test_cli.py holds the two equal), and a
# library module spells them from here rather than reaching up to the parser
HINT_FLAGS = {"shards": {"set_name": "--set", "out_root": "--out", "inputs": "--inputs",
                         "auxiliaries": "--auxiliaries"},
              "train": {"set_name": "--set", "shards_root": "--shards", "run": "--run-dir", "inputs": "--inputs",
                        "auxiliaries": "--auxiliaries"}}
SHIPPED_MAX_BYTES = 25 * 2**20  # a shipped model lives in git: refused above this
# the shipped model's goal: a 1920x1080 frame within 3x OIDN's time on the same CPU; its card times
# the two side by side (kpcn_keras/card.py), the best of SPEED_REPEATS alternating calls after a warm-up
SPEED_FRAME, SPEED_GOAL, SPEED_REPEATS = (1920, 1080), 3.0, 2
COLOUR_CHANNELS = 3  # features[..., :3] is the noisy branch colour (data contract)
BRANCH_CHANNELS = len(BRANCHES)  # one-hot branch indicator of a shared network


# The bounds of the options (prep.bounds). A kernel of k x k taps is k**2 logits a pixel: 41 (1681 taps,
# twice the papers' 21 a side) keeps a training batch's head within a few hundred MB; 1 would be the
# identity, no filter. The trunk's width, depth and convolution size likewise stay well past the papers'
# (100 wide, 28 layers, 5x5).
KERNEL_SIZE = Bound(3, 41, odd=True)
COMPOSITOR_KERNEL_SIZE = Bound(1, 41, odd=True)  # coarse pixels; 1 upsamples by replication
CONV_SIZE = Bound(1, 15, odd=True)
WIDTH = Bound(1, 1024)
DEPTH = Bound(1, 100)
IN_CHANNELS = Bound(COLOUR_CHANNELS, 1024)  # channels 0..2 are the colour
LEVELS = Bound(2, 8)  # one level is the denoiser alone; 8 halves a frame 7 times
# a U-Net's resolutions: 6 pools 5 times, a 32-pixel alignment and a receptive field past a 65-pixel patch
UNET_LEVELS = Bound(2, 6)
# the specialisation module's 1x1 convolutions after λ joins (models.py): 0 puts λ at the input
SLOPE_MODULE = Bound(0, 8)
SLOPE_MIXTURE = Bound(0, 8)  # kernels a λ mixture chooses among; 0 is none, 1 is refused (nothing to choose)
WIDTH_GROWTH = Bound(1.0, 4.0, integer=False)  # filters per level down: constant up to quadrupling
# a trunk convolution's dilation: its taps that many pixels apart; 32 spaces a 3x3's outer taps a 65-pixel patch apart
DILATION = Bound(1, 32)
STEPS = Bound(1, 10_000_000)  # ten days at 12 steps/s
BATCH_SIZE = Bound(1, 4096)
VAL_BATCHES = Bound(1, 10_000)
LEARNING_RATE = Bound(0.0, 1.0, integer=False, low_open=True)
FRACTION = Bound(0.0, 1.0, integer=False, low_open=True)  # (0, 1]: a decay rate, a round's decay, a budget share
SHARE = Bound(0.0, 1.0, integer=False)  # [0, 1]: a mix weight
CLIPNORM = Bound(0.0, 1e6, integer=False, low_open=True)
SLOPE = Bound(1.0, 1000.0, integer=False)  # λ of the asymmetric loss: 1 is SMAPE itself
GAMMA = Bound(0.0, 100.0, integer=False)
SCALE_SUPERVISION = Bound(0.0, 100.0, integer=False)  # weight of each coarser level's loss term; 0 is off
DROPOUT = Bound(0.0, 1.0, integer=False, high_open=True)
ROUNDS = Bound(1, 100)
# τ of the reference weighting (kpcn_keras.losses): the reference relSE at which a pixel weighs 1/2; 0 is off.
# 100 is 2000 times the relSE a converged pixel has (prep.convergence.CONVERGED_RELSE): every weight ~1.
REFERENCE_TAU = Bound(0.0, 100.0, integer=False)
UNWEIGHTED_TAU = 0.0  # reference_tau of an unweighted loss: what a run record without the key was trained with
FIREFLIES = Bound(0.0, 100.0, integer=False)  # synthetic fireflies a training patch, on average
NO_FIREFLIES = 0.0  # fireflies of a run that adds none: what a run record without the key was trained with
PATIENCE = Bound(0, 100_000)  # epochs without a better validation loss before a phase stops
TRAIN_EVERY_STEP = 0  # patience of a run that trains every step: what a run record without the key did
NO_ALBEDO_NETWORK = 0  # albedo_steps of a run without one: what a run record without the key trained
ALBEDO_NETWORK = "albedo"  # the phase, component and model name of a run's albedo network
PIXEL = Bound(0, FRAME_SIDE.high - 1)  # y or x of a pixel (figures --pixel)
PORT = Bound(0, 65535)  # kpcn view --port; 0 takes a free one
VIEW_HOST, VIEW_PORT = "127.0.0.1", 8765  # kpcn view's page is for the person at this machine: nothing else reaches it
VIEW_ADAPT_SECONDS = 30.0  # the seconds kpcn view's adapt field starts at (kpcn denoise --adapt has no default)


def check_kernel_size(k) -> int:
    """Return ``k`` as an int if it is a positive odd integer, else raise ValueError naming the value."""
    if not is_integer(k) or k < 1 or k % 2 == 0:  # ints and numpy integers; not bools, floats or strings
        raise ValueError(f"kernel size must be a positive odd integer, received {k!r}")
    return int(k)


# arch "unet": what its fields are when not given (ModelConfig); the "unet" preset trains these, 32/48/72/96
# filters over four levels, with one convolution per level each way
UNET_DEFAULTS = {"levels": 4, "width_growth": 1.5}
UNET_CAP_FACTOR = 3  # width_cap not given: three times the first level's width
UNET_FIELDS = ("levels", "width_growth", "width_cap")


def _strict_from_dict(cls, d: dict, option: str):
    """``cls(**d)``, but an unknown key is an OptionError naming ``option`` (a typo would pass silently)."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise OptionError(option, f"has unknown {cls.__name__} keys {unknown}; known keys are {sorted(names)}")
    return cls(**d)


# the fields a run record of an earlier kpcn lacks, with the value it was trained with: left out of
# ModelConfig.to_record at that value, so those runs keep their identity
_MODEL_ADDED = {"slope_module": 0, "slope_mixture": 0, "dilations": None}
DILATED_ARCHS = ("kpcn", "dpcn")  # the archs whose trunk is one stack of convolutions, one dilation each


@dataclass
class ModelConfig:
    """Architecture of one branch network. ``batchnorm=None`` means: True for kpal, False otherwise.

    ``depth`` counts trunk convolutions for kpcn/dpcn and residual blocks for kpal. ``dropout`` is the drop
    rate (the report's keep probability 0.7 is ``dropout=0.3``); it is applied after every trunk
    convolution when > 0. ``kernel_size`` is the predicted kernel's side (odd; paper 21) and is ignored by
    dpcn.

    Fields of arch "unet" alone (None for every other arch, and then left out of :meth:`to_dict`, so the
    configurations and run records of the other archs are the ones written before "unet" existed; setting one
    with another arch is refused): ``levels`` resolutions (the encoder pools ``levels - 1`` times), the width
    at level l ``min(width_cap, round(width * width_growth**l))``. None with arch "unet" takes the defaults
    of :data:`UNET_DEFAULTS`, ``width_cap`` ``UNET_CAP_FACTOR * width``; ``depth`` is the convolutions per
    level each way (models.py).

    ``slope_module`` > 0 (with ``slope_channel``): λ bypasses the trunk and joins it after, through that many
    1x1 convolutions before the kernel head (the loss-specialisation module, models.py), so a new λ map
    re-runs only those; left out of :meth:`to_dict` when 0. ``slope_mixture`` J >= 2 (with ``slope_module``):
    the trunk predicts J kernels instead of one, and the module predicts, from the trunk's activations and λ,
    each pixel's mixture of them, so a new map re-runs the module and a J-way blend of filtered colours, not
    the kernels (models.py); left out of :meth:`to_dict` when 0.

    ``dilations`` (arch kpcn or dpcn): the dilation of each of the ``depth`` trunk convolutions, whose taps are
    then that many pixels apart, so the trunk sees further at the same cost (the ``dilated`` preset); None, the
    default, and all ones are the plain stack, left out of :meth:`to_dict`.
    """

    arch: str = "kpcn"
    in_channels: int = bounded(27, IN_CHANNELS)
    width: int = bounded(32, WIDTH)
    depth: int = bounded(7, DEPTH)
    conv_size: int = bounded(3, CONV_SIZE)
    kernel_size: int = bounded(13, KERNEL_SIZE)
    dropout: float = bounded(0.0, DROPOUT)
    batchnorm: bool | None = None
    branch_channels: bool = False
    slope_channel: bool = False
    levels: int | None = bounded(None, UNET_LEVELS)
    width_growth: float | None = bounded(None, WIDTH_GROWTH)
    width_cap: int | None = bounded(None, WIDTH)
    slope_module: int = bounded(_MODEL_ADDED["slope_module"], SLOPE_MODULE)
    slope_mixture: int = bounded(_MODEL_ADDED["slope_mixture"], SLOPE_MIXTURE)
    dilations: tuple[int, ...] | None = bounded(_MODEL_ADDED["dilations"], DILATION)

    def __post_init__(self):
        if self.arch not in ARCHS:
            raise OptionError("arch", f"must be one of {ARCHS}, received {self.arch!r}")
        check_fields(self)
        if self.arch == "unet":
            for name, default in UNET_DEFAULTS.items():
                if getattr(self, name) is None:
                    setattr(self, name, default)
            if self.width_cap is None:
                self.width_cap = UNET_CAP_FACTOR * self.width
            if self.width_cap < self.width:
                raise OptionError("width_cap", f"must be at least the width {self.width} (the first level's), "
                                  f"received {self.width_cap}")
        else:
            for name in UNET_FIELDS:
                if getattr(self, name) is not None:
                    raise OptionError(name, f"is a setting of arch unet alone, received {getattr(self, name)!r} "
                                      f"with arch {self.arch}")
        if self.batchnorm is None:
            self.batchnorm = self.arch == "kpal"
        elif not isinstance(self.batchnorm, bool):
            raise OptionError("batchnorm", f"must be a bool or None, received {self.batchnorm!r}")
        for flag in ("branch_channels", "slope_channel"):
            if not isinstance(getattr(self, flag), bool):
                raise OptionError(flag, f"must be a bool, received {getattr(self, flag)!r}")
        if self.slope_module and not self.slope_channel:
            raise OptionError("slope_module", f"joins λ to the network ({self.slope_module} layers); it needs "
                              "--slope-input (λ as an input, --loss asymmetric)")
        if self.slope_module and self.arch == "dpcn":
            raise OptionError("slope_module", "specialises predicted kernels; arch dpcn predicts colour directly")
        if self.slope_mixture and not self.slope_module:
            raise OptionError("slope_mixture", f"mixes {self.slope_mixture} kernels by λ through the specialisation "
                              "module; it needs --slope-module")
        if self.slope_mixture == 1:
            raise OptionError("slope_mixture", "must be at least 2 kernels to mix (or 0 for none), received 1")
        if self.dilations is not None:
            if not isinstance(self.dilations, tuple):
                raise OptionError("dilations", f"must be a list of dilations, one per convolution, received "
                                  f"{self.dilations!r}")
            if self.arch not in DILATED_ARCHS:
                stacks = ", ".join(DILATED_ARCHS)
                raise OptionError("dilations", f"dilate the convolutions of a plain stack ({stacks}), received "
                                  f"{list(self.dilations)} with arch {self.arch}")
            if len(self.dilations) != self.depth:
                raise OptionError("dilations", f"needs one dilation per trunk convolution, depth {self.depth}; "
                                  f"received {len(self.dilations)}: {list(self.dilations)}")
            if set(self.dilations) == {1}:
                self.dilations = None  # the plain stack: one network, one record

    def trunk_dilations(self) -> tuple[int, ...]:
        """The dilation of each trunk convolution of a kpcn or dpcn (ValueError for another arch)."""
        if self.arch not in DILATED_ARCHS:
            raise ValueError(f"a {self.arch} network's trunk is not one stack of convolutions")
        return self.dilations or (1,) * self.depth

    @property
    def input_channels(self) -> int:
        """Channels of the network input: the features, then the conditioning channels."""
        return self.in_channels + BRANCH_CHANNELS * self.branch_channels + self.slope_channel

    def to_dict(self) -> dict:
        """Plain JSON-able dict; ``batchnorm`` is resolved (never None); the unet fields only for a unet."""
        d = self.to_record()
        if self.arch != "unet":
            for name in UNET_FIELDS:
                del d[name]
        return d

    def to_record(self) -> dict:
        """The dict a run record's ``train.model`` holds: every field but those added since the first runs that
        hold their defaults (:data:`_MODEL_ADDED`), so that the records of networks without them stay as
        written and those runs keep their identity (the unet fields have been written, as null, since unet)."""
        d = dataclasses.asdict(self)
        for name, default in _MODEL_ADDED.items():
            if d[name] == default:
                del d[name]
        if "dilations" in d:
            d["dilations"] = list(d["dilations"])  # as JSON reads it back
        return d

    def unet_widths(self) -> tuple[int, ...]:
        """The filters of each level of a unet, finest first (ValueError for another arch)."""
        if self.arch != "unet":
            raise ValueError(f"a {self.arch} network has no levels")
        return tuple(min(self.width_cap, round(self.width * self.width_growth**level)) for level in range(self.levels))

    @classmethod
    def from_dict(cls, d: dict) -> ModelConfig:
        """Inverse of ``to_dict``; unknown keys are an error (a typo would otherwise be silently ignored)."""
        return _strict_from_dict(cls, d, "model")


COMPOSITOR_KINDS = ("alpha", "kernel")
# the pyramid's 2x downsampling (kpcn_keras/multiscale.py): 2x2 average pooling, or the bicubic (Keys, a = -0.5)
# filter of the report's §2.2.1 and Choi et al.'s pyramid (§3.1.1)
DOWNSAMPLES = ("average", "bicubic")
# the fields a run record of an earlier kpcn lacks, with the value it was trained with: left out of
# CompositorConfig.to_dict at that value, so those runs keep their identity
_COMPOSITOR_ADDED = {"downsample": "average", "scale_supervision": 0.0}


@dataclass
class CompositorConfig:
    """The multiscale module: compositor ``kind`` ("alpha": Vogels' scale compositor, "kernel": the
    report's kernel-predicting one, §3.1.1), pyramid ``levels`` (>= 2), the compositor network (``depth``
    conv layers in all, the last the 1x1 head(s); ``width`` filters of ``conv_size``), the kernel
    compositor's upsampling kernel side ``kernel_size`` (odd, in coarse pixels; the report's is 21) and the
    α regulariser weight ``gamma`` (>= 0).

    ``downsample`` is how the pyramid halves an image (:data:`DOWNSAMPLES`; the blend's own D stays the 2x2
    average, docs/method.md §7). ``scale_supervision`` w > 0 adds to the compositor phase's loss, for every
    level between the finest and the coarsest, w times the training loss of that level's composite output
    against the reference downsampled the same way (Choi et al.'s supervision of every scale, report §3.1.1);
    0, the default, is off. A record without these two fields was trained with the defaults, and
    :meth:`to_dict` leaves them out at their defaults, so those runs keep their identity."""

    kind: str = "alpha"
    levels: int = bounded(3, LEVELS)
    width: int = bounded(32, WIDTH)
    depth: int = bounded(6, DEPTH)
    conv_size: int = bounded(3, CONV_SIZE)
    kernel_size: int = bounded(5, COMPOSITOR_KERNEL_SIZE)
    gamma: float = bounded(0.01, GAMMA)
    downsample: str = _COMPOSITOR_ADDED["downsample"]
    scale_supervision: float = bounded(_COMPOSITOR_ADDED["scale_supervision"], SCALE_SUPERVISION)

    def __post_init__(self):
        if self.kind not in COMPOSITOR_KINDS:
            # the option a user types is --compositor KIND
            raise OptionError("compositor", f"must be one of {COMPOSITOR_KINDS}, received {self.kind!r}")
        if self.downsample not in DOWNSAMPLES:
            raise OptionError("downsample", f"must be one of {DOWNSAMPLES}, received {self.downsample!r}")
        check_fields(self)
        if self.scale_supervision and self.levels < 3:
            raise OptionError("scale_supervision", f"supervises the levels between the finest and the coarsest, "
                              f"and {self.levels} levels have none: it needs levels >= 3")

    def to_dict(self) -> dict:
        """Plain JSON-able dict, without the fields added since the first runs where they hold their defaults."""
        d = dataclasses.asdict(self)
        for name, default in _COMPOSITOR_ADDED.items():
            if d[name] == default:
                del d[name]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> CompositorConfig:
        """Inverse of ``to_dict``; unknown keys are an error (a typo would otherwise be silently ignored)."""
        return _strict_from_dict(cls, d, "compositor")


# "cpu" (the TrainConfig defaults) trains a useful model on a 2-core CPU in minutes; "unet" trains as cpu does, at
# a lower learning rate, with a 4-level U-Net trunk (models.py), whose 59-pixel field sees blotches cpu's 15 cannot.
# The paper presets are for a GPU: "kpcn-paper" is Bako et al. 2017's vanilla network (9 layers: 8 hidden 5x5
# convolutions of 100 filters and the kernel head; 21x21 kernels), "kpal-paper" the report's 28-layer residual
# network (§2.2: batch norm, keep probability 0.7). Both train as the report did (§2.3.2, §3.5.2): batch 12, lr
# 1e-4 with exponential decay, 60000 steps per branch, then 10000 steps of joint fine-tuning at 1e-6.
_PAPER_TRAINING = {
    "batch_size": 12,
    "steps": 60000,
    "steps_per_epoch": 1000,
    "learning_rate": 1e-4,
    "decay_steps": 60000,
    "decay_rate": 0.1,
    "joint_steps": 10000,
    "joint_learning_rate": 1e-6,
}
PRESETS = {
    "cpu": {},
    "kpcn-paper": {
        "model": {"arch": "kpcn", "width": 100, "depth": 8, "conv_size": 5, "kernel_size": 21},
        **_PAPER_TRAINING,
    },
    # cpu's training with a 4-level U-Net trunk (UNET_DEFAULTS: 32/48/72/96 filters) and cpu's 13x13 kernels, at
    # a third of its learning rate: at cpu's 0.001 a specular network's kernels saturated in its first epoch and
    # it never learned (docs/results/10-quality-levers.md §10d; train.frozen now stops such a phase); at 0.0003
    # it learned
    "unet": {"model": {"arch": "unet", "depth": 1}, "learning_rate": 3e-4},
    # cpu with its 7 convolutions dilated 1, 2, 4, 8, 4, 2, 1: a 45-pixel trunk field (every offset within it
    # reached, no gridding gaps) at cpu's cost a step, where the unet's steps cost twice as much
    "dilated": {"model": {"dilations": [1, 2, 4, 8, 4, 2, 1]}},
    # the fast quality mode's: cpu's stack at half the width and 5 convolutions (about 15 000 multiply-adds a pixel
    # against 68 000) with 9x9 kernels (81 taps to apply against 169), for frames that must come back quickly
    "fast": {"model": {"width": 16, "depth": 5, "kernel_size": 9}},
    "kpal-paper": {
        "model": {"arch": "kpal", "width": 100, "depth": 13, "conv_size": 3, "kernel_size": 21, "dropout": 0.3},
        **_PAPER_TRAINING,
    },
}

# Fields that say where the data is, not what is trained: a run is the same run wherever it is read from. A run
# started from another's networks (``init``) records their checksums, which are what it was trained from.
LOCATION_FIELDS = ("set_name", "shards_root", "init")
# What a network's input carries besides the features: set from the training options, never by hand.
_CONDITIONING = ("branch_channels", "slope_channel")


@dataclass(frozen=True)
class Phase:
    """One training phase of a run: what it trains and how long.

    ``name`` names its files; ``network`` is what it trains (``diffuse``, ``specular``, ``shared``, ``joint``,
    ``compositor``; default: the name). A phase of the resample loop (``kpcn_keras.resample``) ``continues``
    the finished phase of that name (its weights and its optimizer, learning-rate schedule included) on
    the shard rounds 0..``rounds``; every other phase builds a new model and reads round 0.
    """

    name: str
    steps: int
    learning_rate: float
    first_epoch: int  # of the run's one epoch numbering (the CSV log's)
    epoch_steps: int
    network: str = ""
    rounds: int = 0
    continues: str | None = None

    @property
    def component(self) -> str:
        return self.network or self.name

    @property
    def epochs(self) -> int:
        """Epochs of ``epoch_steps``, the last one shorter where ``steps`` is not a multiple: a phase trains
        exactly its ``steps`` (and its learning-rate schedule spans those)."""
        return math.ceil(self.steps / self.epoch_steps)

    def epoch_length(self, i: int) -> int:
        """Steps of the phase's epoch ``i`` (0-based, within the phase)."""
        return min(self.epoch_steps, self.steps - i * self.epoch_steps)

    @property
    def trains_on_final_colour(self) -> bool:
        """Whether the phase's loss is on the final colour (joint, compositor, and the albedo network's, whose
        albedo it is multiplied into), not on one branch's reference."""
        return self.component in ("joint", "compositor", ALBEDO_NETWORK)


@dataclass
class TrainConfig:
    """Configuration of ``kpcn train``; every field is saved in the run's config.json.

    The defaults are the "cpu" preset: a vanilla KPCN of 8 layers (7 convolutions of 32 3x3 filters and
    the kernel head; 13x13 kernels; the ModelConfig defaults), 4000 steps of batch 8 per branch,
    augmentation on. ``steps``, ``learning_rate``, ``decay_steps`` and ``decay_rate`` are per branch phase;
    the joint and compositor phases have their own steps and learning rates and share the decay.
    ``model`` and ``compositor`` (None: no multiscale) may be given as dicts of their dataclass's fields
    (a preset, the options, a run record's JSON: ``{"kind": "alpha"}`` at least for a compositor) and
    are held as the :class:`ModelConfig` and :class:`CompositorConfig` they describe, checked once here;
    :meth:`to_dict` writes them back as dicts. With
    ``slope_input`` the network gets λ as an input channel and learns the asymmetric loss for every λ in
    ``slope_range`` (drawn per patch, log-uniform); ``slope`` is then the λ of validation. The run folder
    is not part of the configuration (:class:`kpcn_keras.run.Run` owns that), so a renamed run resumes.

    ``reference_tau`` τ weighs each pixel of the branch phases' losses by 1 / (1 + (relSE / τ)^2), relSE the
    reference's relative standard error there (the shards' ``ref_relse``; ``kpcn_keras.losses``); 0, the
    default, does not weigh (it has not won yet: docs/results/10-quality-levers.md §10a). The joint and
    compositor phases are never weighted (docs/training.md §2). A record written before the weighting existed has no
    ``reference_tau`` and reads as 0 (:meth:`from_record`), and a run of τ = 0 writes none (:meth:`to_dict`),
    so those runs keep their identity.

    ``init`` names a run or a shipped model (``models/default``) whose finished networks of the same input set
    the branch phases start from instead of a seeded initialisation: fine-tuning a model on one's own renders
    (``kpcn_keras.train.init_networks`` checks that they fit; the run's record keeps their checksums). Where
    they are read from is not what is trained (:data:`LOCATION_FIELDS`); None, the default, is written nowhere.

    ``fireflies`` F > 0 adds to each training patch of the branch phases a Poisson(F) number of synthetic
    fireflies, isolated spikes the target does not have (``kpcn_keras.fireflies``: why, and what a spike is);
    the default is 1, measured from scratch at make train's budget (docs/results/18-synthetic-fireflies.md).
    0 adds none and, like τ = 0, is written nowhere, so the runs from before the spikes existed keep their
    identity (a record without the key reads as 0: :meth:`from_record`).

    ``patience`` P > 0 stops a phase once P epochs in a row have not lowered its validation loss (the held-out
    scenes' patches) below its best, and makes the best epoch's weights the phase's model: a run trains as long
    as held-out error keeps falling, ``steps`` (and with it the learning-rate schedule) the most it may take.
    0, the default, trains every step; like τ = 0 it is written nowhere, so the runs from before keep their
    identity. It needs held-out scenes (a shard set cut with ``--val-fraction`` 0 has none).

    ``albedo_steps`` N > 0 adds the ``albedo`` phase after the branch phases: a copy of the finished diffuse network
    trained N steps (at ``albedo_learning_rate``, on the same decay) to filter the albedo that the diffuse irradiance is
    multiplied back by, judged on the final colour of the reference's irradiance times its albedo
    (docs/method.md §1; ``models.build_albedo_training_model``); the denoiser then uses it instead of
    ``prep.albedo``'s prefilter. It needs both branches and a diffuse network of its own without λ (not
    ``shared``, not ``slope_input``); a no-split run, whose one network filters the total colour, passes it over
    as it does ``joint_steps``. 0, the default, adds none and, like τ = 0, is written nowhere.

    ``inputs`` is the input set (``prep.inputs``) the run is trained for, from the shard set cut for it
    (:attr:`set_dir`). A no-split run's specular input is 0 (``prep.inputs.restrict``), so it trains the
    diffuse network alone (:attr:`denoised_branches`): no specular phase, and no joint phase (with one
    branch there is nothing to tune together; ``joint_steps`` of a preset is passed over, and so is
    ``albedo_steps``: no irradiance is multiplied by an albedo); one shared
    network (``shared``) or a compositor, both made for two branches, is refused. A full configuration's
    dict is the one from before input sets existed (``prep.shards.config.without_full_inputs``), so the
    runs and checkpoints written before keep their identity.

    ``auxiliaries`` (``prep.auxiliary.TRAINED``) is how the albedo, normal and depth the networks see are
    prefiltered: the run trains on the shard set cut so (:attr:`set_dir`; ``kpcn train`` checks its manifest says
    so) and is served its frames so (``kpcn_keras.denoise``). ``raw``, the default, is written nowhere, so the
    runs from before keep their identity (a record without the key reads as raw).
    """

    set_name: str = "default"
    shards_root: str = "shards"
    preset: str = "cpu"
    model: ModelConfig = field(default_factory=ModelConfig)
    branches: tuple[str, ...] = bounded(BRANCHES, distinct=True)
    shared: bool = False
    # as many steps as make train's 30 minutes on a 2-core CPU hold: steps beat every lever
    # (docs/results/10-quality-levers.md §10f)
    steps: int = bounded(4000, STEPS)
    steps_per_epoch: int = bounded(50, STEPS)
    batch_size: int = bounded(8, BATCH_SIZE)
    learning_rate: float = bounded(1e-3, LEARNING_RATE)
    decay_steps: int = bounded(4000, STEPS)
    decay_rate: float = bounded(0.3, FRACTION)
    clipnorm: float = bounded(1.0, CLIPNORM)
    loss: str = "smape"
    slope: float = bounded(2.0, SLOPE)
    slope_input: bool = False
    slope_range: tuple[float, float] = bounded((1.0, 8.0), SLOPE)
    augment: bool = True
    reference_tau: float = bounded(UNWEIGHTED_TAU, REFERENCE_TAU)
    fireflies: float = bounded(1.0, FIREFLIES)
    joint_steps: int = bounded(0, Bound(0, STEPS.high))
    joint_learning_rate: float = bounded(1e-4, LEARNING_RATE)
    albedo_steps: int = bounded(NO_ALBEDO_NETWORK, Bound(0, STEPS.high))
    # a rate of its own: at make train's the albedo phase stalled (docs/results/20-albedo-network.md; maybe only
    # its starting plateau, docs/results/21-quality-report-shipped-model.md); the shipped albedo network and the
    # scratch ones were trained at this one
    albedo_learning_rate: float = bounded(3e-4, LEARNING_RATE)
    compositor: CompositorConfig | None = None
    compositor_steps: int = bounded(600, STEPS)
    compositor_learning_rate: float = bounded(1e-3, LEARNING_RATE)
    val_batches: int = bounded(8, VAL_BATCHES)
    patience: int = bounded(TRAIN_EVERY_STEP, PATIENCE)
    seed: int = bounded(0, SEED)
    inputs: str = FULL.name
    init: str | None = None
    auxiliaries: str = RAW

    def __post_init__(self):
        self.branches = tuple(self.branches)
        if self.auxiliaries not in TRAINED:  # pyoidn is checked where it runs (shards, denoise), not where it is read
            raise OptionError("auxiliaries", f"must be one of {', '.join(TRAINED)}, got {self.auxiliaries!r}")
        self.slope_range = tuple(self.slope_range)
        if not self.branches or any(b not in BRANCHES for b in self.branches):
            raise OptionError("branches", f"must be a non-empty subset of {','.join(BRANCHES)}, "
                              f"got {list(self.branches)}")
        if self.loss not in ("smape", "asymmetric"):
            raise OptionError("loss", f"must be 'smape' or 'asymmetric', got {self.loss!r}")
        check_fields(self)
        for name in ("shared", "slope_input", "augment"):
            if not isinstance(getattr(self, name), bool):
                raise OptionError(name, f"must be true or false, got {getattr(self, name)!r}")
        if self.init is not None and (not isinstance(self.init, str) or not self.init):
            raise OptionError("init", f"must be a run or model folder, got {self.init!r}")
        if len(self.slope_range) != 2 or not self.slope_range[0] < self.slope_range[1]:
            raise OptionError("slope_range", f"must be two numbers low < high, got {list(self.slope_range)}")
        if self.slope_input and self.loss != "asymmetric":
            raise OptionError("slope_input", "needs --loss asymmetric (λ is the asymmetric loss's slope)")
        whole = set(self.branches) == set(BRANCHES)
        if self.shared and not whole:
            raise OptionError("shared", f"trains one network for both branches; --branches {','.join(self.branches)} "
                              "leaves one out")
        for name, wanted in (("joint_steps", self.joint_steps > 0), ("compositor", self.compositor is not None),
                             ("albedo_steps", self.albedo_steps > 0)):
            if wanted and not whole:
                raise OptionError(name, f"trains on the final colour, which needs both branches; got --branches "
                                  f"{','.join(self.branches)}")
        if isinstance(self.compositor, dict):
            self.compositor = CompositorConfig.from_dict(self.compositor)
        if not self.input_set.split:
            one = f"a {self.inputs} run (--inputs {self.inputs}) has the diffuse branch alone, the total colour"
            if self.shared:
                raise OptionError("shared", f"trains one network for both branches; {one}")
            if self.compositor is not None:
                raise OptionError("compositor", f"composes the scales of both branches; {one}")
            if "diffuse" not in self.branches:
                raise OptionError("branches", f"{','.join(self.branches)} leaves out the diffuse branch; {one}")
        if self.albedo_steps and (self.shared or self.slope_input):
            raise OptionError("albedo_steps", "trains a copy of the diffuse network on the albedo, which needs a "
                              f"diffuse network of its own without a λ input; got --shared {self.shared}, "
                              f"--slope-input {self.slope_input}")
        given = self.model.to_dict() if isinstance(self.model, ModelConfig) else self.model
        user = {k: v for k, v in given.items() if k not in _CONDITIONING}
        self.model = ModelConfig.from_dict({**user, "branch_channels": self.shared, "slope_channel": self.slope_input})

    @classmethod
    def from_preset(cls, preset: str | None = None, **overrides) -> TrainConfig:
        """The preset's values (None: the default preset), then ``overrides`` (None values ignored;
        ``model`` and ``compositor`` keys merged)."""
        preset = cls.preset if preset is None else preset
        if preset not in PRESETS:
            raise OptionError("preset", f"must be one of {', '.join(PRESETS)}, got {preset!r}")
        values = json.loads(json.dumps(PRESETS[preset]))
        values["model"] = {**values.get("model", {}), **(overrides.pop("model", None) or {})}
        compositor = overrides.pop("compositor", None)
        if compositor:
            values["compositor"] = {**(values.get("compositor") or {}), **compositor}
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(preset=preset, **values)

    @classmethod
    def from_record(cls, train: dict) -> TrainConfig:
        """The configuration a run record's ``train`` holds (one without ``reference_tau`` was unweighted, one
        without ``patience`` trained every step, one without ``fireflies`` added none)."""
        return cls(**{"reference_tau": UNWEIGHTED_TAU, "patience": TRAIN_EVERY_STEP, "fireflies": NO_FIREFLIES,
                      "albedo_steps": NO_ALBEDO_NETWORK,
                      **train})

    @property
    def input_set(self) -> InputSet:
        return InputSet.named(self.inputs)

    def weights_reference(self, phase: Phase) -> bool:
        """Whether ``phase``'s loss is weighted by the reference's relSE: a branch phase, with τ > 0."""
        return self.reference_tau != UNWEIGHTED_TAU and not phase.trains_on_final_colour

    def supervises_scales(self, phase: Phase) -> bool:
        """Whether ``phase``'s loss adds the per-scale terms (``CompositorConfig.scale_supervision``): the
        compositor phase of a run that asks for them; its batches then carry the target as an input too."""
        return phase.component == "compositor" and bool(self.compositor and self.compositor.scale_supervision)

    @property
    def target_channels(self) -> int:
        """Channels of a final-colour batch's target (``kpcn_keras.data``): the reference, then for the
        asymmetric loss the noisy colour, and λ for a network with a slope channel."""
        asymmetric = self.loss == "asymmetric"
        return COLOUR_CHANNELS * (1 + asymmetric) + int(asymmetric and self.slope_input)

    @property
    def denoised_branches(self) -> tuple[str, ...]:
        """The branches the run's denoiser runs: both, or the diffuse alone for a no-split run (its input is
        the total colour; the specular input is 0, and so is the specular output)."""
        return BRANCHES if self.input_set.split else ("diffuse",)

    @property
    def set_dir(self) -> Path:
        return shard_set_dir(self.shards_root, self.set_name, self.inputs, self.auxiliaries)

    def phases(self) -> list[Phase]:
        """The run's phases in training order, each with its place in the run's epoch numbering."""
        branches = ("shared",) if self.shared else tuple(b for b in self.branches if b in self.denoised_branches)
        plan = [(b, self.steps, self.learning_rate) for b in branches]
        if self.albedo_steps and self.input_set.split:
            plan.append((ALBEDO_NETWORK, self.albedo_steps, self.albedo_learning_rate))
        if self.joint_steps and self.input_set.split:
            plan.append(("joint", self.joint_steps, self.joint_learning_rate))
        if self.compositor is not None:
            plan.append(("compositor", self.compositor_steps, self.compositor_learning_rate))
        phases, first = [], 0
        for name, steps, lr in plan:
            phase = Phase(name, steps, lr, first, min(self.steps_per_epoch, steps))
            phases.append(phase)
            first += phase.epochs
        return phases

    def to_dict(self) -> dict:
        d = without_defaults(dataclasses.asdict(self))  # inputs full, auxiliaries raw: as written before either
        d["model"] = self.model.to_record()  # asdict would write the fields its to_record leaves out
        if self.compositor is not None:
            d["compositor"] = self.compositor.to_dict()  # asdict would write the fields its to_dict leaves out
        if d["reference_tau"] == UNWEIGHTED_TAU:
            del d["reference_tau"]  # the record of an unweighted run, as written before weighting existed
        if d["fireflies"] == NO_FIREFLIES:
            del d["fireflies"]  # likewise: a run without synthetic fireflies, as written before they existed
        if d["albedo_steps"] == NO_ALBEDO_NETWORK:  # likewise: a run without one, as written before they existed
            del d["albedo_steps"], d["albedo_learning_rate"]
        if d["patience"] == TRAIN_EVERY_STEP:
            del d["patience"]  # likewise: a run of every step, as written before early stopping existed
        if d["init"] is None:
            del d["init"]  # likewise: a run from a seeded initialisation, as written before --init existed
        d["branches"] = list(self.branches)
        d["slope_range"] = list(self.slope_range)
        return d

    def identity(self) -> dict:
        """The fields that make two runs the same run (everything but where the data is read from)."""
        return {k: v for k, v in self.to_dict().items() if k not in LOCATION_FIELDS}

    @classmethod
    def recorded_identity(cls, train: dict) -> dict:
        """The identity of a recorded ``train`` (a run record's, a study plan's) as this kpcn writes it, so that a
        field added since, held at the value that means "as before", is the same run whether the record has it
        or not; the record as written where this kpcn cannot read it (a newer kpcn's: its extra fields are then
        the difference reported)."""
        try:
            return cls.from_record(train).identity()
        except (TypeError, KpcnError):
            return {k: v for k, v in train.items() if k not in LOCATION_FIELDS}


@dataclass
class ResampleConfig:
    """Configuration of ``kpcn resample`` (kpcn_keras/resample.py), the error-based resampling loop of seed
    report §3.3.2, continuing a finished run.

    ``rounds`` error rounds; in each, ``patches_per_image`` new patches per training input (None: as many as
    the shard set's round 0 cut) are drawn from ``error_weight`` × the PDF of the run's ``metric`` error
    map + (1 − ``error_weight``) × the variance PDF (0: the variance PDF alone, a control), then every
    branch network trains ``round_steps`` more steps on all rounds so far, a patch of round j weighing
    ``round_decay`` ** (k − j) in round k (1: every patch alike; < 1: the newest rounds count more).
    ``patches_per_image`` 0 adds no patches: the rounds only train longer on round 0 (the other control).
    """

    rounds: int = bounded(3, ROUNDS)
    metric: str = "smape"
    error_weight: float = bounded(0.5, SHARE)
    patches_per_image: int | None = bounded(None, Bound(0, PATCH_COUNT.high))  # 0 adds no patches
    round_steps: int = bounded(400, STEPS)
    round_decay: float = bounded(1.0, FRACTION)

    def __post_init__(self):
        from prep.sampling import ERROR_METRICS

        check_fields(self)
        if self.metric not in ERROR_METRICS:
            raise OptionError("metric", f"must be one of {', '.join(ERROR_METRICS)}, got {self.metric!r}")

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def identity(self) -> dict:
        """What must agree for a rerun to continue the same loop (``rounds`` may grow: more rounds)."""
        return {k: v for k, v in self.to_dict().items() if k != "rounds"}
