"""The report half of ``kpcn quality`` (:mod:`kpcn_keras.studies.quality`): reading a quality record, judging it
and writing it.

- **Judging** (:func:`best`, :func:`verdict`, :func:`default_target`, :func:`share_target`, :func:`dssim_target`):
  the headline lever by frames, each lever and the measured model against the anchor (a frame's strongest of plain
  OIDN, prefiltered OIDN and Blender's own frame: ``prep.baselines.anchor``) and against the targets.
- **quality.md** (:func:`format_report`): the levers, the tables of both kinds per input spp, each validation
  frame, the targets, the model beside the levers, the rules.
- **quality.png** (:func:`panel_entries`, :func:`redraw_panels`): input | kpcn (the headline's lever) | the model
  | OIDN | Blender | reference of the validation frames at the panel spp.
- **``--report-only``** (:func:`rewrite_reports`): the md again from ``quality.json`` alone, the png from the
  frames and runs it names; nothing trained.

Everything here reads the record (``quality.json``) alone, but the panels, which denoise its frames again.
"""

from __future__ import annotations

import json
import math
import statistics
from datetime import date
from fractions import Fraction
from pathlib import Path

from kpcn_keras.config import DEFAULT_ENSEMBLE
from kpcn_keras.studies.compare import against
from kpcn_keras.studies.frames import PANEL_COLUMNS, SCORES, beside, by_spp, panels_figure
from kpcn_keras.studies.report import Report
from prep import baselines, layouts
from prep.files import read_json

REPORT = "quality"  # quality.json, quality.md, quality.png in the report folder
KINDS = ("held-out", "validation")
BASELINES = ("raw", *baselines.ANCHORS)
LABELS = {"raw": "raw input", "oidn": "OIDN", "oidn_prefiltered": "OIDN prefiltered", "blender": "Blender's own"}
# the model measured beside the levers (the shipped one unless --model): its key in the record and in each row.
# Not a lever: it trained for as long as it kept improving, not for the budget
MODEL = "model"
# the targets for the shipped model: below OIDN's relMSE on at least two thirds of all frames, and its mean
# DSSIM below OIDN's at these spp
MODEL_SHARE, MODEL_DSSIM_SPP = Fraction(2, 3), (16, 64)


def model_label(model: dict) -> str:
    """How the report names the record's model entry: ``shipped model `default``` or ``model `<folder>```."""
    return f"{'shipped ' if model['shipped'] else ''}model `{Path(model['run']).name}`"



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


def anchor_of(row: dict) -> dict | None:
    """The scores of a frame's anchor: the lowest relMSE of plain OIDN, prefiltered OIDN (a record from before it
    has plain alone) and Blender's own frame where the row has them (``prep.baselines.anchor``); None without
    OIDN (Blender's frame alone does not make a frame judged: without OIDN nothing is counted)."""
    if "oidn" not in row and "oidn_prefiltered" not in row:
        return None
    return baselines.anchor(row)[1]


def against_oidn(rows: list[dict], method: str) -> dict | None:
    """``method`` (a lever or :data:`MODEL`) against the anchor (:func:`anchor_of`) on the ``rows`` that have
    one (``compare.against``: ``lower``, of ``frames``, ``median_ratio``); None where none has."""
    both = [r for r in rows if anchor_of(r) is not None]
    if not both:
        return None
    return against({"frames": [scores_of(r, method) for r in both]}, {"frames": [anchor_of(r) for r in both]})


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


# the target for make train's default: below OIDN's relMSE on at least half of the validation frames at 16 spp
TARGET_SPP, TARGET_SHARE = 16, Fraction(1, 2)


def share_target(rows: list[dict], method: str, share: Fraction) -> dict | None:
    """``method`` against a target of being below OIDN's relMSE on at least ``share`` of the ``rows`` that have
    OIDN's scores: ``lower`` (frames below OIDN's relMSE), ``frames``, ``needed`` (the frames the target asks for)
    and ``deciding``, the ratio to OIDN's relMSE of the frame that decides (the ``needed``-th lowest): below 1
    where the target is met, else how far it is out. None without such rows."""
    def ratio(x: float, a: float) -> float:  # compare.against's convention where the anchor is exact
        return x / a if a > 0 else (math.inf if x > 0 else 1.0)

    ratios = sorted(ratio(scores_of(r, method)["relmse"], anchor_of(r)["relmse"]) for r in rows if anchor_of(r))
    if not ratios:
        return None
    needed = math.ceil(share * len(ratios))
    return {"lower": sum(x < 1 for x in ratios), "frames": len(ratios), "needed": needed,
            "deciding": ratios[needed - 1]}


def default_target(record: dict, method: str) -> dict | None:
    """``method`` against the target for the default (:data:`TARGET_SPP`, :data:`TARGET_SHARE`) on the
    validation frames at ``TARGET_SPP`` (:func:`share_target`)."""
    rows = [r for r in of_kind(record, "validation") if r["spp"] == TARGET_SPP]
    return share_target(rows, method, TARGET_SHARE)


def dssim_target(record: dict, spp: int) -> dict | None:
    """The model's mean DSSIM against the anchors' over the frames of both kinds at ``spp`` that have an anchor
    (``model``, ``oidn``: the mean of each frame's lowest DSSIM of its anchors, ``frames``); None without such
    frames."""
    rows = [r for r in record["frames"] if r["spp"] == spp and anchor_of(r) is not None]
    if not rows:
        return None
    lowest = [min(r[k]["dssim"] for k in baselines.ANCHORS if k in r) for r in rows]
    return {"model": mean(rows, MODEL, "dssim"), "oidn": statistics.fmean(lowest), "frames": len(rows)}


def _judged(ratio: float) -> str:
    """A target by its ratio: met below 1, else how far out (to a tenth of a per cent below one per cent)."""
    if ratio < 1:
        return "met"
    return f"out by {ratio - 1:.0%}" if ratio >= 1.005 else f"out by {ratio - 1:.1%}"


def _target_table(record: dict) -> list[str]:
    """The section on the target for the default, a row per lever and one for the measured model, each with
    the render sets its networks for those frames trained on (nothing without OIDN or such frames)."""
    methods = [*record["config"]["levers"], *([MODEL] if record.get(MODEL) else [])]
    rows = {m: default_target(record, m) for m in methods} if record["oidn"] else {}
    if not rows or None in rows.values():
        return []
    lines = ["", "## The default's target: half the validation frames at 16 spp", "",
             f"The target for `make train`'s default: below OIDN's relMSE on at least {TARGET_SHARE} "
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
    """The section on the measured model: what it is, and the targets for the shipped model judged on the
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
    lines += ["", "The targets for the shipped model, on these frames: the needed-th lowest ratio to OIDN's "
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
    cfg = record["config"]
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
        *_lever_table(record),
    ]
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
    return "\n".join(lines + _rules(record)) + "\n"


def _lever_table(record: dict) -> list[str]:
    """The section on the levers: what each is, what it trained on and for how many steps, and the frames of each
    kind it is below OIDN on; the measured model's row after them."""
    held, val = of_kind(record, "held-out"), of_kind(record, "validation")
    lines = [
        "## The levers", "",
        "| lever | what it is | trains on | steps per network (trained s) | held-out frames below OIDN's relMSE | "
        "validation frames below OIDN's | all frames | median relMSE / OIDN's |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for lever in record["config"]["levers"]:
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
    return lines


def _rules(record: dict) -> list[str]:
    """The section on the rules of the study: the budget, the frames, the judging, the metrics, the machine, and
    what every lever starts from or was overridden with."""
    cfg, machine = record["config"], record["machine"]
    load_b, load_a = machine["load_average_before"][0], machine["load_average_after"][0]
    lines = [
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
        "- **By frames, against the anchor.** A frame's anchor is the strongest of what it is judged against: "
        "the lower relMSE of plain OIDN and OIDN as Blender runs it (albedo and normal prefiltered by OIDN's own "
        "filters, then the colour with `cleanAux`), and of Blender's own denoised frame where the folder has it "
        "(`prep/baselines.py`). *Frames below OIDN's relMSE* counts the frames where the lever's relMSE is "
        "strictly below the anchor's, of the frames OIDN has; the median ratio (to *OIDN's*: the anchor's) is over "
        "the same frames, and a DSSIM target is judged against each frame's lowest anchor DSSIM. A mean over "
        "frames can be carried by one frame (`caustics`, whose reference is itself speckled); these cannot.",
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
    return lines


# ---------------------------------------------------------------- the panels, and the reports written again


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
                  **beside(Path(entry["path"]), frame),
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
