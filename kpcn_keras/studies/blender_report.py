"""The Blender report: kpcn's models on Blender Cycles frames beside what a Blender user already has.

  .venv/bin/python -m kpcn_keras.studies.blender_report [FOLDER ...] [--model NAME=RUN ...] [--out reports]
      # default: ../shared/validation/blender, the shipped model (models/default); make blender-report

The contract:

- **Frames** (``kpcn_keras.studies.frames.renderer_pairs``): every ``<scene>-<spp>spp.exr`` under the folders
  that is not its scene's reference (the same folder's render of the scene with the most samples, 2048 spp in
  the validation sets), with that reference, read in its own layout (``prep.layouts``).
- **Methods**, each scored against the reference: the raw input; each model (``--model NAME=RUN``, repeated: a
  run or model folder each, side by side, e.g. before and after a retraining; default ``default=`` the shipped
  model), by the run's network for what the frame has (``Run.serving``); Blender's own denoised frame
  (``<scene>-<spp>spp-blender-oidn.exr``: OIDN at render time, albedo + normal, prefiltered), where the folder
  has it; and each OIDN mode of :func:`oidn_modes` (``pyoidn``; none where it is not installed).
- **Quality modes** (:func:`model_columns`): a model that holds several (``Run.quality_modes``) is one column
  per mode, ``kpcn NAME MODE``, each denoised by that mode's networks (``InferenceSettings(quality=MODE)``), and
  OIDN is scored at each of those qualities too (``oidn_<mode> <quality>``; at ``high``, OIDN's default, under
  the plain names), so that each mode stands beside OIDN's same one; the record's ``quality_modes`` says which.
  A model with only ``balanced`` is one column, ``kpcn NAME``, and the record has the keys it always had.
- **Scores** (``prep.metrics``, float64): relMSE, DSSIM and relSE p99.9, per frame; their means per spp and per
  effect group and spp.
- **Effect groups**: a scene's groups are the ``groups`` (else ``effects``) list of ``<scene>.json`` beside its
  frames (the recipe the Cycles scene generator writes); a scene without one is in the group ``unknown``, one
  with an empty list in ``none``. A frame counts in every group it has.
- **Against the anchors**, per model and spp: the frames whose relMSE is below Blender's (of the frames that
  have Blender's), below the better OIDN mode's (the lower relMSE of the modes run on that frame), and the
  median over frames of the ratio of its relMSE to Blender's.
- **Writes** ``<out>/blender.json`` (every number), ``blender.md`` (the tables) and ``blender.png`` (input |
  each model | Blender's | reference, one row per effect group at each of :data:`PANEL_SPPS`: the group's first
  scene by name), through ``kpcn_keras.studies.report``.

Frames of any layout ``kpcn denoise`` reads come in the same way: the project's own renders (its held-out
scenes' folders, references at 512 spp) and the Mitsuba fixture (``../shared/fixtures/mitsuba``, 8 and 1024 spp).
Without Blender's frames the anchor is the better OIDN mode: Blender's columns stay empty, the OIDN counts are
"k of N".

Bad input (a folder without a noisy frame and its reference, a ``--model`` that is not ``NAME=RUN`` or names no
run, a recipe that is not JSON) is one line and exit status 2.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from kpcn_keras.config import DEFAULT_QUALITY, QUALITY_MODES
from kpcn_keras.studies.frames import SCORES, panels_figure, read_pairs, renderer_denoised, some_renderer_pairs
from kpcn_keras.studies.frames import scores as _scores
from kpcn_keras.studies.report import Report
from prep import baselines, exr, layouts
from prep.errors import KpcnError

REPORT = "blender"
DEFAULT_FRAMES = ("../shared/validation/blender",)
PANEL_SPPS = (4, 16)
UNKNOWN_GROUP = "unknown"  # a scene without a recipe beside its frames
NO_GROUP = "none"  # a recipe that lists no effect
BLENDER = "blender"
RAW = "raw"
EXIT_USER_ERROR = 2


def oidn_modes(qualities=(baselines.DEFAULT_OIDN_QUALITY,)) -> dict:
    """The OIDN modes scored beside kpcn: name -> function of a frame's layers (``prep.layouts`` names) to the
    denoised colour, one per ``prep.baselines.OIDN_MODES`` and each of ``qualities`` (OIDN's own: ``oidn_plain``,
    ``oidn_prefiltered`` at ``high``, ``oidn_plain fast`` ... at another); none where ``pyoidn`` is not installed.
    Every table and the "better OIDN mode" take what is here."""
    if not baselines.oidn_available():
        return {}
    return {oidn_method(mode, quality): functools.partial(baselines.oidn_denoise, mode=mode, quality=quality)
            for quality in qualities for mode in baselines.OIDN_MODES}


def oidn_method(mode: str, quality: str = baselines.DEFAULT_OIDN_QUALITY) -> str:
    """The method name of OIDN in ``mode`` at ``quality``: ``oidn_<mode>`` at OIDN's default quality (the names
    the reports always had), ``oidn_<mode> <quality>`` at another."""
    return f"oidn_{mode}" if quality == baselines.DEFAULT_OIDN_QUALITY else f"oidn_{mode} {quality}"


def several_modes(models: dict[str, Path]) -> dict[str, list[str]]:
    """{name: its quality modes} of the ``models`` that hold more than the default one (``Run.quality_modes``)."""
    from kpcn_keras.run import Run

    found = {name: Run(path).quality_modes() for name, path in models.items()}
    return {name: modes for name, modes in found.items() if modes != [DEFAULT_QUALITY]}


def model_columns(models: dict[str, Path]) -> dict[str, tuple[Path, str]]:
    """The model columns of the report: key -> (model folder, quality mode). A model with only the default mode
    is one column keyed by its name; one with several, a column per mode keyed ``NAME MODE``."""
    several = several_modes(models)
    columns = {}
    for name, path in models.items():
        for mode in several.get(name, [DEFAULT_QUALITY]):
            columns[f"{name} {mode}" if name in several else name] = (Path(path), mode)
    return columns


def oidn_qualities(models: dict[str, Path]) -> tuple[str, ...]:
    """OIDN's qualities scored beside ``models``: its default (``high``) and each mode of a model that has
    several, in the order of ``config.QUALITY_MODES``."""
    wanted = {baselines.DEFAULT_OIDN_QUALITY, *(m for modes in several_modes(models).values() for m in modes)}
    return tuple(q for q in QUALITY_MODES if q in wanted)


def model_method(name: str) -> str:
    """The method name of model ``name`` in the record: ``kpcn <name>``."""
    return f"kpcn {name}"


def parse_models(given: list[str] | None) -> dict[str, Path]:
    """``--model NAME=RUN`` (or a bare RUN, named by its folder) -> {name: run folder}; default: the shipped
    model as ``default``. KpcnError naming the option for a malformed one or a name given twice."""
    from kpcn_keras.run import default_model

    if not given:
        return {"default": default_model().dir}
    models = {}
    for item in given:
        name, sep, path = item.partition("=")
        if not sep:
            name, path = Path(item).name, item
        if not name or not path:
            raise KpcnError(f"--model {item!r}: give NAME=RUN (a run or model folder)")
        if name in models:
            raise KpcnError(f"--model {item!r}: the name {name} is given twice")
        models[name] = Path(path)
    return models


def effect_groups(noisy_path: Path) -> list[str]:
    """The effect groups of a frame's scene, from the recipe ``<scene>.json`` beside it (module docstring)."""
    scene, _ = exr.parse_render_filename(noisy_path)
    recipe_path = Path(noisy_path).with_name(f"{scene}.json")
    if not recipe_path.exists():
        return [UNKNOWN_GROUP]
    try:
        recipe = json.loads(recipe_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KpcnError(f"{recipe_path}: not a readable JSON recipe ({exc})") from None
    groups = recipe.get("groups", recipe.get("effects")) if isinstance(recipe, dict) else None
    if not isinstance(groups, list) or not all(isinstance(g, str) for g in groups):
        raise KpcnError(f"{recipe_path}: no list of names under 'groups' or 'effects'")
    return sorted(set(groups)) or [NO_GROUP]


def score_frames(paths, models: dict[str, Path], *, keep=lambda row: False, log=print) -> tuple[list, dict]:
    """Per frame under ``paths``: its scene, spp, groups and the scores of every method (module docstring);
    and the images of the frames ``keep(row)`` asks for: {frame: {column: image}}."""
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving
    from kpcn_keras.settings import InferenceSettings

    pairs = some_renderer_pairs(paths)
    groups = {noisy: effect_groups(noisy) for noisy, _ in pairs}  # a bad recipe is refused before any work
    servings = {key: Serving(Run(path), InferenceSettings(quality=mode))
                for key, (path, mode) in model_columns(models).items()}
    modes = oidn_modes(oidn_qualities(models))
    rows, images = [], {}
    for noisy_path, frame, ref, scene, spp in read_pairs(pairs):
        shown = {"input": frame.layers["default"]}
        for name, serving in servings.items():
            shown[model_method(name)] = serving.denoiser(frame.inputs)(frame.served_layers())["default"]
        own = renderer_denoised(noisy_path)
        if own.exists():
            shown[BLENDER] = layouts.read(own).layers["default"]
            layouts.check_same_size(noisy_path, frame.size, own, shown[BLENDER].shape[:2], "Blender's frame")
        given = baselines.oidn_inputs(frame)
        for mode, denoise in modes.items():
            shown[mode] = denoise(given)
        row = {"frame": str(noisy_path), "scene": scene, "spp": spp, "groups": groups[noisy_path],
               "layout": frame.layout, "inputs": frame.inputs.name,
               "scores": {RAW if k == "input" else k: _scores(v, ref) for k, v in shown.items()}}
        rows.append(row)
        if keep(row):
            images[row["frame"]] = {**shown, "reference": ref}
        log(f"blender-report: {noisy_path.name}: " + ", ".join(
            f"{k} {v['relmse']:.4f}" for k, v in row["scores"].items()))
    return rows, images


def _best_oidn(row: dict) -> float | None:
    values = [row["scores"][m]["relmse"] for m in oidn_mode_names(row)]
    return min(values) if values else None


def oidn_mode_names(row: dict) -> list[str]:
    """The OIDN modes a row was scored with (the methods named ``oidn``...)."""
    return [m for m in row["scores"] if m.startswith("oidn")]


def against_anchors(rows: list[dict], method: str) -> dict:
    """``method``'s frames below Blender's and below the better OIDN mode (counts ``below`` of ``of``, the
    frames that have the anchor) and the median ratio of its relMSE to Blender's (None without Blender's)."""
    with_blender = [r for r in rows if BLENDER in r["scores"]]
    with_oidn = [r for r in rows if _best_oidn(r) is not None]
    ratios = [r["scores"][method]["relmse"] / r["scores"][BLENDER]["relmse"] for r in with_blender]
    return {"below_blender": sum(r["scores"][method]["relmse"] < r["scores"][BLENDER]["relmse"]
                                 for r in with_blender),
            "with_blender": len(with_blender),
            "below_oidn": sum(r["scores"][method]["relmse"] < _best_oidn(r) for r in with_oidn),
            "with_oidn": len(with_oidn),
            "median_ratio_blender": float(np.median(ratios)) if ratios else None}


def means(rows: list[dict]) -> dict:
    """The mean of each score of each method over ``rows``, of the methods every row has."""
    methods = [m for m in rows[0]["scores"] if all(m in r["scores"] for r in rows)]
    return {m: {s: float(np.mean([r["scores"][m][s] for r in rows])) for s in SCORES} for m in methods}


def summarise(rows: list[dict], models) -> dict:
    """Per spp, and per effect group and spp: the frames, the mean scores and each model column (``models``: the
    keys of :func:`model_columns`) against the anchors."""
    def block(group_rows):
        return {"frames": len(group_rows), "means": means(group_rows),
                "models": {name: against_anchors(group_rows, model_method(name)) for name in models}}

    spps = sorted({r["spp"] for r in rows})
    groups = sorted({g for r in rows for g in r["groups"]})
    return {"by_spp": {str(spp): block([r for r in rows if r["spp"] == spp]) for spp in spps},
            "by_group": {g: {str(spp): block(sel) for spp in spps
                             if (sel := [r for r in rows if r["spp"] == spp and g in r["groups"]])}
                         for g in groups}}


def panel_frames(rows: list[dict]) -> list[tuple[str, str]]:
    """(group, frame) of each panel row: each group's first scene by name at each of :data:`PANEL_SPPS`."""
    chosen = []
    for group in sorted({g for r in rows for g in r["groups"]}):
        for spp in PANEL_SPPS:
            first = sorted((r for r in rows if group in r["groups"] and r["spp"] == spp), key=lambda r: r["scene"])
            if first:
                chosen.append((group, first[0]["frame"]))
    return chosen


def study(paths, models: dict[str, Path], out_dir, *, note: str = "", command: str | None = None,
          log=print) -> dict:
    """Score every frame under ``paths`` (module docstring); writes the three reports and returns the record."""
    report = Report(Path(out_dir), REPORT)
    report.check_writable()
    session = report.begin()
    for name, path in models.items():
        if not Path(path).is_dir():
            raise KpcnError(f"--model {name}={path}: no such run or model folder")
    # the panel rows are known only once every frame's groups are: keep the images of every frame at a panel spp
    rows, images = score_frames(paths, models, keep=lambda row: row["spp"] in PANEL_SPPS, log=log)
    panels = panel_frames(rows)
    keys = list(model_columns(models))
    record = {**session.envelope(command), "frames_given": [str(p) for p in paths],
              "models": {name: str(path) for name, path in models.items()}, "note": note,
              "oidn_modes": list(oidn_modes(oidn_qualities(models))), "machine": session.machine(), "frames": rows,
              "summary": summarise(rows, keys),
              "panels": [{"group": g, "frame": f} for g, f in panels]}
    if several := several_modes(models):  # only then: models with the default mode alone keep the keys they had
        record["quality_modes"] = several
    columns = ("input", *map(model_method, keys), BLENDER, "reference")
    shown = [(f"{g}: {Path(f).name}", images[f]) for g, f in panels]
    return report.write(record, format_report(record), lambda _: panels_figure(shown, columns))


# ---------------------------------------------------------------- the report


def _n(value, fmt="{:.4f}") -> str:
    return "–" if value is None else fmt.format(value)


def _count(against: dict, key: str) -> str:
    of = against[f"with_{key}"]
    return f"{against[f'below_{key}']} of {of}" if of else "–"


def model_keys(record: dict) -> list[str]:
    """The model columns of a record (:func:`model_columns`' keys): ``NAME MODE`` for each mode of a model in its
    ``quality_modes``, ``NAME`` for any other."""
    modes = record.get("quality_modes", {})
    return [f"{n} {m}" if n in modes else n for n in record["models"] for m in modes.get(n, [DEFAULT_QUALITY])]


def _methods(record: dict) -> list[str]:
    return [RAW, *map(model_method, model_keys(record)), BLENDER, *record["oidn_modes"]]


def _block_table(title: str, blocks: dict, record: dict) -> list[str]:
    """One row per (key, spp) block: the mean relMSE, DSSIM and relSE p99.9 of each method, and each model
    against the anchors."""
    methods = _methods(record)
    head = (["", "spp", "frames"] + [f"{m} {s}" for s in ("relMSE", "DSSIM", "relSE p99.9") for m in methods]
            + [f"{model_method(n)} {c}" for n in model_keys(record)
               for c in ("below Blender's", "below the better OIDN", "median ratio to Blender's")])
    lines = [title, "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for key, by_spp in blocks.items():
        for spp, block in by_spp.items():
            cells = [_n(block["means"].get(m, {}).get(s)) for s in SCORES for m in methods]
            for name in model_keys(record):
                a = block["models"][name]
                cells += [_count(a, "blender"), _count(a, "oidn"), _n(a["median_ratio_blender"], "{:.2f}×")]
            lines.append(f"| {key} | {spp} | {block['frames']} | " + " | ".join(cells) + " |")
    return lines + [""]


def format_report(record: dict) -> str:
    methods = _methods(record)
    models = ", ".join(f"`{model_method(n)}` = `{p}`" for n, p in record["models"].items())
    oidn = (", ".join(f"`{m}`" for m in record["oidn_modes"]) or
            "none (pyoidn is not installed where this ran: no OIDN column)")
    with_blender = any(BLENDER in r["scores"] for r in record["frames"])
    title = ("kpcn on Blender Cycles frames, beside Blender's own denoiser" if with_blender else
             "kpcn beside OIDN, on frames without Blender's own denoised frame")
    lines = [f"# {title} ({record['date']})", "",
             f"`{record['command']}`, {record['started']} to {record['finished']}; "
             f"{record['machine']['cpus']} CPUs, load average {record['machine']['load_average_before'][0]:.2f} "
             f"before. Frames: {', '.join(f'`{p}`' for p in record['frames_given'])}. Models: {models}. "
             f"OIDN modes: {oidn}.", ""]
    if record["note"]:
        lines += [record["note"], ""]
    lines += ["Every score is against the scene's reference, in float64 (`prep.metrics`). `blender`: the frame "
              "Blender's own denoiser wrote at render time (OIDN, albedo + normal, prefiltered). \"below\" "
              "counts frames whose relMSE is strictly lower; the better OIDN is the lower of the modes run on "
              "that frame. kpcn_keras/studies/blender_report.py says how.", ""]
    lines += _block_table("## Per spp (means over the frames)", {"all": record["summary"]["by_spp"]}, record)
    lines += _block_table("## Per effect group (a frame counts in each of its scene's groups)",
                          record["summary"]["by_group"], record)
    head = ["scene", "spp", "groups"] + [f"{m} {s}" for s in ("relMSE", "DSSIM", "relSE p99.9") for m in methods]
    lines += ["## Per frame", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in record["frames"]:
        cells = [_n(r["scores"].get(m, {}).get(s)) for s in SCORES for m in methods]
        lines.append(f"| {r['scene']} | {r['spp']} | {', '.join(r['groups'])} | " + " | ".join(cells) + " |")
    lines += ["", f"`{REPORT}.png`: input | each model | Blender's | reference, one row per effect group at "
              f"{' and '.join(map(str, PANEL_SPPS))} spp (its first scene): "
              + "; ".join(f"{p['group']} {Path(p['frame']).name}" for p in record["panels"]) + "."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.blender_report",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("frames", nargs="*", default=list(DEFAULT_FRAMES),
                        help="folders (or files) of Cycles frames with their references (default: %(default)s)")
    parser.add_argument("--model", action="append", metavar="NAME=RUN",
                        help="a model to score, named (repeat for several, side by side; default: the shipped "
                        "model as 'default')")
    parser.add_argument("--out", default="reports", help="report folder (default: %(default)s)")
    parser.add_argument("--note", default="", help="a paragraph the report shows under its head")
    args = parser.parse_args(argv)
    command = shlex.join(["python", "-m", "kpcn_keras.studies.blender_report",
                          *(sys.argv[1:] if argv is None else argv)])
    try:
        study(args.frames, parse_models(args.model), args.out, note=args.note, command=command)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        print(f"blender-report: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    return 0


if __name__ == "__main__":
    sys.exit(main())
