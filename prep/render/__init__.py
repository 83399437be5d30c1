"""The project's own data source: a numba path tracer and the scene sets it renders.

``render(scene, spp, seed, width, height)`` returns one render in the AOV layout of ``prep.exr``;
``render_set(RenderConfig(...))`` renders families x per_family scenes at an input and a reference
sample count into ``<out_root>/<set_name>/`` and records what it did in ``config.json``.
"""

from __future__ import annotations

import json
import math
import time
import zlib
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from prep.exr import render_filename, write_aovs
from prep.files import atomic_write_text
from prep.render.scene import FAMILIES, Camera, Material, Quad, Scene, Sphere, make_scene

__all__ = [
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

MAX_DEPTH = 5  # scattering vertices per path
RR_DEPTH = 3  # Russian roulette from this vertex (0-based) on
_U64 = (1 << 64) - 1


def _check_int(name, value, lo, hi=None):
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an int, got {value!r}")
    if value < lo or (hi is not None and value > hi):
        bound = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name} must be {bound}, got {value!r}")
    return int(value)


def render(scene: Scene, spp: int, seed: int, width: int = 256, height: int = 256, *,
           max_depth: int = MAX_DEPTH, rr_depth: int = RR_DEPTH) -> dict[str, np.ndarray]:
    """Path-trace ``scene``: ``layer -> float32 array`` with every layer of the AOV contract
    (``default``, ``diffuse``, ``specular``, ``albedo``, ``normal`` (H, W, 3); ``depth`` and the six
    ``*Variance`` layers (H, W)).

    Same (scene, spp, seed, size) gives bit-identical output; ``seed`` in [0, 2**64) picks the noise.
    ``spp >= 2`` because the variance layers need two samples. ``default`` is exactly
    ``diffuse + specular`` in float32. ``max_depth`` caps the scattering vertices of a path,
    Russian roulette starts at vertex ``rr_depth`` (0-based; >= max_depth switches it off).
    """
    from prep.render import tracer  # numba import and kernel loading only when rendering

    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a prep.render.Scene, got {type(scene).__name__}")
    spp = _check_int("spp", spp, 2)
    seed = _check_int("seed", seed, 0, _U64)
    width = _check_int("width", width, 1)
    height = _check_int("height", height, 1)
    max_depth = _check_int("max_depth", max_depth, 0)
    rr_depth = _check_int("rr_depth", rr_depth, 0)
    a = scene.to_arrays()
    tan_half = math.tan(math.radians(scene.camera.fov) / 2)
    # prange gives each thread a contiguous block of iterations; a golden-ratio interleaving of the
    # rows makes every block a mix of cheap (sky) and expensive rows
    row_order = np.argsort(np.arange(height) * 0.6180339887498949 % 1.0, kind="stable").astype(np.int64)
    out = np.zeros((height, width, tracer.N_OUT), dtype=np.float64)
    tracer.render_kernel(
        a.spheres, a.sphere_mat, a.quads, a.quad_mat, a.quad_light, a.n_single, a.groups, a.group_bounds,
        a.materials, a.lights, a.light_cdf, a.light_prob, a.camera, tan_half, a.environment,
        width, height, spp, np.uint64(seed), max_depth, rr_depth, row_order, out,
    )
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
            raise ValueError(f"set_name must be a plain directory name, got {self.set_name!r}")
        if isinstance(self.families, str):
            raise ValueError(f"families must be a tuple of names, got the string {self.families!r}")
        for fam in self.families:
            if fam not in FAMILIES:
                raise ValueError(f"unknown scene family {fam!r}; valid families: {', '.join(FAMILIES)}")
        _check_int("per_family", self.per_family, 1)
        _check_int("width", self.width, 1)
        _check_int("height", self.height, 1)
        _check_int("input_spp", self.input_spp, 2)
        _check_int("reference_spp", self.reference_spp, 2)
        _check_int("seed", self.seed, 0)
        if self.input_spp == self.reference_spp:
            raise ValueError(f"input_spp and reference_spp must differ, both are {self.input_spp!r}")


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
    resumes, and ``config.json`` (the config, each scene's ``to_dict()``, its seeds, seconds per
    render) beside them, rewritten atomically after every scene. Returns the EXR paths, input then
    reference per scene. Raises ValueError if the directory holds a set made with a different
    width, height or seed.
    """
    config.validate()
    out_dir = Path(config.out_root) / config.set_name
    out_dir.mkdir(parents=True, exist_ok=True)
    meta_path = out_dir / "config.json"
    previous = {}
    if meta_path.exists():
        old = json.loads(meta_path.read_text())
        old_cfg = old.get("config", {})
        changed = [k for k in _PIXEL_FIELDS if k in old_cfg and old_cfg[k] != getattr(config, k)]
        if changed:
            raise ValueError(
                f"{out_dir} holds a set rendered with "
                + ", ".join(f"{k}={old_cfg[k]!r}" for k in changed)
                + ", this config has " + ", ".join(f"{k}={getattr(config, k)!r}" for k in changed)
                + ": use another set_name or remove the directory"
            )
        previous = {s["name"]: s for s in old.get("scenes", [])}

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
            old_seconds = previous.get(scene.name, {}).get("seconds", {})
            record = {
                "name": scene.name,
                "family": fam,
                "index": index,
                "seeds": {str(config.input_spp): in_seed, str(config.reference_spp): ref_seed},
                "seconds": {},
                "files": {},
                "scene": scene.to_dict(),
            }
            for spp, seed in ((config.input_spp, in_seed), (config.reference_spp, ref_seed)):
                path = out_dir / render_filename(scene.name, spp)
                if bar is not None:
                    bar.set_postfix_str(f"{scene.name} {spp}spp")
                if path.exists():
                    record["seconds"][str(spp)] = old_seconds.get(str(spp))
                else:
                    t0 = time.perf_counter()
                    layers = render(scene, spp, seed, config.width, config.height)
                    write_aovs(path, layers)
                    record["seconds"][str(spp)] = round(time.perf_counter() - t0, 3)
                record["files"][str(spp)] = path.name
                paths.append(path)
                if bar is not None:
                    bar.update(1)
            meta["scenes"].append(record)
            atomic_write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    finally:
        if bar is not None:
            bar.close()
    atomic_write_text(meta_path, json.dumps(meta, indent=2) + "\n")
    return paths
