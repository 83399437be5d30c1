"""The project's own data source: a numba path tracer and the scene sets it renders.

- ``scene.py``: the scene model (materials, shapes, camera, environment) and the effects a scene calls for;
- ``families.py``: the built-in scene families, seeded random permutations;
- ``packing.py``: a scene flattened into the one structure the kernels take;
- ``tracer.py``, ``lights.py``, ``integrator.py``, ``kernels.py``: the numba building blocks, light sampling
  per light kind, the integrator, and one compiled integrator per effect set;
- ``frame.py``: :func:`render`, one frame in the AOV layout of ``prep.exr``;
- ``renderset.py``: :func:`render_set`, a folder of input and reference renders.
"""

from __future__ import annotations

from prep.render.families import FAMILIES, make_scene
from prep.render.frame import MAX_DEPTH, RR_DEPTH, render
from prep.render.renderset import RenderConfig, render_seed, render_set
from prep.render.scene import EFFECTS, Camera, Material, Quad, Scene, Sphere

__all__ = [
    "EFFECTS",
    "FAMILIES",
    "MAX_DEPTH",
    "RR_DEPTH",
    "Camera",
    "Material",
    "Quad",
    "RenderConfig",
    "Scene",
    "Sphere",
    "make_scene",
    "render",
    "render_seed",
    "render_set",
]
