"""``kpcn render-cycles``: training renders from Blender Cycles, random procedural scenes, each a noisy frame per
input spp and a reference, as Blender writes them (one multilayer OpenEXR a frame, every pass a denoiser can use);
``kpcn import-renders`` then writes them into a render set that ``kpcn shards --inputs no-variance`` cuts
(docs/training.md §6, docs/results/16-cycles-frames.md).

The scenes are built and rendered by ``prep/render/blender/cycles_set.py`` (:data:`BLENDER_SIDE`, shipped with
the package), which runs in a Python that has ``bpy``, Blender's Python module: bpy 5.0.1 wants Python 3.11 and
numpy < 2, so it lives in a venv of its own (``make .venv-bpy/bin/python``), where kpcn is not installed. That
file imports nothing of kpcn; this module checks the options and that Python, and hands the file its arguments
(:func:`blender_command`). The file keeps every frame already there, so a killed run resumes.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from prep.bounds import SEED, Bound, bounded, check_fields
from prep.errors import KpcnError, OptionError
from prep.render.frame import FRAME_SIDE, SPP

BLENDER_SIDE = Path(__file__).with_name("blender") / "cycles_set.py"
CATALOGUE = BLENDER_SIDE.with_name("catalogue.py")  # the effects, a scene's recipe, the manifest: stdlib alone
BLENDER_PYTHON = ".venv-bpy/bin/python"  # where make .venv-bpy/bin/python installs bpy
SCENE_INDEX = Bound(0, 99_999)  # a scene's index seeds it; its name has at least three digits
# asks the Python whether it can import bpy, without importing it (bpy takes seconds to load)
HAS_BPY = "import importlib.util, sys; sys.exit(importlib.util.find_spec('bpy') is None)"


@dataclass
class CyclesConfig:
    """What ``kpcn render-cycles`` renders, where, and with which Python."""

    out: str  # the folder of the frames (OUT)
    scenes: str = "0:32"  # first:end scene indices, end excluded
    res: tuple[int, ...] = bounded((128,), FRAME_SIDE, distinct=True)  # sides; each scene draws one, res x res
    spp: tuple[int, ...] = bounded((4, 8, 16, 32, 64), SPP, distinct=True)  # the inputs' samples
    ref_spp: int = bounded(1024, SPP)  # the reference's samples
    seed: int = bounded(0, SEED)  # another seed draws other scenes under the same indices
    blender_python: str = BLENDER_PYTHON

    def __post_init__(self):
        self.spp = tuple(self.spp)
        self.res = (self.res,) if isinstance(self.res, int) else tuple(self.res)
        check_fields(self)
        if not self.out:
            raise OptionError("out", "names no folder for the frames")
        if self.ref_spp <= max(self.spp):
            raise OptionError("ref_spp", f"must exceed every --spp (the reference is a scene's frame with the most "
                              f"samples), got {self.ref_spp} and {list(self.spp)}")
        self.scene_range()

    def scene_range(self) -> range:
        """The scene indices ``scenes`` names; OptionError unless it is first:end with first < end."""
        first, colon, end = self.scenes.partition(":")
        try:
            first, end = int(first), int(end)
        except ValueError:
            raise OptionError("scenes", f"must be first:end (scene indices, end excluded), got {self.scenes!r}") \
                from None
        if not colon or first >= end:
            raise OptionError("scenes", f"must be first:end with first < end, got {self.scenes!r}")
        for index in (first, end - 1):
            SCENE_INDEX.check("scenes", index)
        return range(first, end)


def blender_command(cfg: CyclesConfig) -> list[str]:
    """The command that renders ``cfg`` in its Python: :data:`BLENDER_SIDE` and its arguments."""
    scenes = cfg.scene_range()
    return [cfg.blender_python, str(BLENDER_SIDE), cfg.out, "--scenes", f"{scenes.start}:{scenes.stop}",
            "--res", ",".join(map(str, cfg.res)), "--spp", ",".join(map(str, cfg.spp)), "--ref-spp", str(cfg.ref_spp),
            "--seed", str(cfg.seed)]


def catalogue():
    """``prep/render/blender/catalogue.py``, the module Blender's Python imports beside ``cycles_set.py``, loaded
    by its path (it is no module of kpcn: that Python has no kpcn)."""
    name = "kpcn_cycles_catalogue"
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, CATALOGUE)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules[name] = module
    return sys.modules[name]


def check_recorded(cfg: CyclesConfig) -> None:
    """KpcnError if a scene of the range is recorded in ``cfg.out`` (``<scene>.json``) as another scene
    than this command draws (another --seed or --res, or an older catalogue): the frames there are of that one."""
    cat, out = catalogue(), Path(cfg.out)
    for index in cfg.scene_range():
        recipe = json.loads(json.dumps(cat.draw(cfg.seed, index, cfg.res)))
        recorded = sorted(out.glob(f"*-{index:03d}.json")) if out.is_dir() else []
        path = recorded[0] if recorded else out / f"{recipe['name']}.json"  # under another kind's name too
        if not path.is_file():
            older = sorted(out.glob(f"*-{index:03d}-*spp.exr")) if out.is_dir() else []
            if older:  # frames of this index with no recipe: an earlier generator's scene, not this one
                raise KpcnError(f"{older[0]}: a frame of scene {index} without its recipe {path.name} (rendered "
                                "before scenes recorded their effects); choose another folder")
            continue
        try:
            recorded = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise KpcnError(f"{path}: not a readable scene recipe ({e})") from None
        drop = {"frames"}
        if {k: v for k, v in recorded.items() if k not in drop} != {k: v for k, v in recipe.items() if k not in drop}:
            raise KpcnError(f"{path} records another scene than --seed {cfg.seed} --res "
                              f"{','.join(map(str, cfg.res))} draws (seed {recorded.get('seed')}, res "
                              f"{recorded.get('res')}, version {recorded.get('version')}); choose another folder")


def check_blender_python(python: str) -> None:
    """OptionError ``blender_python`` unless ``python`` runs and can import bpy."""
    found = shutil.which(python) if os.sep not in python else (python if os.access(python, os.X_OK) else None)
    make = "make .venv-bpy/bin/python makes one (Python 3.11, numpy < 2, bpy 5.0.1)"
    if found is None:
        raise OptionError("blender_python", f"{python}: no such Python; {make}")
    if subprocess.run([python, "-c", HAS_BPY], capture_output=True).returncode != 0:
        raise OptionError("blender_python", f"{python}: a Python without bpy, Blender's module; {make}")


def render_cycles(cfg: CyclesConfig) -> Path:
    """Render ``cfg`` (its frames and ``render_log.json`` into ``cfg.out``) in its Python; KpcnError if that
    Python stops with an error (the frames written are kept: the same command resumes)."""
    check_recorded(cfg)
    return run_blender_side(cfg, blender_command(cfg))


def run_blender_side(cfg, command: list[str]) -> Path:
    """Run ``command`` (the Blender side, in ``cfg.blender_python``, once that Python is checked) writing into
    ``cfg.out``; KpcnError if it stops with an error (the frames it wrote are kept: the same command resumes)."""
    check_blender_python(cfg.blender_python)
    done = subprocess.run(command).returncode
    if done != 0:
        raise KpcnError(f"{cfg.out}: Blender's Python ({cfg.blender_python}) stopped with exit status {done}; the "
                        "frames it wrote are kept, and the same command resumes")
    return Path(cfg.out)


def manifest_summary(out: str | Path) -> str:
    """The folder's manifest in a few lines (``OUT/manifest.json``, recounted from the folder)."""
    cat = catalogue()
    return cat.summary(cat.write_manifest(str(out)))


VALIDATION_SCENES = Bound(1, 999)  # 9 or more cover each of the 9 effect groups twice (catalogue.forced_effects)


@dataclass
class ValidationConfig:
    """What ``kpcn cycles-validation`` renders: the held-out Cycles validation set, scenes ``0:scenes`` of the
    catalogue's validation split (drawn apart from every training scene: catalogue.SPLITS), each an input per
    ``spp`` with every pass, Blender's own denoised frame of each (same seed), the input's two halves at half its
    spp with two other seeds (catalogue.pair_names: every pass), and a reference of Combined alone; or, with
    ``verify``, the check of a folder against its manifest's checksums."""

    out: str
    scenes: int = bounded(12, VALIDATION_SCENES)
    res: int = bounded(128, FRAME_SIDE)
    spp: tuple[int, ...] = bounded((4, 16, 64), SPP, distinct=True)
    ref_spp: int = bounded(2048, SPP)
    seed: int = bounded(0, SEED)
    blender_python: str = BLENDER_PYTHON
    verify: bool = False

    def __post_init__(self):
        self.spp = tuple(self.spp)
        check_fields(self)
        if not self.out:
            raise OptionError("out", "names no folder for the frames")
        if self.ref_spp <= max(self.spp):
            raise OptionError("ref_spp", f"must exceed every --spp, got {self.ref_spp} and {list(self.spp)}")
        odd = [n for n in self.spp if n % 2]
        if odd:  # each input is also rendered as two halves of n / 2 samples (catalogue.pair_names)
            raise OptionError("spp", f"must be even (each input is also rendered in two halves), got {odd}")


def validation_command(cfg: ValidationConfig) -> list[str]:
    """The command that renders ``cfg`` in its Python: :data:`BLENDER_SIDE` with ``--split validation``."""
    return [cfg.blender_python, str(BLENDER_SIDE), cfg.out, "--split", "validation", "--scenes", f"0:{cfg.scenes}",
            "--res", str(cfg.res), "--spp", ",".join(map(str, cfg.spp)), "--ref-spp", str(cfg.ref_spp),
            "--seed", str(cfg.seed)]


def check_validation_recorded(cfg: ValidationConfig) -> None:
    """KpcnError if ``cfg.out`` records a validation scene other than this command draws under its name (another
    --seed, --res, --spp or catalogue), or holds training scenes (their recipes have no split)."""
    cat, out = catalogue(), Path(cfg.out)
    if not out.is_dir():
        return
    frames = [*cfg.spp, cfg.ref_spp]
    for path in sorted(out.glob("*.json")):
        if path.name in (cat.MANIFEST, cat.RENDER_LOG) or path.name.startswith("."):
            continue
        try:
            recorded = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise KpcnError(f"{path}: not a readable scene recipe ({e})") from None
        if not isinstance(recorded, dict) or recorded.get("split") != "validation":
            raise KpcnError(f"{path}: not a validation scene (a training folder?); choose another folder")
        index = recorded.get("index")
        drawn = cat.draw(cfg.seed, index, (cfg.res,), frames, "validation") if isinstance(index, int) else None
        if json.loads(json.dumps(drawn)) != recorded:
            raise KpcnError(f"{path} records another scene than --seed {cfg.seed} --res {cfg.res} --spp "
                            f"{','.join(map(str, cfg.spp))} --ref-spp {cfg.ref_spp} draws; choose another folder")


def verify_validation(out: str | Path) -> str:
    """KpcnError naming the first file of ``out`` that is missing or differs from its manifest's checksum (or a
    planned frame not rendered); else a line saying how many files were checked."""
    cat = catalogue()
    problem = cat.verify(str(out))
    if problem:
        raise KpcnError(problem)
    with open(Path(out) / cat.MANIFEST) as f:
        count = len(json.load(f)["sha256"])
    return f"{out}: {count} files match their sha256 in {cat.MANIFEST}"


def render_validation(cfg: ValidationConfig) -> Path:
    """Render the validation set ``cfg`` (resuming: files there are kept) and write its manifest with every
    file's checksum; KpcnError if Blender's Python stops with an error."""
    check_validation_recorded(cfg)
    return run_blender_side(cfg, validation_command(cfg))
