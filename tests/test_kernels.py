"""Tests of prep.render.kernels: the kernels specialised to a scene's effects render the all-effects
kernel's bits, refuse a scene that calls for an effect they lack, and leave out the code of absent ones."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from prep.render import make_scene, render
from prep.render.packing import pack
from prep.render.scene import Camera, Material, Quad, Scene, Sphere, glossy, lambert


def test_a_scene_calls_for_the_effects_of_what_it_uses():
    cam = Camera((0, 0, 0), (0, 0, -1))
    mats = {"grey": lambert((0.5,) * 3), "metal": glossy((0.9,) * 3, 0.2), "unused": Material("plastic", (0.2,) * 3)}
    diffuse_only = Scene("d", "test", cam, mats, spheres=[Sphere((0, 0, -3), 1, "grey")])
    assert diffuse_only.effects() == {"lambert"}
    lit = dataclasses.replace(diffuse_only, spheres=[Sphere((0, 0, -3), 1, "metal")], environment=(0.1, 0.1, 0.1),
                              materials={**mats, "grey": lambert((0.5,) * 3, texture="uv", albedo2=(0.1,) * 3)},
                              quads=[Quad((0, 1, 0), (1, 0, 0), (0, 0, 1), "grey")])
    assert lit.effects() == {"glossy", "lambert", "texture", "environment"}


SUBSETS = [
    ("lambert only", lambda s: _only(s, "lambert")),
    ("glossy under the environment", lambda s: _only(s, "glossy", env=(0.5, 0.6, 0.7), lights=False)),
    ("plastic under a light", lambda s: _only(s, "plastic")),
]


def _only(scene: Scene, kind: str, env=(0.0, 0.0, 0.0), lights: bool = True) -> Scene:
    """``scene`` with every non-emitting material made ``kind`` (textures dropped), lights kept or not."""
    def one(m):
        if m.kind == "emitter":
            return m
        if kind == "lambert":
            return lambert(m.albedo if max(m.albedo) > 0 else (0.5, 0.5, 0.5))
        if kind == "glossy":
            return glossy((0.8, 0.7, 0.6), 0.3)
        return Material("plastic", albedo=(0.5, 0.4, 0.3), specular=(0.05,) * 3, roughness=0.2)

    quads = [q for q in scene.quads if lights or scene.materials[q.material].kind != "emitter"]
    return dataclasses.replace(scene, materials={k: one(m) for k, m in scene.materials.items()}, quads=quads,
                               environment=env)


@pytest.mark.slow  # compiles specialised kernels: seconds each from a cold cache
@pytest.mark.parametrize("label, make", SUBSETS + [("spheres-000 (no mirror, glass, lens, mesh or map)", None)])
def test_specialised_kernel_renders_the_bits_of_the_all_effects_kernel(label, make):
    from prep.render import EFFECTS, kernels

    scene = make(make_scene("cornell", 1, 0)) if make else make_scene("spheres", 0, 0)
    assert scene.effects() != frozenset(EFFECTS)
    assert kernels.kernel_for(scene.effects()) is not kernels.kernel_for(EFFECTS)
    fast = render(scene, spp=3, seed=9, width=16, height=12, effects=scene.effects())
    full = render(scene, spp=3, seed=9, width=16, height=12, effects=EFFECTS)
    for name in fast:
        np.testing.assert_array_equal(fast[name], full[name], err_msg=f"{label}: {name}")
    assert fast["default"].max() > 0


def test_a_kernel_without_an_effect_the_scene_needs_is_refused():
    scene = make_scene("cornell", 0, 0)
    with pytest.raises(ValueError, match="calls for"):
        render(scene, spp=2, seed=0, width=4, height=4, effects={"lambert"})


@pytest.mark.slow  # compiles two small kernels afresh to read their machine code
def test_a_specialised_kernel_leaves_out_the_code_of_absent_effects():
    # the flags are compile-time constants: a diffuse-only kernel's machine code never calls GGX or the
    # plastic's lobe choice, one with the plastic lobe does (compiled afresh here: numba's disk cache keeps no
    # IR to inspect). The control is the diffuse kernel plus plastic, not the all-effects one: the same proof
    # that the names survive inlining, for a fraction of the compile time.
    import numba

    from prep.render import kernels

    scene = _only(make_scene("cornell", 0, 0), "lambert")
    packed = pack(scene)
    plastic = scene.effects() | {"plastic"}
    calls = {}
    for effects in (scene.effects(), plastic):
        trace = numba.njit(kernels.kernel_for(effects).trace_sample.py_func)
        trace((0.0, 1.0, 5.0), (0.0, 0.0, -1.0), np.uint64(1), packed, 5, 3, np.zeros(16))
        ir = "".join(trace.inspect_llvm().values())
        calls[frozenset(effects)] = {name for name in ("_ggx_d", "_ggx_g1", "_plastic_spec_prob", "intersect")
                                     if name in ir}
    assert calls[scene.effects()] == {"intersect"}
    assert calls[frozenset(plastic)] == {"_ggx_d", "_ggx_g1", "_plastic_spec_prob", "intersect"}


def test_kpcn_kernels_all_renders_every_scene_with_the_all_effects_kernel(monkeypatch):
    from prep.render import EFFECTS, kernels

    needed = frozenset({"lambert", "emitter"})
    monkeypatch.setenv("KPCN_KERNELS", "specialised")
    assert kernels.kernel_effects(needed) == needed
    monkeypatch.delenv("KPCN_KERNELS")
    assert kernels.kernel_effects(needed) == needed
    monkeypatch.setenv("KPCN_KERNELS", "all")
    assert kernels.kernel_effects(needed) == frozenset(EFFECTS)


def test_an_unknown_kpcn_kernels_value_is_refused_naming_the_variable_and_the_choices(monkeypatch):
    from prep.errors import KpcnError

    monkeypatch.setenv("KPCN_KERNELS", "fast")
    with pytest.raises(KpcnError, match=r"KPCN_KERNELS is 'fast'; kpcn reads one of specialised, all"):
        render(make_scene("cornell", 0, 0), spp=2, seed=0, width=4, height=4)
