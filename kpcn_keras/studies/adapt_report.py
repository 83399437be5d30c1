"""The adaptation report (issue 53): kpcn adapted to each validation frame's two halves, beside Blender's own
denoiser on one render of all the samples.

  .venv/bin/python -m kpcn_keras.studies.adapt_report [FOLDER] [--more FOLDER ...] [--spp 16,4,64]
      [--marks 10,30,60,120] [--model RUN] [--seed 0] [--out reports] [--cache runs/adapt-report]  # make adapt-report

The contract:

- **Frames** (:func:`frames_ready`): each scene of ``FOLDER`` (a recipe ``<scene>.json`` beside its frames, as
  ``kpcn cycles-validation`` writes them) at each spp of ``--spp`` (in that order: the first is the target) whose
  files are all there: the frame of N spp, Blender's denoised frame of it, its two halves of N/2 spp and the
  scene's reference (its recipe's last frame, or the render with the most samples), names from
  ``prep.render.blender.catalogue``. Where the folder has a manifest with checksums, a file counts only once the
  manifest records it (a scene still rendering is left for later). The folder is looked at again after each
  frame, so scenes that finish during the run are taken, target spp first. Each folder of ``--more`` (the
  project's own scenes, ``kpcn render --pair``'s set: no recipes, no Blender frames) the same, each scene's
  family its group, after the validation folder at each spp; its rows have their own summary
  (``more_summary``), out of the targets.
- **Methods**, each scored against the reference (``prep.metrics`` in float64: relMSE, DSSIM, relSE p99.9):
  ``input`` (the halves' mean), ``kpcn pair`` (the model, unadapted, on the mean: ``prep.inputs.mean_layers``, the
  network for what a half has, as ``kpcn denoise --pair`` runs it), ``kpcn adapted S s`` for each mark S
  of ``--marks`` (one :class:`kpcn_keras.adapt.Adapter` run of max(marks) seconds, or ``--steps``; at each mark
  what stopping there gives, ``Adapter.snapshots``: its post-correction applied to the unadapted output, or that
  output itself where the guard refused it), ``blender`` (``<scene>-<N>spp-blender-oidn.exr``; in a folder without
  Blender's frames the better OIDN mode on the one render, :func:`_anchor`, named in the row's ``anchor``),
  ``kpcn single`` (the model on the one render of N spp) and ``input single`` (that render).
- **Per frame**: those scores, the guard's outcome at each mark (``Outcome.to_dict``), the adapter's preparation
  seconds, the load average and the busiest other processes when the frame began (the machine is shared).
- **Summary per spp** (:func:`summarise`): per method the median relMSE and DSSIM, the median ratio of relMSE to
  Blender's and the frames strictly below Blender's; per mark how many frames the guard kept it on, the steps run
  and the step the folds chose (where their held-out loss was lowest: what more seconds would not change).
- **Targets** (:func:`targets`), at the first spp of ``--spp`` (16) and the mark :data:`TARGET_MARK` (60 s): below
  Blender's relMSE on at least half the frames; a median ratio to Blender's at least :data:`TARGET_GAIN` below the
  unadapted pair's; no frame's relMSE more than :data:`TARGET_WORST` above the unadapted pair's. The md says which
  hold, on how many frames, and what the first two would read were the guard never wrong (``any_guard``: per
  frame the better of the unadapted output and the correction, chosen with the reference).
- **Costs** (:func:`costs`): the adaptation's preparation (the model on both halves, their crops), seconds per
  step (held-out checks included, as a run pays them), the model on the mean and the correction's application, for
  a frame wrapped to each ``--costs-size`` (256 x 256 and 1920 x 1080, ``card.frame_of_size``) and at the
  validation resolution, in one process, ``--costs-steps`` steps each; measured once, after the target spp's
  frames.
- **Resumable**: the record is written after every frame (``<out>/adapt.{json,md,png}``); a later run with the
  same settings keeps the rows it finds (and their panel images, cached under ``--cache``) and goes on.
  ``--fresh`` starts over; ``--report-only`` computes the tables, md and png again from the json, its run's
  command, times and machine kept.
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

from kpcn_keras.studies.adapt_report_md import (
    BLENDER,
    INPUT,
    INPUT_SINGLE,
    PAIR,
    SINGLE,
    TARGET_GAIN,
    TARGET_WORST,
    UNGUARDED,
    _ratio,
    adapted,
    figure,
    format_report,
    methods,
    panel_rows,
    target_mark,
)
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
COSTS_SIZES = ((256, 256), (1920, 1080))
EXIT_USER_ERROR = 2


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
    """The scene recipes of a Cycles folder; for a folder without any (``kpcn render --pair``'s set), one for each
    scene whose halves are there: its name and, as its one group, its family (the name without its index)."""
    cat = _catalogue()
    try:
        recipes = cat.read_recipes(str(folder))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise KpcnError(f"{folder}: a scene recipe <scene>.json is not readable ({type(exc).__name__}: "
                        f"{exc})") from None
    scenes = sorted({found[0] for p in folder.glob("*-pair-a.exr") if (found := cat.pair_half(p.name))})
    return recipes or [{"name": s, "groups": [s.rsplit("-", 1)[0]]} for s in scenes]


def frame_files(folder: Path, recipe: dict, spp: int) -> dict:
    """The files of ``recipe``'s scene at ``spp`` under ``folder``: ``single``, ``blender`` (Cycles folders alone:
    their recipes say which effects they hold), ``a``, ``b``, ``reference`` (the recipe's last frame; else the
    render with the most samples there)."""
    cat, scene = _catalogue(), recipe["name"]
    a, b = cat.pair_names(scene, spp)
    ref_spp = recipe["frames"][-1] if recipe.get("frames") else max(
        (found[1] for p in folder.glob(f"{scene}-*spp.exr") if (found := _render(p)) and found[0] == scene),
        default=0)
    files = {"single": folder / cat.frame_name(scene, spp), "blender": folder / cat.denoised_name(scene, spp),
             "a": folder / a, "b": folder / b, "reference": folder / cat.frame_name(scene, ref_spp)}
    if "effects" not in recipe:  # no Blender frame: the anchor is the better OIDN mode (adapt_frame)
        del files["blender"]
    return files


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


def adapt_frame(models: Frames, files: dict, settings, marks) -> tuple[dict, dict, dict, str]:
    """One frame: (images of every method, the guard's outcome at each mark, seconds of each part, the anchor
    ``BLENDER`` stands for: :func:`_anchor`)."""
    from kpcn_keras.adapt import Adapter, correct
    from prep.inputs import mean_layers

    a, b = read_halves(files)
    mean = mean_layers(a.layers, b.layers)
    denoiser = models.denoiser(a.inputs)
    begin = time.perf_counter()
    plain = denoiser(mean)
    seconds = {"denoise_s": time.perf_counter() - begin}
    single = layouts.read(files["single"])
    reference = _read_same(files["reference"], files["a"], a.size)
    anchor, anchor_image = _anchor(files, single, reference, a.size)
    images = {INPUT: mean["default"], PAIR: plain["default"],
              SINGLE: models.denoiser(single.inputs)(single.layers)["default"],
              INPUT_SINGLE: single.layers["default"], BLENDER: anchor_image, "reference": reference}
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
    return images, guard, seconds, anchor


def _anchor(files: dict, single, reference: np.ndarray, size) -> tuple[str, np.ndarray]:
    """(name, image) of what kpcn is judged against on one render of all the samples (``single``): Blender's own
    denoised frame where the folder has it, else the better, by relMSE against ``reference``, of OIDN's modes
    (``blender_report.oidn_modes``, the modes every report scores: prefiltered auxiliaries as Blender runs it, and
    plain)."""
    from kpcn_keras.studies.blender_report import oidn_modes
    from prep import metrics

    if "blender" in files:
        return BLENDER, _read_same(files["blender"], files["a"], size)
    modes = oidn_modes()
    if not modes:
        raise KpcnError(f"{files['single']}: no Blender frame beside it, and the better OIDN mode in its place needs "
                        "pyoidn (pip install -e '.[oidn]')")
    found = {name: denoise(single.layers) for name, denoise in modes.items()}
    best = min(found, key=lambda m: metrics.relmse(found[m], reference))
    return best, found[best]


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


def summarise(rows: list[dict], marks) -> dict:
    """Per spp: the frames; per method the median relMSE and DSSIM, the median ratio of each to Blender's and the
    frames strictly below Blender's relMSE; per mark the frames the guard kept the correction on, the median steps
    run and the median step the folds chose (over frames and folds), and the frames whose chosen checkpoints at the
    last mark are those of the target mark."""
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
        # where the held-out loss stopped falling: the folds' chosen steps (0: the model's output)
        block["median_chosen_step"] = {f"{mark:g}": float(np.median([s for r in sel
                                                                       for s in r["guard"][f"{mark:g}"]["best_steps"]]))
                                       for mark in marks}
        last, target = f"{marks[-1]:g}", f"{target_mark(marks):g}"
        block["same_choice_at_last_mark"] = sum(r["guard"][last]["best_steps"] == r["guard"][target]["best_steps"]
                                                for r in sel)
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
    found["any_guard"] = _any_guard(sel, unadapted)
    return found


def _any_guard(sel: list[dict], unadapted: float) -> dict:
    """The most a guard could give with these corrections: per frame the better by relMSE, chosen with the
    reference, of the two things a guard chooses between (the unadapted output and the target mark's chosen
    checkpoints applied, ``UNGUARDED``): what the targets would read were the guard never wrong."""
    best = [min(r["scores"][PAIR]["relmse"], r["scores"][UNGUARDED]["relmse"]) for r in sel]
    ratio = float(np.median([b / r["scores"][BLENDER]["relmse"] for b, r in zip(best, sel)]))
    return {"below_blender": sum(b < r["scores"][BLENDER]["relmse"] for b, r in zip(best, sel)),
            "median_ratio": ratio, "gain": 1.0 - ratio / unadapted}


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
            "target_spp": args.spp[0], "costs_size": [list(v) for v in args.costs_size], "more": list(args.more),
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


def _save_images(path: Path, images: dict, marks) -> None:
    """The panel images of a frame (input, unadapted, adapted at the target mark, the anchor, reference), kept for
    the figure of a resumed run."""
    from prep.files import atomic_path

    shown = {INPUT: images[INPUT], PAIR: images[PAIR], "adapted": images[adapted(target_mark(marks))],
             BLENDER: images[BLENDER], "reference": images["reference"]}
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez_compressed(f, **{k: np.asarray(v, np.float32) for k, v in shown.items()})


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


def _folders(args) -> list[Path]:
    """The folders of frames: the validation folder (the targets' frames) first, then those of ``--more``."""
    folders = [Path(args.frames), *map(Path, args.more)]
    for folder in folders:
        if not folder.is_dir():
            raise KpcnError(f"{folder}: no such folder of frames")
        if not frames_ready(folder, args.spp):
            raise KpcnError(f"{folder}: no complete frame at {', '.join(map(str, args.spp))} spp (a scene's frame, "
                            "Blender's denoised frame in a Cycles folder, the two halves and the reference)")
    if len({f.name for f in folders}) < len(folders):
        raise KpcnError("--more: each folder of frames needs a name of its own (the report's rows say which)")
    return folders


def _todo(folders: list[Path], spps, rows: list[dict]) -> list[tuple]:
    """(folder, recipe, spp, files) of each frame ready and not yet measured, spp by spp (the target's first), each
    the validation folder's first."""
    done = {(r["set"], r["scene"], r["spp"]) for r in rows}
    return [(folder, *f) for spp in spps for folder in folders for f in frames_ready(folder, (spp,))
            if (folder.name, f[0]["name"], f[1]) not in done]


def study(args, command: str, log=print) -> dict:
    """Run the study (module docstring); returns the record written last."""
    from kpcn_keras.batch import torch_threads
    from kpcn_keras.run import default_model
    from kpcn_keras.settings import AdaptSettings

    folders = _folders(args)
    model = Path(args.model) if args.model else default_model().dir
    if not model.is_dir():
        raise KpcnError(f"--model {model}: no such run or model folder")
    report = Report(Path(args.out), REPORT)
    report.check_writable()
    session, key = report.begin(), _settings_key(args, model)
    old = _load(report, key, args.fresh)
    cache = Path(args.cache)
    rows = [r for r in old.get("frames", []) if _cache_path(cache, (r["scene"], r["spp"])).exists()]
    record = {"settings": key, "folder": str(folders[0]), "more": [str(f) for f in folders[1:]],
              "code": code_version(), "busy_at_start": others(), "threads": torch_threads(),
              "costs": old.get("costs"), "frames": rows, "resumed": len(rows)}
    models = Frames(model)

    def save() -> dict:
        return _write(report, record, session.envelope(command), session.machine(threads=record["threads"]), cache)

    settings = AdaptSettings(seconds=max(args.marks), steps=args.steps, seed=args.seed)
    while True:
        todo = _todo(folders, args.spp, rows)
        if (record["costs"] is None and args.costs_steps and rows
                and not any(f[0] == folders[0] and f[2] == args.spp[0] for f in todo)):
            first = next(r for r in rows if r["spp"] == args.spp[0])
            log("adapt-report: costs at " + ", ".join(f"{w}x{h}" for w, h in args.costs_size) + " ...")
            record["costs"] = costs(models, {k: Path(v) for k, v in first["files"].items()}, args.costs_size,
                                    args.costs_steps, args.seed)
            save()
        if not todo or (args.limit and len(rows) - record["resumed"] >= args.limit):
            break
        folder, recipe, spp, files = todo[0]
        load, running = list(os.getloadavg()), others()
        images, guard, seconds, anchor = adapt_frame(models, files, settings, args.marks)
        row = {"set": folder.name, **score_row(recipe, spp, files, images, args.marks), "anchor": anchor,
               "guard": guard, "seconds": seconds, "load_average": load, "busy": running,
               "adapt_py_sha256": record["code"]["adapt_py_sha256"]}
        _save_images(_cache_path(cache, (row["scene"], spp)), images, args.marks)
        rows.append(row)
        log(f"adapt-report: {recipe['name']} {spp} spp: " + ", ".join(
            f"{m} {row['scores'][m]['relmse']:.4f}" for m in (PAIR, adapted(target_mark(args.marks)), UNGUARDED))
            + f", {anchor} {row['scores'][BLENDER]['relmse']:.4f}")
        save()
    return save()


RECORD_KEYS = ("settings", "folder", "more", "code", "busy_at_start", "threads", "costs", "frames", "resumed")
ENVELOPE_KEYS = ("date", "command", "started", "finished")


def rewrite(args) -> dict:
    """``--report-only``: the record at ``--out`` as its run wrote it (its settings, command, times and machine
    kept), its summaries, targets, md and png computed again from its rows; no frame is run."""
    report = Report(Path(args.out), REPORT)
    path = report.path(".json")
    try:
        old = json.loads(path.read_text())
        record, envelope = {k: old[k] for k in RECORD_KEYS}, {k: old[k] for k in ENVELOPE_KEYS}
    except (OSError, ValueError, KeyError) as exc:
        raise KpcnError(f"{path}: no adaptation report to write again ({type(exc).__name__}: {exc})") from None
    return _write(report, record, envelope, old["machine"], Path(args.cache))


def _write(report: Report, record: dict, envelope: dict, machine: dict, cache: Path) -> dict:
    """The record, its md and its png: the summary, targets and panels of the validation folder's frames at the
    settings' marks and target spp; each further folder's summary apart (``more_summary``)."""
    marks, spp = tuple(record["settings"]["marks"]), record["settings"]["target_spp"]
    first = Path(record["folder"]).name
    rows = [r for r in record["frames"] if r["set"] == first]
    more = {Path(f).name: [r for r in record["frames"] if r["set"] == Path(f).name] for f in record["more"]}
    out = {**envelope, **record, "methods": methods(marks), "machine": machine,
           "summary": summarise(rows, marks) if rows else {},
           "more_summary": {name: summarise(sel, marks) for name, sel in more.items() if sel},
           "targets": targets(rows, spp, target_mark(marks))}
    panels = [(r, _cache_path(cache, (r["scene"], r["spp"]))) for r in panel_rows(rows, spp)]
    out["panels"] = [r["scene"] for r, _ in panels]
    out["target_mark"] = target_mark(marks)
    return report.write(out, format_report(out), lambda rec: figure(rec, panels))


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
    p.add_argument("frames", nargs="?", default=DEFAULT_FRAMES, help="the validation folder, whose frames the "
                   "targets are judged on (default: %(default)s)")
    p.add_argument("--more", nargs="+", default=[], metavar="FOLDER", help="further folders of frames in pairs, "
                   "each its own tables: the project's held-out scenes (kpcn render --pair), judged against the "
                   "better OIDN mode where a folder has no Blender frames")
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
    p.add_argument("--report-only", action="store_true", help="write the md and png again from the json at --out, "
                   "its settings, command and times kept, running no frame")
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
        rewrite(args) if args.report_only else study(args, command)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        print(f"adapt-report: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
