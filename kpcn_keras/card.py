"""A shipped model's card, ``CARD.md``, and shipping: a finished run (with a run for every input set) into
``models/<name>/`` (``kpcn ship``, the last step of ``make model``; docs/formats.md §5b).

The card is generated, never written by hand, from what the run itself holds, so it cannot disagree with it:

- **Quality modes**: one row per mode the model has (``kpcn ship --mode``): its architecture, the parameters of
  its full-input networks, the weight of each input set's networks where it is mixed with OIDN's frame
  (``kpcn_keras.oidn_mix``) and the run it came from; the sections below are of the ``balanced`` mode's networks.
- **Configuration**, per input set: preset, architecture and every model field, each phase's steps (those
  it trained, where early stopping ended it, and the step whose weights it keeps) and learning rate with the
  seconds it trained (``timings.json``), the batch size, the command that trained it, and the versions and
  machine.
- **Training data**: the shard set, the render set it was cut from, the scene families, the patches (train and
  held-out) and the spp ladder of the inputs, from the shard set's manifest; the same for each input set's
  network whose shard set was cut from another render set. A network fine-tuned from another (``--init``) says
  from which, with the checksums its run recorded.
- **Held-out table**: the means per input spp over the held-out scenes of ``kpcn evaluate``'s
  ``<run>/eval/metrics.json`` (relMSE and DSSIM of the input, NLM, OIDN where it was installed, and the run);
  after them, where the report has them, prefiltered OIDN's, Blender's own frame's and the frames won (the run's
  relMSE below the strongest of those anchors, ``EvaluatedFrame.won``).
- **Validation table**, where the run was evaluated on another renderer's frames (``<run>/eval-validation/``,
  ``make model``'s ``VALIDATION`` frames): one row per frame, beside OIDN when ``pyoidn`` was installed, and the
  same anchors and "won" where the report has them.
- **Speed**: seconds of the full model on a 1920×1080 frame (:data:`SPEED_FRAME`) beside OIDN's, in one
  process, alternating, with the peak memory of the timing (:func:`speed`; the goal, :data:`SPEED_GOAL`: within
  3× OIDN's time). A model with several quality modes has each mode timed too, beside plain OIDN at the same
  quality, in the same alternation. The measurement is shipped beside the card as ``speed.json``
  (:data:`SPEED`), and the card's figures are that file's (:func:`speed_lines`).
- **Learning curve**: ``loss.png`` and, per phase, the validation loss (the held-out patches' loss after each
  epoch) at its first, best and last epoch: a best before the last says the phase stopped improving.

Shipping is refused, in one line naming what to run, for a run that is unfinished, lacks an input set
(``shipping.shippable_records``), has no held-out report, or whose report is older than a model file it evaluates
(trained on after it was evaluated). The copy is ``shipping.ship``'s: atomic, size-checked, no checkpoints.
"""

from __future__ import annotations

import json
import os
import platform
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from kpcn_keras.config import DEFAULT_MODEL, DEFAULT_QUALITY, QUALITY_MODES, SPEED_FRAME, SPEED_GOAL, SPEED_REPEATS
from kpcn_keras.evaluate import EvaluatedFrame, read_rows
from kpcn_keras.run import CARD, METRICS, Run, RunRecord
from kpcn_keras.shipping import check_modes, is_shipped_model, shippable_records
from kpcn_keras.shipping import ship as ship_folder
from prep.errors import KpcnError
from prep.files import atomic_write_text, read_json
from prep.shards import round_name

# held-out table: (header, method of the eval row, metric), after the spp and the frame count
HELD_OUT_COLUMNS = (
    ("raw relMSE", "raw", "relmse"), ("NLM relMSE", "nlm", "relmse"), ("OIDN relMSE", "oidn", "relmse"),
    ("kpcn relMSE", "denoised", "relmse"),
    ("raw DSSIM", "raw", "dssim"), ("NLM DSSIM", "nlm", "dssim"), ("OIDN DSSIM", "oidn", "dssim"),
    ("kpcn DSSIM", "denoised", "dssim"),
)
# validation table: after the scene, the spp and the input set of the model that served the frame
VALIDATION_COLUMNS = (
    ("raw relMSE", "raw", "relmse"), ("OIDN relMSE", "oidn", "relmse"), ("kpcn relMSE", "denoised", "relmse"),
    ("raw DSSIM", "raw", "dssim"), ("OIDN DSSIM", "oidn", "dssim"), ("kpcn DSSIM", "denoised", "dssim"),
)
# after either table's columns, each where some row of the report has it (a report from before has none)
ANCHOR_COLUMNS = (
    ("OIDN prefiltered relMSE", "oidn_prefiltered", "relmse"), ("OIDN prefiltered DSSIM", "oidn_prefiltered", "dssim"),
    ("Blender relMSE", "blender", "relmse"), ("Blender DSSIM", "blender", "dssim"),
)
SPEED = "speed.json"  # the card's speed measurement, shipped beside it
MISSING = "–"  # a method the evaluation did not run (OIDN not installed, NLM on a frame without variance)


def _number(value) -> str:
    return MISSING if value is None or not np.isfinite(value) else f"{value:.4f}"


def _mean(values) -> float | None:
    """The mean, or None where any value is missing (a method run on some frames only is not comparable)."""
    values = list(values)
    return None if not values or any(v is None for v in values) else float(np.mean(values))


def with_anchors(columns: tuple, rows: list[EvaluatedFrame]) -> tuple:
    """``columns`` and those of :data:`ANCHOR_COLUMNS` whose method some of ``rows`` has."""
    return columns + tuple(c for c in ANCHOR_COLUMNS if any(getattr(r, c[1]) is not None for r in rows))


def _judged(rows: list[EvaluatedFrame]) -> bool:
    """Whether the table says which frames are won: where the report has an anchor beyond plain OIDN."""
    return any(r.oidn_prefiltered is not None or r.blender is not None for r in rows)


def _won(rows: list[EvaluatedFrame]) -> str:
    """"k of n": the frames won of those with an anchor (``EvaluatedFrame.won``)."""
    judged = [r.won for r in rows if r.won is not None]
    return f"{judged.count('yes')} of {len(judged)}" if judged else MISSING


def held_out_means(rows: list[EvaluatedFrame]) -> list[dict]:
    """Per input spp, ascending: ``spp``, ``frames``, the mean of each column of :data:`HELD_OUT_COLUMNS` and of
    the anchors' the rows have (:func:`with_anchors`) over the rows of that spp (None for a method some of them
    lack) and ``won`` (:func:`_won`)."""
    out = []
    for spp in sorted({r.spp for r in rows}):
        of = [r for r in rows if r.spp == spp]
        out.append({"spp": spp, "frames": len(of), "won": _won(of),
                    **{header: _mean(r.score(m, k) for r in of)
                       for header, m, k in with_anchors(HELD_OUT_COLUMNS, rows)}})
    return out


def _table(headers: list[str], lines: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)] + ["| " + " | ".join(c) + " |"
                                                                               for c in lines]


def held_out_table(rows: list[EvaluatedFrame]) -> list[str]:
    means, columns, won = held_out_means(rows), with_anchors(HELD_OUT_COLUMNS, rows), _judged(rows)
    return _table(["input spp", "frames", *(h for h, _, _ in columns), *(["won"] if won else [])],
                  [[str(m["spp"]), str(m["frames"]), *(_number(m[h]) for h, _, _ in columns),
                    *([m["won"]] if won else [])] for m in means])


def validation_table(rows: list[EvaluatedFrame]) -> list[str]:
    columns, won = with_anchors(VALIDATION_COLUMNS, rows), _judged(rows)
    lines = [[r.scene, str(r.spp), r.inputs or "full", *(_number(r.score(m, k)) for _, m, k in columns),
              *([r.won or MISSING] if won else [])] for r in rows]
    if len(rows) > 1:
        lines.append(["**mean**", "", "", *(_number(_mean(r.score(m, k) for r in rows)) for _, m, k in columns),
                      *([_won(rows)] if won else [])])
    return _table(["scene", "input spp", "model", *(h for h, _, _ in columns), *(["won"] if won else [])], lines)


def _family(scene: str) -> str:
    """The family of a built-in scene, ``<family>-<index>`` (``prep.render.families.make_scene``)."""
    family, _, index = scene.rpartition("-")
    return family if family and index.isdigit() else scene


def training_data(run: Run, record: RunRecord) -> list[str]:
    """The lines of the card's training-data section for ``run``, from its shard set's manifest."""
    sset = run.shard_set(record)
    manifest = sset.complete_manifest()
    sources = manifest.get("sources", [])
    inputs = [s for s in sources if s.get("role") == "input"]
    shards = manifest["rounds"][round_name(0)]["shards"]
    patches = {split: sum(s["patches"] for s in shards if s["split"] == split) for split in ("train", "val")}
    config = manifest.get("config", {})
    scenes = {split: sorted({s["scene"] for s in sources if s.get("split") == split}) for split in ("train", "val")}
    references = sorted({int(s["spp"]) for s in sources if s.get("role") == "reference"})
    rounds = len(manifest.get("rounds", {}))
    return [
        f"- shard set `{sset.dir.name}` (input set {record.inputs.name}), cut from the render set "
        f"`{config.get('set_name', '?')}` (under `{config.get('render_root', '?')}`)",
        f"- scene families: {', '.join(sorted({_family(s) for s in scenes['train'] + scenes['val']}))}; "
        f"{len(scenes['train'])} training scenes, {len(scenes['val'])} held out "
        f"({', '.join(scenes['val'])})",
        f"- patches: {patches['train']} for training, {patches['val']} held out ({config.get('patch_size', '?')} px"
        f" a side{'' if rounds <= 1 else f'; {rounds} sampling rounds'})",
        f"- input spp ladder: {', '.join(map(str, sorted({int(s['spp']) for s in inputs})))}; references at "
        f"{', '.join(map(str, references))} spp",
    ]


def training_data_section(run: Run, records: list[RunRecord]) -> list[str]:
    """The card's training-data section: from each input set's shard set manifest (:func:`training_data`), or, for
    a shipped model shipped again (with modes added), its own card's section as it is: its networks are those files,
    and their shard sets need not be on this machine."""
    if is_shipped_model(run):
        return card_section(run.card_path.read_text(), "Training data")
    lines = training_data(run, records[0])
    renders = _render_set(run, records[0])
    others = [(variant, rec, _render_set(variant, rec) == renders)
              for variant, rec in zip(run.variants()[1:], records[1:])]
    same = [f"`{variant.shard_set(rec).dir.name}`" for variant, rec, alike in others if alike]
    if same:
        lines += [f"- the other input sets' networks: the same renders cut for each, {', '.join(same)}"]
    for variant, rec, alike in others:
        if not alike:
            lines += ["", f"The {rec.inputs.name} network's:", ""] + training_data(variant, rec)
    return lines + [""]


def card_sections(text: str) -> dict[str | None, list[str]]:
    """The lines of a card by the section (``## title``) they are in, headings left out; None holds those before the
    first section."""
    sections, title = {None: []}, None
    for line in text.splitlines():
        if line.startswith("## "):
            title = line[3:].strip()
            sections.setdefault(title, [])
        else:
            sections[title].append(line)
    return sections


def card_section(text: str, title: str) -> list[str]:
    """The lines of a card's section ``## title``, from the line after its heading (and the blank line after it) to
    the next heading; KpcnError where the card has none."""
    lines = card_sections(text).get(title)
    if lines is None:
        raise KpcnError(f"the card has no section '## {title}'")
    return lines[1:] if lines and not lines[0] else lines


def _render_set(run: Run, record: RunRecord) -> str | None:
    """The render set the run's shard set was cut from (its manifest's)."""
    return run.shard_set(record).complete_manifest().get("config", {}).get("set_name")


def configuration(variant: Run, record: RunRecord) -> list[str]:
    """The card's configuration lines of one input set's run."""
    train, model = record.train, record.model.to_dict()
    timings = read_json(variant.timings_path, "run timings") if variant.timings_path.is_file() else {}
    phases = record.data.get("phases", {})
    lines = [f"### {record.inputs.name}", "",
             f"- preset `{train.preset}`, architecture `{record.model.arch}`; model: "
             + ", ".join(f"{k} {v}" for k, v in model.items()),
             f"- batch {train.batch_size}, loss {train.loss}, augmentation {'on' if train.augment else 'off'}, "
             + (f"synthetic fireflies {train.fireflies:g} a patch, " if train.fireflies else "")
             + f"seed {train.seed}",
             f"- command: `{record.command or '?'}`"]
    started = record.data.get("init", {}).get("networks")
    if started:
        lines.append(f"- fine-tuned: its branch phases started from the networks of `{train.init}` as they were then ("
                     + ", ".join(f"{name} SHA-256 {sha[:12]}…" for name, sha in started.items()) + ")")
    lines.append("")
    lines += _table(["phase", "steps", "learning rate", "seconds"],
                    [[name, trained_steps(plan, train.steps_per_epoch), f"{plan.get('learning_rate', float('nan')):g}",
                      f"{timings[name]:.0f}" if name in timings else "?"] for name, plan in phases.items()])
    return lines


def trained_steps(plan: dict, steps_per_epoch: int) -> str:
    """A phase's steps as the card shows them: the steps it was given; where early stopping ended it before
    them, the steps it trained of those; where it keeps an earlier epoch's weights, that epoch's last step."""
    from kpcn_keras.train import epochs_trained

    if "steps" not in plan:
        return "?"
    steps = plan["steps"]
    trained = min(epochs_trained(plan) * steps_per_epoch, steps)
    text = str(steps) if trained == steps else f"{trained} of {steps}"
    if plan.get("best_epoch") is not None:
        kept = min((plan["best_epoch"] + 1) * steps_per_epoch, steps)
        if kept < trained:
            text += f", the weights of step {kept}"
    return text


def learning_curve(variant: Run, record: RunRecord) -> list[str]:
    """Per phase of one input set's run: its epochs and the validation loss at its first, best and last."""
    from kpcn_keras.train import epochs_trained, read_log

    rows = {int(r["epoch"]): r for r in read_log(variant.log_path)}
    lines = []
    for name, plan in record.data.get("phases", {}).items():
        epochs = range(plan["first_epoch"], plan["first_epoch"] + epochs_trained(plan))
        losses = [(e, float(rows[e]["val_loss"])) for e in epochs if rows.get(e, {}).get("val_loss") not in (None, "")]
        if not losses:
            continue
        best = min(losses, key=lambda p: p[1])
        lines.append([record.inputs.name, name, str(len(losses)), f"{losses[0][1]:.4f}",
                      f"{best[1]:.4f} (epoch {best[0] - plan['first_epoch'] + 1})", f"{losses[-1][1]:.4f}"])
    return lines


def frame_of_size(layers: dict[str, np.ndarray], width: int, height: int) -> dict[str, np.ndarray]:
    """The frame's layers wrapped around (tiled) or cropped to ``height`` x ``width``: a frame of that size
    with the content of a real render, for timing."""
    out = {}
    for name, a in layers.items():
        h, w = a.shape[:2]
        tiled = np.pad(a, ((0, max(height - h, 0)), (0, max(width - w, 0))) + ((0, 0),) * (a.ndim - 2), mode="wrap")
        out[name] = np.ascontiguousarray(tiled[:height, :width])
    return out


def speed(run: Run, record: RunRecord, frame_size: tuple[int, int] = SPEED_FRAME,
          repeats: int = SPEED_REPEATS, source: str | os.PathLike | None = None,
          modes: dict[str, Run] | None = None) -> dict:
    """Seconds to denoise a ``frame_size`` (width, height) frame, made of ``source`` (an EXR in any layout) or else
    the run's first held-out frame (:func:`frame_of_size`; a shipped model keeps no renders, so re-timing one
    names a frame), by the run's full model (in the default precision, ``kpcn_keras.precision``, as
    ``kpcn denoise`` runs it) and by OIDN when ``pyoidn`` is installed: side by side in this process, each
    warmed up, then called alternately ``repeats`` times, the best of each; with torch's threads, the precision,
    the peak resident memory during the timed calls and what the frame holds whole
    (``batch.frame_bytes``: beyond it, memory is bounded by the tile). With ``modes`` (mode -> run: the other
    quality modes), each mode's full model and plain OIDN at that quality are timed in the same alternation, and
    ``modes`` in the record holds, per mode (the default one too: the model itself), both seconds."""
    import time

    from kpcn_keras.batch import frame_bytes, torch_threads
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_pairs
    from prep import baselines, layouts
    from prep.processes import peak_memory_mb, reset_peak_memory

    noisy = source if source is not None else held_out_pairs(run, record)[0][0]
    width, height = frame_size
    layers = frame_of_size(layouts.read(noisy).served_layers(), width, height)
    denoiser = Denoiser.from_run(run, record=record)
    slope = record.validation_slope
    calls = {"kpcn": lambda: denoiser(layers, slope=slope)}
    if baselines.oidn_available():
        calls["oidn"] = lambda: baselines.oidn_denoise(layers, mode="plain")
    if modes:
        calls.update(_mode_calls({DEFAULT_QUALITY: run, **modes}, layers, slope))
    for call in calls.values():
        call()  # the warm-up: first-call allocations, OIDN's device
    reset = reset_peak_memory()
    best = dict.fromkeys(calls, float("inf"))
    for _ in range(repeats):
        for name, call in calls.items():
            start = time.perf_counter()
            call()
            best[name] = min(best[name], time.perf_counter() - start)
    found = {"width": width, "height": height, "frame": Path(noisy).name, "held_out": source is None,
             "kpcn_s": best["kpcn"], "oidn_s": best.get("oidn"), "repeats": repeats, "threads": torch_threads(),
             "cpus": os.cpu_count(), "precision": denoiser.precision,
             "peak_mb": peak_memory_mb() if reset else None, "frame_mb": frame_bytes(height, width, png=False) / 2**20}
    if modes:  # only then: a model of the default mode alone keeps the record it always had
        kpcn = {k.removeprefix("kpcn "): v for k, v in best.items() if k.startswith("kpcn ")}
        kpcn[DEFAULT_QUALITY] = best["kpcn"]
        found["modes"] = {mode: {"kpcn_s": kpcn[mode], "oidn_s": best.get(f"oidn {mode}")}
                          for mode in QUALITY_MODES if mode in kpcn}
    return found


def _mode_calls(modes: dict[str, Run], layers: dict, slope) -> dict:
    """A call per quality mode but the default (``kpcn MODE``: the mode's full model at its record's validation
    slope) and, where ``pyoidn`` is installed, plain OIDN at each mode's quality (``oidn MODE``)."""
    from kpcn_keras import oidn_mix
    from kpcn_keras.denoise import Denoiser
    from prep import baselines

    calls = {}
    for mode, source in modes.items():
        if mode != DEFAULT_QUALITY:  # the default mode is the model itself, timed as "kpcn"
            record = source.record()
            denoiser = oidn_mix.served(Denoiser.from_run(source, record=record), record)
            calls[f"kpcn {mode}"] = lambda d=denoiser, s=record.validation_slope: d(layers, slope=s)
        if baselines.oidn_available():
            calls[f"oidn {mode}"] = lambda q=mode: baselines.oidn_denoise(layers, mode="plain", quality=q)
    return calls


def speed_lines(found: dict) -> list[str]:
    """The card's speed section from :func:`speed`'s record ``found``, as shipped in :data:`SPEED`; sizes in
    MiB (``peak_mb`` and ``frame_mb`` are bytes / 2**20)."""
    size = f"{found['width']}×{found['height']}"
    made_of = "a held-out frame" if found.get("held_out", True) else "a frame"
    when = (f"measured {found['measured']} by `{found['command']}`" if "measured" in found
            else "written with this card")
    lines = [f"A {size} frame (`{found['frame']}`, {made_of} wrapped around to that size), denoised in one "
             f"process beside OIDN, alternately, the best of {found['repeats']} calls each after a warm-up, "
             f"{found['threads']} torch threads, {found['cpus']} CPUs, the networks' trunks in "
             f"{found.get('precision', 'float32')} (`--precision`, docs/denoise.md §5); from `{SPEED}`, {when}:", ""]
    rows = [["kpcn (this model)", f"{found['kpcn_s']:.2f}"]]
    if found["oidn_s"] is None:
        rows.append(["OIDN", "not installed (pip install -e '.[oidn]')"])
    else:
        ratio = found["kpcn_s"] / found["oidn_s"]
        rows.append(["OIDN", f"{found['oidn_s']:.2f}"])
        rows.append(["kpcn / OIDN", f"{ratio:.2f}× ({'within' if ratio <= SPEED_GOAL else 'over'} the goal of "
                     f"{SPEED_GOAL:g}×)"])
    lines += _table(["denoiser", f"seconds a {size} frame"], rows) + [""]
    peak = "" if found["peak_mb"] is None else "peak resident memory of the process during the timing (torch and " \
        f"the networks included) {found['peak_mb']:.0f} MiB; "
    if "modes" in found:
        lines += ["Each quality mode (its own networks) beside plain OIDN at the same quality, in the same "
                  "alternation:", ""]
        lines += _table(["quality mode", "kpcn s", "OIDN s (same quality)", "kpcn / OIDN"],
                        [[mode, f"{t['kpcn_s']:.2f}", MISSING if t["oidn_s"] is None else f"{t['oidn_s']:.2f}",
                          MISSING if t["oidn_s"] is None else f"{t['kpcn_s'] / t['oidn_s']:.2f}×"]
                         for mode, t in found["modes"].items()]) + [""]
    lines.append(f"Memory: {peak}the frame's own layers and outputs {found['frame_mb']:.0f} MiB, the rest bounded "
                 "by the tile (docs/denoise.md §3).")
    return lines


def check_report(run: Run, record: RunRecord, folder: Path, command: str) -> None:
    """KpcnError unless the report in ``folder`` is newer than every model file it evaluates. A shipped model's
    report is the one it was shipped with, checked then, and its files' times are a checkout's, not the order they
    were written in: it is not checked again (its networks are still checked against their SHA-256 at loading)."""
    if is_shipped_model(run):
        return
    report = folder / METRICS
    models = [run.dir / entry.file for entry in record.components.values()]
    for variant in run.variants():
        if variant is not run and variant.has_record():
            models += [variant.dir / e.file for e in variant.record().components.values()]
    newer = [m for m in models if m.stat().st_mtime > report.stat().st_mtime]
    if newer:
        raise KpcnError(f"{report}: older than {newer[0]}, which it should evaluate; evaluate again with '{command}'")


def parameters(run: Run, record: RunRecord) -> int:
    """The parameters of the run's networks, every component's (each read once, checked as serving reads it)."""
    return sum(run.load_component(record, name).count_params() for name in record.components)


def quality_lines(modes: dict[str, Run]) -> list[str]:
    """The card's quality-mode table: per mode (mode -> the run it comes from) its architecture, the parameters of
    its full-input networks and the run."""
    from kpcn_keras.oidn_mix import of_record

    rows = []
    for mode, source in modes.items():
        record = source.record()
        variants = [variant.record() for variant in source.variants() if variant.has_record()]
        mixes = [(rec.inputs.name, of_record(rec.data, str(rec.path))) for rec in variants]
        mixed = ", ".join(f"{name} {mix.weight:g}" for name, mix in mixes if mix is not None) or MISSING
        rows.append([mode + (" (default)" if mode == DEFAULT_QUALITY else ""), record.model.arch,
                     str(parameters(source, record)), mixed, f"`{source.dir}`"])
    return ["## Quality modes", "",
            "Each mode is a network set of its own (`kpcn denoise --quality MODE`; `quality/<mode>/` beside the "
            "model's own networks, which are its balanced mode). Where a mode's input set is mixed with OIDN's "
            "frame (`kpcn mix-oidn`), the weight of the networks' frame is given (OIDN's is 1 less it):", "",
            *_table(["mode", "architecture", "parameters", "networks' weight beside OIDN", "shipped from"], rows), ""]


def make_card(run: Run, dest: str | os.PathLike, command: str, speed_frame: tuple[int, int] = SPEED_FRAME,
              modes: dict[str, Run] | None = None) -> tuple[str, dict]:
    """The card of the shipped model ``dest`` made from ``run`` by ``command`` and the speed record its speed
    section shows, timed on a ``speed_frame`` (width, height) frame (:func:`speed`), with a row for each run of
    ``modes`` (mode -> run, the other quality modes); KpcnError (one line) for a run that cannot be shipped (see
    the module docstring)."""
    records = shippable_records(run)
    record = records[0]
    if not (run.eval_dir / METRICS).is_file():
        raise KpcnError(f"{run.dir}: no held-out report ({run.eval_dir / METRICS}) for the model's card; "
                        f"evaluate it first with 'kpcn evaluate --run {run.dir}'")
    check_report(run, record, run.eval_dir, f"kpcn evaluate --run {run.dir}")
    name = Path(dest).name
    versions = record.data.get("versions", {})
    made = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# kpcn model `{name}`", "",
             f"Made {made} by `{command}` from the run `{run.dir}` (generated by kpcn_keras/card.py: do not edit).",
             f"Denoise with `kpcn denoise FILE --run {dest}` (`kpcn denoise FILE` where it is the default model, "
             f"models/{DEFAULT_MODEL}); `kpcn evaluate --run {dest} --out DIR` reproduces the held-out table from "
             f"the same renders and shard set (`{record.data['train']['set_name']}`, which `make model` makes).", ""]
    lines += quality_lines({DEFAULT_QUALITY: run, **(modes or {})})
    lines += ["## Configuration", "",
             "One network per input set (docs/training.md §6): a frame is denoised by the model trained for what it "
             "has (`Run.serving`).", "",
             f"Versions: keras {versions.get('keras', '?')}, torch {versions.get('torch', '?')}, numpy "
             f"{versions.get('numpy', '?')}; machine: {platform.machine()}, {os.cpu_count()} CPUs, "
             f"{platform.system()} {platform.release()}.", ""]
    for variant, rec in zip(run.variants(), records):
        lines += configuration(variant, rec) + [""]
    lines += ["## Training data", ""] + training_data_section(run, records)
    lines += ["## Held-out frames", "",
              f"Means over the held-out scenes per input spp, from `{Path('eval') / METRICS}` "
              "(`kpcn evaluate`; relMSE and DSSIM as in docs/method.md):", ""]
    lines += held_out_table(read_rows(run.eval_dir)) + [""]
    if (run.validation_dir / METRICS).is_file():
        check_report(run, record, run.validation_dir,
                     f"kpcn evaluate --run {run.dir} --out {run.validation_dir} FRAMES")
        lines += ["## Validation frames", "",
                  f"Another renderer's frames, from `{Path(run.validation_dir.name) / METRICS}`; "
                  "*model* is the input set of the network that served the frame:", ""]
        lines += validation_table(read_rows(run.validation_dir)) + [""]
    found = speed(run, record, speed_frame, modes=modes)
    lines += ["## Speed", ""] + speed_lines(found) + [""]
    lines += ["## Learning curve", "", "![training and validation loss per epoch](loss.png)", "",
              "Validation loss (the held-out patches, after each epoch) per phase of each input set's run; a best "
              "epoch before the last says the phase had stopped improving:", ""]
    lines += _table(["input set", "phase", "epochs", "first", "best", "last"],
                    [line for variant, rec in zip(run.variants(), records) for line in learning_curve(variant, rec)])
    return "\n".join(lines) + "\n", found


def ship(run: Run, dest: str | os.PathLike, command: str, speed_frame: tuple[int, int] = SPEED_FRAME,
         modes: dict[str, Run] | None = None) -> Run:
    """Ship ``run`` to ``dest`` with its card (:func:`make_card`, ``shipping.ship``) and the speed record the card
    shows (:data:`SPEED`), and each run of ``modes`` (mode -> run) as that quality mode; every run is checked
    (``shipping.check_modes``) before the card is made."""
    check_modes(run, dest, modes or {})
    card, found = make_card(run, dest, command, speed_frame, modes)
    return ship_folder(run, dest, {CARD: card, SPEED: json.dumps(found, indent=2) + "\n"}, modes=modes)


def retime(model: Run, source: str | os.PathLike, command: str, frame_size: tuple[int, int] = SPEED_FRAME) -> dict:
    """Time the shipped ``model`` again (:func:`speed`, on a ``frame_size`` frame made of ``source``) and write the
    record to its :data:`SPEED` and the card's speed section from it, the rest of the card as it was; returns the
    record. What a card shows of its speed is then always its :data:`SPEED` file, measured by a named command."""
    card_path = model.card_path
    if not card_path.is_file():
        raise KpcnError(f"{model.dir}: no {CARD}, not a shipped model (kpcn ship makes one)")
    text = card_path.read_text()
    start, end = text.find("## Speed\n"), text.find("\n## ", text.find("## Speed\n") + 1)
    if start < 0 or end < 0:
        raise KpcnError(f"{card_path}: no speed section followed by another to replace")
    others = {mode: model.for_quality(mode) for mode in model.quality_modes() if mode != DEFAULT_QUALITY}
    found = speed(model, model.record(), frame_size, source=source, modes=others)
    found.update(measured=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), command=command)
    atomic_write_text(model.dir / SPEED, json.dumps(found, indent=2) + "\n")
    section = "\n".join(["## Speed", ""] + speed_lines(found) + [""])
    atomic_write_text(card_path, text[:start] + section + text[end:])
    return found


def card_tables(text: str) -> dict[str, list[list[str]]]:
    """The tables of a card, by the section (``## ...``) they are in: rows of cells, header first (for tests
    and for readers that compare a card with its run's reports)."""
    tables = {}
    for section, lines in card_sections(text).items():
        rows = [[c.strip() for c in line.strip("|").split("|")] for line in lines
                if line.startswith("|") and not re.fullmatch(r"\|(---\|)+", line)]
        if rows:
            tables[section] = rows
    return tables
