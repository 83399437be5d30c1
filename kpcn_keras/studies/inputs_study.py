"""``kpcn inputs-study``: kpcn on other renderers' frames beside OIDN and Blender's own denoiser, and what each
input a renderer may not write costs, at equal training time.

The contract:

- **One network per input set, each trained for the same seconds.** For every set of ``prep.inputs.INPUT_SETS``
  the render set's shards are cut for it (``kpcn shards --inputs``; the full set is ``make shards``' own and is
  reused) and a run is trained on them for ``budget`` seconds of training steps: the full run in
  ``<runs_root>/<set>-<budget>s-seed<seed>/run``, the others in its ``inputs/<set>/`` folders, so that the run
  serves a frame of any layout (``Run.serving``). Seconds become steps as ``kpcn compare`` turns them
  (:func:`kpcn_keras.studies.compare.probe_configuration`, :func:`~kpcn_keras.studies.compare.budget_steps`): a
  no-split run, which trains the diffuse branch alone, gets about twice the diffuse steps. The probes and
  steps are kept in ``plan.json``, so the same command resumes.
- **What each missing piece costs** is measured on the render set's held-out frames (every validation scene at
  every input spp), the same frames for every set, each restricted to the set by its denoiser: mean relMSE,
  DSSIM and relSE p99.9, beside the raw input and OIDN (``pyoidn``, colour + albedo + normal).
- **Other renderers' frames** are every ``<scene>-<spp>spp.exr`` under ``frames`` (files or folders) that is not
  its scene's reference (the same folder's render of the scene with the most samples), read in its own layout
  (``prep.layouts``) and denoised by the run's model for what it has; beside them the raw input, OIDN on the same
  colour + albedo + normal, and, where the folder has it, the renderer's own denoised frame
  (``<scene>-<spp>spp-blender-oidn.exr``: what Blender wrote at render time).
- **Two renders of half the samples** (``pairs``: folders of ``<scene>-<spp>spp-pair-a.exr`` and ``-pair-b.exr``,
  two seeds, and the scene's reference: ``kpcn cycles-validation``'s folder,
  ``kpcn_keras.studies.render_blender_pairs``):
  their mean denoised without variance (``kpcn denoise A --pair B``) and with the variance of their difference
  (``studies.pair_variance``), the same pixels either way.
- **Writes** ``<out_dir>/inputs.md`` (the tables, with the date and the machine), ``inputs.json`` (every number)
  and ``inputs.png`` (input | kpcn | OIDN | Blender | reference of every other renderer's frame at the middle
  spp), through ``kpcn_keras.studies.report``.
"""

from __future__ import annotations

import functools
import glob
import time
from pathlib import Path

import numpy as np

from kpcn_keras.config import TrainConfig
from kpcn_keras.studies.compare import PlannedRuns, _training_seconds, deep_learning_stack, plan_steps, with_steps
from kpcn_keras.studies.config import InputsStudyConfig
from kpcn_keras.studies.frames import SCORES, beside, panels_figure, renderer_pairs, wins
from kpcn_keras.studies.frames import scores as _scores
from kpcn_keras.studies.report import Report
from prep import exr, layouts
from prep.errors import KpcnError
from prep.inputs import INPUT_SETS, InputSet

REPORT = "inputs"


def group_dir(cfg: InputsStudyConfig) -> Path:
    return Path(cfg.runs_root) / f"{cfg.set_name}-{cfg.budget:g}s-seed{cfg.seed}"


def train_config(cfg: InputsStudyConfig, inputs: str, overrides: dict | None = None) -> TrainConfig:
    return TrainConfig.from_preset(cfg.preset, set_name=cfg.set_name, shards_root=cfg.shards_root, seed=cfg.seed,
                                   inputs=inputs, **(overrides or {}))


def shard_options(set_name: str, render_root: str, shards_root: str) -> dict:
    """The options the full shard set ``<shards_root>/<set_name>`` was cut with (``make shards``' own, read from
    its manifest; none, the defaults, where there is no set yet), less where it is and what it holds."""
    from prep.shards import ShardConfig, ShardSet

    full = ShardConfig(set_name=set_name, render_root=render_root, out_root=shards_root)
    if not (full.set_dir / "manifest.json").exists():
        return {}
    return {k: v for k, v in ShardSet(full.set_dir).complete_manifest()["config"].items()
            if k not in ("set_name", "render_root", "out_root", "inputs", "command")}


def cut_input_shards(set_name: str, render_root: str, shards_root: str, input_sets=INPUT_SETS, *,
                     options: dict | None = None, log=print) -> None:
    """The render set ``<render_root>/<set_name>`` cut into shards for each of ``input_sets`` with ``options``
    (ShardConfig fields), each resumed, or reused when complete."""
    from prep.shards import ShardConfig, build_shards

    for inputs in input_sets:
        shard_cfg = ShardConfig(set_name=set_name, render_root=render_root, out_root=shards_root, inputs=inputs,
                                **(options or {}))
        log(f"shards for {inputs}: {shard_cfg.set_dir}")
        build_shards(shard_cfg, progress=False)


def cut_shards(cfg: InputsStudyConfig, *, log=print) -> None:
    """The render set's shards cut for every input set as its full set was cut (:func:`shard_options`)."""
    cut_input_shards(cfg.set_name, cfg.render_root, cfg.shards_root, INPUT_SETS,
                     options=shard_options(cfg.set_name, cfg.render_root, cfg.shards_root),
                     log=lambda line: log(f"inputs-study: {line}"))


def plan_and_train(cfg: InputsStudyConfig, *, overrides: dict | None = None, verbose="auto", log=print) -> dict:
    """Each input set's steps for ``budget`` seconds (probed once, kept in ``plan.json``) and its trained run."""
    from kpcn_keras.run import Run
    from kpcn_keras.train import train

    group = group_dir(cfg)
    run = Run(group / "run")
    plans = {}
    with PlannedRuns(group, "inputs study") as planned:
        for inputs in INPUT_SETS:
            base = train_config(cfg, inputs, overrides)
            variant = run.for_inputs(InputSet.named(inputs))
            key = {"train": base.identity(), "budget": cfg.budget}
            entry, _ = planned.entry((inputs,), key, variant.dir, functools.partial(plan_steps, base, cfg.budget))
            log(f"inputs-study: {inputs}: {entry['steps']}")
            train(with_steps(base, entry["steps"]), run.dir, verbose=verbose)
            plans[inputs] = {**entry, "run": str(variant.dir), "trained_s": _training_seconds(variant.dir)}
    return plans


def _mean(rows: list[dict], method: str) -> dict:
    return {m: float(np.mean([r[method][m] for r in rows])) for m in SCORES} if all(method in r for r in rows) else {}


def held_out(cfg: InputsStudyConfig, plans: dict, *, log=print) -> dict:
    """Mean scores of every input set's run, the raw input and OIDN on the render set's held-out frames."""
    from kpcn_keras.denoise import Denoiser
    from kpcn_keras.evaluate import held_out_frames
    from kpcn_keras.run import Run
    from prep import baselines

    root = Run(plans["full"]["run"])
    frames = held_out_frames(root, root.record())
    rows = [{"frame": f["name"], "raw": _scores(f["noisy"]["default"], f["reference"])} for f in frames]
    if baselines.oidn_available():
        for row, f in zip(rows, frames):
            row["oidn"] = _scores(baselines.oidn_denoise(f["noisy"], mode="plain"), f["reference"])
    for inputs in INPUT_SETS:
        den = Denoiser.from_run(Run(plans[inputs]["run"]))
        for row, f in zip(rows, frames):
            row[inputs] = _scores(den(f["noisy"])["default"], f["reference"])
        log(f"inputs-study: held-out {inputs}: relMSE {_mean(rows, inputs)['relmse']:.4f}")
    return {"frames": rows, "means": {m: _mean(rows, m) for m in ("raw", "oidn", *INPUT_SETS)}}


def renderers(cfg: InputsStudyConfig, plans: dict, *, log=print) -> tuple[list[dict], list]:
    """Per frame of another renderer: its layout and input set, the model that served it, and the scores of the
    raw input, kpcn, OIDN and the renderer's own denoiser; and the panels of the figure."""
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving

    serving = Serving(Run(plans["full"]["run"]))
    rows, panels = [], []
    for noisy_path, ref_path in renderer_pairs(cfg.frames):
        frame = layouts.read(noisy_path)
        ref = layouts.read(ref_path).layers["default"]
        denoiser = serving.denoiser(frame.inputs, warm_up=True)
        start = time.perf_counter()
        out = denoiser(frame.layers)["default"]
        seconds = time.perf_counter() - start
        scene, spp = exr.parse_render_filename(noisy_path)
        row = {"frame": str(noisy_path), "scene": scene, "spp": spp, "renderer": noisy_path.parent.name,
               "layout": frame.layout, "inputs": frame.inputs.name, "model": serving.record(frame.inputs).inputs.name,
               "seconds": seconds, "raw": _scores(frame.layers["default"], ref), "kpcn": _scores(out, ref)}
        for name, layer in frame.alternatives.items():  # the layer the adapter could have taken instead
            row[f"kpcn_alternative_{name}"] = _scores(denoiser({**frame.layers, name: layer})["default"], ref)
        images = {"input": frame.layers["default"], "kpcn": out, **beside(noisy_path, frame), "reference": ref}
        for name in ("OIDN", "Blender"):
            if name in images:
                row[name.lower()] = _scores(images[name], ref)
        rows.append(row)
        panels.append((f"{row['renderer']}/{scene} {spp} spp", images))
        log(f"inputs-study: {noisy_path}: {frame.layout}, {frame.inputs}, kpcn relMSE {row['kpcn']['relmse']:.4f}"
            + (f", OIDN {row['oidn']['relmse']:.4f}" if "oidn" in row else ""))
    return rows, panels


def pair_files(paths) -> list[tuple[Path, Path, Path]]:
    """(half a, half b, reference) of every pair of renders under ``paths`` (files or folders): each
    ``<scene>-<spp>spp-pair-a.exr`` (``catalogue.pair_names``) with its ``-pair-b.exr`` and the scene's render
    with the most samples, ``<scene>-<spp>spp.exr`` beside it; a half without either is passed over."""
    from prep.render.cycles import catalogue

    cat, out = catalogue(), []
    for given in map(Path, paths):
        for first in sorted(given.rglob("*-pair-a.exr")) if given.is_dir() else [given]:
            half = cat.pair_half(first.name)
            if half is None:
                continue
            second = first.with_name(cat.pair_names(half[0], half[1])[1])
            renders = []
            for p in first.parent.glob(f"{glob.escape(half[0])}-*spp.exr"):
                try:
                    scene, spp = exr.parse_render_filename(p)
                except exr.AOVError:
                    continue
                if scene == half[0]:  # not "<scene>-extra-...": another scene's
                    renders.append((spp, p))
            if second.exists() and renders and max(renders)[0] > half[1]:
                out.append((first, second, max(renders)[1]))
    return out


def pairs(cfg: InputsStudyConfig, plans: dict, *, log=print) -> list[dict]:
    """Per pair of renders under ``cfg.pairs`` (:func:`pair_files`): the scores of their mean
    denoised without variance and with the variance of their difference (``studies.pair_variance``), each by the
    run's model for it, beside the mean's raw scores and OIDN's on it."""
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.studies.pair_variance import read_with_pair_variance
    from prep import baselines
    from prep.exr import VARIANCE_LAYERS
    from prep.render.cycles import catalogue

    serving = Serving(Run(plans["full"]["run"]))
    rows = []
    for first, second, ref_path in pair_files(cfg.pairs):
        with_variance = read_with_pair_variance(first, second)
        layers = {k: v for k, v in with_variance.layers.items() if k not in VARIANCE_LAYERS}
        without = InputSet(split=with_variance.inputs.split, variance=False)
        ref = layouts.read(ref_path).layers["default"]
        scene, spp, _ = catalogue().pair_half(first.name)
        row = {"scene": scene, "spp": spp, "raw": _scores(layers["default"], ref)}
        for key, frame_layers, inputs in (("without", layers, without), ("pair", with_variance.layers,
                                                                         with_variance.inputs)):
            row[key] = _scores(serving.denoiser(inputs)(frame_layers)["default"], ref)
            row[f"{key}_model"] = serving.record(inputs).inputs.name
        if baselines.oidn_available():
            row["oidn"] = _scores(baselines.oidn_denoise(layers, mode="plain"), ref)
        rows.append(row)
        log(f"inputs-study: pair {first.name} + {second.name}: relMSE without variance "
            f"{row['without']['relmse']:.4f}, with the pair's {row['pair']['relmse']:.4f}")
    return rows


def study(cfg: InputsStudyConfig, *, overrides: dict | None = None, command: str | None = None, verbose="auto",
          log=print) -> dict:
    """Run the study (module docstring); writes the three reports and returns the record."""
    report = Report(cfg.out_dir, REPORT)
    report.check_writable()
    if not renderer_pairs(cfg.frames):
        raise KpcnError(f"--frames {' '.join(cfg.frames)}: no noisy frame with a reference beside it")
    session = report.begin()
    cut_shards(cfg, log=log)
    plans = plan_and_train(cfg, overrides=overrides, verbose=verbose, log=log)
    cost = held_out(cfg, plans, log=log)
    rows, panels = renderers(cfg, plans, log=log)
    record = {**session.envelope(command), "config": {**vars(cfg), "frames": list(cfg.frames),
                                                      "pairs": list(cfg.pairs)},
              "overrides": overrides or {}, "machine": session.machine(**deep_learning_stack()), "plans": plans,
              "held_out": cost, "renderers": rows, "pairs": pairs(cfg, plans, log=log)}
    middle = sorted({r["spp"] for r in rows})[len({r["spp"] for r in rows}) // 2]
    shown = [p for p, r in zip(panels, rows) if r["spp"] == middle]
    return report.write(record, format_report(record), lambda _: panels_figure(shown))


# ---------------------------------------------------------------- the report


def _n(value, fmt="{:.4f}") -> str:
    return "–" if value is None else fmt.format(value)


def _get(row: dict, method: str, metric: str):
    return row.get(method, {}).get(metric)


def format_report(record: dict) -> str:
    cfg, rows, cost = record["config"], record["renderers"], record["held_out"]
    lines = [f"# kpcn on other renderers' frames, and what each missing input costs ({record['date']})", "",
             f"`{record['command']}`, {record['started']} to {record['finished']}; {record['machine']['cpus']} CPUs, "
             f"load average {record['machine']['load_average_before'][0]:.2f} before. Every input set trained "
             f"{cfg['budget']:g} s ({cfg['preset']} preset, seed {cfg['seed']}) on the `{cfg['set_name']}` render set "
             "(kpcn_keras/studies/inputs_study.py says how).", "",
             "## Other renderers' frames", "",
             "relMSE, DSSIM and relSE p99.9 against the reference beside each frame. kpcn: the model of the input set "
             "the frame gives; OIDN: `pyoidn` on the same colour, albedo and normal; Blender: the frame Blender's own "
             "denoiser wrote at render time.", "",
             "| frame | layout | inputs | raw relMSE | kpcn relMSE | OIDN relMSE | Blender relMSE | kpcn DSSIM | "
             "OIDN DSSIM | Blender DSSIM | kpcn relSE p99.9 | OIDN relSE p99.9 | Blender relSE p99.9 |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['renderer']}/{r['scene']} {r['spp']} spp | {r['layout']} | {r['inputs']} | "
                     + " | ".join(_n(_get(r, m, s)) for m, s in
                                  (("raw", "relmse"), ("kpcn", "relmse"), ("oidn", "relmse"), ("blender", "relmse"),
                                   ("kpcn", "dssim"), ("oidn", "dssim"), ("blender", "dssim"),
                                   ("kpcn", "relse_p999"), ("oidn", "relse_p999"), ("blender", "relse_p999")))
                     + " |")
    alt = [r for r in rows if "kpcn_alternative_albedo" in r]
    if alt:
        lines += ["", f"Cycles' albedo: with Diffuse Color (the default) kpcn's mean relMSE over these {len(alt)} "
                  f"frames is {np.mean([r['kpcn']['relmse'] for r in alt]):.4f}, with Denoising Albedo clipped to "
                  f"[0, 1] {np.mean([r['kpcn_alternative_albedo']['relmse'] for r in alt]):.4f} (lower on "
                  f"{wins(alt, 'kpcn_alternative_albedo', 'kpcn')} frames)."]
    lines += ["", "| layout | spp | frames | mean raw relMSE | mean kpcn relMSE | mean OIDN relMSE | mean Blender "
              "relMSE | kpcn below OIDN | kpcn below Blender |", "|---|---|---|---|---|---|---|---|---|"]
    for layout in sorted({r["layout"] for r in rows}):
        for spp in sorted({r["spp"] for r in rows if r["layout"] == layout}):
            group = [r for r in rows if r["layout"] == layout and r["spp"] == spp]
            means = [_n(float(np.mean([r[m]["relmse"] for r in group])) if all(m in r for r in group) else None)
                     for m in ("raw", "kpcn", "oidn", "blender")]
            lines.append(f"| {layout} | {spp} | {len(group)} | {' | '.join(means)} | {wins(group)} | "
                         f"{wins(group, other='blender')} |")
    if record["pairs"]:
        lines += ["", "## Two renders of half the samples: variance from their difference", "",
                  "Each frame is the mean of two renders of the scene with different seeds and half the samples, "
                  "denoised without variance (the no-variance model) and with the variance of the mean estimated "
                  "from their difference (`kpcn denoise A --pair B`: the full model); the same pixels either way.", "",
                  "| scene | total spp | raw relMSE | kpcn without variance | kpcn with the pair's variance | OIDN "
                  "relMSE | DSSIM without | DSSIM with | relSE p99.9 without | relSE p99.9 with |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for r in record["pairs"]:
            lines.append(f"| {r['scene']} | {r['spp']} | {r['raw']['relmse']:.4f} | {r['without']['relmse']:.4f} | "
                         f"{r['pair']['relmse']:.4f} | {_n(_get(r, 'oidn', 'relmse'))} | {r['without']['dssim']:.4f} | "
                         f"{r['pair']['dssim']:.4f} | {r['without']['relse_p999']:.4f} | "
                         f"{r['pair']['relse_p999']:.4f} |")
        better = sum(r["pair"]["relmse"] < r["without"]["relmse"] for r in record["pairs"])
        lines += ["", f"The pair's variance lowers relMSE on {better} of {len(record['pairs'])} frames."]
    lines += ["", "## What each missing input costs, at equal training time", "",
              f"The `{cfg['set_name']}` set's {len(cost['frames'])} held-out frames, each denoised by the network of "
              "each input set (the frame restricted to it as `prep.inputs` says), means over the frames.", "",
              "A mean relMSE is carried by the worst frame (`caustics`, whose reference is itself speckled), so "
              "the median over frames and the count of frames where each set beats the full set say more.", "",
              "| inputs | steps | trained s | mean relMSE | median relMSE | DSSIM | relSE p99.9 | frames below full's "
              "relMSE | frames below OIDN |", "|---|---|---|---|---|---|---|---|---|"]
    frames = cost["frames"]
    for inputs in INPUT_SETS:
        plan, mean = record["plans"][inputs], cost["means"][inputs]
        steps = ", ".join(f"{k} {v}" for k, v in plan["steps"].items() if k != "decay_steps")
        median = float(np.median([f[inputs]["relmse"] for f in frames]))
        against = "–" if inputs == "full" else wins(frames, inputs, "full")
        lines.append(f"| {inputs} | {steps} | {plan['trained_s']:.0f} | {mean['relmse']:.4f} | {median:.4f} | "
                     f"{mean['dssim']:.4f} | {mean['relse_p999']:.4f} | {against} | {wins(frames, inputs)} |")
    for method, label in (("raw", "raw input"), ("oidn", "OIDN")):
        mean = cost["means"].get(method) or {}
        if mean:
            median = float(np.median([f[method]["relmse"] for f in frames]))
            lines.append(f"| {label} | – | – | {mean['relmse']:.4f} | {median:.4f} | {mean['dssim']:.4f} | "
                         f"{mean['relse_p999']:.4f} | {wins(frames, method, 'full')} | – |")
    return "\n".join(lines) + "\n"
