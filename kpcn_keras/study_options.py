"""The options of the lab's commands (``kpcn bench``, ``compare``, ``resample-study``, ``inputs-study``, ``quality``,
``aux-study``): each builder adds one subcommand through ``add`` (:func:`kpcn_keras.parser.build_parser`)."""

from __future__ import annotations

from kpcn_keras.options import csv, csv_floats, csv_ints, default, defaults, experiment_folders


def _bench_options(add) -> None:
    """The options of ``kpcn bench`` and of ``kpcn bench render``."""
    from kpcn_keras.studies.config import BENCH_PRESETS, BenchConfig
    from kpcn_keras.studies.render_bench import RenderBenchConfig

    b = add("bench", (BenchConfig, RenderBenchConfig), help="what accuracy costs in time: "
               "reports/accuracy_time.{md,json,png} (or, with 'render', the path tracer's samples per second: "
               "reports/render.{md,json})")
    d = defaults(BenchConfig)
    b.add_argument("what", nargs="?", choices=["accuracy", "render"], default="accuracy",
                   help="accuracy (the default): error against time per frame of raw Monte Carlo, our denoisers "
                   "and the baselines, equal-error spp, training cost, stage costs; render: samples per second "
                   "per scene family, specialised against all-effects kernels")
    experiment_folders(b, d, "the bench's trained runs")
    b.add_argument("--full", action="store_true", help="the full ladder (every spp, five times the training); "
                   "default: the reduced one, under 45 minutes on a 2-core CPU")
    b.add_argument("--raw-spp", type=csv_ints, help="raw Monte Carlo spp, comma-separated (default: the ladder's)")
    b.add_argument("--input-spp", type=csv_ints, help="spp the denoisers get, comma-separated (default: the ladder's)")
    b.add_argument("--budget", type=float, help="training seconds of every configuration (default: the ladder's)")
    b.add_argument("--budget-fractions", type=csv_floats, help="the presets' training-cost curve, fractions of "
                   "--budget (default: the ladder's)")
    b.add_argument("--configurations", type=csv, help="configurations of kpcn compare to train and measure "
                   "(default: the ladder's)")
    b.add_argument("--presets", type=csv, help="presets of the training-cost curve (default: "
                   f"{','.join(BENCH_PRESETS)})")
    b.add_argument("--large-frame", type=csv_ints, help="WIDTH,HEIGHT of the frame timed against OIDN "
                   f"{d('large_frame')}")
    b.add_argument("--repeats", type=int, help=f"timed calls per stage cost {d('repeats')}")
    b.add_argument("--seed", type=int, help=d("seed"))
    d = defaults(RenderBenchConfig)
    b.add_argument("--families", type=csv, help=f"bench render: comma-separated scene families {d('families')}")
    b.add_argument("--width", type=int, help=f"bench render: {d('width')}")
    b.add_argument("--height", type=int, help=f"bench render: {d('height')}")
    b.add_argument("--spp", type=int, help=f"bench render: {d('spp')}")


def _compare_options(add) -> None:
    """The options of ``kpcn compare``."""
    from kpcn_keras.studies.config import CompareConfig

    c = add("compare", (CompareConfig,), help="train every configuration for the same seconds, then compare accuracy "
               "and cost on held-out frames; writes reports/compare.{md,json,png}")
    d = defaults(CompareConfig)
    experiment_folders(c, d, "the comparison's runs")
    c.add_argument("--budget", type=float, help=f"seconds of training per configuration {d('budget')}")
    c.add_argument("--configurations", type=csv, help=f"comma-separated {d('configurations')}")
    c.add_argument("--frame", type=int, help=f"side of the crop whose inference is timed {d('frame')}")
    c.add_argument("--repeats", type=int, help=f"timed calls per row, the median is reported {d('repeats')}")
    c.add_argument("--seed", type=int, help=d("seed"))
    c.add_argument("--report-only", action="store_true", help="write compare.md and compare.png again from the "
                   "--out folder's compare.json, training and measuring nothing")


def _resample_study_options(add) -> None:
    """The options of ``kpcn resample-study``."""
    from kpcn_keras.config import ResampleConfig
    from kpcn_keras.studies.config import ResampleStudyConfig

    y = add("resample-study", (ResampleStudyConfig, ResampleConfig), help="error rounds against variance sampling "
               "alone, at equal steps and equal wall time, over several seeds; writes reports/resample.{md,json,png}")
    d = defaults(ResampleStudyConfig)
    experiment_folders(y, d, "the study's runs and shard copies")
    y.add_argument("--seeds", type=csv_ints, help=f"training seeds, comma-separated {d('seeds')}")
    y.add_argument("--arms", type=csv, help=f"comma-separated {d('arms')}")
    y.add_argument("--base-steps", type=int, help=f"steps per network of each seed's base run {d('base_steps')}")
    y.add_argument("--rounds", type=int, help=d("rounds"))
    y.add_argument("--round-steps", type=int, help=f"steps per network per round {d('round_steps')}")
    y.add_argument("--patches-per-image", type=int, help="new patches per training input per round "
                   f"{d('patches_per_image')}")
    y.add_argument("--error-weight", type=float, help="share of the error PDF in the error arm's mix (default: "
                   f"{default(ResampleConfig, 'error_weight')})")
    y.add_argument("--metric", help=f"smape or relmse (default: {default(ResampleConfig, 'metric')})")


def _inputs_study_options(add) -> None:
    """The options of ``kpcn inputs-study``."""
    from kpcn_keras.studies.config import InputsStudyConfig

    s = add("inputs-study", (InputsStudyConfig,), help="a network per input set for the same seconds, measured on "
            "held-out frames and on other renderers' frames beside OIDN and Blender; writes "
            "reports/inputs.{md,json,png}")
    d = defaults(InputsStudyConfig)
    experiment_folders(s, d, "the study's runs")
    s.add_argument("--renders", dest="render_root", help=f"folder holding render sets {d('render_root')}")
    s.add_argument("--frames", nargs="+", help="other renderers' frames: files or folders, each noisy frame with its "
                   f"reference beside it {d('frames')}")
    s.add_argument("--pairs", nargs="+", help="folders of two renders of a frame, <scene>-<spp>spp-pair-a.exr and "
                   "-pair-b.exr, with the scene's reference (kpcn cycles-validation's folder, python -m "
                   "kpcn_keras.studies.render_blender_pairs; default: none)")
    s.add_argument("--budget", type=float, help=f"seconds of training per input set {d('budget')}")
    s.add_argument("--preset", help=f"training preset of every run {d('preset')}")
    s.add_argument("--seed", type=int, help=d("seed"))


def _quality_options(add) -> None:
    """The options of ``kpcn quality``."""
    from kpcn_keras.studies.config import QualityConfig

    q = add("quality", (QualityConfig,), help="each lever for beating OIDN, alone and combined, for the same "
            "seconds, measured on held-out and validation frames beside OIDN and Blender; writes "
            "reports/quality.{md,json,png}")
    d = defaults(QualityConfig)
    experiment_folders(q, d, "the study's runs")
    q.add_argument("--renders", dest="render_root", help=f"folder holding render sets {d('render_root')}")
    q.add_argument("--levers", type=csv, help=f"comma-separated {d('levers')}")
    q.add_argument("--frames", nargs="+", help="validation frames: files or folders, each noisy frame with its "
                   f"reference beside it {d('frames')}")
    q.add_argument("--budget", type=float, help=f"seconds of training per lever, shared by its networks {d('budget')}")
    q.add_argument("--panel-spp", type=int, help=f"input spp of the validation frames in the panels {d('panel_spp')}")
    q.add_argument("--seed", type=int, help=d("seed"))
    q.add_argument("--ensemble", type=int, help="denoise every frame as a self-ensemble of this many members (as "
                   f"kpcn denoise --ensemble); the trained runs serve every value {d('ensemble')}")
    q.add_argument("--model", help="a finished run or shipped model measured beside the levers on the same frames "
                   "(default: the one kpcn denoise uses without --run, where there is one)")
    mode = q.add_mutually_exclusive_group()
    mode.add_argument("--report-only", action="store_true", help="write quality.md and quality.png again from the "
                      "--out folder's quality.json (and the frames and runs it names), training nothing")
    mode.add_argument("--measure-model", action="store_true", help="measure the model (--model, else the shipped "
                      "one) on the frames of the --out folder's quality.json, add it to the record and write the "
                      "reports again, training nothing")


def _aux_study_options(add) -> None:
    """The options of ``kpcn aux-study``."""
    a = add("aux-study", help="the shipped model (or --model) on Cycles frames with its auxiliary inputs raw, "
            "from the scene's cleanest render, OIDN-prefiltered and NLM-prefiltered, beside Blender's own "
            "denoised frame; writes reports/aux.{md,json,png}")
    a.add_argument("frames", nargs="*", default=["data/cycles/validation"], help="folders (or files) of Cycles "
                   "frames with their references (default: data/cycles/validation)")
    a.add_argument("--model", default="models/default", help="a run or model folder (default: models/default)")
    a.add_argument("--out", default="reports", help="report folder (default: reports)")
    a.add_argument("--blender-record", default="reports/blender.json", help="the Blender report's record to "
                   "check the raw variant against (default: reports/blender.json; none there: no check)")


# the lab's subcommands, in the order of ``kpcn --help``
STUDY_BUILDERS = {
    "bench": _bench_options,
    "compare": _compare_options,
    "resample-study": _resample_study_options,
    "inputs-study": _inputs_study_options,
    "quality": _quality_options,
    "aux-study": _aux_study_options,
}
