"""Tests of prep.render: the AOV contract, determinism, analytic cases and unbiasedness statistics.

Images are tiny (<= 32x32) so the file runs in seconds once numba's cache is warm.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from helpers.commands import assert_one_line_error, run_main
from helpers.files import checksums
from helpers.references import rect_form_factor

from prep.exr import LAYER_OF_VARIANCE, RGB_LAYERS, SCALAR_LAYERS, VARIANCE_OF, read_aovs
from prep.render import FAMILIES, RenderConfig, make_scene, render, render_seed, render_set
from prep.render.families import REFERENCE_SPP_FACTOR
from prep.render.packing import pack
from prep.render.renderset import reference_spp
from prep.render.scene import (
    Camera,
    Material,
    Quad,
    Scene,
    Sphere,
    emitter,
    glossy,
    lambert,
)

ALL_LAYERS = RGB_LAYERS + SCALAR_LAYERS
VAR_OF = LAYER_OF_VARIANCE  # variance layer -> the layer whose pixel mean it describes


def _lum(c):
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


def grey(scene: Scene) -> Scene:
    """The scene with every colour replaced by its luminance: R, G and B of each path sample are then
    identical, so each channel's variance equals the channel-averaged variance layers exactly."""
    def g(c):
        y = _lum(c)
        return (y, y, y)

    mats = {k: dataclasses.replace(m, albedo=g(m.albedo), albedo2=g(m.albedo2), specular=g(m.specular),
                                   emission=g(m.emission))
            for k, m in scene.materials.items()}
    env = g(scene.environment)
    return dataclasses.replace(scene, materials=mats, environment=env)


def facing_scene(env=(0.2, 0.3, 0.4), with_sphere=False, half=0.6) -> Scene:
    """Camera at the origin looking down -z at a unit-ish quad 3 units away (its cross(u, v) points
    away from the camera, so the shading normal must be flipped) or a sphere; the image corners see
    only the environment."""
    cam = Camera(position=(0, 0, 0), look_at=(0, 0, -1), up=(0, 1, 0), fov=40.0)
    mats = {"grey": lambert((0.5, 0.4, 0.3))}
    if with_sphere:
        return Scene("sphere", "test", cam, mats, spheres=[Sphere((0, 0, -4), 0.7, "grey")],
                     environment=env)
    quad = Quad((-half, -half, -3.0), (0, 2 * half, 0), (2 * half, 0, 0), "grey")  # cross(u, v) = -z
    return Scene("quad", "test", cam, mats, quads=[quad], environment=env)


# ------------------------------------------------------------------------------------------
# contract
# ------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def cornell_render():
    return render(make_scene("cornell", 0, 0), spp=4, seed=3, width=24, height=20)


def test_every_layer_present_shaped_float32_finite(cornell_render):
    r = cornell_render
    assert set(r) == set(ALL_LAYERS)
    for name in ALL_LAYERS:
        want = (20, 24, 3) if name in RGB_LAYERS else (20, 24)
        assert r[name].shape == want, name
        assert r[name].dtype == np.float32, name
        assert np.all(np.isfinite(r[name])), name
    for name in VAR_OF:
        assert np.all(r[name] >= 0), name
    assert np.all(np.abs(r["normal"]) <= 1.0 + 1e-6)
    assert np.array_equal(r["default"], r["diffuse"] + r["specular"])
    # a closed room at 4 spp: both buffers carry light, and noise
    assert r["diffuse"].mean() > 0.01 and r["specular"].mean() > 0.01
    assert r["colorVariance"].mean() > 0


def test_same_seed_identical_different_seed_differs(cornell_render):
    scene = make_scene("cornell", 0, 0)
    again = render(scene, spp=4, seed=3, width=24, height=20)
    for name in ALL_LAYERS:
        assert np.array_equal(again[name], cornell_render[name]), name
    other = render(scene, spp=4, seed=4, width=24, height=20)
    assert not np.array_equal(other["default"], cornell_render["default"])
    # independent noise: the two renders differ at nearly every pixel that is not constant
    noisy = cornell_render["colorVariance"] > 0
    differs = np.any(other["default"] != cornell_render["default"], axis=-1)
    assert differs[noisy].mean() > 0.95


def test_neighbouring_seeds_give_uncorrelated_noise():
    # residuals against a high-spp reference of renders with seeds 3 and 4 are uncorrelated
    scene = grey(make_scene("cornell", 1, 0))
    a, b = (render(scene, spp=4, seed=s, width=24, height=24)["default"][..., 0] for s in (3, 4))
    ref = render(scene, spp=256, seed=77, width=24, height=24)["default"][..., 0]
    ra, rb = (a - ref).ravel(), (b - ref).ravel()
    # sd of a correlation over 576 pixels is ~0.04; the reference's own noise adds a little shared part
    assert abs(np.corrcoef(ra, rb)[0, 1]) < 0.15


def test_output_does_not_depend_on_thread_count(cornell_render):
    import numba

    scene = make_scene("cornell", 0, 0)
    before = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        single = render(scene, spp=4, seed=3, width=24, height=20)
    finally:
        numba.set_num_threads(before)
    for name in ALL_LAYERS:
        assert np.array_equal(single[name], cornell_render[name]), name


@pytest.mark.parametrize(
    "kwargs, needle",
    [
        ({"spp": 1}, "spp must be an integer in [2, 65536], got 1"),
        ({"spp": 2.5}, "got 2.5"),
        ({"width": 0}, "width must be an integer in [1, 16384], got 0"),
        ({"height": -3}, "got -3"),
        ({"seed": -1}, "got -1"),
    ],
)
def test_render_rejects_bad_arguments(kwargs, needle):
    args = {"scene": facing_scene(), "spp": 2, "seed": 0, "width": 4, "height": 4}
    args.update(kwargs)
    with pytest.raises(ValueError, match=re.escape(needle)):
        render(**args)


def test_render_rejects_non_scene():
    with pytest.raises(ValueError, match="dict"):
        render({"name": "x"}, 2, 0)


# ------------------------------------------------------------------------------------------
# first-hit buffers and analytic cases
# ------------------------------------------------------------------------------------------

def _centre_pixel_rays(cam: Camera, size: int, n: int = 64):
    """Unit directions through an n x n grid over the centre pixel of a size x size image
    (same pinhole model as the tracer, computed here independently)."""
    frame = cam.frame()
    fwd, right, up = frame[3:6], frame[6:9], frame[9:12]
    th = math.tan(math.radians(cam.fov) / 2)
    c = size // 2
    j = (np.arange(n) + 0.5) / n
    jx, jy = np.meshgrid(j, j)
    sx = (2 * (c + jx) / size - 1) * th
    sy = (1 - 2 * (c + jy) / size) * th
    d = fwd + sx[..., None] * right + sy[..., None] * up
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_misses_are_zero_and_environment_is_specular():
    scene = facing_scene(env=(0.2, 0.3, 0.4))
    r = render(scene, spp=4, seed=0, width=25, height=25)
    miss = r["depth"] == 0
    # the corners see past the quad (it covers about 35 degrees of the 40 degree view only near the centre)
    assert miss[0, 0] and miss[-1, -1] and miss.sum() > 50 and (~miss).sum() > 50
    assert np.all(r["normal"][miss] == 0) and np.all(r["albedo"][miss] == 0)
    env = np.broadcast_to([0.2, 0.3, 0.4], r["specular"][miss].shape)
    np.testing.assert_allclose(r["specular"][miss], env, rtol=1e-6)
    assert np.all(r["diffuse"][miss] == 0)
    for name in VAR_OF:
        assert np.all(r[name][miss] == 0), name


def test_depth_normal_albedo_of_a_facing_quad():
    scene = facing_scene()
    size = 25
    r = render(scene, spp=16, seed=1, width=size, height=size)
    c = size // 2
    d = _centre_pixel_rays(scene.camera, size)
    expected = np.mean(3.0 / -d[..., 2])  # plane z = -3 seen from the origin
    assert abs(r["depth"][c, c] - expected) < 5 * math.sqrt(r["depthVariance"][c, c]) + 1e-5
    assert abs(r["depth"][c, c] - 3.0) < 1e-3
    # cross(u, v) points away from the camera: the double-sided shading normal faces the viewer
    np.testing.assert_allclose(r["normal"][c, c], [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(r["albedo"][c, c], [0.5, 0.4, 0.3], rtol=1e-6)
    assert np.all(r["specular"][c, c] == 0)


def test_depth_and_its_variance_equal_per_sample_recomputation():
    # Replay the tracer's pixel jitter (its counter-based RNG is callable from Python) and compute each
    # sample's depth to the plane z = -3 here: the depth layer must be their mean and depthVariance
    # their unbiased sample variance divided by spp.
    from prep.render import tracer

    scene = facing_scene(half=5.0)  # fills the view
    w, h, spp, seed = 7, 5, 5, 11
    r = render(scene, spp=spp, seed=seed, width=w, height=h)
    frame = scene.camera.frame()
    fwd, right, up = frame[3:6], frame[6:9], frame[9:12]
    th = math.tan(math.radians(scene.camera.fov) / 2)
    for y in range(h):
        for x in range(w):
            depths = []
            for s in range(spp):
                key = np.uint64(tracer.sample_key(np.uint64(seed), y * w + x, s))  # keep it uint64
                sx = (2 * (x + tracer.rand(key, 0)) / w - 1) * th * (w / h)
                sy = (1 - 2 * (y + tracer.rand(key, 1)) / h) * th
                d = fwd + sx * right + sy * up
                d /= np.linalg.norm(d)
                depths.append(3.0 / -d[2])
            depths = np.array(depths)
            np.testing.assert_allclose(r["depth"][y, x], depths.mean(), rtol=1e-6)
            np.testing.assert_allclose(r["depthVariance"][y, x], depths.var(ddof=1) / spp,
                                       rtol=1e-4, atol=1e-12)
    assert r["depthVariance"].max() > 0


def test_depth_of_a_sphere_matches_ray_sphere_distance():
    scene = facing_scene(with_sphere=True)
    size = 15
    r = render(scene, spp=64, seed=2, width=size, height=size)
    c = size // 2
    d = _centre_pixel_rays(scene.camera, size, n=128)
    centre = np.array([0.0, 0.0, -4.0])
    b = d @ centre
    t = b - np.sqrt(b * b - (centre @ centre - 0.49))
    expected = t.mean()
    assert abs(r["depth"][c, c] - expected) < 5 * math.sqrt(r["depthVariance"][c, c]) + 1e-6
    assert abs(r["depth"][c, c] - 3.3) < 1e-2  # sanity: the pixel is on the sphere's front
    n = (d * t[..., None] - centre) / 0.7
    # each channel's variance is at most 3x the channel-averaged layer
    bound = 5 * math.sqrt(3 * r["normalVariance"][c, c]) + 1e-6
    np.testing.assert_allclose(r["normal"][c, c], n.mean(axis=(0, 1)), atol=bound)


def test_lambert_plane_under_environment_reflects_albedo_times_environment():
    # Every path: camera -> plane (cosine-sampled bounce, weight = albedo) -> environment.
    cam = Camera(position=(0, 1, 2), look_at=(0, 0, 0), fov=30)
    scene = Scene("furnace", "test", cam, {"g": lambert((0.3, 0.5, 0.7))},
                  quads=[Quad((-500, 0, -500), (0, 0, 1000), (1000, 0, 0), "g")], environment=(0.5, 1.0, 2.0))
    r = render(scene, spp=4, seed=0, width=8, height=8)
    np.testing.assert_allclose(r["diffuse"], np.broadcast_to([0.15, 0.5, 1.4], (8, 8, 3)), rtol=1e-6)
    assert np.all(r["specular"] == 0)
    assert np.all(r["diffuseVariance"] < 1e-12)


@pytest.mark.parametrize(
    "lights",
    [
        [(-0.2, 0.2, -0.2, 0.2, 5.0)],  # small: carried by light sampling
        [(-1.0, 1.0, -1.0, 1.0, 5.0)],  # large and close: BSDF hits matter too (MIS)
        [(-0.2, 0.2, -0.2, 0.2, 20.0), (0.5, 1.5, -0.5, 0.5, 2.0)],  # light picking by power
    ],
)
def test_lambert_plane_under_area_lights_matches_form_factor(lights):
    # L = albedo * sum(Le * F) for a diffuse point lit by uniform rectangles (nothing else in the scene)
    h, albedo = 1.0, 0.6
    cam = Camera(position=(0, 0.5, 1.0), look_at=(0, 0, 0), fov=1.0)
    mats = {"g": lambert((albedo,) * 3)}
    quads = [Quad((-50, 0, -50), (0, 0, 100), (100, 0, 0), "g")]
    expected = 0.0
    for i, (x0, x1, z0, z1, le) in enumerate(lights):
        mats[f"light{i}"] = emitter((le,) * 3)
        quads.append(Quad((x0, h, z0), (x1 - x0, 0, 0), (0, 0, z1 - z0), f"light{i}"))  # faces down
        expected += albedo * le * rect_form_factor(x0, x1, z0, z1, h)
    r = render(Scene("ff", "test", cam, mats, quads=quads), spp=4096, seed=5, width=3, height=3)
    got = r["diffuse"][1, 1]
    sigma = math.sqrt(r["diffuseVariance"][1, 1])
    assert np.all(np.abs(got - expected) < 4 * sigma + 1e-4 * expected), (got, expected, sigma)
    assert sigma < 0.02 * expected  # the check above is not vacuous
    assert np.all(r["specular"][1, 1] == 0)


def _ggx_reference(n, wo, wi, alpha, f0):
    """GGX microfacet BRDF (Smith separable G, Schlick Fresnel), written out independently."""
    h = wo + wi
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    nh, oh = h @ n, h @ wo
    no, ni = wo @ n, wi @ n
    a2 = alpha * alpha
    d = a2 / (np.pi * (nh * nh * (a2 - 1) + 1) ** 2)

    def g1(c):
        return 2 * c / (c + np.sqrt(a2 + (1 - a2) * c * c))

    f = f0 + (1 - f0) * (1 - oh) ** 5
    return f * d * g1(no) * g1(ni) / (4 * no * ni)


@pytest.mark.parametrize(
    "material",
    [
        glossy((0.9, 0.9, 0.9), 0.3),
        glossy((0.9, 0.9, 0.9), 0.08),  # sharp highlight: BSDF sampling carries it, MIS must weigh
        Material("plastic", albedo=(0.5, 0.5, 0.5), specular=(0.05, 0.05, 0.05), roughness=0.15),
    ],
    ids=["glossy-0.3", "glossy-0.08", "plastic"],
)
def test_glossy_and_plastic_plane_under_area_light_match_quadrature(material):
    # Direct light only (black environment, the light reflects nothing): the pixel's radiance is the
    # integral over the light of f * cos_i * Le * cos_l / r^2, computed here on a fine grid; for
    # plastic the lambert part must land in diffuse and the coat in specular.
    le = 4.0
    cam = Camera(position=(0, 0.5, 1.0), look_at=(0, 0, 0), fov=1.0)
    x0, z0, side, h = -0.5, -2.5, 1.0, 1.0  # the mirror direction of the view meets the light's centre
    scene = Scene("gq", "test", cam, {"m": material, "light": emitter((le,) * 3)},
                  quads=[Quad((-50, 0, -50), (0, 0, 100), (100, 0, 0), "m"),
                         Quad((x0, h, z0), (side, 0, 0), (0, 0, side), "light")])
    r = render(scene, spp=4096, seed=9, width=3, height=3)

    m = 800
    g = (np.arange(m) + 0.5) / m * side
    px, pz = np.meshgrid(x0 + g, z0 + g)
    pts = np.stack([px, np.full_like(px, h), pz], axis=-1).reshape(-1, 3)
    dist = np.linalg.norm(pts, axis=-1)
    wi = pts / dist[:, None]
    n = np.array([0.0, 1.0, 0.0])
    wo = np.array([0.0, 0.5, 1.0]) / math.sqrt(1.25)
    geom = wi[:, 1] * wi[:, 1] / dist ** 2 * (side / m) ** 2  # cos_i * cos_l / r^2 * dA
    spec = np.sum(_ggx_reference(n, wo, wi, material.roughness, material.specular[0]) * geom) * le
    diff = np.sum(material.albedo[0] / np.pi * geom) * le
    for layer, expected in (("specular", spec), ("diffuse", diff)):
        sigma = math.sqrt(r[f"{layer}Variance"][1, 1])
        got = r[layer][1, 1]
        assert np.all(np.abs(got - expected) <= 4 * sigma + 1e-3 * expected), (layer, got, expected, sigma)
    assert spec > 0.1 and math.sqrt(r["specularVariance"][1, 1]) < 0.03 * spec


@pytest.mark.slow
@pytest.mark.parametrize(
    "material",
    [
        glossy((0.9, 0.8, 0.7), 0.3),
        Material("plastic", albedo=(0.5, 0.4, 0.3), specular=(0.05, 0.05, 0.05), roughness=0.15),
    ],
    ids=["glossy", "plastic"],
)
def test_glossy_and_plastic_plane_under_environment_match_hemisphere_quadrature(material):
    # No lights: every contribution comes from BSDF sampling (lobe choice, GGX normal sampling and
    # their pdf) and must integrate to E * directional albedo: kd for the lambert part and the
    # hemisphere integral of the GGX lobe times cos for the coat, per channel.
    env = np.array([1.0, 2.0, 0.5])
    cam = Camera(position=(0, 0.5, 1.0), look_at=(0, 0, 0), fov=1.0)
    scene = Scene("env", "test", cam, {"m": material},
                  quads=[Quad((-500, 0, -500), (0, 0, 1000), (1000, 0, 0), "m")], environment=tuple(env))
    r = render(scene, spp=4096, seed=13, width=3, height=3)

    nu, nphi = 1200, 2400
    u = (np.arange(nu) + 0.5) / nu  # cos(theta)
    phi = (np.arange(nphi) + 0.5) / nphi * 2 * np.pi
    uu, pp = np.meshgrid(u, phi, indexing="ij")
    st = np.sqrt(1 - uu * uu)
    wi = np.stack([st * np.cos(pp), uu, st * np.sin(pp)], axis=-1).reshape(-1, 3)
    wo = np.array([0.0, 0.5, 1.0]) / math.sqrt(1.25)
    n = np.array([0.0, 1.0, 0.0])
    dw = (1 / nu) * (2 * np.pi / nphi)  # d(cos theta) d(phi)
    spec = np.array([np.sum(_ggx_reference(n, wo, wi, material.roughness, f0) * wi[:, 1]) * dw
                     for f0 in material.specular]) * env
    diff = np.array(material.albedo) * env
    for layer, expected in (("specular", spec), ("diffuse", diff)):
        # per-channel sd is at most sqrt(3) times the channel-averaged one
        sigma = math.sqrt(3 * r[f"{layer}Variance"][1, 1])
        got = r[layer][1, 1]
        assert np.all(np.abs(got - expected) <= 4 * sigma + 2e-3 * expected), (layer, got, expected, sigma)
    assert math.sqrt(r["specularVariance"][1, 1]) < 0.05 * spec.mean()  # not vacuous


def test_russian_roulette_is_unbiased():
    # Roulette from vertex 1 on against none at all (same max depth) in a closed room where long paths
    # carry much of the light: equal expectations, compared through the image sum.
    scene = grey(make_scene("cornell", 1, 0))
    a = render(scene, spp=64, seed=21, width=24, height=24, rr_depth=1)
    b = render(scene, spp=64, seed=22, width=24, height=24, rr_depth=99)
    for layer, var in (("default", "colorVariance"), ("diffuse", "diffuseVariance")):
        diff = (a[layer].astype(np.float64) - b[layer]).sum()
        z = diff / math.sqrt(3 * 3 * (a[var].astype(np.float64) + b[var]).sum())  # 3 identical channels
        assert abs(z) < 4.5, (layer, z)
    assert not np.array_equal(a["default"], b["default"])


def test_lambert_only_scene_has_no_specular_off_lights():
    scene = make_scene("cornell", 2, 0)
    mats = {k: (lambert(m.albedo if max(m.albedo) > 0 else (0.5, 0.5, 0.5)) if m.kind != "emitter" else m)
            for k, m in scene.materials.items()}
    scene = dataclasses.replace(scene, materials=mats)
    r = render(scene, spp=4, seed=1, width=32, height=32)
    # pixels whose every sample hit the same non-emitting surface (albedo constant and non-zero)
    surface = (r["depth"] > 0) & (r["albedo"].max(axis=-1) > 0) & (r["albedoVariance"] == 0)
    assert surface.mean() > 0.8
    assert np.all(r["specular"][surface] == 0)
    assert np.mean(r["diffuse"][surface].sum(axis=-1) > 0) > 0.95
    # and the light seen directly is specular
    light = (r["depth"] > 0) & (r["albedo"].max(axis=-1) == 0)
    assert light.any() and np.all(r["specular"][light].min(axis=-1) > 1.0)


def test_glossy_only_scene_has_no_diffuse():
    scene = make_scene("spheres", 1, 0)
    mats = {k: (glossy((0.8, 0.7, 0.6), 0.2) if m.kind != "emitter" else m)
            for k, m in scene.materials.items()}
    r = render(dataclasses.replace(scene, materials=mats), spp=4, seed=1, width=24, height=24)
    assert np.all(r["diffuse"] == 0) and np.all(r["albedo"] == 0)
    assert r["specular"].mean() > 0.01


# ------------------------------------------------------------------------------------------
# statistics
# ------------------------------------------------------------------------------------------

def _mean_vs_reference(scene, layer, k, spp, ref_spp, size, seed0, ref_scale=1.0):
    """Compare the mean of k independent spp renders with a ref_spp reference (times ref_scale).

    Returns (z, z_sum, const_diff): per pixel-channel z with Var(mean of k) predicted from the
    reference's variance layer (ref_var * ref_spp / (k * spp)) plus the reference's own ref_var; the
    image-level z of the summed difference (variances from both sides' layers); and |difference|
    at pixels whose layers say both are exactly constant.

    The per-pixel z uses the reference's variance layer (512 samples) rather than the low-spp
    renders' own: those are correlated with their means (a firefly raises both), which skews z
    negative for heavy-tailed path samples even when nothing is biased.
    """
    runs = [render(scene, spp=spp, seed=seed0 + i, width=size, height=size) for i in range(k)]
    ref = render(scene, spp=ref_spp, seed=seed0 + 10_000, width=size, height=size)
    var_name = VARIANCE_OF[layer]
    mean = np.mean([r_[layer] for r_ in runs], axis=0, dtype=np.float64)
    diff = mean - ref_scale * ref[layer].astype(np.float64)
    ref_var = ref[var_name].astype(np.float64) * ref_scale ** 2
    run_var = np.mean([r_[var_name] for r_ in runs], axis=0, dtype=np.float64) / k
    var = ref_var * ref_spp / (k * spp) + ref_var
    if diff.ndim == 3:  # grey scenes: every channel has the (channel-averaged) variance of the layer
        var = np.repeat(var[..., None], 3, axis=-1)
        run_var = np.repeat(run_var[..., None], 3, axis=-1)
        ref_var = np.repeat(ref_var[..., None], 3, axis=-1)
    ok = var > 0
    z = diff[ok] / np.sqrt(var[ok])
    z_sum = diff.sum() / math.sqrt((run_var + ref_var).sum())
    const = (run_var == 0) & (ref_var == 0)
    return z, z_sum, np.abs(diff[const])


# Criteria, calibrated on 4 seed sets for each family (numbers in the report) and justified:
# * |z_sum| < 4.5: the summed difference over ~500 pixels is close to Gaussian (CLT); observed
#   |z_sum| <= 3.2 over 36 layer/seed/family cases (a bit wider than N(0, 1): heavy tails). It
#   catches a bias of ~0.2 noise sigma per pixel: 5-10 % of the signal depending on the scene
#   (see test_statistical_check_detects_a_small_bias).
# * mean of min(z^2, 16) in [0.6, 1.6]: ~1 when the variance layers predict the spread (observed
#   0.9-1.4; winsorised because a rare event missing from the reference gives one huge z); a
#   variance layer off by 2x (spp or ddof mistakes) moves it to ~0.5 or ~2.
# * fraction |z| > 4 below 3 %: 6e-5 for a Gaussian; path samples are heavy-tailed (observed up to
#   1.8 % on glossy floors); a biased renderer or wrong variance puts far more mass out there.
# * the families with glass, tiny lights, meshes and lenses are heavy-tailed enough at 4 spp that the
#   mean of 8 renders sits below the reference in most seed sets (caustics-000: z_sum -1.4 to -3.3 over
#   four sets at 4 spp, -0.13 at 64 spp, the reference's sample count): they are compared at 64 spp.
#   (indirect uses no effect the others lack, and its glossy paths to the hidden light are rare enough
#   that the reference's variance layer underestimates their spread: it is left out.)
# * fireflies' small bright lights seen in glossy surfaces are rare enough at 512 samples that the
#   reference's variance layer underestimates their spread too (mean min(z^2, 16) 1.25-1.67 over four seed
#   sets at 64 spp); its reference takes 2048 (1.06-1.37; |z_sum| <= 2.6). The sign of its z_sum shows no
#   bias: -0.45 on average over twelve seed sets against 512.
# * textures is left out like indirect: its mirror throws caustics of the area light onto diffuse
#   surfaces (light -> mirror -> floor is found only by BSDF sampling), so over four seed sets the diffuse
#   z_sum ran -3.8, -4.6, +0.7, -3.6 against a 512 spp reference and -4.8, -5.9, +1.0, -3.0 against 2048,
#   alike before and after GGX sampling changed: heavy tails, not a bias these criteria can separate.
@pytest.mark.slow
@pytest.mark.parametrize("family,index,spp,ref_spp", [
    ("cornell", 1, 4, 512), ("spheres", 2, 4, 512), ("boxes", 0, 4, 512), ("fireflies", 0, 64, 2048),
    ("caustics", 0, 64, 512), ("outdoor", 1, 64, 512)])
def test_mean_of_low_spp_renders_matches_reference(family, index, spp, ref_spp):
    scene = grey(make_scene(family, index, 0))
    for layer in ("default", "diffuse", "specular"):
        z, z_sum, const_diff = _mean_vs_reference(scene, layer, k=8, spp=spp, ref_spp=ref_spp, size=24,
                                                  seed0=100)
        assert z.size > 150, layer  # pixel-channels with variance (the specular of indirect, textures: ~200)
        assert np.all(const_diff < 1e-5), layer
        assert abs(z_sum) < 4.5, (layer, z_sum)
        assert 0.6 < np.mean(np.minimum(z ** 2, 16)) < 1.6, (layer, np.mean(np.minimum(z ** 2, 16)))
        assert np.mean(np.abs(z) > 4) < 0.03, (layer, np.mean(np.abs(z) > 4))


def test_statistical_check_detects_a_small_bias():
    # the same criteria on the same renders reject a reference off by 10 %
    scene = grey(make_scene("cornell", 1, 0))
    _, z_sum, _ = _mean_vs_reference(scene, "default", k=8, spp=4, ref_spp=512, size=24, seed0=100,
                                     ref_scale=1.1)
    assert abs(z_sum) >= 4.5, z_sum


def test_variance_layers_match_variance_across_seeds():
    # 24 independent 4-spp renders: the empirical variance of the pixel mean across seeds and the
    # variance layers estimate the same thing; compare their sums over the image, per layer.
    scene = grey(make_scene("spheres", 0, 0))
    k = 24
    runs = [render(scene, spp=4, seed=500 + i, width=24, height=24) for i in range(k)]
    for var_name, layer in VAR_OF.items():
        stack = np.array([r[layer] for r in runs], dtype=np.float64)
        emp = stack.var(axis=0, ddof=1)
        if emp.ndim == 3:
            emp = emp.mean(axis=-1)
        pred = np.mean([r[var_name] for r in runs], axis=0)
        assert pred.sum() > 0, var_name
        ratio = emp.sum() / pred.sum()
        assert 0.8 < ratio < 1.25, (var_name, ratio)
        # per pixel too: where every render's layer says 0 the samples never varied
        assert np.all(emp[pred == 0] < 1e-12), var_name


# ------------------------------------------------------------------------------------------
# scenes and sets
# ------------------------------------------------------------------------------------------

def test_make_scene_is_deterministic_and_named():
    for fam in FAMILIES:
        a, b = make_scene(fam, 3, 7), make_scene(fam, 3, 7)
        assert a.name == f"{fam}-003" and a.family == fam
        assert json.dumps(a.to_dict()) == json.dumps(b.to_dict())
        assert a.to_dict() != make_scene(fam, 4, 7).to_dict()
        assert a.to_dict() != make_scene(fam, 3, 8).to_dict()
        back = Scene.from_dict(json.loads(json.dumps(a.to_dict())))
        for x, y in zip(pack(back), pack(a)):
            np.testing.assert_array_equal(x, y)


def test_unknown_family_is_named():
    with pytest.raises(ValueError, match=r"'kitchen'.*cornell.*spheres.*boxes"):
        make_scene("kitchen", 0, 0)


def test_scene_validation_names_the_problem():
    with pytest.raises(ValueError, match="'nope'"):
        pack(Scene("x", "test", Camera((0, 0, 0), (0, 0, -1)), {}, spheres=[Sphere((0, 0, -2), 1, "nope")]))
    with pytest.raises(ValueError, match="'velvet'"):
        Material("velvet")
    with pytest.raises(ValueError, match="-1"):
        Sphere((0, 0, 0), -1, "m")


# what each family must show in its first four permutations, besides lambert surfaces and a light
FAMILY_EFFECTS = {
    "cornell": {"texture"}, "spheres": {"environment", "texture"}, "boxes": {"environment"},
    "indirect": set(), "fireflies": {"glossy"}, "caustics": {"glass", "mirror"},
    "outdoor": {"environment_map", "lens", "texture", "mesh"}, "textures": {"texture", "mirror"},
    "media": {"medium"},
}
# families lit by an environment map alone (the sun in the sky), not by emitters
MAP_LIT = {"outdoor"}


def _smallest_light_area(scene):
    return min(q.area for q in scene.quads if scene.materials[q.material].kind == "emitter")


def test_families_vary_and_show_what_they_are_for():
    assert set(FAMILY_EFFECTS) == set(FAMILIES) and len(FAMILIES) >= 8
    for fam, wanted in FAMILY_EFFECTS.items():
        scenes = [make_scene(fam, i, 0) for i in range(4)]
        effects = set().union(*(s.effects() for s in scenes))
        assert {"lambert"} | ({"environment_map"} if fam in MAP_LIT else {"emitter"}) | wanted <= effects, (
            fam, effects)
        assert len({json.dumps(s.to_dict()) for s in scenes}) == 4
    # small bright lights make fireflies; the indirect room's light faces the ceiling, away from view
    assert max(_smallest_light_area(make_scene("fireflies", i, 0)) for i in range(4)) < 0.01
    for i in range(4):
        scene = make_scene("indirect", i, 0)
        light = next(q for q in scene.quads if scene.materials[q.material].kind == "emitter")
        assert light.normal[1] > 0.99 and scene.camera.position[1] < light.corner[1]
        assert make_scene("spheres", i, 0).environment_zenith is not None  # a gradient
        sky = make_scene("outdoor", i, 0).environment_map.sky  # an HDR sky: a sun far brighter than the rest
        assert min(sky.sun) > 100 * max(sky.zenith + sky.horizon)
    # fine texture detail: several checker cells per unit
    assert any(m.texture == "world" and m.checker_scale >= 6 for m in make_scene("textures", 0, 0).materials.values())


def test_slow_families_get_references_with_more_samples(tmp_path):
    cfg = RenderConfig(set_name="refs", families=("cornell", "caustics"), per_family=1, width=6, height=4,
                       input_spp=(2,), reference_spp=4, seed=1, out_root=str(tmp_path))
    names = sorted(p.name for p in render_set(cfg, progress=False))
    assert REFERENCE_SPP_FACTOR["caustics"] > 1 and "cornell" not in REFERENCE_SPP_FACTOR
    assert names == ["caustics-000-00002spp.exr", f"caustics-000-{4 * REFERENCE_SPP_FACTOR['caustics']:05d}spp.exr",
                     "cornell-000-00002spp.exr", "cornell-000-00004spp.exr"]
    assert reference_spp(cfg, "caustics") == 4 * REFERENCE_SPP_FACTOR["caustics"]


def test_a_render_set_names_its_folder_record_renders_and_the_sets_made_from_it(tmp_path):
    from prep.errors import OptionError
    from prep.render.renderset import RenderSet

    tiny = RenderSet("tiny", tmp_path)
    assert tiny.dir == tmp_path / "tiny" and tiny.record_path == tmp_path / "tiny" / "config.json"
    assert tiny.render_path("boxes-000", 16) == tmp_path / "tiny" / "boxes-000-00016spp.exr"
    assert tiny.derived("r1a2b3c4") == RenderSet("tiny-r1a2b3c4", tmp_path)
    assert RenderConfig(set_name="tiny", out_root=str(tmp_path)).render_set == tiny
    assert RenderSet("tiny").dir == Path("data") / "renders" / "tiny"  # kpcn render's --out default
    (tmp_path / "tiny").mkdir()
    for name in ("b-000-00004spp.exr", "a-000-00004spp.exr", "notes.txt"):
        (tmp_path / "tiny" / name).write_bytes(b"")
    assert tiny.renders() == [tmp_path / "tiny" / "a-000-00004spp.exr", tmp_path / "tiny" / "b-000-00004spp.exr"]
    for bad in ("", "a/b", "..", "."):
        with pytest.raises(OptionError) as caught:
            RenderSet(bad, tmp_path)
        assert caught.value.option == "set_name"


def test_render_set_writes_resumes_and_records(tmp_path):
    cfg = RenderConfig(set_name="tiny", families=("cornell", "boxes"), per_family=1, width=12, height=10,
                       input_spp=(3, 2), reference_spp=4, seed=3, out_root=str(tmp_path))
    paths = render_set(cfg, progress=False)
    names = sorted(p.name for p in paths)
    assert names == ["boxes-000-00002spp.exr", "boxes-000-00003spp.exr", "boxes-000-00004spp.exr",
                     "cornell-000-00002spp.exr", "cornell-000-00003spp.exr", "cornell-000-00004spp.exr"]
    for p in paths:
        layers = read_aovs(p)
        assert layers["default"].shape == (10, 12, 3)
    meta = json.loads((tmp_path / "tiny" / "config.json").read_text())
    assert meta["config"]["seed"] == 3 and len(meta["scenes"]) == 2
    rec = meta["scenes"][0]
    assert len(set(rec["seeds"].values())) == 3  # each sample count has a seed of its own
    assert rec["seeds"] == {str(spp): render_seed(3, rec["family"], rec["index"], spp) for spp in (2, 3, 4)}
    assert rec["scene"] == make_scene(rec["family"], rec["index"], 3).to_dict()
    sheet = (tmp_path / "tiny" / "contact-sheet.png").read_bytes()
    assert sheet.startswith(b"\x89PNG")
    times = json.loads((tmp_path / "tiny" / "timings.json").read_text())
    assert set(times) == {p.name for p in paths} and all(v >= 0 for v in times.values())
    # the written input is the render of the recorded seed
    again = render(make_scene("cornell", 0, 3), 2, rec["seeds"]["2"], 12, 10)
    np.testing.assert_array_equal(read_aovs(tmp_path / "tiny" / "cornell-000-00002spp.exr")["diffuse"],
                                  again["diffuse"])

    mtimes = {p: p.stat().st_mtime_ns for p in paths}
    (tmp_path / "tiny" / "boxes-000-00004spp.exr").unlink()
    paths2 = render_set(cfg, progress=False)
    assert paths2 == paths
    assert all(p.stat().st_mtime_ns == mtimes[p] for p in paths if p.name != "boxes-000-00004spp.exr")
    assert (tmp_path / "tiny" / "boxes-000-00004spp.exr").exists()
    assert (tmp_path / "tiny" / "contact-sheet.png").read_bytes() == sheet  # same renders, same bytes
    with pytest.raises(ValueError, match="seed=3"):
        render_set(dataclasses.replace(cfg, seed=4), progress=False)
    with pytest.raises(ValueError, match="'kitchen'"):
        render_set(dataclasses.replace(cfg, families=("kitchen",)), progress=False)
    with pytest.raises(ValueError, match="reference_spp must exceed every input_spp"):
        render_set(dataclasses.replace(cfg, input_spp=(2, 8)), progress=False)


def test_render_on_a_full_disk_ends_in_one_line_and_a_rerun_with_space_finishes_the_set(tmp_path, small_disk):
    args = ("render", "--set", "s", "--out", "disk", "--families", "cornell", "--per-family", "1", "--width", "48",
            "--height", "40", "--input-spp", "2", "--reference-spp", "4")
    res = run_main(*args, cwd=tmp_path)
    assert_one_line_error(res, "disk/s/cornell-000-00002spp.exr: cannot write (No space left on device)")
    # the set's record holds its config and no scene yet, as when a render is interrupted: a rerun resumes
    assert sorted(p.name for p in (small_disk.path / "s").iterdir()) == [".lock", "config.json"]
    assert json.loads((small_disk.path / "s" / "config.json").read_text())["scenes"] == []
    small_disk.grow()
    res = run_main(*args, cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    (tmp_path / "twin").mkdir()
    assert run_main(*args, cwd=tmp_path / "twin").returncode == 0
    once = checksums(tmp_path / "twin" / "disk" / "s")
    resumed = checksums(small_disk.path / "s")
    assert once.pop("timings.json") and resumed.pop("timings.json") and resumed == once


def test_prep_render_does_not_import_frameworks():
    import subprocess
    import sys

    code = ("import sys, prep.render, prep.render.tracer, prep.render.scene, prep.render.kernels; "
            "bad = [m for m in ('keras', 'torch', 'kpcn_keras') if m in sys.modules]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.slow  # compiles specialised kernels: seconds each from a cold cache
def test_render_bench_writes_its_report_for_every_family_it_is_given(tmp_path):
    from kpcn_keras.studies.render_bench import RenderBenchConfig, bench_render

    # two families of one effect set: one specialised kernel to compile, the one test_kernels checks bit for bit
    families = ("spheres", "boxes")
    record = bench_render(RenderBenchConfig(families=families, width=8, height=6, spp=2, repeats=1,
                                            out_dir=str(tmp_path)), progress=False)
    saved = json.loads((tmp_path / "render.json").read_text())
    assert saved == json.loads(json.dumps(record))
    scenes = [row["scene"] for row in saved["families"]]
    assert scenes == [f"{f}-000" for f in families] + ["cornell-000 (lambert only)"]
    lean = saved["families"][-1]
    assert lean["effects"] == ["emitter", "lambert"] and not lean["same_kernel"]
    for row in saved["families"]:
        assert row["specialised_samples_per_s"] > 0 and row["all_effects_samples_per_s"] > 0
        assert math.isclose(row["saving"], 1 - row["specialised_s"] / row["all_effects_s"])
    md = (tmp_path / "render.md").read_text()
    assert all(s in md for s in scenes) and "Msamples/s" in md


@pytest.mark.parametrize("families, needle", [(("nope",), "unknown scene family 'nope'"),
                                             ((), "at least one scene family"), ("cornell", "the string 'cornell'")])
def test_render_bench_refuses_families_it_cannot_time_naming_the_option(families, needle):
    from kpcn_keras.studies.render_bench import RenderBenchConfig
    from prep.errors import OptionError

    with pytest.raises(OptionError, match=needle) as caught:
        RenderBenchConfig(families=families)
    assert caught.value.option == "families"


def test_the_render_report_says_the_production_figure_is_quoted_not_measured():
    from helpers.paths import REPO

    from kpcn_keras.studies.render_bench import format_report

    record = json.loads((REPO / "reports" / "render.json").read_text())
    md = format_report(record)
    line = next(row for row in md.splitlines() if row.startswith("Reference point"))
    assert "quoted for a production CPU path tracer" in line and "not measured here" in line
    assert md == (REPO / "reports" / "render.md").read_text()  # the committed report is its record's


# --- the frame size: both bounds, and the memory the machine has ---

def test_frame_bytes_are_what_the_renderer_allocates_per_pixel():
    import tracemalloc

    from prep.render.frame import frame_bytes

    scene = make_scene("cornell", 0, 0)
    render(scene, 2, 0, 4, 4)  # compiled (or loaded) before measuring
    peaks = {}
    for side in (32, 64):
        tracemalloc.start()
        render(scene, 2, 0, side, side)
        peaks[side] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    per_pixel = (peaks[64] - peaks[32]) / (64 * 64 - 32 * 32)  # what a pixel more costs, overheads cancelled
    assert per_pixel == pytest.approx(frame_bytes(1, 1), rel=0.02)
    assert frame_bytes(100, 30) == 3000 * frame_bytes(1, 1)


def test_a_frame_beyond_the_memory_available_is_refused_naming_what_it_needs():
    from prep.errors import OptionError
    from prep.render.frame import check_frame, frame_bytes

    need_mb = frame_bytes(1000, 2000) / 2**20
    assert check_frame(1000, 2000, available_mb=need_mb) == (1000, 2000)
    with pytest.raises(OptionError) as err:
        check_frame(1000, 2000, available_mb=need_mb - 1)
    assert err.value.option == "height"  # the larger side
    assert f"({frame_bytes(1, 1)} bytes a pixel) needs {frame_bytes(1000, 2000) / 2**30:.1f} GiB" in str(err.value)


def _available_gib() -> float:
    from prep.processes import proc_megabytes

    return proc_megabytes("/proc/meminfo", ("MemAvailable",)).get("MemAvailable", math.inf) / 1024


def test_a_huge_frame_is_refused_in_one_line_before_anything_is_written(tmp_path):
    from helpers.commands import assert_one_line_error, run_main

    res = run_main("render", "--width", "100000", "--height", "100000", "--out", "renders", cwd=tmp_path)
    assert_one_line_error(res, "--width must be an integer in [1, 16384], got 100000")
    assert not any(tmp_path.iterdir())


@pytest.mark.skipif(_available_gib() > 70, reason="a 16384x16384 frame (79 GiB) fits this machine's memory")
def test_a_frame_the_machine_cannot_hold_is_refused_before_anything_is_written(tmp_path, monkeypatch, capsys):
    from kpcn_keras.cli import main
    from prep.render.frame import FRAME_SIDE

    monkeypatch.chdir(tmp_path)
    example = Path(__file__).resolve().parents[1] / "scenes" / "example.toml"
    side = str(FRAME_SIDE.high)
    for argv in (["render", "--width", side, "--height", side, "--out", "renders"],
                 ["render", "--scene", str(example), "--width", side, "--height", side, "--out", "x.exr"]):
        assert main(["-q", *argv]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and f"--width {side} (with height {side}): rendering the frame (" in err
        assert "this machine has available" in err
        assert not any(tmp_path.iterdir())
