"""``kpcn quality``: each lever that may make kpcn beat Open Image Denoise, alone and combined, at equal training
time, on the project's held-out frames and on other renderers' validation frames, beside OIDN (issue 23).

The contract:

- **Levers** are :data:`kpcn_keras.studies.config.QUALITY_LEVERS` (name -> what it is, preset, TrainConfig
  overrides, the options of a render set of its own or None), the one place they are defined; ``combination``
  is an entry that merges others (``config.combine``).
- **Data.** A lever without render options trains on the study's render set ``<render_root>/<set_name>`` as
  ``make shards`` cut it. A lever with render options (more scenes per family, a longer spp ladder) trains on a
  larger set rendered from the study's own (its seed, size, reference spp and families, the lever's options on
  top) in ``<render_root>/<set_name>-r<hash of the options>``: the renders the two sets share are hard-linked
  from the study's set (``prep.render.renderset.reuse_renders``: the same bytes), the rest rendered, resumably;
  it is cut with the study's shard options and the study's held-out scenes as its validation scenes, so that no
  lever trains on a scene any lever is judged on. Levers of the same render options share the set.
- **Every input layout served.** The input sets the validation frames give (``prep.inputs``: Cycles writes no
  variance, a Mitsuba or PBRT frame no split) besides the full set are the networks each lever trains: the full
  run in ``<runs_root>/<set>-<budget>s-seed<seed>/<lever>``, the others in its ``inputs/<set>/`` folders
  (``Run.for_inputs``), so that ``Run.serving`` picks each frame's network. A network for frames without a
  split has the diffuse branch alone, so a lever's compositor, shared network or joint fine-tuning is left out
  of it (:data:`WITHOUT_SPLIT`).
- **Equal training time.** A lever's ``budget`` seconds are shared evenly by its networks (the full network and
  one per other input set: ``budget / networks`` each); within a network, seconds become steps as ``kpcn
  compare`` turns them (:func:`kpcn_keras.studies.compare.plan_steps`: probed steps, the branch phases' share,
  the compositor's). The probes and steps are kept in ``plan.json`` beside the runs, keyed by the training's
  identity (less the step counts the budget sets), its seconds and its shard set's content key, so the same
  command resumes; a run that was trained for other settings is refused. How the frames are denoised
  (``ensemble``) is not part of the key: the same runs serve every value.
- **Measured on the same frames for every lever:** the study set's held-out frames (every validation scene at
  every input spp; the full network) and the validation frames under ``frames`` (``<scene>-<spp>spp.exr`` that
  are not their scene's reference, read in their own layout, each served by the lever's network for what it
  gives), beside the raw input, OIDN (``pyoidn``: colour, albedo, normal; "not installed" without it) and, where
  the folder has it, the renderer's own denoised frame. Per frame relMSE, DSSIM and relSE p99.9
  (``kpcn_keras.studies.frames.scores``); the report's means per input spp, per lever the frames where its
  relMSE is below OIDN's of how many, and the median of the ratio (``compare.against``).
- **The headline judges by frames** (:func:`verdict`): the lever whose relMSE is below OIDN's on the most frames
  (:func:`best`; without OIDN, the lowest mean held-out relMSE), then on how many of all the frames it is;
  "beats OIDN" means on most frames.
- **The default's target** (:func:`default_target`): issue 23 asks ``make train``'s default to be below OIDN on at
  least half of the validation frames at 16 spp; per lever, the frame that decides (the needed-th lowest ratio to
  OIDN's relMSE) says whether it is met and, where not, by how much it is out.
- **The model beside the levers** (:func:`model_run`, :func:`measure_model`): the shipped model (``kpcn denoise``'s
  without ``--run``), or ``cfg.model``, measured on the same frames, each served by its network for what the frame
  gives, its scores in every row under :data:`MODEL`. It is not a lever (it trained for as long as it improved,
  not for the budget), so it never heads the report; its section judges issue 23's targets for the shipped model
  on these frames (:data:`MODEL_SHARE` of all frames below OIDN's relMSE, decided as the default's is; its mean
  DSSIM below OIDN's at :data:`MODEL_DSSIM_SPP`). A model that trained on the study's held-out scenes is refused
  (:func:`check_unseen`). ``kpcn quality --measure-model`` adds it to a record already written, training
  nothing (:func:`add_model`): a record outlives its runs.
- **Writes** ``<out_dir>/quality.md`` (the tables, the date, the machine, the rules), ``quality.json`` (every
  number, per frame) and ``quality.png`` (input | kpcn (the headline's lever) | OIDN | Blender | reference of the
  validation frames at ``panel_spp``, with the model's column where there is one, every image tonemapped by the
  one ``prep.metrics.tonemap``) through ``prep.studies.report``. ``kpcn quality --report-only`` writes the md
  again from ``quality.json`` alone and the png from the frames and runs it names (:func:`rewrite_reports`),
  training nothing; where a run the panels need is gone, the png is left as it is and a line says so.

The table of levers and :class:`kpcn_keras.studies.config.QualityConfig` are in ``kpcn_keras/studies/config.py``.
This module imports keras and torch only inside the functions that train or denoise.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import math
import os
import statistics
from datetime import date
from fractions import Fraction
from pathlib import Path

from kpcn_keras.config import DEFAULT_ENSEMBLE, TrainConfig
from kpcn_keras.studies.compare import (
    PlannedRuns,
    _training_seconds,
    against,
    deep_learning_stack,
    plan_steps,
    with_steps,
)
from kpcn_keras.studies.config import QUALITY_BASE, QUALITY_LEVERS, QualityConfig
from kpcn_keras.studies.frames import (
    PANEL_COLUMNS,
    SCORES,
    beside,
    by_spp,
    panels_figure,
    renderer_pairs,
    scores,
)
from kpcn_keras.studies.inputs_study import cut_input_shards, shard_options
from prep import exr, layouts
from prep.errors import KpcnError
from prep.files import read_json
from prep.inputs import FULL, INPUT_SETS, InputSet
from prep.studies.report import Report

REPORT = "quality"  # quality.json, quality.md, quality.png in the report folder
KINDS = ("held-out", "validation")
BASELINES = ("raw", "oidn", "blender")
LABELS = {"raw": "raw input", "oidn": "OIDN", "blender": "Blender's own"}
# a network for frames without a diffuse/specular split has the diffuse branch alone: what joins both branches
# (a compositor, one shared network, joint fine-tuning) is left out of a lever's network for them
WITHOUT_SPLIT = {"compositor": None, "shared": False, "joint_steps": 0}
# the model measured beside the levers (the shipped one unless --model): its key in the record and in each row.
# Not a lever: it trained for as long as it kept improving, not for the budget
MODEL = "model"
# issue 23's targets for the shipped model: below OIDN's relMSE on at least two thirds of all frames, and its mean
# DSSIM below OIDN's at these spp
MODEL_SHARE, MODEL_DSSIM_SPP = Fraction(2, 3), (16, 64)


# ---------------------------------------------------------------- levers and their data


def group_dir(cfg: QualityConfig) -> Path:
    # budget and seed in the name: another budget is another set of runs, not a clash with these
    return Path(cfg.runs_root) / f"{cfg.set_name}-{cfg.budget:g}s-seed{cfg.seed}"


def lever_set(cfg: QualityConfig, lever: str) -> str:
    """The render and shard set ``lever`` trains on: the study's, or the larger one its render options make."""
    options = QUALITY_LEVERS[lever][3]
    if not options:
        return cfg.set_name
    digest = hashlib.sha256(json.dumps(options, sort_keys=True, default=list).encode()).hexdigest()[:8]
    return f"{cfg.set_name}-r{digest}"


def render_config(cfg: QualityConfig, lever: str):
    """The RenderConfig of ``lever``'s own render set: the study set's record with the lever's options."""
    from prep.render.renderset import RenderConfig

    base = Path(cfg.render_root) / cfg.set_name / "config.json"
    if not base.exists():
        raise KpcnError(f"{base.parent}: not a render set (run 'kpcn render --set {cfg.set_name}' first); lever "
                        f"{lever!r} renders a larger set from it")
    recorded = read_json(base, "render set record", keys=("config",))["config"]
    fields = {f.name for f in dataclasses.fields(RenderConfig)}
    values = {**{k: v for k, v in recorded.items() if k in fields}, **QUALITY_LEVERS[lever][3],
              "set_name": lever_set(cfg, lever), "out_root": cfg.render_root}
    return RenderConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def held_out_scenes(cfg: QualityConfig) -> list[str]:
    """The validation scenes of the study's full shard set: every lever's held-out scenes."""
    from prep.shards import ShardSet

    manifest = ShardSet(Path(cfg.shards_root) / cfg.set_name).complete_manifest()
    return sorted({s["scene"] for s in manifest["sources"] if s["split"] == "val"})


def prepare_data(cfg: QualityConfig, input_sets: tuple[str, ...], *, log=print) -> dict[str, str]:
    """Render and cut what every lever of ``cfg`` trains on, for each of ``input_sets``; returns lever -> set."""
    from prep.render.renderset import render_set, reuse_renders

    options = shard_options(cfg.set_name, cfg.render_root, cfg.shards_root)
    cut_input_shards(cfg.set_name, cfg.render_root, cfg.shards_root, input_sets, options=options,
                     log=lambda line: log(f"quality: {line}"))
    sets, done = {}, {cfg.set_name}
    for lever in cfg.levers:
        sets[lever] = name = lever_set(cfg, lever)
        if name in done:
            continue
        rc = render_config(cfg, lever)
        linked = reuse_renders(rc, Path(cfg.render_root) / cfg.set_name)
        log(f"quality: {lever}: render set {Path(rc.out_root) / rc.set_name} ({len(linked)} renders linked from "
            f"{cfg.set_name}, the rest rendered)")
        render_set(rc, progress=False)
        cut_input_shards(name, cfg.render_root, cfg.shards_root, input_sets,
                         options={**options, "val_scenes": tuple(held_out_scenes(cfg))},
                         log=lambda line: log(f"quality: {line}"))
        done.add(name)
    return sets


def train_config(cfg: QualityConfig, lever: str, set_name: str, inputs: str,
                 overrides: dict | None = None) -> TrainConfig:
    """The TrainConfig of ``lever``'s network for ``inputs`` before its steps are set: :data:`QUALITY_BASE`, the
    lever's own overrides on it, then ``overrides`` (``model`` merged)."""
    _, preset, own, _ = QUALITY_LEVERS[lever]
    overrides = dict(overrides or {})
    values = {**QUALITY_BASE, **own, **overrides}
    values["model"] = {**own.get("model", {}), **(overrides.get("model") or {})}
    if not InputSet.named(inputs).split:
        values.update(WITHOUT_SPLIT)
    return TrainConfig.from_preset(preset, set_name=set_name, shards_root=cfg.shards_root, seed=cfg.seed,
                                   inputs=inputs, **values)


def plan_and_train(cfg: QualityConfig, sets: dict[str, str], input_sets: tuple[str, ...], *,
                   overrides: dict | None = None, verbose="auto", log=print) -> dict:
    """Every lever's networks planned (or their plan reused) and trained; lever -> {set, run, networks}."""
    from kpcn_keras.run import Run
    from kpcn_keras.train import train
    from prep.shards import ShardSet
    from prep.shards.config import shard_set_dir

    group = group_dir(cfg)
    seconds = cfg.budget / len(input_sets)
    plans = {}
    with PlannedRuns(group, "quality study") as planned:
        for lever in cfg.levers:
            run = Run(group / lever)
            networks = {}
            for inputs in input_sets:
                base = train_config(cfg, lever, sets[lever], inputs, overrides)
                manifest = ShardSet(shard_set_dir(cfg.shards_root, sets[lever], inputs)).complete_manifest()
                key = {"train": base.identity(), "seconds": seconds, "content_key": manifest["content_key"]}
                variant = run.for_inputs(InputSet.named(inputs))
                entry, _ = planned.entry((lever, inputs), key, variant.dir,
                                         functools.partial(plan_steps, base, seconds))
                log(f"quality: [{lever}] {inputs}: {seconds:g} s, steps "
                    + ", ".join(f"{k} {v}" for k, v in entry["phase_steps"].items()))
                train(with_steps(base, entry["steps"]), run.dir, verbose=verbose)
                networks[inputs] = {**entry, "run": str(variant.dir), "trained_s": _training_seconds(variant.dir)}
            plans[lever] = {"set": sets[lever], "run": str(run.dir), "networks": networks}
    return plans


# ---------------------------------------------------------------- the frames


def validation_frames(cfg: QualityConfig) -> list[dict]:
    """Every validation frame under ``cfg.frames`` read once, with its reference and the denoisers beside kpcn."""
    for given in cfg.frames:
        if not Path(given).exists():
            raise KpcnError(f"--frames {given}: no such file or folder")
    pairs = renderer_pairs(cfg.frames)
    if not pairs:
        raise KpcnError(f"--frames {' '.join(cfg.frames)}: no noisy frame with a reference beside it")
    frames = []
    for noisy_path, ref_path in pairs:
        frame = layouts.read(noisy_path)
        scene, spp = exr.parse_render_filename(noisy_path)
        frames.append({"path": noisy_path, "reference_path": ref_path, "scene": scene, "spp": spp,
                       "renderer": noisy_path.parent.name, "frame": frame,
                       "reference": layouts.read(ref_path).layers["default"],
                       "beside": beside(noisy_path, frame.layers)})
    return frames


def input_sets_for(frames: list[dict]) -> tuple[str, ...]:
    """The networks every lever trains: the full set, and each set a validation frame gives, in the order of
    ``prep.inputs.INPUT_SETS``."""
    given = {FULL.name} | {f["frame"].inputs.name for f in frames}
    return tuple(s for s in INPUT_SETS if s in given)


def held_out_frames(cfg: QualityConfig) -> list[dict]:
    """The study set's held-out frames (every validation scene at every input spp), read once."""
    from kpcn_keras.evaluate import read_frames
    from prep.shards import ShardSet

    sset = ShardSet(Path(cfg.shards_root) / cfg.set_name)
    frames = read_frames(sset.pairs(sset.complete_manifest(), "val"))
    if not frames:
        raise KpcnError(f"{sset.dir}: no held-out scenes to measure on")
    return frames


# ---------------------------------------------------------------- measuring


def validation_name(f: dict) -> str:
    """A validation frame's name in the record: ``<renderer>/<scene> <spp> spp``."""
    return f"{f['renderer']}/{f['scene']} {f['spp']} spp"


def measure(cfg: QualityConfig, plans: dict, held: list[dict], frames: list[dict], *, log=print) -> tuple:
    """Per-frame rows of both kinds (raw input, OIDN, Blender's own, every lever) and each lever's outputs on
    the validation frames at ``cfg.panel_spp`` (for the panels)."""
    from kpcn_keras.run import Run
    from prep import baselines

    rows, outputs = [], {}
    oidn = baselines.oidn_available()
    for f in held:
        scene, spp = f["name"].split(" ")[0], int(f["name"].split(" ")[1])
        row = {"kind": "held-out", "frame": f["name"], "scene": scene, "spp": spp,
               "raw": scores(f["noisy"]["default"], f["reference"]), "levers": {}}
        if oidn:
            row["oidn"] = scores(baselines.oidn_denoise(f["noisy"]), f["reference"])
        rows.append(row)
    for f in frames:
        row = {"kind": "validation", "frame": validation_name(f), "scene": f["scene"],
               "spp": f["spp"], "path": str(f["path"]), "reference_path": str(f["reference_path"]),
               "renderer": f["renderer"], "layout": f["frame"].layout, "inputs": f["frame"].inputs.name,
               "raw": scores(f["frame"].layers["default"], f["reference"]), "levers": {}}
        for name, image in f["beside"].items():
            row[name.lower()] = scores(image, f["reference"])
        rows.append(row)
    denoisers = {}
    for lever, plan in plans.items():
        entries, shown = measure_run(Run(plan["run"]), held, frames, cfg, denoisers)
        for row, entry in zip(rows, entries):
            row["levers"][lever] = entry
        outputs.update({(lever, path): out for path, out in shown.items()})
        held_mean = statistics.fmean(r["levers"][lever]["relmse"] for r in rows[:len(held)])
        val_mean = statistics.fmean(r["levers"][lever]["relmse"] for r in rows[len(held):])
        log(f"quality: [{lever}] mean relMSE held-out {held_mean:.4f}, validation {val_mean:.4f}")
    return rows, outputs


def measure_run(run, held: list[dict], frames: list[dict], cfg: QualityConfig, denoisers: dict) -> tuple:
    """``run``'s scores on every frame, held-out then validation (the rows' order): the held-out frames by its
    own networks, each validation frame by the network that serves what it gives (``Run.serving``); and its
    outputs of the validation frames at ``cfg.panel_spp`` by path. ``denoisers`` caches one per network."""
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.settings import InferenceSettings

    def denoiser(variant):
        if variant.dir not in denoisers:
            denoisers[variant.dir] = Denoiser.from_run(variant, InferenceSettings(ensemble=cfg.ensemble))
        return denoisers[variant.dir]

    entries = [{**scores(denoiser(run)(f["noisy"])["default"], f["reference"]), "model": FULL.name} for f in held]
    shown = {}
    for f in frames:
        variant = run.serving(f["frame"].inputs)
        out = denoiser(variant)(f["frame"].layers)["default"]
        trained = variant.record()
        entries.append({**scores(out, f["reference"]), "model": trained.inputs.name, "run": str(variant.dir),
                        "set": trained.train.set_name})
        if f["spp"] == cfg.panel_spp:
            shown[str(f["path"])] = out
    return entries, shown


# ---------------------------------------------------------------- the model beside the levers


def model_run(cfg: QualityConfig, *, log=print):
    """The model measured beside the levers: ``cfg.model``, else the one ``kpcn denoise`` uses without ``--run``
    (None, said in a line, where there is none). KpcnError where ``cfg.model`` is not a finished run, or where
    the model trained on the study's held-out scenes (:func:`check_unseen`); the study's shard set must exist."""
    from kpcn_keras.run import Run, default_model

    if cfg.model:
        run = Run(cfg.model)
        run.record().finished()
    else:
        try:
            run = default_model()
        except KpcnError as exc:
            log(f"quality: no model measured beside the levers ({exc})")
            return None
    check_unseen(cfg, run)
    return run


def check_unseen(cfg: QualityConfig, run) -> None:
    """KpcnError unless the model's networks for the held-out frames (its own, full ones) were trained without
    the study's held-out scenes: checked where its set is the study's or one made from it (``<set>-...``, whose
    renders of a scene are the same), since scenes of other sets share names, not pixels."""
    record = run.record()
    own = record.train.set_name
    if own != cfg.set_name and not own.startswith(f"{cfg.set_name}-"):
        return
    seen = sorted(set(record.data["shards"].get("split", {}).get("train", ())) & set(held_out_scenes(cfg)))
    if seen:
        raise KpcnError(f"--model {run.dir}: trained on {', '.join(seen)} of the set {own}, which the study holds "
                        "out: a model is not judged on the scenes it trained on")


def measure_model(cfg: QualityConfig, run, rows: list[dict], held: list[dict], frames: list[dict], *,
                  log=print) -> tuple[dict, dict]:
    """``run`` measured on the study's frames: its scores put in every row under :data:`MODEL`; returns the
    record's entry for it (where it is, the set it trained on) and its outputs of the panels' frames by path."""
    entries, shown = measure_run(run, held, frames, cfg, {})
    for row, entry in zip(rows, entries):
        row[MODEL] = entry
    # relative where it can be: a report in the repository names models/default, not this machine's folders
    where = os.path.relpath(run.dir.resolve())
    model = {"run": str(run.dir) if where.startswith("..") else where, "set": run.record().train.set_name,
             "shipped": is_shipped(run.dir)}
    log(f"quality: [{model_label(model)}] mean relMSE held-out "
        f"{statistics.fmean(e['relmse'] for e in entries[:len(held)]):.4f}")
    return model, shown


def is_shipped(folder) -> bool:
    """Whether ``folder`` is a model shipped in the repository's ``models/``."""
    from kpcn_keras.config import MODELS_DIR

    return Path(folder).resolve().parent == MODELS_DIR


def model_label(model: dict) -> str:
    """How the report names the record's model entry: ``shipped model `default``` or ``model `<folder>```."""
    return f"{'shipped ' if model['shipped'] else ''}model `{Path(model['run']).name}`"


def add_model(cfg: QualityConfig, *, command: str | None = None, log=print) -> dict:
    """``kpcn quality --measure-model``: the model (``cfg.model``, else the shipped one) measured on the frames of
    ``<cfg.out_dir>/quality.json``'s study, put in the record, and the reports written again; nothing trained.
    KpcnError where the frames found are not the record's."""
    report = Report(cfg.out_dir, REPORT)
    record = read_json(report.path(".json"), "quality record", RECORD_KEYS)
    report.check_writable()
    fields = {f.name for f in dataclasses.fields(QualityConfig)}
    study = QualityConfig(**{**{k: v for k, v in record["config"].items() if k in fields},
                             "out_dir": cfg.out_dir, "model": cfg.model})
    run = model_run(study, log=log)
    if run is None:
        raise KpcnError("--measure-model: no model to measure; name one with --model")
    held, frames = held_out_frames(study), validation_frames(study)
    found = [f["name"] for f in held] + [validation_name(f) for f in frames]
    recorded = [r["frame"] for r in record["frames"]]
    if found != recorded:
        now, then = next((a, b) for a, b in itertools.zip_longest(found, recorded) if a != b)
        raise KpcnError(f"{report.path('.json')}: the frames found now are not the record's (found {now!r} where "
                        f"it has {then!r}); measure the model by running the study again")
    entry, shown = measure_model(study, run, record["frames"], held, frames, log=log)
    record = {**record, MODEL: {**entry, "measured": f"`{command or 'kpcn quality --measure-model'}` on "
                                                      f"{date.today().isoformat()}"}}
    report.write(record, format_report(record), panels_or_none(record, log=log))
    return record


# ---------------------------------------------------------------- the command


def quality(cfg: QualityConfig, *, overrides: dict | None = None, command: str | None = None, verbose="auto",
            log=print) -> dict:
    """Run the study (module docstring); writes the three reports and returns the record.

    ``overrides``: TrainConfig fields applied to every lever after its own (a tiny network for a test); they are
    part of the plan's key and of the record. ``command``: the command line that asked, for the report."""
    from prep import baselines

    report = Report(cfg.out_dir, REPORT)
    report.check_writable()
    frames = validation_frames(cfg)
    session = report.begin()
    input_sets = input_sets_for(frames)
    log(f"quality: {len(cfg.levers)} levers, {cfg.budget:g} s of training each over {len(input_sets)} networks "
        f"({', '.join(input_sets)}); {len(frames)} validation frames")
    sets = prepare_data(cfg, input_sets, log=log)
    run = model_run(cfg, log=log)  # before the training: a model it cannot judge is refused first
    plans = plan_and_train(cfg, sets, input_sets, overrides=overrides, verbose=verbose, log=log)
    held = held_out_frames(cfg)
    rows, outputs = measure(cfg, plans, held, frames, log=log)
    model, shown = measure_model(cfg, run, rows, held, frames, log=log) if run else (None, {})
    record = {
        **session.envelope(command),
        "config": {**dataclasses.asdict(cfg), "levers": list(cfg.levers), "frames": list(cfg.frames)},
        "levers": {n: {"what": QUALITY_LEVERS[n][0], "preset": QUALITY_LEVERS[n][1],
                       "overrides": QUALITY_LEVERS[n][2], "renders": QUALITY_LEVERS[n][3]} for n in cfg.levers},
        "base": QUALITY_BASE,
        "overrides": overrides or {},
        "input_sets": list(input_sets),
        "rules": {"seconds_per_network": cfg.budget / len(input_sets)},
        "oidn": baselines.oidn_available(),
        "machine": session.machine(**deep_learning_stack()),
        "plans": plans,
        "frames": rows,
        **({MODEL: model} if model else {}),
    }
    record["panels"] = panel_entries(record)
    top = best(record)
    panels = []
    for entry, f in zip(record["panels"], [f for f in frames if f["spp"] == cfg.panel_spp]):
        images = {"input": f["frame"].layers["default"], "kpcn": outputs[top, str(f["path"])], **f["beside"],
                  "reference": f["reference"]}
        if model:
            images[model_column(record)] = shown[str(f["path"])]
        panels.append((entry["title"], images))
    return report.write(record, format_report(record), lambda _: panels_figure(panels, panel_columns(record)))


def panel_entries(record: dict) -> list[dict]:
    """The panels' frames: each validation frame at the panel spp, with the run of the headline's lever that
    served it (what ``--report-only`` reads again)."""
    top = best(record)
    members = ensemble_of(record)
    shown = top + (f", an ensemble of {members}" if members > 1 else "")
    return [{"title": f"{r['frame']} ({shown})", "path": r["path"], "reference_path": r["reference_path"],
             "run": r["levers"][top]["run"]}
            for r in record["frames"] if r["kind"] == "validation" and r["spp"] == record["config"]["panel_spp"]]


def panel_columns(record: dict) -> tuple[str, ...]:
    """The panels' columns: input, kpcn (the headline's lever), the measured model where there is one, the
    other denoisers, the reference."""
    return PANEL_COLUMNS[:2] + ((model_column(record),) if record.get(MODEL) else ()) + PANEL_COLUMNS[2:]


def model_column(record: dict) -> str:
    return "shipped model" if record[MODEL]["shipped"] else "model"


def redraw_panels(record: dict):
    """quality.png from the frames of the record's panels, denoised by the runs of the headline's lever as this
    kpcn judges it (``--report-only``: :func:`panel_entries` again, so that the panels follow the headline) and
    by the measured model's network for each."""
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.run import Run
    from kpcn_keras.settings import InferenceSettings

    def denoised(run: Run, frame) -> object:
        return Denoiser.from_run(run, InferenceSettings(ensemble=ensemble_of(record)))(frame.layers)["default"]

    shown = []
    for entry in panel_entries(record):
        frame = layouts.read(entry["path"])
        images = {"input": frame.layers["default"], "kpcn": denoised(Run(entry["run"]), frame),
                  **beside(Path(entry["path"]), frame.layers),
                  "reference": layouts.read(entry["reference_path"]).layers["default"]}
        if record.get(MODEL):
            images[model_column(record)] = denoised(Run(record[MODEL]["run"]).serving(frame.inputs), frame)
        shown.append((entry["title"], images))
    return panels_figure(shown, panel_columns(record))


def panels_or_none(record: dict, *, log=print):
    """:func:`redraw_panels`, or None (the png left as it is, said in a line) where a run the panels need is
    gone: a report's numbers are its record's, and a record outlives its runs."""
    from kpcn_keras.run import Run

    needed = [e["run"] for e in panel_entries(record)] + ([record[MODEL]["run"]] if record.get(MODEL) else [])
    gone = [r for r in needed if not Run(r).has_record()]
    if gone:
        log(f"quality: {REPORT}.png left as it was: the run {gone[0]} its panels need is gone")
        return None
    return redraw_panels


RECORD_KEYS = ("date", "config", "levers", "input_sets", "rules", "oidn", "machine", "plans", "frames", "panels")


def rewrite_reports(out_dir: str | Path, *, log=print) -> dict:
    """``quality.md`` written again from ``<out_dir>/quality.json`` and ``quality.png`` from the frames and runs
    it names (``kpcn quality --report-only``), nothing trained; returns the record as the report read it (with
    ``rewritten``; ``quality.json`` is left as it is)."""
    report = Report(out_dir, REPORT)
    record = read_json(report.path(".json"), "quality record", RECORD_KEYS)
    report.check_writable((".md", ".png"))
    record = {**record, "rewritten": f"`kpcn quality --report-only` on {date.today().isoformat()}"}
    report.write_text(record, format_report(record), panels_or_none(record, log=log))
    return record


# ---------------------------------------------------------------- judging


def of_kind(record: dict, kind: str) -> list[dict]:
    return [r for r in record["frames"] if r["kind"] == kind]


def mean(rows: list[dict], method: str, metric: str, lever: bool = False) -> float | None:
    """The mean over ``rows`` of ``metric`` of ``method`` (a lever's with ``lever``); None where a row lacks it."""
    values = [(r["levers"] if lever else r).get(method, {}).get(metric) for r in rows]
    return None if not values or None in values else statistics.fmean(values)


def scores_of(row: dict, method: str) -> dict:
    """The scores in ``row`` of ``method``: a lever, or :data:`MODEL` (no lever has its name)."""
    return row[MODEL] if method == MODEL else row["levers"][method]


def against_oidn(rows: list[dict], method: str) -> dict | None:
    """``method`` (a lever or :data:`MODEL`) against OIDN on the ``rows`` that have OIDN's scores
    (``compare.against``: ``lower``, of ``frames``, ``median_ratio``); None where none has."""
    both = [r for r in rows if "oidn" in r]
    if not both:
        return None
    return against({"frames": [scores_of(r, method) for r in both]}, {"frames": [r["oidn"] for r in both]})


def best(record: dict) -> str:
    """The lever below OIDN's relMSE on the most frames (held-out and validation together), the lower median
    ratio to OIDN's, then the lower mean held-out relMSE breaking ties; without OIDN, the lowest mean held-out
    relMSE (``compare``'s rule). By frames first because a mean is carried by one frame: ``caustics``, whose
    reference is itself speckled, made a lever below OIDN on fewer frames than `cpu` the best by its mean."""
    held = of_kind(record, "held-out")

    def held_mean(lever: str) -> float:
        return mean(held, lever, "relmse", lever=True)

    if not record["oidn"]:
        return min(record["config"]["levers"], key=held_mean)

    def by_frames(lever: str) -> tuple:
        got = against_oidn(record["frames"], lever)
        return -got["lower"], got["median_ratio"], held_mean(lever)

    return min(record["config"]["levers"], key=by_frames)


# issue 23's target for make train's default: below OIDN's relMSE on at least half of the validation frames at 16 spp
TARGET_SPP, TARGET_SHARE = 16, Fraction(1, 2)


def share_target(rows: list[dict], method: str, share: Fraction) -> dict | None:
    """``method`` against a target of being below OIDN's relMSE on at least ``share`` of the ``rows`` that have
    OIDN's scores: ``lower`` (frames below OIDN's relMSE), ``frames``, ``needed`` (the frames the target asks for)
    and ``deciding``, the ratio to OIDN's relMSE of the frame that decides (the ``needed``-th lowest): below 1
    where the target is met, else how far it is out. None without such rows."""
    ratios = sorted(scores_of(r, method)["relmse"] / r["oidn"]["relmse"] for r in rows if "oidn" in r)
    if not ratios:
        return None
    needed = math.ceil(share * len(ratios))
    return {"lower": sum(x < 1 for x in ratios), "frames": len(ratios), "needed": needed,
            "deciding": ratios[needed - 1]}


def default_target(record: dict, method: str) -> dict | None:
    """``method`` against issue 23's target for the default (:data:`TARGET_SPP`, :data:`TARGET_SHARE`) on the
    validation frames at ``TARGET_SPP`` (:func:`share_target`)."""
    rows = [r for r in of_kind(record, "validation") if r["spp"] == TARGET_SPP]
    return share_target(rows, method, TARGET_SHARE)


def dssim_target(record: dict, spp: int) -> dict | None:
    """The model's mean DSSIM against OIDN's over the frames of both kinds at ``spp`` that have OIDN's scores
    (``model``, ``oidn``, ``frames``); None without such frames."""
    rows = [r for r in record["frames"] if r["spp"] == spp and "oidn" in r]
    if not rows:
        return None
    return {"model": mean(rows, MODEL, "dssim"), "oidn": mean(rows, "oidn", "dssim"), "frames": len(rows)}


def _judged(ratio: float) -> str:
    """A target by its ratio: met below 1, else how far out (to a tenth of a per cent below one per cent)."""
    if ratio < 1:
        return "met"
    return f"out by {ratio - 1:.0%}" if ratio >= 1.005 else f"out by {ratio - 1:.1%}"


def _target_table(record: dict) -> list[str]:
    """The section on issue 23's target for the default, a row per lever and one for the measured model, each with
    the render sets its networks for those frames trained on (nothing without OIDN or such frames)."""
    methods = [*record["config"]["levers"], *([MODEL] if record.get(MODEL) else [])]
    rows = {m: default_target(record, m) for m in methods} if record["oidn"] else {}
    if not rows or None in rows.values():
        return []
    lines = ["", "## The default's target: half the validation frames at 16 spp", "",
             f"Issue 23 asks `make train`'s default to be below OIDN's relMSE on at least {TARGET_SHARE} "
             f"of the validation frames at {TARGET_SPP} spp. Per lever (and the model beside them): the frames it is "
             "below OIDN on, how many the target needs, and the ratio to OIDN's relMSE of the frame that decides (the "
             "needed-th lowest): below 1 the target is met; above, it is out by that much. *Trained on*: the render "
             "sets of the networks that denoised these frames.", "",
             "| | below OIDN | needed | deciding frame / OIDN's relMSE | target | trained on |",
             "|---|---|---|---|---|---|"]
    at = [r for r in of_kind(record, "validation") if r["spp"] == TARGET_SPP]
    for method, got in rows.items():
        label = model_label(record[MODEL]) if method == MODEL else f"`{method}`"
        sets = sorted({scores_of(r, method).get("set", "—") for r in at})  # a record before sets were kept: —
        lines.append(f"| {label} | {got['lower']} of {got['frames']} | {got['needed']} | {got['deciding']:.3f}× | "
                     f"{_judged(got['deciding'])} | {', '.join(sets)} |")
    return lines


def _model_section(record: dict) -> list[str]:
    """The section on the measured model: what it is, and issue 23's targets for the shipped model judged on the
    study's frames (nothing without a model; the targets only with OIDN)."""
    model = record.get(MODEL)
    if not model:
        return []
    label = model_label(model)
    lines = ["", f"## The {label}", "",
             f"`{model['run']}` (trained on the `{model['set']}` set; its card: `{model['run']}/CARD.md`) is not a "
             "lever: it trained for as long as it kept improving, not for the study's budget"
             + (", and it is what `kpcn denoise` uses without `--run`" if model["shipped"] else "")
             + ". It was measured on the same frames as the levers, each served by its network for what the frame "
             "gives" + (f", by {model['measured']}" if model.get("measured") else "") + "."]
    if not record["oidn"]:
        return lines
    total = share_target(record["frames"], MODEL, MODEL_SHARE)
    lines += ["", "Issue 23's targets for the shipped model, on these frames: the needed-th lowest ratio to OIDN's "
              "relMSE decides a target on frames; a mean DSSIM is judged by its ratio to OIDN's.", "",
              "| target | model | needed, or OIDN's | ratio to OIDN's | target |", "|---|---|---|---|---|",
              f"| below OIDN's relMSE on at least {MODEL_SHARE} of all frames | {total['lower']} of "
              f"{total['frames']} | {total['needed']} frames | {total['deciding']:.3f}× (the deciding frame) | "
              f"{_judged(total['deciding'])} |"]
    for spp in MODEL_DSSIM_SPP:
        got = dssim_target(record, spp)
        if got:
            ratio = got["model"] / got["oidn"]
            lines.append(f"| mean DSSIM below OIDN's at {spp} spp ({got['frames']} frames) | {got['model']:.4f} | "
                         f"{got['oidn']:.4f} | {ratio:.2f}× | {_judged(ratio)} |")
    return lines


def verdict(record: dict) -> str:
    """The headline: the best lever (:func:`best`), then how it does against OIDN judged by frames, both kinds
    together."""
    top = best(record)
    held_mean = mean(of_kind(record, "held-out"), top, "relmse", lever=True)
    if not record["oidn"]:
        return (f"**Best lever by held-out relMSE: `{top}`** (mean {held_mean:.4f}); OIDN, the denoiser to beat, "
                "is not installed here.")
    line = f"**Best lever by frames: `{top}`** (mean held-out relMSE {held_mean:.4f})"
    parts = {kind: against_oidn(of_kind(record, kind), top) for kind in KINDS}
    total = against_oidn(record["frames"], top)
    lower, n = total["lower"], total["frames"]
    judged = ("it beats OIDN on most frames" if 2 * lower > n else
              "OIDN is better on most frames" if 2 * lower < n else "level with OIDN: lower on half the frames")
    each = "; ".join(f"{p['lower']} of {p['frames']} {kind} frames" for kind, p in parts.items() if p)
    return (line + f". Against OIDN: lower relMSE on {lower} of {n} frames ({each}), the median ratio of its "
            f"relMSE to OIDN's {total['median_ratio']:.2f}×: {judged}.")


def _model_verdict(record: dict) -> list[str]:
    """The headline's second line: the measured model against OIDN by frames (nothing without a model or OIDN)."""
    if not record.get(MODEL) or not record["oidn"]:
        return []
    total = against_oidn(record["frames"], MODEL)
    return ["", f"**The {model_label(record[MODEL])}** (`{record[MODEL]['run']}`, not a lever: below): lower "
            f"relMSE than OIDN on {total['lower']} of {total['frames']} frames, the median ratio "
            f"{total['median_ratio']:.2f}×."]


# ---------------------------------------------------------------- the report


def _n(value, fmt="{:.4f}") -> str:
    return "—" if value is None else fmt.format(value)


def _count(got: dict | None) -> str:
    return "—" if got is None else f"{got['lower']} of {got['frames']}"


def _ratio(got: dict | None) -> str:
    return "—" if got is None else f"{got['median_ratio']:.2f}×"


def _kind_table(record: dict, kind: str) -> list[str]:
    rows = of_kind(record, kind)
    lines = ["| spp | method | frames | relMSE | DSSIM | relSE p99.9 | frames below OIDN's relMSE | median relMSE "
             "/ OIDN's |", "|---|---|---|---|---|---|---|---|"]
    for spp, group in by_spp(rows).items():
        for lever in record["config"]["levers"]:
            got = against_oidn(group, lever)
            lines.append(f"| {spp} | `{lever}` | {len(group)} | "
                         + " | ".join(_n(mean(group, lever, m, lever=True)) for m in SCORES)
                         + f" | {_count(got)} | {_ratio(got)} |")
        if record.get(MODEL):
            got = against_oidn(group, MODEL)
            lines.append(f"| {spp} | {model_label(record[MODEL])} | {len(group)} | "
                         + " | ".join(_n(mean(group, MODEL, m)) for m in SCORES)
                         + f" | {_count(got)} | {_ratio(got)} |")
        for method in BASELINES:
            if any(method in r for r in group):
                have = [r for r in group if method in r]
                lines.append(f"| {spp} | {LABELS[method]} | {len(have)} | "
                             + " | ".join(_n(mean(have, method, m)) for m in SCORES) + " | — | — |")
        if not record["oidn"]:
            lines.append(f"| {spp} | OIDN | — | not installed (pip install '.[oidn]') | — | — | — | — |")
    return lines


def ensemble_of(record: dict) -> int:
    """The members each frame was denoised by; a record from before ``--ensemble`` has none: 1."""
    return record["config"].get("ensemble", DEFAULT_ENSEMBLE)


def format_report(record: dict) -> str:
    """quality.md: the levers, the tables of both kinds per input spp, each validation frame, the rules."""
    cfg, machine = record["config"], record["machine"]
    held, val = of_kind(record, "held-out"), of_kind(record, "validation")
    lines = [
        f"# Each lever against OIDN, at equal training time ({record['date']})", "",
        (f"`{record['command']}`, {record['started']} to {record['finished']}. " if record.get("command") else "")
        + f"Every lever trained {cfg['budget']:g} s on this machine, shared evenly by its "
        f"{len(record['input_sets'])} networks ({', '.join(record['input_sets'])}: "
        f"{record['rules']['seconds_per_network']:g} s each), then measured on the same {len(held)} held-out frames "
        f"of the `{cfg['set_name']}` set and {len(val)} validation frames ({', '.join(cfg['frames'])})."
        + (f" Every frame was denoised as a self-ensemble of {ensemble_of(record)} members (`--ensemble`: the "
           "per-pixel median of the frame denoised in that many orientations, docs/denoise.md §5b), at that many "
           "times the time of one pass." if ensemble_of(record) > 1 else "")
        + (f" This report was written again from `quality.json` by {record['rewritten']}; every number is the "
           "record's." if record.get("rewritten") else ""),
        "", verdict(record), *_model_verdict(record), "",
        "## The levers", "",
        "| lever | what it is | trains on | steps per network (trained s) | held-out frames below OIDN's relMSE | "
        "validation frames below OIDN's | all frames | median relMSE / OIDN's |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for lever in cfg["levers"]:
        plan = record["plans"][lever]
        steps = "; ".join(f"{inputs}: " + ", ".join(f"{k} {v}" for k, v in n["phase_steps"].items())
                          + f" ({n['trained_s']:.0f} s)" for inputs, n in plan["networks"].items())
        total = against_oidn(record["frames"], lever)
        lines.append(f"| `{lever}` | {record['levers'][lever]['what']} | `{plan['set']}` | {steps} | "
                     f"{_count(against_oidn(held, lever))} | {_count(against_oidn(val, lever))} | {_count(total)} | "
                     f"{_ratio(total)} |")
    if record.get(MODEL):
        lines.append(f"| {model_label(record[MODEL])} | not a lever: trained for as long as it kept improving "
                     f"(below) | `{record[MODEL]['set']}` | its card | {_count(against_oidn(held, MODEL))} | "
                     f"{_count(against_oidn(val, MODEL))} | {_count(against_oidn(record['frames'], MODEL))} | "
                     f"{_ratio(against_oidn(record['frames'], MODEL))} |")
    for kind, what in (("held-out", f"The `{cfg['set_name']}` set's held-out frames (every validation scene at "
                                    "every input spp; each lever's full network)"),
                       ("validation", "The validation frames, each denoised by the lever's network for the inputs "
                                      "it gives; Blender's own: the frame Blender's denoiser wrote at render time")):
        lines += ["", f"## {kind.capitalize()} frames", "", f"{what}. Means over the frames of each input spp.", "",
                  *_kind_table(record, kind)]
    methods = [*cfg["levers"], *([MODEL] if record.get(MODEL) else [])]
    lines += ["", "## Each validation frame (relMSE)", "",
              "| frame | layout | inputs | raw | "
              + " | ".join(model_label(record[MODEL]) if m == MODEL else f"`{m}`" for m in methods)
              + " | OIDN | Blender's own |", "|---|---|---|---|" + "---|" * len(methods) + "---|---|"]
    for r in val:
        lines.append(f"| {r['frame']} | {r['layout']} | {r['inputs']} | {r['raw']['relmse']:.4f} | "
                     + " | ".join(f"{scores_of(r, m)['relmse']:.4f}" for m in methods)
                     + f" | {_n(r.get('oidn', {}).get('relmse'))} | {_n(r.get('blender', {}).get('relmse'))} |")
    lines += _target_table(record)
    lines += _model_section(record)
    load_b, load_a = machine["load_average_before"][0], machine["load_average_after"][0]
    lines += [
        "", "## The rules", "",
        f"- **Same budget.** Each lever's {cfg['budget']:g} s are shared evenly by its networks: the full one (the "
        "held-out frames) and one per input set a validation frame gives (`Run.serving` picks each frame's). "
        "Within a network, seconds become steps as `kpcn compare` turns them: each phase's steps are timed by a "
        "scratch training, the branch phases get their share, a compositor the rest. A network for frames without "
        "a split has the diffuse branch alone: a lever's compositor, shared network or joint fine-tuning is left "
        "out of it. Building, validation and checkpoints come on top: *trained s* is what the run's phases took.",
        "- **Same frames.** A lever with a render set of its own trains on a larger set rendered from the study's "
        "(the renders they share linked, the same bytes) whose validation scenes are the study's held-out scenes: "
        "no lever trains on a frame any lever is judged on.",
        "- **By frames.** *Frames below OIDN's relMSE* counts the frames where the lever's relMSE is strictly "
        "below OIDN's, of the frames OIDN has; the median ratio is over the same frames. A mean over frames can "
        "be carried by one frame (`caustics`, whose reference is itself speckled); these cannot.",
        "- **Metrics** (`prep/metrics.py`): relMSE = mean((x − r)² / (r² + 0.01)); relSE p99.9, the error of the "
        "worst 0.1 % of pixels; DSSIM = (1 − SSIM) / 2 on tonemapped images. `quality.json` has every frame's "
        "values; `quality.png` shows input | kpcn (the best lever) | "
        + ("the model beside the levers | " if record.get(MODEL) else "")
        + f"OIDN | Blender's own | reference of the validation frames at {cfg['panel_spp']} spp, every image through "
        "one tonemap.",
        f"- **Machine:** {machine['cpus']} CPUs, load average {load_b:.2f} before and {load_a:.2f} after; "
        f"{machine['platform']}, Python {machine['python']}, torch {machine['torch']}, keras {machine['keras']}, "
        f"{machine['torch_threads']} torch threads. What else ran on the machine is for the caller to note: on a "
        "busy machine the probed steps, and so the budgets, are not the same.",
    ]
    if record.get("base"):
        lines.append(f"- **Every lever starts from** `{json.dumps(record['base'])}` (TrainConfig fields, under the "
                     "lever's own), so that each lever is measured alone against `cpu`.")
    if record.get("overrides"):
        lines.append(f"- **Every lever overridden** with `{json.dumps(record['overrides'])}` (TrainConfig fields, "
                     "after the lever's own).")
    return "\n".join(lines) + "\n"
