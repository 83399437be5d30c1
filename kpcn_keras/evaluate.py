"""Held-out evaluation of a run: raw input, the network and a classical baseline, per scene.

For every (noisy, reference) pair it measures relMSE, the 99.9th percentile of the per-pixel relative
squared error (relSE p99.9: the worst pixels, e.g. fireflies copied rather than repaired) and DSSIM of the
raw input, of the denoised frame, of non-local means, when ``pyoidn`` is installed of Intel Open Image Denoise
in both its modes (``prep.baselines.OIDN_MODES``: plain, and prefiltered as Blender runs it) and, where the
folder has it, of Blender's own denoised frame of the same render (``<scene>-<spp>spp-blender-oidn.exr``), plus
seconds per frame and whether the frame is won (its relMSE below the strongest of those anchors,
``prep.baselines.anchor``), and writes ``<run>/eval/`` with ``report.md``, ``metrics.json`` (every metric of
``prep.metrics.METRICS``) and one PNG per scene (input | NLM | OIDN | OIDN prefiltered | Blender | KPCN |
reference). A baseline that did not run has NaN in its columns. Every file of the report is checked
against every file the evaluation reads (renders, references, the run's models), and every reference against its
frame's size (``prep.layouts.check_same_size``), before the run is loaded.
A frame's row is an :class:`EvaluatedFrame`, written into ``metrics.json`` and read back (the card's tables) by
:func:`read_rows`.
"""

from __future__ import annotations

import glob
import json
import time
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np

from kpcn_keras.batch import ReadOptions, read_reference
from kpcn_keras.config import DEFAULT_ENSEMBLE
from kpcn_keras.denoise import Denoiser
from kpcn_keras.panels import side_by_side_png
from kpcn_keras.run import METRICS, REPORT, Run, RunRecord
from kpcn_keras.serving import Serving
from kpcn_keras.settings import InferenceSettings
from prep import baselines, exr, layouts, metrics
from prep.errors import KpcnError
from prep.files import atomic_write_text, check_outputs, check_writable, read_json

# the outputs a row scores: the input, the network, the baselines ("oidn" is plain OIDN, as reports always held it)
METHODS = ("raw", "denoised", "nlm", *baselines.ANCHORS)


@dataclass(frozen=True)
class EvaluatedFrame:
    """One evaluated render, a row of ``metrics.json``: its scene and samples, what served it, the scores
    (``prep.metrics.all_metrics``: metric name -> value) of each of :data:`METHODS` against the reference, the
    seconds each took, and its side-by-side PNG. A baseline that did not run (NLM on a frame without colour
    variance or under --no-baseline, OIDN without pyoidn, Blender's frame where the folder has none) is None, as
    are ``ensemble`` at the default (one member), layout, inputs, model and precision in a report from before
    evaluate recorded them, and ``spp`` and ``png`` in :func:`format_table`'s mean row; :meth:`to_json` leaves
    what is None out."""

    scene: str
    spp: int | None
    raw: dict[str, float]
    denoised: dict[str, float]
    seconds: float
    layout: str | None = None
    inputs: str | None = None
    model: str | None = None
    precision: str | None = None
    ensemble: int | None = None
    nlm: dict[str, float] | None = None
    nlm_seconds: float | None = None
    oidn: dict[str, float] | None = None
    oidn_seconds: float | None = None
    oidn_prefiltered: dict[str, float] | None = None
    oidn_prefiltered_seconds: float | None = None
    blender: dict[str, float] | None = None
    png: str | None = None

    # (field, its key in metrics.json), in the order evaluate has always written them
    JSON_KEYS = (("scene", "scene"), ("spp", "input spp"), ("layout", "layout"), ("inputs", "inputs"),
                 ("model", "model"), ("precision", "precision"), ("ensemble", "ensemble"), ("raw", "raw"),
                 ("denoised", "denoised"), ("seconds", "seconds"), ("nlm_seconds", "nlm_seconds"), ("nlm", "nlm"),
                 ("oidn_seconds", "oidn_seconds"), ("oidn", "oidn"),
                 ("oidn_prefiltered_seconds", "oidn_prefiltered_seconds"), ("oidn_prefiltered", "oidn_prefiltered"),
                 ("blender", "blender"), ("png", "png"))
    REQUIRED = ("scene", "input spp", "raw", "denoised", "seconds", "png")  # in every row evaluate ever wrote

    def to_json(self) -> dict:
        """The row as ``metrics.json`` holds it."""
        return {key: getattr(self, name) for name, key in self.JSON_KEYS if getattr(self, name) is not None}

    @classmethod
    def from_json(cls, row) -> EvaluatedFrame:
        """A row of ``metrics.json`` (keys evaluate does not write are passed over); ValueError naming what is
        missing where ``row`` is not one."""
        missing = [key for key in cls.REQUIRED if key not in row] if isinstance(row, dict) else ["a JSON object"]
        if missing:
            raise ValueError(f"not a row of kpcn evaluate's report: no {', '.join(missing)}")
        return cls(**{name: int(row[key]) if name == "spp" else row[key] for name, key in cls.JSON_KEYS if key in row})

    def score(self, method: str, metric: str) -> float | None:
        """``metric`` of ``method`` (one of :data:`METHODS`); None where the method did not run or lacks it."""
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        scores = getattr(self, method)
        return None if scores is None else scores.get(metric)

    @property
    def won(self) -> str | None:
        """"yes" where the network's relMSE is strictly below the strongest anchor's the row has (the better of
        the OIDN modes and Blender's own frame: ``prep.baselines.anchor``), else "no"; None without an anchor,
        and for :func:`mean_row` (a mean is no frame)."""
        strongest = baselines.anchor({key: getattr(self, key) for key in baselines.ANCHORS})
        if strongest is None or self.spp is None:
            return None
        return "yes" if self.denoised["relmse"] < strongest[1]["relmse"] else "no"


def read_rows(folder: Path) -> list[EvaluatedFrame]:
    """The rows of a report folder's ``metrics.json``; KpcnError naming it where it is not one."""
    rows = read_json(Path(folder) / METRICS, "evaluation report")
    try:
        if not isinstance(rows, list):
            raise ValueError("not a list of rows")
        return [EvaluatedFrame.from_json(r) for r in rows]
    except ValueError as e:
        raise KpcnError(f"{Path(folder) / METRICS}: not an evaluation report of kpcn evaluate; evaluate again") from e


# (header, format, where the value is in a row: a field of EvaluatedFrame, or (method, metric))
COLUMNS = (
    ("scene", "{}", "scene"),
    ("input spp", "{}", "spp"),
    ("raw relMSE", "{:.4f}", ("raw", "relmse")),
    ("denoised relMSE", "{:.4f}", ("denoised", "relmse")),
    ("raw relSE p99.9", "{:.4f}", ("raw", "relse_p999")),
    ("denoised relSE p99.9", "{:.4f}", ("denoised", "relse_p999")),
    ("raw DSSIM", "{:.4f}", ("raw", "dssim")),
    ("denoised DSSIM", "{:.4f}", ("denoised", "dssim")),
    ("NLM relMSE", "{:.4f}", ("nlm", "relmse")),
    ("NLM relSE p99.9", "{:.4f}", ("nlm", "relse_p999")),
    ("OIDN relMSE", "{:.4f}", ("oidn", "relmse")),
    ("OIDN relSE p99.9", "{:.4f}", ("oidn", "relse_p999")),
    ("s/frame", "{:.2f}", "seconds"),
)
# the anchors' columns after plain OIDN's, each only where some row has it (a report from before prefiltered OIDN
# prints as it did); "won": the network below the strongest anchor (EvaluatedFrame.won), with the new anchors
ANCHOR_COLUMNS = (
    ("OIDN prefiltered relMSE", "{:.4f}", ("oidn_prefiltered", "relmse")),
    ("OIDN prefiltered relSE p99.9", "{:.4f}", ("oidn_prefiltered", "relse_p999")),
    ("Blender relMSE", "{:.4f}", ("blender", "relmse")),
    ("Blender relSE p99.9", "{:.4f}", ("blender", "relse_p999")),
    ("won", "{}", "won"),
)


def table_columns(rows: list[EvaluatedFrame]) -> tuple:
    """The columns of ``rows``' table: :data:`COLUMNS`, with those of :data:`ANCHOR_COLUMNS` whose anchor some row
    has inserted before the seconds."""
    has = {key for key in ("oidn_prefiltered", "blender") if any(getattr(r, key) is not None for r in rows)}
    extra = tuple(c for c in ANCHOR_COLUMNS if (c[2][0] in has if isinstance(c[2], tuple) else bool(has)))
    return COLUMNS[:-1] + extra + COLUMNS[-1:]


def held_out_pairs(run: Run, record: RunRecord) -> list[tuple[str, str]]:
    """(noisy, reference) paths of the validation scenes of the shard set of ``run`` (its ``record``)."""
    sset = run.shard_set(record)
    return [(str(a), str(b)) for a, b in sset.pairs(sset.complete_manifest(), "val")]


def held_out_frames(run: Run, record: RunRecord) -> list[dict]:
    """The run's held-out frames read once: ``name`` ("<scene> <spp> spp"), ``noisy`` AOVs, ``reference`` colour."""
    return read_frames(held_out_pairs(run, record))


def read_frames(pairs) -> list[dict]:
    """(noisy, reference) render paths in the AOV layout read as :func:`held_out_frames` reads them."""
    frames = []
    for noisy_path, ref_path in pairs:
        scene, spp = exr.parse_render_filename(noisy_path)
        frames.append({"name": f"{scene} {spp} spp", "noisy": exr.read_aovs(noisy_path),
                       "reference": exr.read_aovs(ref_path, variances=False)["default"]})
    return frames


SCORES = ("relmse", "dssim", "relse_p999")


def frame_scores(outputs: list[np.ndarray], frames: list[dict]) -> dict:
    """relMSE, DSSIM and relSE p99.9 of each output against its frame's reference, and their means over the
    frames (the numbers compare and resample report)."""
    per_frame = [{"frame": f["name"], "relmse": metrics.relmse(x, f["reference"]),
                  "dssim": metrics.dssim(x, f["reference"]), "relse_p999": metrics.relse_p999(x, f["reference"])}
                 for x, f in zip(outputs, frames)]
    means = {m: float(sum(p[m] for p in per_frame) / len(per_frame)) for m in SCORES}
    return {**means, "frames": per_frame}


def noisy_renders(folder: str | Path) -> list[Path]:
    """The noisy renders of a folder: every ``<scene>-<spp>spp.exr`` in it but each scene's render with the
    most samples (its reference), in name order; files named otherwise (a renderer's own denoised frame,
    ``<scene>-<spp>spp-blender-oidn.exr``) are passed over."""
    renders = {}
    for path in sorted(Path(folder).glob("*spp.exr")):
        try:
            scene, spp = exr.parse_render_filename(path)
        except exr.AOVError:
            continue
        if not path.name.startswith("."):
            renders.setdefault(scene, []).append((spp, path))
    return sorted(path for found in renders.values() for _, path in sorted(found)[:-1])


def pairs_for_inputs(inputs: list[str]) -> list[tuple[str, str]]:
    """Each noisy render with the reference of its scene: the same folder's render of that scene with the
    most samples. Only the input's own scene is looked at: other files in the folder (of other scenes, or
    not named ``<scene>-<spp>spp.exr``) are neither read nor judged. A folder stands for its
    :func:`noisy_renders`."""
    pairs = []
    inputs = [str(p) for path in inputs for p in (noisy_renders(path) if Path(path).is_dir() else [path])]
    if not inputs:
        raise KpcnError("no noisy renders (<scene>-<spp>spp.exr with a reference beside it) in the inputs")
    for path in inputs:
        scene, spp = exr.parse_render_filename(path)
        ref, ref_spp = None, spp
        for other in Path(path).parent.glob(f"{glob.escape(scene)}-*spp.exr"):
            try:
                other_scene, other_spp = exr.parse_render_filename(other)
            except exr.AOVError:  # e.g. "<scene>-extra-00004spp.exr": not this scene's
                continue
            if other_scene == scene and other_spp > ref_spp and not other.name.startswith("."):
                ref, ref_spp = other, other_spp
        if ref is None:
            raise KpcnError(f"{path}: no reference with more samples than {spp} spp beside it")
        pairs.append((str(path), str(ref)))
    return pairs


def frame_png(out_dir: Path, scene: str, spp: int) -> Path:
    """The side-by-side PNG of the evaluated render of ``scene`` at ``spp`` in the report folder."""
    return out_dir / Path(exr.render_filename(scene, spp)).with_suffix(".png")


def evaluate(run: Run, pairs: list[tuple[str, str]] | None = None, *, out_dir=None,
             settings: InferenceSettings = InferenceSettings(), baseline: bool = True, slope: float | None = None,
             reading: ReadOptions = ReadOptions()) -> list[EvaluatedFrame]:
    """Evaluate ``run`` on ``pairs`` (default: its held-out scenes) at ``slope`` (λ, for a run trained with it as an
    input; refused elsewhere); writes the report and returns the rows. Inputs in any layout ``prep.layouts``
    reads, read by ``reading`` (its layout, view layer: ``batch.ReadOptions``), each denoised by the run's model
    for what it has (``Serving.variant``) with ``settings`` (tile, the trunks' precision, a self-ensemble's
    members: a row then says how many; the quality mode, whose run's held-out scenes and ``eval/`` are the
    defaults)."""
    mode = run.for_quality(settings.quality)  # a mode's report is its own folder's (and the model's: balanced)
    out_dir = Path(out_dir) if out_dir else mode.eval_dir
    if run.card_path.is_file() and out_dir.resolve() in {folder.resolve() for model in (run, mode)
                                                          for folder in (model.eval_dir, model.validation_dir)}:
        raise KpcnError(f"{run.dir}: a shipped model, whose {out_dir.name}/ holds the tables its card shows; "
                        "evaluate it into another folder with --out DIR")
    check_writable(out_dir, "report folder (--out)", directory=True)
    record = mode.record()
    pairs = pairs or held_out_pairs(mode, record)
    if not pairs:
        raise KpcnError(f"{run.dir}: no held-out scenes to evaluate; pass noisy renders explicitly")
    headers = {noisy: reading.header(noisy) for noisy, _ in pairs}
    for noisy, ref in pairs:  # before any work: a report is of every frame or of none
        layouts.check_same_size(noisy, headers[noisy].size, ref, reading.for_reference().header(ref).size)
        own = baselines.renderer_denoised(noisy)
        if baseline and own.is_file():
            layouts.check_same_size(noisy, headers[noisy].size, own, reading.for_reference().header(own).size,
                                    "denoised frame of Blender")
    serving = Serving(run, settings)
    given = {noisy: header.inputs for noisy, header in headers.items()}
    written = [("report", out_dir / REPORT), ("metrics", out_dir / METRICS)]
    written += [(f"the PNG of {noisy}", frame_png(out_dir, *exr.parse_render_filename(noisy))) for noisy, _ in pairs]
    read = [("input", noisy) for noisy, _ in pairs] + [("reference", ref) for _, ref in pairs]
    read += [("Blender's own denoised frame", own) for own in map(baselines.renderer_denoised, given) if own.is_file()]
    models = serving.read_files(given.values())
    check_outputs(written, read + models, "choose another --out (a report folder takes one render of each name)")
    ensemble = settings.ensemble
    rows = []
    for noisy_path, ref_path in pairs:
        denoiser = serving.denoiser(given[noisy_path], warm_up=True, slope=slope)
        rows.append(evaluate_frame(denoiser, noisy_path, ref_path, out_dir, reading=reading, slope=slope,
                                   baseline=baseline, ensemble=ensemble))
    table = format_table(rows)
    atomic_write_text(out_dir / METRICS, json.dumps([row.to_json() for row in rows], indent=2))
    at = ("" if slope is None else f" at λ = {slope:g}") + (f", an ensemble of {ensemble}" if ensemble > 1 else "")
    atomic_write_text(out_dir / REPORT, f"# Evaluation of {run.dir}{at} ({date.today().isoformat()})\n\n{table}\n")
    return rows


def evaluate_frame(denoiser: Denoiser, noisy_path: str, ref_path: str, out_dir: Path, *, reading: ReadOptions,
                   slope: float | None, baseline: bool, ensemble: int) -> EvaluatedFrame:
    """One row of :func:`evaluate`: the render ``noisy_path`` denoised by ``denoiser`` (timed), scored against
    ``ref_path`` with the raw input and, under ``baseline``, NLM and OIDN where they run; writes its PNG."""
    scene, spp = exr.parse_render_filename(noisy_path)
    frame = reading.read(noisy_path)
    noisy = frame.layers
    ref = read_reference(ref_path, noisy_path, frame.size, reading)
    start = time.perf_counter()
    out = denoiser(frame.served_layers(), slope=slope)["default"]
    seconds = time.perf_counter() - start
    denoised = metrics.all_metrics(out, ref)
    panels = [(f"input {spp} spp", noisy["default"]), (f"KPCN relMSE {denoised['relmse']:.4f}", out)]
    found = {}
    if baseline:
        if frame.inputs.variance:  # NLM weighs by the colour's variance: none without it
            start = time.perf_counter()
            nlm = baselines.nlm_denoise(noisy["default"], noisy["colorVariance"])
            found.update(nlm_seconds=time.perf_counter() - start, nlm=metrics.all_metrics(nlm, ref))
            panels.insert(1, (f"NLM relMSE {found['nlm']['relmse']:.4f}", nlm))
        found.update(_anchors(noisy_path, baselines.oidn_inputs(frame), ref, panels, reading))
    panels.append(("reference", ref))
    png = side_by_side_png(frame_png(out_dir, scene, spp), panels, title=scene)
    return EvaluatedFrame(scene, spp, raw=metrics.all_metrics(noisy["default"], ref), denoised=denoised,
                          seconds=seconds, layout=frame.layout, inputs=frame.inputs.name, model=str(denoiser.run.dir),
                          precision=denoiser.precision, ensemble=None if ensemble == DEFAULT_ENSEMBLE else ensemble,
                          png=str(png), **found)


def _anchors(noisy_path: str, noisy: dict, ref: np.ndarray, panels: list, reading: ReadOptions) -> dict:
    """The anchors' fields of a row: OIDN in each of its modes on ``noisy`` (``baselines.oidn_inputs``) when
    ``pyoidn`` is installed (timed), and Blender's
    own denoised frame where it lies beside ``noisy_path``; each one's panel goes in before the network's."""
    found = {}
    if baselines.oidn_available():
        for mode in baselines.OIDN_MODES:
            key = baselines.OIDN_KEYS[mode]
            start = time.perf_counter()
            oidn = baselines.oidn_denoise(noisy, mode=mode)
            found.update({f"{key}_seconds": time.perf_counter() - start, key: metrics.all_metrics(oidn, ref)})
            label = "OIDN" if mode == "plain" else f"OIDN {mode}"
            panels.insert(len(panels) - 1, (f"{label} relMSE {found[key]['relmse']:.4f}", oidn))
    own = baselines.renderer_denoised(noisy_path)
    if own.is_file():
        blender = reading.for_reference().read(own).layers["default"]
        found["blender"] = metrics.all_metrics(blender, ref)
        panels.insert(len(panels) - 1, (f"Blender relMSE {found['blender']['relmse']:.4f}", blender))
    return found


def _value(row: EvaluatedFrame, where):
    """The value of one column in a row; NaN for a method the row lacks (NLM under --no-baseline)."""
    if isinstance(where, str):
        return getattr(row, where)
    value = row.score(*where)
    return float("nan") if value is None else value


def _cells(row: EvaluatedFrame, columns=COLUMNS) -> list[str]:
    values = [(fmt, _value(row, where)) for _, fmt, where in columns]
    return ["" if value is None else fmt.format(value) for fmt, value in values]  # None: the mean row's spp


def mean_row(rows: list[EvaluatedFrame]) -> EvaluatedFrame:
    """The table's mean row: the mean over ``rows`` of each column (for relSE p99.9 the mean of the scenes'
    percentiles, not a percentile of all their pixels); a method some row lacks is left out (NaN in the table)."""
    means = {}
    for _, _, where in (*COLUMNS, *ANCHOR_COLUMNS):
        if isinstance(where, tuple) and all(getattr(r, where[0]) is not None for r in rows):
            means.setdefault(where[0], {})[where[1]] = float(np.mean([_value(r, where) for r in rows]))
    return EvaluatedFrame("**mean**", None, seconds=float(np.mean([r.seconds for r in rows])), **means)


def format_table(rows: list[EvaluatedFrame]) -> str:
    """A Markdown table, one row per scene, with a :func:`mean_row` where there are several."""
    columns = table_columns(rows)
    names = [name for name, _, _ in columns]
    lines = ["| " + " | ".join(names) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(_cells(r, columns)) + " |" for r in rows]
    if len(rows) > 1:
        cells = _cells(mean_row(rows), columns)
        if "won" in names:  # the mean row's: the frames won, of those judged
            judged = [r.won for r in rows if r.won is not None]
            cells[names.index("won")] = f"{judged.count('yes')} of {len(judged)}" if judged else ""
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
