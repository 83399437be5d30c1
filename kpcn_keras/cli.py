"""``kpcn``: the command line of the toolkit.

Subcommands: render, references, render-cycles, cycles-validation, import-renders, shards, train, resample, denoise,
adapt, evaluate, ship, figures, bench, compare, resample-study, inputs-study, quality, aux-study: one ``cmd_*``
function each (:data:`COMMANDS`). Each fills its stage's config dataclass from the options the user gave; an option
left out takes the dataclass's default. The parser, which never retypes a default or a bound, is
:mod:`kpcn_keras.parser`; the few options no dataclass holds (``--slope``, ``--port``, ...) are checked against
their bounds before the command starts. The inference settings (``--tile``, ``--precision``, ``--ensemble``) travel
as one ``InferenceSettings``, the model as one ``Run``, each made once here.
``render``, ``references``, ``render-cycles``, ``cycles-validation``, ``import-renders``, ``shards``, ``bench render``
and ``figures --set`` never import keras or torch.

Errors: a :class:`prep.errors.KpcnError` (bad input, a bad option, a folder in the wrong state) ends with
one line naming the file, layer or option, and exit status 2; an option is named by its flag. Anything
else is a bug and keeps its traceback. ``KPCN_DEBUG=1`` shows the traceback of a KpcnError too.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import sys

from kpcn_keras import oidn_args, onnx_cli
from kpcn_keras.parser import (
    DATA_INVARIANT,
    _check_own_bounds,
    _command_line,
    _flags,
    _given,
    adapt_settings,
    build_parser,
    inference_settings,
)
from kpcn_keras.version import version_text
from prep.errors import KpcnError, OptionError

# The exit status of a KpcnError; argparse uses the same for a malformed command line.
EXIT_USER_ERROR = 2


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

    shared = {"width", "height", "seed", "out_root", "pair"}  # the options that also mean something with --scene
    for dest in sorted({f.name for f in dataclasses.fields(RenderConfig)} - shared | {"part"}):
        if dest in args:
            raise OptionError(dest, "is for a built-in scene set, not for --scene FILE (use --spp)")
    part = Part.from_environment()
    if not part.whole:
        raise KpcnError(f"kpcn render --scene renders one file, as one process, not as part {part} of a "
                        "launcher's processes: run it without torchrun")
    overrides = {k: getattr(args, k) for k in ("spp", "seed", "width", "height") if k in args}
    report = render_scene_file(args.scene, getattr(args, "out_root", None), overrides=overrides,
                               png="no_png" not in args, pair="pair" in args)
    if "outputs" in report:  # --pair: the frame's two halves
        print("wrote " + " and ".join(map(str, report["outputs"])))
    else:
        print(f"wrote {report['output']}" + (f" and {report['png']}" if "png" in report else ""))
    print(f"rendered in {report['seconds']:.2f} s")
    return 0


def cmd_references(args) -> int:
    from prep.render import RenderConfig
    from prep.render.renderset import CONVERGENCE_REPORT, convergence_markdown, convergence_report

    cfg = RenderConfig(**_given(args, RenderConfig))
    report = convergence_report(cfg, progress=not args.quiet)
    print(convergence_markdown(report), end="")
    print("wrote " + ", ".join(f"{cfg.out_root}/{cfg.set_name}/{name}" for name in CONVERGENCE_REPORT))
    return 0


def cmd_render_cycles(args) -> int:
    from prep.render.cycles import CyclesConfig, manifest_summary, render_cycles

    cfg = CyclesConfig(out=args.out, **_given(args, CyclesConfig))
    out = render_cycles(cfg)
    print(manifest_summary(out))
    print(f"frames in {out}; kpcn import-renders {out} --set NAME makes them a render set")
    return 0


def cmd_cycles_validation(args) -> int:
    from prep.render.cycles import ValidationConfig, manifest_summary, render_validation, verify_validation

    cfg = ValidationConfig(out=args.out, **_given(args, ValidationConfig))
    if cfg.verify:
        print(verify_validation(cfg.out))
        return 0
    out = render_validation(cfg)
    print(manifest_summary(out))
    print(verify_validation(out))
    return 0


def cmd_blend_pair(args) -> int:
    from prep.render.blendpair import BlendPairConfig, render_blend_pair

    cfg = BlendPairConfig(blend=args.blend, **_given(args, BlendPairConfig))
    a, b = render_blend_pair(cfg)
    print(f"kpcn denoise {a} --pair {b} denoises their mean")
    return 0


def cmd_import_renders(args) -> int:
    from prep.imported import import_renders
    from prep.render.renderset import RENDER_ROOT, RenderSet

    render_set = RenderSet(args.set_name, getattr(args, "render_root", RENDER_ROOT))
    files = import_renders(args.src, render_set)
    print(f"{len(files)} renders in {render_set.dir}")
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
    # the compositor's own options (its width and depth are not the network's --width and --depth; its
    # kernel_size is --compositor-kernel, not the network's --kernel-size)
    compositor = {k: getattr(args, k) for k in ("gamma", "downsample", "scale_supervision") if k in args}
    if "compositor_kernel" in args:
        compositor["kernel_size"] = args.compositor_kernel
        if args.__dict__.get("compositor") != "kernel":
            raise OptionError("compositor_kernel", "is the kernel-predicting compositor's kernel side: it needs "
                              "--compositor kernel")
    for name in compositor:
        if "compositor" not in args:
            raise OptionError(name, "is a setting of the multiscale compositor: it needs --compositor alpha|kernel")
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
    from kpcn_keras.run import Run

    cfg = ResampleConfig(**_given(args, ResampleConfig))
    loop = resample(cfg, Run(args.run), verbose=0 if args.quiet else "auto", progress=not args.quiet,
                    command=_command_line(args, DATA_INVARIANT))
    print(f"{len(loop['rounds'])} rounds; records: {os.path.join(args.run, 'resample', 'rounds.json')}")
    return 0


def _model(args):
    """The ``Run`` of ``--run``, else the model ``kpcn denoise`` uses by default (``run.default_model``)."""
    from kpcn_keras.run import Run, default_model

    return Run(args.run) if "run" in args else default_model()


def cmd_denoise(args) -> int:
    from kpcn_keras.batch import ReadOptions, denoise_files

    def frame(report):
        print(f"wrote {report.output}" + (f" and {report.png}" if report.png is not None else "")
              + f" ({report.layout} layout, {report.inputs}, model {report.model}; "
              f"{report.seconds * 1000:.0f} ms denoising, {report.frame_s * 1000:.0f} ms with files)")

    settings, adapt = inference_settings(args), adapt_settings(args)
    reading = ReadOptions(layout=args.layout, pair=args.pair, albedo=args.albedo, normal=args.normal,
                          view_layer=args.view_layer)
    with _AdaptBar(adapt, args.quiet) as bar:
        batch = denoise_files(args.inputs, _model(args), args.output, args.reference, settings=settings,
                              reading=reading, png=args.png, slope=getattr(args, "slope", None),
                              slope_map=getattr(args, "slope_map", None), on_frame=frame, adapt=adapt, on_adapt=bar)
    frames = batch.frames
    for report in frames:
        if report.adaptation is not None:
            print(report.adaptation.line())
    if batch.skipped:
        print(f"skipped {len(batch.skipped)} earlier outputs or temporaries: {', '.join(batch.skipped)}")
    startup = "?" if batch.startup_s is None else f"{batch.startup_s:.2f} s"
    print(f"start-up {startup}, model load {batch.load_s:.2f} s, warm-up {batch.warmup_s:.2f} s "
          f"({batch.threads} thread{'s' if batch.threads != 1 else ''}, {batch.precision}"
          + (f", an ensemble of {batch.ensemble}" if batch.ensemble > 1 else "") + ")")
    if batch.peak_memory_mb is not None:
        print(f"peak memory {batch.peak_memory_mb:.0f} MiB")
    per_frame = sorted(f.seconds for f in frames)[len(frames) // 2]
    print(f"denoised {len(frames)} frame{'s' if len(frames) > 1 else ''} in {sum(f.seconds for f in frames):.2f} s"
          + (f" (median {per_frame * 1000:.0f} ms a frame)" if len(frames) > 1 else ""))
    report = frames[0]
    if report.metrics is not None:
        print(f"{'':10s} " + " ".join(f"{m:>10s}" for m in report.metrics))
        for label, measured in (("input", report.input_metrics), ("denoised", report.metrics)):
            print(f"{label:10s} " + " ".join(f"{v:10.5f}" for v in measured.values()))
    return 0


class _AdaptBar:
    """The progress of an adaptation (``AdaptSettings``: steps, or seconds), with the self-supervised loss; a
    callable ``(step, loss, seconds)``; nothing where ``adapt`` is None or ``quiet``. The bar appears at the first
    step, so that a pair refused before training is its one line alone."""

    def __init__(self, adapt, quiet: bool):
        self.adapt, self.quiet, self.bar = adapt, quiet, None

    def __enter__(self):
        return self

    def _open(self):
        from tqdm import tqdm

        steps = self.adapt.steps
        return tqdm(total=steps if steps is not None else self.adapt.seconds, desc="adapting",
                    unit="step" if steps is not None else "s", bar_format="{l_bar}{bar}| {n:.0f}/{total:.0f} "
                    "{unit} [{elapsed}<{remaining}{postfix}]")

    def __call__(self, step: int, loss: float, seconds: float) -> None:
        if self.bar is None and self.adapt is not None and not self.quiet:
            self.bar = self._open()
        if self.bar is not None:
            self.bar.n = step if self.adapt.steps is not None else min(seconds, self.adapt.seconds)
            self.bar.set_postfix(step=step, loss=f"{loss:.4g}", refresh=False)
            self.bar.refresh()

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.close()


def cmd_adapt(args) -> int:
    from kpcn_keras.batch import ReadOptions, adapt_shot, shot_pairs

    adapt = adapt_settings(args)
    pairs = shot_pairs(args.frames, getattr(args, "pairs", None))
    reading = ReadOptions(layout=args.layout, view_layer=args.view_layer)
    with _AdaptBar(adapt, args.quiet) as bar:
        outcome, out = adapt_shot(pairs, _model(args), args.out, settings=inference_settings(args), adapt=adapt,
                                  reading=reading, progress=bar)
    print(outcome.line())
    print(f"wrote {out} ({len(pairs)} frame{'s' if len(pairs) > 1 else ''}; "
          + ("denoise with --run " + str(out) if outcome.kept else "it serves as the model it came from") + ")")
    return 0


def cmd_view(args) -> int:
    from kpcn_keras.batch import ReadOptions
    from kpcn_keras.viewer import ViewSession, listen, serve

    settings = inference_settings(args)
    httpd = listen(**{k: getattr(args, k) for k in ("port",) if k in args})
    try:
        reading = ReadOptions(layout=args.layout, view_layer=args.view_layer, pair=args.pair)
        session = ViewSession.open(args.frame, _model(args), args.reference, reading=reading,
                                   slope=getattr(args, "slope", None), settings=settings)
    except BaseException:
        httpd.server_close()
        raise
    return serve(httpd, session)


def cmd_evaluate(args) -> int:
    from kpcn_keras.batch import ReadOptions
    from kpcn_keras.evaluate import evaluate, format_table, pairs_for_inputs
    from kpcn_keras.run import Run

    settings = inference_settings(args)
    pairs = pairs_for_inputs(args.inputs) if args.inputs else None
    rows = evaluate(Run(args.run), pairs, out_dir=args.out, settings=settings, baseline=not args.no_baseline,
                    reading=ReadOptions(layout=args.layout, view_layer=args.view_layer),
                    slope=getattr(args, "slope", None))
    print(format_table(rows))
    print(f"report: {args.out or Run(args.run).for_quality(settings.quality).eval_dir}/report.md")
    return 0


def cmd_mix_oidn(args) -> int:
    from kpcn_keras.evaluate import pairs_for_inputs
    from kpcn_keras.oidn_mix_fit import fit_run
    from kpcn_keras.run import Run

    fit_run(Run(args.run), pairs_for_inputs(args.inputs))
    return 0


def cmd_ship(args) -> int:
    from kpcn_keras.card import ship
    from kpcn_keras.run import Run

    if "speed_frame" in args and len(args.speed_frame) != 2:
        raise OptionError("speed_frame", f"must be WIDTH,HEIGHT, got {list(args.speed_frame)}")
    modes = {}
    for mode, run in getattr(args, "mode", ()):
        if mode in modes:
            raise OptionError("mode", f"names the {mode} mode twice ({modes[mode].dir} and {run}); give each once")
        modes[mode] = Run(run)
    shipped = ship(Run(args.run), args.out, _command_line(args, DATA_INVARIANT),
                   **{k: tuple(getattr(args, k)) for k in ("speed_frame",) if k in args}, modes=modes)
    size = sum(f.stat().st_size for f in shipped.dir.rglob("*") if f.is_file())
    print(f"shipped {args.run} to {shipped.dir} ({size / 2**20:.1f} MiB); its card: {shipped.card_path}")
    return 0


def cmd_figures(args) -> int:
    settings = inference_settings(args)
    if "run" not in args:
        return cmd_shard_set_figures(args)
    shard_set = [dest for dest in ("set_name", "shards_root") if dest in args]
    if shard_set:
        raise OptionError(shard_set[0], "is for the figures of a shard set alone: a run's figures are drawn from "
                          "its own shard set; leave out --run or this option")
    from kpcn_keras.evaluate import pairs_for_inputs
    from kpcn_keras.figures import make_figures
    from kpcn_keras.run import Run

    frame = pairs_for_inputs([args.input])[0] if args.input else None
    if "pixel" in args and len(args.pixel) != 2:
        raise OptionError("pixel", f"must be two integers y,x, got {','.join(map(str, args.pixel))}")
    written = make_figures(Run(args.run), frame, settings=settings,
                           **{k: getattr(args, k) for k in ("pixel", "slopes") if k in args})
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0


def cmd_shard_set_figures(args) -> int:
    """``kpcn figures --set NAME``: the data figures of a shard set (prep.figures), no keras nor torch."""
    from prep.figures import shard_set_figures
    from prep.shards import ShardConfig

    if "set_name" not in args and "shards_root" not in args:
        raise KpcnError("give --run RUN (a run's figures) or --set NAME (a shard set's sampling and input figures)")
    for dest in ("pixel", "slopes", "tile"):
        if dest in args:
            raise OptionError(dest, "is an option of a run's figures: it needs --run")
    written = shard_set_figures(getattr(args, "shards_root", ShardConfig.out_root),
                                getattr(args, "set_name", ShardConfig.set_name), args.input)
    for name, path in written.items():
        print(f"{name}: {path}")
    return 0


def cmd_bench(args) -> int:
    from kpcn_keras.studies.config import BenchConfig
    from kpcn_keras.studies.render_bench import RenderBenchConfig

    # an option of one bench that the other does not have (both have --out and --repeats)
    render_only, accuracy_only = ({f.name for f in dataclasses.fields(a)} - {f.name for f in dataclasses.fields(b)}
                                  for a, b in ((RenderBenchConfig, BenchConfig), (BenchConfig, RenderBenchConfig)))
    if args.what == "render":
        from kpcn_keras.studies.render_bench import bench_render, format_report

        for dest in sorted(d for d in accuracy_only if d in args):
            raise OptionError(dest, "is an option of 'kpcn bench' (accuracy against time), not of 'kpcn bench render'")
        cfg = RenderBenchConfig(**_given(args, RenderBenchConfig))
        record = bench_render(cfg, progress=not args.quiet)
        print(format_report(record))
        print(f"report: {cfg.out_dir}/render.md")
        return 0
    from kpcn_keras.studies.bench import REPORT, bench

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


def _study(args, config_class, study, rewrite_reports, format_report, report: str) -> int:
    """A study that trains runs of its own and writes ``<out_dir>/<report>.md``, or with ``--report-only``
    writes its reports again from their JSON."""
    cfg = config_class(**_given(args, config_class))
    if getattr(args, "report_only", False):  # a flag left out is absent: the parser suppresses defaults
        record = rewrite_reports(cfg.out_dir)
    else:
        record = study(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto")
    print(format_report(record))
    print(f"report: {cfg.out_dir}/{report}.md")
    return 0


def cmd_compare(args) -> int:
    from kpcn_keras.studies import compare
    from kpcn_keras.studies.config import CompareConfig

    return _study(args, CompareConfig, compare.compare, compare.rewrite_reports, compare.format_report,
                  compare.REPORT)


def cmd_resample_study(args) -> int:
    from kpcn_keras.studies.config import ResampleStudyConfig
    from kpcn_keras.studies.resample_study import format_report, study

    cfg = ResampleStudyConfig(**_given(args, ResampleStudyConfig))
    record = study(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto",
                   progress=not args.quiet)
    print(format_report(record))
    print(f"report: {cfg.out_dir}/resample.md")
    return 0


def cmd_inputs_study(args) -> int:
    from kpcn_keras.studies.config import InputsStudyConfig
    from kpcn_keras.studies.inputs_study import format_report, study

    cfg = InputsStudyConfig(**_given(args, InputsStudyConfig))
    record = study(cfg, command=_command_line(args), verbose=0 if args.quiet else "auto")
    print(format_report(record))
    print(f"report: {cfg.out_dir}/inputs.md")
    return 0


def cmd_quality(args) -> int:
    from kpcn_keras.studies import quality, quality_report
    from kpcn_keras.studies.config import QualityConfig

    if getattr(args, "measure_model", False):
        cfg = QualityConfig(**_given(args, QualityConfig))
        record = quality.add_model(cfg, command=_command_line(args))
        print(quality_report.format_report(record))
        print(f"report: {cfg.out_dir}/{quality_report.REPORT}.md")
        return 0
    return _study(args, QualityConfig, quality.quality, quality_report.rewrite_reports, quality_report.format_report,
                  quality_report.REPORT)


def cmd_aux_study(args) -> int:
    from kpcn_keras.studies import aux_study

    aux_study.study(args.frames, args.model, args.out, record_path=args.blender_record,
                    command=_command_line(args), log=(lambda _: None) if args.quiet else print)
    print(f"report: {args.out}/{aux_study.REPORT}.md, .json and .png")
    return 0


# the subcommand -> its function (the parser, kpcn_keras.parser, builds the same names)
COMMANDS = {
    "render": cmd_render,
    "references": cmd_references,
    "render-cycles": cmd_render_cycles,
    "cycles-validation": cmd_cycles_validation,
    "blend-pair": cmd_blend_pair,
    "import-renders": cmd_import_renders,
    "shards": cmd_shards,
    "train": cmd_train,
    "resample": cmd_resample,
    "denoise": cmd_denoise,
    "adapt": cmd_adapt,
    "view": cmd_view,
    "evaluate": cmd_evaluate,
    "mix-oidn": cmd_mix_oidn,
    "ship": cmd_ship,
    "export": onnx_cli.cmd_export,
    "figures": cmd_figures,
    "bench": cmd_bench,
    "compare": cmd_compare,
    "resample-study": cmd_resample_study,
    "inputs-study": cmd_inputs_study,
    "quality": cmd_quality,
    "aux-study": cmd_aux_study,
}

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


def _user_error(command: str, message: str) -> int:
    print(f"kpcn {command}: error: {message}", file=sys.stderr)
    return EXIT_USER_ERROR


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="kpcn: %(message)s")
    argv = sys.argv[1:] if argv is None else list(argv)
    if oidn_args.applies(argv):  # oidnDenoise's options: run as kpcn denoise's own (kpcn_keras/oidn_args.py)
        try:
            return oidn_args.run(argv, main)
        except KpcnError as exc:
            if os.environ.get("KPCN_DEBUG"):
                raise
            return _user_error("denoise", str(exc))
    if [a for a in argv if a not in ("-q", "--quiet")] == ["--version"]:  # what the Blender add-on's Check runs
        print(version_text())
        return 0
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv, args.parser = argv, parser
    args.flags = _flags(parser, args.command)
    try:
        from prep.processes import keep_freed_memory
        from prep.threads import set_threads

        keep_freed_memory()
        set_threads(getattr(args, "threads", None))
        _check_launcher(args.command)
        _check_own_bounds(args)
        return COMMANDS[args.command](args)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        message = str(exc)
        if isinstance(exc, OptionError):
            flag = args.flags.get(exc.option)
            if flag:
                message = f"{flag} {exc.detail}"
        return _user_error(args.command, message)
    except KeyboardInterrupt:
        print(f"kpcn {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
