"""``kpcn``: the command line of the toolkit.

Subcommands: render, shards, train, denoise, evaluate. Each fills its stage's config dataclass from
the options; ``render`` and ``shards`` never import keras or torch. Bad input ends with a one-line
message naming the file, layer or option and exit status 2 (set KPCN_DEBUG=1 for the traceback).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

from prep.errors import KpcnError


def _csv(text: str) -> tuple[str, ...]:
    return tuple(t for t in (s.strip() for s in text.split(",")) if t)


def cmd_render(args) -> int:
    from prep.render import RenderConfig, render_set

    cfg = RenderConfig(
        set_name=args.set, families=args.families, per_family=args.per_family, width=args.width,
        height=args.height, input_spp=args.input_spp, reference_spp=args.reference_spp, seed=args.seed,
        out_root=args.out,
    )
    paths = render_set(cfg, progress=not args.quiet)
    print(f"{len(paths)} renders in {cfg.out_root}/{cfg.set_name}")
    return 0


def cmd_shards(args) -> int:
    from prep.shards import ShardConfig, build_shards

    cfg = ShardConfig(
        set_name=args.set, render_root=args.renders, out_root=args.out, patch_size=args.patch_size,
        patches_per_image=args.patches_per_image, patches_per_shard=args.patches_per_shard,
        val_fraction=args.val_fraction, val_scenes=args.val_scenes, input_spp=args.input_spp, seed=args.seed,
        command=" ".join(["kpcn"] + sys.argv[1:]),
    )
    manifest = build_shards(cfg, progress=not args.quiet)
    shards = manifest["rounds"]["round-000"]["shards"]
    for split in ("train", "val"):
        n = sum(s["patches"] for s in shards if s["split"] == split)
        print(f"{split}: {len(manifest['split'][split])} scenes, {n} patches")
    print(f"manifest: {cfg.set_dir}/manifest.json")
    return 0


def cmd_train(args) -> int:
    from kpcn_keras.train import TrainConfig, train

    run = Path(args.run)
    model = {k: v for k, v in (("arch", args.arch), ("width", args.width), ("depth", args.depth),
                                ("kernel_size", args.kernel_size)) if v is not None}
    cfg = TrainConfig.from_preset(
        args.preset, set_name=args.set, shards_root=args.shards, run=run.name, runs_root=str(run.parent),
        model=model, branches=args.branches, steps=args.steps, batch_size=args.batch_size,
        learning_rate=args.lr, loss=args.loss, slope=args.slope, seed=args.seed,
    )
    run_dir = train(cfg, verbose=0 if args.quiet else "auto")
    print(f"run: {run_dir}")
    return 0


def cmd_denoise(args) -> int:
    from kpcn_keras.denoise import denoise_file

    output = args.output or str(args.input).replace(".exr", "-denoised.exr")
    report = denoise_file(args.input, args.run, output, args.reference, png=not args.no_png, tile=args.tile)
    print(f"wrote {report['output']}" + (f" and {report['png']}" if "png" in report else ""))
    print(f"denoised in {report['seconds']:.2f} s")
    if "metrics" in report:
        print(f"{'':10s} " + " ".join(f"{m:>10s}" for m in report["metrics"]))
        for label, key in (("input", "input_metrics"), ("denoised", "metrics")):
            print(f"{label:10s} " + " ".join(f"{v:10.5f}" for v in report[key].values()))
    return 0


def cmd_evaluate(args) -> int:
    from kpcn_keras.evaluate import evaluate, format_table, pairs_for_inputs

    pairs = pairs_for_inputs(args.inputs) if args.inputs else None
    rows = evaluate(args.run, pairs, out_dir=args.out, tile=args.tile, baseline=not args.no_baseline)
    print(format_table(rows))
    print(f"report: {args.out or os.path.join(args.run, 'eval')}/report.md")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="kpcn", description="Kernel-predicting denoisers for path-traced renders.")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a built-in scene set (noisy inputs + references) to EXR")
    r.add_argument("--set", default="default", help="render set name (folder under --out)")
    r.add_argument("--families", type=_csv, default=("cornell", "spheres", "boxes"), help="comma-separated scene families")
    r.add_argument("--per-family", type=int, default=4, help="random permutations per family")
    r.add_argument("--width", type=int, default=256)
    r.add_argument("--height", type=int, default=256)
    r.add_argument("--input-spp", type=int, default=8)
    r.add_argument("--reference-spp", type=int, default=512)
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--out", default="data/renders")
    r.set_defaults(func=cmd_render)

    s = sub.add_parser("shards", help="cut 65x65 patches of a render folder into HDF5 shards")
    s.add_argument("--set", default="default", help="render set to read and shard set to write")
    s.add_argument("--renders", default="data/renders", help="folder holding render sets")
    s.add_argument("--out", default="shards")
    s.add_argument("--patch-size", type=int, default=65)
    s.add_argument("--patches-per-image", type=int, default=100)
    s.add_argument("--patches-per-shard", type=int, default=256)
    s.add_argument("--val-fraction", type=float, default=0.25, help="scenes held out per family")
    s.add_argument("--val-scenes", type=_csv, default=(), help="explicit held-out scenes (comma-separated)")
    s.add_argument("--input-spp", type=int, default=None, help="use only inputs of this spp")
    s.add_argument("--seed", type=int, default=0)
    s.set_defaults(func=cmd_shards)

    t = sub.add_parser("train", help="train the diffuse and specular networks (resumes by itself)")
    t.add_argument("--set", default="default", help="shard set")
    t.add_argument("--shards", default="shards", help="folder holding shard sets")
    t.add_argument("--run", default="runs/default", help="run folder (created, or resumed if it exists)")
    t.add_argument("--preset", default="cpu", choices=("cpu", "paper"))
    t.add_argument("--arch", choices=("kpcn", "kpal", "dpcn"))
    t.add_argument("--width", type=int)
    t.add_argument("--depth", type=int)
    t.add_argument("--kernel-size", type=int)
    t.add_argument("--branches", type=_csv, default=None, help="comma-separated subset of diffuse,specular")
    t.add_argument("--steps", type=int, help="training steps per branch")
    t.add_argument("--batch-size", type=int)
    t.add_argument("--lr", type=float, help="initial learning rate")
    t.add_argument("--loss", choices=("smape", "asymmetric"))
    t.add_argument("--slope", type=float, help="asymmetric loss slope (>= 1)")
    t.add_argument("--seed", type=int)
    t.set_defaults(func=cmd_train)

    d = sub.add_parser("denoise", help="denoise one EXR in the AOV layout")
    d.add_argument("input")
    d.add_argument("--run", required=True, help="run folder with diffuse.keras and specular.keras")
    d.add_argument("-o", "--output", help="output EXR (default: <input>-denoised.exr)")
    d.add_argument("--reference", help="reference EXR: prints MSE, relMSE, SMAPE, DSSIM, PSNR")
    d.add_argument("--tile", type=int, default=256, help="tile size in pixels (memory bound)")
    d.add_argument("--no-png", action="store_true")
    d.set_defaults(func=cmd_denoise)

    e = sub.add_parser("evaluate", help="compare a run with the raw input and NLM on held-out scenes")
    e.add_argument("--run", required=True)
    e.add_argument("inputs", nargs="*", help="noisy renders (default: the run's held-out scenes); "
                   "each reference is the same scene's render with the most samples in the same folder")
    e.add_argument("--out", help="report folder (default: <run>/eval)")
    e.add_argument("--tile", type=int, default=256)
    e.add_argument("--no-baseline", action="store_true")
    e.set_defaults(func=cmd_evaluate)
    return p


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="kpcn: %(message)s")
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (KpcnError, ValueError, FileNotFoundError) as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        print(f"kpcn {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"kpcn {args.command}: interrupted; run the same command again to resume", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
