"""Environment maps: the latitude-longitude mapping, importance sampling by texel luminance, the
procedural sky, and renders lit by a map against float64 quadratures over its texels (written here,
independently of the tracer)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.chi_square import assert_follows, assert_rejects

from prep.exr import write_aovs
from prep.render import EFFECTS, render
from prep.render.environment import bake_sky, sampling_tables, texel_directions
from prep.render.packing import pack
from prep.render.scene import Camera, EnvironmentMap, Quad, Scene, Sky, Sphere, lambert, mirror
from prep.render.tracer import env_lookup, env_sample, env_texel

DEEP = 256


def texel_irradiance(texels: np.ndarray) -> np.ndarray:
    """Irradiance (RGB) on an upward-facing plane: sum over the texels of the upper hemisphere of radiance
    x the exact integral of cos(theta) over the texel's solid angle."""
    height, width = texels.shape[:2]
    t0 = np.arange(height) * math.pi / height
    t1 = t0 + math.pi / height
    # integral of cos sin over [t0, t1] x the azimuth span, clipped at the horizon
    t1 = np.minimum(t1, math.pi / 2)
    w = np.where(t0 < math.pi / 2, (np.sin(t1) ** 2 - np.sin(t0) ** 2) / 2, 0.0) * (2 * math.pi / width)
    return np.einsum("i,ijc->c", w, texels)


def stripes_map(tmp_path, height=16, width=32, seed=0):
    """An EXR map of random colours with one hot texel (a small sun), and its texels."""
    rng = np.random.default_rng(seed)
    texels = rng.uniform(0.05, 1.0, (height, width, 3)).astype(np.float32)
    texels[3, 5] = (400.0, 380.0, 350.0)
    path = tmp_path / "env.exr"
    write_aovs(path, {"default": texels})
    return path, texels.astype(np.float64)


def plane_under(env_map, albedo=0.5, size=8):
    cam = Camera(position=(0, 3, 0.01), look_at=(0, 0, 0), fov=10)
    return Scene("plane", "test", cam, {"g": lambert((albedo,) * 3)},
                 quads=[Quad((-1, 0, -1), (0, 0, 2), (2, 0, 0), "g")], environment_map=env_map), size


def test_texel_of_a_direction_agrees_with_the_documented_mapping():
    sc = pack(plane_under(EnvironmentMap(sky=Sky(height=8)))[0])
    d, _ = texel_directions(8, 16)
    for i in range(8):
        for j in range(16):
            assert env_texel(sc, tuple(d[i, j])) == (i, j)
    assert env_texel(sc, (0.0, 1.0, 0.0))[0] == 0  # straight up: the first row
    assert env_texel(sc, (1.0, 0.0, 0.0))[1] == 8  # +x: azimuth 0, the middle column
    assert env_texel(sc, (0.0, 0.0, 1.0))[1] == 12  # +z: azimuth 90 degrees


@pytest.mark.slow
def test_sampled_directions_estimate_the_irradiance_of_the_map(tmp_path):
    # E[L cos / pdf] over env_sample's draws is the irradiance; the hot texel makes a wrong pdf show
    path, texels = stripes_map(tmp_path)
    sc = pack(plane_under(EnvironmentMap(image=str(path)))[0])
    rng = np.random.default_rng(1)
    n = 60000
    vals = np.zeros((n, 3))
    for s, (u1, u2) in enumerate(rng.random((n, 2))):
        d, pdf, le = env_sample(sc, u1, u2)
        assert pdf > 0
        np.testing.assert_allclose(pdf, env_lookup(sc, d)[1], rtol=1e-6)
        if d[1] > 0:
            vals[s] = np.asarray(le) * d[1] / pdf
    want = texel_irradiance(texels)
    sigma = vals.std(axis=0) / math.sqrt(n)
    assert np.all(np.abs(vals.mean(axis=0) - want) < 5 * sigma), (vals.mean(axis=0), want, sigma)
    assert np.all(sigma < 0.02 * want)  # importance sampling: the sun costs little variance


def test_sampled_directions_fall_in_each_texel_in_proportion_to_luminance_times_solid_angle(tmp_path):
    # the sampler's inversion of its CDFs, held to texel weights written here: luminance x sin(theta) at the
    # texel's centre (its solid angle, to first order)
    path, texels = stripes_map(tmp_path)
    sc = pack(plane_under(EnvironmentMap(image=str(path)))[0])
    height, width = texels.shape[:2]
    n = 20000
    observed = np.zeros((height, width))
    for u1, u2 in np.random.default_rng(4).random((n, 2)):
        observed[env_texel(sc, env_sample(sc, u1, u2)[0])] += 1
    sin_t = np.sin((np.arange(height) + 0.5) * math.pi / height)[:, None]
    luminance = texels @ np.array([0.2126, 0.7152, 0.0722])
    assert_follows(observed, n * luminance * sin_t / (luminance * sin_t).sum(), alpha=1e-4)
    # the same draws reject the weights without the solid angle
    assert_rejects(observed, n * luminance / luminance.sum(), alpha=1e-4)


def test_sampling_tables_follow_luminance_times_solid_angle():
    texels = bake_sky(Sky(height=16))
    pdf, row_cdf, col_cdf, mean_lum = sampling_tables(texels)
    _, sin_t = texel_directions(16, 32)
    lum = texels @ np.array([0.2126, 0.7152, 0.0722])
    np.testing.assert_allclose(pdf.mean(), 1.0, rtol=1e-12)  # a density over the unit square
    np.testing.assert_allclose(pdf / pdf.max(), lum * sin_t[:, None] / (lum * sin_t[:, None]).max(), rtol=1e-12)
    np.testing.assert_allclose(row_cdf[-1], 1.0)
    np.testing.assert_allclose(col_cdf[:, -1], 1.0)
    np.testing.assert_allclose(mean_lum, (lum * sin_t[:, None]).sum() / (sin_t.sum() * 32), rtol=1e-12)


def test_lambert_plane_under_a_map_reflects_albedo_times_irradiance(tmp_path):
    path, texels = stripes_map(tmp_path)
    scene, size = plane_under(EnvironmentMap(image=str(path), scale=0.5), albedo=0.6)
    r = render(scene, spp=64, seed=2, width=size, height=size, max_depth=DEEP)
    want = 0.6 / math.pi * texel_irradiance(0.5 * texels)
    got = r["default"].astype(np.float64).reshape(-1, 3).mean(axis=0)
    sigma = math.sqrt(r["colorVariance"].astype(np.float64).sum()) / size**2
    np.testing.assert_allclose(got, want, atol=5 * sigma + 1e-6)
    assert sigma < 0.02 * want.mean()  # the hot texel is light-sampled


def test_white_furnace_under_a_constant_map_returns_it(tmp_path):
    path = tmp_path / "grey.exr"
    write_aovs(path, {"default": np.full((8, 16, 3), 0.7, dtype=np.float32)})
    cam = Camera(position=(0, 0, 4), look_at=(0, 0, 0), fov=20)
    for material in (lambert((1.0, 1.0, 1.0)), mirror()):
        scene = Scene("furnace", "test", cam, {"m": material}, spheres=[Sphere((0, 0, 0), 1.0, "m")],
                      environment_map=EnvironmentMap(image=str(path)))
        r = render(scene, spp=64, seed=3, width=12, height=12, max_depth=DEEP)
        np.testing.assert_allclose(r["default"].astype(np.float64), 0.7,
                                   atol=5 * math.sqrt(r["colorVariance"].max()) + 1e-6)


def test_the_sun_is_seen_directly_and_the_sky_elsewhere():
    sky = Sky(sun_elevation=30.0, sun_azimuth=90.0, sun_radius=5.0, height=64)
    el = math.radians(30.0)
    sun = (0.0, math.sin(el), math.cos(el))
    cam = Camera(position=(0, 0, 0), look_at=sun, fov=1.0)
    scene = Scene("sun", "test", cam, {}, environment_map=EnvironmentMap(sky=sky, scale=2.0))
    r = render(scene, spp=4, seed=0, width=4, height=4)
    np.testing.assert_allclose(r["specular"], np.broadcast_to(np.multiply(sky.sun, 2.0), (4, 4, 3)), rtol=1e-6)
    assert np.all(r["diffuse"] == 0) and np.all(r["depth"] == 0)
    away = Scene("sky", "test", Camera(position=(0, 0, 0), look_at=(0, 1, -0.01), fov=1.0), {},
                 environment_map=EnvironmentMap(sky=sky))
    r = render(away, spp=4, seed=0, width=2, height=2)
    assert np.all(r["specular"] < 0.01 * min(sky.sun))


@pytest.mark.slow  # compiles specialised kernels: seconds each from a cold cache
def test_a_map_and_its_kernel_specialisation_render_the_same_bits(tmp_path):
    path, _ = stripes_map(tmp_path)
    scene, size = plane_under(EnvironmentMap(image=str(path)))
    scene.spheres.append(Sphere((0, 0.3, 0), 0.3, "g"))
    assert scene.effects() == {"lambert", "environment_map"}
    a = render(scene, spp=4, seed=5, width=size, height=size, effects=scene.effects())
    b = render(scene, spp=4, seed=5, width=size, height=size, effects=EFFECTS)
    for layer in a:
        np.testing.assert_array_equal(a[layer], b[layer], err_msg=layer)


@pytest.mark.parametrize("kwargs, needle", [
    (dict(), "exactly one"),
    (dict(image="sky.exr", sky=Sky()), "exactly one"),
    (dict(image="sky.hdr"), "EnvironmentMap.image must be an .exr or .png"),
    (dict(sky=Sky(), scale=-1.0), "EnvironmentMap.scale must be >= 0"),
])
def test_environment_map_rejects_bad_fields(kwargs, needle):
    with pytest.raises(ValueError, match=needle):
        EnvironmentMap(**kwargs)


def test_a_map_with_a_colour_environment_is_refused():
    scene, _ = plane_under(EnvironmentMap(sky=Sky()))
    scene.environment = (0.1, 0.1, 0.1)
    with pytest.raises(ValueError, match="Scene.environment must stay black"):
        scene.validate()


def test_an_environment_image_that_is_not_a_map_is_named(tmp_path):
    bad = tmp_path / "aovs.exr"
    write_aovs(bad, {"depth": np.ones((4, 8), dtype=np.float32)})
    with pytest.raises(ValueError, match=r"aovs\.exr: an RGB image needs channels R G B"):
        pack(plane_under(EnvironmentMap(image=str(bad)))[0])
    neg = tmp_path / "neg.exr"
    write_aovs(neg, {"default": np.full((4, 8, 3), -1.0, dtype=np.float32)})
    with pytest.raises(ValueError, match=r"neg\.exr: environment texels must be finite and >= 0"):
        pack(plane_under(EnvironmentMap(image=str(neg)))[0])
