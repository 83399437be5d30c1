"""Render sets: :func:`render_set` renders families x per_family built-in scenes at a ladder of input
sample counts (each with its own seed) and one reference count into ``<out_root>/<set_name>/``, and
records what it did in ``config.json`` (reproducible: the same command writes the same bytes) and how
long it took in ``timings.json`` (the one file that differs between runs). This module owns that folder, and
:class:`RenderSet` names it and its files (for the commands, ``kpcn import-renders`` and the studies alike)::

    <set>/<scene>-<spp>spp.exr             every input and reference render
    <set>/<scene>-<spp/2>spp-pair-{a,b}.exr  with ``pair``: each input's two halves (catalogue.pair_names)
    <set>/config.json                      the config, and once every render is there, every scene and its seeds
    <set>/timings.json                     seconds per render
    <set>/timings.part-<i>-of-<N>.json     a part's seconds (``prep.parts``), until the last part folds them in
    <set>/contact-sheet.png                the references, one row per family
    <set>/convergence.{md,json,png}        ``kpcn references``: how converged the references are
    <set>/.lock, .lock-part-<i>-of-<N>     the set's lock (its records), a part's lock (its renders)
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from prep.bounds import SEED, Bound, bounded, check_fields, is_integer
from prep.errors import KpcnError, OptionError
from prep.exr import SPP_ATTRIBUTE, render_filename, write_aovs
from prep.files import (
    atomic_path,
    atomic_write_json,
    check_set_name,
    check_writable,
    exclusive_lock,
    read_json,
    remove_temporaries,
)
from prep.parts import Part
from prep.render.cycles import catalogue
from prep.render.families import DEFAULT_FAMILIES, REFERENCE_SPP_FACTOR, check_families, make_scene
from prep.render.frame import FRAME_SIDE, SPP, check_frame, render

log = logging.getLogger("kpcn")


PER_FAMILY = Bound(1, 1000)  # scenes per family: a set of 1000 x 8 scenes is far past any use of one
RENDER_ROOT = "data/renders"  # the folder of render sets unless an option names another (--out, --renders)
RECORD = "config.json"  # a set's record: its config, and once finished every scene and its seeds


@dataclass
class RenderConfig:
    """What :func:`render_set` renders and where."""

    set_name: str = "default"
    families: tuple[str, ...] = bounded(DEFAULT_FAMILIES, distinct=True)
    per_family: int = bounded(3, PER_FAMILY)
    width: int = bounded(256, FRAME_SIDE)
    height: int = bounded(256, FRAME_SIDE)
    input_spp: tuple[int, ...] = bounded((4, 16, 64), SPP, distinct=True)  # a ladder: every noise level
    reference_spp: int = bounded(512, SPP)  # times families.REFERENCE_SPP_FACTOR for the families slow to converge
    seed: int = bounded(0, SEED)
    out_root: str = RENDER_ROOT
    pair: bool = False  # each input also as two halves of half its spp, two seeds of their own (kpcn denoise --pair)

    def __post_init__(self):
        if is_integer(self.input_spp):
            self.input_spp = (int(self.input_spp),)
        self.input_spp = tuple(self.input_spp)
        self.families = tuple(self.families) if not isinstance(self.families, str) else self.families

    def validate(self) -> None:
        check_set_name(self.set_name)
        check_families(self.families)
        if not self.input_spp:
            raise OptionError("input_spp", "must name at least one sample count")
        check_fields(self)
        odd = [n for n in self.input_spp if n % 2 or n < 4]
        if self.pair and odd:  # a half renders at least 2 spp, as every render (prep.render.frame.SPP)
            raise OptionError("input_spp", f"with --pair each input renders as two halves of half its samples, "
                              f"so each must be even and 4 or more, got {odd}")
        if self.reference_spp <= max(self.input_spp):
            raise OptionError("reference_spp", f"must exceed every input_spp (the reference is a scene's render "
                                               f"with the most samples), got {self.reference_spp} and "
                                               f"{list(self.input_spp)}")
        for fam in self.families:
            if reference_spp(self, fam) > SPP.high:
                raise OptionError("reference_spp", f"{self.reference_spp} renders {fam}'s references at "
                                  f"{REFERENCE_SPP_FACTOR[fam]} times that, {reference_spp(self, fam)}, above the "
                                  f"{SPP.high} of any render; at most {SPP.high // REFERENCE_SPP_FACTOR[fam]} "
                                  f"with {fam}")
        check_frame(self.width, self.height)

    @property
    def render_set(self) -> RenderSet:
        return RenderSet(self.set_name, self.out_root)


@dataclass(frozen=True)
class RenderSet:
    """The folder of one render set, ``<root>/<name>`` (its layout: the module docstring), and the sets named
    after it: the one place a render set's folder and files are named, so that no command or study retypes them."""

    name: str
    root: Path = Path(RENDER_ROOT)  # any path-like given becomes a Path: two sets are equal when their folders are

    def __post_init__(self):
        check_set_name(self.name)
        object.__setattr__(self, "root", Path(self.root))

    @property
    def dir(self) -> Path:
        return self.root / self.name

    @property
    def record_path(self) -> Path:
        """``config.json``: written by ``kpcn render``; a folder without it is no finished set of ours."""
        return self.dir / RECORD

    def render_path(self, scene: str, spp: int) -> Path:
        """The EXR of ``scene`` at ``spp`` samples."""
        return self.dir / render_filename(scene, spp)

    def renders(self) -> list[Path]:
        """Every EXR in the folder, sorted by name."""
        return sorted(self.dir.glob("*.exr"))

    def derived(self, tag: str) -> RenderSet:
        """The set ``<name>-<tag>`` beside this one: a set made from it (a study's larger set, renders of two
        sets joined), named so that its origin shows."""
        return RenderSet(f"{self.name}-{tag}", self.root)


def reference_spp(config: RenderConfig, family: str) -> int:
    """The sample count of the references of ``family`` in a set made with ``config``."""
    return config.reference_spp * REFERENCE_SPP_FACTOR.get(family, 1)


def render_seed(seed: int, family: str, index: int, spp: int, half: str = "") -> int:
    """The seed of the ``spp`` render of scene ``index`` of ``family`` in a set with ``seed``: one per
    sample count, stable, derived by SeedSequence so that no two renders of a set share noise; ``half`` "a" or
    "b": the seed of that half of the ``spp`` input (its own entropy word, 1 or 2: another seed than any frame's)."""
    words = [int(seed), zlib.crc32(family.encode()), int(index), int(spp), 0x52454E44]
    ss = np.random.SeedSequence(words + ([" ab".index(half)] if half else []))
    return int(ss.generate_state(1, dtype=np.uint64)[0])


# config fields that change the pixels of files already on disk
_PIXEL_FIELDS = ("width", "height", "seed")
_TIMINGS = "timings.json"


def _part_timings(label: str) -> str:
    return f"timings.{label}.json"


@dataclass(frozen=True)
class _Render:
    family: str
    index: int
    spp: int
    seed: int
    name: str  # the EXR's file name
    half: str = ""  # "a" or "b": a half of the input of ``2 * spp`` samples (its spp is the half's own)


def _renders(config: RenderConfig) -> list[_Render]:
    """Every render of the set, scene by scene (families x per_family), inputs by sample count, each followed by
    its two halves with ``pair``, then the reference."""
    pair_names = catalogue().pair_names
    out = []
    for fam in config.families:
        for index in range(config.per_family):
            name = make_scene(fam, index, config.seed).name
            for spp in sorted(config.input_spp) + [reference_spp(config, fam)]:
                out.append(_Render(fam, index, spp, render_seed(config.seed, fam, index, spp),
                                   render_filename(name, spp)))
                if config.pair and spp in config.input_spp:
                    out += [_Render(fam, index, spp // 2, render_seed(config.seed, fam, index, spp, half), file,
                                    half) for half, file in zip("ab", pair_names(name, spp))]
    return out


def render_set(config: RenderConfig, progress: bool = True, part: Part = Part()) -> list[Path]:
    """Render every scene of ``config`` (families x per_family) at each input_spp and at its family's
    reference count (:func:`reference_spp`).

    Writes ``<out_root>/<set_name>/<scene>-<spp>spp.exr`` (each with its own seed, see
    :func:`render_seed`), skipping files that exist so an interrupted run resumes, seconds per render to
    ``timings.json``, and, once every render is there, ``config.json`` (the config, each scene's
    ``to_dict()`` and its seeds) and the contact sheet. A new set's ``config.json`` holds its config (no
    scenes) from the start, so that a rerun with other pixels is refused. Returns the EXR paths this call
    is responsible for, input then reference per scene. Raises OptionError if the directory holds a set
    made with a different width, height or seed.

    ``part``: render only this part's share (``prep.parts``: balanced by sample count), under the part's own
    lock, its seconds to ``timings.part-<i>-of-<N>.json``; the part that finds every render there (each looks, under
    the set's lock, when it is done) writes ``config.json``, ``timings.json`` and the contact sheet, the same
    files as one process (``timings.json`` apart, the one file that differs between runs anyway).
    """
    config.validate()
    out_dir = config.render_set.dir
    check_writable(out_dir, "render set folder (--out)", directory=True)
    renders = _renders(config)
    with exclusive_lock(out_dir, "render set"):
        _open_record(config, out_dir)
    mine = [renders[i] for i in part.balanced([r.spp for r in renders])]
    times_name = _TIMINGS if part.whole else _part_timings(part.label)
    with exclusive_lock(out_dir, "render set" if part.whole else f"part {part} of render set", part.lock_name):
        remove_temporaries(out_dir, targets={r.name for r in mine} | {times_name})
        _render_all(config, out_dir, mine, out_dir / times_name, progress)
    with exclusive_lock(out_dir, "render set"):
        _finish(config, out_dir, renders, part)
    return [out_dir / r.name for r in mine]


def reuse_renders(config: RenderConfig, source: str | os.PathLike) -> list[str]:
    """Hard-link (copy, where the file system cannot link) into ``config``'s set folder every render of
    ``config`` that the finished render set in ``source`` holds with the same pixels, so that a larger set made
    from a smaller one (more scenes per family, a longer spp ladder) renders only what it adds. A render is the
    same when the two sets share width, height and seed and ``source``'s record gives the file the seed
    :func:`render_seed` gives it here: the same scene at the same samples and seed, hence the same bytes
    (:func:`render_set` writes the same bytes for the same command). Renders already there are left as they are;
    a source that is not a finished set gives nothing. Returns the names it linked."""
    config.validate()
    source, out_dir = Path(source), config.render_set.dir
    meta_path = source / RECORD
    if source.resolve() == out_dir.resolve() or not meta_path.exists():
        return []
    meta = read_json(meta_path, "render set record", keys=("config", "scenes"))
    if any(meta["config"].get(k) != getattr(config, k) for k in _PIXEL_FIELDS) or not meta["scenes"]:
        return []
    seeds = {(sc["family"], sc["index"], int(spp)): (seed, sc["files"][spp]) for sc in meta["scenes"]
             for spp, seed in sc["seeds"].items()}
    linked = []
    check_writable(out_dir, "render set folder (--out)", directory=True)
    with exclusive_lock(out_dir, "render set"):
        for r in _renders(config):
            found = seeds.get((r.family, r.index, r.spp))
            if found is None or found != (r.seed, r.name) or (out_dir / r.name).exists() \
                    or not (source / r.name).is_file():
                continue
            with atomic_path(out_dir / r.name) as tmp:
                try:
                    os.link(source / r.name, tmp)
                except OSError:  # another file system, or one without hard links
                    shutil.copyfile(source / r.name, tmp)
            linked.append(r.name)
    return linked


def _open_record(config: RenderConfig, out_dir: Path) -> None:
    """Refuse a folder holding a set of other pixels; give a new set its ``config.json`` (no scenes yet)."""
    remove_temporaries(out_dir, targets={RECORD, _TIMINGS, CONTACT_SHEET})
    meta_path = out_dir / RECORD
    if meta_path.exists():
        old_cfg = read_json(meta_path, "render set record", keys=("config",))["config"]
        changed = [k for k in _PIXEL_FIELDS if k in old_cfg and old_cfg[k] != getattr(config, k)]
        if changed:
            raise OptionError(
                changed[0],
                f"differs from the set in {out_dir}, rendered with "
                + ", ".join(f"{k}={old_cfg[k]!r}" for k in changed)
                + "; this config has " + ", ".join(f"{k}={getattr(config, k)!r}" for k in changed)
                + ": use another set_name or remove the directory",
            )
    else:
        atomic_write_json(meta_path, {"config": _config_record(config), "scenes": []})


def _config_record(config: RenderConfig) -> dict:
    record = asdict(config)
    record["families"] = list(config.families)
    record["input_spp"] = list(config.input_spp)
    return record


def _render_all(config: RenderConfig, out_dir: Path, renders: list[_Render], times_path: Path,
                progress: bool) -> None:
    """Render each of ``renders`` whose file is not there yet, its seconds recorded in ``times_path``."""
    times = read_json(times_path, "render timings") if times_path.exists() else {}
    from tqdm import tqdm

    with tqdm(total=len(renders), unit="render", desc=config.set_name, disable=not progress) as bar:
        scene = {}  # the scene of the last render: a scene's renders come one after another
        for r in renders:
            path = out_dir / r.name
            bar.set_postfix_str(r.name)
            if not path.exists():
                if (r.family, r.index) not in scene:
                    scene = {(r.family, r.index): make_scene(r.family, r.index, config.seed)}
                t0 = time.perf_counter()
                layers = render(scene[r.family, r.index], r.spp, r.seed, config.width, config.height)
                # a half's name does not parse as <scene>-<spp>spp.exr: its header states its spp
                write_aovs(path, layers, attributes={SPP_ATTRIBUTE: r.spp} if r.half else None)
                times[path.name] = round(time.perf_counter() - t0, 3)
                atomic_write_json(times_path, times)
            bar.update(1)


def _finish(config: RenderConfig, out_dir: Path, renders: list[_Render], part: Part) -> None:
    """Once every render of the set is there: ``config.json`` with every scene, the parts' seconds folded
    into ``timings.json``, and the contact sheet. The set's lock held."""
    missing = [r.name for r in renders if not (out_dir / r.name).exists()]
    if missing:
        log.info("%s: part %s rendered; %d render%s of other parts still to come (%s%s); the last part to "
                 "finish writes config.json", out_dir, part, len(missing), "s" if len(missing) > 1 else "",
                 ", ".join(missing[:3]), ", ..." if len(missing) > 3 else "")
        return
    meta = {"config": _config_record(config), "scenes": []}
    for r in renders:
        if not meta["scenes"] or (meta["scenes"][-1]["family"], meta["scenes"][-1]["index"]) != (r.family, r.index):
            scene = make_scene(r.family, r.index, config.seed)
            meta["scenes"].append({"name": scene.name, "family": r.family, "index": r.index, "seeds": {},
                                   "files": {}, "scene": scene.to_dict()})
        if r.half:  # under the input's spp, apart from the seeds by spp that reuse_renders reads
            halves = meta["scenes"][-1].setdefault("pairs", {}).setdefault(str(2 * r.spp), {})
            halves[r.half] = {"seed": r.seed, "file": r.name}
            continue
        meta["scenes"][-1]["seeds"][str(r.spp)] = r.seed
        meta["scenes"][-1]["files"][str(r.spp)] = r.name
    atomic_write_json(out_dir / RECORD, meta)
    part_times = sorted(out_dir.glob(_part_timings("part-*-of-*")))
    if part_times:
        times = read_json(out_dir / _TIMINGS, "render timings") if (out_dir / _TIMINGS).exists() else {}
        for path in part_times:
            times.update(read_json(path, "render timings"))
        atomic_write_json(out_dir / _TIMINGS, times)
        for path in part_times:
            path.unlink()
    contact_sheet(out_dir, [(s["family"], s["name"], out_dir / s["files"][str(reference_spp(config, s["family"]))])
                            for s in meta["scenes"]])


CONTACT_SHEET = "contact-sheet.png"


def contact_sheet(out_dir: Path, entries: list[tuple[str, str, Path]]) -> Path:
    """``<out_dir>/contact-sheet.png``: the reference render of every scene, one row per family (the
    same bytes for the same renders: no metadata that changes between runs)."""
    from prep.files import pyplot, save_png

    plt = pyplot()

    from prep.colour import tonemap
    from prep.exr import read_aovs

    rows: dict[str, list[tuple[str, Path]]] = {}
    for family, name, path in entries:
        rows.setdefault(family, []).append((name, path))
    n_cols = max(len(v) for v in rows.values())
    fig, axes = plt.subplots(len(rows), n_cols, figsize=(2.0 * n_cols, 2.1 * len(rows)), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for i, scenes in enumerate(rows.values()):
        for j, (name, path) in enumerate(scenes):
            axes[i, j].imshow(tonemap(read_aovs(path, variances=False)["default"]), interpolation="nearest")
            axes[i, j].set_title(name, fontsize=8)
    fig.tight_layout()
    return save_png(fig, out_dir / CONTACT_SHEET, dpi=80)


# ``kpcn references``: how converged a set's references are (prep.convergence), written into the set's folder
CONVERGENCE_REPORT = ("convergence.md", "convergence.json", "convergence.png")
# the colours a reference is judged by: each branch's target, and the final colour
REPORT_BRANCHES = ("diffuse", "specular", "default")


def convergence_report(config: RenderConfig, progress: bool = True) -> dict:
    """Measure every reference of the finished render set ``<out_root>/<set_name>`` (``prep.convergence``:
    per scene and per colour, diffuse, specular and final, the median and p99 relSE, the converged fraction
    and the spp p99 would need) and write :data:`CONVERGENCE_REPORT` into the set's folder, each atomically,
    under the set's lock. Returns the JSON's content. KpcnError naming the folder if there is no such set or
    ``kpcn render`` has not finished it; AOVError naming a reference without its variance layers."""
    from tqdm import tqdm

    from prep import convergence
    from prep.exr import read_aovs
    from prep.files import atomic_write_text

    check_set_name(config.set_name)
    out_dir, record = config.render_set.dir, config.render_set.record_path
    if not record.is_file():
        raise KpcnError(f"{out_dir}: no render set there (no config.json); render it with "
                        f"'kpcn render --set {config.set_name}'")
    with exclusive_lock(out_dir, "render set"):
        scenes = read_json(record, "render set record", keys=("config", "scenes"))["scenes"]
        if not scenes:
            raise KpcnError(f"{out_dir}: the render set is unfinished (no scenes in config.json); "
                            f"'kpcn render --set {config.set_name}' finishes it")
        frames = []
        for scene in tqdm(scenes, desc=f"references {config.set_name}", unit="frame", disable=not progress):
            spp = max(int(k) for k in scene["files"])
            path = out_dir / scene["files"][str(spp)]
            layers = read_aovs(path, variances=None)
            frame = {"family": scene["family"], "scene": scene["name"], "file": path.name, "spp": spp}
            for branch in REPORT_BRANCHES:
                frame[branch] = convergence.frame_summary(convergence.branch_relse(layers, branch, path), spp)
            frames.append(frame)
        report = {"set": config.set_name, "constants": {"CONVERGENCE_EPS": convergence.CONVERGENCE_EPS,
                                                        "CONVERGED_RELSE": convergence.CONVERGED_RELSE,
                                                        "percentile": convergence.SUMMARY_PERCENTILE},
                  "families": _family_summaries(frames), "frames": frames}
        md, js, png = (out_dir / name for name in CONVERGENCE_REPORT)
        atomic_write_json(js, report)
        atomic_write_text(md, convergence_markdown(report))
        _convergence_png(report, png)
    return report


def _family_summaries(frames: list[dict]) -> dict:
    """family -> its references' spp, the worst p99 relSE of each colour and the most spp any frame needs."""
    out: dict[str, dict] = {}
    for frame in frames:
        fam = out.setdefault(frame["family"], {"frames": 0, "spp": frame["spp"]})
        fam["frames"] += 1
        for branch in REPORT_BRANCHES:
            key = f"{branch}_p99_max"
            fam[key] = max(fam.get(key, 0.0), frame[branch]["p99"])
        fam["spp_needed_max"] = max(fam.get("spp_needed_max", 0), frame["default"]["spp_needed"])
    return out


def convergence_markdown(report: dict) -> str:
    """``convergence.md``: one row per reference, then one per family."""
    c = report["constants"]
    lines = [f"# Reference convergence of render set `{report['set']}`", "",
             f"relSE = sqrt(variance of the mean) / (mean over R G B + {c['CONVERGENCE_EPS']}) per pixel; a pixel is "
             f"converged at relSE <= {c['CONVERGED_RELSE']}; p{c['percentile']:g} over the frame's pixels; spp needed: "
             f"where the final colour's p{c['percentile']:g} would reach {c['CONVERGED_RELSE']} were it to fall as "
             "1/sqrt(spp) (prep/convergence.py).", "",
             "| scene | spp | diffuse p99 | specular p99 | final median | final p99 | final converged | spp needed |",
             "|---|---|---|---|---|---|---|---|"]
    for f in report["frames"]:
        d = f["default"]
        lines.append(f"| {f['scene']} | {f['spp']} | {f['diffuse']['p99']:.4f} | {f['specular']['p99']:.4f} | "
                     f"{d['median']:.4f} | {d['p99']:.4f} | {d['converged']:.3f} | {d['spp_needed']} |")
    lines += ["", "| family | frames | spp | worst diffuse p99 | worst specular p99 | worst final p99 | "
              "most spp needed |", "|---|---|---|---|---|---|---|"]
    for name, fam in report["families"].items():
        lines.append(f"| {name} | {fam['frames']} | {fam['spp']} | {fam['diffuse_p99_max']:.4f} | "
                     f"{fam['specular_p99_max']:.4f} | {fam['default_p99_max']:.4f} | {fam['spp_needed_max']} |")
    return "\n".join(lines) + "\n"


def _convergence_png(report: dict, path: Path) -> Path:
    """``convergence.png``: per family, a box of its references' final-colour p99 relSE, with the line of
    CONVERGED_RELSE (log scale: the families span two decades)."""
    from prep.files import pyplot, save_png

    plt = pyplot()
    families = list(report["families"])
    values = [[f["default"]["p99"] for f in report["frames"] if f["family"] == fam] for fam in families]
    fig, ax = plt.subplots(figsize=(max(4.5, 1.0 + 0.9 * len(families)), 3.6))
    ax.boxplot(values, whis=(0, 100))
    ax.set_xticks(range(1, len(families) + 1), families, rotation=30, ha="right")
    ax.axhline(report["constants"]["CONVERGED_RELSE"], color="tab:red", linestyle="--",
               label=f"converged: relSE {report['constants']['CONVERGED_RELSE']}")
    ax.set_yscale("log")
    ax.set_ylabel("reference p99 relSE (final colour)")
    ax.set_title(f"render set {report['set']}: reference convergence", fontsize=9)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, path, dpi=80)
