"""Render sets: :func:`render_set` renders families x per_family built-in scenes at a ladder of input
sample counts (each with its own seed) and one reference count into ``<out_root>/<set_name>/``, and
records what it did in ``config.json`` (reproducible: the same command writes the same bytes) and how
long it took in ``timings.json`` (the one file that differs between runs). This module owns that folder.
"""

from __future__ import annotations

import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from prep.errors import OptionError
from prep.exr import render_filename, write_aovs
from prep.files import atomic_write_json, check_set_name, check_writable, exclusive_lock, read_json, remove_temporaries
from prep.render.families import FAMILIES, REFERENCE_SPP_FACTOR, make_scene
from prep.render.frame import _check_int, render


@dataclass
class RenderConfig:
    """What :func:`render_set` renders and where."""

    set_name: str = "default"
    families: tuple[str, ...] = tuple(FAMILIES)
    per_family: int = 3
    width: int = 256
    height: int = 256
    input_spp: tuple[int, ...] = (4, 16, 64)  # a ladder: the network sees every noise level
    reference_spp: int = 512  # times families.REFERENCE_SPP_FACTOR for the families slow to converge
    seed: int = 0
    out_root: str = "data/renders"

    def __post_init__(self):
        if isinstance(self.input_spp, (int, np.integer)) and not isinstance(self.input_spp, bool):
            self.input_spp = (int(self.input_spp),)
        self.input_spp = tuple(self.input_spp)
        self.families = tuple(self.families) if not isinstance(self.families, str) else self.families

    def validate(self) -> None:
        check_set_name(self.set_name)
        if isinstance(self.families, str):
            raise OptionError("families", f"must be a tuple of names, got the string {self.families!r}")
        if not self.families:
            raise OptionError("families", "must name at least one scene family")
        for fam in self.families:
            if fam not in FAMILIES:
                raise OptionError("families", f"has unknown scene family {fam!r}; valid families: {', '.join(FAMILIES)}")
        _check_int("per_family", self.per_family, 1)
        _check_int("width", self.width, 1)
        _check_int("height", self.height, 1)
        if not self.input_spp or len(set(self.input_spp)) != len(self.input_spp):
            raise OptionError("input_spp", f"must be distinct sample counts, got {list(self.input_spp)}")
        for spp in self.input_spp:
            _check_int("input_spp", spp, 2)
        _check_int("reference_spp", self.reference_spp, 2)
        _check_int("seed", self.seed, 0)
        if self.reference_spp <= max(self.input_spp):
            raise OptionError("reference_spp", f"must exceed every input_spp (the reference is a scene's render "
                                               f"with the most samples), got {self.reference_spp} and "
                                               f"{list(self.input_spp)}")


def reference_spp(config: RenderConfig, family: str) -> int:
    """The sample count of the references of ``family`` in a set made with ``config``."""
    return config.reference_spp * REFERENCE_SPP_FACTOR.get(family, 1)


def render_seed(seed: int, family: str, index: int, spp: int) -> int:
    """The seed of the ``spp`` render of scene ``index`` of ``family`` in a set with ``seed``: one per
    sample count, stable, derived by SeedSequence so that no two renders of a set share noise."""
    ss = np.random.SeedSequence([int(seed), zlib.crc32(family.encode()), int(index), int(spp), 0x52454E44])
    return int(ss.generate_state(1, dtype=np.uint64)[0])


# config fields that change the pixels of files already on disk
_PIXEL_FIELDS = ("width", "height", "seed")


def render_set(config: RenderConfig, progress: bool = True) -> list[Path]:
    """Render every scene of ``config`` (families x per_family) at each input_spp and at its family's
    reference count (:func:`reference_spp`).

    Writes ``<out_root>/<set_name>/<scene>-<spp>spp.exr`` (each with its own seed, see
    :func:`render_seed`), skipping files that exist so an interrupted run
    resumes, and ``config.json`` (the config, each scene's ``to_dict()`` and its seeds) beside them,
    rewritten atomically after every scene; seconds per render go to ``timings.json``. Holds the
    set's lock. Returns the EXR paths, input then reference per scene. Raises OptionError if the
    directory holds a set made with a different width, height or seed.
    """
    config.validate()
    out_dir = Path(config.out_root) / config.set_name
    check_writable(out_dir, "render set folder (--out)", directory=True)
    with exclusive_lock(out_dir, "render set"):
        remove_temporaries(out_dir)
        return _render_set_locked(config, out_dir, progress)


def _render_set_locked(config: RenderConfig, out_dir: Path, progress: bool) -> list[Path]:
    meta_path, times_path = out_dir / "config.json", out_dir / "timings.json"
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
    times = read_json(times_path, "render timings") if times_path.exists() else {}

    jobs = []
    for fam in config.families:
        for index in range(config.per_family):
            jobs.append((fam, index))
    meta = {"config": asdict(config), "scenes": []}
    meta["config"]["families"] = list(config.families)
    meta["config"]["input_spp"] = list(config.input_spp)
    paths: list[Path] = []

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=(len(config.input_spp) + 1) * len(jobs), unit="render", desc=config.set_name)
    try:
        for fam, index in jobs:
            scene = make_scene(fam, index, config.seed)
            counts = sorted(config.input_spp) + [reference_spp(config, fam)]
            seeds = {spp: render_seed(config.seed, fam, index, spp) for spp in counts}
            record = {
                "name": scene.name,
                "family": fam,
                "index": index,
                "seeds": {str(spp): seed for spp, seed in seeds.items()},
                "files": {},
                "scene": scene.to_dict(),
            }
            for spp, seed in seeds.items():
                path = out_dir / render_filename(scene.name, spp)
                if bar is not None:
                    bar.set_postfix_str(f"{scene.name} {spp}spp")
                if not path.exists():
                    t0 = time.perf_counter()
                    layers = render(scene, spp, seed, config.width, config.height)
                    write_aovs(path, layers)
                    times[path.name] = round(time.perf_counter() - t0, 3)
                    atomic_write_json(times_path, times)
                record["files"][str(spp)] = path.name
                paths.append(path)
                if bar is not None:
                    bar.update(1)
            meta["scenes"].append(record)
            atomic_write_json(meta_path, meta)
    finally:
        if bar is not None:
            bar.close()
    atomic_write_json(meta_path, meta)
    contact_sheet(out_dir, [(r["family"], r["name"], out_dir / r["files"][str(reference_spp(config, r["family"]))])
                            for r in meta["scenes"]])
    return paths


CONTACT_SHEET = "contact-sheet.png"


def contact_sheet(out_dir: Path, entries: list[tuple[str, str, Path]]) -> Path:
    """``<out_dir>/contact-sheet.png``: the reference render of every scene, one row per family (the
    same bytes for the same renders: no metadata that changes between runs)."""
    from prep.files import pyplot, save_png

    plt = pyplot()

    from prep.exr import read_aovs
    from prep.metrics import tonemap

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
