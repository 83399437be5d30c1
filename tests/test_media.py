"""Tests of the participating medium (prep/render/media.py and the ``medium`` kernels): transmittance and the
absorbing slab against exp(-sigma_t d), single scattering in a slab against a float64 quadrature, the HG phase
sampling against its moments, and scenes without a medium untouched by the medium's code."""

from __future__ import annotations

import math

import numpy as np
import pytest

from prep.render import Camera, Quad, Scene, Sphere, render
from prep.render.packing import (
    MEDIUM_COLS,
    MEDIUM_G,
    MEDIUM_HI,
    MEDIUM_LO,
    MEDIUM_SIGMA_A,
    MEDIUM_SIGMA_S,
    pack,
    pack_medium,
)
from prep.render.scene import Medium, emitter

SIGMA_A = (0.2, 0.5, 0.9)
SIGMA_S = 0.8
G = 0.4
SLAB = dict(box_min=(-50.0, -50.0, -1.0), box_max=(50.0, 50.0, 0.0))  # 1 thick, z in [-1, 0]


def _slab(sigma_a=SIGMA_A, sigma_s=SIGMA_S, g=G) -> Medium:
    return Medium(sigma_a=sigma_a, sigma_s=sigma_s, g=g, **SLAB)


def test_the_medium_columns_of_the_kernels_mirror_the_packing():
    from prep.render import media

    assert (media.MD_SIGMA_A, media.MD_SIGMA_S, media.MD_G, media.MD_LO, media.MD_HI) == (
        MEDIUM_SIGMA_A, MEDIUM_SIGMA_S, MEDIUM_G, MEDIUM_LO, MEDIUM_HI)
    row = pack_medium(Scene("s", "test", Camera((0, 0, 2), (0, 0, 0)), {}, medium=_slab()))
    assert row.shape == (MEDIUM_COLS,) and row[MEDIUM_SIGMA_S] == SIGMA_S and row[MEDIUM_HI + 2] == 0.0


@pytest.mark.parametrize("origin, direction, tmax, length", [
    ((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), math.inf, 1.0),  # straight through
    ((0.3, -0.2, 2.0), (0.6, 0.0, -0.8), math.inf, 1.25),  # slanted: 1 / cos
    ((0.0, 0.0, -0.25), (0.0, 0.0, 1.0), math.inf, 0.25),  # from inside, out of the top
    ((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), 2.6, 0.6),  # stopped by a surface inside the slab
    ((0.0, 0.0, 2.0), (0.0, 0.0, 1.0), math.inf, 0.0),  # away from it
    ((0.0, 0.0, 2.0), (1.0, 0.0, 0.0), math.inf, 0.0),  # parallel to it, above
])
def test_transmittance_through_a_slab_is_exp_of_minus_sigma_t_times_the_length(origin, direction, tmax, length):
    from prep.render.media import transmittance

    med = pack_medium(Scene("s", "test", Camera((0, 0, 2), (0, 0, 0)), {}, medium=_slab()))
    got = transmittance(origin, direction, tmax, med)
    want = np.exp(-(np.asarray(SIGMA_A) + SIGMA_S) * length)
    np.testing.assert_allclose(got, want, rtol=1e-12)


def test_a_scene_without_a_medium_packs_an_empty_box_that_no_ray_enters():
    from prep.render.media import free_flight, transmittance

    med = pack(Scene("s", "test", Camera((0, 0, 2), (0, 0, 0)), {})).medium
    for o, d in [((0.0, 0.0, 0.0), (0.0, 0.0, 1.0)), ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0)), ((1.0, 2.0, 3.0),
                                                                                         (0.0, -0.6, -0.8))]:
        assert transmittance(o, d, math.inf, med) == (1.0, 1.0, 1.0)
        assert free_flight(o, d, 5.0, med, 0.5) == (False, 5.0, (1.0, 1.0, 1.0))


def _looking_down(medium, objects, size=8):
    """A camera above the slab looking straight down through it, its field so narrow that every ray is the
    axis to 1e-7."""
    cam = Camera((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), fov=0.001, up=(0.0, 1.0, 0.0))
    return Scene("slab", "test", cam, {"light": emitter((4.0, 5.0, 6.0))}, medium=medium, **objects), size


def test_an_absorbing_slab_dims_an_emitter_behind_it_by_exp_of_minus_sigma_a_d_without_noise():
    # sigma_s = 0: free flight never scatters and absorption is a weight, so every sample is the same
    light = Quad((-5.0, -5.0, -2.0), (10.0, 0.0, 0.0), (0.0, 10.0, 0.0), "light")  # faces +z, 1 below the slab
    scene, size = _looking_down(_slab(sigma_s=0.0), {"quads": [light]})
    out = render(scene, spp=4, seed=3, width=size, height=size)
    want = np.asarray((4.0, 5.0, 6.0)) * np.exp(-np.asarray(SIGMA_A) * 1.0)
    np.testing.assert_allclose(out["default"], np.broadcast_to(want, out["default"].shape), rtol=1e-6)
    assert out["colorVariance"].max() < 1e-10
    without = render(_looking_down(None, {"quads": [light]})[0], spp=4, seed=3, width=size, height=size)
    np.testing.assert_allclose(without["default"], np.broadcast_to((4.0, 5.0, 6.0), out["default"].shape),
                               rtol=1e-6)


def _single_scattering_quadrature(centre, radius, le) -> np.ndarray:
    """Radiance along the axis (down -z from above the slab) scattered once in the slab from a sphere light, in
    float64: the integral over the depth s of sigma_s exp(-sigma_t s) times the integral over the cone the
    sphere subtends of phase x Le x exp(-sigma_t l), l the way up out of the slab (Gauss-Legendre in s and in
    the cone's cosine, the trapezoid rule in its azimuth)."""
    sigma_t = np.asarray(SIGMA_A) + SIGMA_S
    gs, ws = np.polynomial.legendre.leggauss(64)
    s, w_s = (gs + 1) / 2, ws / 2  # depth in [0, 1]
    gm, wm = np.polynomial.legendre.leggauss(48)
    phi = np.arange(128) * 2 * np.pi / 128
    total = np.zeros(3)
    d = np.array([0.0, 0.0, -1.0])
    for si, wsi in zip(s, w_s):
        x = np.array([0.0, 0.0, -si])
        axis = np.asarray(centre) - x
        dist = np.linalg.norm(axis)
        axis /= dist
        cos_max = math.sqrt(1 - (radius / dist) ** 2)
        mu = cos_max + (1 - cos_max) * (gm + 1) / 2
        w_mu = wm * (1 - cos_max) / 2
        t1 = np.cross(axis, [0.0, 1.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(axis, t1)
        sin = np.sqrt(1 - mu**2)
        om = (mu[:, None, None] * axis + sin[:, None, None] * (np.cos(phi)[None, :, None] * t1
                                                                 + np.sin(phi)[None, :, None] * t2))
        cos = om @ d
        phase = (1 - G**2) / (4 * np.pi * (1 + G**2 - 2 * G * cos) ** 1.5)
        way_up = si / om[..., 2]
        inner = (w_mu[:, None] * phase)[..., None] * np.exp(-way_up[..., None] * sigma_t)  # (mu, phi, rgb)
        total += wsi * SIGMA_S * np.exp(-sigma_t * si) * inner.sum(axis=(0, 1)) * (2 * np.pi / 128)
    return total * np.asarray(le)


def test_single_scattering_in_a_slab_matches_a_float64_quadrature():
    centre, radius = (1.5, 0.0, 1.0), 0.3
    scene, size = _looking_down(_slab(), {"spheres": [Sphere(centre, radius, "light")]})
    # max_depth 1: the camera ray's one scattering event, lit by light sampling and by phase sampling (MIS)
    out = render(scene, spp=2048, seed=11, width=size, height=size, max_depth=1, rr_depth=1)
    pixels = out["default"].reshape(-1, 3).astype(np.float64)
    mean = pixels.mean(axis=0)
    se = pixels.std(axis=0, ddof=1) / math.sqrt(len(pixels))
    want = _single_scattering_quadrature(centre, radius, (4.0, 5.0, 6.0))
    assert np.all(se < 0.02 * want), (se, want)  # the bound below is tight enough to mean something
    assert np.all(np.abs(mean - want) < 4 * se), (mean, want, se)
    # the light in-scattered at the camera ray's first event is specular, its auxiliary features those of the
    # background (docs/formats.md), its depth that of the event
    assert out["diffuse"].max() == 0.0 and out["albedo"].max() == 0.0 and out["normal"].max() == 0.0
    # depth: 2 + s at an event at depth s (drawn with density sigma_s exp(-sigma_s s)), 0 where the ray left
    gs, ws = np.polynomial.legendre.leggauss(32)
    s = (gs + 1) / 2
    depth = np.sum(ws / 2 * (2 + s) * SIGMA_S * np.exp(-SIGMA_S * s))
    d = out["depth"].astype(np.float64).ravel()
    assert abs(d.mean() - depth) < 4 * d.std(ddof=1) / math.sqrt(len(d)), (d.mean(), depth)


def test_hg_sampling_draws_the_phase_function():
    from prep.render.media import hg_eval, hg_sample

    rng = np.random.default_rng(0)
    d = (0.0, 0.6, 0.8)
    for g in (-0.5, 0.0, 0.7):
        cos = np.empty(20000)
        for i, (u1, u2) in enumerate(rng.random((len(cos), 2))):
            wi, pdf = hg_sample(g, d, u1, u2)
            cos[i] = np.dot(wi, d)
            assert pdf == pytest.approx(hg_eval(g, cos[i]), rel=1e-9, abs=1e-12)
        assert abs(cos.mean() - g) < 4 * cos.std() / math.sqrt(len(cos))  # HG's mean cosine is g
        mu = np.linspace(-1, 1, 200001)
        assert np.trapezoid([hg_eval(g, m) for m in mu[::100]], mu[::100]) * 2 * np.pi == pytest.approx(1, rel=1e-3)


@pytest.mark.slow  # compiles three small kernels afresh to read their machine code
def test_a_kernel_for_a_scene_without_a_medium_has_no_medium_code_and_one_without_a_grid_no_tracking():
    # the scene's own effects plus a medium, then plus its density grid: the smallest kernels that show the
    # medium code appear with each flag (the all-effects kernel would show the same, at several times the compile)
    import numba

    from prep.render import kernels

    light = Quad((-5.0, -5.0, -2.0), (10.0, 0.0, 0.0), (0.0, 10.0, 0.0), "light")
    scene = _looking_down(None, {"quads": [light]})[0]
    assert "medium" not in scene.effects()
    packed = pack(scene)
    homogeneous = scene.effects() | {"medium"}
    heterogeneous = homogeneous | {"heterogeneous"}
    calls = {}
    for effects in (scene.effects(), homogeneous, heterogeneous):
        trace = numba.njit(kernels.kernel_for(effects).trace_sample.py_func)
        trace((0.0, 0.0, 2.0), (0.0, 0.0, -1.0), np.uint64(1), packed, 5, 3, np.zeros(16))
        ir = "".join(trace.inspect_llvm().values())
        calls[frozenset(effects)] = {name for name in ("medium_vertex", "log1p", "tracked_free_flight",
                                                       "tracked_transmittance") if name in ir}
    assert calls[scene.effects()] == set()
    assert calls[homogeneous] == {"medium_vertex", "log1p"}  # and no tracking: that is the heterogeneous effect's
    assert calls[heterogeneous] == {"medium_vertex", "log1p", "tracked_free_flight", "tracked_transmittance"}


def test_a_medium_is_part_of_the_scene_description_and_its_effects():
    scene = _looking_down(_slab(), {"spheres": [Sphere((1.5, 0.0, 1.0), 0.3, "light")]})[0]
    assert scene.effects() == {"emitter", "medium"}
    assert Scene.from_dict(scene.to_dict()) == scene
    assert "medium" not in _looking_down(None, {})[0].to_dict()
    with pytest.raises(ValueError, match="Medium.g"):
        Medium(sigma_a=(0, 0, 0), sigma_s=1.0, g=0.99, **SLAB)
    with pytest.raises(ValueError, match="Medium.box_min"):
        Medium(sigma_a=(0, 0, 0), sigma_s=1.0, g=0.0, box_min=(0, 0, 0), box_max=(1, 0, 1))


def test_a_scene_file_describes_a_medium_and_names_a_bad_field(tmp_path):
    from prep.render.scenefile import SceneFileError, dump_scene, load_scene

    scene = _looking_down(_slab(), {"spheres": [Sphere((1.5, 0.0, 1.0), 0.3, "light")]})[0]
    path = tmp_path / "slab.toml"
    path.write_text(dump_scene(scene))
    loaded, _ = load_scene(path)
    assert loaded.medium == scene.medium and loaded.effects() == {"emitter", "medium"}
    path.write_text(dump_scene(scene).replace("g = 0.4", "g = 2.0"))
    with pytest.raises(SceneFileError, match=r"slab.toml: medium.g = 2.0: Medium.g must be in \[-0.95, 0.95\]"):
        load_scene(path)


def test_the_media_family_fills_rooms_with_fog_some_lit_through_an_opening_and_is_not_a_default():
    from prep.render import RenderConfig, make_scene

    scenes = [make_scene("media", i, 0) for i in range(8)]
    assert all("medium" in s.effects() for s in scenes)
    above = [s for s in scenes if any(sp.center[1] > s.medium.box_max[1] for sp in s.spheres)]  # shaft lights
    assert 0 < len(above) < len(scenes)
    assert len({s.medium for s in scenes}) == len(scenes)
    assert {s.medium.density for s in scenes} == {"homogeneous", "noise"}
    room = [s for s in scenes if s.medium.box_max[2] > 2.0]  # the room's fog reaches the camera's side
    assert 0 < len(room) < len(scenes)
    assert "media" not in RenderConfig().families and RenderConfig(families=("media",)).families == ("media",)


# ---------------------------------------------------------------------------------------------
# heterogeneous media: delta and ratio tracking against a majorant
# ---------------------------------------------------------------------------------------------

def _trilinear(grid, lo, hi, p):
    """float64 trilinear interpolation of the lattice ``grid`` spanning [lo, hi] at the points p (N, 3)."""
    n = grid.shape[0]
    x = np.clip((p - lo) / (hi - lo) * (n - 1), 0, n - 1)
    i = np.minimum(x.astype(int), n - 2)
    f = x - i
    out = np.zeros(len(p))
    for c in range(8):
        o = np.array([(c >> a) & 1 for a in range(3)])
        w = np.prod(np.where(o, f, 1 - f), axis=1)
        out += w * grid[i[:, 0] + o[0], i[:, 1] + o[1], i[:, 2] + o[2]]
    return out


@pytest.mark.parametrize("amount", [0.0, 1.0])
def test_ratio_tracking_estimates_the_transmittance_of_the_density_grid(amount):
    from prep.render.media import tracked_transmittance
    from prep.render.packing import medium_grid

    medium = Medium(sigma_a=SIGMA_A, sigma_s=SIGMA_S, g=G, box_min=(-1.0, -1.0, -1.0), box_max=(1.0, 1.0, 1.0),
                    density="noise", noise_cells=3, noise_amount=amount, noise_seed=5)
    scene = Scene("s", "test", Camera((0, 0, 2), (0, 0, 0)), {}, medium=medium)
    med, grid = pack_medium(scene), medium_grid(medium)
    o, d = np.array([-0.3, 0.2, 2.0]), np.array([0.3, -0.2, -1.0]) / np.linalg.norm([0.3, -0.2, -1.0])
    t = np.linspace((2.0 - 1.0) / -d[2], (2.0 + 1.0) / -d[2], 20001)  # the chord through z in [-1, 1]
    rho = _trilinear(grid, -1.0, 1.0, o + t[:, None] * d)
    depth = np.trapezoid(rho, t) * (np.asarray(SIGMA_A) + SIGMA_S)
    draws = np.array([tracked_transmittance(tuple(o), tuple(d), math.inf, med, grid, np.uint64(k), 0)
                      for k in range(4000)])
    se = draws.std(axis=0, ddof=1) / math.sqrt(len(draws))
    assert np.all(np.abs(draws.mean(axis=0) - np.exp(-depth)) < 4 * se + 1e-12), (draws.mean(axis=0), np.exp(-depth))
    if amount == 0.0:
        np.testing.assert_allclose(depth, (np.asarray(SIGMA_A) + SIGMA_S) * 2 / -d[2], rtol=1e-9)


def test_a_constant_density_grid_scatters_as_the_homogeneous_medium():
    centre, radius = (1.5, 0.0, 1.0), 0.3
    constant = Medium(sigma_a=SIGMA_A, sigma_s=SIGMA_S, g=G, density="noise", noise_amount=0.0, **SLAB)
    scene, size = _looking_down(constant, {"spheres": [Sphere(centre, radius, "light")]})
    assert scene.effects() == {"emitter", "medium", "heterogeneous"}
    want = _single_scattering_quadrature(centre, radius, (4.0, 5.0, 6.0))
    means = []
    for s in (scene, _looking_down(_slab(), {"spheres": [Sphere(centre, radius, "light")]})[0]):
        out = render(s, spp=2048, seed=11, width=size, height=size, max_depth=1, rr_depth=1)
        pixels = out["default"].reshape(-1, 3).astype(np.float64)
        mean, se = pixels.mean(axis=0), pixels.std(axis=0, ddof=1) / math.sqrt(len(pixels))
        assert np.all(se < 0.03 * want), (se, want)
        assert np.all(np.abs(mean - want) < 4 * se), (mean, want, se)
        means.append((mean, se))
    (m1, s1), (m2, s2) = means
    assert np.all(np.abs(m1 - m2) < 4 * np.hypot(s1, s2))
