"""Tests of prep.render.packing: the row layouts of the tables the kernels take, as the tracer reads them."""

import dataclasses

import numpy as np
import pytest

from prep.render.packing import pack
from prep.render.scene import Camera, Quad, Scene, Sphere, emitter, lambert


def test_kernel_table_layouts_agree_with_scene():
    from prep.render import packing as sc
    from prep.render import scene, tracer
    from prep.render.scene import Mesh

    assert (tracer.M_KIND, tracer.M_ALBEDO, tracer.M_SPECULAR, tracer.M_ROUGHNESS, tracer.M_EMISSION,
            tracer.M_TEXTURE, tracer.M_ALBEDO2, tracer.M_SCALE) == (
        sc.MAT_KIND, sc.MAT_ALBEDO, sc.MAT_SPECULAR, sc.MAT_ROUGHNESS, sc.MAT_EMISSION, sc.MAT_TEXTURE,
        sc.MAT_ALBEDO2, sc.MAT_SCALE)
    assert scene.MATERIAL_KINDS.index("plastic") == tracer.PLASTIC and scene.TEXTURES.index("uv") == tracer.TEX_UV
    assert scene.TEXTURES.index("image") == tracer.TEX_IMAGE
    q = Quad((1, 2, 3), (0, 0, 2), (3, 0, 0), "m")
    row = pack(Scene("x", "test", Camera((0, 5, 0), (0, 0, 0), up=(0, 0, 1)), {"m": lambert((0.5,) * 3)},
                     quads=[q])).quads[0]
    np.testing.assert_allclose(row[tracer.Q_CORNER:tracer.Q_CORNER + 3], q.corner)
    np.testing.assert_allclose(row[tracer.Q_U:tracer.Q_U + 3], q.u)
    np.testing.assert_allclose(row[tracer.Q_V:tracer.Q_V + 3], q.v)
    np.testing.assert_allclose(row[tracer.Q_NORMAL:tracer.Q_NORMAL + 3], [0, 1, 0])
    assert row[tracer.Q_AREA] == pytest.approx(6.0)
    p = np.array([1 + 0.75, 2, 3 + 0.5])  # a = 0.25 along u, b = 0.25 along v
    assert (p - q.corner) @ row[tracer.Q_DUAL_U:tracer.Q_DUAL_U + 3] == pytest.approx(0.25)
    assert (p - q.corner) @ row[tracer.Q_DUAL_V:tracer.Q_DUAL_V + 3] == pytest.approx(0.25)
    assert (tracer.T_V0, tracer.T_E1, tracer.T_E2, tracer.T_NORMAL, tracer.T_AREA) == (
        sc.TRI_V0, sc.TRI_E1, sc.TRI_E2, sc.TRI_NORMAL, sc.TRI_AREA)
    assert (tracer.L_QUAD, tracer.L_SPHERE, tracer.L_TRIANGLE, tracer.L_ENVIRONMENT) == (
        sc.LIGHT_QUAD, sc.LIGHT_SPHERE, sc.LIGHT_TRIANGLE, sc.LIGHT_ENVIRONMENT)
    assert (tracer.B_LEFT, tracer.B_RIGHT, tracer.B_IS_LEAF, tracer.B_FIRST, tracer.B_COUNT) == (
        sc.BVH_LEFT, sc.BVH_RIGHT, sc.BVH_IS_LEAF, sc.BVH_FIRST, sc.BVH_COUNT)
    assert tracer.BVH_STACK > sc.BVH_MAX_DEPTH
    mesh = Mesh(((1, 2, 3), (3, 2, 3), (1, 2, 5)), ((0, 1, 2),), "m")  # normal cross((2,0,0), (0,0,2)) = -y
    packed = pack(Scene("x", "test", Camera((0, 5, 0), (0, 0, 0), up=(0, 0, 1)), {"m": lambert((0.5,) * 3)},
                        meshes=[mesh]))
    tri = packed.triangles[0]
    assert packed.triangles.shape == (1, sc.TRI_COLS)
    np.testing.assert_allclose(tri[tracer.T_V0:tracer.T_V0 + 3], (1, 2, 3))
    np.testing.assert_allclose(tri[tracer.T_E1:tracer.T_E1 + 3], (2, 0, 0))
    np.testing.assert_allclose(tri[tracer.T_E2:tracer.T_E2 + 3], (0, 0, 2))
    np.testing.assert_allclose(tri[tracer.T_NORMAL:tracer.T_NORMAL + 3], (0, -1, 0))
    assert tri[tracer.T_AREA] == pytest.approx(2.0)
    node = packed.bvh_nodes[0]
    assert node[tracer.B_IS_LEAF] == 1 and (node[tracer.B_FIRST], node[tracer.B_COUNT]) == (0, 1)
    np.testing.assert_allclose(packed.bvh_bounds[0], (1, 2, 3, 3, 2, 5), atol=1e-6)
    # surface() of a triangle hit: the geometric normal and the barycentrics (u along e1, v along e2)
    ng, u, v = tracer.surface((1.5, 2.0, 4.0), 2, 0, packed.spheres, packed.quads, packed.triangles)
    np.testing.assert_allclose(ng, (0, -1, 0))
    assert (u, v) == (pytest.approx(0.25), pytest.approx(0.5))
    # the light table: each light's row holds its own table's values and its material's emission
    assert (tracer.L_A, tracer.L_B, tracer.L_C, tracer.L_NORMAL, tracer.L_AREA, tracer.L_EMISSION) == (
        sc.LIGHT_A, sc.LIGHT_B, sc.LIGHT_C, sc.LIGHT_NORMAL, sc.LIGHT_AREA, sc.LIGHT_EMISSION)
    lights = {"q": emitter((1, 2, 3)), "s": emitter((4, 5, 6)), "t": emitter((7, 8, 9)), "m": lambert((0.5,) * 3)}
    lit = pack(Scene("x", "test", Camera((0, 5, 0), (0, 0, 0), up=(0, 0, 1)), lights,
                     quads=[Quad((9, 9, 9), (1, 0, 0), (0, 0, 1), "m"), dataclasses.replace(q, material="q")],
                     spheres=[Sphere((0, 1, 2), 0.5, "s")], meshes=[dataclasses.replace(mesh, material="t")]))
    assert lit.light_table.shape == (3, sc.LIGHT_COLS) and list(lit.light_kind) == [
        sc.LIGHT_QUAD, sc.LIGHT_SPHERE, sc.LIGHT_TRIANGLE]
    quad, sphere, triangle = lit.light_table
    np.testing.assert_array_equal(quad[:sc.LIGHT_EMISSION], np.r_[row[:12], row[tracer.Q_AREA]])
    np.testing.assert_array_equal(sphere[:sc.LIGHT_B + 1], (0, 1, 2, 0.5))
    np.testing.assert_array_equal(triangle[:sc.LIGHT_EMISSION], tri)
    for light, emission in zip(lit.light_table, ((1, 2, 3), (4, 5, 6), (7, 8, 9))):
        np.testing.assert_array_equal(light[sc.LIGHT_EMISSION:], emission)
