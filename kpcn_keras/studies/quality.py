"""``kpcn quality``: each lever that may make kpcn beat Open Image Denoise, alone and combined, at equal training
time, on the project's held-out frames and on other renderers' validation frames, beside OIDN.

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
- **The default's target** (:func:`default_target`): ``make train``'s default is to be below OIDN on at
  least half of the validation frames at 16 spp; per lever, the frame that decides (the needed-th lowest ratio to
  OIDN's relMSE) says whether it is met and, where not, by how much it is out.
- **The model beside the levers** (:func:`model_run`, :func:`measure_model`): the shipped model (``kpcn denoise``'s
  without ``--run``), or ``cfg.model``, measured on the same frames, each served by its network for what the frame
  gives, its scores in every row under :data:`MODEL`. It is not a lever (it trained for as long as it improved,
  not for the budget), so it never heads the report; its section judges the targets for the shipped model
  on these frames (:data:`MODEL_SHARE` of all frames below OIDN's relMSE, decided as the default's is; its mean
  DSSIM below OIDN's at :data:`MODEL_DSSIM_SPP`). A model that trained on the study's held-out scenes is refused
  (:func:`check_unseen`). ``kpcn quality --measure-model`` adds it to a record already written, training
  nothing (:func:`add_model`): a record outlives its runs.
- **Writes** ``<out_dir>/quality.md`` (the tables, the date, the machine, the rules), ``quality.json`` (every
  number, per frame) and ``quality.png`` (input | kpcn (the headline's lever) | OIDN | Blender | reference of the
  validation frames at ``panel_spp``, with the model's column where there is one, every image tonemapped by the
  one ``prep.colour.tonemap``) through ``kpcn_keras.studies.report``. ``kpcn quality --report-only`` writes the md
  again from ``quality.json`` alone and the png from the frames and runs it names (:func:`rewrite_reports`),
  training nothing; where a run the panels need is gone, the png is left as it is and a line says so.

The table of levers and :class:`kpcn_keras.studies.config.QualityConfig` are in ``kpcn_keras/studies/config.py``;
the judging of a record (:func:`best`, :func:`verdict`, the targets) and its reports (``quality.md``, the panels,
``--report-only``) in :mod:`kpcn_keras.studies.quality_report`.
This module imports keras and torch only inside the functions that train or denoise.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import json
import os
import statistics
from datetime import date
from pathlib import Path

from kpcn_keras.config import TrainConfig
from kpcn_keras.studies.compare import (
    PlannedRuns,
    _training_seconds,
    deep_learning_stack,
    plan_steps,
    with_steps,
)
from kpcn_keras.studies.config import QUALITY_BASE, QUALITY_LEVERS, QualityConfig
from kpcn_keras.studies.frames import (
    BESIDE_KEYS,
    beside,
    panels_figure,
    renderer_pairs,
    scores,
)
from kpcn_keras.studies.inputs_study import cut_input_shards, shard_options
from kpcn_keras.studies.quality_report import (
    MODEL,
    RECORD_KEYS,
    REPORT,
    best,
    format_report,
    model_column,
    model_label,
    panel_columns,
    panel_entries,
    panels_or_none,
)
from kpcn_keras.studies.report import Report
from prep import exr, layouts
from prep.errors import KpcnError
from prep.files import read_json
from prep.inputs import FULL, INPUT_SETS, InputSet

# a network for frames without a diffuse/specular split has the diffuse branch alone: what joins both branches
# (a compositor, one shared network, joint fine-tuning) is left out of a lever's network for them
WITHOUT_SPLIT = {"compositor": None, "shared": False, "joint_steps": 0}


# ---------------------------------------------------------------- levers and their data


def group_dir(cfg: QualityConfig) -> Path:
    # budget and seed in the name: another budget is another set of runs, not a clash with these
    return Path(cfg.runs_root) / f"{cfg.set_name}-{cfg.budget:g}s-seed{cfg.seed}"


def lever_set(cfg: QualityConfig, lever: str) -> str:
    """The render and shard set ``lever`` trains on: the study's, or the larger one its render options make."""
    options = QUALITY_LEVERS[lever][3]
    if not options:
        return cfg.set_name
    from prep.render.renderset import RenderSet

    digest = hashlib.sha256(json.dumps(options, sort_keys=True, default=list).encode()).hexdigest()[:8]
    return RenderSet(cfg.set_name, cfg.render_root).derived(f"r{digest}").name


def render_config(cfg: QualityConfig, lever: str):
    """The RenderConfig of ``lever``'s own render set: the study set's record with the lever's options."""
    from prep.render.renderset import RenderConfig, RenderSet

    base = RenderSet(cfg.set_name, cfg.render_root).record_path
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

    manifest = ShardSet.named(cfg.shards_root, cfg.set_name).complete_manifest()
    return sorted({s["scene"] for s in manifest["sources"] if s["split"] == "val"})


def prepare_data(cfg: QualityConfig, input_sets: tuple[str, ...], *, log=print) -> dict[str, str]:
    """Render and cut what every lever of ``cfg`` trains on, for each of ``input_sets``; returns lever -> set."""
    from prep.render.renderset import RenderSet, render_set, reuse_renders

    options = shard_options(cfg.set_name, cfg.render_root, cfg.shards_root)
    cut_input_shards(cfg.set_name, cfg.render_root, cfg.shards_root, input_sets, options=options,
                     log=lambda line: log(f"quality: {line}"))
    sets, done = {}, {cfg.set_name}
    for lever in cfg.levers:
        sets[lever] = name = lever_set(cfg, lever)
        if name in done:
            continue
        rc = render_config(cfg, lever)
        linked = reuse_renders(rc, RenderSet(cfg.set_name, cfg.render_root).dir)
        log(f"quality: {lever}: render set {rc.render_set.dir} ({len(linked)} renders linked from "
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

    group = group_dir(cfg)
    seconds = cfg.budget / len(input_sets)
    plans = {}
    with PlannedRuns(group, "quality study") as planned:
        for lever in cfg.levers:
            run = Run(group / lever)
            networks = {}
            for inputs in input_sets:
                base = train_config(cfg, lever, sets[lever], inputs, overrides)
                manifest = ShardSet.named(cfg.shards_root, sets[lever], inputs).complete_manifest()
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
                       "beside": beside(noisy_path, frame)})
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

    sset = ShardSet.named(cfg.shards_root, cfg.set_name)
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
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings
    from prep import baselines

    rows, outputs = [], {}
    oidn = baselines.oidn_available()
    for f in held:
        scene, spp = f["name"].split(" ")[0], int(f["name"].split(" ")[1])
        row = {"kind": "held-out", "frame": f["name"], "scene": scene, "spp": spp,
               "raw": scores(f["noisy"]["default"], f["reference"]), "levers": {}}
        if oidn:
            for mode, key in baselines.OIDN_KEYS.items():
                row[key] = scores(baselines.oidn_denoise(f["noisy"], mode=mode), f["reference"])
        rows.append(row)
    for f in frames:
        row = {"kind": "validation", "frame": validation_name(f), "scene": f["scene"],
               "spp": f["spp"], "path": str(f["path"]), "reference_path": str(f["reference_path"]),
               "renderer": f["renderer"], "layout": f["frame"].layout, "inputs": f["frame"].inputs.name,
               "raw": scores(f["frame"].layers["default"], f["reference"]), "levers": {}}
        for name, image in f["beside"].items():
            row[BESIDE_KEYS[name]] = scores(image, f["reference"])
        rows.append(row)
    servings = {}  # one per run, so two levers of one run load its networks once
    for lever, plan in plans.items():
        if plan["run"] not in servings:
            servings[plan["run"]] = Serving(Run(plan["run"]), InferenceSettings(ensemble=cfg.ensemble))
        entries, shown = measure_run(servings[plan["run"]], held, frames, cfg)
        for row, entry in zip(rows, entries):
            row["levers"][lever] = entry
        outputs.update({(lever, path): out for path, out in shown.items()})
        held_mean = statistics.fmean(r["levers"][lever]["relmse"] for r in rows[:len(held)])
        val_mean = statistics.fmean(r["levers"][lever]["relmse"] for r in rows[len(held):])
        log(f"quality: [{lever}] mean relMSE held-out {held_mean:.4f}, validation {val_mean:.4f}")
    return rows, outputs


def measure_run(serving, held: list[dict], frames: list[dict], cfg: QualityConfig) -> tuple:
    """The scores of the run ``serving`` serves (a ``kpcn_keras.serving.Serving``) on every frame, held-out then
    validation (the rows' order): the held-out frames by its own networks (the run serves a full frame itself),
    each validation frame by the network that serves what it gives (``Run.serving``); and its outputs of the
    validation frames at ``cfg.panel_spp`` by path."""
    entries = [{**scores(serving.denoiser(FULL)(f["noisy"])["default"], f["reference"]), "model": FULL.name}
               for f in held]
    shown = {}
    for f in frames:
        variant = serving.variant(f["frame"].inputs)
        out = serving.denoiser(f["frame"].inputs)(f["frame"].layers)["default"]
        trained = serving.record(f["frame"].inputs)
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
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings

    entries, shown = measure_run(Serving(run, InferenceSettings(ensemble=cfg.ensemble)), held, frames, cfg)
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


