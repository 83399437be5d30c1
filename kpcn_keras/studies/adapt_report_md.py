"""What the adaptation report shows (``adapt_report``): its methods' names, the target mark, the figure and the
markdown, from the record the study writes. Nothing here computes a score."""

from __future__ import annotations

import numpy as np

TARGET_MARK = 60.0
TARGET_GAIN = 0.25  # the median ratio to Blender's at least this much lower than the unadapted pair's
TARGET_WORST = 0.02  # no frame more than this much worse than unadapted
MEDIA = "media"  # the effect group of participating media (catalogue.EFFECTS)
PANEL_ROWS = 4
BLENDER, PAIR, SINGLE, INPUT, INPUT_SINGLE = "blender", "kpcn pair", "kpcn single", "input", "input single"
UNGUARDED = "kpcn unguarded"  # the target mark's chosen checkpoints applied whatever the guard decided


def adapted(mark: float) -> str:
    """The method name of kpcn adapted for ``mark`` seconds."""
    return f"kpcn adapted {mark:g} s"


def methods(marks) -> list[str]:
    return [INPUT, PAIR, *map(adapted, marks), UNGUARDED, BLENDER, SINGLE, INPUT_SINGLE]


def target_mark(marks) -> float:
    """The mark the targets are judged at: :data:`TARGET_MARK` where measured, else the largest."""
    return TARGET_MARK if TARGET_MARK in marks else marks[-1]


def _ratio(row: dict, method: str, score: str = "relmse") -> float:
    return row["scores"][method][score] / row["scores"][BLENDER][score]


PANEL_COLUMNS = (INPUT, PAIR, "adapted", BLENDER, "reference")


def panel_rows(rows: list[dict], spp: int) -> list[dict]:
    """The frames shown in panels: at ``spp``, those with participating media first, then the others, by scene,
    :data:`PANEL_ROWS` at most."""
    sel = sorted((r for r in rows if r["spp"] == spp), key=lambda r: (MEDIA not in r["groups"], r["scene"]))
    return sel[:PANEL_ROWS]


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
        "", f"All three hold: **{'yes' if t['held'] else 'no'}** (on the {t['frames']} frames measured).", "",
        *_any_guard_lines(t["any_guard"], t["frames"])]


def _any_guard_lines(g: dict, frames: int) -> list[str]:
    return [f"The most any guard could give with these corrections (per frame the better of the unadapted output "
            f"and the correction, chosen with the reference): below Blender's on {g['below_blender']} of {frames} "
            f"frames, median ratio {g['median_ratio']:.3f} ({g['gain']:.1%} lower than unadapted). What targets 1 and "
            "2 need beyond these figures no guard can give: the correction and the model fall short of it.", ""]


def _summary_lines(summary: dict, title: str, anchor: str) -> list[str]:
    """The medians per spp of ``summary`` (``adapt_report.summarise``'s) under the heading ``title``, each ratio
    and count against ``anchor``."""
    head = ["spp", "frames", "method", "median relMSE", "median DSSIM", f"median relMSE / {anchor}",
            f"median DSSIM / {anchor}", f"frames below {anchor}"]
    lines = [f"## {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for spp, block in summary.items():
        for m, s in block["methods"].items():
            lines.append(f"| {spp} | {block['frames']} | {m} | {s['median_relmse']:.4f} | {s['median_dssim']:.4f} | "
                         f"{s['median_ratio_blender']:.3f} | {s['median_dssim_ratio_blender']:.3f} | "
                         f"{s['below_blender']} of {block['frames']} |")
    lines += ["", "Frames on which the guard kept the correction, per mark: " + "; ".join(
        f"{spp} spp: " + ", ".join(f"{k} s {v} of {b['frames']}" for k, v in b["kept"].items())
        for spp, b in summary.items()) + ". Median steps run by each mark (at the held-out check that "
        "decided it; the machine's load sets how many a second buys): " + "; ".join(
        f"{spp} spp: " + ", ".join(f"{k} s {v:g}" for k, v in b["median_steps"].items())
        for spp, b in summary.items()) + ". Median step the folds chose by each mark (where their held-out loss "
        "was lowest; 0 the model's output): " + "; ".join(
        f"{spp} spp: " + ", ".join(f"{k} s {v:g}" for k, v in b["median_chosen_step"].items())
        for spp, b in summary.items() if "median_chosen_step" in b) + ". Frames whose chosen checkpoints at the "
        "last mark are those of the target mark: " + "; ".join(
        f"{spp} spp: {b['same_choice_at_last_mark']} of {b['frames']}" for spp, b in summary.items()
        if "same_choice_at_last_mark" in b) + ".", ""]
    return lines


def _frame_lines(record: dict) -> list[str]:
    marks = record["settings"]["marks"]
    shown = [INPUT, PAIR, *map(adapted, marks), UNGUARDED, BLENDER, SINGLE]
    head = ["scene", "spp", "groups", "anchor", *(f"{m} relMSE" for m in shown), "adapted / anchor",
            *(f"{m} DSSIM" for m in shown), "guard per mark", "steps", "load"]
    lines = ["## Per frame", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    target = adapted(target_mark(marks))
    for r in record["frames"]:
        guard = " ".join(("kept" if r["guard"][f"{m:g}"]["kept"] else "no") for m in marks)
        lines.append(f"| {r['scene']} | {r['spp']} | {', '.join(r['groups'])} | {r['anchor']} | "
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
             "and wrapped to the larger sizes (`card.frame_of_size`). Preparation: the model on both halves and their "
             "mean (the guard's), and their crops (at most 16 of 128 pixels a side per half, so a training step "
             "costs the same at any size; a held-out check every 10 steps runs every crop); a run of S seconds then "
             "takes about "
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
             + "".join(f" and `{f}`" for f in record.get("more", []))
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
             "`blender`: Blender's own denoiser (OIDN) on one render of N spp (in a folder without Blender's frames, "
             "the project's own scenes, the better of OIDN's modes on it by relMSE: each row's `anchor`); `kpcn "
             "single`: the model on that one render. Scores against the reference (2048 spp for Cycles) "
             "in float64 (`prep.metrics`).", ""]
    if record["targets"].get("held") is not None or record["frames"]:
        lines += _targets_lines(record["targets"])
    if record["summary"]:
        lines += _summary_lines(record["summary"], "Medians per spp", "Blender's")
    for name, summary in record["more_summary"].items():
        lines += _summary_lines(summary, f"`{name}`: medians per spp (not in the targets)", "anchor's")
    lines += _costs_lines(record.get("costs"), record["frames"])
    lines += _frame_lines(record)
    lines += ["`adapt.png`: the median ratio of relMSE (left) and DSSIM (right) to Blender's against the seconds of "
              "adaptation, one line per spp (0 s: unadapted); under it input | kpcn (pair, unadapted) | kpcn adapted "
              f"({record['target_mark']:g} s) | Blender's | reference of " + ", ".join(record["panels"])
              + " (participating media first).", ""]
    return "\n".join(lines)
