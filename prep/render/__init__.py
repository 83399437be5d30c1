"""The project's own data source: a numba path tracer and the scene sets it renders.

``render(scene, spp, seed, width, height)`` returns one render in the AOV layout of ``prep.exr``;
``render_set(RenderConfig(...))`` renders families x per_family scenes at an input and a reference
sample count into ``<out_root>/<set_name>/`` and records what it did in ``config.json`` (reproducible:
the same command writes the same bytes) and how long it took in ``timings.json`` (the one file that
differs between runs).
"""

from __future__ import annotations

import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from prep.errors import OptionError
from prep.exr import render_filename, write_aovs
from prep.files import atomic_write_json, check_writable, exclusive_lock, read_json, remove_temporaries
from prep.render.families import FAMILIES, make_scene
from prep.render.scene import EFFECTS, Camera, Material, Quad, Scene, Sphere

__all__ = [
    "EFFECTS",
    "FAMILIES",
    "Camera",
    "Material",
    "Quad",
    "RenderConfig",
    "Scene",
    "Sphere",
    "make_scene",
    "render",
    "render_seeds",
    "render_set",
]

# Paths end by Russian roulette from vertex RR_DEPTH (0-based) on; MAX_DEPTH only guards against a
# path that roulette keeps alive by chance (a scene may set a lower cap to imitate another renderer).
MAX_DEPTH = 256
RR_DEPTH = 3
_U64 = (1 << 64) - 1


def _check_int(name, value, lo, hi=None):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise OptionError(name, f"must be an int, got {value!r}")
    if value < lo or (hi is not None and value > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise OptionError(name, f"must be {bound}, got {value!r}")
    return int(value)


def render(scene: Scene, spp: int, seed: int, width: int = 256, height: int = 256, *,
           max_depth: int = MAX_DEPTH, rr_depth: int = RR_DEPTH, effects=None) -> dict[str, np.ndarray]:
    """Path-trace ``scene``: ``layer -> float32 array`` with every layer of the AOV contract
    (``default``, ``diffuse``, ``specular``, ``albedo``, ``normal`` (H, W, 3); ``depth`` and the six
    ``*Variance`` layers (H, W)).

    Same (scene, spp, seed, size) gives bit-identical output; ``seed`` in [0, 2**64) picks the noise.
    ``spp >= 2`` because the variance layers need two samples. ``default`` is exactly
    ``diffuse + specular`` in float32. ``max_depth`` caps the scattering vertices of a path,
    Russian roulette starts at vertex ``rr_depth`` (0-based; >= max_depth switches it off).
    The kernel is the one compiled for ``effects`` (default: ``scene.effects()``, the effects the scene
    calls for; ``EFFECTS`` gives the all-effects kernel, which renders the same bits).
    """
    from prep.render import kernels, tracer  # numba import and kernel loading only when rendering
    from prep.render.packing import pack

    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a prep.render.Scene, got {type(scene).__name__}")
    spp = _check_int("spp", spp, 2)
    seed = _check_int("seed", seed, 0, _U64)
    width = _check_int("width", width, 1)
    height = _check_int("height", height, 1)
    max_depth = _check_int("max_depth", max_depth, 0)
    rr_depth = _check_int("rr_depth", rr_depth, 0)
    needed = scene.effects()
    effects = needed if effects is None else frozenset(effects)
    if not needed <= effects:
        raise ValueError(f"scene {scene.name} calls for {sorted(needed - effects)}, not in effects {sorted(effects)}")
    kernel = kernels.kernel_for(effects)
    packed = pack(scene)
    # prange gives each thread a contiguous block of iterations; a golden-ratio interleaving of the
    # rows makes every block a mix of cheap (sky) and expensive rows
    row_order = np.argsort(np.arange(height) * 0.6180339887498949 % 1.0, kind="stable").astype(np.int64)
    out = np.zeros((height, width, tracer.N_OUT), dtype=np.float64)
    kernel.render_kernel(packed, width, height, spp, np.uint64(seed), max_depth, rr_depth, row_order, out)
    f = out.astype(np.float32)
    diffuse = np.ascontiguousarray(f[..., 0:3])
    specular = np.ascontiguousarray(f[..., 3:6])
    layers = {
        "default": diffuse + specular,
        "diffuse": diffuse,
        "specular": specular,
        "albedo": np.ascontiguousarray(f[..., 6:9]),
        "normal": np.ascontiguousarray(f[..., 9:12]),
        "depth": np.ascontiguousarray(f[..., 12]),
    }
    names = ("diffuseVariance", "specularVariance", "colorVariance", "albedoVariance", "normalVariance",
             "depthVariance")
    for i, name in enumerate(names):
        layers[name] = np.ascontiguousarray(f[..., tracer.OUT_MEANS + i])
    return layers


@dataclass
class RenderConfig:
    """What :func:`render_set` renders and where."""

    set_name: str = "default"
    families: tuple[str, ...] = ("cornell", "spheres", "boxes")
    per_family: int = 4
    width: int = 256
    height: int = 256
    input_spp: int = 8
    reference_spp: int = 512
    seed: int = 0
    out_root: str = "data/renders"

    def validate(self) -> None:
        if not self.set_name or "/" in self.set_name or self.set_name in (".", ".."):
            raise OptionError("set_name", f"must be a plain directory name, got {self.set_name!r}")
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
        _check_int("input_spp", self.input_spp, 2)
        _check_int("reference_spp", self.reference_spp, 2)
        _check_int("seed", self.seed, 0)
        if self.input_spp == self.reference_spp:
            raise OptionError("reference_spp", f"must differ from input_spp, both are {self.input_spp!r}")


def render_seeds(seed: int, family: str, index: int) -> tuple[int, int]:
    """(input seed, reference seed) of scene ``index`` of ``family`` in a set with ``seed``: distinct,
    stable, derived by SeedSequence so sets with neighbouring seeds do not share noise."""
    ss = np.random.SeedSequence([int(seed), zlib.crc32(family.encode()), int(index), 0x52454E44])
    a, b = (int(x) for x in ss.generate_state(2, dtype=np.uint64))
    if a == b:  # astronomically unlikely, but the contract is "different"
        b ^= 1
    return a, b


# config fields that change the pixels of files already on disk
_PIXEL_FIELDS = ("width", "height", "seed")


def render_set(config: RenderConfig, progress: bool = True) -> list[Path]:
    """Render every scene of ``config`` (families x per_family) at input_spp and reference_spp.

    Writes ``<out_root>/<set_name>/<scene>-<spp>spp.exr`` (input and reference rendered with
    different seeds, see :func:`render_seeds`), skipping files that exist so an interrupted run
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
    paths: list[Path] = []

    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=2 * len(jobs), unit="render", desc=config.set_name)
    try:
        for fam, index in jobs:
            scene = make_scene(fam, index, config.seed)
            in_seed, ref_seed = render_seeds(config.seed, fam, index)
            record = {
                "name": scene.name,
                "family": fam,
                "index": index,
                "seeds": {str(config.input_spp): in_seed, str(config.reference_spp): ref_seed},
                "files": {},
                "scene": scene.to_dict(),
            }
            for spp, seed in ((config.input_spp, in_seed), (config.reference_spp, ref_seed)):
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
    return paths
