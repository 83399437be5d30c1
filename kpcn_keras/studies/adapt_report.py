"""The adaptation report (issue 53): kpcn adapted to each validation frame's two halves, beside Blender's own
denoiser on one render of all the samples.

  .venv/bin/python -m kpcn_keras.studies.adapt_report [FOLDER] [--spp 16,4,64] [--marks 10,30,60,120]
      [--model RUN] [--seed 0] [--out reports] [--cache runs/adapt-report]      # make adapt-report

The contract:

- **Frames** (:func:`frames_ready`): each scene of ``FOLDER`` (a recipe ``<scene>.json`` beside its frames, as
  ``kpcn cycles-validation`` writes them) at each spp of ``--spp`` (in that order: the first is the target) whose
  files are all there: the frame of N spp, Blender's denoised frame of it, its two halves of N/2 spp and the
  scene's reference (its recipe's last frame, or the render with the most samples), names from
  ``prep.render.blender.catalogue``. Where the folder has a manifest with checksums, a file counts only once the
  manifest records it (a scene still rendering is left for later). The folder is looked at again after each
  frame, so scenes that finish during the run are taken, target spp first.
- **Methods**, each scored against the reference (``prep.metrics`` in float64: relMSE, DSSIM, relSE p99.9):
  ``input`` (the halves' mean), ``kpcn pair`` (the model, unadapted, on the mean: ``prep.inputs.mean_layers``, the
  network for what a half has, as ``kpcn denoise --pair`` runs it), ``kpcn adapted S s`` for each mark S
  of ``--marks`` (one :class:`kpcn_keras.adapt.Adapter` run of max(marks) seconds, or ``--steps``; at each mark
  what stopping there gives, ``Adapter.snapshots``: its post-correction applied to the unadapted output, or that
  output itself where the guard refused it), ``blender`` (``<scene>-<N>spp-blender-oidn.exr``), ``kpcn single``
  (the model on the one render of N spp) and ``input single`` (that render).
- **Per frame**: those scores, the guard's outcome at each mark (``Outcome.to_dict``), the adapter's preparation
  seconds, the load average and the busiest other processes when the frame began (the machine is shared).
- **Summary per spp** (:func:`summarise`): per method the median relMSE and DSSIM, the median ratio of relMSE to
  Blender's and the frames strictly below Blender's; per mark how many frames the guard kept it on.
- **Targets** (:func:`targets`), at the first spp of ``--spp`` (16) and the mark :data:`TARGET_MARK` (60 s): below
  Blender's relMSE on at least half the frames; a median ratio to Blender's at least :data:`TARGET_GAIN` below the
  unadapted pair's; no frame's relMSE more than :data:`TARGET_WORST` above the unadapted pair's. The md says which
  hold, on how many frames.
- **Costs** (:func:`costs`): the adaptation's preparation (the model on both halves, their crops), seconds per
  step (held-out checks included, as a run pays them), the model on the mean and the correction's application, for
  a frame wrapped to each ``--costs-size`` (256 x 256 and 1920 x 1080, ``card.frame_of_size``) and at the
  validation resolution, in one process, ``--costs-steps`` steps each; measured once, after the target spp's
  frames.
- **Resumable**: the record is written after every frame (``<out>/adapt.{json,md,png}``); a later run with the
  same settings keeps the rows it finds (and their panel images, cached under ``--cache``) and goes on.
  ``--fresh`` starts over.
- **Figure** ``adapt.png``: the median ratio of relMSE to Blender's against the adaptation's seconds, one line
  per spp (Blender's = 1); under it panels (input | kpcn | kpcn adapted | Blender's | reference) of a few frames at
  the target spp, the participating-media ones (effect group ``media``) first.

Seeds are fixed (``--seed``: the crops, their order, the held-out blocks, the first weights); with seconds the
steps run depend on the machine's speed and load, with ``--steps`` they do not. Bad input (a folder without a
complete frame, an option out of range) is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shlex
import sys
import time
from pathlib import Path

import numpy as np

from kpcn_keras.studies.frames import scores as _scores
from kpcn_keras.studies.report import Report
from prep import layouts
from prep.errors import KpcnError

os.environ.setdefault("KERAS_BACKEND", "torch")

REPORT = "adapt"
DEFAULT_FRAMES = "data/cycles/validation"
DEFAULT_CACHE = "runs/adapt-report"
SPPS = (16, 4, 64)
MARKS = (10.0, 30.0, 60.0, 120.0)
TARGET_MARK = 60.0
TARGET_GAIN = 0.25  # the median ratio to Blender's at least this much lower than the unadapted pair's
TARGET_WORST = 0.02  # no frame more than this much worse than unadapted
MEDIA = "media"  # the effect group of participating media (catalogue.EFFECTS)
PANEL_ROWS = 4
COSTS_SIZES = ((256, 256), (1920, 1080))
BLENDER, PAIR, SINGLE, INPUT, INPUT_SINGLE = "blender", "kpcn pair", "kpcn single", "input", "input single"
UNGUARDED = "kpcn unguarded"  # the target mark's chosen checkpoints applied whatever the guard decided
EXIT_USER_ERROR = 2


def adapted(mark: float) -> str:
    """The method name of kpcn adapted for ``mark`` seconds."""
    return f"kpcn adapted {mark:g} s"


def methods(marks) -> list[str]:
    return [INPUT, PAIR, *map(adapted, marks), UNGUARDED, BLENDER, SINGLE, INPUT_SINGLE]


def target_mark(marks) -> float:
    """The mark the targets are judged at: :data:`TARGET_MARK` where measured, else the largest."""
    return TARGET_MARK if TARGET_MARK in marks else marks[-1]


# ---------------------------------------------------------------- the frames


def _catalogue():
    from prep.render.cycles import catalogue

    return catalogue()


def _recorded(folder: Path) -> set | None:
    """The files the folder's manifest records with checksums, None where it has no such manifest."""
    try:
        found = json.loads((folder / _catalogue().MANIFEST).read_text()).get("sha256")
    except (OSError, ValueError, AttributeError):
        return None
    return set(found) if isinstance(found, dict) else None


def _recipes(folder: Path) -> list[dict]:
    cat = _catalogue()
    try:
        return cat.read_recipes(str(folder))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise KpcnError(f"{folder}: a scene recipe <scene>.json is not readable ({type(exc).__name__}: "
                        f"{exc})") from None


def frame_files(folder: Path, recipe: dict, spp: int) -> dict:
    """The files of ``recipe``'s scene at ``spp`` under ``folder``: ``single``, ``blender``, ``a``, ``b``,
    ``reference`` (the recipe's last frame; else the render with the most samples there)."""
    cat, scene = _catalogue(), recipe["name"]
    a, b = cat.pair_names(scene, spp)
    ref_spp = recipe["frames"][-1] if recipe.get("frames") else max(
        (found[1] for p in folder.glob(f"{scene}-*spp.exr") if (found := _render(p)) and found[0] == scene),
        default=0)
    return {"single": folder / cat.frame_name(scene, spp), "blender": folder / cat.denoised_name(scene, spp),
            "a": folder / a, "b": folder / b, "reference": folder / cat.frame_name(scene, ref_spp)}


def _render(path: Path):
    """(scene, spp) of a frame's file name, None for another file."""
    from prep import exr

    try:
        return exr.parse_render_filename(path)
    except exr.AOVError:
        return None


def frames_ready(folder: Path, spps) -> list[tuple[dict, int, dict]]:
    """(recipe, spp, files) of every complete frame under ``folder`` (module docstring), in ``spps``' order, then
    by scene."""
    recorded = _recorded(folder)
    ready = []
    for spp in spps:
        for recipe in _recipes(folder):
            if recipe.get("frames") and spp not in recipe["frames"][:-1]:
                continue
            files = frame_files(folder, recipe, spp)
            if all(p.is_file() and (recorded is None or p.name in recorded) for p in files.values()):
                ready.append((recipe, spp, files))
    return ready


def groups_of(recipe: dict) -> list[str]:
    groups = recipe.get("groups", recipe.get("effects", []))
    return sorted(set(groups)) if isinstance(groups, list) else []


# ---------------------------------------------------------------- one frame


class Frames:
    """The model's denoisers, loaded once (one per input set a frame has) and each warmed up."""

    def __init__(self, model: Path):
        from kpcn_keras.run import Run
        from kpcn_keras.serving import Serving

        self.serving = Serving(Run(model))
        self.denoisers = {}

    def denoiser(self, inputs):
        if inputs not in self.denoisers:
            self.denoisers[inputs] = self.serving.denoiser(inputs, warm_up=True)
        return self.denoisers[inputs]


def read_halves(files: dict):
    """The two halves of a frame, checked to be two renders of one frame (``batch.read_halves``)."""
    from kpcn_keras.batch import ReadOptions
    from kpcn_keras.batch import read_halves as _read

    return _read(files["a"], ReadOptions(pair=files["b"]))


def adapt_frame(models: Frames, files: dict, settings, marks) -> tuple[dict, dict, dict]:
    """One frame: (images of every method, the guard's outcome at each mark, seconds of each part)."""
    from kpcn_keras.adapt import Adapter, correct
    from prep.inputs import mean_layers

    a, b = read_halves(files)
    mean = mean_layers(a.layers, b.layers)
    denoiser = models.denoiser(a.inputs)
    begin = time.perf_counter()
    plain = denoiser(mean)
    seconds = {"denoise_s": time.perf_counter() - begin}
    single = layouts.read(files["single"])
    images = {INPUT: mean["default"], PAIR: plain["default"],
              SINGLE: models.denoiser(single.inputs)(single.layers)["default"],
              INPUT_SINGLE: single.layers["default"], BLENDER: _read_same(files["blender"], files["a"], a.size),
              "reference": _read_same(files["reference"], files["a"], a.size)}
    begin = time.perf_counter()
    adapter = Adapter(denoiser, [(a.layers, b.layers)], settings)
    seconds["prepare_s"] = time.perf_counter() - begin
    outcome = adapter.run(marks=marks)
    seconds.update(adapt_s=outcome.seconds, steps=outcome.steps)
    guard = {}
    apply = lambda weights: plain["default"] if weights is None else correct(  # noqa: E731
        adapter.apply_weights(weights), plain, mean, denoiser.tile)["default"]
    for mark in marks:
        decided, weights, best = adapter.snapshots[mark]
        guard[f"{mark:g}"] = decided.to_dict()
        images[adapted(mark)] = apply(weights)
        if mark == target_mark(marks):
            images[UNGUARDED] = apply(best)
    return images, guard, seconds


def _read_same(path: Path, frame_path: Path, size) -> np.ndarray:
    image = layouts.read(path).layers["default"]
    layouts.check_same_size(frame_path, size, path, image.shape[:2])
    return image


def score_row(recipe: dict, spp: int, files: dict, images: dict, marks) -> dict:
    ref = images["reference"]
    return {"scene": recipe["name"], "spp": spp, "groups": groups_of(recipe),
            "files": {k: str(v) for k, v in files.items()},
            "scores": {m: _scores(images[m], ref) for m in methods(marks)}}


# ---------------------------------------------------------------- the summary


def _ratio(row: dict, method: str, score: str = "relmse") -> float:
    return row["scores"][method][score] / row["scores"][BLENDER][score]


def summarise(rows: list[dict], marks) -> dict:
    """Per spp: the frames; per method the median relMSE and DSSIM, the median ratio of each to Blender's and the
    frames strictly below Blender's relMSE; per mark the frames the guard kept the correction on."""
    out = {}
    for spp in sorted({r["spp"] for r in rows}):
        sel = [r for r in rows if r["spp"] == spp]
        block = {"frames": len(sel), "methods": {}, "kept": {}}
        for m in methods(marks):
            block["methods"][m] = {
                "median_relmse": float(np.median([r["scores"][m]["relmse"] for r in sel])),
                "median_dssim": float(np.median([r["scores"][m]["dssim"] for r in sel])),
                "median_ratio_blender": float(np.median([_ratio(r, m) for r in sel])),
                "median_dssim_ratio_blender": float(np.median([_ratio(r, m, "dssim") for r in sel])),
                "below_blender": sum(r["scores"][m]["relmse"] < r["scores"][BLENDER]["relmse"] for r in sel)}
        block["kept"] = {f"{mark:g}": sum(r["guard"][f"{mark:g}"]["kept"] for r in sel) for mark in marks}
        block["median_steps"] = {f"{mark:g}": float(np.median([r["guard"][f"{mark:g}"]["steps"] for r in sel]))
                                 for mark in marks}
        out[str(spp)] = block
    return out


def targets(rows: list[dict], spp: int, mark: float) -> dict:
    """The three targets of issue 53 at ``spp`` with ``mark`` seconds of adaptation (module docstring): each with
    its figures and whether it holds (None without frames)."""
    sel = [r for r in rows if r["spp"] == spp]
    method = adapted(mark)
    if not sel or method not in sel[0]["scores"]:
        return {"spp": spp, "mark": mark, "frames": len(sel), "held": None}
    below = sum(r["scores"][method]["relmse"] < r["scores"][BLENDER]["relmse"] for r in sel)
    ratio = float(np.median([_ratio(r, method) for r in sel]))
    unadapted = float(np.median([_ratio(r, PAIR) for r in sel]))
    change = [r["scores"][method]["relmse"] / r["scores"][PAIR]["relmse"] - 1.0 for r in sel]
    worst = max(change)
    found = {"spp": spp, "mark": mark, "frames": len(sel),
             "below_blender": {"frames": below, "needed": math.ceil(len(sel) / 2),
                               "holds": below >= math.ceil(len(sel) / 2)},
             "median_ratio": {"adapted": ratio, "unadapted": unadapted, "gain": 1.0 - ratio / unadapted,
                              "needed_gain": TARGET_GAIN, "holds": ratio <= (1.0 - TARGET_GAIN) * unadapted},
             "worst_change": {"frame": sel[int(np.argmax(change))]["scene"], "change": worst,
                              "allowed": TARGET_WORST, "holds": worst <= TARGET_WORST}}
    found["held"] = all(found[k]["holds"] for k in ("below_blender", "median_ratio", "worst_change"))
    return found


# ---------------------------------------------------------------- the costs


def costs(models: Frames, files: dict, sizes, steps: int, seed: int) -> dict:
    """What adapting costs at the validation resolution and for the frame wrapped to each of ``sizes`` ((width,
    height) each), in this process, ``steps`` steps each (module docstring)."""
    from kpcn_keras.adapt import Adapter, correct
    from kpcn_keras.card import frame_of_size
    from kpcn_keras.settings import AdaptSettings
    from prep.inputs import mean_layers

    a, b = read_halves(files)
    found = {"frame": str(files["a"]), "steps": steps}
    frames = {"validation": (a.layers, b.layers)}
    frames.update({"x".join(map(str, size)): (frame_of_size(a.layers, *size), frame_of_size(b.layers, *size))
                   for size in sizes})
    for name, (ha, hb) in frames.items():
        denoiser, mean = models.denoiser(a.inputs), mean_layers(ha, hb)
        begin = time.perf_counter()
        adapter = Adapter(denoiser, [(ha, hb)], AdaptSettings(steps=steps, seed=seed))
        prepare = time.perf_counter() - begin
        times = [0.0]
        outcome = adapter.run(lambda step, loss, seconds, times=times: times.append(seconds))
        step_s, check_s = _step_and_check(np.diff(times), adapter.settings.check_every)
        begin = time.perf_counter()
        plain = denoiser(mean)
        denoise = time.perf_counter() - begin
        begin = time.perf_counter()
        correct(adapter.net, plain, mean, denoiser.tile)
        found[name] = {"size": [int(ha["depth"].shape[1]), int(ha["depth"].shape[0])], "crops": len(adapter.crops),
                       "prepare_s": prepare, "seconds_per_step": outcome.seconds / outcome.steps,
                       "step_s": step_s, "check_s": check_s, "denoise_s": denoise,
                       "apply_s": time.perf_counter() - begin, "load_average": list(os.getloadavg())}
    return found


def _step_and_check(intervals: np.ndarray, every: int) -> tuple[float, float | None]:
    """(median seconds of a training step, median seconds of a held-out check) from the seconds between the ends
    of consecutive steps (``intervals[k]``: step k + 1's), where a check follows every ``every``-th step and so
    lands in the next interval; the first interval (first-call allocations) left out."""
    index = np.arange(1, len(intervals) + 1)  # the step each interval ends
    checked = (index > 1) & ((index - 1) % every == 0)
    plain = intervals[(~checked) & (index > 1)]
    step = float(np.median(plain)) if plain.size else float(np.median(intervals))
    return step, float(np.median(intervals[checked]) - step) if checked.any() else None


# ---------------------------------------------------------------- the run


def _settings_key(args, model: Path) -> dict:
    """What a resumed run must share with the record it goes on from: the method's code (``adapt.py``) among it,
    so that rows of another method are never mixed in."""
    return {"model": str(model), "marks": list(args.marks), "seed": args.seed, "steps": args.steps,
            "target_spp": args.spp[0], "costs_size": [list(v) for v in args.costs_size],
            "adapt_py_sha256": adapt_sha256()}


def _load(report: Report, key: dict, fresh: bool) -> dict:
    """The record a previous run with the same settings wrote, or an empty one."""
    path = report.path(".json")
    if fresh or not path.exists():
        return {}
    try:
        old = json.loads(path.read_text())
    except (OSError, ValueError):
        return {}
    return old if isinstance(old, dict) and old.get("settings") == key else {}


def _cache_path(cache: Path, row_or_key) -> Path:
    scene, spp = row_or_key
    return Path(cache) / f"{scene}-{spp:05d}spp.npz"


def others(count: int = 6) -> list[str]:
    """What else runs on the machine: the ``count`` busiest other processes as "%CPU nice command line" (the line
    cut at 160 characters), this process and its children left out."""
    import subprocess

    try:
        ps = subprocess.run(["ps", "-eo", "pid,ppid,pcpu,ni,args", "--sort=-pcpu"], capture_output=True, text=True,
                            timeout=30).stdout
    except (OSError, subprocess.SubprocessError):
        return []
    rows = [line.split(None, 2) for line in ps.splitlines()[1:]]
    return [rest.strip()[:160] for pid, ppid, rest in rows if os.getpid() not in (int(pid), int(ppid))][:count]


def adapt_sha256() -> str:
    """The SHA-256 of ``kpcn_keras/adapt.py``: the method measured."""
    from kpcn_keras import adapt
    from prep.files import sha256_file

    return sha256_file(adapt.__file__)


def code_version() -> dict:
    """The commit of the code that ran, whether its tree had changes, and the SHA-256 of ``kpcn_keras/adapt.py``
    (the method measured)."""
    import subprocess

    from kpcn_keras import adapt

    root = Path(adapt.__file__).resolve().parents[1]
    git = ["git", "-C", str(root)]
    try:
        commit = subprocess.run([*git, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30).stdout.strip()
        dirty = bool(subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                                    text=True, timeout=30).stdout.strip())
    except (OSError, subprocess.SubprocessError):
        commit, dirty = None, None
    return {"commit": commit or None, "changed": dirty, "adapt_py_sha256": adapt_sha256()}


def study(args, command: str, log=print) -> dict:
    """Run the study (module docstring); returns the record written last."""
    from kpcn_keras.batch import torch_threads
    from kpcn_keras.run import default_model
    from kpcn_keras.settings import AdaptSettings

    folder = Path(args.frames)
    if not folder.is_dir():
        raise KpcnError(f"{folder}: no such folder of validation frames")
    model = Path(args.model) if args.model else default_model().dir
    if not model.is_dir():
        raise KpcnError(f"--model {model}: no such run or model folder")
    report = Report(Path(args.out), REPORT)
    report.check_writable()
    if not frames_ready(folder, args.spp):
        raise KpcnError(f"{folder}: no complete frame at {', '.join(map(str, args.spp))} spp (a scene's frame, "
                        "Blender's denoised frame, the two halves and the reference)")
    session, key = report.begin(), _settings_key(args, model)
    old = _load(report, key, args.fresh)
    cache = Path(args.cache)
    rows = [r for r in old.get("frames", []) if _cache_path(cache, (r["scene"], r["spp"])).exists()]
    record = {"settings": key, "folder": str(folder), "code": code_version(), "busy_at_start": others(),
              "threads": torch_threads(),
              "costs": old.get("costs"), "frames": rows, "resumed": len(rows)}
    models = Frames(model)
    settings = AdaptSettings(seconds=max(args.marks), steps=args.steps, seed=args.seed)
    while True:
        done = {(r["scene"], r["spp"]) for r in rows}
        todo = [f for f in frames_ready(folder, args.spp) if (f[0]["name"], f[1]) not in done]
        if (record["costs"] is None and args.costs_steps and rows and not args.report_only
                and not any(f[1] == args.spp[0] for f in todo)):
            first = next(r for r in rows if r["spp"] == args.spp[0])
            log("adapt-report: costs at " + ", ".join(f"{w}x{h}" for w, h in args.costs_size) + " ...")
            record["costs"] = costs(models, {k: Path(v) for k, v in first["files"].items()}, args.costs_size,
                                    args.costs_steps, args.seed)
            _write(report, session, record, command, cache, args)
        if args.report_only or not todo or (args.limit and len(rows) - record["resumed"] >= args.limit):
            break
        recipe, spp, files = todo[0]
        load, running = list(os.getloadavg()), others()
        images, guard, seconds = adapt_frame(models, files, settings, args.marks)
        row = {**score_row(recipe, spp, files, images, args.marks), "guard": guard, "seconds": seconds,
               "load_average": load, "busy": running, "adapt_py_sha256": record["code"]["adapt_py_sha256"]}
        _save_images(_cache_path(cache, (row["scene"], spp)), images, args.marks)
        rows.append(row)
        log(f"adapt-report: {recipe['name']} {spp} spp: " + ", ".join(
            f"{m} {row['scores'][m]['relmse']:.4f}" for m in (PAIR, adapted(target_mark(args.marks)), UNGUARDED,
                                                               BLENDER)))
        _write(report, session, record, command, cache, args)
    return _write(report, session, record, command, cache, args)


PANEL_COLUMNS = (INPUT, PAIR, "adapted", BLENDER, "reference")


def _save_images(path: Path, images: dict, marks) -> None:
    """The panel images of a frame (input, unadapted, adapted at the target mark, Blender's, reference), kept for
    the figure of a resumed run."""
    from prep.files import atomic_path

    shown = {INPUT: images[INPUT], PAIR: images[PAIR], "adapted": images[adapted(target_mark(marks))],
             BLENDER: images[BLENDER], "reference": images["reference"]}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **{k: np.asarray(v, np.float32) for k, v in shown.items()})


def panel_rows(rows: list[dict], spp: int) -> list[dict]:
    """The frames shown in panels: at ``spp``, those with participating media first, then the others, by scene,
    :data:`PANEL_ROWS` at most."""
    sel = sorted((r for r in rows if r["spp"] == spp), key=lambda r: (MEDIA not in r["groups"], r["scene"]))
    return sel[:PANEL_ROWS]


def _write(report: Report, session, record: dict, command: str, cache: Path, args) -> dict:
    rows, marks = record["frames"], args.marks
    out = {**session.envelope(command), **record, "methods": methods(marks),
           "machine": session.machine(threads=record["threads"]), "summary": summarise(rows, marks) if rows else {},
           "targets": targets(rows, args.spp[0], target_mark(marks))}
    panels = [(r, _cache_path(cache, (r["scene"], r["spp"]))) for r in panel_rows(rows, args.spp[0])]
    out["panels"] = [r["scene"] for r, _ in panels]
    out["target_mark"] = target_mark(marks)
    return report.write(out, format_report(out), lambda rec: figure(rec, panels))


def figure(record: dict, panels):
    """The error-against-seconds plot over the panels."""
    from prep.files import pyplot

    plt = pyplot()
    marks = record["settings"]["marks"]
    fig = plt.figure(figsize=(11, 3.6 + 2.4 * len(panels)))
    top, bottom = fig.subfigures(2, 1, height_ratios=[3.6, 2.4 * len(panels)]) if panels else (fig, None)
    axes = top.subplots(1, 2)
    for ax, score in zip(axes, ("median_ratio_blender", "median_dssim_ratio_blender")):
        for spp, block in record["summary"].items():
            ys = [block["methods"][PAIR][score]] + [block["methods"][adapted(m)][score] for m in marks]
            ax.plot([0.0, *marks], ys, marker="o", label=f"{spp} spp ({block['frames']} frames)")
        ax.axhline(1.0, color="k", lw=1, ls="--", label="Blender's denoiser")
        ax.set_xlabel("adaptation seconds")
        ax.set_ylabel(("relMSE" if score == "median_ratio_blender" else "DSSIM") + " / Blender's (median)")
        ax.legend(fontsize=7)
    if panels:
        _draw_panels(bottom, panels, record["target_mark"])
    return fig


def _draw_panels(target, panels, mark: float) -> None:
    """One row per frame of ``panels`` ((row, cached images)), :data:`PANEL_COLUMNS` in order, each image
    tonemapped (``prep.colour.tonemap``, the same for every column)."""
    from prep.colour import tonemap

    axes = target.subplots(len(panels), len(PANEL_COLUMNS), squeeze=False)
    names = {PAIR: "kpcn (unadapted)", "adapted": f"kpcn adapted {mark:g} s", BLENDER: "Blender's"}
    for row_axes, (row, path) in zip(axes, panels):
        with np.load(path) as data:
            images = {k: data[k] for k in data.files}
        for ax, name in zip(row_axes, PANEL_COLUMNS):
            ax.axis("off")
            ax.imshow(tonemap(images[name]), interpolation="nearest")
            title = names.get(name, name)
            if name in (PAIR, "adapted", BLENDER):
                title += f"\nrelMSE {row['scores'][adapted(mark) if name == 'adapted' else name]['relmse']:.4f}"
            elif name == INPUT:
                title = f"{row['scene']} {row['spp']} spp\n({', '.join(row['groups'])}) input"
            ax.set_title(title, fontsize=8)


# ---------------------------------------------------------------- the markdown


def _n(value, fmt="{:.4f}") -> str:
    return "–" if value is None else fmt.format(value)


def _holds(flag) -> str:
    return "**holds**" if flag else "**does not hold**"


def _targets_lines(t: dict) -> list[str]:
    head = [f"## Targets (issue 53): {t['spp']} spp, {t['mark']:g} s of adaptation", "",
            "1. Below Blender's own denoiser at equal samples (relMSE) on at least half the validation frames.",
            f"2. The median ratio to Blender's at least {TARGET_GAIN:.0%} lower than the unadapted pair's.",
            f"3. No frame more than {TARGET_WORST:.0%} worse (relMSE) than the unadapted pair.", ""]
    if t.get("held") is None:
        return head + [f"No frame at {t['spp']} spp yet: the targets are not checked.", ""]
    b, m, w = t["below_blender"], t["median_ratio"], t["worst_change"]
    return head + [
        f"- 1 {_holds(b['holds'])}: below Blender's on {b['frames']} of {t['frames']} frames (needs {b['needed']}).",
        f"- 2 {_holds(m['holds'])}: median ratio {m['adapted']:.3f} adapted vs {m['unadapted']:.3f} unadapted, "
        f"{m['gain']:+.1%} lower (needs {TARGET_GAIN:.0%}).",
        f"- 3 {_holds(w['holds'])}: the worst frame, {w['frame']}, changes by {w['change']:+.2%} (allowed "
        f"{TARGET_WORST:+.0%}).",
        "", f"All three hold: **{'yes' if t['held'] else 'no'}** (on the {t['frames']} frames measured).", ""]


def _summary_lines(record: dict) -> list[str]:
    head = ["spp", "frames", "method", "median relMSE", "median DSSIM", "median relMSE / Blender's",
            "median DSSIM / Blender's", "frames below Blender's"]
    lines = ["## Medians per spp", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for spp, block in record["summary"].items():
        for m, s in block["methods"].items():
            lines.append(f"| {spp} | {block['frames']} | {m} | {s['median_relmse']:.4f} | {s['median_dssim']:.4f} | "
                         f"{s['median_ratio_blender']:.3f} | {s['median_dssim_ratio_blender']:.3f} | "
                         f"{s['below_blender']} of {block['frames']} |")
    lines += ["", "Frames on which the guard kept the correction, per mark: " + "; ".join(
        f"{spp} spp: " + ", ".join(f"{k} s {v} of {b['frames']}" for k, v in b["kept"].items())
        for spp, b in record["summary"].items()) + ". Median steps run by each mark (at the held-out check that "
        "decided it; the machine's load sets how many a second buys): " + "; ".join(
        f"{spp} spp: " + ", ".join(f"{k} s {v:g}" for k, v in b["median_steps"].items())
        for spp, b in record["summary"].items()) + ".", ""]
    return lines


def _frame_lines(record: dict) -> list[str]:
    marks = record["settings"]["marks"]
    shown = [INPUT, PAIR, *map(adapted, marks), UNGUARDED, BLENDER, SINGLE]
    head = ["scene", "spp", "groups", *(f"{m} relMSE" for m in shown), "adapted / Blender's",
            *(f"{m} DSSIM" for m in shown), "guard per mark", "steps", "load"]
    lines = ["## Per frame", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    target = adapted(target_mark(marks))
    for r in record["frames"]:
        guard = " ".join(("kept" if r["guard"][f"{m:g}"]["kept"] else "no") for m in marks)
        lines.append(f"| {r['scene']} | {r['spp']} | {', '.join(r['groups'])} | "
                     + " | ".join(_n(r["scores"][m]["relmse"]) for m in shown)
                     + f" | {_ratio(r, target):.3f} | " + " | ".join(_n(r["scores"][m]["dssim"]) for m in shown)
                     + f" | {guard} | {r['seconds']['steps']} | {r['load_average'][0]:.2f} |")
    return lines + [""]


def _costs_lines(c: dict | None, rows: list[dict]) -> list[str]:
    if not c:
        return ["## Costs", "", "Not measured yet (they are measured once the target spp's frames are done).", ""]
    sizes = [k for k in c if isinstance(c[k], dict)]
    head = ["frame", "crops", "preparation s", "s per step (checks included)", "s per training step",
            "s per held-out check", "kpcn on the mean s", "correction applied s", "load"]
    lines = ["## What adapting costs", "",
             f"One process, {c['steps']} steps each (held-out checks included), the frame `{c['frame']}` as it is "
             "and wrapped to the larger sizes (`card.frame_of_size`). Preparation: the model on both halves and "
             "their crops (at most 16 of 128 pixels a side per half, so a training step costs the same at any "
             "size; a held-out check every 10 steps runs every crop); a run of S seconds then takes about "
             "S / (s per step) steps.", "",
             "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k in sizes:
        v = c[k]
        lines.append(f"| {v['size'][0]}x{v['size'][1]} | {v['crops']} | {v['prepare_s']:.2f} | "
                     f"{v['seconds_per_step']:.4f} | {v['step_s']:.4f} | {_n(v['check_s'])} | {v['denoise_s']:.2f} | "
                     f"{v['apply_s']:.2f} | {v['load_average'][0]:.2f} |")
    runs = [r["seconds"]["adapt_s"] / r["seconds"]["steps"] for r in rows if r["seconds"]["steps"]]
    if runs:  # many steps, under the same load as the scores: the probe's few steps are noisier
        lines += ["", f"Over the frames' own runs ({len(runs)}, at the validation size, checks included): median "
                  f"{np.median(runs):.3f} s per step (from {min(runs):.3f} to {max(runs):.3f}), with preparations "
                  f"of median {np.median([r['seconds']['prepare_s'] for r in rows]):.2f} s."]
    return lines + [""]


def _seen(record: dict) -> list[str]:
    """The commands (cut at 100 characters) among the three busiest processes at any frame's start, once each, not
    already named at the run's start; the CPU share and nice left out."""
    def command(line: str) -> str:  # "%CPU nice command line", or "%CPU name" as earlier runs recorded it
        parts = line.split(None, 2)
        nice = len(parts) == 3 and parts[1].lstrip("-").isdigit()
        return (parts[2] if nice else line.split(None, 1)[-1])[:100]

    start = {command(p) for p in record["busy_at_start"]}
    seen = dict.fromkeys(command(p) for r in record["frames"] for p in r.get("busy", [])[:3])
    return [c for c in seen if c not in start and "ps -eo" not in c] or ["nothing else"]


def _code(code: dict | None) -> str:
    if not code:
        return "unrecorded"
    return (f"`{(code['commit'] or 'no commit')[:12]}`" + (" with changes" if code["changed"] else "")
            + f", `kpcn_keras/adapt.py` sha256 `{code['adapt_py_sha256'][:12]}`")


def format_report(record: dict) -> str:
    s, machine = record["settings"], record["machine"]
    lines = [f"# Adapting kpcn to each frame's two halves, beside Blender's own denoiser ({record['date']})", "",
             f"`{record['command']}`, {record['started']} to {record['finished']}; model `{s['model']}`, seed "
             f"{s['seed']}, marks {', '.join(f'{m:g}' for m in s['marks'])} s"
             + (f", {s['steps']} steps" if s["steps"] else "") + f"; frames `{record['folder']}`"
             + (f" ({record['resumed']} frames kept from an earlier run with the same settings)"
                if record["resumed"] else "") + f"; code {_code(record.get('code'))}.", "",
             f"Machine: {machine['cpus']} CPUs, torch threads {record['threads']}, load average "
             f"{machine['load_average_before'][0]:.2f} before and {machine['load_average_after'][0]:.2f} after; "
             "busiest other processes at the start (%CPU, nice, command): " + "; ".join(
                 f"`{p}`" for p in record["busy_at_start"])
             + ". Also among the three busiest at a frame's start: " + "; ".join(f"`{c}`" for c in _seen(record))
             + ". Seconds of adaptation buy fewer steps on a busy machine than on an idle one; each frame's load "
             "average and steps are in its row, what ran beside it in the json.", "",
             "Each frame of N spp is given as two renders of N/2 spp (its halves, different seeds). `input`: their "
             "mean; `kpcn pair`: the model on the mean, unadapted (0 s); `kpcn adapted S s`: after S seconds of "
             "adaptation on the halves (one run, what stopping at S gives: `Adapter.snapshots`; the unadapted "
             "output where the guard refused the correction); `kpcn unguarded`: the chosen checkpoints at "
             f"{record['target_mark']:g} s applied whatever the guard decided (what the guard forgoes, or spares); "
             "`blender`: Blender's own denoiser (OIDN) on one "
             "render of N spp; `kpcn single`: the model on that one render. Scores against the 2048-spp reference "
             "in float64 (`prep.metrics`).", ""]
    if record["targets"].get("held") is not None or record["frames"]:
        lines += _targets_lines(record["targets"])
    if record["summary"]:
        lines += _summary_lines(record)
    lines += _costs_lines(record.get("costs"), record["frames"])
    lines += _frame_lines(record)
    lines += ["`adapt.png`: the median ratio of relMSE (left) and DSSIM (right) to Blender's against the seconds of "
              "adaptation, one line per spp (0 s: unadapted); under it input | kpcn (pair, unadapted) | kpcn adapted "
              f"({record['target_mark']:g} s) | Blender's | reference of " + ", ".join(record["panels"])
              + " (participating media first).", ""]
    return "\n".join(lines)


def _floats(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give numbers separated by commas") from None
    if not values or any(v <= 0 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give positive numbers separated by commas")
    return values


def _spps(text: str) -> tuple[int, ...]:
    values = _floats(text)
    if any(v != int(v) or int(v) % 2 for v in values):
        raise argparse.ArgumentTypeError(f"{text!r}: give even sample counts (each frame has two equal halves)")
    return tuple(int(v) for v in values)


def _size(text: str) -> tuple[int, int]:
    try:
        width, height = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give WIDTH,HEIGHT") from None
    return width, height


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.adapt_report",
                                description=__doc__.splitlines()[0])
    p.add_argument("frames", nargs="?", default=DEFAULT_FRAMES, help="the validation folder (default: %(default)s)")
    p.add_argument("--spp", type=_spps, default=SPPS,
                   help="total spp of the frames, the target first (default: 16,4,64)")
    p.add_argument("--marks", type=_floats, default=MARKS,
                   help="seconds of adaptation measured, one run of the largest (default: 10,30,60,120)")
    p.add_argument("--steps", type=int, default=None, help="train exactly this many steps instead of the largest "
                   "mark's seconds (reproducible on any machine)")
    p.add_argument("--seed", type=int, default=0, help="the adaptation's seed (default: %(default)s)")
    p.add_argument("--model", help="the model (default: the shipped one)")
    p.add_argument("--out", default="reports", help="report folder (default: %(default)s)")
    p.add_argument("--cache", default=DEFAULT_CACHE, help="the panels' images of each frame, kept for a resumed run "
                   "(default: %(default)s)")
    p.add_argument("--fresh", action="store_true", help="start over: keep no frame of an earlier run")
    p.add_argument("--report-only", action="store_true", help="write the md and png again from the json an earlier "
                   "run with the same settings wrote, computing nothing")
    p.add_argument("--limit", type=int, default=0, help="stop after this many new frames (0: all)")
    p.add_argument("--costs-size", type=_size, nargs="+", default=COSTS_SIZES, help="WIDTH,HEIGHT of each size the "
                   "cost probe wraps the frame to (default: 256,256 1920,1080)")
    p.add_argument("--costs-steps", type=int, default=20, help="steps timed per size (0: no cost probe)")
    return p


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    command = shlex.join(["python", "-m", "kpcn_keras.studies.adapt_report", *(sys.argv[1:] if argv is None else argv)])
    from prep.processes import keep_freed_memory

    keep_freed_memory()
    try:
        if args.steps is not None and args.steps < 1:
            raise KpcnError(f"--steps {args.steps}: give 1 or more")
        study(args, command)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        print(f"adapt-report: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
