"""The configurations of the studies (``kpcn compare``, ``kpcn bench``, ``kpcn resample-study``, ``kpcn
inputs-study``, ``kpcn quality``) and their tables: :data:`CONFIGURATIONS` (what ``compare`` and ``bench``
train), :data:`QUALITY_LEVERS` (what ``quality`` trains), :data:`ARMS` (the arms of the resample study),
:data:`BENCH_LADDERS` and :data:`BENCH_PRESETS` (the ladders of ``bench``).

No keras, no torch: the command line builds its parser from these. Each default is written once, here,
with its bound (``prep.bounds``), as in :mod:`kpcn_keras.config`, whose training configuration the studies
fill.
"""

from __future__ import annotations

from dataclasses import dataclass

from kpcn_keras.config import (
    DEFAULT_ENSEMBLE,
    ENSEMBLE,
    FRACTION,
    NO_FIREFLIES,
    ROUNDS,
    STEPS,
    UNWEIGHTED_TAU,
    ResampleConfig,
)
from prep.bounds import PATCH_COUNT, REPEATS, SEED, Bound, bounded, check_fields
from prep.errors import OptionError
from prep.files import check_set_name
from prep.render.frame import FRAME_SIDE, SPP
from prep.render.renderset import RENDER_ROOT

# name -> (what it is, preset, TrainConfig overrides). A joint_steps or compositor entry only says that the
# phase exists: every step count is set by the budget.
CONFIGURATIONS: dict[str, tuple[str, str, dict]] = {
    "cpu": ("the default (cpu preset)", "cpu", {}),
    "kpcn-paper": ("Bako et al. 2017's network and training", "kpcn-paper", {}),
    "kpal-paper": ("the report's residual network and training", "kpal-paper", {}),
    "dpcn": ("cpu, predicting the colour directly instead of kernels", "cpu", {"model": {"arch": "dpcn"}}),
    "shared": ("cpu, one network for both branches", "cpu", {"shared": True}),
    "joint": ("cpu, then both branches fine-tuned together on the final colour", "cpu", {"joint_steps": 1}),
    "multiscale-alpha": ("cpu + Vogels' scale compositor", "cpu", {"compositor": {"kind": "alpha"}}),
    "multiscale-kernel": ("cpu + the kernel-predicting compositor", "cpu", {"compositor": {"kind": "kernel"}}),
    # each of the three below changes one thing of multiscale-kernel (report §2.2.1, §3.1.1)
    "multiscale-kernel-21": ("multiscale-kernel with the report's 21×21 upsampling kernels (5×5)", "cpu",
                             {"compositor": {"kind": "kernel", "kernel_size": 21}}),
    "multiscale-bicubic": ("multiscale-kernel on a bicubic pyramid (2×2 average pooling)", "cpu",
                           {"compositor": {"kind": "kernel", "downsample": "bicubic"}}),
    "multiscale-scales": ("multiscale-kernel, each inner scale supervised too (the finest alone)", "cpu",
                          {"compositor": {"kind": "kernel", "scale_supervision": 1.0}}),
    "asymmetric": ("cpu, asymmetric loss instead of SMAPE", "cpu", {"loss": "asymmetric", "slope": 2.0}),
    "no-augment": ("cpu without flips, rotations and colour permutations", "cpu", {"augment": False}),
    "kernel-5": ("cpu with 5×5 kernels", "cpu", {"model": {"kernel_size": 5}}),
    "kernel-21": ("cpu with the papers' 21×21 kernels", "cpu", {"model": {"kernel_size": 21}}),
    "kpal": ("cpu-sized residual network", "cpu", {"model": {"arch": "kpal", "depth": 3}}),
}


def combine(*names: str, levers: dict | None = None) -> tuple[str, str, dict, dict | None]:
    """One lever that pulls every lever of ``names`` (of ``levers``, default :data:`QUALITY_LEVERS`) at once: their
    TrainConfig overrides merged (``model`` and ``compositor`` field by field), their render-set options merged,
    and the one preset among them other than ``cpu`` (ValueError where two differ)."""
    levers = QUALITY_LEVERS if levers is None else levers
    presets = {levers[n][1] for n in names} - {"cpu"}
    if len(presets) > 1:
        raise ValueError(f"levers {list(names)} need different presets {sorted(presets)}")
    overrides: dict = {}
    render: dict = {}
    for name in names:
        _, _, own, renders = levers[name]
        for key, value in own.items():
            overrides[key] = {**overrides.get(key, {}), **value} if isinstance(value, dict) else value
        render.update(renders or {})
    return ("every lever together: " + ", ".join(names), presets.pop() if presets else "cpu", overrides,
            render or None)


# The levers of ``kpcn quality`` (kpcn_keras/studies/quality.py): name -> (what it is, preset, TrainConfig
# overrides, the options of a render set of its own or None). A render-set entry (RenderConfig fields: scenes
# per family, the input spp ladder) makes the study render and cut a larger set from the study's own (its seed,
# size and reference spp), whose held-out scenes are the study's; every other lever trains on the study's set.
# Adding a lever is one entry; "combination" names the levers it combines.
# the data lever's render set: 8 scenes per family instead of 3, and the ladder from the lowest spp a render has
MORE_DATA = {"per_family": 8, "input_spp": (2, 4, 8, 16, 32, 64)}
# What every lever starts from, under its own overrides: the training before the quality levers (no reference
# weighting, no synthetic fireflies), so that each lever is measured alone against the baseline ``cpu``.
QUALITY_BASE = {"reference_tau": UNWEIGHTED_TAU, "fireflies": NO_FIREFLIES}
QUALITY_LEVERS: dict[str, tuple[str, str, dict, dict | None]] = {
    "cpu": ("the cpu preset without reference weighting or synthetic fireflies, the baseline", "cpu", {}, None),
    "unet": ("the kernel-predicting network on a U-Net trunk (unet preset)", "unet", {}, None),
    "dilated": ("cpu with its trunk dilated 1, 2, 4, 8, 4, 2, 1 (dilated preset)", "dilated", {}, None),
    "multiscale-kernel": (CONFIGURATIONS["multiscale-kernel"][0], *CONFIGURATIONS["multiscale-kernel"][1:], None),
    "reference-weight": ("cpu, each reference pixel's loss weighted by its convergence (τ = 0.1)", "cpu",
                         {"reference_tau": 0.1}, None),
    "fireflies": ("cpu, each training patch with synthetic fireflies (1 a patch on average)", "cpu",
                  {"fireflies": 1.0}, None),
    "data": (f"cpu on {MORE_DATA['per_family']} scenes per family and inputs at "
             f"{', '.join(map(str, MORE_DATA['input_spp']))} spp", "cpu", {}, MORE_DATA),
}
# dilated and unet are two trunks of one network: the combination takes one of them, the unet's
QUALITY_LEVERS["combination"] = combine("unet", "multiscale-kernel", "reference-weight", "fireflies", "data")

# name -> (what it is, the loop's settings besides the study's)
ARMS: dict[str, tuple[str, dict]] = {
    "continue": ("no new patches: round 0 (variance-PDF sampling only), trained as long",
                 {"patches_per_image": 0, "error_weight": 0.0}),
    "variance": ("new patches each round from the variance PDF alone", {"error_weight": 0.0}),
    "error": ("new patches each round from the error PDF mixed with the variance PDF", {}),
}

BUDGET = Bound(0.0, 7 * 86400.0, integer=False, low_open=True)  # training seconds: at most a week


def _all_configurations() -> tuple[str, ...]:
    return tuple(CONFIGURATIONS)


@dataclass
class CompareConfig:
    """Configuration of ``kpcn compare`` (kpcn_keras/studies/compare.py): each of ``configurations`` trained for
    ``budget`` seconds on the shard set ``<shards_root>/<set_name>`` into ``runs_root``, measured on the
    set's held-out frames, reported in ``out_dir``; ``frame`` is the side of the crop whose inference is
    timed, ``repeats`` how many timed calls the median is of, ``seed`` the training seed of every run."""

    set_name: str = "default"
    shards_root: str = "shards"
    runs_root: str = "runs/compare"
    out_dir: str = "reports"
    budget: float = bounded(180, BUDGET)
    configurations: tuple[str, ...] = bounded(default_factory=_all_configurations, distinct=True)
    frame: int = bounded(256, FRAME_SIDE)
    repeats: int = bounded(5, REPEATS)
    seed: int = bounded(0, SEED)

    def __post_init__(self):
        known = _all_configurations()
        if isinstance(self.configurations, str):
            self.configurations = tuple(c.strip() for c in self.configurations.split(",") if c.strip())
        self.configurations = tuple(self.configurations)
        check_set_name(self.set_name)
        for name in ("shards_root", "runs_root", "out_dir"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise OptionError(name, f"must be a folder, got {getattr(self, name)!r}")
        unknown = [c for c in self.configurations if c not in known]
        if unknown or not self.configurations:
            found = f"has unknown {', '.join(map(repr, unknown))}" if unknown else "is empty"
            raise OptionError("configurations", f"{found}; the known ones are {', '.join(known)}")
        check_fields(self)


@dataclass
class InputsStudyConfig:
    """Configuration of ``kpcn inputs-study`` (kpcn_keras/studies/inputs_study.py): a run per input set trained for
    ``budget`` seconds (``preset``, ``seed``) on the render set ``<render_root>/<set_name>`` cut into
    ``shards_root``, in ``runs_root``; measured on the set's held-out frames, on the other renderers' frames
    under ``frames`` and on the pairs of renders under ``pairs``; reports in ``out_dir``."""

    set_name: str = "default"
    render_root: str = RENDER_ROOT
    shards_root: str = "shards"
    runs_root: str = "runs/inputs-study"
    out_dir: str = "reports"
    frames: tuple[str, ...] = ("tests/fixtures/renderers",)
    pairs: tuple[str, ...] = ()
    budget: float = bounded(300, BUDGET)
    preset: str = "cpu"
    seed: int = bounded(0, SEED)

    def __post_init__(self):
        from kpcn_keras.config import PRESETS

        self.frames, self.pairs = tuple(self.frames), tuple(self.pairs)
        check_set_name(self.set_name)
        for name in ("render_root", "shards_root", "runs_root", "out_dir"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise OptionError(name, f"must be a folder, got {getattr(self, name)!r}")
        if not self.frames:
            raise OptionError("frames", "must name at least one file or folder")
        if self.preset not in PRESETS:
            raise OptionError("preset", f"must be one of {', '.join(PRESETS)}, got {self.preset!r}")
        check_fields(self)


def _all_levers() -> tuple[str, ...]:
    return tuple(QUALITY_LEVERS)


# the repository's parent holds shared/: Blender's frames with its own denoiser's, and a Mitsuba 3 fixture
VALIDATION_FRAMES = ("../shared/validation/blender", "../shared/fixtures/mitsuba")


@dataclass
class QualityConfig:
    """Configuration of ``kpcn quality`` (kpcn_keras/studies/quality.py): each of ``levers``
    (:data:`QUALITY_LEVERS`) trained for ``budget`` seconds (all its networks together; ``seed``) on the render
    set ``<render_root>/<set_name>`` cut into ``shards_root`` (or on the larger set a lever renders from it), in
    ``runs_root``; measured on the set's held-out frames and on the frames under ``frames``, each denoised as a
    self-ensemble of ``ensemble`` members (``kpcn denoise --ensemble``; 1: the networks once), with panels of the
    frames at ``panel_spp``; reports in ``out_dir``. ``ensemble`` is not part of what is trained: the same runs
    serve every value. ``model``: a finished run or shipped model measured beside the levers on the same frames
    (empty: the one ``kpcn denoise`` uses without ``--run``, where there is one)."""

    set_name: str = "default"
    render_root: str = RENDER_ROOT
    shards_root: str = "shards"
    runs_root: str = "runs/quality"
    out_dir: str = "reports"
    levers: tuple[str, ...] = bounded(default_factory=_all_levers, distinct=True)
    frames: tuple[str, ...] = VALIDATION_FRAMES
    budget: float = bounded(600, BUDGET)
    panel_spp: int = bounded(16, SPP)
    seed: int = bounded(0, SEED)
    ensemble: int = bounded(DEFAULT_ENSEMBLE, ENSEMBLE)
    model: str = ""

    def __post_init__(self):
        known = _all_levers()
        if isinstance(self.levers, str):
            self.levers = tuple(c.strip() for c in self.levers.split(",") if c.strip())
        self.levers, self.frames = tuple(self.levers), tuple(self.frames)
        check_set_name(self.set_name)
        for name in ("render_root", "shards_root", "runs_root", "out_dir"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise OptionError(name, f"must be a folder, got {getattr(self, name)!r}")
        unknown = [c for c in self.levers if c not in known]
        if unknown or not self.levers:
            found = f"has unknown {', '.join(map(repr, unknown))}" if unknown else "is empty"
            raise OptionError("levers", f"{found}; the known ones are {', '.join(known)}")
        if not self.frames:
            raise OptionError("frames", "must name at least one file or folder")
        if not isinstance(self.model, str):
            raise OptionError("model", f"must be a run folder or empty (the shipped model), got {self.model!r}")
        check_fields(self)


def _study_arms() -> tuple[str, ...]:
    return tuple(ARMS)


@dataclass
class ResampleStudyConfig:
    """Configuration of ``kpcn resample-study`` (kpcn_keras/studies/resample_study.py): for each of ``seeds``, a run
    trained ``base_steps`` per network on ``<shards_root>/<set_name>``, then each of ``arms`` continues it for
    ``rounds`` rounds of ``round_steps`` (adding ``patches_per_image`` per training input where the arm adds
    any), in ``runs_root``; reports in ``out_dir``. ``error_weight`` and ``metric`` None take
    :class:`kpcn_keras.config.ResampleConfig`'s."""

    set_name: str = "default"
    shards_root: str = "shards"
    runs_root: str = "runs/resample-study"
    out_dir: str = "reports"
    seeds: tuple[int, ...] = bounded((0, 1, 2), SEED, distinct=True)
    arms: tuple[str, ...] = bounded(default_factory=_study_arms, distinct=True)
    base_steps: int = bounded(600, STEPS)
    rounds: int = bounded(3, ROUNDS)
    round_steps: int = bounded(200, STEPS)
    patches_per_image: int = bounded(8, PATCH_COUNT)
    error_weight: float | None = None
    metric: str | None = None

    def __post_init__(self):
        self.seeds, self.arms = tuple(self.seeds), tuple(self.arms)
        check_set_name(self.set_name)
        if not self.seeds:
            raise OptionError("seeds", "must name at least one seed")
        known = _study_arms()
        if not self.arms or any(a not in known for a in self.arms):
            raise OptionError("arms", f"must be names among {', '.join(known)}, got {list(self.arms)}")
        check_fields(self)
        self.loop()  # the loop's own checks of rounds, round_steps, error_weight (the error arm's), metric

    def loop(self, error_weight: float | None = None, patches_per_image: int | None = None) -> ResampleConfig:
        """The resample loop of one arm: the study's settings, the arm's error weight and patches."""
        given = {"metric": self.metric}
        weight = self.error_weight if error_weight is None else error_weight
        return ResampleConfig(rounds=self.rounds, round_steps=self.round_steps,
                              patches_per_image=(self.patches_per_image if patches_per_image is None
                                                 else patches_per_image),
                              **({"error_weight": weight} if weight is not None else {}),
                              **{k: v for k, v in given.items() if v is not None})


# The ladders of ``kpcn bench`` (kpcn_keras/studies/bench.py). "reduced", the default, finishes in under 45 minutes
# on a 2-core CPU; "full" (--full) measures every spp up to half the references' and trains five times longer.
# raw_spp: the raw Monte Carlo curve; input_spp: what the denoisers get; budget: training seconds of every
# configuration; budget_fractions: the training-cost curve of the presets, as fractions of the budget.
BENCH_LADDERS = {
    "reduced": {"raw_spp": (2, 4, 8, 16, 32, 64, 128), "input_spp": (4, 16, 64), "budget": 120.0,
                "budget_fractions": (1 / 3, 1.0),
                "configurations": ("cpu", "kernel-5", "kernel-21", "kpal", "dpcn", "multiscale-alpha")},
    "full": {"raw_spp": (2, 4, 8, 16, 32, 64, 128, 256), "input_spp": (2, 4, 8, 16, 32, 64, 128),
             "budget": 600.0, "budget_fractions": (1 / 9, 1 / 3, 1.0),
             "configurations": ("cpu", "kernel-5", "kernel-21", "kpal", "dpcn", "multiscale-alpha",
                                "multiscale-kernel", "shared", "joint")},
}
BENCH_PRESETS = ("cpu", "kpcn-paper", "kpal-paper")  # the training-cost curve: error against training seconds


@dataclass
class BenchConfig:
    """Configuration of ``kpcn bench`` (kpcn_keras/studies/bench.py): the held-out scenes of the shard set
    ``<shards_root>/<set_name>`` rendered at every spp of a ladder, denoised by each configuration trained
    for ``budget`` seconds in ``runs_root`` and by the baselines; reports in ``out_dir``. ``full`` picks the
    full ladder of :data:`BENCH_LADDERS`; ``raw_spp``, ``input_spp``, ``budget``, ``budget_fractions``,
    ``configurations`` and ``presets`` None take the ladder's (presets: :data:`BENCH_PRESETS`).
    ``large_frame`` (width, height) is the frame whose inference time and memory are measured against
    Intel Open Image Denoise; ``repeats`` how many timed calls a stage cost is the best or median of."""

    set_name: str = "default"
    shards_root: str = "shards"
    runs_root: str = "runs/bench"
    out_dir: str = "reports"
    full: bool = False
    raw_spp: tuple[int, ...] | None = bounded(None, SPP, distinct=True)
    input_spp: tuple[int, ...] | None = bounded(None, SPP, distinct=True)
    budget: float | None = bounded(None, BUDGET)
    budget_fractions: tuple[float, ...] | None = bounded(None, FRACTION, distinct=True)
    configurations: tuple[str, ...] | None = bounded(None, distinct=True)
    presets: tuple[str, ...] | None = bounded(None, distinct=True)
    large_frame: tuple[int, int] = bounded((1920, 1080), FRAME_SIDE)
    repeats: int = bounded(3, REPEATS)
    seed: int = bounded(0, SEED)

    def __post_init__(self):
        ladder = BENCH_LADDERS["full" if self.full else "reduced"]
        for name in ("raw_spp", "input_spp", "budget", "budget_fractions", "configurations"):
            if getattr(self, name) is None:
                setattr(self, name, ladder[name])
        if self.presets is None:
            self.presets = BENCH_PRESETS
        check_set_name(self.set_name)
        known = _all_configurations()
        for name in ("configurations", "presets"):
            values = getattr(self, name)
            values = tuple(c.strip() for c in values.split(",") if c.strip()) if isinstance(values, str) \
                else tuple(values)
            unknown = [c for c in values if c not in known]
            if unknown:
                raise OptionError(name, f"must be names among {', '.join(known)}, got {list(values)}")
            setattr(self, name, values)
        for name in ("raw_spp", "input_spp", "budget_fractions"):
            setattr(self, name, tuple(getattr(self, name)))
            if not getattr(self, name):
                raise OptionError(name, "must name at least one value")
        if len(self.large_frame) != 2:
            raise OptionError("large_frame", f"must be WIDTH,HEIGHT, got {list(self.large_frame)}")
        check_fields(self)
        for name in ("raw_spp", "input_spp", "budget_fractions"):
            setattr(self, name, tuple(sorted(getattr(self, name))))
        if len(self.raw_spp) < 2:
            raise OptionError("raw_spp", f"needs at least two sample counts for a curve, got {list(self.raw_spp)}")
        if not self.configurations:
            raise OptionError("configurations", "must name at least one configuration")

    def budgets(self) -> tuple[float, ...]:
        """The training budgets of the runs: the presets' curve, whose largest is the budget itself."""
        return tuple(sorted({round(self.budget * f, 3) for f in self.budget_fractions} | {self.budget}))
