"""The auxiliaries study: does kpcn gain from denoising its albedo, normal and depth before its networks see them?

  kpcn aux-study [FOLDER ...] [--model RUN] [--out reports]      # make aux-study

The contract:

- **Frames**: those of the Blender report (``kpcn_keras.studies.frames.renderer_pairs``): every
  ``<scene>-<spp>spp.exr`` under the folders with its scene's reference, and Blender's own denoised frame
  beside it where the folder has one; default the held-out Cycles validation set.
- **Variants**, each the same model (default the shipped one, by its network for what the frame has,
  ``Serving``) on the frame whose auxiliaries are given by ``prep.auxiliary.auxiliaries`` (the one place they
  are chosen, so that a variant that helps can be trained and served with the same call): ``raw`` (as rendered:
  today's kpcn, the Blender report's figures), ``oracle`` (method ``clean``: those of the scene's render with the
  most samples below the reference, the 64-spp frame in the validation set: at that spp the oracle is the raw
  frame), ``oidn`` (OIDN's auxiliary filters, as Blender runs them; left out without ``pyoidn``) and ``nlm``
  (kpcn's own variance-guided NLM prefilter on all three, the variance estimated from the layer where the
  frame has none).
- **Scores** (``prep.metrics``, float64, against the reference): relMSE and DSSIM of each variant and of
  Blender's frame; per spp and variant: the median over frames of the ratio of its relMSE to Blender's, the
  frames whose relMSE is below Blender's, the mean relMSE and DSSIM; and the seconds each prefilter took.
- **Check** (``--blender-record``, default ``reports/blender.json``): where that record scored the same model
  (by its folder) on the same frames, the raw variant's relMSE and DSSIM beside the record's, and the largest
  difference; the raw variant is the Blender report's denoise, so it is 0.
- **Writes** ``<out>/aux.json`` (every number), ``aux.md`` (the tables) and ``aux.png`` (a crop of one 4-spp
  frame, the one the oracle gains most on: input | each variant | Blender's | reference).

Bad input (a folder without a noisy frame and its reference, a model folder that is not there) is one line
naming it and exit status 2.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from kpcn_keras.studies.frames import panels_figure, read_pairs, some_renderer_pairs
from kpcn_keras.studies.frames import scores as _scores
from kpcn_keras.studies.report import Report
from prep import auxiliary, baselines, exr, layouts
from prep.errors import KpcnError

REPORT = "aux"
DEFAULT_FRAMES = ("data/cycles/validation",)
DEFAULT_RECORD = "reports/blender.json"
BLENDER = "blender"
# variant -> the prep.auxiliary method that gives it
VARIANTS = {"raw": "raw", "oracle": "clean", "oidn": "oidn", "nlm": "nlm"}
# what each variant gives the networks, as the report says it (prep.auxiliary's table)
DESCRIPTIONS = {"raw": "as rendered", "oracle": "the scene's render with the most samples below the reference",
                "oidn": "OIDN's auxiliary filters: albedo and normal each by an RT filter with that layer alone, "
                        "depth through the albedo's filter as a grey image over its maximum",
                "nlm": "prep.albedo's variance-guided NLM on all three, the variance estimated from each layer "
                       "(prep.auxiliary.local_variance: the smallest of four directional second-difference "
                       "estimates over 3x3)"}
PANEL_SPP = 4
CROP = 64  # the panel's crop, pixels a side (the whole frame where it is smaller)


def variants() -> dict[str, str]:
    """The variants this machine runs (``oidn`` only where ``pyoidn`` is installed)."""
    return {k: m for k, m in VARIANTS.items() if m != "oidn" or baselines.oidn_available()}


def method(variant: str) -> str:
    return f"kpcn {variant}"


def cleanest(pairs) -> dict[Path, Path]:
    """Each noisy frame -> its scene's noisy frame with the most samples (below the reference), in its folder."""
    best: dict[tuple[Path, str], tuple[int, Path]] = {}
    for noisy, _ in pairs:
        scene, spp = exr.parse_render_filename(noisy)
        key = (Path(noisy).parent, scene)
        if key not in best or spp > best[key][0]:
            best[key] = (spp, Path(noisy))
    return {Path(n): best[(Path(n).parent, exr.parse_render_filename(n)[0])][1] for n, _ in pairs}


def score_frames(paths, model: Path, names: dict[str, str], *, log=print) -> tuple[list, dict]:
    """Per frame: its scene, spp, the scores of each variant and of Blender's frame, the seconds each prefilter
    took; and the images of the frames at :data:`PANEL_SPP`: {frame: {column: image}}."""
    from kpcn_keras.run import Run
    from kpcn_keras.serving import Serving

    pairs = some_renderer_pairs(paths)
    clean_of, cleans = cleanest(pairs), {}
    serving = Serving(Run(model))
    rows, images = [], {}
    for noisy_path, frame, ref, scene, spp in read_pairs(pairs):
        shown, seconds = {"input": frame.layers["default"]}, {}
        denoise = serving.denoiser(frame.inputs)
        if denoise.auxiliaries != auxiliary.RAW:  # its variants would be prefiltered twice
            raise KpcnError(f"{denoise.run.dir}: trained with --auxiliaries {denoise.auxiliaries}; the study "
                            "varies what a network trained on raw auxiliaries is given: pass such a model")
        for variant, how in names.items():
            clean = None
            if how == "clean":
                source = clean_of[Path(noisy_path)]
                if source not in cleans:
                    cleans[source] = layouts.read(source).layers
                clean = cleans[source]
                layouts.check_same_size(noisy_path, frame.size, source, clean["default"].shape[:2], "oracle")
            begin = time.perf_counter()
            given = auxiliary.auxiliaries(frame.layers, how, clean=clean)
            seconds[variant] = time.perf_counter() - begin
            shown[method(variant)] = denoise(given)["default"]
        own = baselines.renderer_denoised(noisy_path)
        if own.exists():
            shown[BLENDER] = layouts.read(own).layers["default"]
            layouts.check_same_size(noisy_path, frame.size, own, shown[BLENDER].shape[:2], "Blender's frame")
        row = {"frame": str(noisy_path), "scene": scene, "spp": spp, "inputs": frame.inputs.name,
               "oracle_from": str(clean_of[Path(noisy_path)]), "prefilter_s": seconds,
               "scores": {k: {s: v for s, v in _scores(x, ref).items() if s != "relse_p999"}
                          for k, x in shown.items()}}
        rows.append(row)
        if spp == PANEL_SPP:
            images[row["frame"]] = {**shown, "reference": ref}
        log(f"aux-study: {Path(noisy_path).name}: " + ", ".join(
            f"{k} {v['relmse']:.4f}" for k, v in row["scores"].items()))
    return rows, images


def summarise(rows: list[dict], names) -> dict:
    """Per spp and variant: the frames, median ratio of relMSE to Blender's, frames below Blender's (of the
    frames that have Blender's), frames whose relMSE and whose DSSIM are below the raw variant's, mean relMSE
    and DSSIM, mean prefilter seconds; Blender's means."""
    out = {}
    for spp in sorted({r["spp"] for r in rows}):
        sel = [r for r in rows if r["spp"] == spp]
        own = [r for r in sel if BLENDER in r["scores"]]
        block = {"frames": len(sel), "with_blender": len(own), "variants": {}}
        for v in names:
            m = method(v)
            ratios = [r["scores"][m]["relmse"] / r["scores"][BLENDER]["relmse"] for r in own]
            block["variants"][v] = {
                "median_ratio_blender": float(np.median(ratios)) if ratios else None,
                "below_blender": sum(r["scores"][m]["relmse"] < r["scores"][BLENDER]["relmse"] for r in own),
                "below_raw": {s: sum(r["scores"][m][s] < r["scores"][method("raw")][s] for r in sel)
                              for s in ("relmse", "dssim")},
                "relmse": float(np.mean([r["scores"][m]["relmse"] for r in sel])),
                "dssim": float(np.mean([r["scores"][m]["dssim"] for r in sel])),
                "prefilter_s": float(np.mean([r["prefilter_s"][v] for r in sel]))}
        if own:
            block[BLENDER] = {s: float(np.mean([r["scores"][BLENDER][s] for r in own])) for s in ("relmse", "dssim")}
        out[str(spp)] = block
    return out


def check_against(record_path: Path, model: Path, rows: list[dict]) -> dict | None:
    """The raw variant beside the Blender report's record of the same model on the same frames (module
    docstring); None where there is no such record or it scored another model."""
    try:
        record = json.loads(Path(record_path).read_text())
    except (OSError, ValueError):
        return None
    names = [n for n, p in record.get("models", {}).items() if Path(p).resolve() == Path(model).resolve()]
    if not names:
        return None
    theirs = {Path(r["frame"]).resolve(): r["scores"][f"kpcn {names[0]}"] for r in record.get("frames", [])}
    pairs = [(r["scores"][method("raw")], theirs[Path(r["frame"]).resolve()]) for r in rows
             if Path(r["frame"]).resolve() in theirs]
    if not pairs:
        return None
    return {"record": str(record_path), "model": names[0], "frames": len(pairs),
            "max_abs_diff": {s: max(abs(a[s] - b[s]) for a, b in pairs) for s in ("relmse", "dssim")}}


def panel(rows: list[dict], images: dict, names) -> tuple[str, dict] | None:
    """(title, {column: crop}) of the :data:`PANEL_SPP` frame the oracle gains most on (by relMSE against raw;
    the first by name without an oracle), cut to :data:`CROP` pixels about the point where raw and the best
    variant differ most."""
    at = [r for r in rows if r["frame"] in images]
    if not at:
        return None
    best = "oracle" if "oracle" in names else "raw"
    row = max(at, key=lambda r: r["scores"][method("raw")]["relmse"] / r["scores"][method(best)]["relmse"])
    shown = images[row["frame"]]
    h, w = shown["input"].shape[:2]
    diff = np.abs(np.asarray(shown[method("raw")], np.float64) - shown[method(best)]).sum(axis=-1)
    y, x = np.unravel_index(np.argmax(diff), diff.shape)
    c = min(CROP, h, w)
    y0, x0 = int(np.clip(y - c // 2, 0, h - c)), int(np.clip(x - c // 2, 0, w - c))
    title = f"{Path(row['frame']).name} [{y0}:{y0 + c}, {x0}:{x0 + c}]"
    return title, {k: v[y0 : y0 + c, x0 : x0 + c] for k, v in shown.items()}


def study(paths, model: Path, out_dir, *, record_path=DEFAULT_RECORD, command: str | None = None,
          log=print) -> dict:
    """Score every frame under ``paths`` with each variant (module docstring); writes the reports."""
    report = Report(Path(out_dir), REPORT)
    report.check_writable()
    session = report.begin()
    if not Path(model).is_dir():
        raise KpcnError(f"--model {model}: no such run or model folder")
    names = variants()
    rows, images = score_frames(paths, Path(model), names, log=log)
    shown = panel(rows, images, names)
    record = {**session.envelope(command), "frames_given": [str(p) for p in paths], "model": str(model),
              "variants": names, "machine": session.machine(), "frames": rows, "summary": summarise(rows, names),
              "check": check_against(Path(record_path), Path(model), rows),
              "panel": shown[0] if shown else None}
    columns = ("input", *map(method, names), BLENDER, "reference")
    return report.write(record, format_report(record),
                        lambda _: panels_figure([shown] if shown else [], columns))


def _n(value, fmt="{:.4f}") -> str:
    return "–" if value is None else fmt.format(value)


def format_report(record: dict) -> str:
    lines = [f"# kpcn with clean auxiliary inputs ({record['date']})", "",
             f"`{record['command']}`, {record['started']} to {record['finished']}; {record['machine']['cpus']} "
             f"CPUs. Frames: {', '.join(f'`{p}`' for p in record['frames_given'])}. Model: `{record['model']}`. "
             "Variants (the auxiliaries the networks see, `prep.auxiliary`): "
             + "; ".join(f"`{v}` ({DESCRIPTIONS.get(v, m)})" for v, m in record["variants"].items()) + ".", "",
             "Scores against the scene's reference, float64 (`prep.metrics`); \"below\": relMSE strictly below "
             "Blender's own denoised frame. kpcn_keras/studies/aux_study.py says how.", "",
             "| spp | variant | median relMSE ratio to Blender's | frames below Blender's | frames below raw "
             "(relMSE, DSSIM) | mean relMSE | mean DSSIM | prefilter s/frame |", "|---|---|---|---|---|---|---|---|"]
    for spp, block in record["summary"].items():
        for v, s in block["variants"].items():
            lines.append(f"| {spp} | {v} | {_n(s['median_ratio_blender'], '{:.3f}×')} | {s['below_blender']} of "
                         f"{block['with_blender']} | {s['below_raw']['relmse']}, {s['below_raw']['dssim']} of "
                         f"{block['frames']} | {_n(s['relmse'])} | {_n(s['dssim'])} | "
                         f"{_n(s['prefilter_s'], '{:.3f}')} |")
        if BLENDER in block:
            lines.append(f"| {spp} | Blender's | 1 | – | – | {_n(block[BLENDER]['relmse'])} | "
                         f"{_n(block[BLENDER]['dssim'])} | – |")
    check = record["check"]
    lines += ["", "Check: " + (f"the raw variant against `{check['record']}` (model `{check['model']}`), "
                               f"{check['frames']} frames: largest difference relMSE "
                               f"{check['max_abs_diff']['relmse']:.3g}, DSSIM {check['max_abs_diff']['dssim']:.3g}."
                               if check else "no Blender report of this model on these frames to check against.")]
    methods = [*map(method, record["variants"]), BLENDER]
    head = ["scene", "spp"] + [f"{m} {s}" for s in ("relMSE", "DSSIM") for m in methods]
    lines += ["", "## Per frame", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in record["frames"]:
        cells = [_n(r["scores"].get(m, {}).get(s)) for s in ("relmse", "dssim") for m in methods]
        lines.append(f"| {r['scene']} | {r['spp']} | " + " | ".join(cells) + " |")
    if record["panel"]:
        lines += ["", f"`{REPORT}.png`: {record['panel']}: input | "
                  + " | ".join(map(method, record["variants"])) + " | Blender's | reference."]
    return "\n".join(lines) + "\n"
