"""The effects beyond diffuse and glossy surfaces: mirrors, glass, thin-lens depth of field, a
gradient environment and emissive meshes, each against an analytic value, and each rendered by a kernel
specialised to it that gives the all-effects kernel's bits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from helpers.references import rect_form_factor

from prep.render import EFFECTS, render
from prep.render.packing import pack
from prep.render.scene import Camera, Mesh, Quad, Scene, Sphere, emitter, glass, glossy, lambert, mirror
from prep.render.shapes import icosphere, torus

DEEP = 256  # max_depth for paths that must not be cut short: roulette ends them


def sphere_under(material, env=0.7, **camera):
    cam = Camera(position=(0, 0, 4), look_at=(0, 0, 0), fov=camera.pop("fov", 20.0), **camera)
    return Scene("furnace", "test", cam, {"m": material}, spheres=[Sphere((0, 0, 0), 1.0, "m")],
                 environment=(env, env, env))


@pytest.mark.parametrize("material", [lambert((1.0, 1.0, 1.0)), mirror(), glass(1.5), glass(2.4)],
                         ids=["lambert", "mirror", "glass-1.5", "glass-2.4"])
def test_white_furnace_returns_the_environment(material):
    # a lossless object under a uniform environment of radiance 0.7 looks exactly like the environment:
    # every path ends in it with weight 1 (lambert: cosine sampling of albedo 1; mirror: reflectance 1;
    # glass: Fresnel reflection and clear refraction)
    r = render(sphere_under(material), spp=64, seed=3, width=12, height=12, max_depth=DEEP)
    on_sphere = r["depth"] > 0
    assert on_sphere.mean() > 0.3
    got = r["default"][on_sphere].astype(np.float64)
    sigma = np.sqrt(r["colorVariance"][on_sphere]).max() + 1e-6
    np.testing.assert_allclose(got, 0.7, atol=5 * sigma)


def test_rough_conductor_furnace_loses_only_single_scattering_energy():
    # GGX without multiple scattering loses energy that grows with roughness; at alpha 0.1 the loss is
    # below 2 % (Kulla & Conty 2017, fig. 4), and nothing can add energy
    r = render(sphere_under(glossy((1.0, 1.0, 1.0), 0.1)), spp=256, seed=4, width=12, height=12, max_depth=DEEP)
    on_sphere = r["depth"] > 0
    ratio = r["default"][on_sphere].astype(np.float64).mean() / 0.7
    assert 0.97 < ratio <= 1.0 + 3 * math.sqrt(r["colorVariance"][on_sphere].mean()) / 0.7


def fresnel(cos_i: float, eta: float) -> float:
    """Unpolarised Fresnel reflectance (float64 reference, written independently of the tracer)."""
    sin_t = eta * math.sqrt(1 - cos_i**2)
    if sin_t >= 1:
        return 1.0
    cos_t = math.sqrt(1 - sin_t**2)
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return (rs**2 + rp**2) / 2


@pytest.mark.parametrize("tilt", [0.0, 60.0])
def test_glass_slab_transmits_the_fresnel_fraction(tilt):
    # a camera looks through a glass slab (two parallel faces, outward normals) at a light of radiance 1
    # that the transmitted rays hit and the reflected ones miss: summing the internal reflections,
    # T = (1 - F) / (1 + F) with F the reflectance at the slab's angle
    ior, th = 1.5, math.radians(tilt)
    n = np.array([0.0, math.sin(th), math.cos(th)])  # front face normal, towards the camera
    u = np.array([1.0, 0.0, 0.0]) * 40
    v = np.cross(n, u / 40) * 40  # cross(u, v) along n
    centre = np.zeros(3)
    front = Quad(tuple(centre + 0.05 * n - (u + v) / 2), tuple(u), tuple(v), "glass")
    back = Quad(tuple(centre - 0.05 * n - (u + v) / 2), tuple(v), tuple(u), "glass")  # normal -n
    light = Quad((-3, -3, -5), (6, 0, 0), (0, 6, 0), "light")  # normal +z, towards the slab
    cam = Camera(position=(0, 0, 5), look_at=(0, 0, 0), fov=0.5)
    scene = Scene("slab", "test", cam, {"glass": glass(ior), "light": emitter((1.0, 1.0, 1.0))},
                  quads=[front, back, light])
    r = render(scene, spp=2048, seed=5, width=3, height=3, max_depth=DEEP)
    f = fresnel(math.cos(th), 1 / ior)
    expected = (1 - f) / (1 + f)
    got = r["default"].astype(np.float64).mean()
    sigma = math.sqrt(r["colorVariance"].astype(np.float64).mean() / 9)
    assert abs(got - expected) < 5 * sigma + 1e-3, (got, expected, sigma)
    assert np.all(r["diffuse"] == 0) and np.all(r["albedo"] == 0)  # glass is specular at the first hit


def test_gradient_environment_blends_horizon_to_zenith():
    up = Camera(position=(0, 0, 0), look_at=(0, 1, 0), up=(0, 0, 1), fov=0.5)
    level = Camera(position=(0, 0, 0), look_at=(0, 0, -1), fov=0.5)
    scene = Scene("sky", "test", up, {}, environment=(0.2, 0.3, 0.4), environment_zenith=(1.0, 2.0, 3.0))
    np.testing.assert_allclose(render(scene, spp=2, seed=0, width=1, height=1)["specular"][0, 0], [1, 2, 3],
                               rtol=1e-4)
    level_px = render(dataclasses.replace(scene, camera=level), spp=2, seed=0, width=1, height=1)
    np.testing.assert_allclose(level_px["specular"][0, 0], [0.2, 0.3, 0.4], atol=0.01)


def checker_wall(z, aperture=0.0, focus=None):
    cam = Camera(position=(0, 0, 0), look_at=(0, 0, -1), fov=30, aperture=aperture, focus_distance=focus)
    wall = Quad((-20, -20, z), (0, 40, 0), (40, 0, 0), "c")
    return Scene("dof", "test", cam, {"c": lambert((0.9,) * 3, texture="world", albedo2=(0.05,) * 3,
                                                   checker_scale=1.0)},
                 quads=[wall], environment=(1.0, 1.0, 1.0))


def test_thin_lens_keeps_the_focal_plane_sharp_and_blurs_the_rest():
    pinhole = render(checker_wall(-4), spp=64, seed=6, width=24, height=24)["albedo"]
    focused = render(checker_wall(-4, aperture=0.3, focus=4.0), spp=64, seed=6, width=24, height=24)["albedo"]
    blurred = render(checker_wall(-4, aperture=0.3, focus=1.0), spp=64, seed=6, width=24, height=24)["albedo"]
    # in focus the lens only moves where in the pixel a sample lands: the same image up to pixel noise
    assert np.abs(focused - pinhole).mean() < 0.05
    # out of focus, the checker's contrast drops
    assert blurred.std() < 0.7 * pinhole.std()


@pytest.mark.parametrize("scene", [
    sphere_under(mirror((0.9, 0.8, 0.7))),
    sphere_under(glass(1.5, (0.9, 1.0, 0.9))),
    checker_wall(-4, aperture=0.3, focus=2.0),
    dataclasses.replace(sphere_under(lambert((0.5,) * 3)), environment_zenith=(2.0, 2.0, 3.0)),
], ids=["mirror", "glass", "lens", "gradient"])
def test_specialised_kernel_gives_the_all_effects_bits_for_new_effects(scene):
    assert_specialised_kernel_gives_the_all_effects_bits(scene)


def assert_specialised_kernel_gives_the_all_effects_bits(scene):
    assert scene.effects() != frozenset(EFFECTS)
    fast = render(scene, spp=3, seed=9, width=10, height=8, max_depth=DEEP)
    full = render(scene, spp=3, seed=9, width=10, height=8, max_depth=DEEP, effects=EFFECTS)
    for name in fast:
        np.testing.assert_array_equal(fast[name], full[name], err_msg=name)
    assert fast["default"].max() > 0


@pytest.mark.parametrize("radius,height", [(0.1, 1.0), (0.6, 0.8)], ids=["small-far", "large-close"])
def test_lambert_plane_under_a_sphere_light_matches_the_analytic_irradiance(radius, height):
    # a sphere of radiance Le seen from a point whose normal points at its centre: E = pi Le (r / d)^2,
    # so a plane of albedo a reflects L = a Le (r / d)^2. Small and far is carried by light sampling;
    # large and close needs the MIS weight of BSDF-sampled hits to be right as well.
    albedo, le = 0.6, 5.0
    cam = Camera(position=(0, 0.3, 1.0), look_at=(0, 0, 0), fov=0.5)
    scene = Scene("sphere-light", "test", cam, {"g": lambert((albedo,) * 3), "light": emitter((le,) * 3)},
                  spheres=[Sphere((0, height, 0), radius, "light")],
                  quads=[Quad((-50, 0, -50), (0, 0, 100), (100, 0, 0), "g")])
    assert "emitter" in scene.effects()
    r = render(scene, spp=2048, seed=8, width=3, height=3)
    expected = albedo * le * (radius / height) ** 2
    got = r["diffuse"][1, 1].astype(np.float64)
    sigma = math.sqrt(r["diffuseVariance"][1, 1])
    assert np.all(np.abs(got - expected) < 5 * sigma + 1e-3 * expected), (got, expected, sigma)
    assert sigma < 0.05 * expected  # not vacuous


def test_a_sphere_light_seen_directly_shows_its_radiance():
    cam = Camera(position=(0, 0, 3), look_at=(0, 0, 0), fov=2.0)
    scene = Scene("lamp", "test", cam, {"light": emitter((2.0, 3.0, 4.0))}, spheres=[Sphere((0, 0, 0), 0.5, "light")])
    r = render(scene, spp=2, seed=0, width=3, height=3)
    np.testing.assert_allclose(r["specular"], np.broadcast_to([2.0, 3.0, 4.0], (3, 3, 3)), rtol=1e-6)


def test_image_texture_gives_the_texel_under_each_pixel(tmp_path):
    # a 2x2 PNG on a quad that fills the view: each image quadrant's albedo AOV is albedo x its texel
    import matplotlib.image

    texels = np.array([[[255, 0, 0], [0, 255, 0]], [[0, 0, 255], [128, 128, 128]]], dtype=np.uint8)
    png = tmp_path / "t.png"
    matplotlib.image.imsave(png, texels)
    cam = Camera(position=(0, 0, 0), look_at=(0, 0, -1), fov=40.0)
    h = math.tan(math.radians(20.0)) * 3.0  # the quad at z = -3 exactly fills the view
    # corner at the image's top left: u runs right (across), v runs down
    quad = Quad((-h, h, -3.0), (2 * h, 0, 0), (0, -2 * h, 0), "t")
    mat = lambert((0.5, 0.8, 1.0), texture="image", image=str(png))
    r = render(Scene("img", "test", cam, {"t": mat}, quads=[quad]), spp=2, seed=0, width=8, height=8)
    linear = (texels / 255.0) ** 2.2
    for (y, x), (ty, tx) in {(1, 1): (0, 0), (1, 6): (0, 1), (6, 1): (1, 0), (6, 6): (1, 1)}.items():
        np.testing.assert_allclose(r["albedo"][y, x], np.array([0.5, 0.8, 1.0]) * linear[ty, tx], rtol=1e-3, atol=1e-4)
    assert "texture" in Scene("img", "test", cam, {"t": mat}, quads=[quad]).effects()


def test_an_image_texture_that_cannot_be_read_is_named(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    mat = lambert((0.5,) * 3, texture="image", image=str(tmp_path / "bad.png"))
    scene = Scene("img", "test", Camera((0, 0, 0), (0, 0, -1)), {"t": mat},
                  quads=[Quad((-1, -1, -3), (2, 0, 0), (0, 2, 0), "t")])
    with pytest.raises(ValueError, match="bad.png"):
        render(scene, spp=2, seed=0, width=4, height=4)
    with pytest.raises(ValueError, match="image"):
        lambert((0.5,) * 3, texture="image")


# ------------------------------------------------------------------------------------------------
# emissive meshes: area lights made of triangles
# ------------------------------------------------------------------------------------------------

def rect_mesh(x0, x1, z0, z1, h, material) -> Mesh:
    """The rectangle [x0, x1] x [z0, z1] at height h as two triangles whose normals, cross(v1 - v0, v2 - v0),
    point down (-y), as the quad below does."""
    return Mesh(((x0, h, z0), (x1, h, z0), (x1, h, z1), (x0, h, z1)), ((0, 1, 2), (0, 2, 3)), material)


def rect_quad(x0, x1, z0, z1, h, material) -> Quad:
    return Quad((x0, h, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), material)  # cross(u, v) points down


def plane_under(receiver, quads=(), meshes=(), spheres=(), le=5.0) -> Scene:
    """A plane of material ``receiver`` at y = 0 under lights of radiance ``le``, its point at the origin
    filling the view (the camera looks at it from (0, 0.5, 1), like the quad-light tests of test_render)."""
    cam = Camera(position=(0, 0.5, 1.0), look_at=(0, 0, 0), fov=1.0)
    return Scene("mesh-light", "test", cam, {"r": receiver, "light": emitter((le,) * 3)},
                 quads=[Quad((-50, 0, -50), (0, 0, 100), (100, 0, 0), "r"), *quads], meshes=list(meshes),
                 spheres=list(spheres))


def assert_centre_pixel(r, layer, expected, k=4.0):
    """The centre pixel of ``layer`` is ``expected`` within k standard errors of its mean (and the check is
    not vacuous: the standard error is below 3 % of the value)."""
    sigma = math.sqrt(r[f"{layer}Variance"][1, 1])
    got = r[layer][1, 1].astype(np.float64)
    assert np.all(np.abs(got - expected) < k * sigma + 1e-4 * expected), (layer, got, expected, sigma)
    assert sigma < 0.03 * expected, (layer, sigma, expected)


@pytest.mark.parametrize("extent", [0.2, 1.0], ids=["small", "large-close"])
def test_lambert_plane_under_an_emissive_mesh_matches_the_form_factor(extent):
    # the rectangle light of test_render's form-factor test, made of two triangles: L = albedo Le F. Small, it
    # is carried by light sampling; large and close, BSDF-sampled hits on the triangles carry weight too.
    albedo, le = 0.6, 5.0
    scene = plane_under(lambert((albedo,) * 3), meshes=[rect_mesh(-extent, extent, -extent, extent, 1.0, "light")],
                        le=le)
    assert scene.effects() == {"lambert", "emitter", "mesh"}
    r = render(scene, spp=4096, seed=5, width=3, height=3)
    assert_centre_pixel(r, "diffuse", albedo * le * rect_form_factor(-extent, extent, -extent, extent, 1.0))
    assert np.all(r["specular"][1, 1] == 0)


@pytest.mark.parametrize("receiver", [lambert((0.6,) * 3), glossy((0.9,) * 3, 0.3)],
                         ids=["lambert", "glossy-0.3"])
def test_a_rectangle_light_as_a_mesh_lights_like_the_same_quad(receiver):
    # the light is met in the mirror direction of the view, so that for the glossy receiver BSDF-sampled
    # rays hit it often and their MIS weight, with the density of sampling a point on a triangle, matters.
    # Grey, so that each channel's variance is the variance layer's RGB average.
    light = (-0.5, 0.5, -2.5, -1.5, 1.0)
    as_quad = render(plane_under(receiver, quads=[rect_quad(*light, "light")]), spp=4096, seed=7, width=3, height=3)
    as_mesh = render(plane_under(receiver, meshes=[rect_mesh(*light, "light")]), spp=4096, seed=8, width=3, height=3)
    layer = "diffuse" if receiver.kind == "lambert" else "specular"
    a, b = as_quad[layer][1, 1].astype(np.float64), as_mesh[layer][1, 1].astype(np.float64)
    sigma = math.sqrt(as_quad[f"{layer}Variance"][1, 1] + as_mesh[f"{layer}Variance"][1, 1])
    assert np.all(np.abs(a - b) < 4 * sigma), (a, b, sigma)
    assert sigma < 0.03 * a.min()  # not vacuous


@pytest.mark.parametrize("facing", ["down", "up"])
def test_an_emissive_mesh_emits_on_the_side_of_its_normal_only(facing):
    # a square at y = 1 whose triangles face down (towards the plane below, and a camera under it) or up
    square = rect_mesh(-0.5, 0.5, -0.5, 0.5, 1.0, "light")
    if facing == "up":
        square = Mesh(square.vertices, tuple((a, c, b) for a, b, c in square.faces), "light")
    scene = plane_under(lambert((0.5,) * 3), meshes=[square])
    scene = dataclasses.replace(scene, materials={**scene.materials, "light": emitter((2.0, 3.0, 4.0))})
    seen = render(dataclasses.replace(scene, camera=Camera((0, 0.5, 0), (0, 1, 0), up=(0, 0, -1), fov=20.0)),
                  spp=4, seed=1, width=4, height=4)
    lit = render(scene, spp=4, seed=1, width=3, height=3)
    np.testing.assert_allclose(seen["depth"], 0.5, rtol=0.03)  # the camera sees the square either way
    if facing == "down":
        np.testing.assert_allclose(seen["specular"], np.broadcast_to([2.0, 3.0, 4.0], (4, 4, 3)), rtol=1e-6)
        assert np.all(lit["diffuse"] > 0)
    else:  # black from behind, and it lights nothing behind it
        assert np.all(seen["default"] == 0)
        assert np.all(lit["default"] == 0)


def polygon_form_factor(x, n, verts) -> float:
    """Form factor from a differential area at x with unit normal n to a polygon wholly above its horizon:
    Lambert's contour integral, (1 / 2 pi) |sum over edges of the angle the edge subtends at x times the
    cosine between n and the normal of the plane through x and the edge|."""
    r = np.asarray(verts, dtype=np.float64) - x
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    total = 0.0
    for a, b in zip(r, np.roll(r, -1, axis=0)):
        g = np.cross(a, b)
        total += math.acos(min(1.0, max(-1.0, float(a @ b)))) * float(n @ g) / np.linalg.norm(g)
    return abs(total) / (2 * math.pi)


def test_an_icosphere_light_of_many_triangles_matches_the_sum_of_their_form_factors():
    # 1280 emitting triangles (light picking by bisection over them): each ray from the lit point meets one
    # triangle facing it, so E = Le * sum of the form factors of the triangles facing the point
    albedo, le, centre, radius = 0.6, 5.0, np.array([0.0, 1.0, 0.0]), 0.4
    ball = icosphere(tuple(centre), radius, 3, "light")
    scene = plane_under(lambert((albedo,) * 3), meshes=[ball], le=le)
    v, f = (np.asarray(a) for a in ball.arrays())
    x, n = np.zeros(3), np.array([0.0, 1.0, 0.0])
    tris = v[f]
    facing = np.einsum("ij,ij->i", np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), x - tris[:, 0]) > 0
    ff = sum(polygon_form_factor(x, n, t) for t in tris[facing])
    sphere_ff = (radius / np.linalg.norm(centre - x)) ** 2  # the sphere it approximates, from inside
    assert len(f) == 1280 and 0.97 * sphere_ff < ff < sphere_ff
    r = render(scene, spp=4096, seed=6, width=3, height=3)
    assert np.all(np.isfinite(r["default"]))
    assert_centre_pixel(r, "diffuse", albedo * le * ff)


def linear_pick(cdf, u) -> int:
    """The light selection the kernels used before bisection: a scan from the first light."""
    i = 0
    while i < len(cdf) - 1 and u >= cdf[i]:
        i += 1
    return i


def test_the_light_pick_bisects_to_the_index_a_linear_scan_gives():
    from prep.render.tracer import search_cdf

    rng = np.random.default_rng(0)
    many = pack(plane_under(lambert((0.5,) * 3), quads=[rect_quad(-1, 1, -1, 1, 2, "light")],
                            meshes=[icosphere((0, 1, 0), 0.4, 2, "light")])).light_cdf
    cdfs = [many, np.array([1.0]), np.array([0.5, 1.0]), np.array([0.25, 0.25, 0.25, 0.7, 0.7, 1.0]),
            np.cumsum(rng.dirichlet(np.ones(37)))]
    for cdf in cdfs:
        cdf = np.ascontiguousarray(cdf, dtype=np.float64)
        # random u, and u on and next to every boundary, where a wrong comparison would show
        us = np.concatenate([rng.random(500), [0.0, np.nextafter(1.0, 0.0)], cdf, np.nextafter(cdf, 0.0),
                             np.nextafter(cdf, 2.0)])
        for u in us:
            assert search_cdf(cdf, float(u)) == linear_pick(cdf, u), (len(cdf), u)


def test_emissive_triangles_join_the_light_list_after_quads_and_spheres_in_bvh_order():
    from prep.render import tracer

    ball = icosphere((0, 1, 0), 0.3, 1, "light")  # 80 triangles, wound among a lambert torus's in the BVH
    dim = Mesh(((0, 2, 0), (1, 2, 0), (0, 2, 1)), ((0, 1, 2),), "off")  # emitter of zero emission: no light
    scene = plane_under(lambert((0.5,) * 3), quads=[rect_quad(-1, 1, -1, 1, 3, "light")],
                        spheres=[Sphere((2, 1, 0), 0.2, "light")],
                        meshes=[torus((0, 1, 0), 0.5, 0.2, "r", 8, 6), ball, dim])
    scene = dataclasses.replace(scene, materials={**scene.materials, "off": emitter((0.0, 0.0, 0.0))})
    sc = pack(scene)
    assert list(sc.light_kind) == [tracer.L_QUAD, tracer.L_SPHERE] + [tracer.L_TRIANGLE] * 80
    light_mat = list(scene.materials).index("light")
    assert np.array_equal(sc.tri_light >= 0, sc.tri_mat == light_mat)
    emitting = np.flatnonzero(sc.tri_light >= 0)
    assert not np.array_equal(emitting, 96 + np.arange(80))  # the BVH did reorder the triangles of the meshes
    assert np.array_equal(sc.lights[sc.tri_light[emitting]], emitting)
    assert np.array_equal(sc.tri_light[emitting], 2 + np.arange(80))
    # each light entry is a triangle of the ball, by its vertices in the packed (BVH-ordered) table
    ball_v = np.asarray(ball.vertices)
    for i in sc.lights[2:]:
        v0 = sc.triangles[i, tracer.T_V0:tracer.T_V0 + 3]
        assert np.min(np.linalg.norm(ball_v - v0, axis=1)) < 1e-12
    # power: area x luminance, as for the quad (area 4) and the sphere (area 4 pi r^2)
    v, f = ball.arrays()
    area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    np.testing.assert_allclose(sorted(sc.triangles[sc.lights[2:], tracer.T_AREA]), sorted(area), rtol=1e-12)
    areas = np.concatenate([[4.0, 4 * math.pi * 0.2**2], sc.triangles[sc.lights[2:], tracer.T_AREA]])
    np.testing.assert_allclose(sc.light_prob, areas / areas.sum(), rtol=1e-12)


def test_specialised_kernel_gives_the_all_effects_bits_for_emissive_meshes():
    # a quad light, a rectangle and a ball of emitting triangles, and a torus casting shadows
    scene = plane_under(lambert((0.5,) * 3), quads=[rect_quad(-1, -0.5, -1, -0.5, 2, "light")],
                        meshes=[rect_mesh(0.2, 0.8, -0.5, 0.1, 1.5, "light"),
                                icosphere((-0.6, 0.8, 0.3), 0.25, 1, "light"),
                                torus((0.3, 0.4, 0), 0.3, 0.1, "r", 12, 6)])
    scene = dataclasses.replace(scene, camera=Camera((0, 1.5, 3), (0, 0.5, 0), fov=60))
    assert scene.effects() == {"lambert", "emitter", "mesh"}
    assert_specialised_kernel_gives_the_all_effects_bits(scene)
