"""``kpcn``: the command line of the toolkit.

Subcommands: render, shards, train, resample, denoise, evaluate, figures, bench, compare, resample-study. Each fills its stage's config dataclass from the
options the user gave; an option left out takes the dataclass's default (the parser never retypes one).
Every number's help states the bound it is checked against, from the same ``prep.bounds.Bound``
(:func:`_state_bounds`); the few options no dataclass holds (``--tile``, ``--slope``, ...) are checked
against theirs before the command starts.
``render`` and ``shards`` never import keras or torch.

Errors: a :class:`prep.errors.KpcnError` (bad input, a bad option, a folder in the wrong state) ends with
one line naming the file, layer or option, and exit status 2; an option is named by its flag. Anything
else is a bug and keeps its traceback. ``KPCN_DEBUG=1`` shows the traceback of a KpcnError too.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import sys

from prep.bounds import BOUND, DISTINCT, check_distinct
from prep.errors import KpcnError, OptionError

# The exit status of a KpcnError; argparse uses the same for a malformed command line.
EXIT_USER_ERROR = 2


def _csv(text: str) -> tuple[str, ...]:
    return tuple(t for t in (s.strip() for s in text.split(",")) if t)


def _csv_ints(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(t) for t in _csv(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _csv_floats(text: str) -> tuple[float, ...]:
    try:
        return tuple(float(t) for t in _csv(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


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


def _default(cls, name: str) -> str:
    """A dataclass field's default, for help texts."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    value = f.default_factory() if f.default is dataclasses.MISSING else f.default
    return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)


def _part(args):
    """The part of the work this process does: ``--part``, else the launcher's. A process that a launcher
    started dies with it: a cancelled job leaves no part writing on, holding its lock."""
    from prep.parts import Part
    from prep.processes import die_with_parent

    part = Part.chosen(getattr(args, "part", None))
    if "part" not in args and not part.whole:
        die_with_parent(os.getppid())
    return part


def cmd_render(args) -> int:
    from prep.render import RenderConfig, render_set

    if "scene" in args:
        return cmd_render_scene(args)
    for dest in ("spp", "no_png"):
        if dest in args:
            raise OptionError(dest, "is for one scene file: it needs --scene FILE")
    cfg = RenderConfig(**_given(args, RenderConfig))
    part = _part(args)
    paths = render_set(cfg, progress=not args.quiet, part=part)
    print(f"{len(paths)} renders in {cfg.out_root}/{cfg.set_name}" + ("" if part.whole else f" (part {part})"))
    return 0


def cmd_render_scene(args) -> int:
    """``kpcn render --scene FILE``: one scene file (prep/render/scenefile.py) to one EXR and a PNG."""
    from prep.parts import Part
    from prep.render import RenderConfig
    from prep.render.scenefile import render_scene_file

    shared = {"width", "height", "seed", "out_root"}  # the options that also mean something with --scene
    for dest in sorted({f.name for f in dataclasses.fields(RenderConfig)} - shared | {"part"}):
        if dest in args:
            raise OptionError(dest, "is for a built-in scene set, not for --scene FILE (use --spp)")
    part = Part.from_environment()
    if not part.whole:
        raise KpcnError(f"kpcn render --scene renders one file, as one process, not as part {part} of a "
                        "launcher's processes: run it without torchrun")
    overrides = {k: getattr(args, k) for k in ("spp", "seed", "width", "height") if k in args}
    report = render_scene_file(args.scene, getattr(args, "out_root", None), overrides=overrides,
                               png="no_png" not in args)
    print(f"wrote {report['output']}" + (f" and {report['png']}" if "png" in report else ""))
    print(f"rendered in {report['seconds']:.2f} s")
    return 0


def cmd_shards(args) -> int:
    from prep.shards import ShardConfig, build_shards, round_name

    cfg = ShardConfig(**_given(args, ShardConfig), command=_command_line(args, DATA_INVARIANT))
    part = _part(args)
    manifest = build_shards(cfg, progress=not args.quiet, part=part)
    if manifest["status"] != "complete":
        print(f"part {part} of {cfg.set_dir} written; its manifest is written by the last part to finish")
        return 0
    shards = manifest["rounds"][round_name(0)]["shards"]
    for split in ("train", "val"):
        n = sum(s["patches"] for s in shards if s["split"] == split)
        print(f"{split}: {len(manifest['split'][split])} scenes, {n} patches")
    print(f"manifest: {cfg.set_dir}/manifest.json")
    return 0


def cmd_train(args) -> int:
    from kpcn_keras.config import ModelConfig, TrainConfig
    from kpcn_keras.distributed import from_environment
    from kpcn_keras.train import train

    given = _given(args, TrainConfig)
    given["model"] = _given(args, ModelConfig)
    # the compositor's own options (its width and depth are not the network's --width and --depth)
    compositor = {k: getattr(args, k) for k in ("gamma",) if k in args}
    if compositor and "compositor" not in args:
        raise OptionError("gamma", "is a setting of the multiscale compositor: it needs --compositor alpha|kernel")
    if "compositor" in args:
        given["compositor"] = {"kind": args.compositor, **compositor}
    cfg = TrainConfig.from_preset(given.pop("preset", None), **given)
    run_dir = train(cfg, args.run, verbose=0 if args.quiet else "auto")
    if from_environment().writer:  # one line for a data-parallel run, not one per process
        print(f"run: {run_dir}")
    return 0


def cmd_resample(args) -> int:
    from kpcn_keras.config import ResampleConfig
    from kpcn_keras.resample import resample

    cfg = ResampleConfig(**_given(args, ResampleConfig))
    loop = resample(cfg, args.run, verbose=0 if args.quiet else "auto", progress=not args.quiet,
                    command=_command_line(args, DATA_INVARIANT))
    print(f"{len(loop['rounds'])} rounds; records: {os.path.join(args.run, 'resample', 'rounds.json')}")
    return 0


def cmd_denoise(args) -> int:
    from kpcn_keras.denoise import denoise_files

    def frame(report):
        print(f"wrote {report['output']}" + (f" and {report['png']}" if "png" in report else "")
              + f" ({report['seconds'] * 1000:.0f} ms denoising, {report['frame_s'] * 1000:.0f} ms with files)")

    batch = denoise_files(args.inputs, args.run, args.output, args.reference, png=not args.no_png, on_frame=frame,
                          **{k: getattr(args, k) for k in ("tile", "slope") if k in args})
    frames = batch["frames"]
    if batch["skipped"]:
        print(f"skipped {len(batch['skipped'])} earlier outputs or temporaries: {', '.join(batch['skipped'])}")
    startup = "?" if batch["startup_s"] is None else f"{batch['startup_s']:.2f} s"
    print(f"start-up {startup}, model load {batch['load_s']:.2f} s, warm-up {batch['warmup_s']:.2f} s "
          f"({batch['threads']} thread{'s' if batch['threads'] != 1 else ''})")
    if batch["peak_memory_mb"] is not None:
        print(f"peak memory {batch['peak_memory_mb']:.0f} MB")
    per_frame = sorted(f["seconds"] for f in frames)[len(frames) // 2]
    print(f"denoised {len(frames)} frame{'s' if len(frames) > 1 else ''} in {sum(f['seconds'] for f in frames):.2f} s"
          + (f" (median {per_frame * 1000:.0f} ms a frame)" if len(frames) > 1 else ""))
    if "metrics" in frames[0]:
        report = frames[0]
        print(f"{'':10s} " + " ".join(f"{m:>10s}" for m in report["metrics"]))
        for label, key in (("input", "input_metrics"), ("denoised", "metrics")):
            print(f"{label:10s} " + " ".join(f"{v:10.5f}" for v in report[key].values()))
    return 0


def cmd_evaluate(args) -> int:
    from kpcn_keras.evaluate import evaluate, format_table, pairs_for_inputs

    pairs = pairs_for_inputs(args.inputs) if args.inputs else None
    rows = evaluate(args.run, pairs, out_dir=args.out, baseline=not args.no_baseline,
                    **({"tile": args.tile} if "tile" in args else {}))
    print(format_table(rows))
    print(f"report: {args.out or os.path.join(args.run, 'eval')}/report.md")
    return 0


def cmd_figures(args) -> int:
    from kpcn_keras.evaluate import pairs_for_inputs
    from kpcn_keras.figures import make_figures

    frame = pairs_for_inputs([args.input])[0] if args.input else None
    if "pixel" in args and len(args.pixel) != 2:
        raise OptionError("pixel", f"must be two integers y,x, got {','.join(map(str, args.pixel))}")
    written = make_figures(args.run, frame, **{k: getattr(args, k) for k in ("pixel", "slopes", "tile") if k in args})
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0


def cmd_bench(args) -> int:
    from kpcn_keras.config import BenchConfig
    from prep.render.bench import RenderBenchConfig

    # an option of one bench that the other does not have (both have --out and --repeats)
    render_only, accuracy_only = ({f.name for f in dataclasses.fields(a)} - {f.name for f in dataclasses.fields(b)}
                                  for a, b in ((RenderBenchConfig, BenchConfig), (BenchConfig, RenderBenchConfig)))
    if args.what == "render":
        from prep.render.bench import bench_render, format_report

        for dest in sorted(d for d in accuracy_only if d in args):
            raise OptionError(dest, "is an option of 'kpcn bench' (accuracy against time), not of 'kpcn bench render'")
        cfg = RenderBenchConfig(**_given(args, RenderBenchConfig))
        record = bench_render(cfg, progress=not args.quiet)
        print(format_report(record))
        print(f"report: {cfg.out_dir}/render.md")
        return 0
    from kpcn_keras.bench import REPORT, bench

    for dest in sorted(d for d in render_only if d in args):
        raise OptionError(dest, "is an option of 'kpcn bench render', not of 'kpcn bench' (accuracy against time)")
    given = _given(args, BenchConfig)
    if "large_frame" in given and len(given["large_frame"]) != 2:
        raise OptionError("large_frame", f"must be WIDTH,HEIGHT, got {list(given['large_frame'])}")
    cfg = BenchConfig(**given)
    bench(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto",
          progress=not args.quiet)
    print(f"report: {cfg.out_dir}/{REPORT}.md, {REPORT}.json and {REPORT}.png")
    return 0


def cmd_compare(args) -> int:
    from kpcn_keras.compare import compare, format_report, rewrite_reports
    from kpcn_keras.config import CompareConfig

    cfg = CompareConfig(**_given(args, CompareConfig))
    if args.report_only:
        record = rewrite_reports(cfg.out_dir)
    else:
        record = compare(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto")
    print(format_report(record))
    print(f"report: {cfg.out_dir}/compare.md")
    return 0


def cmd_resample_study(args) -> int:
    from kpcn_keras.config import ResampleStudyConfig
    from kpcn_keras.resample_study import format_report, study

    cfg = ResampleStudyConfig(**_given(args, ResampleStudyConfig))
    record = study(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto",
                   progress=not args.quiet)
    print(format_report(record))
    print(f"report: {cfg.out_dir}/resample.md")
    return 0


def _run_option(parser: argparse.ArgumentParser, **kwargs) -> None:
    """``--run`` (the run folder), also spelled ``--run-dir``: launched by ``torchrun ... -m kpcn_keras.cli``,
    our arguments pass through torchrun's own parser first, which takes ``--run`` for an ambiguous
    abbreviation of its ``--run-path`` and stops; ``--run-dir`` it leaves alone (``tests/test_cli.py`` checks
    every option of ours against torchrun's)."""
    parser.add_argument("--run", "--run-dir", dest="run", **kwargs)


def build_parser() -> argparse.ArgumentParser:
    from prep.render import RenderConfig  # light: no numba kernels until a render runs
    from prep.shards import ShardConfig

    p = argparse.ArgumentParser(prog="kpcn", description="Kernel-predicting denoisers for path-traced renders.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True)
    p.set_defaults(subcommands={}, bounded={})

    def parser(name, configs=(), own=None, own_distinct=(), **kw):
        """The subcommand ``name``, whose options are fields of ``configs`` (their bounds) or in ``own``
        (dest -> Bound: the options no config holds; those in ``own_distinct`` take no repeat)."""
        p.get_default("subcommands")[name] = sub.add_parser(name, argument_default=argparse.SUPPRESS, **kw)
        p.get_default("bounded")[name] = (tuple(configs), dict(own or {}), frozenset(own_distinct))
        # every command computes (numba, torch or both); prep/threads.py makes the count hold for both
        p.get_default("subcommands")[name].add_argument(
            "--threads", type=int, help="threads for numba and torch, an integer from 1 to the cores this process "
            "may use (default: every one of them; under torchrun, its share of them)")
        return p.get_default("subcommands")[name]

    from prep.render.bench import RenderBenchConfig
    from prep.render.frame import SPP

    from kpcn_keras.config import (PIXEL, SLOPE, TILE, CompareConfig, CompositorConfig, ModelConfig, ResampleConfig,
                                   ResampleStudyConfig, TrainConfig)

    r = parser("render", (RenderConfig,), {"spp": SPP}, help="render a built-in scene set (noisy inputs + references), or one scene file, to EXR")
    d = lambda name: f"(default: {_default(RenderConfig, name)})"  # noqa: E731
    r.add_argument("--set", dest="set_name", help=f"render set name, a folder under --out {d('set_name')}")
    r.add_argument("--families", type=_csv, help=f"comma-separated scene families {d('families')}")
    r.add_argument("--per-family", type=int, help=f"random permutations per family {d('per_family')}")
    r.add_argument("--width", type=int, help=d("width"))
    r.add_argument("--height", type=int, help=d("height"))
    r.add_argument("--input-spp", type=_csv_ints, help=f"comma-separated input sample counts {d('input_spp')}")
    r.add_argument("--reference-spp", type=int, help=d("reference_spp"))
    r.add_argument("--seed", type=int, help=d("seed"))
    r.add_argument("--out", dest="out_root", help=f"folder holding render sets {d('out_root')}; with --scene: "
                   "the EXR (default: <scene file stem>-<spp>spp.exr beside the scene file)")
    r.add_argument("--scene", help="render this scene file (.toml or .json; see README, 'Scene files') instead "
                   "of a set; --spp, --seed, --width, --height override its [render] table")
    r.add_argument("--spp", type=int, help="with --scene: samples per pixel (default: the file's)")
    r.add_argument("--no-png", action="store_true", help="with --scene: no tonemapped PNG beside the EXR")
    _part_option(r, "renders")
    r.set_defaults(func=cmd_render)

    s = parser("shards", (ShardConfig,), help="cut 65x65 patches of a render folder into HDF5 shards")
    d = lambda name: f"(default: {_default(ShardConfig, name)})"  # noqa: E731
    s.add_argument("--set", dest="set_name", help=f"render set to read and shard set to write {d('set_name')}")
    s.add_argument("--renders", dest="render_root", help=f"folder holding render sets {d('render_root')}")
    s.add_argument("--out", dest="out_root", help=f"folder holding shard sets {d('out_root')}")
    s.add_argument("--patch-size", type=int, help=d("patch_size"))
    s.add_argument("--patches-per-image", type=int, help=f"at most the patch positions of the smallest image {d('patches_per_image')}")
    s.add_argument("--patches-per-shard", type=int, help=d("patches_per_shard"))
    s.add_argument("--val-fraction", type=float, help=f"scenes held out per family {d('val_fraction')}")
    s.add_argument("--val-scenes", type=_csv, help="explicit held-out scenes (comma-separated)")
    s.add_argument("--input-spp", type=int, help="use only inputs of this spp (default: every input)")
    s.add_argument("--seed", type=int, help=d("seed"))
    _part_option(s, "shards")
    s.set_defaults(func=cmd_shards)

    from kpcn_keras.config import DEFAULT_SLOPES, DEFAULT_TILE, PRESETS

    t = parser("train", (TrainConfig, ModelConfig, CompositorConfig), help="train a denoiser in phases: branches, joint fine-tuning, compositor (resumes by itself)")
    d = lambda name: f"(default: {_default(TrainConfig, name)})"  # noqa: E731
    t.add_argument("--set", dest="set_name", help=f"shard set {d('set_name')}")
    t.add_argument("--shards", dest="shards_root", help=f"folder holding shard sets {d('shards_root')}")
    _run_option(t, default="runs/default", help="run folder, created or resumed (default: runs/default)")
    t.add_argument("--preset", help=f"{', '.join(PRESETS)} {d('preset')}; the options below override it")
    g = t.add_argument_group("network (each branch, or the shared one)")
    g.add_argument("--arch", help="kpcn (Bako's plain stack), kpal (residual, batch norm) or dpcn (direct prediction)")
    g.add_argument("--width", type=int, help="filters per convolution")
    g.add_argument("--depth", type=int, help="convolutions (kpcn, dpcn) or residual blocks (kpal)")
    g.add_argument("--conv-size", type=int, help="convolution size (odd)")
    g.add_argument("--kernel-size", type=int, help="predicted kernel side (odd; the papers use 21)")
    g.add_argument("--dropout", type=float, help="drop rate after every convolution (the report's keep 0.7 is 0.3)")
    g.add_argument("--shared", action="store_true", help="one network for both branches, told apart by a one-hot "
                   "input (default: one network per branch)")
    g = t.add_argument_group("phases")
    g.add_argument("--branches", type=_csv, help=f"comma-separated subset of diffuse,specular {d('branches')}")
    g.add_argument("--steps", type=int, help=f"training steps per branch {d('steps')}")
    g.add_argument("--joint-steps", type=int, help=f"joint fine-tuning steps on the final colour, 0 for none {d('joint_steps')}")
    g.add_argument("--joint-lr", dest="joint_learning_rate", type=float, help=d("joint_learning_rate"))
    g.add_argument("--compositor", help="alpha or kernel: add the multiscale compositor phase (default: none)")
    g.add_argument("--compositor-steps", type=int, help=d("compositor_steps"))
    g.add_argument("--compositor-lr", dest="compositor_learning_rate", type=float, help=d("compositor_learning_rate"))
    g.add_argument("--gamma", type=float, help=f"weight of the compositor's α regulariser "
                   f"(default: {_default(CompositorConfig, 'gamma')})")
    g = t.add_argument_group("optimisation")
    g.add_argument("--batch-size", type=int, help=d("batch_size"))
    g.add_argument("--lr", dest="learning_rate", type=float, help=f"initial learning rate {d('learning_rate')}")
    g.add_argument("--decay-steps", type=int, help=f"steps per decay of the learning rate by --decay-rate {d('decay_steps')}")
    g.add_argument("--decay-rate", type=float, help=d("decay_rate"))
    g.add_argument("--clipnorm", type=float, help=f"gradient norm clip {d('clipnorm')}")
    g.add_argument("--loss", help=f"smape or asymmetric {d('loss')}")
    g.add_argument("--slope", type=float, help=f"asymmetric loss slope λ {d('slope')}")
    g.add_argument("--slope-input", action="store_true", help="λ as an input channel: one network for every λ "
                   "in --slope-range, chosen at 'kpcn denoise --slope'")
    g.add_argument("--slope-range", type=_csv_floats, help=f"low,high {d('slope_range')}")
    g.add_argument("--no-augment", dest="augment", action="store_false", help="no flips, rotations or colour "
                   "permutations of the training patches")
    g.add_argument("--seed", type=int, help=d("seed"))
    t.set_defaults(func=cmd_train)

    m = parser("resample", (ResampleConfig,), help="error-based resampling rounds: new patches where the run's denoiser errs, "
               "then more training on every round (resumes by itself)")
    d = lambda name: f"(default: {_default(ResampleConfig, name)})"  # noqa: E731
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
    m.set_defaults(func=cmd_resample)

    n = parser("denoise", own={"tile": TILE, "slope": SLOPE}, help="denoise EXRs in the AOV layout: files, or every render in a folder, in one process")
    n.add_argument("inputs", nargs="+", metavar="input", help="EXR files and folders (a folder: every *.exr in it "
                   "but earlier *-denoised.exr outputs)")
    _run_option(n, required=True, help="a run folder that finished training (kpcn train)")
    n.add_argument("-o", "--output", default=None, help="output EXR, or a folder for <input stem>-denoised.exr "
                   "(a folder with several inputs; default: beside each input)")
    n.add_argument("--reference", default=None, help="reference EXR of a single input: prints MSE, relMSE, SMAPE, "
                   "DSSIM, PSNR")
    n.add_argument("--tile", type=int, help=f"tile size in pixels, bounds memory (default: {DEFAULT_TILE})")
    n.add_argument("--slope", type=float, help="λ, for a run trained with --slope-input: higher keeps more of the "
                   "input's detail (and noise)")
    n.add_argument("--no-png", action="store_true", default=False)
    n.set_defaults(func=cmd_denoise)

    e = parser("evaluate", own={"tile": TILE}, help="compare a run with the raw input and NLM on held-out scenes")
    _run_option(e, required=True)
    e.add_argument("inputs", nargs="*", default=[], help="noisy renders (default: the run's held-out scenes); "
                   "each reference is the same scene's render with the most samples in the same folder")
    e.add_argument("--out", default=None, help="report folder (default: <run>/eval)")
    e.add_argument("--tile", type=int, help=f"tile size in pixels (default: {DEFAULT_TILE})")
    e.add_argument("--no-baseline", action="store_true", default=False)
    e.set_defaults(func=cmd_evaluate)

    f = parser("figures", own={"tile": TILE, "slopes": SLOPE, "pixel": PIXEL}, own_distinct=("slopes",), help="draw the report's figures from a run: kernels, α maps, with and without "
               "multiscale, a λ sweep (into <run>/figures)")
    _run_option(f, required=True)
    f.add_argument("input", nargs="?", default=None, help="noisy render (default: the run's first held-out scene "
                   "at its lowest spp); its reference is the same scene's render with the most samples beside it")
    f.add_argument("--pixel", type=_csv_ints, help="y,x of the kernel figure's pixel (default: the noisiest)")
    slopes = ",".join(f"{s:g}" for s in DEFAULT_SLOPES)
    f.add_argument("--slopes", type=_csv_floats, help=f"the λ of the sweep (default: {slopes})")
    f.add_argument("--tile", type=int, help=f"tile size in pixels (default: {DEFAULT_TILE})")
    f.set_defaults(func=cmd_figures)

    from kpcn_keras.config import BENCH_PRESETS, BenchConfig

    b = parser("bench", (BenchConfig, RenderBenchConfig), help="what accuracy costs in time: reports/accuracy_time.{md,json,png} (or, with 'render', "
               "the path tracer's samples per second: reports/render.{md,json})")
    d = lambda name: f"(default: {_default(BenchConfig, name)})"  # noqa: E731
    b.add_argument("what", nargs="?", choices=["accuracy", "render"], default="accuracy",
                   help="accuracy (the default): error against time per frame of raw Monte Carlo, our denoisers "
                   "and the baselines, equal-error spp, training cost, stage costs; render: samples per second "
                   "per scene family, specialised against all-effects kernels")
    _experiment_folders(b, d, "the bench's trained runs")
    b.add_argument("--full", action="store_true", help="the full ladder (every spp, five times the training); "
                   "default: the reduced one, under 45 minutes on a 2-core CPU")
    b.add_argument("--raw-spp", type=_csv_ints, help="raw Monte Carlo spp, comma-separated (default: the ladder's)")
    b.add_argument("--input-spp", type=_csv_ints, help="spp the denoisers get, comma-separated (default: the ladder's)")
    b.add_argument("--budget", type=float, help="training seconds of every configuration (default: the ladder's)")
    b.add_argument("--budget-fractions", type=_csv_floats, help="the presets' training-cost curve, fractions of "
                   "--budget (default: the ladder's)")
    b.add_argument("--configurations", type=_csv, help="configurations of kpcn compare to train and measure "
                   "(default: the ladder's)")
    b.add_argument("--presets", type=_csv, help=f"presets of the training-cost curve (default: {','.join(BENCH_PRESETS)})")
    b.add_argument("--large-frame", type=_csv_ints, help=f"WIDTH,HEIGHT of the frame timed against OIDN {d('large_frame')}")
    b.add_argument("--repeats", type=int, help=f"timed calls per stage cost {d('repeats')}")
    b.add_argument("--seed", type=int, help=d("seed"))
    d = lambda name: f"(default: {_default(RenderBenchConfig, name)})"  # noqa: E731
    b.add_argument("--width", type=int, help=f"bench render: {d('width')}")
    b.add_argument("--height", type=int, help=f"bench render: {d('height')}")
    b.add_argument("--spp", type=int, help=f"bench render: {d('spp')}")
    b.set_defaults(func=cmd_bench)

    c = parser("compare", (CompareConfig,), help="train every configuration for the same seconds, then compare accuracy and cost "
               "on held-out frames; writes reports/compare.{md,json,png}")
    d = lambda name: f"(default: {_default(CompareConfig, name)})"  # noqa: E731
    _experiment_folders(c, d, "the comparison's runs")
    c.add_argument("--budget", type=float, help=f"seconds of training per configuration {d('budget')}")
    c.add_argument("--configurations", type=_csv, help=f"comma-separated {d('configurations')}")
    c.add_argument("--frame", type=int, help=f"side of the crop whose inference is timed {d('frame')}")
    c.add_argument("--repeats", type=int, help=f"timed calls per row, the median is reported {d('repeats')}")
    c.add_argument("--seed", type=int, help=d("seed"))
    c.add_argument("--report-only", action="store_true", help="write compare.md and compare.png again from the "
                   "--out folder's compare.json, training and measuring nothing")
    c.set_defaults(func=cmd_compare)

    y = parser("resample-study", (ResampleStudyConfig, ResampleConfig), help="error rounds against variance sampling alone, at equal steps and equal "
               "wall time, over several seeds; writes reports/resample.{md,json,png}")
    d = lambda name: f"(default: {_default(ResampleStudyConfig, name)})"  # noqa: E731
    _experiment_folders(y, d, "the study's runs and shard copies")
    y.add_argument("--seeds", type=_csv_ints, help=f"training seeds, comma-separated {d('seeds')}")
    y.add_argument("--arms", type=_csv, help=f"comma-separated {d('arms')}")
    y.add_argument("--base-steps", type=int, help=f"steps per network of each seed's base run {d('base_steps')}")
    y.add_argument("--rounds", type=int, help=d("rounds"))
    y.add_argument("--round-steps", type=int, help=f"steps per network per round {d('round_steps')}")
    y.add_argument("--patches-per-image", type=int, help=f"new patches per training input per round {d('patches_per_image')}")
    y.add_argument("--error-weight", type=float, help="share of the error PDF in the error arm's mix (default: "
                   f"{_default(ResampleConfig, 'error_weight')})")
    y.add_argument("--metric", help=f"smape or relmse (default: {_default(ResampleConfig, 'metric')})")
    y.set_defaults(func=cmd_resample_study)
    _state_bounds(p)
    return p


def _part_option(parser: argparse.ArgumentParser, what: str) -> None:
    parser.add_argument("--part", help=f"write only part i of N of the {what} (1 <= i <= N; e.g. 1/4), the last part "
                        "to finish merging the record (default: RANK of WORLD_SIZE under torchrun, else all)")


def _experiment_folders(p: argparse.ArgumentParser, d, runs: str) -> None:
    """--set, --shards, --runs and --out of a command that trains runs of its own (compare, resample-study);
    ``d(name)`` is the help text of a field's default."""
    p.add_argument("--set", dest="set_name", help=f"shard set {d('set_name')}")
    p.add_argument("--shards", dest="shards_root", help=f"folder holding shard sets {d('shards_root')}")
    p.add_argument("--runs", dest="runs_root", help=f"folder of {runs}, reused when run again {d('runs_root')}")
    p.add_argument("--out", dest="out_dir", help=f"report folder {d('out_dir')}")


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


# the commands that divide their work between the processes torchrun starts (each its rank's share)
SPLIT_COMMANDS = ("render", "shards", "train")


def _check_launcher(command: str) -> None:
    """Refuse to run a command that does not split its work as one of several processes of a launcher:
    each would do all of it, one after the other behind the folder's lock."""
    from prep.parts import Part

    part = Part.from_environment()
    if not part.whole and command not in SPLIT_COMMANDS:
        raise KpcnError(f"kpcn {command} runs as one process, not as part {part} of a launcher's processes "
                        f"(RANK, WORLD_SIZE); only {', '.join(SPLIT_COMMANDS)} split their work: run it "
                        "without torchrun")


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="kpcn: %(message)s")
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv, args.parser = (sys.argv[1:] if argv is None else list(argv)), parser
    args.flags = _flags(parser, args.command)
    try:
        from prep.threads import set_threads

        set_threads(getattr(args, "threads", None))
        _check_launcher(args.command)
        _check_own_bounds(args)
        return args.func(args)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        message = str(exc)
        if isinstance(exc, OptionError):
            flag = args.flags.get(exc.option)
            if flag:
                message = f"{flag} {exc.detail}"
        print(f"kpcn {args.command}: error: {message}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"kpcn {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
