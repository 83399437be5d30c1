"""The library's numba functions compiled into numba's disk cache once, before a suite's workers start.

numba compiles a function for each set of argument types it is called with, and keeps what it compiled on disk
(``cache=True``: next to the source, in a ``__pycache__`` folder; the render kernels' in ``KPCN_KERNEL_DIR``,
prep/render/kernels.py). From a fresh clone that cache is empty: every worker and every ``kpcn`` process a test
starts, until one of them has written it, compiles the same functions again (the albedo prefilter alone over a
minute on two loaded cores). :func:`compile_all` calls each through the library's own functions, on tiny inputs
of the dtypes and layouts the library passes them, so that each specialisation the suite meets is compiled
here, once; :func:`compiled` lists what the cache holds, and tests/test_compiled.py checks that a fresh process
then compiles none of them again.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np


def _aovs(dtype, h: int = 6, w: int = 7) -> dict[str, np.ndarray]:
    """A noisy render's layers (prep.exr.read_aovs' names), every one of ``dtype``, variances above 0."""
    from prep.features import VARIANCE_OF

    rng = np.random.default_rng(0)
    shapes = {"diffuse": (h, w, 3), "specular": (h, w, 3), "albedo": (h, w, 3), "normal": (h, w, 3),
              "depth": (h, w)}
    aovs = {name: rng.uniform(0.1, 1.0, shape).astype(dtype) for name, shape in shapes.items()}
    for layer in shapes:
        aovs[VARIANCE_OF[layer]] = rng.uniform(0.01, 0.1, (h, w)).astype(dtype)
    return aovs


def _features() -> None:
    """prep.features' kernels as the shard writer (whole frame, its own float64 relative variances) and the
    denoiser and figures (windows at an edge and inside, into the float32 features) call them, on the float32
    layers prep.exr reads and on float64 ones (the renderer's, the tests' own)."""
    from prep import features

    for dtype in (np.float32, np.float64):
        aovs = _aovs(dtype)
        scale = features.depth_scale(aovs["depth"])
        for branch in features.BRANCHES:
            features.branch_buffers(aovs, branch, scale=scale)
            # the whole frame, windows at its edge and inside it, and one pixel (contiguous slices, another type)
            for window in (None, (0, 3, 0, 3), (3, 6, 4, 7), (2, 3, 2, 3)):
                features.branch_features(aovs, branch, window, scale=scale)


def _albedo() -> None:
    """The non-local-means prefilter of the albedo, as prep.auxiliary and the denoiser call it."""
    from prep import albedo

    aovs = _aovs(np.float32)
    albedo.prefilter(aovs["albedo"], aovs["albedoVariance"])


def _sampling() -> None:
    """The error map and the patch PDF of the shard rounds."""
    from prep import sampling

    rng = np.random.default_rng(0)
    out, ref = rng.uniform(0, 1, (6, 6, 3)), rng.uniform(0, 1, (6, 6, 3)).astype(np.float32)
    for metric in sampling.ERROR_METRICS:
        sampling.patch_pdf(sampling.error_map(out, ref, metric), 2)


def _colour() -> None:
    """The scalar relative variance and its inverse (kpcn_keras.fireflies calls them on Python floats)."""
    from prep import colour

    colour.variance_of(colour.relative_variance(0.5, 0.25), 0.25)


def _kernel_apply() -> None:
    """The kernel-prediction layer's inference path (kpcn_keras.layers), on float32 and float64 tensors."""
    import torch

    from kpcn_keras.layers import kernel_apply

    with torch.no_grad():
        for dtype in (torch.float32, torch.float64):
            kernel_apply(torch.ones((1, 4, 4, 3), dtype=dtype), torch.zeros((1, 4, 4, 9), dtype=dtype), 3)


def _render() -> None:
    """The all-effects render kernel (the suite's KPCN_KERNELS=all, tests/conftest.py)."""
    from prep.render import make_scene, render

    render(make_scene("cornell", 0, 0), spp=2, seed=0, width=2, height=2)


# each numba function of the library but the render kernel's, through the library's functions
STEPS = (_albedo, _features, _sampling, _colour, _kernel_apply)


def compile_all(*, render: bool = True) -> None:
    """Each step of :data:`STEPS` (and the render kernel with ``render``): each numba function of the library
    the suite reaches compiled for the types the library calls it with, into numba's disk cache (loaded from it
    where it is there already). numba compiles on one core: the torch side and the render kernel compile in a
    second process meanwhile, which also keeps torch's import out of this one."""
    steps = "_kernel_apply(); _render()" if render else "_kernel_apply()"
    tests = str(Path(__file__).resolve().parents[1])
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (tests, os.environ.get("PYTHONPATH")) if p))
    code = f"from helpers.compiled import _kernel_apply, _render; {steps}"
    child = subprocess.Popen([sys.executable, "-c", code], env=env, cwd=Path(tests).parent,
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        for step in STEPS:
            if step is not _kernel_apply:
                step()
    finally:
        out, _ = child.communicate()
    if child.returncode:
        raise RuntimeError(f"the numba warm-up's second process failed ({child.returncode}):\n{out[-3000:]}")


def compiled() -> dict[str, dict]:
    """numba's count of what each library function loaded from its disk cache and compiled afresh in this
    process: ``{module.name: {"hits": n, "misses": m}}`` (specialisations), for those called at all."""
    from numba.core.registry import CPUDispatcher

    out = {}
    for module_name, module in list(sys.modules.items()):
        if not module_name.startswith(("prep", "kpcn_")) or module is None:
            continue
        for name, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher) and value.__module__ == module_name and value.signatures:
                hits, misses = sum(value.stats.cache_hits.values()), sum(value.stats.cache_misses.values())
                out[f"{module_name}.{name}"] = {"hits": hits, "misses": misses}
    return out
