"""Triangle meshes from Wavefront OBJ files: :func:`load_obj`.

Reads the ``v`` (vertex) and ``f`` (face) lines; a face of more than three vertices is fan-triangulated
(``a b c d`` gives ``a b c`` and ``a c d``), a face vertex may be written ``i``, ``i/t``, ``i//n`` or
``i/t/n`` (only ``i`` is used), and a negative index counts back from the last vertex read so far (``-1``
is the latest). Everything else (``vt``, ``vn``, ``g``, ``o``, ``s``, ``usemtl``, ``mtllib``, lines and
points, comments) is ignored. Winding is kept: for glass, faces must be counter-clockwise seen from
outside (see ``scene.Mesh``).

A problem is an :class:`ObjError` (a :class:`prep.errors.KpcnError` and a ``ValueError``) whose one-line
message starts with the file's path and, where it is about one line, its number:
``torus.obj:12: face vertex '0': OBJ indices start at 1``.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from prep.bounds import is_number
from prep.errors import KpcnError
from prep.files import read_input
from prep.render.scene import Mesh, Vec3, _vec

__all__ = ["ObjError", "load_obj", "transform_vertices"]


class ObjError(KpcnError, ValueError):
    """An OBJ file that cannot be read or describes no valid mesh; the message starts with its path."""


def transform_vertices(vertices: np.ndarray, translate: Vec3 = (0.0, 0.0, 0.0), scale: float = 1.0,
                       rotate_y: float = 0.0) -> np.ndarray:
    """``vertices`` (N, 3) scaled by ``scale``, then turned by ``rotate_y`` degrees about the y axis
    (counter-clockwise seen from +y: +x towards -z), then moved by ``translate``."""
    a = math.radians(rotate_y)
    c, s = math.cos(a), math.sin(a)
    rot = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return (np.asarray(vertices, dtype=np.float64) * scale) @ rot.T + np.asarray(translate, dtype=np.float64)


def _index(token: str, n_read: int, where: str) -> int:
    head = token.split("/", 1)[0]
    try:
        i = int(head)
    except ValueError:
        raise ObjError(f"{where}: face vertex {token!r}: expected an integer vertex index") from None
    if i == 0:
        raise ObjError(f"{where}: face vertex {token!r}: OBJ indices start at 1 (0 is not an index)")
    if i < 0:
        if -i > n_read:
            raise ObjError(f"{where}: face vertex {token!r}: counts back {-i} vertices, only {n_read} read so far")
        return n_read + i
    return i - 1


def load_obj(path, material: str, translate: Vec3 = (0.0, 0.0, 0.0), scale: float = 1.0,
             rotate_y: float = 0.0) -> Mesh:
    """The mesh of the OBJ file ``path`` with ``material``, placed by :func:`transform_vertices`
    (``scale``, then ``rotate_y`` degrees about y, then ``translate``). Raises :class:`ObjError`."""
    path = Path(path)
    translate = _vec(translate, "translate")
    if not is_number(scale) or not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite number > 0, got {scale!r}")
    if not is_number(rotate_y) or not math.isfinite(rotate_y):
        raise ValueError(f"rotate_y must be a finite number of degrees, got {rotate_y!r}")
    data = read_input(path, "an OBJ file", ObjError)
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        text = data.decode("latin-1")  # OBJ is ASCII; names in comments may be anything

    vertices: list[tuple[float, float, float]] = []
    faces: list[tuple[int, int, int]] = []
    face_lines: list[int] = []
    for number, line in enumerate(text.splitlines(), start=1):
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        where = f"{path}:{number}"
        if words[0] == "v":
            if len(words) < 4:
                raise ObjError(f"{where}: vertex {line.strip()!r}: expected 3 coordinates (v x y z)")
            try:
                xyz = tuple(float(w) for w in words[1:4])
            except ValueError:
                raise ObjError(f"{where}: vertex {line.strip()!r}: coordinates must be numbers") from None
            if not all(math.isfinite(c) for c in xyz):
                raise ObjError(f"{where}: vertex {line.strip()!r}: coordinates must be finite")
            vertices.append(xyz)
        elif words[0] == "f":
            if len(words) < 4:
                raise ObjError(f"{where}: face {line.strip()!r}: needs at least 3 vertices")
            idx = [_index(w, len(vertices), where) for w in words[1:]]
            for k in range(1, len(idx) - 1):
                faces.append((idx[0], idx[k], idx[k + 1]))
                face_lines.append(number)
    if not faces:
        raise ObjError(f"{path}: no faces (f lines) in the file")
    for face, number in zip(faces, face_lines):
        if max(face) >= len(vertices):
            raise ObjError(f"{path}:{number}: face vertex {max(face) + 1} does not exist: the file has "
                           f"{len(vertices)} vertices")
    placed = transform_vertices(np.asarray(vertices, dtype=np.float64), translate, float(scale), float(rotate_y))
    try:
        return Mesh(tuple(map(tuple, placed.tolist())), tuple(faces), material)
    except ValueError as exc:
        raise ObjError(f"{path}: {exc}") from None
