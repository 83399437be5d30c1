"""A :class:`~prep.render.scene.Scene` packed into the one typed structure the kernels take.

:func:`pack` flattens a scene into a :class:`PackedScene`, a named tuple of arrays and scalars that numba
passes to the kernels as one argument (``sc.quads``, ``sc.materials``, ...). This module owns the row
layouts of the tables; ``tracer.py`` mirrors the column numbers (a test checks they agree).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from prep.render.scene import MATERIAL_KINDS, TEXTURES, Scene, _luminance, _vec

# Layout of one row of the material table handed to the kernels (see tracer.py).
MAT_KIND, MAT_ALBEDO, MAT_SPECULAR, MAT_ROUGHNESS = 0, 1, 4, 7
MAT_EMISSION, MAT_TEXTURE, MAT_ALBEDO2, MAT_SCALE = 8, 11, 12, 15
MAT_IOR = 16
MAT_COLS = 17
# Layout of one row of the quad table: corner, u, v, unit normal, dual vectors of u and v, area.
QUAD_COLS = 19



class PackedScene(NamedTuple):
    """The flat arrays (and scalars) of a scene, in the layouts above."""

    spheres: np.ndarray  # (Ns, 4) centre, radius
    sphere_mat: np.ndarray  # (Ns,) int64
    quads: np.ndarray  # (Nq, QUAD_COLS)
    quad_mat: np.ndarray  # (Nq,) int64
    quad_light: np.ndarray  # (Nq,) int64, index into lights or -1
    n_single: int  # quads[:n_single] are tested one by one
    groups: np.ndarray  # (Ng, 2) int64 [start, end) ranges of the other quads
    group_bounds: np.ndarray  # (Ng, 4) bounding sphere (centre, radius) of each range
    materials: np.ndarray  # (Nm, MAT_COLS)
    lights: np.ndarray  # (Nl,) int64 quad index of each light
    light_cdf: np.ndarray  # (Nl,) cumulative selection probability
    light_prob: np.ndarray  # (Nl,) selection probability (proportional to power)
    camera: np.ndarray  # (12,) see Camera.frame
    tan_half: float  # tan(vertical field of view / 2)
    lens_radius: float  # 0 for a pinhole
    focus_distance: float  # along the view direction
    environment: np.ndarray  # (3,) radiance towards the horizon
    environment_zenith: np.ndarray  # (3,) radiance straight up (= environment when constant)


def _quad_order(quads) -> tuple[list[int], int, np.ndarray, np.ndarray]:
    """Order of the quads in the kernel's table: quads tested one by one first, then runs of >= 3
    consecutive quads sharing a material (the faces of one box), each with a bounding sphere so that
    a ray missing it skips them all. Returns (order, number of single quads, ranges, spheres)."""
    singles, runs = [], []
    i = 0
    while i < len(quads):
        j = i + 1
        while j < len(quads) and quads[j].material == quads[i].material:
            j += 1
        (runs.append(list(range(i, j))) if j - i >= 3 else singles.extend(range(i, j)))
        i = j
    order = list(singles)
    ranges, bounds = [], []
    for run in runs:
        pts = np.array([np.asarray(quads[k].corner) + a * np.asarray(quads[k].u) + b * np.asarray(quads[k].v)
                        for k in run for a in (0, 1) for b in (0, 1)])
        centre = (pts.min(axis=0) + pts.max(axis=0)) / 2
        radius = np.linalg.norm(pts - centre, axis=1).max() * (1 + 1e-6) + 1e-6
        ranges.append((len(order), len(order) + len(run)))
        bounds.append((*centre, radius))
        order.extend(run)
    return (order, len(singles), np.asarray(ranges, dtype=np.int64).reshape(-1, 2),
            np.asarray(bounds, dtype=np.float64).reshape(-1, 4))


def pack(scene: Scene) -> PackedScene:
    """Flatten ``scene`` (validated first) into a :class:`PackedScene`."""
    scene.validate()
    names = list(scene.materials)
    index = {n: i for i, n in enumerate(names)}
    mats = np.zeros((max(len(names), 1), MAT_COLS), dtype=np.float64)
    for i, n in enumerate(names):
        m = scene.materials[n]
        mats[i, MAT_KIND] = MATERIAL_KINDS.index(m.kind)
        mats[i, MAT_ALBEDO:MAT_ALBEDO + 3] = m.albedo
        mats[i, MAT_SPECULAR:MAT_SPECULAR + 3] = m.specular
        mats[i, MAT_ROUGHNESS] = m.roughness
        mats[i, MAT_EMISSION:MAT_EMISSION + 3] = m.emission
        mats[i, MAT_TEXTURE] = TEXTURES.index(m.texture)
        mats[i, MAT_ALBEDO2:MAT_ALBEDO2 + 3] = m.albedo2
        mats[i, MAT_SCALE] = m.checker_scale
        mats[i, MAT_IOR] = m.ior

    spheres = np.array([[*s.center, s.radius] for s in scene.spheres], dtype=np.float64).reshape(-1, 4)
    sphere_mat = np.array([index[s.material] for s in scene.spheres], dtype=np.int64)

    order, n_single, groups, bounds = _quad_order(scene.quads)
    quads = np.zeros((len(scene.quads), QUAD_COLS), dtype=np.float64)
    quad_mat = np.zeros(len(scene.quads), dtype=np.int64)
    quad_light = np.full(len(scene.quads), -1, dtype=np.int64)
    lights, powers = [], []
    for i, q in enumerate(scene.quads[k] for k in order):
        u, v = np.asarray(q.u), np.asarray(q.v)
        nn = np.cross(u, v)
        w = nn / nn.dot(nn)
        # p - corner = a*u + b*v  =>  a = (p - corner).cross(v, w), b = (p - corner).cross(w, u)
        quads[i] = np.concatenate([q.corner, u, v, nn / np.linalg.norm(nn),
                                   np.cross(v, w), np.cross(w, u), [np.linalg.norm(nn)]])
        quad_mat[i] = index[q.material]
        m = scene.materials[q.material]
        if m.kind == "emitter" and max(m.emission) > 0:
            quad_light[i] = len(lights)
            lights.append(i)
            powers.append(q.area * max(_luminance(m.emission), 1e-6))
    powers = np.asarray(powers, dtype=np.float64)
    prob = powers / powers.sum() if len(powers) else powers
    cdf = np.cumsum(prob)
    if len(cdf):
        cdf[-1] = 1.0
    return PackedScene(
        spheres=spheres, sphere_mat=sphere_mat, quads=quads, quad_mat=quad_mat, quad_light=quad_light,
        n_single=n_single, groups=groups, group_bounds=bounds, materials=mats,
        lights=np.asarray(lights, dtype=np.int64), light_cdf=cdf, light_prob=prob,
        camera=scene.camera.frame(), tan_half=math.tan(math.radians(scene.camera.fov) / 2),
        lens_radius=float(scene.camera.aperture), focus_distance=scene.camera.focus,
        environment=np.asarray(_vec(scene.environment, "environment")),
        environment_zenith=np.asarray(_vec(scene.environment if scene.environment_zenith is None
                                           else scene.environment_zenith, "environment_zenith")),
    )

