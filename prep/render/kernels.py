"""One integrator kernel per set of effects: ``kernel_for(effects)``.

A scene's effect set (``Scene.effects()``) picks a copy of ``integrator.py`` whose ``HAS_*`` flags say
exactly those effects; numba compiles the flags as constants, so a diffuse-only scene runs a kernel
without glossy lobes, emitter lookups or an environment, rather than one that branches past them on
every sample. The copies are generated source files in a cache folder (``KPCN_KERNEL_DIR``, by default
``~/.cache/kpcn/kernels``), named by their flags and rewritten only when the integrator changes, so
numba's own on-disk cache keeps each compiled kernel across processes. The all-effects kernel is a
copy too (every flag on), so that every kernel's file name carries a digest of the integrator *and* of
the modules it calls: numba's cache checks only the file a function is in, and would otherwise serve a
kernel compiled against an older ``tracer.py``.

``KPCN_KERNELS=all`` renders every scene with the all-effects kernel instead (:func:`kernel_effects`): the
same bits, one compile for every scene rather than one per effect set (several seconds each), slower per
sample. Short-lived processes that render many small scenes of different effects gain: the test suite sets it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import re
import sys
from pathlib import Path
from types import ModuleType

import prep.render.integrator as integrator
import prep.render.lights as lights
import prep.render.media as media
import prep.render.packing as packing
import prep.render.tracer as tracer
from prep.errors import KpcnError
from prep.files import atomic_write_text
from prep.render.scene import EFFECTS

_BLOCK = re.compile(r"(# --- effects \(kernels\.py rewrites this block.*?\n)(.*?)(# --- end of effects ---)", re.S)
_loaded: dict[frozenset, ModuleType] = {}
KERNEL_CHOICES = ("specialised", "all")  # the values of KPCN_KERNELS; the first is the default


def flag_name(effect: str) -> str:
    return f"HAS_{effect.upper()}"


def kernel_dir() -> Path:
    return Path(os.environ.get("KPCN_KERNEL_DIR") or Path.home() / ".cache" / "kpcn" / "kernels")


def kernel_effects(needed) -> frozenset:
    """The effects of the kernel that renders a scene calling for ``needed``: ``needed`` itself, or every
    effect where ``KPCN_KERNELS=all``."""
    choice = os.environ.get("KPCN_KERNELS") or KERNEL_CHOICES[0]
    if choice not in KERNEL_CHOICES:
        raise KpcnError(f"the environment variable KPCN_KERNELS is {choice!r}; kpcn reads one of "
                        f"{', '.join(KERNEL_CHOICES)}")
    return frozenset(EFFECTS) if choice == "all" else frozenset(needed)


def _source(effects: frozenset) -> str:
    text = Path(integrator.__file__).read_text()
    match = _BLOCK.search(text)
    if match is None or {line.split(" = ")[0] for line in match.group(2).splitlines()} != {
            flag_name(e) for e in EFFECTS}:
        raise RuntimeError(f"{integrator.__file__}: its effects block does not list one flag per scene.EFFECTS")
    flags = "".join(f"{flag_name(e)} = {e in effects}\n" for e in EFFECTS)
    return text[: match.start(2)] + flags + text[match.end(2):]


def kernel_for(effects) -> ModuleType:
    """The integrator module (``render_kernel``, ``trace_sample``, ...) compiled for ``effects``."""
    effects = frozenset(effects)
    unknown = effects - set(EFFECTS)
    if unknown:
        raise ValueError(f"unknown effects {sorted(unknown)}; known: {', '.join(EFFECTS)}")
    if effects in _loaded:
        return _loaded[effects]
    text = _source(effects)
    tag = "".join("1" if e in effects else "0" for e in EFFECTS)
    callees = "".join(Path(m.__file__).read_text() for m in (tracer, lights, media, packing))
    digest = hashlib.sha256((text + callees).encode()).hexdigest()[:12]
    name = f"kpcn_integrator_{tag}_{digest}"
    path = kernel_dir() / f"{name}.py"
    if not path.is_file() or path.read_text() != text:
        atomic_write_text(path, text)
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # numba's cache finds a kernel's module by name when it loads it
    spec.loader.exec_module(module)
    _loaded[effects] = module
    return module
