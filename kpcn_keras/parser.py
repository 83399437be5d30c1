"""The argparse parser of ``kpcn``: one builder per subcommand, and what reads a command line back.

Each subcommand's options are the fields of its stage's config dataclass (``kpcn_keras.config``, ``kpcn_keras.studies.
config``, ``prep``); an option left out takes the dataclass's default, and a help text states that default from the
dataclass (:func:`_default`) and the bound it is checked against from the same ``prep.bounds.Bound``
(:func:`_state_bounds`): the parser never retypes either. The few options no dataclass holds (``--slope``,
``--port``, ...) are checked against theirs (:func:`_check_own_bounds`) before the command starts. :func:`command_line`
turns values back into the arguments of a command, under the flags this parser gives them. The command functions
are in :mod:`kpcn_keras.cli`; ``kpcn export`` and ``--runtime``, in :mod:`kpcn_keras.onnx_cli`. Building the parser
imports no keras and no torch (the configs are plain dataclasses), so ``kpcn --help``, ``kpcn render`` and ``kpcn
shards`` stay light.
"""

from __future__ import annotations

import argparse
import dataclasses

from kpcn_keras.onnx_cli import export_options, runtime_option
from kpcn_keras.options import csv as _csv
from kpcn_keras.options import csv_floats as _csv_floats
from kpcn_keras.options import csv_ints as _csv_ints
from kpcn_keras.options import default as _default
from kpcn_keras.options import defaults as _defaults
from kpcn_keras.study_options import STUDY_BUILDERS
from prep.bounds import BOUND, DISTINCT, check_distinct

# kpcn denoise's adaptation options: each one's dest and the ``AdaptSettings`` field it sets
DENOISE_ADAPT = {"adapt": "seconds", "adapt_steps": "steps", "adapt_seed": "seed", "adapt_confidence": "confidence"}


def _adapt_own() -> dict:
    """kpcn denoise's adaptation options (dest -> bound), bounded as ``AdaptSettings``' fields are."""
    from kpcn_keras.settings import AdaptSettings
    from prep.bounds import bound_of

    return {dest: bound_of(AdaptSettings, field) for dest, field in DENOISE_ADAPT.items()}


def _mode_run(text: str) -> tuple[str, str]:
    """``MODE=RUN`` of ``kpcn ship --mode``: a quality mode other than the default (whose networks are --run's) and
    a run folder."""
    from kpcn_keras.config import DEFAULT_QUALITY, QUALITY_MODES

    mode, sep, run = text.partition("=")
    others = [m for m in QUALITY_MODES if m != DEFAULT_QUALITY]
    if not sep or not run:
        raise argparse.ArgumentTypeError(f"expected MODE=RUN (e.g. fast=runs/fast), got {text!r}")
    if mode == DEFAULT_QUALITY:
        raise argparse.ArgumentTypeError(f"the {DEFAULT_QUALITY} mode is the networks of --run; --mode names the "
                                         f"others ({', '.join(others)}), got {text!r}")
    if mode not in others:
        raise argparse.ArgumentTypeError(f"the mode must be one of {', '.join(others)}, got {mode!r} in {text!r}")
    return mode, run


def _given(args, cls) -> dict:
    """The options of the subcommand that the user gave and that are fields of the dataclass ``cls``."""
    names = {f.name for f in dataclasses.fields(cls)} & set(args.flags)
    return {k: v for k, v in vars(args).items() if k in names}


# options that change no byte of the data a command writes: left out of the command line that shards record,
# so that a set cut in parts, or with another thread count, holds the same files as one cut in one go
# (reports keep them: how many threads ran is part of what they measured)
DATA_INVARIANT = ("threads", "part", "quiet")


def _command_line(args, leave_out=()) -> str:
    """The command as it was typed, ``kpcn`` and its arguments, less the options whose dest is in
    ``leave_out`` (each found as the parser finds it: ``--threads 2``, ``--threads=2``, an abbreviation)."""
    actions = {**args.parser._option_string_actions,
               **args.parser.get_default("subcommands")[args.command]._option_string_actions}
    kept, skip = [], 0
    for token in args.argv:
        if skip:
            skip -= 1
            continue
        flag = token.split("=", 1)[0]
        found = [a for option, a in actions.items() if option == flag] or \
            [a for option, a in actions.items() if flag.startswith("--") and option.startswith(flag)]
        if token.startswith("-") and len(found) == 1 and found[0].dest in leave_out:
            skip = 0 if "=" in token or found[0].nargs == 0 else 1
            continue
        kept.append(token)
    return " ".join(["kpcn"] + kept)


def _state_bounds(parser: argparse.ArgumentParser) -> None:
    """Append to the help of every option of every subcommand the bound it is checked against
    (``prep.bounds``): its config field's, or, for an option no config holds, the subcommand's own (which
    :func:`main` checks), and, for a list, that it takes no repeat. Every help states what the check does."""
    for command, sub in parser.get_default("subcommands").items():
        configs, own, own_distinct = parser.get_default("bounded")[command]
        for action in sub._actions:
            if not action.option_strings or action.help is argparse.SUPPRESS or action.nargs == 0:
                continue
            fields = [f for cls in configs for f in dataclasses.fields(cls) if f.name == action.dest]
            bound = own.get(action.dest) or next((f.metadata[BOUND] for f in fields if f.metadata.get(BOUND)), None)
            distinct = any(f.metadata.get(DISTINCT) for f in fields) or action.dest in own_distinct
            listed = action.type in (_csv, _csv_ints, _csv_floats)
            stated = [("each " if listed else "") + bound.text()] if bound else []
            if distinct:
                stated.append("no repeats")
            if stated:
                stated = ", ".join(stated)
                # "an integer in [1, 16384] (default: 256)", "random permutations per family (default: 3); an ..."
                help = action.help or ""
                action.help = f"{stated} {help}" if help.startswith("(") else f"{help}; {stated}" if help else stated


def _check_own_bounds(args) -> None:
    """Check the options of the subcommand that no config dataclass holds against their bounds (before
    anything is read or written, as a config's check is)."""
    _, own, own_distinct = args.parser.get_default("bounded")[args.command]
    for dest, bound in own.items():
        if dest in args:
            value = getattr(args, dest)
            for v in value if isinstance(value, tuple) else (value,):
                bound.check(dest, v)
            if dest in own_distinct:
                check_distinct(dest, value)


def inference_settings(args):
    """The ``kpcn_keras.settings.InferenceSettings`` of the options given (tile, precision, ensemble, quality: those
    the subcommand has), the others at their defaults; checked once, there (an OptionError naming the option)."""
    from kpcn_keras.settings import InferenceSettings

    return InferenceSettings(**_given(args, InferenceSettings))


def _run_option(parser: argparse.ArgumentParser, **kwargs) -> None:
    """``--run`` (the run folder), also spelled ``--run-dir``: launched by ``torchrun ... -m kpcn_keras.cli``,
    our arguments pass through torchrun's own parser first, which takes ``--run`` for an ambiguous
    abbreviation of its ``--run-path`` and stops; ``--run-dir`` it leaves alone (``tests/test_cli.py`` checks
    every option of ours against torchrun's)."""
    parser.add_argument("--run", "--run-dir", dest="run", **kwargs)


def _part_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--part", help=f"write only part i of N of the {what} (1 <= i <= N; e.g. 1/4), the last part "
                        "to finish merging the record (default: RANK of WORLD_SIZE under torchrun, else all)")


def _flags(parser: argparse.ArgumentParser, command: str) -> dict[str, str]:
    """dest -> the flag a user types, for the subcommand ``command``."""
    sub = parser.get_default("subcommands")[command]
    return {a.dest: max(a.option_strings, key=len) for a in sub._actions if a.option_strings}


def command_line(command: str, values: dict) -> list[str]:
    """The arguments of ``kpcn <command>`` that give ``values`` (dest -> value; None and empty sequences are
    left out, other sequences comma-joined as the options read them), each under the flag this parser gives
    it, so that a caller never retypes the flags. ValueError for a value the command has no option for."""
    flags = _flags(build_parser(), command)
    unknown = sorted(set(values) - set(flags))
    if unknown:
        raise ValueError(f"kpcn {command} has no option for {unknown}")
    args = []
    for dest, value in values.items():
        if isinstance(value, (list, tuple)):
            value = ",".join(map(str, value)) or None
        if value is not None:
            args += [flags[dest], str(value)]
    return args


def _add_subcommand(p: argparse.ArgumentParser, sub, name: str, configs=(), own=None, own_distinct=(), **kw):
    """The subcommand ``name``, whose options are fields of ``configs`` (their bounds) or in ``own``
    (dest -> Bound: the options no config holds; those in ``own_distinct`` take no repeat)."""
    p.get_default("subcommands")[name] = sub.add_parser(name, argument_default=argparse.SUPPRESS, **kw)
    p.get_default("bounded")[name] = (tuple(configs), dict(own or {}), frozenset(own_distinct))
    # every command computes (numba, torch or both); prep/threads.py makes the count hold for both
    p.get_default("subcommands")[name].add_argument(
        "--threads", type=int, help="threads for numba and torch, an integer from 1 to the cores this process "
        "may use (default: every one of them; under torchrun, its share of them)")
    return p.get_default("subcommands")[name]


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``kpcn``: every subcommand of :data:`BUILDERS`, each option's help stating its bound."""
    p = argparse.ArgumentParser(prog="kpcn", description="Kernel-predicting denoisers for path-traced renders.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True)
    p.set_defaults(subcommands={}, bounded={})

    def add(name, configs=(), own=None, own_distinct=(), **kw):
        return _add_subcommand(p, sub, name, configs, own, own_distinct, **kw)

    for builder in BUILDERS.values():
        builder(add)
    _state_bounds(p)
    return p


def _render_options(add) -> None:
    """The options of ``kpcn render``: a built-in scene set, or one scene file."""
    from prep.render import RenderConfig  # light: no numba kernels until a render runs
    from prep.render.frame import SPP

    r = add("render", (RenderConfig,), {"spp": SPP}, help="render a built-in scene set (noisy inputs + references), "
               "or one scene file, to EXR")
    d = _defaults(RenderConfig)
    r.add_argument("--set", dest="set_name", help=f"render set name, a folder under --out {d('set_name')}")
    r.add_argument("--families", type=_csv, help=f"comma-separated scene families {d('families')}")
    r.add_argument("--per-family", type=int, help=f"random permutations per family {d('per_family')}")
    r.add_argument("--width", type=int, help=d("width"))
    r.add_argument("--height", type=int, help=d("height"))
    r.add_argument("--input-spp", type=_csv_ints, help=f"comma-separated input sample counts {d('input_spp')}")
    r.add_argument("--reference-spp", type=int, help=d("reference_spp"))
    r.add_argument("--seed", type=int, help=d("seed"))
    r.add_argument("--out", dest="out_root", help=f"folder holding render sets {d('out_root')}; with --scene: "
                   "the EXR (default: <scene file stem>-<spp>spp.exr beside the scene file; with --pair, the "
                   "folder of the two halves)")
    r.add_argument("--scene", help="render this scene file (.toml or .json; docs/scenes.md §5) instead "
                   "of a set; --spp, --seed, --width, --height override its [render] table")
    r.add_argument("--spp", type=int, help="with --scene: samples per pixel (default: the file's)")
    r.add_argument("--no-png", action="store_true", help="with --scene: no tonemapped PNG beside the EXR")
    r.add_argument("--pair", action="store_true", help="also render each input as two halves of half its "
                   "samples with two seeds of their own, <scene>-<spp/2>spp-pair-a.exr and -pair-b.exr beside it "
                   "(their spp in the header), for kpcn denoise A --pair B; with --scene: the two halves of the "
                   "file's frame instead of the frame")
    _part_option(r, "renders")


def _references_options(add) -> None:
    """The options of ``kpcn references``: the render set whose references are measured."""
    from prep.render import RenderConfig

    r = add("references", (RenderConfig,), help="how converged a render set's references are, per family and "
            "frame: writes convergence.{md,json,png} into the set's folder")
    d = _defaults(RenderConfig)
    r.add_argument("--set", dest="set_name", help=f"render set, a folder under --out {d('set_name')}")
    r.add_argument("--out", dest="out_root", help=f"folder holding render sets {d('out_root')}")


def _render_cycles_options(add) -> None:
    """The options of ``kpcn render-cycles``: Blender Cycles' frames of random scenes, in Blender's Python."""
    from prep.render.cycles import CyclesConfig

    c = add("render-cycles", (CyclesConfig,), help="render random scenes with Blender Cycles (inputs and a "
            "reference each, every pass, Blender's multilayer EXR) in a Python with bpy, each drawing its "
            "effects from a catalogue (media, subsurface, textures, depth of field, motion blur, hair, skies, "
            "emission, caustics, coats and sheen) and recording them in OUT/<scene>.json; OUT/manifest.json "
            "counts scenes per effect, frames done and CPU hours; kpcn import-renders makes them a render set")
    d = _defaults(CyclesConfig)
    c.add_argument("out", help="folder of the frames; a frame already there is kept, so a killed run resumes and "
                   "a larger --scenes range grows the set")
    c.add_argument("--scenes", help=f"first:end scene indices, end excluded {d('scenes')}")
    c.add_argument("--res", type=_csv_ints, help="comma-separated frame sides in pixels, each scene drawing one "
                   f"(from its seed and index) {d('res')}")
    c.add_argument("--spp", type=_csv_ints, help=f"comma-separated input sample counts {d('spp')}")
    c.add_argument("--ref-spp", type=int, help=f"the reference's samples {d('ref_spp')}")
    c.add_argument("--seed", type=int, help="draws the scenes with the indices; another seed, other scenes "
                   f"{d('seed')}")
    c.add_argument("--blender-python", help="a Python that has bpy, Blender's module (make .venv-bpy/bin/python "
                   f"makes one) {d('blender_python')}")


def _cycles_validation_options(add) -> None:
    """The options of ``kpcn cycles-validation``: the held-out Cycles validation set, or its check."""
    from prep.render.cycles import ValidationConfig

    v = add("cycles-validation", (ValidationConfig,), help="render the held-out Cycles validation set (scenes of "
            "the catalogue's validation split, drawn apart from every training scene, each carrying two effect "
            "groups so that every group has two scenes or more): per scene an input per --spp with every pass, "
            "Blender's own denoised frame of it (same seed: OIDN, albedo + normal, accurate prefilter), its two "
            "halves (<scene>-<spp/2>spp-pair-a.exr and -pair-b.exr: two other seeds, every pass, for kpcn denoise "
            "--pair) and a reference of Combined alone; OUT/manifest.json records each file's sha256; resumes "
            "where it stopped (a folder rendered before pairs gains its halves)")
    d = _defaults(ValidationConfig)
    v.add_argument("out", help="folder of the set (make cycles-validation: data/cycles/validation); a file "
                   "already there is kept, so a killed run resumes")
    v.add_argument("--scenes", type=int, help=f"how many scenes (indices 0 to N-1 of the split) {d('scenes')}")
    v.add_argument("--res", type=int, help=f"frame side in pixels {d('res')}")
    v.add_argument("--spp", type=_csv_ints, help=f"comma-separated input sample counts, each even (its halves) "
                   f"{d('spp')}")
    v.add_argument("--ref-spp", type=int, help=f"the reference's samples {d('ref_spp')}")
    v.add_argument("--seed", type=int, help=f"draws the scenes; another seed, other scenes {d('seed')}")
    v.add_argument("--blender-python", help=f"a Python that has bpy, Blender's module {d('blender_python')}")
    v.add_argument("--verify", action="store_true", help="render nothing: check every file of OUT against the "
                   "sha256 its manifest records (exit status 2 and one line naming the first that is missing or "
                   "differs)")


def _blend_pair_options(add) -> None:
    """The options of ``kpcn blend-pair``: a user's .blend frame as two halves, in Blender's Python."""
    from prep.render.blendpair import BlendPairConfig

    b = add("blend-pair", (BlendPairConfig,), help="render a .blend file's frame with Cycles as two halves for "
            "kpcn denoise A --pair B: twice at half the samples with two seeds of their own, every pass kpcn reads, "
            "<blend stem>-<spp/2>spp-pair-a.exr and -pair-b.exr (32-bit multilayer EXR); in a Python with bpy")
    d = _defaults(BlendPairConfig)
    b.add_argument("blend", help="the .blend file (its scene, camera, resolution and light paths as saved)")
    b.add_argument("--spp", type=int, help=f"the whole frame's samples, even: each half renders half {d('spp')}")
    b.add_argument("--frame", type=int, help="the frame to render (default: the file's current frame)")
    b.add_argument("--out", help="folder of the two halves (default: beside the .blend); a half there is kept")
    b.add_argument("--blender-python", help=f"a Python that has bpy, Blender's module {d('blender_python')}")


def _import_renders_options(add) -> None:
    """The options of ``kpcn import-renders``: another renderer's frames into a render set."""
    from prep.render.renderset import RENDER_ROOT

    i = add("import-renders", help="write another renderer's <scene>-<spp>spp.exr frames (Cycles, Mitsuba 3, "
            "PBRT-v4) into a new render set in kpcn's layout, for kpcn shards")
    i.add_argument("src", help="folder of another renderer's <scene>-<spp>spp.exr frames, each scene with a "
                   "reference (its frame with the most samples)")
    i.add_argument("--set", dest="set_name", required=True, help="the render set to write, a new folder under "
                   "--renders")
    i.add_argument("--renders", dest="render_root", help=f"folder holding render sets (default: {RENDER_ROOT})")


def _shards_options(add) -> None:
    """The options of ``kpcn shards``."""
    from prep.shards import ShardConfig

    s = add("shards", (ShardConfig,), help="cut 65x65 patches of a render folder into HDF5 shards")
    d = _defaults(ShardConfig)
    s.add_argument("--set", dest="set_name", help=f"render set to read and shard set to write {d('set_name')}")
    s.add_argument("--renders", dest="render_root", help=f"folder holding render sets {d('render_root')}")
    s.add_argument("--out", dest="out_root", help=f"folder holding shard sets {d('out_root')}")
    s.add_argument("--patch-size", type=int, help=d("patch_size"))
    s.add_argument("--patches-per-image", type=int, help="at most the patch positions of the smallest image "
                   f"{d('patches_per_image')}")
    s.add_argument("--patches-per-shard", type=int, help=d("patches_per_shard"))
    s.add_argument("--val-fraction", type=float, help=f"scenes held out per family {d('val_fraction')}")
    s.add_argument("--val-scenes", type=_csv, help="explicit held-out scenes (comma-separated)")
    s.add_argument("--input-spp", type=int, help="use only inputs of this spp (default: every input)")
    s.add_argument("--seed", type=int, help=d("seed"))
    s.add_argument("--inputs", help=f"input set the patches hold: {_input_sets()} {d('inputs')}; another than "
                   "full writes the shard set <set>.<inputs>")
    s.add_argument("--auxiliaries", help=f"{_auxiliaries()}: the albedo, normal and depth the patches hold, as "
                   f"rendered or prefiltered (prep.auxiliary; oidn needs pyoidn) {d('auxiliaries')}; another than "
                   "raw writes the shard set <set>[.<inputs>].aux-<auxiliaries>")
    _part_option(s, "shards")


def _train_options(add) -> None:
    """The options of ``kpcn train``: the network, the phases, the optimisation."""
    from kpcn_keras.config import COMPOSITOR_KERNEL_SIZE, PRESETS, CompositorConfig, ModelConfig, TrainConfig

    # --compositor-kernel is CompositorConfig.kernel_size, whose name --kernel-size (the branch network's) holds
    t = add("train", (TrainConfig, ModelConfig, CompositorConfig), {"compositor_kernel": COMPOSITOR_KERNEL_SIZE},
            help="train a denoiser in phases: branches, joint fine-tuning, compositor (resumes by itself)")
    d = _defaults(TrainConfig)
    t.add_argument("--set", dest="set_name", help=f"shard set {d('set_name')}")
    t.add_argument("--shards", dest="shards_root", help=f"folder holding shard sets {d('shards_root')}")
    _run_option(t, default="runs/default", help="run folder, created or resumed (default: runs/default)")
    t.add_argument("--inputs", help=f"input set of the network: {_input_sets()} {d('inputs')}; another than full "
                   "trains on the shard set <set>.<inputs> into <run>/inputs/<inputs>")
    t.add_argument("--auxiliaries", help=f"{_auxiliaries()}: train on the shard set cut with kpcn shards "
                   "--auxiliaries (<set>[.<inputs>].aux-<auxiliaries>); the run is served its auxiliaries so "
                   f"{d('auxiliaries')}")
    t.add_argument("--preset", help=f"{', '.join(PRESETS)} {d('preset')}; the options below override it")
    _network_options(t.add_argument_group("network (each branch, or the shared one)"))
    _phase_options(t.add_argument_group("phases"), d)
    _optimisation_options(t.add_argument_group("optimisation"), d)


def _network_options(g) -> None:
    """``kpcn train``'s options of the network: each branch's, or the shared one's."""
    from kpcn_keras.config import UNET_CAP_FACTOR, UNET_DEFAULTS

    g.add_argument("--arch", help="kpcn (Bako's plain stack), kpal (residual, batch norm), dpcn (direct prediction) "
                   "or unet (kernel prediction on a U-Net trunk)")
    g.add_argument("--width", type=int, help="filters per convolution (unet: of the finest level)")
    g.add_argument("--depth", type=int, help="convolutions (kpcn, dpcn), residual blocks (kpal) or convolutions per "
                   "level each way (unet)")
    g.add_argument("--levels", type=int, help="unet only: resolutions, the finest included "
                   f"(default: {UNET_DEFAULTS['levels']})")
    g.add_argument("--width-growth", type=float, help="unet only: filters multiplied by this a level down "
                   f"(default: {UNET_DEFAULTS['width_growth']})")
    g.add_argument("--width-cap", type=int, help=f"unet only: most filters of a level (default: {UNET_CAP_FACTOR} x "
                   "--width)")
    g.add_argument("--dilations", type=_csv_ints, help="kpcn, dpcn: comma-separated dilation of each convolution, "
                   "one per --depth, its taps that many pixels apart (the dilated preset: 1,2,4,8,4,2,1; "
                   "default: 1 each)")
    g.add_argument("--conv-size", type=int, help="convolution size (odd)")
    g.add_argument("--kernel-size", type=int, help="predicted kernel side (odd; the papers use 21)")
    g.add_argument("--dropout", type=float, help="drop rate after every convolution (the report's keep 0.7 is 0.3)")
    g.add_argument("--slope-module", type=int, help="λ joined after the trunk through this many 1x1 convolutions, "
                   "trained on λ maps (needs --slope-input): a new map re-runs only those (kpcn denoise --slope-map; "
                   "default: 0, λ at the input)")
    g.add_argument("--slope-mixture", type=int, help="with --slope-module: the trunk predicts this many kernels and "
                   "the module mixes them per pixel by λ, so a new map re-runs the module and a blend, not the "
                   "kernels (default: 0, the module feeds the one kernel head)")
    g.add_argument("--shared", action="store_true", help="one network for both branches, told apart by a one-hot "
                   "input (default: one network per branch)")


def _phase_options(g, d) -> None:
    """``kpcn train``'s options of the phases: which ones train, for how many steps, at what rate; the
    compositor's. ``d``: the sentence giving a TrainConfig field's default."""
    from kpcn_keras.config import DOWNSAMPLES, CompositorConfig

    g.add_argument("--branches", type=_csv, help=f"comma-separated subset of diffuse,specular {d('branches')}")
    g.add_argument("--steps", type=int, help=f"training steps per branch {d('steps')}")
    g.add_argument("--joint-steps", type=int, help="joint fine-tuning steps on the final colour, 0 for none "
                   f"{d('joint_steps')}")
    g.add_argument("--joint-lr", dest="joint_learning_rate", type=float, help=d("joint_learning_rate"))
    g.add_argument("--albedo-steps", type=int, help="steps of the albedo network, a copy of the diffuse network "
                   "trained to filter the albedo the irradiance is multiplied by (docs/training.md §1); 0 for none, "
                   f"the albedo then prefiltered {d('albedo_steps')}")
    g.add_argument("--albedo-lr", dest="albedo_learning_rate", type=float, help=d("albedo_learning_rate"))
    g.add_argument("--compositor", help="alpha or kernel: add the multiscale compositor phase (default: none)")
    g.add_argument("--compositor-steps", type=int, help=d("compositor_steps"))
    g.add_argument("--compositor-lr", dest="compositor_learning_rate", type=float, help=d("compositor_learning_rate"))
    g.add_argument("--gamma", type=float, help=f"weight of the compositor's α regulariser "
                   f"(default: {_default(CompositorConfig, 'gamma')})")
    g.add_argument("--compositor-kernel", dest="compositor_kernel", type=int, help="side of the kernel "
                   "compositor's upsampling kernels, in coarse pixels (the report's is 21; default: "
                   f"{_default(CompositorConfig, 'kernel_size')})")
    g.add_argument("--downsample", choices=DOWNSAMPLES, help="how the compositor's pyramid halves the image: 2x2 "
                   "average pooling, or the bicubic filter (less noise at the coarse levels, a wider footprint) "
                   f"(default: {_default(CompositorConfig, 'downsample')})")
    g.add_argument("--scale-supervision", type=float, help="weight of each inner pyramid level's loss term, its "
                   "composite output against the reference downsampled the same way; 0 is off "
                   f"(default: {_default(CompositorConfig, 'scale_supervision')})")


def _optimisation_options(g, d) -> None:
    """``kpcn train``'s options of the optimisation: batches, learning rate, loss, augmentation, stopping, the
    start. ``d``: the sentence giving a TrainConfig field's default."""
    g.add_argument("--batch-size", type=int, help=d("batch_size"))
    g.add_argument("--lr", dest="learning_rate", type=float, help=f"initial learning rate {d('learning_rate')}")
    g.add_argument("--decay-steps", type=int, help="steps per decay of the learning rate by --decay-rate "
                   f"{d('decay_steps')}")
    g.add_argument("--decay-rate", type=float, help=d("decay_rate"))
    g.add_argument("--clipnorm", type=float, help=f"gradient norm clip {d('clipnorm')}")
    g.add_argument("--loss", help=f"smape or asymmetric {d('loss')}")
    g.add_argument("--slope", type=float, help=f"asymmetric loss slope λ {d('slope')}")
    g.add_argument("--slope-input", action="store_true", help="λ as an input channel: one network for every λ "
                   "in --slope-range, chosen at 'kpcn denoise --slope'")
    g.add_argument("--slope-range", type=_csv_floats, help=f"low,high {d('slope_range')}")
    g.add_argument("--no-augment", dest="augment", action="store_false", help="no flips, rotations or colour "
                   "permutations of the training patches")
    g.add_argument("--reference-tau", type=float, help="τ of the branch losses' reference weighting: a pixel weighs "
                   "1/(1+(relSE/τ)^2), relSE its reference's relative standard error; 0 weighs none "
                   f"{d('reference_tau')}")
    g.add_argument("--fireflies", type=float, help="synthetic fireflies a training patch of the branch phases, on "
                   "average: isolated spikes the reference does not have, so that the networks learn to remove "
                   f"them; 0 adds none {d('fireflies')}")
    g.add_argument("--patience", type=int, help="stop a phase after this many epochs without a lower validation "
                   "(held-out) loss and keep its best epoch; --steps is then the most it trains; 0 trains every "
                   f"step {d('patience')}")
    g.add_argument("--init", help="start the branch networks from the finished ones of the same input set in this run "
                   "or model folder (e.g. models/default: fine-tune it on your own renders); its network options "
                   "must be this run's (default: a seeded initialisation)")
    g.add_argument("--seed", type=int, help=d("seed"))


def _input_sets() -> str:
    from prep.inputs import INPUT_SETS

    return ", ".join(INPUT_SETS)


def _auxiliaries() -> str:
    """The prefilters a network is trained and served with (``prep.auxiliary.TRAINED``), as "a, b or c"."""
    from prep.auxiliary import TRAINED

    return f"{', '.join(TRAINED[:-1])} or {TRAINED[-1]}"


def _resample_options(add) -> None:
    """The options of ``kpcn resample``."""
    from kpcn_keras.config import ResampleConfig

    m = add("resample", (ResampleConfig,), help="error-based resampling rounds: new patches where the run's denoiser "
               "errs, then more training on every round (resumes by itself)")
    d = _defaults(ResampleConfig)
    _run_option(m, required=True, help="a run folder that finished training (kpcn train)")
    m.add_argument("--rounds", type=int, help=f"error rounds in all; a rerun with more adds rounds {d('rounds')}")
    m.add_argument("--metric", help=f"per-pixel error of the error maps: smape or relmse {d('metric')}")
    m.add_argument("--error-weight", type=float, help="share of the error PDF in the mix with the variance PDF; "
                   f"0 draws from the variance PDF alone {d('error_weight')}")
    m.add_argument("--patches-per-image", type=int, help="new patches per training input per round "
                   "(default: as many as the shard set's round 0)")
    m.add_argument("--round-steps", type=int, help=f"training steps per network per round {d('round_steps')}")
    m.add_argument("--round-decay", type=float, help="a patch of round j weighs DECAY**(k-j) in round k; 1: all "
                   f"alike {d('round_decay')}")


def _denoise_options(add) -> None:
    """The options of ``kpcn denoise``."""
    from kpcn_keras.config import DEFAULT_TILE, SLOPE
    from kpcn_keras.settings import AdaptSettings, InferenceSettings

    n = add("denoise", (InferenceSettings,), {"slope": SLOPE, **_adapt_own()}, help="denoise EXRs (kpcn, Blender "
            "Cycles, Mitsuba 3, PBRT-v4 or plain colour): files, or every render in a folder, in one process; "
            "or, with OIDN's options (kpcn denoise --hdr color.pfm --alb albedo.pfm --nrm normal.pfm -o out.pfm), "
            "as oidnDenoise (kpcn denoise --hdr x -h lists what it takes)")
    n.add_argument("inputs", nargs="+", metavar="input", help="EXR files and folders (a folder: every *.exr in it "
                   "but earlier *-denoised.exr outputs)")
    from kpcn_keras.config import DEFAULT_MODEL, MODEL_ENV

    _run_option(n, help="a run folder that finished training (kpcn train), or a shipped model (default: the "
                f"folder ${MODEL_ENV} names, else the shipped models/{DEFAULT_MODEL}: make model)")
    n.add_argument("-o", "--output", default=None, help="output EXR, or a folder for <input stem>-denoised.exr "
                   "(a folder with several inputs; default: beside each input)")
    n.add_argument("--reference", default=None, help="reference EXR of a single input: prints MSE, relMSE, SMAPE, "
                   "DSSIM, PSNR")
    n.add_argument("--tile", type=int, help=f"tile size in pixels, bounds memory (default: {DEFAULT_TILE})")
    n.add_argument("--slope", type=float, help="λ, for a run trained with --slope-input: higher keeps more of the "
                   "input's detail (and noise)")
    n.add_argument("--slope-map", help="a painted λ map, for a run trained with --slope-module: a one-channel EXR "
                   "of λ, or a greyscale PNG from the low (black) to the high end (white) of the run's λ range, "
                   "resized to the frame if its aspect ratio matches")
    _precision_option(n)
    _ensemble_option(n)
    _quality_option(n)
    n.add_argument("--png", action="store_true", default=False, help="also write a tonemapped PNG beside each "
                   "output: input | denoised (| reference), side by side")
    _layout_option(n)
    n.add_argument("--pair", default=None, help="a second render of a single input with another seed and the same "
                   "spp: the two are denoised as one render of all their samples, their mean (with --adapt: the two "
                   "halves the model adapts on first)")
    n.add_argument("--adapt", type=float, help="with --pair: seconds at most of adapting a post-correction to the "
                   "frame's two halves, each the other's target (docs/adapt.md; default: none)")
    n.add_argument("--adapt-steps", type=int, help="with --pair: adapt for exactly this many steps instead (the same "
                   "seed and steps give the same result on any machine)")
    n.add_argument("--adapt-seed", type=int, help=f"the adaptation's seed {_defaults(AdaptSettings)('seed')}")
    n.add_argument("--adapt-confidence", type=float, help="standard errors the guard's estimated gain must clear "
                   "to keep the correction; negative keeps one estimated up to that many worse (docs/adapt.md §4) "
                   f"{_defaults(AdaptSettings)('confidence')}")
    n.add_argument("--albedo", default=None, help="an RGB EXR of a single rgb-layout input's albedo")
    n.add_argument("--normal", default=None, help="an RGB EXR of a single rgb-layout input's normal")
    n.add_argument("--clean-aux", action="store_true", help="the frame's albedo, normal and depth are clean "
                   "already (OIDN's cleanAux): a model trained on prefiltered auxiliaries is given them as they are")


def adapt_settings(args):
    """The ``kpcn_keras.settings.AdaptSettings`` of the options given: ``kpcn adapt``'s own, or ``kpcn denoise``'s
    --adapt, --adapt-steps, --adapt-seed and --adapt-confidence (None where neither --adapt nor --adapt-steps is
    given)."""
    from kpcn_keras.settings import AdaptSettings

    if args.command == "adapt":
        return AdaptSettings(**_given(args, AdaptSettings))
    if "adapt" not in args and "adapt_steps" not in args:
        return None
    given = {field: getattr(args, dest, None) for dest, field in DENOISE_ADAPT.items()}
    return AdaptSettings(**{k: v for k, v in given.items() if v is not None})


def _adapt_options(add) -> None:
    """The options of ``kpcn adapt``."""
    from kpcn_keras.config import DEFAULT_MODEL
    from kpcn_keras.settings import AdaptSettings, InferenceSettings

    a = add("adapt", (AdaptSettings, InferenceSettings), help="adapt a model to a shot: a post-correction trained on "
            "frames given as two independent renders each (no reference), written as a model folder that kpcn "
            "denoise --run, evaluate, view and kpcn.denoise take (docs/adapt.md)")
    d = _defaults(AdaptSettings)
    a.add_argument("frames", nargs="+", help="the first render of each frame (files), or folders of pairs named "
                   "<scene>-<spp>spp-pair-a.exr and -pair-b.exr")
    a.add_argument("--pairs", nargs="+", help="the second render of each frame given as a file, in order")
    a.add_argument("--out", required=True, help="the adapted model folder to write (a new folder)")
    _run_option(a, help=f"the model to adapt (default: as kpcn denoise, models/{DEFAULT_MODEL})")
    _quality_option(a)
    _layout_option(a)
    a.add_argument("--seconds", type=float, help=f"seconds of adapting at most {d('seconds')}")
    a.add_argument("--steps", type=int, help="exactly this many steps instead (reproducible on any machine)")
    a.add_argument("--seed", type=int, help=d("seed"))
    a.add_argument("--learning-rate", type=float, help=d("learning_rate"))
    a.add_argument("--crop", type=int, help=f"side of the training crops {d('crop')}")
    a.add_argument("--crops", type=int, help=f"crops per render at most (bounds memory) {d('crops')}")
    a.add_argument("--block", type=int, help=f"side of the held-out blocks {d('block')}")
    a.add_argument("--check-every", type=int, help=f"steps between held-out checks {d('check_every')}")
    a.add_argument("--confidence", type=float, help="standard errors the held-out gain must clear; negative keeps a "
                   f"correction estimated up to that many worse {d('confidence')}")


def _view_options(add) -> None:
    """The options of ``kpcn view``."""
    from kpcn_keras.config import DEFAULT_MODEL, DEFAULT_TILE, PORT, SLOPE, VIEW_HOST, VIEW_PORT
    from kpcn_keras.settings import InferenceSettings

    v = add("view", (InferenceSettings,), {"slope": SLOPE, "port": PORT}, help="one frame on a local page: input, "
            "kpcn, reference and OIDN with a swipe, zoom and exposure, and a brush that paints λ (a run trained "
            "with --slope-module)")
    v.add_argument("frame", help="an EXR in any layout kpcn denoise reads")
    _run_option(v, help=f"a finished run folder or shipped model (default: as kpcn denoise, models/{DEFAULT_MODEL})")
    v.add_argument("--reference", default=None, help="the frame's reference EXR, a view of the page")
    v.add_argument("--pair", default=None, metavar="B.exr", help="a second render of the frame with another seed, "
                   "each at half the samples: the page shows their mean, and its adapt action adapts the model to "
                   "the two halves (docs/adapt.md)")
    v.add_argument("--slope", type=float, help="λ to start from (everywhere), for a run trained with λ as an "
                   "input (default: the run's validation λ)")
    v.add_argument("--port", type=int, help=f"port on {VIEW_HOST} (default: {VIEW_PORT}; 0 takes a free one)")
    v.add_argument("--tile", type=int, help=f"tile size in pixels (default: {DEFAULT_TILE})")
    _precision_option(v)
    _quality_option(v)
    _layout_option(v)


def _precision_option(parser) -> None:
    from kpcn_keras.config import DEFAULT_PRECISION, PRECISIONS

    parser.add_argument("--precision", choices=PRECISIONS, help="the networks' arithmetic: bfloat16 convolutions "
                        "are faster where the CPU has them natively, and change the output slightly; auto takes "
                        f"bfloat16 there and float32 elsewhere (default: {DEFAULT_PRECISION})")
    runtime_option(parser)


def _ensemble_option(parser) -> None:
    from kpcn_keras.config import DEFAULT_ENSEMBLE

    parser.add_argument("--ensemble", type=int, help="denoise the frame moved by this many of the square's 8 "
                        "symmetries and keep each pixel's median: that many times the time, for a lower error "
                        f"(default: {DEFAULT_ENSEMBLE}, the networks once)")


def _quality_option(parser) -> None:
    from kpcn_keras.config import DEFAULT_QUALITY, QUALITY_MODES

    parser.add_argument("--quality", choices=QUALITY_MODES, help="the model's quality mode, as OIDN's: the network "
                        "set the model holds for it (kpcn ship --mode); a mode the model lacks is refused, naming "
                        f"those it has (default: {DEFAULT_QUALITY}, the model's own networks)")


def _layout_option(parser) -> None:
    """The options of how a frame is read (``batch.ReadOptions``) that every command reading frames takes."""
    from prep.layouts import LAYOUTS

    parser.add_argument("--layout", choices=tuple(LAYOUTS), default=None, help="the renderer layout of the inputs "
                        "(default: found from each file's channels; docs/formats.md §1b)")
    parser.add_argument("--view-layer", default=None, metavar="NAME", help="the Cycles view layer to read (default: "
                        "the one with the most passes kpcn uses)")


def _evaluate_options(add) -> None:
    """The options of ``kpcn evaluate``."""
    from kpcn_keras.config import DEFAULT_TILE, SLOPE
    from kpcn_keras.settings import InferenceSettings

    e = add("evaluate", (InferenceSettings,), {"slope": SLOPE}, help="compare a run with the raw "
            "input and NLM on held-out scenes")
    _run_option(e, required=True, help="a run folder that finished training (kpcn train), or a shipped model "
                "(models/<name>)")
    e.add_argument("inputs", nargs="*", default=[], help="noisy renders, or folders of them (default: the run's "
                   "held-out scenes); each reference is the same scene's render with the most samples in the same "
                   "folder")
    e.add_argument("--out", default=None, help="report folder (default: <run>/eval)")
    e.add_argument("--tile", type=int, help=f"tile size in pixels (default: {DEFAULT_TILE})")
    e.add_argument("--slope", type=float, help="λ, for a run trained with --slope-input (as kpcn denoise --slope)")
    e.add_argument("--no-baseline", action="store_true", default=False)
    _precision_option(e)
    _ensemble_option(e)
    _quality_option(e)
    _layout_option(e)


def _mix_oidn_options(add) -> None:
    """The options of ``kpcn mix-oidn``."""
    m = add("mix-oidn", help="fit the weight at which each input set's networks of a run are mixed with OIDN's "
            "frame (prefiltered, high quality) and write it into their records: every command that denoises with "
            "the run then mixes so (docs/denoise.md §5c)")
    _run_option(m, required=True, help="a run folder that finished training (kpcn train)")
    m.add_argument("inputs", nargs="+", help="noisy renders, or folders of them, each with its scene's reference "
                   "(the same folder's render of the scene with the most samples): frames of scenes the run "
                   "trained on and those a report will judge are both the wrong ones")


def _ship_options(add) -> None:
    """The options of ``kpcn ship``."""
    from kpcn_keras.config import SHIPPED_MAX_BYTES, SPEED_FRAME
    from prep.render.frame import FRAME_SIDE

    s = add("ship", own={"speed_frame": FRAME_SIDE}, help="copy a finished, evaluated run with a model for every "
            f"input set into a model folder with its card (CARD.md), for git: no checkpoints, at most "
            f"{SHIPPED_MAX_BYTES / 2**20:.0f} MiB")
    _run_option(s, required=True, help="the run folder: finished, for every input set (kpcn train --inputs), "
                "evaluated (kpcn evaluate)")
    s.add_argument("--out", required=True, help="the model folder, e.g. models/<name>; an earlier one is replaced")
    s.add_argument("--mode", action="append", type=_mode_run, metavar="MODE=RUN", help="also ship the finished run "
                   "RUN (for every input set, as --run) as the quality mode MODE, into <out>/quality/MODE; "
                   "repeatable (e.g. --mode fast=runs/fast --mode high=runs/high; default: the balanced mode "
                   "alone, --run's)")
    s.add_argument("--speed-frame", type=_csv_ints, help="WIDTH,HEIGHT of the frame the card times beside OIDN "
                   f"(default: {','.join(map(str, SPEED_FRAME))})")


def _figures_options(add) -> None:
    """The options of ``kpcn figures``."""
    from kpcn_keras.config import DEFAULT_SLOPES, DEFAULT_TILE, PIXEL, SLOPE
    from kpcn_keras.settings import InferenceSettings
    from prep.shards import ShardConfig

    f = add("figures", (InferenceSettings,), {"slopes": SLOPE, "pixel": PIXEL}, own_distinct=("slopes",),
            help="draw the report's figures from a run: kernels, α maps, with and without multiscale, a λ sweep, "
            "and its shard set's sampling PDF and network inputs (into <run>/figures); or, with --set, the last "
            "two of a shard set alone (into <set>/figures)")
    _run_option(f, help="a run folder that finished training (kpcn train)")
    f.add_argument("input", nargs="?", default=None, help="noisy render (default: the run's first held-out scene "
                   "at its lowest spp); its reference is the same scene's render with the most samples beside it; "
                   "with --set, an input render of the set (default: its first held-out one)")
    d = _defaults(ShardConfig)
    f.add_argument("--set", dest="set_name", help=f"instead of --run: the shard set, a folder under --shards "
                   f"{d('set_name')}")
    f.add_argument("--shards", dest="shards_root", help=f"with --set: folder holding shard sets {d('out_root')}")
    f.add_argument("--pixel", type=_csv_ints, help="y,x of the kernel figure's pixel (default: the noisiest)")
    slopes = ",".join(f"{s:g}" for s in DEFAULT_SLOPES)
    f.add_argument("--slopes", type=_csv_floats, help=f"the λ of the sweep (default: {slopes})")
    f.add_argument("--tile", type=int, help=f"tile size in pixels (default: {DEFAULT_TILE})")


# the subcommands, in the order of ``kpcn --help``: name -> the builder of its options
BUILDERS = {
    "render": _render_options,
    "references": _references_options,
    "render-cycles": _render_cycles_options,
    "cycles-validation": _cycles_validation_options,
    "blend-pair": _blend_pair_options,
    "import-renders": _import_renders_options,
    "shards": _shards_options,
    "train": _train_options,
    "resample": _resample_options,
    "denoise": _denoise_options,
    "adapt": _adapt_options,
    "view": _view_options,
    "evaluate": _evaluate_options,
    "mix-oidn": _mix_oidn_options,
    "ship": _ship_options,
    "export": export_options,
    "figures": _figures_options,
    **STUDY_BUILDERS,
}
