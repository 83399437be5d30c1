"""Triangle meshes: the BVH against brute force, a mesh box against the same box of quads, OBJ files and
their errors, meshes in scene files and the specialised mesh kernel against the all-effects one."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from prep.render import EFFECTS, Camera, Quad, Scene, render
from prep.render.obj import ObjError, load_obj
from prep.render.packing import BVH_LEAF_SIZE, pack
from prep.render.scene import Mesh, emitter, glass, lambert
from prep.render.scenefile import dump_scene, load_scene
from prep.render.shapes import box_mesh, icosphere, torus

REPO = Path(__file__).resolve().parents[1]
T_MIN = 1e-7


def mesh_scene(meshes, quads=(), materials=None, **kw) -> Scene:
    mats = materials or {"m": lambert((0.5, 0.5, 0.5))}
    return Scene("mesh", "test", Camera((0, 1, 4), (0, 0.5, 0)), mats, quads=list(quads), meshes=list(meshes), **kw)


def brute_force(o, d, tris):
    """Nearest (t, index) over every row of a packed triangle table (v0, e1, e2, ...), numpy Moeller-Trumbore
    written apart from the tracer's; (inf, -1) on a miss."""
    v0, e1, e2 = tris[:, 0:3], tris[:, 3:6], tris[:, 6:9]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = o - v0
        u = np.einsum("ij,ij->i", s, p) / det
        q = np.cross(s, e1)
        v = q @ d / det
        t = np.einsum("ij,ij->i", e2, q) / det
        ok = (det != 0) & (u >= 0) & (u <= 1) & (v >= 0) & (u + v <= 1) & (t > T_MIN)
    if not ok.any():
        return math.inf, -1
    i = int(np.argmin(np.where(ok, t, np.inf)))
    return float(t[i]), i


def random_rays(rng, sc, n):
    """Rays from around the geometry: half aimed at random triangles, a quarter axis-aligned."""
    lo, hi = sc.bvh_bounds[0, :3], sc.bvh_bounds[0, 3:]
    centre, size = (lo + hi) / 2, (hi - lo).max()
    rays = []
    for k in range(n):
        o = centre + rng.uniform(-1, 1, 3) * size
        if k % 2 == 0:
            i = rng.integers(len(sc.triangles))
            target = sc.triangles[i, 0:3] + sc.triangles[i, 3:6] * 0.3 + sc.triangles[i, 6:9] * 0.3
            d = target - o
        elif k % 4 == 1:
            d = np.zeros(3)
            d[rng.integers(3)] = rng.choice([-1.0, 1.0])
            o = centre + rng.uniform(-0.5, 0.5, 3) * size
        else:
            d = rng.normal(size=3)
        rays.append((o, d / np.linalg.norm(d)))
    return rays


def soup(rng, n=300):
    v = rng.uniform(-1, 1, (3 * n, 3)) * np.repeat(rng.uniform(0.02, 0.5, (n, 1)), 3, axis=0)
    v += np.repeat(rng.uniform(-2, 2, (n, 3)), 3, axis=0)
    return Mesh(tuple(map(tuple, v.tolist())), tuple((3 * i, 3 * i + 1, 3 * i + 2) for i in range(n)), "m")


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["soup", "shapes"])
def test_bvh_finds_the_brute_force_nearest_hit_and_occlusion(kind):
    from prep.render.tracer import intersect_mesh, occluded_mesh

    rng = np.random.default_rng(4)
    if kind == "soup":
        meshes = [soup(rng)]
    else:
        meshes = [torus((0, 0.3, 0), 0.8, 0.25, "m", tilt=30), icosphere((1.5, 0.5, 0.5), 0.5, 2, "m"),
                  box_mesh(-2, -1, 0, 1, -0.5, 0.5, "m")]
    sc = pack(mesh_scene(meshes))
    assert len(sc.triangles) == sum(len(m.faces) for m in meshes)
    hits = 0
    for o, d in random_rays(rng, sc, 400):
        t_ref, i_ref = brute_force(o, d, sc.triangles)
        t, i = intersect_mesh(tuple(o), tuple(d), np.inf, sc)
        assert i == i_ref, (o, d, t, t_ref)
        if i_ref >= 0:
            hits += 1
            assert t == pytest.approx(t_ref, rel=1e-12)
            # a shorter segment stops before the hit, a longer one finds the same
            assert intersect_mesh(tuple(o), tuple(d), t_ref * 0.999, sc)[1] == -1
            assert intersect_mesh(tuple(o), tuple(d), t_ref * 1.001, sc)[1] == i_ref
            assert occluded_mesh(tuple(o), tuple(d), t_ref * 1.001, sc)
            assert not occluded_mesh(tuple(o), tuple(d), t_ref * 0.999, sc)
        else:
            assert t == np.inf
            assert not occluded_mesh(tuple(o), tuple(d), np.inf, sc)
    assert 150 < hits < 400  # both cases exercised


def test_bvh_leaves_partition_the_triangles_inside_nested_bounds():
    # 40 copies of one triangle: no split plane separates their centroids, the median must
    copies = Mesh(((0, 0, 0), (1, 0, 0), (0, 1, 0)), ((0, 1, 2),) * 40, "m")
    sc = pack(mesh_scene([soup(np.random.default_rng(1), 200), copies]))
    nodes, bounds, tris = sc.bvh_nodes, sc.bvh_bounds, sc.triangles
    covered = np.zeros(len(tris), dtype=int)

    def visit(n, depth):
        lo, hi = bounds[n, :3], bounds[n, 3:]
        if nodes[n, 2]:
            first, count = nodes[n, 0], nodes[n, 1]
            assert 1 <= count <= BVH_LEAF_SIZE
            covered[first:first + count] += 1
            for k in range(first, first + count):
                pts = tris[k, 0:3] + np.array([[0, 0], [1, 0], [0, 1]]) @ tris[k, 3:9].reshape(2, 3)
                assert np.all(pts >= lo) and np.all(pts <= hi)
            return depth
        for child in nodes[n, :2]:
            assert child > n and np.all(bounds[child, :3] >= lo) and np.all(bounds[child, 3:] <= hi)
        return max(visit(c, depth + 1) for c in nodes[n, :2])

    assert visit(0, 0) < 40
    assert np.all(covered == 1)
    assert sc.bvh_nodes.dtype == np.int64 and sc.tri_mat.dtype == np.int64


def test_a_scene_without_meshes_packs_empty_tables_of_the_same_types():
    empty = pack(mesh_scene([]))
    full = pack(mesh_scene([box_mesh(0, 1, 0, 1, 0, 1, "m")]))
    for name in ("triangles", "tri_mat", "tri_light", "bvh_bounds", "bvh_nodes"):
        a, b = getattr(empty, name), getattr(full, name)
        assert a.shape[0] == 0 and a.dtype == b.dtype and a.ndim == b.ndim and a.shape[1:] == b.shape[1:], name
        assert a.flags.c_contiguous and b.flags.c_contiguous
    assert "mesh" not in mesh_scene([]).effects() and "mesh" in mesh_scene([box_mesh(0, 1, 0, 1, 0, 1, "m")]).effects()


def test_mesh_model_validates_and_round_trips():
    m = Mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], [[0, 1, 2], [0, 0, 3]], "m")  # one degenerate face
    assert m.vertices[1] == (1.0, 0.0, 0.0) and m.faces == ((0, 1, 2), (0, 0, 3))
    assert "4 vertices" in repr(m) and "2 faces" in repr(m)
    assert len(pack(mesh_scene([m])).triangles) == 1  # degenerate faces are dropped
    for bad, needle in [
        (dict(faces=[[0, 1, 4]]), "face 0 is (0, 1, 4)"),
        (dict(faces=[[0, 1, -1]]), "face 0"),
        (dict(vertices=[[0, 0, 0], [1, 0, float("nan")], [0, 1, 0]]), "vertex 1"),
        (dict(vertices=[[0, 0], [1, 0], [0, 1]]), "Mesh.vertices"),
        (dict(faces=[[0, 0, 1]]), "degenerate"),
        (dict(faces=[]), "at least one face"),
        (dict(faces=[[0.0, 1.0, 2.0]]), "integer"),
    ]:
        kw = {"vertices": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "faces": [[0, 1, 2]], "material": "m", **bad}
        with pytest.raises(ValueError, match=needle.replace("(", r"\(").replace(")", r"\)")):
            Mesh(**kw)
    scene = mesh_scene([torus((0, 0.3, 0), 0.5, 0.2, "m", 8, 6)])
    assert Scene.from_dict(scene.to_dict()) == scene
    assert "meshes" not in mesh_scene([]).to_dict()  # scenes without meshes are described as before
    light = dataclasses.replace(scene, materials={"m": emitter((1.0, 1.0, 1.0))})
    light.validate()  # an emitter mesh is an area light (tests/test_integrator.py)
    assert {"emitter", "mesh"} <= light.effects()
    with pytest.raises(ValueError, match="'nope'"):
        dataclasses.replace(scene, meshes=[box_mesh(0, 1, 0, 1, 0, 1, "nope")]).validate()


def box_scenes():
    """The same closed box as 6 quads and as a 12-triangle mesh, on a floor under an area light."""
    x0, x1, y0, y1, z0, z1 = -0.5, 0.4, 0.0, 0.8, -0.6, 0.3
    mesh = box_mesh(x0, x1, y0, y1, z0, z1, "box")
    v = np.asarray(mesh.vertices)
    faces = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    quads = [Quad(tuple(v[a]), tuple(v[b] - v[a]), tuple(v[d] - v[a]), "box") for a, b, c, d in faces]
    mats = {"box": lambert((0.7, 0.5, 0.3)), "floor": lambert((0.6, 0.6, 0.6)), "light": emitter((8.0, 8.0, 8.0))}
    room = [Quad((-3, 0, -3), (0, 0, 6), (6, 0, 0), "floor"), Quad((-0.5, 2.5, -0.5), (1, 0, 0), (0, 0, 1), "light")]
    cam = Camera((1.2, 1.6, 2.5), (0, 0.3, 0), fov=35)
    with_quads = Scene("quads", "test", cam, mats, quads=room + quads)
    with_mesh = Scene("mesh", "test", cam, mats, quads=room, meshes=[mesh])
    return with_quads, with_mesh


def test_a_mesh_box_renders_like_the_same_box_of_quads():
    with_quads, with_mesh = box_scenes()
    a = render(with_quads, spp=4, seed=3, width=24, height=18)
    b = render(with_mesh, spp=4, seed=3, width=24, height=18)
    on_box = np.abs(a["albedo"] - np.array([0.7, 0.5, 0.3], dtype=np.float32)).max(axis=-1) < 1e-6
    assert on_box.mean() > 0.15
    for layer in ("depth", "normal", "albedo"):
        np.testing.assert_allclose(b[layer], a[layer], atol=1e-5, err_msg=layer)
    # the same random numbers meet the same geometry: the colour agrees up to rounding at rare edges
    diff = np.abs(b["default"].astype(np.float64) - a["default"])
    assert np.mean(diff < 1e-4) > 0.99 and diff.mean() < 1e-3 * a["default"].mean()


@pytest.mark.slow  # compiles specialised kernels: seconds each from a cold cache
def test_the_specialised_mesh_kernel_gives_the_all_effects_bits():
    from prep.render import kernels

    _, scene = box_scenes()
    scene = dataclasses.replace(scene, meshes=scene.meshes + [icosphere((0.9, 0.3, 0.6), 0.3, 1, "glass")],
                                materials={**scene.materials, "glass": glass(1.5)})
    assert scene.effects() == {"lambert", "emitter", "glass", "mesh"}
    assert kernels.kernel_for(scene.effects()) is not kernels.kernel_for(EFFECTS)
    fast = render(scene, spp=3, seed=9, width=16, height=12, effects=scene.effects())
    full = render(scene, spp=3, seed=9, width=16, height=12, effects=EFFECTS)
    for name in fast:
        np.testing.assert_array_equal(fast[name], full[name], err_msg=name)
    with pytest.raises(ValueError, match="mesh"):
        render(scene, spp=2, seed=0, width=4, height=4, effects=scene.effects() - {"mesh"})


def test_a_glass_icosphere_under_a_uniform_environment_returns_the_environment():
    # a closed lossless glass mesh with outward normals: every path leaves with weight 1 (white furnace)
    scene = Scene("furnace", "test", Camera((0, 0, 4), (0, 0, 0), fov=20.0), {"g": glass(1.5)},
                  meshes=[icosphere((0, 0, 0), 1.0, 2, "g")], environment=(0.7, 0.7, 0.7))
    r = render(scene, spp=64, seed=3, width=12, height=12, max_depth=256)
    on = r["depth"] > 0
    assert on.mean() > 0.3
    sigma = np.sqrt(r["colorVariance"][on]).max() + 1e-6
    np.testing.assert_allclose(r["default"][on].astype(np.float64), 0.7, atol=5 * sigma)


# ------------------------------------------------------------------------------------------------
# OBJ files
# ------------------------------------------------------------------------------------------------

OBJ = """# a unit square as one quad, a triangle written with slashes and one with negative indices
mtllib x.mtl
o square
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
vt 0 0
vn 0 0 1
g a
s off
usemtl red
f 1 2 3 4
v 0 0 1
f 1/1/1 2//1 5/1
f -5 -4 -1   # v1 v2 v5 again
l 1 2
"""


def test_obj_faces_are_fan_triangulated_with_slashes_and_negative_indices(tmp_path):
    path = tmp_path / "m.obj"
    path.write_text(OBJ)
    m = load_obj(path, "red")
    assert m.material == "red" and len(m.vertices) == 5
    assert m.faces == ((0, 1, 2), (0, 2, 3), (0, 1, 4), (0, 1, 4))
    placed = load_obj(path, "red", translate=(1, 2, 3), scale=2.0, rotate_y=90.0)
    # scale, then a quarter turn about y (+x goes to -z), then translate
    np.testing.assert_allclose(placed.vertices[1], (1, 2, 3 - 2), atol=1e-12)
    np.testing.assert_allclose(placed.vertices[4], (1 + 2, 2, 3), atol=1e-12)
    assert placed.faces == m.faces


@pytest.mark.parametrize("text, line, needle", [
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 0\n", 4, "indices start at 1"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\n\nf 1 2 7\n", 5, "face vertex 7 does not exist"),
    ("v 0 0 0\nv 1 0 0\nf 1 2\n", 3, "at least 3 vertices"),
    ("v 0 0 0\nv 1 zero 0\n", 2, "must be numbers"),
    ("v 0 0\n", 1, "3 coordinates"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", 4, "only 3 read so far"),
    ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x/1\n", 4, "integer vertex index"),
])
def test_obj_errors_name_the_file_and_line(tmp_path, text, line, needle):
    path = tmp_path / "bad.obj"
    path.write_text(text)
    with pytest.raises(ObjError) as info:
        load_obj(path, "m")
    message = str(info.value)
    assert message.startswith(f"{path}:{line}: ") and needle in message and "\n" not in message, message
    assert isinstance(info.value, ValueError)


def test_obj_errors_about_the_whole_file(tmp_path):
    for text, needle in [("v 0 0 0\n", "no faces"), ("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n", "degenerate")]:
        (tmp_path / "w.obj").write_text(text)
        with pytest.raises(ObjError, match=f"^{re.escape(str(tmp_path / 'w.obj'))}: .*{needle}"):
            load_obj(tmp_path / "w.obj", "m")
    with pytest.raises(ObjError, match="no such file"):
        load_obj(tmp_path / "missing.obj", "m")


def test_the_mesh_scene_file_loads_from_its_obj_and_renders(tmp_path):
    scene, settings = load_scene(REPO / "scenes" / "mesh.toml")
    torus_mesh, pyramid = scene.meshes
    assert len(torus_mesh.faces) == 2 * 32 * 16 and len(pyramid.faces) == 6
    assert torus_mesh == load_obj(REPO / "scenes" / "torus.obj", "gold", translate=(-0.55, 0.141, 0.1), scale=0.4,
                                  rotate_y=15.0)
    assert (REPO / "scenes" / "torus.obj").stat().st_size < 50_000
    assert "mesh" in scene.effects()
    # dumped inline, it loads back to the same scene (no OBJ needed) and renders the same bits
    text = dump_scene(scene, settings)
    assert "obj =" not in text and "vertices = [[" in text
    (tmp_path / "inline.toml").write_text(text)
    again, _ = load_scene(tmp_path / "inline.toml")
    assert again == scene
    kw = dict(spp=2, seed=1, width=24, height=18, effects=EFFECTS)
    a, b = render(scene, **kw), render(again, **kw)
    assert a["default"].tobytes() == b["default"].tobytes()
    # the meshes are seen: the torus's gold and the pyramid's blue plastic albedo
    assert np.any(np.all(np.abs(a["albedo"] - np.float32([0.1, 0.2, 0.6])) < 1e-6, axis=-1))
    assert (a["specular"].sum(axis=-1) > 0.05).mean() > 0.05
