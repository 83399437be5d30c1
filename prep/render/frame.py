"""One frame: :func:`render` path-traces a scene into the AOV layout of ``prep.exr``, with the integrator
kernel compiled for the effects the scene calls for (``kernels.kernel_for``)."""

from __future__ import annotations

import numpy as np

from prep.bounds import Bound
from prep.errors import OptionError
from prep.processes import memory_shortfall
from prep.render.scene import Scene

# Paths end by Russian roulette from vertex RR_DEPTH (0-based) on; MAX_DEPTH only guards against a
# path that roulette keeps alive by chance (a scene may set a lower cap to imitate another renderer).
MAX_DEPTH = 256
RR_DEPTH = 3
# The bounds of a frame's settings. A side of 16384 (16K) is four times 4K; what the machine can hold is
# checked too (check_frame). spp >= 2: the variance layers need two samples; at most 65536, within the
# five digits of a render's file name (prep.exr.render_filename).
FRAME_SIDE = Bound(1, 16384)
SPP = Bound(2, 65536)
PATH_DEPTH = Bound(0, 4096)
NOISE_SEED = Bound(0, (1 << 64) - 1)  # a render's own seed; render sets derive theirs from an option's SEED


def frame_bytes(width: int, height: int) -> int:
    """The bytes :func:`render` holds at its peak for a ``width`` x ``height`` frame: the kernel's float64
    output, its float32 copy and the float32 layers cut from it (the layers have the output's channels and
    ``default``'s three)."""
    from prep.render.tracer import N_OUT  # numba loads with it, as it will for the render anyway

    return width * height * (8 * N_OUT + 4 * N_OUT + 4 * (N_OUT + 3))


def check_frame(width, height, *, available_mb: float | None = None) -> tuple[int, int]:
    """``(width, height)`` as ints, or OptionError: a side outside :data:`FRAME_SIDE`, or a frame whose
    :func:`frame_bytes` exceed the memory this machine has available (``prep.processes.memory_shortfall``;
    ``available_mb`` instead where given)."""
    width, height = FRAME_SIDE.check("width", width), FRAME_SIDE.check("height", height)
    needed = frame_bytes(width, height)
    short = memory_shortfall(needed, available_mb=available_mb)
    if short:
        # named by the larger side: the one to make smaller (and, with --scene, the one likely given)
        (big, b), (small, s) = sorted([("width", width), ("height", height)], key=lambda t: -t[1])
        raise OptionError(big, f"{b} (with {small} {s}): rendering the frame ({needed // (width * height)} bytes a "
                          f"pixel) {short}")
    return width, height


def render(scene: Scene, spp: int, seed: int, width: int = 256, height: int = 256, *,
           max_depth: int = MAX_DEPTH, rr_depth: int = RR_DEPTH, effects=None) -> dict[str, np.ndarray]:
    """Path-trace ``scene``: ``layer -> float32 array`` with every layer of the AOV contract
    (``default``, ``diffuse``, ``specular``, ``albedo``, ``normal`` (H, W, 3); ``depth`` and the six
    ``*Variance`` layers (H, W)).

    Same (scene, spp, seed, size) gives bit-identical output; ``seed`` (:data:`NOISE_SEED`) picks the
    noise. ``spp`` in :data:`SPP`, the size in :data:`FRAME_SIDE` and within memory (:func:`check_frame`).
    ``default`` is exactly ``diffuse + specular`` in float32. ``max_depth`` caps the scattering vertices of a path,
    Russian roulette starts at vertex ``rr_depth`` (0-based; >= max_depth switches it off).
    The kernel is the one compiled for ``effects`` (default: ``scene.effects()``, the effects the scene
    calls for, or all of them where ``KPCN_KERNELS=all``; ``EFFECTS`` gives the all-effects kernel, which
    renders the same bits).
    """
    # numba and the kernels load only when a frame is rendered
    import prep.render.kernels as kernels
    import prep.render.tracer as tracer
    from prep.render.packing import pack

    if not isinstance(scene, Scene):
        raise ValueError(f"scene must be a prep.render.Scene, got {type(scene).__name__}")
    spp = SPP.check("spp", spp)
    seed = NOISE_SEED.check("seed", seed)
    width, height = check_frame(width, height)
    max_depth = PATH_DEPTH.check("max_depth", max_depth)
    rr_depth = PATH_DEPTH.check("rr_depth", rr_depth)
    needed = scene.effects()
    effects = kernels.kernel_effects(needed) if effects is None else frozenset(effects)
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
