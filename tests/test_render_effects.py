"""The effects beyond diffuse and glossy surfaces: mirrors, glass, thin-lens depth of field and a
gradient environment, each against an analytic value, and each rendered by a kernel specialised to
it that gives the all-effects kernel's bits."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from prep.render import EFFECTS, render
from prep.render.scene import Camera, Quad, Scene, Sphere, emitter, glass, glossy, lambert, mirror

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
    assert scene.effects() != frozenset(EFFECTS)
    fast = render(scene, spp=3, seed=9, width=10, height=8, max_depth=DEEP)
    full = render(scene, spp=3, seed=9, width=10, height=8, max_depth=DEEP, effects=EFFECTS)
    for name in fast:
        np.testing.assert_array_equal(fast[name], full[name], err_msg=name)


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
    scene = Scene("img", "test", Camera((0, 0, 0), (0, 0, -1)), {"t": mat}, quads=[Quad((-1, -1, -3), (2, 0, 0), (0, 2, 0), "t")])
    with pytest.raises(ValueError, match="bad.png"):
        render(scene, spp=2, seed=0, width=4, height=4)
    with pytest.raises(ValueError, match="image"):
        lambert((0.5,) * 3, texture="image")
