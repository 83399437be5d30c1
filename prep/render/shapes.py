"""Procedural triangle meshes (``scene.Mesh``), wound counter-clockwise seen from outside so that their
normals point outwards (closed shapes that glass can use): :func:`icosphere`, :func:`torus`,
:func:`box_mesh`, and :func:`write_obj` to save one as an OBJ file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from prep.render.scene import Mesh, Vec3


def _mesh(vertices: np.ndarray, faces, material: str) -> Mesh:
    return Mesh(tuple(map(tuple, np.asarray(vertices, dtype=np.float64).tolist())),
                tuple(tuple(int(i) for i in f) for f in faces), material)


def icosphere(center: Vec3, radius: float, subdivisions: int, material: str) -> Mesh:
    """A sphere of 20 * 4**subdivisions triangles: an icosahedron whose faces are split in four
    ``subdivisions`` times, vertices pushed onto the sphere."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
             (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    verts = [tuple(np.asarray(v, dtype=np.float64) / math.sqrt(1 + t * t)) for v in verts]
    faces = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
             (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
             (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = (np.asarray(verts[a]) + np.asarray(verts[b])) / 2
                verts.append(tuple(m / np.linalg.norm(m)))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    v = np.asarray(verts) * radius + np.asarray(center, dtype=np.float64)
    return _mesh(v, faces, material)


def torus(center: Vec3, major: float, minor: float, material: str, n_major: int = 24, n_minor: int = 12,
          tilt: float = 0.0) -> Mesh:
    """A torus around the y axis through ``center`` (tube radius ``minor`` at distance ``major``),
    ``n_major * n_minor`` quads split in two triangles each, turned by ``tilt`` degrees about the x axis."""
    i = np.arange(n_major)[:, None]
    j = np.arange(n_minor)[None, :]
    phi = 2 * np.pi * i / n_major  # around the y axis
    theta = 2 * np.pi * j / n_minor  # around the tube
    r = major + minor * np.cos(theta)
    v = np.stack([r * np.cos(phi), minor * np.sin(theta) * np.ones_like(phi), -r * np.sin(phi)], axis=-1)
    v = v.reshape(-1, 3)
    a = math.radians(tilt)
    rot = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    v = v @ rot.T + np.asarray(center, dtype=np.float64)
    faces = []
    for p in range(n_major):
        for q in range(n_minor):
            k00 = p * n_minor + q
            k10 = ((p + 1) % n_major) * n_minor + q
            k01 = p * n_minor + (q + 1) % n_minor
            k11 = ((p + 1) % n_major) * n_minor + (q + 1) % n_minor
            faces += [(k00, k10, k11), (k00, k11, k01)]
    return _mesh(v, faces, material)


def box_mesh(x0, x1, y0, y1, z0, z1, material: str) -> Mesh:
    """The six faces of an axis-aligned box, two triangles each, normals outwards."""
    v = [(x, y, z) for x in (x0, x1) for y in (y0, y1) for z in (z0, z1)]  # index = 4 * ix + 2 * iy + iz
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    return _mesh(np.asarray(v, dtype=np.float64), faces, material)


def write_obj(mesh: Mesh, path, comment: str = "") -> None:
    """Save ``mesh`` as an OBJ file (vertices with 9 significant digits, 1-based faces)."""
    lines = [f"# {line}" for line in comment.splitlines()]
    lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    Path(path).write_text("\n".join(lines) + "\n")
