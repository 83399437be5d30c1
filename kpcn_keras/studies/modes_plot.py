"""Error against seconds per frame: kpcn's quality modes beside OIDN's, from a timing and a Blender report.

  .venv/bin/python -m kpcn_keras.studies.modes_plot [--costs reports/mode_costs.json]
      [--errors reports/blender.json] [--name MODEL] [--out reports]      # make modes-report

One point per kpcn quality mode and per OIDN mode (prefiltered, plain) at each of its qualities:

- **x**: the best seconds of that method on a 1920 x 1080 frame, from ``--costs`` (what
  ``kpcn_keras.studies.mode_costs`` printed).
- **y**, at each spp of ``--errors`` (the record ``kpcn_keras.studies.blender_report`` wrote): the median over
  that spp's frames of the method's relMSE over Blender's own frame's, where the report's frames have Blender's;
  the mean relMSE where none has (the project's held-out scenes, the Mitsuba fixture). The record says which.
- **Which columns**: kpcn mode MODE is the report's ``kpcn NAME MODE`` (a model with several modes) or ``kpcn NAME``
  for ``balanced`` (a model with that one alone); NAME is ``--name``, else the report's model whose folder is the
  timed one, else its only model. OIDN at ``high`` is the report's ``oidn_<mode>``, at another quality
  ``oidn_<mode> <quality>``. A method the report did not score (or the probe did not time) has no point.

Writes ``<out>/modes.json`` (every point, and the two records it was drawn from) and ``<out>/modes.png`` (a panel
per spp, seconds on a log axis). Bad input (a missing or unreadable record, no model to pick) is one line and exit
status 2.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from kpcn_keras.studies.blender_report import BLENDER, model_method, oidn_method
from kpcn_keras.studies.mode_costs import kpcn_method
from kpcn_keras.studies.mode_costs import oidn_method as timed_oidn
from prep import baselines
from prep.errors import KpcnError
from prep.files import atomic_path, atomic_write_json, pyplot

QUALITIES = baselines.OIDN_QUALITIES  # kpcn's modes and OIDN's qualities share their names
RATIO = "median relMSE ratio to Blender's"
MEAN = "mean relMSE"


def _read(path: Path, what: str) -> dict:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise KpcnError(f"{path}: not a readable {what} record ({exc})") from None


def pick_model(errors: dict, costs: dict, name: str | None) -> str:
    """The report's model the timed one is: ``name``, else the one whose folder is the timed model's, else the only
    one; KpcnError naming the report's models otherwise."""
    models = errors.get("models", {})
    if name is None:
        same = [n for n, p in models.items() if Path(p).resolve() == Path(costs["model"]).resolve()]
        name = same[0] if same else next(iter(models)) if len(models) == 1 else None
    if name not in models:
        raise KpcnError(f"--name {name}: give one of the report's models: {', '.join(models) or 'none'}")
    return name


def columns(errors: dict, name: str) -> dict[str, str]:
    """The probe's method name -> the report's column, for every method that may have both (module docstring)."""
    modes = errors.get("quality_modes", {}).get(name)
    found = {kpcn_method(m): model_method(f"{name} {m}") for m in modes} if modes else \
        {kpcn_method("balanced"): model_method(name)}
    for quality in QUALITIES:
        found.update({timed_oidn(mode, quality): oidn_method(mode, quality) for mode in baselines.OIDN_MODES})
    return found


def error_by_spp(rows: list[dict], method: str, kind: str) -> dict[str, float]:
    """``method``'s error at each spp of ``rows`` that scored it: the median ratio of its relMSE to Blender's over
    the frames that have both (``kind`` :data:`RATIO`), or its mean relMSE (:data:`MEAN`)."""
    found = {}
    for spp in sorted({r["spp"] for r in rows}):
        have = [r["scores"] for r in rows if r["spp"] == spp and method in r["scores"]]
        if kind == RATIO:
            values = [s[method]["relmse"] / s[BLENDER]["relmse"] for s in have if BLENDER in s]
            if values:
                found[str(spp)] = float(np.median(values))
        elif have:
            found[str(spp)] = float(np.mean([s[method]["relmse"] for s in have]))
    return found


def points(costs: dict, errors: dict, name: str) -> tuple[str, list[dict]]:
    """(the y quantity, one point per method the probe timed and the report scored)."""
    rows = errors["frames"]
    kind = RATIO if any(BLENDER in r["scores"] for r in rows) else MEAN
    found = []
    for timed_name, column in columns(errors, name).items():
        if timed_name in costs["best_s"] and (error := error_by_spp(rows, column, kind)):
            kpcn = timed_name.startswith("kpcn")
            found.append({"method": timed_name, "column": column, "family": "kpcn" if kpcn else
                          timed_name.split()[0], "quality": timed_name.split()[-1],
                          "seconds": costs["best_s"][timed_name], "error": error})
    return kind, found


def figure(record: dict):
    """A panel per spp: each family's points (kpcn, OIDN prefiltered, OIDN plain) joined in quality order."""
    from matplotlib import ticker

    plt = pyplot()
    spps = sorted({spp for p in record["points"] for spp in p["error"]}, key=int)
    fig, axes = plt.subplots(1, max(len(spps), 1), figsize=(4.2 * max(len(spps), 1), 3.6), squeeze=False)
    for ax, spp in zip(axes[0], spps):
        for family in dict.fromkeys(p["family"] for p in record["points"]):
            mine = sorted((p for p in record["points"] if p["family"] == family and spp in p["error"]),
                          key=lambda p: QUALITIES.index(p["quality"]))
            xs, ys = [p["seconds"] for p in mine], [p["error"][spp] for p in mine]
            ax.plot(xs, ys, marker="o", label=family)
            for p, x, y in zip(mine, xs, ys):
                ax.annotate(p["quality"], (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        for axis in (ax.xaxis.set_major_formatter, ax.xaxis.set_minor_formatter):
            axis(ticker.FormatStrFormatter("%g"))  # 0.3, 2: not 3×10⁻¹ on every minor tick
        ax.tick_params(axis="x", which="both", labelsize=7)
        ax.set_title(f"{spp} spp", fontsize=9)
        ax.set_xlabel(f"seconds per {record['size'][0]}×{record['size'][1]} frame (best of {record['repeats']})")
        ax.set_ylabel(record["y"])
        ax.legend(fontsize=7)
    fig.tight_layout()
    return fig


def plot(costs_path: Path, errors_path: Path, out: Path, name: str | None, command: str) -> dict:
    costs, errors = _read(costs_path, "mode-costs"), _read(errors_path, "Blender report")
    if "best_s" not in costs or "frames" not in errors:
        raise KpcnError(f"{costs_path} or {errors_path}: not a mode_costs and a blender_report record")
    name = pick_model(errors, costs, name)
    kind, found = points(costs, errors, name)
    record = {"command": command, "costs": str(costs_path), "errors": str(errors_path), "model": name,
              "size": costs["size"], "repeats": costs["repeats"], "x": "best seconds per frame", "y": kind,
              "points": found}
    out.mkdir(parents=True, exist_ok=True)
    fig = figure(record)
    with atomic_path(out / "modes.png") as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    pyplot().close(fig)
    atomic_write_json(out / "modes.json", record)
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m kpcn_keras.studies.modes_plot",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--costs", default="reports/mode_costs.json", help="the timing (default: %(default)s)")
    parser.add_argument("--errors", default="reports/blender.json", help="the Blender report (default: %(default)s)")
    parser.add_argument("--name", help="the report's model that was timed (default: the one of the timed folder)")
    parser.add_argument("--out", default="reports", help="report folder (default: %(default)s)")
    args = parser.parse_args(argv)
    command = shlex.join(["python", "-m", "kpcn_keras.studies.modes_plot", *(sys.argv[1:] if argv is None else argv)])
    try:
        record = plot(Path(args.costs), Path(args.errors), Path(args.out), args.name, command)
    except KpcnError as exc:
        if os.environ.get("KPCN_DEBUG"):
            raise
        print(f"modes-plot: error: {exc}", file=sys.stderr)
        return 2
    print(f"modes-plot: {len(record['points'])} points ({record['y']}) in {args.out}/modes.png and modes.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
