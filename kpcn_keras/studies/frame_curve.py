"""Whole-frame error as a network trains, beside OIDN: train as long as the held-out error falls, and plot it.

A run's own learning curve (``log.csv``, ``loss.png``) is its loss on held-out *patches* of its own renders. This
is what users judge instead: relMSE of whole frames, other renderers' among them, epoch by epoch, against OIDN's on
the same frames.

``watch`` runs beside a training: every ``--every`` seconds it copies each phase's resume checkpoint
(``Run.checkpoint_path``, rewritten atomically after every epoch) into ``--into`` as
``<phase>-<epochs done>.keras`` (the epoch read from the training state inside the copy), until the run is
finished. ``measure`` then denoises each frame with every snapshot in place of its phase's network (the run's
finished network for the other branch) and with the finished run itself (under ``--patience`` its best epoch),
and writes ``<out>.json``, ``<out>.md`` and ``<out>.png`` (``report`` writes the last two again from the json).

  .venv/bin/python -m kpcn_keras.studies.frame_curve watch --run runs/model/inputs/no-variance --into DIR &
  .venv/bin/python -m kpcn_keras.studies.frame_curve measure --run runs/model/inputs/no-variance --snapshots DIR \\
      [--frames ../shared/validation/blender] [--spp 4,16,64] [--compare RUN ...] [--out reports/frame_curve]

The frames: the run's own held-out frames at ``--spp`` and every noisy render of each ``--frames`` folder (each
with its scene's highest-spp render as reference, as ``kpcn evaluate`` pairs them).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import time
from pathlib import Path

os.environ.setdefault("KERAS_BACKEND", "torch")


def watch(run_dir: Path, into: Path, every: float) -> None:
    from kpcn_keras.run import Run, read_state
    from prep.errors import KpcnError

    run = Run(run_dir)
    into.mkdir(parents=True, exist_ok=True)
    while True:
        for ckpt in sorted(run.checkpoint_dir.glob("*.keras")):
            if ckpt.stem.endswith("-best"):
                continue
            tmp = into / f".{ckpt.name}"
            try:
                shutil.copyfile(ckpt, tmp)
                state = read_state(tmp) or {}
            except (OSError, KpcnError):  # replaced as it was read: the next round copies the new one
                continue
            if "epochs_done" in state:
                tmp.replace(into / f"{state['phase']}-{int(state['epochs_done']):04d}.keras")
        try:
            run.record().finished()
            return
        except KpcnError:
            time.sleep(every)


def snapshots(folder: Path) -> dict[str, list[tuple[int, Path]]]:
    """Each phase's snapshots as (epochs done, path), in epoch order."""
    found: dict[str, list[tuple[int, Path]]] = {}
    for path in folder.glob("*-*.keras"):
        phase, _, epochs = path.stem.rpartition("-")
        found.setdefault(phase, []).append((int(epochs), path))
    return {phase: sorted(items) for phase, items in sorted(found.items())}


def measure(run_dir: Path, folder: Path, frame_folders: list[str], spp: set[int], out: Path, stride: int,
            compare: list[Path]) -> None:
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_pairs, pairs_for_inputs
    from kpcn_keras.run import Run, load_model
    from kpcn_keras.studies.compare import against
    from kpcn_keras.train import epochs_trained
    from prep import baselines, exr, layouts, metrics

    run = Run(run_dir)
    record = run.record().finished()
    held = [(a, b) for a, b in held_out_pairs(run, record) if exr.parse_render_filename(a)[1] in spp]
    pairs = [("held-out", a, b) for a, b in held] + [("validation", a, b) for a, b in pairs_for_inputs(frame_folders)]
    frames = []
    for source, noisy, ref in pairs:
        scene, frame_spp = exr.parse_render_filename(noisy)
        layers = layouts.read(noisy).layers
        reference = layouts.read(ref).layers["default"]
        oidn = (metrics.relmse(baselines.oidn_denoise(layers, mode="plain"), reference)
                if baselines.oidn_available() else None)
        frames.append({"source": source, "name": f"{Path(noisy).parent.name}/{scene} {frame_spp} spp",
                       "layers": layers, "reference": reference, "oidn": oidn})
    final = {b: run.load_component(record, b) for b in record.branches}
    steps_per_epoch = record.train.steps_per_epoch
    plans = record.data["phases"]

    def point(networks, phase, epochs, steps, of=run, of_record=record):
        denoiser = Denoiser(of, of_record, networks)
        errors = [metrics.relmse(denoiser(f["layers"])["default"], f["reference"]) for f in frames]
        row = {"phase": phase, "epochs": epochs, "steps": steps, "relmse": errors}
        for source in ("held-out", "validation"):
            mine = [(e, f["oidn"]) for e, f in zip(errors, frames) if f["source"] == source]
            row[source] = {"mean": statistics.fmean(e for e, _ in mine)}
            if all(o is not None for _, o in mine):  # judged by frames as the quality study judges them
                got = against({"frames": [{"relmse": e} for e, _ in mine]},
                              {"frames": [{"relmse": o} for _, o in mine]})
                row[source].update(below_oidn=got["lower"], of=got["frames"], median_ratio=got["median_ratio"])
        print(json.dumps({k: row[k] for k in ("phase", "epochs", "held-out", "validation")}), flush=True)
        return row

    rows, offset = [], 0
    for phase in record.branches:
        shots = snapshots(folder).get(phase, [])
        for epochs, path in shots[::stride] + ([shots[-1]] if shots and (len(shots) - 1) % stride else []):
            rows.append(point({**final, phase: load_model(path, compile=False)}, phase, epochs,
                              offset + epochs * steps_per_epoch))
        offset += epochs_trained(plans[phase]) * steps_per_epoch
    rows.append(point(final, "finished", None, offset))
    for other_dir in compare:  # another finished run of the same input set, on the same frames
        other = Run(other_dir)
        other_record = other.record().finished()
        networks = {b: other.load_component(other_record, b) for b in other_record.branches}
        steps = sum(epochs_trained(p) for p in other_record.data["phases"].values())
        steps *= other_record.train.steps_per_epoch
        rows.append(point(networks, str(other_dir), None, steps, other, other_record))

    found = {"run": str(run_dir), "snapshots": str(folder), "frames": [
        {k: f[k] for k in ("source", "name", "oidn")} for f in frames], "points": rows,
        "branches": list(record.branches), "phases": {p: plans[p] for p in record.branches},
        "steps_per_epoch": steps_per_epoch, "load_after": os.getloadavg()}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(found, indent=1))
    report(out)


def report(out: Path) -> None:
    """``<out>.md`` and ``<out>.png`` from ``<out>.json``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from kpcn_keras.train import epochs_trained

    found = json.loads(out.with_suffix(".json").read_text())
    run_dir, rows, frames, branches = found["run"], found["points"], found["frames"], found["branches"]
    lines = [f"# Whole-frame error as `{run_dir}` trains", "",
             f"`python -m kpcn_keras.studies.frame_curve measure --run {run_dir}`: relMSE of each frame with each "
             "phase's network at the epoch of a snapshot (the other branch: the run's finished network), of the "
             "finished run (its best epochs, under --patience) and of each --compare run. Steps count both phases, "
             "the diffuse phase first; OIDN: `pyoidn` on the same frames.", "",
             "| phase | epochs | steps | held-out mean relMSE | held-out below OIDN | held-out median / OIDN | "
             "validation mean relMSE | validation below OIDN | validation median / OIDN |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        cells = [r["phase"], "" if r["epochs"] is None else str(r["epochs"]), str(r["steps"])]
        for source in ("held-out", "validation"):
            s = r[source]
            cells += [f"{s['mean']:.4f}", f"{s['below_oidn']} of {s['of']}" if "of" in s else "—",
                      f"{s['median_ratio']:.2f}×" if "median_ratio" in s else "—"]
        lines.append("| " + " | ".join(cells) + " |")
    for source in ("held-out", "validation"):
        oidn = [f["oidn"] for f in frames if f["source"] == source]
        if oidn and None not in oidn:
            lines.append(f"\nOIDN, {source} frames ({len(oidn)}): mean relMSE {statistics.fmean(oidn):.4f}.")
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    curve = [r for r in rows if r["phase"] in branches]
    ends = [r for r in rows if r["phase"] not in branches]
    for source, colour in (("held-out", "C0"), ("validation", "C1")):
        if "median_ratio" not in curve[0][source]:
            continue
        steps = [r["steps"] for r in curve]
        axes[0].plot(steps, [r[source]["median_ratio"] for r in curve], "o-", color=colour, ms=3,
                     label=f"{source} frames")
        axes[1].plot(steps, [r[source]["below_oidn"] / r[source]["of"] for r in curve], "o-", color=colour, ms=3,
                     label=f"{source} frames")
        for r, marker in zip(ends, "*Xs^"):
            axes[0].plot(r["steps"], r[source]["median_ratio"], marker, color=colour, ms=9, mec="k",
                         label=f"{r['phase']}" if source == "held-out" else None)
            axes[1].plot(r["steps"], r[source]["below_oidn"] / r[source]["of"], marker, color=colour, ms=9, mec="k")
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--", label="OIDN")
    axes[0].set_ylabel("median relMSE / OIDN's")
    axes[1].set_ylabel("share of frames below OIDN's relMSE")
    axes[1].axhline(0.5, color="k", lw=0.8, ls=":")
    first = found["phases"][branches[0]]
    for ax in axes:
        for phase, start in zip(branches, (0, epochs_trained(first))):
            ax.axvline(start * found["steps_per_epoch"], color="0.7", lw=0.8)
            ax.text(start * found["steps_per_epoch"], ax.get_ylim()[1], f" {phase}", va="top", fontsize=8,
                    color="0.4")
        ax.set_xlabel("training steps (both phases)")
    axes[0].legend(fontsize=7)
    axes[1].legend(fontsize=7)
    fig.suptitle(f"{run_dir}: whole frames as it trains (finished: its best epochs)", fontsize=10)
    fig.tight_layout()
    fig.savefig(out.with_suffix(".png"), dpi=110)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    commands = parser.add_subparsers(dest="command", required=True)
    w = commands.add_parser("watch")
    w.add_argument("--run", type=Path, required=True)
    w.add_argument("--into", type=Path, required=True)
    w.add_argument("--every", type=float, default=120.0)
    m = commands.add_parser("measure")
    m.add_argument("--run", type=Path, required=True)
    m.add_argument("--snapshots", type=Path, required=True)
    m.add_argument("--frames", nargs="+", default=["../shared/validation/blender"])
    m.add_argument("--spp", default="4,16,64")
    m.add_argument("--stride", type=int, default=1, help="every n-th snapshot (and the last)")
    m.add_argument("--compare", type=Path, nargs="*", default=[], help="finished runs measured beside it")
    m.add_argument("--out", type=Path, default=Path("reports/frame_curve"))
    r = commands.add_parser("report", help="write <out>.md and <out>.png again from <out>.json")
    r.add_argument("--out", type=Path, default=Path("reports/frame_curve"))
    args = parser.parse_args()
    if args.command == "watch":
        watch(args.run, args.into, args.every)
    elif args.command == "report":
        report(args.out)
    else:
        from prep.processes import keep_freed_memory

        keep_freed_memory()  # as every kpcn command does (kpcn_keras.cli.main)
        measure(args.run, args.snapshots, args.frames, {int(s) for s in args.spp.split(",")}, args.out, args.stride,
                args.compare)


if __name__ == "__main__":
    main()
