"""One frame: :func:`render` path-traces a scene into the AOV layout of ``prep.exr``, with the integrator
kernel compiled for the effects the scene calls for (``kernels.kernel_for``)."""

from __future__ import annotations

import numpy as np

from prep.errors import OptionError
from prep.render.scene import Scene

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
    from prep.render import kernels, tracer  # numba and the kernels load only when a frame is rendered
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
